"""The body model: kinematic chain + geometry + named keypoints, and pose-vector helpers.

The keypoints are the joint centres and body points both papers measure: the colour-shirt
tracker's IK constrains patch centroids but reports joint positions (Wang et al. 2011 §7),
the stereo particle filter's 3D distance cue uses head and hand positions (Azad et al. 2007
§III.C), and its 14-DOF model moves only the root and the arms (Azad et al. 2007 §III.A).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from .chain import ROOT_DOFS, KinematicChain, fk
from .geometry import ArrayLike, Geometry
from .roles import KEYPOINT_NAMES, BodyRoles, require_roles

ROOT_DOF_NAMES = ("root_tx", "root_ty", "root_tz", "root_rx", "root_ry", "root_rz")
# Azad et al. 2007 §III.A: 6 root DOFs + 3 per shoulder + 1 per elbow = 14 DOFs (joint roles).
STEREO_JOINTS = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow")
DEFAULT_URDF = Path(__file__).parent / "data" / "upper_body.urdf"
# Keypoints of the bundled model: link and offset (m, link frame), cf. data/upper_body.urdf.
DEFAULT_KEYPOINTS = {
    "pelvis": ("pelvis", (0.0, 0.0, 0.0)),
    "chest": ("chest", (0.0, 0.0, 0.30)),
    "neck": ("head", (0.0, 0.0, 0.0)),
    "head": ("head", (0.0, 0.0, 0.15)),
    "l_shoulder": ("l_upper_arm", (0.0, 0.0, 0.0)),
    "r_shoulder": ("r_upper_arm", (0.0, 0.0, 0.0)),
    "l_elbow": ("l_forearm", (0.0, 0.0, 0.0)),
    "r_elbow": ("r_forearm", (0.0, 0.0, 0.0)),
    "l_wrist": ("l_hand", (0.0, 0.0, 0.0)),
    "r_wrist": ("r_hand", (0.0, 0.0, 0.0)),
    "l_hand": ("l_hand", (0.0, 0.0, -0.09)),
    "r_hand": ("r_hand", (0.0, 0.0, -0.09)),
}


class BodyModel(eqx.Module):
    """Kinematic chain, its geometry, named keypoints (link index + offset in link frame) and
    the roles of its parts (:class:`~jaxmocap.body.roles.BodyRoles`; None for hand-made
    models: functions that need roles then say so in one line)."""

    chain: KinematicChain
    geometry: Geometry
    keypoint_link: Int[Array, " n_keypoints"]
    keypoint_offset: Float[Array, "n_keypoints 3"]
    keypoint_names: tuple[str, ...] = eqx.field(static=True)
    roles: BodyRoles | None = eqx.field(static=True, default=None)

    @property
    def n_dof(self) -> int:
        return self.chain.n_dof


def make_body_model(
    chain: KinematicChain,
    geometry: Geometry,
    keypoints: dict[str, tuple[str, ArrayLike]] | None = None,
    roles: BodyRoles | None = None,
) -> BodyModel:
    """BodyModel with keypoints given as ``{name: (link name, offset xyz in the link frame)}``
    and optional roles."""
    keypoints = keypoints or {}
    names = tuple(keypoints)
    links = np.array([chain.link_index(keypoints[k][0]) for k in names], dtype=np.int32)
    offsets = np.array([np.asarray(keypoints[k][1], float) for k in names]).reshape(-1, 3)
    return BodyModel(
        chain=chain,
        geometry=geometry,
        keypoint_link=jnp.asarray(links),
        keypoint_offset=jnp.asarray(offsets),
        keypoint_names=names,
        roles=roles,
    )


def keypoints_from_transforms(
    model: BodyModel, link_transforms: Float[Array, "n_links 4 4"]
) -> Float[Array, "n_keypoints 3"]:
    """Keypoint world positions (m) given the links' world transforms from ``fk``."""
    t = link_transforms[model.keypoint_link]
    off = model.keypoint_offset.astype(link_transforms.dtype)
    return (t[:, :3, :3] * off[:, None, :]).sum(-1) + t[:, :3, 3]


