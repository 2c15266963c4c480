"""BVH motion files: reader, writer, and BVH <-> body-model pose conversion.

A BVH file has a HIERARCHY (joints with an ``OFFSET`` from their parent and ``CHANNELS``) and
a MOTION block (one row of channel values per frame). Conventions used here:

* Rotation channels are Euler angles in **degrees**, applied in the order listed:
  ``Zrotation Xrotation Yrotation`` means ``R_local = Rz(a) @ Rx(b) @ Ry(c)``; any order and
  any subset of the three axes is accepted.
* A joint's local position is its ``OFFSET``, with each position channel **replacing** the
  offset's component (as Blender's importer and bvhio read it); its position is
  ``parent position + R_parent @ local position``.
* Files are **Y up** (the BVH convention); our world is Z up: ``v_ours = M v_bvh`` with
  ``M = Y_UP_TO_Z_UP`` (x forward stays x, BVH z = our -y).

:func:`body_to_bvh` writes any body model's pose sequence: one BVH joint per pivot of the
chain (:func:`body_bvh_layout`), named after the keypoint role on it, offsets from the
model's rest pose, three rotation channels ``Zrotation Xrotation Yrotation`` per animated
joint (none for a fixed one) holding the rest-relative rotation, and
``Xposition Yposition Zposition`` on the root; Blender's ``import_anim.bvh`` (default axis
conversion), bvhio and the PyPI ``bvh`` parser read it back with joint positions equal to the
body's forward kinematics.
:func:`bvh_to_body_q` drives our model from any BVH clip by rotation transfer
(:mod:`jaxmocap.synth.retarget`), with a default name mapping for common skeletons.
"""

from __future__ import annotations

