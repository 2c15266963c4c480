"""Sampling the database poses (Wang et al. 2011 §5.2, Step 2) and the canonical camera.

Wang et al. select their 80,000 poses "by uniformly sampling a large database spanning a
variety of upper-body configurations and 3-D orientations", built from "linear blends of
generic action poses". We have no Poser library; our large database is

* the frames of the training mocap clips (:data:`jaxmocap.synth.TRAIN_CLIPS`, retargeted to the
  body model, within the joint limits) and their left/right mirror images;
* **linear blends** ``theta = (1 - alpha) theta_a + alpha theta_b`` of two random frames of
  that pool, ``alpha ~ U(0, 1)`` (a fraction ``p_real`` of the poses are real frames,
  ``alpha = 0``), plus a small Gaussian jitter ``N(0, joint_noise^2)`` per joint angle; blends
  of in-limit poses stay in the limits (the box is convex), the jitter is clipped;
* a **root orientation relative to the camera**, ``R = R_z(yaw) R_y(pitch) R_x(roll)`` with
  ``yaw ~ U(-yaw_range, yaw_range)`` (all around by default: the subject may face any way),
  ``pitch ~ U(-pitch_range, pitch_range)`` (leaning forward/back) and
  ``roll ~ U(-roll_range, roll_range)`` (sideways), replacing the clip's own root rotation.

The poses are drawn i.i.d. from this distribution (each draw picks frames uniformly in the
pool), which is what "uniformly sampling" gives in expectation.

**Canonical camera.** Every pose is rendered with the root (pelvis origin) at the world origin,
``t = 0``, seen by :func:`canonical_camera`: a pinhole camera ``CANON_DISTANCE`` metres in front
of the body at rest (on +x, the way the body faces at rest), looking back along -x at the
middle of the torso. ``yaw = 0`` is therefore a subject facing the camera. Since the tiny map
is normalised to the shirt's bounding box (:mod:`jaxmocap.render`), only the orientation
relative to the camera and the articulation matter; the stored root rotation ``w`` is the
body's orientation in the canonical world, ``R_c = R_canon exp([w]_x)`` its orientation in the
canonical camera frame. :func:`pose_in_camera` maps a database (or blended) pose into the world
of a real camera.
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..body import ROOT_DOFS, BodyModel, require_roles, so3_exp
from ..camera import Camera, look_at
from ..errors import InputError
from ..rotations import matrix_to_rotvec

DEFAULT_SIZE = 80_000  # Wang et al. §5.2: "a database of 80,000 upper-body poses"
CANON_DISTANCE = 3.0  # m, canonical camera to body (only the window-normalised map matters)
CANON_HEIGHT = 0.25  # m above the pelvis origin: the camera looks at the middle of the torso
CANON_FOCAL = 500.0  # px; a 640x480 webcam-like canonical camera (Wang et al. §3)
CANON_SIZE = (640, 480)
P_REAL = 0.25  # fraction of poses that are real clip frames (no blend)
P_MIRROR = 0.5  # probability of mirroring a pose left/right
JOINT_NOISE = 0.05  # rad, jitter of every joint angle
YAW_RANGE = float(np.pi)  # rad, yaw relative to the camera: all around
PITCH_RANGE = 0.35  # rad, forward/backward lean (about 20 degrees)
ROLL_RANGE = 0.2  # rad, sideways lean (about 11 degrees)


class SamplingError(InputError):
    """Invalid sampling settings (size, ranges, probabilities, clips)."""


class SamplingConfig(NamedTuple):
    """Settings of the pose sampler (module docstring); part of the database's cache key."""

    size: int = DEFAULT_SIZE
    seed: int = 0
    p_real: float = P_REAL
    p_mirror: float = P_MIRROR
    joint_noise: float = JOINT_NOISE
    yaw_range: float = YAW_RANGE
    pitch_range: float = PITCH_RANGE
    roll_range: float = ROLL_RANGE
    clips: tuple[str, ...] | None = None  # None: jaxmocap.synth.TRAIN_CLIPS

    def validate(self) -> SamplingConfig:
        if not isinstance(self.size, int | np.integer) or not 1 <= self.size <= 500_000:
            raise SamplingError(f"SamplingConfig.size: expected an integer in 1..500000, "
                                f"got {self.size!r}")
        if not isinstance(self.seed, int | np.integer) or self.seed < 0:
            raise SamplingError(f"SamplingConfig.seed: expected an integer >= 0, got {self.seed!r}")
        for name in ("p_real", "p_mirror"):
            v = getattr(self, name)
            if not 0.0 <= v <= 1.0:
                raise SamplingError(f"SamplingConfig.{name}: expected a probability in [0, 1], "
                                    f"got {v!r}")
        for name in ("joint_noise", "yaw_range", "pitch_range", "roll_range"):
            v = getattr(self, name)
            if not (np.isfinite(v) and 0.0 <= v <= np.pi):
                raise SamplingError(f"SamplingConfig.{name}: expected an angle in [0, pi] rad, "
                                    f"got {v!r}")
        if self.clips is not None and len(self.clips) == 0:
            raise SamplingError("SamplingConfig.clips: expected at least one clip name")
        return self