def keypoints(model: BodyModel, q: Float[Array, " n_dof"]) -> Float[Array, "n_keypoints 3"]:
    """World positions (m) of the model's named keypoints (``model.keypoint_names``) at ``q``."""
    return keypoints_from_transforms(model, fk(model.chain, q))


def geom_world_poses(
    model: BodyModel, link_transforms: Float[Array, "n_links 4 4"]
) -> Float[Array, "n_geoms 4 4"]:
    """World -> geom transforms: ``T_link(g) @ pose_g`` for every geom ``g``."""
    t = link_transforms[model.geometry.link]
    return t @ model.geometry.pose.astype(link_transforms.dtype)


def keypoint_index(model: BodyModel, names: str | Sequence[str]) -> np.ndarray:
    """Indices of the named keypoints in ``keypoints(model, q)``."""
    names = [names] if isinstance(names, str) else list(names)
    bad = [n for n in names if n not in model.keypoint_names]
    if bad:
        raise ValueError(f"unknown keypoints {bad}; the model has {model.keypoint_names}")
    return np.array([model.keypoint_names.index(n) for n in names], dtype=np.int32)


def dof_index(model: BodyModel | KinematicChain, names: str | Sequence[str]) -> np.ndarray:
    """Indices into ``q`` of the named DOFs (``root_tx .. root_rz`` or joint names).

    Returns a NumPy int array (static), usable to slice traced ``q`` without a recompile.
    """
    chain = model.chain if isinstance(model, BodyModel) else model
    names = [names] if isinstance(names, str) else list(names)
    bad = [n for n in names if n not in chain.dof_names]
    if bad:
        raise ValueError(f"unknown DOFs {bad}; the model has {chain.dof_names}")
    return np.array([chain.dof_names.index(n) for n in names], dtype=np.int32)


def stereo_dofs(model: BodyModel) -> np.ndarray:
    """The 14 DOFs of Azad et al. 2007 §III.A, ascending: root 6, shoulders 3+3, elbows 1+1
    (the DOFs of the joint roles :data:`STEREO_JOINTS`: as many as the body has there)."""
    roles = require_roles(model, "stereo_dofs")
    joints = tuple(d for j in STEREO_JOINTS for d in roles.dofs(j))
    return np.sort(dof_index(model, ROOT_DOF_NAMES + joints))


def expand_q(
    model: BodyModel,
    q_sub: Float[Array, " n_sub"],
    index: np.ndarray,
    default: Float[Array, " n_dof"] | None = None,
) -> Float[Array, " n_dof"]:
    """Full pose vector with ``q[index] = q_sub`` and the other DOFs held at ``default``.

    ``default`` is the rest pose (zeros) if not given. ``index`` is static (e.g.
    ``stereo_dofs(model)``); differentiable w.r.t. ``q_sub`` and ``default``.
    """
    index = np.asarray(index)
    if q_sub.shape != index.shape:
        raise ValueError(f"expand_q: q_sub has shape {q_sub.shape}, index {index.shape}")
    if default is None:
        default = jnp.zeros((model.n_dof,), dtype=q_sub.dtype)
    return default.astype(q_sub.dtype).at[index].set(q_sub)


def clip_to_limits(model: BodyModel, q: Float[Array, "*b n_dof"]) -> Float[Array, "*b n_dof"]:
    """``q`` clipped into the joint limits ``[lower, upper]`` (root DOFs are unbounded)."""
    lo = model.chain.lower.astype(q.dtype)
    hi = model.chain.upper.astype(q.dtype)
    return jnp.clip(q, lo, hi)


def rest_pose(model: BodyModel, dtype=None) -> Float[Array, " n_dof"]:
    """The rest pose q = 0 (upright, facing +x, arms hanging for the bundled model)."""
    return jnp.zeros((model.n_dof,), dtype=dtype)


__all__ = [
    "KEYPOINT_NAMES", "ROOT_DOFS", "BodyModel", "make_body_model", "keypoints",
    "keypoints_from_transforms", "geom_world_poses", "keypoint_index", "dof_index",
    "stereo_dofs", "expand_q", "clip_to_limits", "rest_pose",
]  # fmt: skip
