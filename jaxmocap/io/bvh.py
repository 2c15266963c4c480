"""BVH motion files: reader, writer, and BVH <-> body-model pose conversion.

A BVH file has a HIERARCHY (joints with an ``OFFSET`` from their parent and ``CHANNELS``) and
a MOTION block (one row of channel values per frame). Conventions used here:

* Rotation channels are Euler angles in **degrees**, applied in the order listed:
  ``Zrotation Xrotation Yrotation`` means ``R_local = Rz(a) @ Rx(b) @ Ry(c)``; any order and
  any subset of the three axes is accepted.
* A joint's position is ``parent position + R_parent @ (OFFSET + position channels)``.
* Files are **Y up** (the BVH convention); our world is Z up: ``v_ours = M v_bvh`` with
  ``M = Y_UP_TO_Z_UP`` (x forward stays x, BVH z = our -y).

:func:`body_to_bvh` writes our model's pose sequence: one BVH joint per body segment
(pelvis, chest, head, upper arms, forearms, hands), offsets from the model's rest pose, and one
rotation channel per 1-DOF joint in chain order (a 3-DOF ``*_x, *_y, *_z`` joint becomes
``Xrotation Zrotation Yrotation`` with the Z channel = -angle, as our y axis is BVH's -z);
the root has ``Xposition Yposition Zposition Xrotation Yrotation Zrotation``.
:func:`bvh_to_body_q` drives our model from any BVH clip by rotation transfer
(:mod:`jaxmocap.synth.retarget`), with a default name mapping for common skeletons.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxmocap.body import FIXED, BodyModel, default_body, require_roles
from jaxmocap.synth._rotations import Y_UP_TO_Z_UP, euler_xyz
from jaxmocap.synth.retarget import (
    Retargeted,
    SourcePose,
    _rest_transforms,
    _segment_links,
    plan,
    retarget,
    role_bone_ends,
)

ROTATIONS = ("Xrotation", "Yrotation", "Zrotation")
POSITIONS = ("Xposition", "Yposition", "Zposition")
_M = np.array(Y_UP_TO_Z_UP)

# Our link *role* -> BVH joint names tried in order (after the body's own link name for the
# role: common skeletons CMU / Mixamo / Biovision).
DEFAULT_BVH_NAMES: dict[str, tuple[str, ...]] = {
    "pelvis": ("pelvis", "Hips", "hips", "Hip", "hip", "Pelvis", "Root", "root"),
    "chest": ("chest", "Chest", "Spine1", "Spine2", "UpperChest", "Spine", "spine", "chest1"),
    "head": ("head", "Head", "Neck", "neck"),
    "l_upper_arm": ("l_upper_arm", "LeftArm", "LeftUpArm", "lShldr", "mixamorig:LeftArm",
                    "LeftShoulder"),
    "l_forearm": ("l_forearm", "LeftForeArm", "LeftLowArm", "lForeArm",
                  "mixamorig:LeftForeArm"),
    "l_hand": ("l_hand", "LeftHand", "lHand", "mixamorig:LeftHand"),
    "r_upper_arm": ("r_upper_arm", "RightArm", "RightUpArm", "rShldr", "mixamorig:RightArm",
                    "RightShoulder"),
    "r_forearm": ("r_forearm", "RightForeArm", "RightLowArm", "rForeArm",
                  "mixamorig:RightForeArm"),
    "r_hand": ("r_hand", "RightHand", "rHand", "mixamorig:RightHand"),
}


class BVHError(ValueError):
    """A malformed BVH file; the message is ``<file>:<line>: <what was expected>``."""

    def __init__(self, path: str | os.PathLike, line: int, message: str):
        super().__init__(f"{path}:{line}: {message}")
        self.path, self.line = str(path), line


@dataclass(frozen=True)
class BVHJoint:
    """One joint: parent index (-1 for the root), offset, channel names, end-site offset."""

    name: str
    parent: int
    offset: tuple[float, float, float]
    channels: tuple[str, ...]
    end_site: tuple[float, float, float] | None = None


@dataclass(frozen=True)
class BVH:
    """A parsed BVH clip: joints in file order, frame time (s), motion (n_frames, n_channels)."""

    joints: tuple[BVHJoint, ...]
    frame_time: float
    motion: np.ndarray = field(repr=False)

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(j.name for j in self.joints)

    @property
    def n_frames(self) -> int:
        return self.motion.shape[0]

    def channel_slices(self) -> list[slice]:
        """Columns of ``motion`` that hold each joint's channels."""
        out, start = [], 0
        for j in self.joints:
            out.append(slice(start, start + len(j.channels)))
            start += len(j.channels)
        return out