def canonical_camera(dtype=None) -> Camera:
    """The camera every database pose is rendered with (module docstring): at
    ``(CANON_DISTANCE, 0, CANON_HEIGHT)`` looking along -x, ``CANON_FOCAL`` px, 640x480."""
    dtype = dtype or jnp.result_type(float)
    w, h = CANON_SIZE
    eye = jnp.asarray([CANON_DISTANCE, 0.0, CANON_HEIGHT], dtype)
    target = jnp.asarray([0.0, 0.0, CANON_HEIGHT], dtype)
    return look_at(eye, target, width=w, height=h, fx=CANON_FOCAL)


# ----------------------------------------------------------------------------- mirroring


class Mirror(NamedTuple):
    """Left/right mirror of pose vectors: ``q'[i] = sign[i] q[perm[i]]``."""

    perm: np.ndarray
    sign: np.ndarray


def mirror_table(model: BodyModel) -> Mirror:
    """The reflection ``y -> -y`` (the body's sagittal plane at rest) as a map of pose vectors.

    Joints swap with their mirror partners of the body's roles
    (:class:`~jaxmocap.body.BodyRoles` ``mirror``: the arm joints by role, the others by
    geometry). With ``M = diag(1, -1, 1)``, ``M Rot(a, theta) M = Rot(M a, -theta)``, so a joint
    whose partner's rest axis (world) is ``+M a`` changes sign and one whose partner axis is
    ``-M a`` keeps it. Root: ``t -> M t``, ``w -> (-w_x, w_y, -w_z)``. Raises one line for a
    joint without a partner or a pair whose rest axes are not mirror images.
    """
    roles = require_roles(model, "mirror_table")
    names = model.chain.dof_names
    pairs = {a: (b, s) for a, b, s in roles.mirror}
    perm = np.arange(len(names))
    sign = np.array([1.0, -1.0, 1.0, -1.0, 1.0, -1.0] + [1.0] * (len(names) - ROOT_DOFS))
    unpaired = [n for n in names[ROOT_DOFS:] if n not in pairs]
    if unpaired:
        raise InputError(
            f"mirror_table: {roles.source}: joints {unpaired} have no left/right mirror partner; "
            "name the pairs under 'mirror' in the body's roles file (or give p_mirror=0)"
        )
    for i in range(ROOT_DOFS, len(names)):
        partner, s = pairs[names[i]]
        if s == 0.0:
            raise InputError(
                f"mirror_table: {roles.source}: the rest axes of {names[i]!r} and {partner!r} "
                "are not mirror images; the body is not left/right symmetric (give p_mirror=0)"
            )
        perm[i], sign[i] = names.index(partner), s
    return Mirror(perm=perm, sign=sign)


def mirror_pose(mirror: Mirror, q: Float[Array, "*b n_dof"]) -> Float[Array, "*b n_dof"]:
    """The left/right mirror image of pose(s) ``q`` (see :func:`mirror_table`)."""
    sign = jnp.asarray(mirror.sign, q.dtype).reshape((1,) * (q.ndim - 1) + (-1,))
    return q[..., mirror.perm] * sign


