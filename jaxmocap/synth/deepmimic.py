"""DeepMimic motion-capture clips shipped in pybullet's ``pybullet_data`` (decoding + FK).

A clip file is JSON with a ``"Frames"`` list; each frame (44 numbers) is

    [0] duration to the next frame (s)   [1:4] root position (Y up, m)   [4:8] root quaternion
    [8:12] chest  [12:16] neck  [16:20] right hip  [20] right knee  [21:25] right ankle
    [25:29] right shoulder  [29] right elbow  [30:34] left hip  [34] left knee
    [35:39] left ankle  [39:43] left shoulder  [43] left elbow

with quaternions ``(w, x, y, z)`` (not always unit: we normalise) and knees/elbows one angle
(rad) about the hinge's z axis. The skeleton these angles pose is pybullet's
``humanoid/humanoid.urdf`` loaded with ``globalScaling = 0.25`` (``pybullet_envs/deep_mimic/env/
humanoid_stable_pd.py``): Y up, facing +x, its right side at +z; every joint origin has zero
rotation, so a joint's local rotation acts in its parent's axes. ``skeleton_fk`` reproduces
pybullet's posing (``resetBasePositionAndOrientation`` + ``resetJointStatesMultiDof``).
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from functools import cache
from pathlib import Path
from typing import NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxmocap.body.packages import DEEPMIMIC_SCALE
from jaxmocap.rotations import mm, mv, normalize_quat, quat_to_matrix, slerp

FRAME_WIDTH = 44

# Source skeleton links in pybullet's joint-index order (URDF_MAINTAIN_LINK_ORDER); link 0 is the
# root (the URDF's base with its fixed "root" joint).
LINKS = ("root", "chest", "neck", "right_hip", "right_knee", "right_ankle", "right_shoulder",
         "right_elbow", "right_wrist", "left_hip", "left_knee", "left_ankle", "left_shoulder",
         "left_elbow", "left_wrist")
SPHERICAL = ("chest", "neck", "right_hip", "right_ankle", "right_shoulder", "left_hip",
             "left_ankle", "left_shoulder")
HINGES = ("right_knee", "right_elbow", "left_knee", "left_elbow")
# Offsets of each joint's data in a frame row.
_SPHERICAL_COL = (8, 12, 16, 21, 25, 30, 35, 39)
_HINGE_COL = (20, 29, 34, 43)


def motions_dir() -> Path:
    """Folder of the clips inside the installed ``pybullet_data`` package."""
    import pybullet_data

    return Path(pybullet_data.getDataPath()) / "data" / "motions"


def list_clips() -> tuple[str, ...]:
    """Names of the humanoid clips: ``humanoid3d_*`` (15) and ``walker/*`` (5), sorted."""
    root = motions_dir()
    names = [p.stem for p in root.glob("humanoid3d_*.txt")]
    names += [f"walker/{p.stem}" for p in (root / "walker").glob("*.txt")]
    return tuple(sorted(names))


def clip_path(name_or_path: str | os.PathLike) -> Path:
    """Resolve a clip name (``"walk"``, ``"humanoid3d_walk"``, ``"walker/turn_left0"``) or path."""
    p = Path(name_or_path)
    if p.suffix == ".txt" and p.exists():
        return p
    root = motions_dir()
    for cand in (root / f"{name_or_path}.txt", root / f"humanoid3d_{name_or_path}.txt"):
        if cand.exists():
            return cand
    raise FileNotFoundError(
        f"no DeepMimic clip {str(name_or_path)!r}: not a file, and not one of {list_clips()} "
        f"in {root}"
    )


class Clip(eqx.Module):
    """A decoded DeepMimic clip (source skeleton, Y-up world, metres, radians).

    ``times[k]`` is when frame ``k`` is shown (s, ``times[0] = 0``); quaternions are unit
    ``(w, x, y, z)``; ``joint_quat[:, j]`` is the local rotation of ``SPHERICAL[j]`` and
    ``hinge[:, j]`` the angle of ``HINGES[j]`` about its joint's z axis.
    """

    times: Float[Array, " n_frames"]
    root_pos: Float[Array, "n_frames 3"]
    root_quat: Float[Array, "n_frames 4"]
    joint_quat: Float[Array, "n_frames 8 4"]
    hinge: Float[Array, "n_frames 4"]
    name: str = eqx.field(static=True)
    loop: str = eqx.field(static=True, default="none")

    @property
    def n_frames(self) -> int:
        return self.times.shape[0]

    @property
    def duration(self) -> float:
        return float(self.times[-1])

    @property
    def fps(self) -> float:
        """Nominal frame rate: one over the median frame duration."""
        return float(1.0 / np.median(np.diff(np.asarray(self.times))))


def load_deepmimic(name_or_path: str | os.PathLike, dtype=np.float32) -> Clip:
    """Read a DeepMimic clip (by name from :func:`list_clips` or by path) into a :class:`Clip`.

    Raises ``ValueError`` naming the file and the frame when the JSON is not a non-empty
    ``"Frames"`` list of 44-number rows with positive durations between frames.
    """
    path = clip_path(name_or_path)
    from jaxmocap.io.preflight import read_json

    data = read_json(path, "a DeepMimic motion clip (a JSON object with 'Frames')")
    frames = data.get("Frames") if isinstance(data, dict) else None
    if not isinstance(frames, list) or len(frames) < 2:
        raise ValueError(f"{path}: expected a 'Frames' list of at least 2 frames")
    for k, row in enumerate(frames):
        if not isinstance(row, list) or len(row) != FRAME_WIDTH:
            n = len(row) if isinstance(row, list) else type(row).__name__
            raise ValueError(f"{path}: frame {k} has {n} values, expected {FRAME_WIDTH}")
    f = np.asarray(frames, dtype=np.float64)
    dur = f[:-1, 0]
    if np.any(dur <= 0):
        k = int(np.argmax(dur <= 0))
        raise ValueError(f"{path}: frame {k} has duration {dur[k]}, expected > 0")
    times = np.concatenate([[0.0], np.cumsum(dur)])
    quat = np.stack([f[:, c:c + 4] for c in _SPHERICAL_COL], axis=1)
    for arr, what in ((f[:, 4:8], "root quaternion"), (quat, "joint quaternion")):
        if np.any(np.linalg.norm(arr, axis=-1) < 0.5):
            raise ValueError(f"{path}: a {what} is far from unit length (corrupt clip?)")
    name = path.stem if path.parent.name != "walker" else f"walker/{path.stem}"
    cast = lambda a: jnp.asarray(np.asarray(a, dtype=dtype))
    return Clip(
        times=cast(times),
        root_pos=cast(f[:, 1:4]),
        root_quat=normalize_quat(cast(f[:, 4:8])),
        joint_quat=normalize_quat(cast(quat)),
        hinge=cast(f[:, list(_HINGE_COL)]),
        name=name,
        loop=str(data.get("Loop", "none")),
    )


def resample(clip: Clip, fps: float) -> Clip:
    """The clip at a uniform frame rate ``fps`` over ``[0, duration]``.

    Positions and hinge angles are interpolated linearly, rotations by slerp (shorter arc),
    which is what DeepMimic's own ``HumanoidPoseInterpolator.Slerp`` does between key frames.
    """
    if not fps > 0:
        raise ValueError(f"resample: fps must be > 0, got {fps}")
    times = np.asarray(clip.times, dtype=np.float64)
    n_out = int(np.floor(times[-1] * fps + 1e-9)) + 1
    t = np.minimum(np.arange(n_out) / fps, times[-1])
    k = np.clip(np.searchsorted(times, t, side="right") - 1, 0, len(times) - 2)
    u_np = np.clip((t - times[k]) / (times[k + 1] - times[k]), 0.0, 1.0)
    dt = clip.times.dtype
    u = jnp.asarray(u_np.astype(dt))
    k0, k1 = jnp.asarray(k), jnp.asarray(k + 1)
    lerp = lambda a: a[k0] + u.reshape((-1,) + (1,) * (a.ndim - 1)) * (a[k1] - a[k0])
    return Clip(
        times=jnp.asarray(t.astype(dt)),
        root_pos=lerp(clip.root_pos),
        root_quat=slerp(clip.root_quat[k0], clip.root_quat[k1], u),
        joint_quat=slerp(clip.joint_quat[k0], clip.joint_quat[k1], u[:, None]),
        hinge=lerp(clip.hinge),
        name=clip.name,
        loop=clip.loop,
    )


class Skeleton(NamedTuple):
    """The DeepMimic humanoid as a tree (NumPy constants, metres).

    ``offsets[i]`` is link ``i``'s joint origin in its parent's frame; ``bone_end[i]`` is the
    point in link ``i``'s frame where its bone ends (its main child joint; for the neck and
    the wrists, the centre of the head / hand sphere), so the bone of link ``i`` runs from
    the link origin to ``bone_end[i]``.
    """

    parents: tuple[int, ...]
    offsets: np.ndarray  # (n_links, 3)
    bone_end: np.ndarray  # (n_links, 3)


_MAIN_CHILD = {"root": "chest", "chest": "neck", "right_hip": "right_knee",
               "right_knee": "right_ankle", "right_shoulder": "right_elbow",
               "right_elbow": "right_wrist", "left_hip": "left_knee", "left_knee": "left_ankle",
               "left_shoulder": "left_elbow", "left_elbow": "left_wrist"}


def _vec(s: str) -> np.ndarray:
    return np.array([float(v) for v in s.split()])


@cache
def deepmimic_skeleton(scale: float = DEEPMIMIC_SCALE) -> Skeleton:
    """Parse pybullet's ``humanoid/humanoid.urdf`` (joint origins, scaled by ``scale``)."""
    import pybullet_data

    path = Path(pybullet_data.getDataPath()) / "humanoid" / "humanoid.urdf"
    root = ET.fromstring(path.read_text().rstrip("\x00 \r\n"))  # the file ends in a NUL byte
    joints = {j.find("child").get("link"): j for j in root.iter("joint")}
    parents, offsets = [], []
    for name in LINKS:
        j = joints[name]
        parents.append(-1 if name == "root" else LINKS.index(j.find("parent").get("link")))
        origin = j.find("origin")
        if np.any(_vec(origin.get("rpy", "0 0 0")) != 0):
            raise ValueError(f"{path}: joint {name!r} has a rotated origin; expected rpy = 0")
        offsets.append(_vec(origin.get("xyz")) * scale)
    offsets = np.stack(offsets)
    bone_end = np.zeros_like(offsets)
    for i, name in enumerate(LINKS):
        if name in _MAIN_CHILD:
            bone_end[i] = offsets[LINKS.index(_MAIN_CHILD[name])]
        else:  # neck, ankles, wrists: the centre of the collision shape
            link = root.find(f"./link[@name='{name}']")
            bone_end[i] = _vec(link.find("collision/origin").get("xyz")) * scale
    return Skeleton(parents=tuple(parents), offsets=offsets, bone_end=bone_end)


def local_rotations(clip: Clip) -> Float[Array, "n_frames n_links 3 3"]:
    """Local rotation of every skeleton link (identity for the root and fixed wrists)."""
    n, dt = clip.n_frames, clip.times.dtype
    eye = jnp.broadcast_to(jnp.eye(3, dtype=dt), (n, 3, 3))
    rots = [eye] * len(LINKS)
    for j, name in enumerate(SPHERICAL):
        rots[LINKS.index(name)] = quat_to_matrix(clip.joint_quat[:, j])
    for j, name in enumerate(HINGES):  # revolute about the joint's z axis
        a = clip.hinge[:, j]
        c, s, o, one = jnp.cos(a), jnp.sin(a), jnp.zeros_like(a), jnp.ones_like(a)
        rots[LINKS.index(name)] = jnp.stack(
            [jnp.stack([c, -s, o], -1), jnp.stack([s, c, o], -1), jnp.stack([o, o, one], -1)], -2
        )
    return jnp.stack(rots, axis=1)


def skeleton_fk(
    clip: Clip,
) -> tuple[Float[Array, "n_frames n_links 3 3"], Float[Array, "n_frames n_links 3"]]:
    """World rotations and origins (Y-up source frame, m) of every skeleton link, per frame.

    Composes ``R_i = R_parent @ L_i`` and ``p_i = p_parent + R_parent @ offset_i`` from the
    root pose (``root_pos``, ``root_quat``), as pybullet poses ``humanoid.urdf``.
    """
    sk = deepmimic_skeleton()
    local = local_rotations(clip)
    off = jnp.asarray(sk.offsets.astype(clip.times.dtype))
    rots = [quat_to_matrix(clip.root_quat)]
    pos = [clip.root_pos]
    for i in range(1, len(sk.parents)):
        p = sk.parents[i]
        rots.append(mm(rots[p], local[:, i]))
        pos.append(pos[p] + mv(rots[p], off[i]))
    return jnp.stack(rots, 1), jnp.stack(pos, 1)
