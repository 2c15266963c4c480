"""The subject's proportions: segment lengths as parameters of a multi-frame fit.

Beyond the papers: Wang et al. 2011 (§6) name their limit themselves ("our database assumes a
generic upper body shape ... subjects that differ significantly ... are tracked less well").
Here the body's bone lengths become unknowns, estimated from the first frames of a capture.

**Segments** are named by keypoint roles (the 12 :data:`~jaxmocap.body.KEYPOINT_NAMES`, which
every loaded body has), never by link names (:data:`SEGMENTS`): a segment ``(a, b)`` runs from
keypoint ``a`` to keypoint ``b``; left and right share one length factor. A segment owns the
links on the chain path from ``b``'s link up to (not including) ``a``'s link: their joint-origin
translations (the bones leading into them) are multiplied by the segment's factor ``s``. When
``a`` and ``b`` sit on the same link (wrist -> hand, neck -> head) the segment owns the offset
between them: ``off_b' = off_a' + s (off_b - off_a)``. Other keypoint offsets, and the
offsets of any other body point, scale with the factor of their link's segment (1 for links no
segment owns, e.g. legs). A factor is isotropic along its bones: a subject whose shoulders are
wider but not higher is fitted by the nearest member of this family.

**The fit** (:func:`fit_proportions`): over ``T`` frames seen by ``C`` calibrated cameras, with
observed pixel positions ``u_tck`` of keypoint ``k`` (visibility ``v_tck``), solve jointly for
the poses ``q_t`` and the log factors ``l = log s``

    min  sum_tck v_tck ||pi_c(x_k(q_t, e^l)) - u_tck||^2 / sigma_px^2
         + sum_t ||q_t - q0_t||^2 / sigma_q^2 + ||l||^2 / sigma_l^2

with optimistix' Levenberg-Marquardt (implicit adjoint: the result is differentiable w.r.t.
the observations and cameras). ``q0`` is a per-frame start (e.g. the generic body's track);
the priors keep DOFs the keypoints do not see (wrist twist, neck roll) and segments no frame
observes well-posed. :func:`scaled_body` returns the fitted body for the pose database and the
trackers (geoms scaled with their link's factor).
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jaxtyping import Array, Bool, Float

from ..camera import Camera, project
from ..errors import InputError
from .chain import fk, path_to_root
from .geometry import CAPSULE, CYLINDER, SPHERE
from .model import BodyModel, keypoint_index

# Segment -> (proximal keypoint, distal keypoint) pairs sharing one length factor.
SEGMENTS: dict[str, tuple[tuple[str, str], ...]] = {
    "torso": (("pelvis", "neck"),),
    "shoulders": (("chest", "l_shoulder"), ("chest", "r_shoulder")),
    "upper_arm": (("l_shoulder", "l_elbow"), ("r_shoulder", "r_elbow")),
    "forearm": (("l_elbow", "l_wrist"), ("r_elbow", "r_wrist")),
    "hand": (("l_wrist", "l_hand"), ("r_wrist", "r_hand")),
    "head": (("neck", "head"),),
}
SIGMA_PX = 2.0  # observation noise (px): the shirt tracker's centroid std (ik covariances)
SIGMA_Q = 1.0  # prior std of q - q0 (rad / m): weak, only for DOFs no keypoint sees
SIGMA_LOG_SCALE = 0.3  # prior std of log s: subjects within ~0.7x..1.4x of the body
FIT_RTOL, FIT_ATOL, FIT_MAX_STEPS = 1e-8, 1e-8, 400


class ProportionsError(InputError):
    """A body or observation set the proportions fit cannot use."""


class SegmentTable(NamedTuple):
    """Static tables of a body's segments (:func:`segment_table`).

    ``names``: segment names; ``link_segment[i]``: segment index owning link ``i``'s incoming
    bone (-1: none); ``kp_parent[k]``: for a keypoint that is the distal end of a same-link
    segment, the index of its proximal keypoint (else -1); ``kp_segment[k]``: the segment that
    scales keypoint ``k``'s offset (-1: none)."""

    names: tuple[str, ...]
    link_segment: np.ndarray
    kp_parent: np.ndarray
    kp_segment: np.ndarray