# ----------------------------------------------------------------------------- reading


def _tokens(text: str):
    for n, line in enumerate(text.splitlines(), start=1):
        for tok in line.split():
            yield n, tok


class _Parser:
    def __init__(self, text: str, path: str):
        self.toks = list(_tokens(text))
        self.i = 0
        self.path = path

    def line(self) -> int:
        if self.i < len(self.toks):
            return self.toks[self.i][0]
        return self.toks[-1][0] if self.toks else 1

    def fail(self, msg: str):
        raise BVHError(self.path, self.line(), msg)

    def next(self, what: str) -> str:
        if self.i >= len(self.toks):
            self.fail(f"unexpected end of file, expected {what}")
        tok = self.toks[self.i][1]
        self.i += 1
        return tok

    def expect(self, word: str):
        tok = self.next(repr(word))
        if tok != word:
            self.i -= 1
            self.fail(f"expected {word!r}, got {tok!r}")

    def number(self, what: str) -> float:
        tok = self.next(what)
        try:
            return float(tok)
        except ValueError:
            self.i -= 1
            self.fail(f"expected a number ({what}), got {tok!r}")

    def offset(self) -> tuple[float, float, float]:
        self.expect("OFFSET")
        return tuple(self.number("OFFSET value") for _ in range(3))

    def joint(self, name: str, parent: int, joints: list[BVHJoint]):
        self.expect("{")
        off = self.offset()
        self.expect("CHANNELS")
        n_tok = self.next("channel count")
        if not n_tok.isdigit():
            self.i -= 1
            self.fail(f"expected a channel count, got {n_tok!r}")
        chans = []
        for _ in range(int(n_tok)):
            c = self.next("a channel name")
            if c not in ROTATIONS + POSITIONS:
                self.i -= 1
                self.fail(f"unknown channel {c!r} of joint {name!r}; expected one of "
                          f"{ROTATIONS + POSITIONS}")
            chans.append(c)
        index = len(joints)
        joints.append(BVHJoint(name, parent, off, tuple(chans)))
        while True:
            tok = self.next("JOINT, End Site or '}'")
            if tok == "}":
                return
            if tok == "JOINT":
                self.joint(self.next("a joint name"), index, joints)
            elif tok == "End":
                self.expect("Site")
                self.expect("{")
                site = self.offset()
                self.expect("}")
                j = joints[index]
                joints[index] = BVHJoint(j.name, j.parent, j.offset, j.channels, site)
            else:
                self.i -= 1
                self.fail(f"expected JOINT, End Site or '}}' in joint {name!r}, got {tok!r}")


def parse_bvh(text: str, path: str | os.PathLike = "<string>") -> BVH:
    """Parse BVH text; :class:`BVHError` (``file:line: message``) on malformed input."""
    p = _Parser(text, str(path))
    p.expect("HIERARCHY")
    p.expect("ROOT")
    joints: list[BVHJoint] = []
    p.joint(p.next("the root joint name"), -1, joints)
    p.expect("MOTION")
    p.expect("Frames:")
    n_line = p.line()
    n_frames = p.number("frame count")
    if n_frames != int(n_frames) or n_frames < 0:
        raise BVHError(path, n_line, f"Frames: expected a non-negative integer, got {n_frames}")
    p.expect("Frame")
    p.expect("Time:")
    t_line = p.line()
    frame_time = p.number("frame time")
    if not frame_time > 0:
        raise BVHError(path, t_line, f"Frame Time: expected > 0 seconds, got {frame_time}")
    n_chan = sum(len(j.channels) for j in joints)
    rest = p.toks[p.i:]
    rows: dict[int, list[str]] = {}
    for n, tok in rest:
        rows.setdefault(n, []).append(tok)
    if len(rows) != int(n_frames):
        line = max(rows) if rows else p.line()
        raise BVHError(path, line, f"Frames: {int(n_frames)} declared, {len(rows)} rows found")
    motion = np.empty((int(n_frames), n_chan))
    for k, (n, toks) in enumerate(sorted(rows.items())):
        if len(toks) != n_chan:
            raise BVHError(path, n, f"frame {k} has {len(toks)} values, expected {n_chan} "
                           "(the channels of the hierarchy)")
        try:
            motion[k] = [float(t) for t in toks]
        except ValueError:
            raise BVHError(path, n, f"frame {k}: non-numeric value") from None
    if not np.all(np.isfinite(motion)):
        n = sorted(rows)[int(np.argmax(~np.isfinite(motion).all(1)))]
        raise BVHError(path, n, "non-finite channel value")
    return BVH(joints=tuple(joints), frame_time=float(frame_time), motion=motion)