import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxmocap.body import FIXED, PRISMATIC, BodyModel, default_body, fk, require_roles
from jaxmocap.body.chain import over_frames
from jaxmocap.rotations import Y_UP_TO_Z_UP
from jaxmocap.synth.retarget import (
    Retargeted,
    SourcePose,
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
    lines += ["MOTION", f"Frames: {bvh.n_frames}", f"Frame Time: {bvh.frame_time:.10f}"]
    lines += [_fmt(row) for row in bvh.motion]
    return "\n".join(lines) + "\n"


def write_bvh(path: str | os.PathLike, bvh: BVH) -> None:
    """Write a clip to ``path``."""
    Path(path).write_text(format_bvh(bvh))


# Rotation channels of every animated joint, in the Biovision / CMU / MotionBuilder order that
# Blender's importer, bvhio and MotionBuilder-style readers all read: R = Rz(a) @ Rx(b) @ Ry(c).
ROTATION_ORDER = ("Zrotation", "Xrotation", "Yrotation")


def euler_zxy(r: np.ndarray) -> np.ndarray:
    """Angles ``(a, b, c)`` (rad) with ``r = Rz(a) @ Rx(b) @ Ry(c)``, ``b`` in [-pi/2, pi/2];
    at the gimbal lock ``|b| = pi/2`` the split is ``c = 0`` (the product stays exact)."""
    r = np.asarray(r, np.float64)
    cos_b = np.hypot(r[..., 2, 0], r[..., 2, 2])
    b = np.arctan2(r[..., 2, 1], cos_b)  # well conditioned near +-pi/2, unlike arcsin
    lock = cos_b < 1e-9
    a = np.where(lock, np.arctan2(r[..., 1, 0], r[..., 0, 0]),
                 np.arctan2(-r[..., 0, 1], r[..., 1, 1]))
    c = np.where(lock, 0.0, np.arctan2(-r[..., 2, 0], r[..., 2, 2]))
    return np.stack([a, b, c], axis=-1)


class BodyBVHLayout(NamedTuple):
    """How a body model maps to BVH joints (:func:`body_bvh_layout`).

    ``links[j]`` is the body link whose origin and orientation BVH joint ``j`` carries,
    ``parents[j]`` the BVH parent (-1 for the root), ``names[j]`` its name, ``rotates[j]``
    whether its joint group has a moving joint (3 rotation channels, else 0), ``slides[j]``
    whether it has a prismatic one (3 position channels too), ``end_keypoints[j]`` the
    keypoint index of a leaf's End Site (-1: none)."""

    links: tuple[int, ...]
    parents: tuple[int, ...]
    names: tuple[str, ...]
    rotates: tuple[bool, ...]
    slides: tuple[bool, ...]
    end_keypoints: tuple[int, ...]


def body_bvh_layout(model: BodyModel) -> BodyBVHLayout:
    """The BVH hierarchy of any body model, from its kinematic chain alone.

    BVH joints are the chain's segment links (root, links with geometry, branch points,
    children of fixed joints) and every link that a child joint is offset from; the massless
    links in between (the 1-DOF axes of a ball or universal joint at one pivot) merge into
    the BVH joint below them. With that choice each BVH joint's origin is fixed in its BVH
    parent's frame unless a prismatic joint lies between them (then it gets position
    channels). A joint is named after the keypoint role that sits on its pivot
    (``model.keypoint_names``: pelvis, neck, l_shoulder, l_elbow, l_wrist, ...), else after its
    link (``<link>_link`` where that is a keypoint's name elsewhere: a BVH joint named like a
    keypoint is at that keypoint); leaves end in an End Site at their farthest keypoint.
    """
    chain = model.chain
    topo = chain.topology
    origin_t = np.asarray(chain.joint_origin, np.float64)[:, :3, 3]
    offset_from = {topo[i][0] for i in range(1, len(topo)) if np.any(origin_t[i] != 0)}
    links = sorted(set(_segment_links(model)) | offset_from | {0})
    parents, groups = [], []
    for j in links:
        group, i = [], j
        while i > 0 and (i == j or i not in links):
            group.append(i)
            i = topo[i][0]
        parents.append(-1 if j == 0 else links.index(i))
        groups.append([0] if j == 0 else group)
    rest = np.asarray(fk(chain, jnp.zeros(chain.n_dof)), np.float64)
    kp_link = np.asarray(model.keypoint_link)
    kp_off = np.asarray(model.keypoint_offset, np.float64)
    kp_rest = np.einsum("kij,kj->ki", rest[kp_link, :3, :3], kp_off) + rest[kp_link, :3, 3]
    slides = [j != 0 and any(topo[i][1] == PRISMATIC for i in g)
              for j, g in zip(links, groups, strict=True)]
    names, used = [], set()
    for n, j in enumerate(links):
        # links a point on the pivot moves with: the joint's group, and its parent's link
        # unless a prismatic joint slides the pivot against the parent
        carriers = set(groups[n]) | ({links[parents[n]]} if parents[n] >= 0
                                     and not slides[n] else set())
        on_pivot = [k for k in range(len(kp_link)) if int(kp_link[k]) in carriers
                    and np.linalg.norm(kp_rest[k] - rest[j, :3, 3]) < 1e-9]
        name = next((model.keypoint_names[k] for k in on_pivot
                     if model.keypoint_names[k] not in used), None)
        if name is None:  # no keypoint on the pivot: the link's name, never a keypoint's
            name = chain.link_names[j]
            name = f"{name}_link" if name in model.keypoint_names else name
        name = "_".join(name.split())
        while name in used:
            name += "_"
        used.add(name)
        names.append(name)
    leaves = [n for n in range(len(links)) if n not in parents]
    ends = []
    for n, j in enumerate(links):
        kps = [k for k in range(len(kp_link)) if kp_link[k] == j and np.any(kp_off[k] != 0)]
        far = max(kps, key=lambda k: np.linalg.norm(kp_off[k]), default=-1)
        ends.append(far if n in leaves else -1)
    return BodyBVHLayout(
        links=tuple(links), parents=tuple(parents), names=tuple(names),
        rotates=tuple(j == 0 or any(topo[i][1] != FIXED for i in g)
                      for j, g in zip(links, groups, strict=True)),
        slides=tuple(slides),
        end_keypoints=tuple(ends))


def body_to_bvh(model: BodyModel, q, fps: float) -> BVH:
    """Our pose sequence ``q`` (n_frames, n_dof) as a Y-up BVH clip at ``fps`` (metres, deg).

    Hierarchy from :func:`body_bvh_layout` (any body). The BVH rest pose (all channels 0) is
    the body's rest pose ``q = 0``; each joint's rotation channels hold its rest-relative
    rotation ``D_j = R_j(q) R_j(0)^T`` (world, hence frame-free) relative to its parent's,
    ``D_parent^T D_j``, as ``Zrotation Xrotation Yrotation`` Euler angles (unwrapped over
    time). Then BVH forward kinematics (``p_j = p_parent + D_parent offset_j``) reproduces the
    body's link origins exactly, whatever the joints' axes or rest frames. The root has
    ``Xposition Yposition Zposition`` (its origin, ``OFFSET 0``) before its rotations; fixed
    joints have no channels; a joint behind a prismatic joint keeps its rest ``OFFSET`` and
    gets its whole local position in position channels (which replace the offset, as Blender
    and bvhio read them).
    """
    q = np.asarray(q, dtype=np.float64)
    chain = model.chain
    if q.ndim != 2 or q.shape[1] != chain.n_dof:
        raise ValueError(f"body_to_bvh: q has shape {q.shape}, expected (n_frames, "
                         f"{chain.n_dof})")
    if not fps > 0:
        raise ValueError(f"body_to_bvh: fps must be > 0, got {fps}")
    lay = body_bvh_layout(model)
    rest = np.asarray(fk(chain, jnp.zeros(chain.n_dof)), np.float64)
    n = q.shape[0]
    if n:
        tr = over_frames(fk, chain, q)
    else:
        tr = np.zeros((0,) + rest.shape)
    links = list(lay.links)
    # rest-relative world rotations and positions in the BVH frame (v_bvh = M^T v_world)
    tr, rest_l = tr[:, links], rest[links]
    d = _M.T @ (tr[..., :3, :3] @ np.swapaxes(rest_l[:, :3, :3], -1, -2)) @ _M
    p = tr[..., :3, 3] @ _M
    p_rest = rest_l[:, :3, 3] @ _M
    kp_off = np.asarray(model.keypoint_offset, np.float64)
    joints, motion = [], []
    for j, link in enumerate(links):
        par = lay.parents[j]
        chans: list[str] = []
        offset = np.zeros(3) if par < 0 else p_rest[j] - p_rest[par]
        if par < 0 or lay.slides[j]:
            chans += list(POSITIONS)
            if par < 0:
                motion.append(p[:, j])
            else:
                motion.append(np.einsum("nji,nj->ni", d[:, par], p[:, j] - p[:, par]))
        if lay.rotates[j]:
            chans += list(ROTATION_ORDER)
            local = d[:, j] if par < 0 else np.swapaxes(d[:, par], -1, -2) @ d[:, j]
            motion.append(np.degrees(np.unwrap(euler_zxy(local), axis=0)))
        end = None
        if j not in lay.parents:
            k = lay.end_keypoints[j]
            end = (0.0, 0.0, 0.0) if k < 0 else tuple(_M.T @ rest[link, :3, :3] @ kp_off[k])
        joints.append(BVHJoint(lay.names[j], par, tuple(float(v) for v in offset),
                               tuple(chans), end))
    motion = np.concatenate(motion, axis=1) if motion else np.zeros((n, 0))
    return BVH(joints=tuple(joints), frame_time=1.0 / fps, motion=motion)


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
                local_t[:, POSITIONS.index(c)] = vals[:, m]
        if j.parent < 0:
            rots.append(local_r)
            pos.append(local_t)
        else:
            rp = rots[j.parent]
            pos.append(pos[j.parent] + np.einsum("nij,nj->ni", rp, local_t))
            rots.append(rp @ local_r)
    return np.stack(rots, 1), np.stack(pos, 1)


def default_mapping(bvh: BVH, model: BodyModel) -> dict[str, str]:
    """Our segment link -> BVH joint: the joints :func:`body_to_bvh` wrote for this body when
    the file has them all (:func:`body_bvh_layout`), else for every role of
    :data:`DEFAULT_BVH_NAMES` the link playing it (by the body's roles) gets the first BVH joint
    present among its own name and the role's candidates."""
    lay = body_bvh_layout(model)
    if set(lay.names) <= set(bvh.names):
        segs = set(_segment_links(model))
        return {model.chain.link_names[link]: name
                for link, name in zip(lay.links, lay.names, strict=True) if link in segs}
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
    "body_bvh_layout", "BodyBVHLayout", "euler_zxy", "ROTATION_ORDER",
    "bvh_to_body_q",
]  # fmt: skip