# ----------------------------------------------------------------------------- sampling


def _rot_z(a):
    c, s, o, i = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, -s, o], -1), np.stack([s, c, o], -1),
                     np.stack([o, o, i], -1)], -2)


def _rot_y(a):
    c, s, o, i = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([c, o, s], -1), np.stack([o, i, o], -1),
                     np.stack([-s, o, c], -1)], -2)


def _rot_x(a):
    c, s, o, i = np.cos(a), np.sin(a), np.zeros_like(a), np.ones_like(a)
    return np.stack([np.stack([i, o, o], -1), np.stack([o, c, -s], -1),
                     np.stack([o, s, c], -1)], -2)


def orientation_rotvec(yaw, pitch, roll) -> np.ndarray:
    """Rotation vectors (rad) of ``R_z(yaw) R_y(pitch) R_x(roll)`` (NumPy, float64)."""
    r = _rot_z(np.asarray(yaw, float)) @ _rot_y(np.asarray(pitch, float)) @ _rot_x(
        np.asarray(roll, float))
    return np.asarray(matrix_to_rotvec(jnp.asarray(r, jnp.float32)), np.float64)


def sample_poses(
    config: SamplingConfig, model: BodyModel, pool: np.ndarray
) -> Float[np.ndarray, "n n_dof"]:
    """Draw ``config.size`` database poses (float32, root at the origin) from the pool of clip
    frames ``pool`` (n_frames, n_dof): blends, mirrors, jitter and camera-relative
    orientations as in the module docstring. Deterministic given ``config.seed``."""
    config.validate()
    if pool.ndim != 2 or pool.shape[1] != model.n_dof or len(pool) == 0:
        raise SamplingError(f"sample_poses: pool must have shape (n >= 1, {model.n_dof}), "
                            f"got {pool.shape}")
    rng = np.random.default_rng(config.seed)
    n = config.size
    joints = np.asarray(pool, np.float64)[:, ROOT_DOFS:]
    a = joints[rng.integers(0, len(pool), n)]
    b = joints[rng.integers(0, len(pool), n)]
    alpha = rng.uniform(0.0, 1.0, n) * (rng.uniform(size=n) >= config.p_real)
    theta = (1.0 - alpha)[:, None] * a + alpha[:, None] * b
    theta = theta + config.joint_noise * rng.standard_normal(theta.shape)
    q = np.zeros((n, model.n_dof))
    q[:, ROOT_DOFS:] = theta
    flip = rng.uniform(size=n) < config.p_mirror
    if flip.any():
        mir = mirror_table(model)
        q[flip] = q[flip][:, mir.perm] * mir.sign
    lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
    q[:, ROOT_DOFS:] = np.clip(q[:, ROOT_DOFS:], lo[ROOT_DOFS:], hi[ROOT_DOFS:])
    yaw = rng.uniform(-config.yaw_range, config.yaw_range, n)
    pitch = rng.uniform(-config.pitch_range, config.pitch_range, n)
    roll = rng.uniform(-config.roll_range, config.roll_range, n)
    q[:, 3:6] = orientation_rotvec(yaw, pitch, roll)
    return q.astype(np.float32)