def read_bvh(path: str | os.PathLike) -> BVH:
    """Read a BVH file (see :func:`parse_bvh`)."""
    return parse_bvh(Path(path).read_text(), path)


# ----------------------------------------------------------------------------- writing


def _fmt(v) -> str:
    return " ".join(f"{x:.6f}" for x in v)


def format_bvh(bvh: BVH) -> str:
    """BVH text of a clip (tabs for nesting, 6 decimals)."""
    children: dict[int, list[int]] = {}
    for i, j in enumerate(bvh.joints):
        children.setdefault(j.parent, []).append(i)
    lines = ["HIERARCHY"]

    def emit(i: int, depth: int):
        j, pad = bvh.joints[i], "\t" * depth
        lines.append(f"{pad}{'ROOT' if j.parent < 0 else 'JOINT'} {j.name}")
        lines.append(f"{pad}{{")
        lines.append(f"{pad}\tOFFSET {_fmt(j.offset)}")
        lines.append(f"{pad}\tCHANNELS {len(j.channels)} {' '.join(j.channels)}".rstrip())
        for c in children.get(i, []):
            emit(c, depth + 1)
        if j.end_site is not None:
            lines.extend([f"{pad}\tEnd Site", f"{pad}\t{{",
                          f"{pad}\t\tOFFSET {_fmt(j.end_site)}", f"{pad}\t}}"])
        lines.append(f"{pad}}}")

    emit(0, 0)
    lines += ["MOTION", f"Frames: {bvh.n_frames}", f"Frame Time: {bvh.frame_time:.8f}"]
    lines += [_fmt(row) for row in bvh.motion]
    return "\n".join(lines) + "\n"


def write_bvh(path: str | os.PathLike, bvh: BVH) -> None:
    """Write a clip to ``path``."""
    Path(path).write_text(format_bvh(bvh))


def _axis_channel(axis_bvh: np.ndarray, where: str) -> tuple[str, float]:
    k = int(np.argmax(np.abs(axis_bvh)))
    if not np.isclose(abs(axis_bvh[k]), 1.0, atol=1e-9):
        raise ValueError(f"body_to_bvh: joint {where!r} has axis {axis_bvh} (BVH frame); "
                         "only axes along x, y or z can be written as BVH channels")
    return ROTATIONS[k], float(np.sign(axis_bvh[k]))


def body_to_bvh(model: BodyModel, q, fps: float) -> BVH:
    """Our pose sequence ``q`` (n_frames, n_dof) as a Y-up BVH clip at ``fps`` (metres, deg).

    One BVH joint per segment link of the model, named after it; channels as in the module
    docstring. Needs joint frames aligned with the world at rest (true of the bundled body);
    raises ``ValueError`` naming the joint otherwise.
    """
    q = np.asarray(q, dtype=np.float64)
    chain = model.chain
    if q.ndim != 2 or q.shape[1] != chain.n_dof:
        raise ValueError(f"body_to_bvh: q has shape {q.shape}, expected (n_frames, "
                         f"{chain.n_dof})")
    topo = chain.topology
    origin = np.asarray(chain.joint_origin, dtype=np.float64)
    axes = np.asarray(chain.joint_axis, dtype=np.float64)
    rest = _rest_transforms(origin, topo)
    segs = _segment_links(model)
    kp_link = np.asarray(model.keypoint_link)
    kp_off = np.asarray(model.keypoint_offset, dtype=np.float64)
    names = chain.link_names
    joints, columns = [], []
    for s in segs:
        if not np.allclose(rest[s, :3, :3], np.eye(3), atol=1e-9):
            raise ValueError(f"body_to_bvh: link {names[s]!r} is rotated at rest; BVH joints "
                             "must be aligned with the world at rest")
        parent_seg = -1
        group = []
        i = s
        while i != 0:
            group.append(i)
            i = topo[i][0]
            if i in segs:
                parent_seg = segs.index(i)
                break
        group = group[::-1]
        chans, cols = [], []
        if s == 0:
            chans = list(POSITIONS) + list(ROTATIONS)
            cols = [("root_t", k) for k in range(3)] + [("root_r", k) for k in range(3)]
            offset = np.zeros(3)  # the position channels carry the root link's origin
        else:
            offset = _M.T @ (rest[s, :3, 3] - rest[segs[parent_seg], :3, 3])
            for m, i in enumerate(group):
                if m > 0 and np.any(origin[i, :3, 3] != 0):
                    raise ValueError(f"body_to_bvh: joint of {names[i]!r} is offset from the "
                                     "previous joint of its group; BVH needs one pivot")
                if topo[i][1] == FIXED:
                    continue
                ch, sign = _axis_channel(_M.T @ axes[i], names[i])
                chans.append(ch)
                cols.append(("dof", topo[i][2], sign))
        end = None
        if not any(_seg_parent(topo, segs, c) == s for c in segs if c != 0):  # a leaf
            kps = [k for k in range(len(kp_link)) if kp_link[k] == s]
            far = max(kps, key=lambda k: np.linalg.norm(kp_off[k]), default=None)
            end = tuple(_M.T @ kp_off[far]) if far is not None else (0.0, 0.0, 0.0)
        joints.append(BVHJoint(names[s], parent_seg, tuple(offset), tuple(chans), end))
        columns.append(cols)
    n = q.shape[0]
    root_r = _root_matrix(q[:, 3:6])
    root_p = q[:, 0:3] + root_r @ origin[0, :3, 3]
    root_euler = np.degrees(np.asarray(euler_xyz(jnp.asarray(_M.T @ root_r @ _M))))
    motion = []
    for cols in columns:
        for c in cols:
            if c[0] == "root_t":
                motion.append((root_p @ _M)[:, c[1]])
            elif c[0] == "root_r":
                motion.append(root_euler[:, c[1]])
            else:
                motion.append(c[2] * np.degrees(q[:, c[1]]))
    motion = np.stack(motion, axis=1) if motion else np.zeros((n, 0))
    return BVH(joints=tuple(joints), frame_time=1.0 / fps, motion=motion)