def segment_table(model: BodyModel, segments=SEGMENTS) -> SegmentTable:
    """The segments of ``model`` (module docstring); one line naming what is missing if the
    body lacks a keypoint role or a segment's ends are not on one branch of the chain."""
    names = tuple(segments)
    kp_link = np.asarray(model.keypoint_link)
    need = sorted({k for pairs in segments.values() for pair in pairs for k in pair})
    missing = [k for k in need if k not in model.keypoint_names]
    if missing:
        raise ProportionsError(f"proportions: the body has no keypoints {missing} (its roles "
                               "place them; see docs/USER_GUIDE.md, body roles)")  # fmt: skip
    link_segment = np.full(model.chain.n_links, -1, np.int32)
    kp_parent = np.full(len(model.keypoint_names), -1, np.int32)
    kp_segment = np.full(len(model.keypoint_names), -1, np.int32)
    for s, pairs in enumerate(segments.values()):
        for a, b in pairs:
            ia, ib = (int(keypoint_index(model, k)[0]) for k in (a, b))
            la, lb = int(kp_link[ia]), int(kp_link[ib])
            path = path_to_root(model.chain.topology, lb)
            if la not in path:
                raise ProportionsError(
                    f"proportions: segment {names[s]!r}: keypoint {a!r} (link "
                    f"{model.chain.link_names[la]!r}) is not on the chain above {b!r}"
                )
            if la == lb:
                kp_parent[ib], kp_segment[ib] = ia, s
            for link in path[: path.index(la)]:
                if link_segment[link] < 0:
                    link_segment[link] = s
    for k in range(len(model.keypoint_names)):
        if kp_segment[k] < 0:
            kp_segment[k] = link_segment[kp_link[k]]
    return SegmentTable(names, link_segment, kp_parent, kp_segment)


def _factor(table_index: np.ndarray, scales: Array) -> Array:
    """Per-row factor: ``scales[i]`` where ``i >= 0``, 1 where ``i = -1``."""
    s = jnp.concatenate([scales, jnp.ones((1,), scales.dtype)])
    return s[jnp.where(table_index >= 0, table_index, scales.shape[0])]


def scaled_kinematics(
    model: BodyModel, table: SegmentTable, scales: Float[Array, " n_segments"]
) -> BodyModel:
    """``model`` with its bones and keypoint offsets scaled by segment (module docstring).

    Differentiable w.r.t. ``scales`` (joint origins and offsets are traced fields); the
    geometry is left as it is (see :func:`scaled_body` for a body to render)."""
    dtype = model.chain.joint_origin.dtype
    scales = scales.astype(dtype)
    f_link = _factor(table.link_segment, scales)
    origin = model.chain.joint_origin
    origin = origin.at[:, :3, 3].multiply(f_link[:, None])
    off = model.keypoint_offset.astype(dtype)
    f_kp = _factor(table.kp_segment, scales)
    scaled_off = off * f_kp[:, None]
    same_link = table.kp_parent >= 0
    if same_link.any():  # off_b' = off_a' + s (off_b - off_a), proximal a first (no chains)
        idx = np.flatnonzero(same_link)
        a = table.kp_parent[idx]
        scaled_off = scaled_off.at[idx].set(
            scaled_off[a] + f_kp[idx][:, None] * (off[idx] - off[a]))
    model = eqx.tree_at(lambda m: m.chain.joint_origin, model, origin)
    return eqx.tree_at(lambda m: m.keypoint_offset, model, scaled_off)


def segment_lengths(model: BodyModel, segments=SEGMENTS) -> dict[str, float]:
    """Length (m) of each segment at the rest pose: the mean over its pairs of the distance
    between the two keypoints."""
    from .model import keypoints

    kp = np.asarray(keypoints(model, jnp.zeros((model.n_dof,), model.chain.joint_origin.dtype)))
    out = {}
    for name, pairs in segments.items():
        d = [np.linalg.norm(kp[keypoint_index(model, a)[0]] - kp[keypoint_index(model, b)[0]])
             for a, b in pairs]  # fmt: skip
        out[name] = float(np.mean(d))
    return out


class ProportionFit(eqx.Module):
    """Result of :func:`fit_proportions`: ``scales`` (n_segments,) factors w.r.t. the input
    body, ``segments`` their names, ``q`` (T, n_dof) the fitted poses, ``rms_px`` the RMS
    reprojection error of the visible keypoints, ``result`` optimistix' result code."""

    scales: Float[Array, " n_segments"]
    q: Float[Array, "T n_dof"]
    rms_px: Float[Array, ""]
    result: optx.RESULTS
    segments: tuple[str, ...] = eqx.field(static=True)