def source_pool(model: BodyModel, clips: tuple[str, ...], cache: str | None = None
                ) -> np.ndarray:
    """Frames of ``clips`` retargeted to ``model`` (n_frames, n_dof), float32, within the
    limits. Cached as ``pool-<hash>.npz`` in ``cache`` (default: the jaxmocap cache dir), since
    retargeting all clips compiles a few programs."""
    from .._config import cache_folder
    from ..synth import clip_to_body_q, list_clips, load_deepmimic

    known = set(list_clips())
    bad = [c for c in clips if c not in known]
    if bad:
        raise SamplingError(f"SamplingConfig.clips: unknown clips {bad}; known: {sorted(known)}")
    folder = cache_folder("posedb") if cache is None else Path(cache)
    key = hashlib.sha256((model_digest(model) + repr(clips) + "pool-v1").encode()).hexdigest()
    path = folder / f"pool-{key[:16]}.npz"
    if path.exists():
        from ..io.preflight import read_npz

        try:  # checked by its digest: a crash or a disk may have damaged it
            got = read_npz(path, "a cached pose pool", ("q", "digest"))
            if str(got["digest"]) != _array_digest(got["q"]):
                raise InputError(f"{path}: its poses do not match their digest")
            return got["q"]
        except InputError as e:
            why = str(e).removeprefix(f"{path}: ")
            print(f"jaxmocap: the cached pose pool {path} is damaged ({why}); building it again",
                  file=sys.stderr)
            path.unlink(missing_ok=True)
    qs = [np.asarray(clip_to_body_q(load_deepmimic(c), model).q, np.float32) for c in clips]
    pool = np.concatenate(qs)
    from ..io.atomic import atomic_path

    with atomic_path(path) as tmp:
        np.savez(tmp, q=pool, digest=np.asarray(_array_digest(pool)))
    return pool


def _array_digest(a: np.ndarray) -> str:
    a = np.ascontiguousarray(a)
    return hashlib.sha256(f"{a.dtype.str}{a.shape}".encode() + a.tobytes()).hexdigest()


def model_digest(*trees) -> str:
    """SHA-256 of pytrees' array leaves (bytes, dtype, shape) and structure (static fields)."""
    h = hashlib.sha256()
    for tree in trees:
        leaves, treedef = jax.tree.flatten(tree)
        h.update(str(treedef).encode())
        for leaf in leaves:
            a = np.asarray(leaf)
            h.update(f"{a.dtype}{a.shape}".encode())
            h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()


# ----------------------------------------------------------------------------- camera frames


def _min_rotation(a: Float[Array, " 3"], b: Float[Array, " 3"]) -> Float[Array, "3 3"]:
    """Smallest rotation taking the direction of ``a`` to that of ``b`` (NaN-free if equal)."""
    a = a / jnp.linalg.norm(a)
    b = b / jnp.linalg.norm(b)
    axis = jnp.cross(a, b)
    s = jnp.linalg.norm(axis)
    angle = jnp.arctan2(s, jnp.dot(a, b))
    safe = jnp.where(s > 0, s, 1.0)
    return so3_exp(axis * jnp.where(s > 0, angle / safe, 0.0))


def pose_in_camera(
    q_db: Float[Array, " n_dof"],
    cam: Camera,
    root_in_camera: Float[Array, " 3"] | None = None,
) -> Float[Array, " n_dof"]:
    """Map a database (or blended) pose into the world of a real camera ``cam``.

    The database pose has root rotation ``R_db = exp([w]_x)`` in the canonical world, i.e.
    ``R_c = R_canon R_db`` in the canonical camera frame, with the root on the canonical line
    of sight ``t_canon`` (the root's canonical camera-frame position). Placing the root at
    ``x = root_in_camera`` (metres, ``cam``'s frame; default ``t_canon``) on a different line of
    sight, the body looks the same up to perspective when it is turned with that line of
    sight, ``R_x = Rmin(t_canon -> x)``, so the world pose is

        R_world = R_cam^T  R_x  R_canon  R_db,        t_world = R_cam^T (x - t_cam).

    Joint angles are unchanged. jit/vmap/grad-safe; follows ``q_db.dtype``.
    """
    dt = q_db.dtype
    canon = canonical_camera(dt)
    t_canon = canon.t.astype(dt)
    x = t_canon if root_in_camera is None else root_in_camera.astype(dt)
    r_c = canon.R.astype(dt) @ so3_exp(q_db[3:6])
    r_world = cam.R.astype(dt).T @ _min_rotation(t_canon, x) @ r_c
    t_world = cam.R.astype(dt).T @ (x - cam.t.astype(dt))
    w = matrix_to_rotvec(r_world)
    return jnp.concatenate([t_world, w, q_db[ROOT_DOFS:]])