def _seg_parent(topo, segs, c: int) -> int:
    i = topo[c][0]
    while i not in segs:
        i = topo[i][0]
    return i


def _root_matrix(w: np.ndarray) -> np.ndarray:
    theta = np.linalg.norm(w, axis=-1, keepdims=True)
    axis = w / np.where(theta > 0, theta, 1.0)
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    o = np.zeros_like(x)
    k = np.stack([np.stack([o, -z, y], -1), np.stack([z, o, -x], -1),
                  np.stack([-y, x, o], -1)], -2)
    s, c = np.sin(theta)[..., None], np.cos(theta)[..., None]
    return np.eye(3) + s * k + (1 - c) * (k @ k)


def write_body_bvh(path: str | os.PathLike, model: BodyModel, q, fps: float) -> None:
    """Write our pose sequence ``q`` (n_frames, n_dof) as a BVH file (see :func:`body_to_bvh`)."""
    write_bvh(path, body_to_bvh(model, q, fps))


# ----------------------------------------------------------------------------- BVH -> body


def _euler_matrix(channels: Sequence[str], deg: np.ndarray) -> np.ndarray:
    """``R = R_c1(a1) @ R_c2(a2) @ ...`` for the rotation channels (angles in degrees)."""
    r = np.broadcast_to(np.eye(3), deg.shape[:1] + (3, 3)).copy()
    for m, ch in enumerate(channels):
        a = np.radians(deg[:, m])
        c, s = np.cos(a), np.sin(a)
        rot = np.zeros(deg.shape[:1] + (3, 3))
        k = ROTATIONS.index(ch)
        i, j = (k + 1) % 3, (k + 2) % 3
        rot[:, k, k] = 1.0
        rot[:, i, i], rot[:, i, j], rot[:, j, i], rot[:, j, j] = c, -s, s, c
        r = r @ rot
    return r


def bvh_fk(bvh: BVH) -> tuple[np.ndarray, np.ndarray]:
    """World rotations (n_frames, n_joints, 3, 3) and positions (n_frames, n_joints, 3) of
    every joint, in the file's frame and units."""
    n = bvh.n_frames
    rots, pos = [], []
    for j, sl in zip(bvh.joints, bvh.channel_slices(), strict=True):
        vals = bvh.motion[:, sl]
        rch = [(c, m) for m, c in enumerate(j.channels) if c in ROTATIONS]
        local_r = _euler_matrix([c for c, _ in rch], vals[:, [m for _, m in rch]])
        local_t = np.broadcast_to(np.asarray(j.offset), (n, 3)).copy()
        for m, c in enumerate(j.channels):
            if c in POSITIONS:
                local_t[:, POSITIONS.index(c)] += vals[:, m]
        if j.parent < 0:
            rots.append(local_r)
            pos.append(local_t)
        else:
            rp = rots[j.parent]
            pos.append(pos[j.parent] + np.einsum("nij,nj->ni", rp, local_t))
            rots.append(rp @ local_r)
    return np.stack(rots, 1), np.stack(pos, 1)