def fit_proportions(
    model: BodyModel,
    cams: Camera,
    uv: Float[Array, "T C K 2"],
    visible: Bool[Array, "T C K"],
    q0: Float[Array, "T n_dof"],
    *,
    segments=SEGMENTS,
    sigma_px: float = SIGMA_PX,
    sigma_q: float = SIGMA_Q,
    sigma_log_scale: float = SIGMA_LOG_SCALE,
    max_steps: int = FIT_MAX_STEPS,
) -> ProportionFit:
    """Segment length factors and poses from keypoint observations (module docstring).

    ``cams``: stacked cameras (C); ``uv``: pixel positions of ``model.keypoint_names`` in each
    camera and frame; ``visible``: which observations count; ``q0``: per-frame start poses.
    jit-able (with ``model`` and ``segments`` static via closure) and differentiable w.r.t.
    ``uv`` and ``cams`` (implicit adjoint)."""
    table = segment_table(model, segments)
    n_seg = len(table.names)
    dtype = jnp.result_type(q0.dtype, uv.dtype)
    w = visible.astype(dtype)[..., None] / sigma_px

    def residuals(y, _):
        q, log_s = y
        body = scaled_kinematics(model, table, jnp.exp(log_s))
        kp = jax.vmap(lambda qt: _keypoints(body, qt))(q)  # (T, K, 3)
        pred = jax.vmap(lambda c: jax.vmap(lambda x: project(c, x))(kp), out_axes=1)(cams)
        r_obs = (pred - uv) * w
        return r_obs, (q - q0) / sigma_q, log_s / sigma_log_scale

    y0 = (q0.astype(dtype), jnp.zeros((n_seg,), dtype))
    solver = optx.LevenbergMarquardt(rtol=FIT_RTOL, atol=FIT_ATOL)
    sol = optx.least_squares(
        residuals, solver, y0, max_steps=max_steps, throw=False,
        adjoint=optx.ImplicitAdjoint(linear_solver=lx.AutoLinearSolver(well_posed=False)),
    )  # fmt: skip
    q, log_s = sol.value
    r_obs = residuals(sol.value, None)[0] * sigma_px
    n_vis = jnp.maximum(jnp.sum(visible), 1)
    rms = jnp.sqrt(jnp.sum(r_obs**2) / n_vis)
    return ProportionFit(jnp.exp(log_s), q, rms, sol.result, table.names)


def _keypoints(body: BodyModel, q: Array) -> Array:
    from .model import keypoints_from_transforms

    return keypoints_from_transforms(body, fk(body.chain, q))


def scaled_body(model: BodyModel, scales, segments=SEGMENTS) -> BodyModel:
    """A concrete body with the fitted factors applied: bones and keypoints as in
    :func:`scaled_kinematics`, each geom's position in its link frame and its size scaled
    by its link's segment factor (girth follows length), so the pose database and the
    trackers can be rebuilt for the subject."""
    table = segment_table(model, segments)
    scales = np.asarray(scales, np.float64)
    if scales.shape != (len(table.names),) or not np.all(np.isfinite(scales) & (scales > 0)):
        raise ProportionsError(f"scaled_body: expected {len(table.names)} positive factors "
                               f"for {table.names}, got {scales}")  # fmt: skip
    body = scaled_kinematics(model, table, jnp.asarray(scales, model.chain.joint_origin.dtype))
    geo = model.geometry
    f_link = np.asarray(_factor(table.link_segment, jnp.asarray(scales)))
    f = f_link[np.asarray(geo.link)]
    pose = np.array(geo.pose)
    pose[:, :3, 3] *= f[:, None]
    size = np.array(geo.size) * f[:, None]
    kind = np.asarray(geo.kind)
    size[kind == SPHERE, 1:] = 0.0
    size[(kind == CAPSULE) | (kind == CYLINDER), 2] = 0.0
    new_geo = eqx.tree_at(lambda g: (g.pose, g.size), geo,
                          (jnp.asarray(pose, geo.pose.dtype), jnp.asarray(size, geo.size.dtype)))
    return eqx.tree_at(lambda m: m.geometry, body, new_geo)


__all__ = [
    "SEGMENTS", "ProportionFit", "ProportionsError", "SegmentTable", "fit_proportions",
    "scaled_body", "scaled_kinematics", "segment_lengths", "segment_table",
]  # fmt: skip