def default_mapping(bvh: BVH, model: BodyModel) -> dict[str, str]:
    """Our segment link -> BVH joint: for every role of :data:`DEFAULT_BVH_NAMES`, the link
    playing it (by the body's roles) gets the first BVH joint present among its own name and
    the role's candidates."""
    roles = require_roles(model, "bvh_to_body_q")
    out = {}
    for role, cands in DEFAULT_BVH_NAMES.items():
        ours = roles.link(role)
        if ours in out:
            continue
        hit = next((c for c in (ours, *cands) if c in bvh.names and c not in out.values()), None)
        if hit is not None:
            out[ours] = hit
    return out


def bvh_to_body_q(bvh: BVH, model: BodyModel | None = None,
                  mapping: Mapping[str, str] | None = None, scale: float = 1.0,
                  bone_ends: Mapping[str, str] | None = None) -> Retargeted:
    """Drive ``model`` (default: the bundled body) with a BVH clip.

    ``bone_ends``: link -> bone end (default: by the body's roles, ``role_bone_ends``).
    ``mapping`` maps our link names to BVH joint names (default :func:`default_mapping`; it
    must include our root link). ``scale`` converts the file's units to metres (e.g. 0.01 for
    centimetres). The BVH rest pose may differ from ours (a T-pose, say): each segment's rest
    bone direction — towards the BVH joint mapped to our bone's end, else its single child or
    End Site — is aligned by the rotation transfer of :mod:`jaxmocap.synth.retarget`.
    """
    model = default_body() if model is None else model
    bone_ends = role_bone_ends(model) if bone_ends is None else bone_ends
    mapping = dict(default_mapping(bvh, model) if mapping is None else mapping)
    root = model.chain.link_names[0]
    for ours, theirs in mapping.items():
        if theirs not in bvh.names:
            raise ValueError(f"bvh_to_body_q: BVH joint {theirs!r} (for {ours!r}) not in the "
                             f"file; joints are {bvh.names}")
    if root not in mapping:
        raise ValueError(f"bvh_to_body_q: no BVH joint for our root {root!r}; pass mapping="
                         f"{{{root!r}: <BVH root name>, ...}} (joints: {bvh.names})")
    order = [root] + [k for k in mapping if k != root]
    rots, pos = bvh_fk(bvh)
    zero = BVH(bvh.joints, bvh.frame_time, np.zeros((1, bvh.motion.shape[1])))
    _, rest_pos = bvh_fk(zero)
    rest_pos = rest_pos[0]
    idx = [bvh.names.index(mapping[k]) for k in order]
    dirs = []
    for ours, j in zip(order, idx, strict=True):
        end = bone_ends.get(ours)
        if end in mapping and end != ours:
            d = rest_pos[bvh.names.index(mapping[end])] - rest_pos[j]
        else:
            kids = [c for c, jj in enumerate(bvh.joints) if jj.parent == j]
            site = bvh.joints[j].end_site
            d = (rest_pos[kids[0]] - rest_pos[j]) if len(kids) == 1 else (
                np.asarray(site) if site is not None else np.zeros(3))
        if np.linalg.norm(d) < 1e-12:
            raise ValueError(f"bvh_to_body_q: cannot tell the rest bone direction of BVH joint "
                             f"{mapping[ours]!r} (driving {ours!r}): it has no single child or "
                             "End Site; map our bone's end joint too")
        dirs.append(_M @ d / np.linalg.norm(d))
    source = SourcePose(
        root_pos=jnp.asarray(scale * pos[:, idx[0]] @ _M.T),
        delta=jnp.asarray(_M @ rots[:, idx] @ _M.T),
        rest_dir=jnp.asarray(np.stack(dirs)),
        links=tuple(order),
    )
    plan(model, source.links, bone_ends)  # validates names early with a clear message
    return retarget(model, source, bone_ends)


__all__ = [
    "BVH", "BVHJoint", "BVHError", "DEFAULT_BVH_NAMES", "parse_bvh", "read_bvh", "format_bvh",
    "write_bvh", "body_to_bvh", "write_body_bvh", "bvh_fk", "default_mapping",
    "bvh_to_body_q",
]  # fmt: skip
