"""Gradient-based tuning of the pipeline's covariances through the differentiable pipeline.

Neither paper could do this: Wang et al. (§5.2 step 4) "train off-line on ground-truth data"
the IK covariances Sigma_c, Sigma_b, Sigma_p by taking the covariance of each term at the true
pose (:func:`jaxmocap.ik.estimate_covariances`); Azad et al. (§III-D) pick sigma_g, sigma_d by
hand. Here each parameter group gets a differentiable loss that measures what the user wants
(tracking error), and an optax optimiser descends it (:func:`fit`: Adam, or L-BFGS with
its linesearch; resumable from a :class:`FitState`). Three groups:

**1. IK covariances (Wang §5.2 step 4).** ``ik_loss`` runs the tracker's last step, the IK
solve, over a window of frames in a ``jax.lax.scan``: frame t solves

    q*_t = argmin_q  sum_{i,k} ||c^{*i}_k(q) - c^{ki}_t||^2_{Sigma_c}
                     + ||q - q_{b,t}||^2_{Sigma_b} + ||q - q_h||^2_{Sigma_p},

with ``q_h = q*_{t-1}`` (after a frame with fewer than ``MIN_VALID_PATCHES`` centroids the
tracker holds the pose and drops the temporal prior, ``q_h := q_b``; so does this scan), and
the loss is the mean per-joint position error (metres) ``mean_t mean_j ||x_j(q*_t) -
x_j(q_gt,t)||`` over valid frames, plus optionally ``jitter_weight`` times the mean error of
the joints' frame-to-frame displacement. Gradients go through the scan (through ``q_h``, so
a covariance's effect on later frames counts) and through each LM solve by optimistix's
implicit adjoint. **What is held fixed**: the discrete parts of the tracker — histogram
search, hard classification, the 10-NN database blend and hence the measured centroids
``c^{ki}_t``, their validity and ``q_{b,t}`` — are precomputed by running the real tracker
(:func:`ik_observations_from_tracker`: ``centroids``, ``visible``, ``q_blend`` of
:class:`jaxmocap.trackers.shirt.ShirtOutput`). In the real tracker ``q*`` also feeds back into
the next frame's white balance; that loop is cut (the IK-covariance tuning sees the tracker's
observations as produced with the covariances it ran with).

**2. Colour model (Wang §5.2 step 1).** The Gaussians' covariances Sigma_k and the threshold T
through :func:`jaxmocap.color.soft_classify` (responsibilities ``softmax(-d^2 / 2t)`` over
background + colours, background at ``T^2``): ``color_loss`` is the pixel cross-entropy
against ground-truth colour-id maps of rendered frames (0 = background), with the frames'
white balance W held fixed. The temperature ``t`` is a fixed hyper-parameter of the surrogate
(the hard classifier is its ``t -> 0`` limit); means are not tuned (the paper's scribble fit
estimates them well; their covariances and T decide the trade-off between colours and
background).

**3. Stereo-filter cue widths (Azad §III-D).** sigma_g, sigma_d act through the particle
weights ``w_j ∝ exp(log p(z | s_j))``. ``pf_loss`` is the filter's own frame loop with the
candidate widths: the tracker's annealed initialisation on its start frame with its key, then
its frame step over every frame (:func:`jaxmocap.trackers.stereo_pf.filter.filter_step`: the
resampling, the motion model's adaptive noise, the guided and swivel proposals), on the
observations the tracker made (held fixed: edge maps, foreground, triangulated head and hands),
scored on every frame: the mean per-joint error of its estimate against the ground-truth
keypoints -- in value the experiment's all-frames error of that run. Its gradient crosses the
resamplings by the filter's stop-gradient resampling (Scibior & Wood 2021,
:mod:`jaxmocap.pf.resample`; the forward pass is unchanged) and is truncated to windows of
:data:`PF_WINDOW` frames (truncated backpropagation through time: a frame's error is
differentiated through the frames since the last window boundary, the state entering a
window is held constant); the initialisation's annealing is run with the widths but not
differentiated. (Before issue 51 the loss was one weighting step over fixed particles; it did
not predict the running filter, docs/results/tuning.md section 3.)

**Constrained parameters** are declared once (as dynamax's ``ParameterProperties``):
:data:`IK_PARAMETERS`, :data:`COLOR_PARAMETERS`, :data:`PF_PARAMETERS` name the bijection of
each field; the optimiser sees only unconstrained arrays.

**Why one file** (over 600 lines): the three losses, their constraint table and the one
optimiser loop (:func:`fit`, its checkpoints) are one study's parts, read together; split,
each piece would import the others' private helpers (``_constrain``, the theta classes).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxmocap.body import BodyModel, keypoints
from jaxmocap.camera import Camera
from jaxmocap.color import ColorModel, soft_classify
from jaxmocap.errors import InputError
from jaxmocap.ik import (
    DEFAULT_ATOL,
    DEFAULT_RTOL,
    IKCovariances,
    PatchAnchors,
    estimate_covariances,
    solve_ik,
)
from jaxmocap.pf.cues import Observation, StereoLikelihood
from jaxmocap.trackers.shirt import MIN_VALID_PATCHES

SOFT_TEMPERATURE = 1.0  # t of the soft classifier in the colour loss (squared std units)
NORM_EPS = 1e-12  # m^2 under the square root of a joint error (NaN-free gradient at 0)


class TuneError(InputError):
    """Tuning data or settings that cannot be used (shapes, lengths, empty sets)."""


# ----------------------------------------------------------------------------- constraints


class Constraint(NamedTuple):
    """A bijection from unconstrained parameters to a constrained value (and back)."""

    name: str
    to_value: Callable[[Array], Array]
    to_unconstrained: Callable[[Array], Array]


def _tril(n: int) -> tuple[np.ndarray, np.ndarray]:
    return np.tril_indices(n, -1)


def _n_from_log_cholesky(m: int) -> int:
    n = int(round((np.sqrt(8 * m + 1) - 1) / 2))
    if n * (n + 1) // 2 != m:
        raise ValueError(f"log-Cholesky vector of length {m} is not n (n + 1) / 2 for any n")
    return n


def spd_from_log_cholesky(theta: Float[Array, " m"]) -> Float[Array, "n n"]:
    """``Sigma = L L^T`` with ``L = diag(exp(a)) (I + N)``: ``a = theta[:n]`` the log of L's
    diagonal and ``N`` strictly lower triangular from ``theta[n:]`` (row-major,
    ``np.tril_indices(n, -1)``); ``m = n (n + 1) / 2``.

    Scaling the unit-lower factor by the diagonal makes the off-diagonal parameters unit-free
    (``N[i, j] = L[i, j] / L[i, i]``): one optimiser step means the same for a DOF with a
    variance of 1e-6 m^2 as for one of 1 rad^2 (a plain log-Cholesky's off-diagonals are in
    the units of the covariance and swamp tiny diagonals)."""
    n = _n_from_log_cholesky(theta.shape[0])
    rows, cols = _tril(n)
    unit = jnp.eye(n, dtype=theta.dtype).at[rows, cols].set(theta[n:])
    L = jnp.exp(theta[:n])[:, None] * unit
    return L @ L.T


def log_cholesky_from_spd(cov: Float[Array, "n n"]) -> Float[Array, " m"]:
    """Inverse of :func:`spd_from_log_cholesky`."""
    L = jnp.linalg.cholesky(cov)
    d = jnp.diagonal(L)
    rows, cols = _tril(cov.shape[0])
    return jnp.concatenate([jnp.log(d), (L / d[:, None])[rows, cols]])


LOG_CHOLESKY = Constraint(
    "scaled log-Cholesky (SPD matrix)", spd_from_log_cholesky, log_cholesky_from_spd
)
LOG = Constraint("log (positive)", jnp.exp, jnp.log)
BATCH_LOG_CHOLESKY = Constraint(
    "log-Cholesky per row (stack of SPD matrices)",
    jax.vmap(spd_from_log_cholesky),
    jax.vmap(log_cholesky_from_spd),
)

# Which bijection each tuned field goes through (declared once).
IK_PARAMETERS = {"centroid": LOG_CHOLESKY, "blend": LOG_CHOLESKY, "prior": LOG_CHOLESKY}
COLOR_PARAMETERS = {"cov": BATCH_LOG_CHOLESKY, "threshold": LOG}
PF_PARAMETERS = {"sigma_g": LOG, "sigma_d": LOG}


def _constrain(theta: eqx.Module, table: dict[str, Constraint]) -> dict[str, Array]:
    return {k: c.to_value(getattr(theta, k)) for k, c in table.items()}


# ----------------------------------------------------------------------------- 1. IK covariances


class IKTheta(eqx.Module):
    """Unconstrained IK covariances (:data:`IK_PARAMETERS`): full log-Cholesky vectors of
    Sigma_c (2 x 2: 3 numbers), Sigma_b and Sigma_p (n_dof x n_dof: n (n + 1) / 2 each)."""

    centroid: Float[Array, " 3"]
    blend: Float[Array, " m"]
    prior: Float[Array, " m"]


def ik_theta(cov: IKCovariances) -> IKTheta:
    """Unconstrained parameters of shared (2, 2) Sigma_c and Sigma_b, Sigma_p given as
    matrices or variance vectors (a vector becomes a diagonal matrix)."""
    if cov.centroid.ndim != 2:
        raise TuneError("ik_theta: tuning needs a shared Sigma_c (2, 2), got per-patch (P, 2, 2)")
    full = lambda a: jnp.diag(a) if a.ndim == 1 else a
    return IKTheta(
        centroid=LOG_CHOLESKY.to_unconstrained(cov.centroid),
        blend=LOG_CHOLESKY.to_unconstrained(full(cov.blend)),
        prior=LOG_CHOLESKY.to_unconstrained(full(cov.prior)),
    )


class IKRoleTheta(eqx.Module):
    """Unconstrained IK covariances shared by bodies through their roles: the log-Cholesky
    vector of Sigma_c (2 x 2) and the log variances of Sigma_b and Sigma_p (diagonal) on the
    DOFs of a reference body (the bundled one); a body's DOF takes the variances of its
    counterpart (``IKSetup.dof_index``, the matching of
    :func:`jaxmocap.trackers.shirt.covariances.transfer_covariances`), or the defaults. What
    one tunes over sequences whose bodies differ (the test world: one body per sequence)."""

    centroid: Float[Array, " 3"]
    blend: Float[Array, " n_ref"]
    prior: Float[Array, " n_ref"]


def ik_role_theta(cov: IKCovariances) -> IKRoleTheta:
    """:class:`IKRoleTheta` of the reference body's covariances (their diagonals)."""
    if cov.centroid.ndim != 2:
        raise TuneError("ik_role_theta: tuning needs a shared Sigma_c (2, 2)")
    diag = lambda a: a if a.ndim == 1 else jnp.diagonal(a)
    return IKRoleTheta(LOG_CHOLESKY.to_unconstrained(cov.centroid), jnp.log(diag(cov.blend)),
                       jnp.log(diag(cov.prior)))  # fmt: skip


def ik_covariances(theta: IKTheta | IKRoleTheta, setup: IKSetup | None = None) -> IKCovariances:
    """The covariances of unconstrained parameters (positive definite by construction); an
    :class:`IKRoleTheta` gives the reference body's, or with ``setup`` (its ``dof_index``)
    those of the setup's body."""
    if isinstance(theta, IKTheta):
        return IKCovariances(**_constrain(theta, IK_PARAMETERS))
    centroid = LOG_CHOLESKY.to_value(theta.centroid)
    blend, prior = jnp.exp(theta.blend), jnp.exp(theta.prior)
    if setup is not None and setup.dof_index is not None:
        idx = setup.dof_index
        hit = idx >= 0
        j = jnp.maximum(idx, 0)
        blend = jnp.where(hit, blend[j], setup.default_var[0])
        prior = jnp.where(hit, prior[j], setup.default_var[1])
    return IKCovariances(centroid=centroid, blend=blend, prior=prior)


class IKSetup(eqx.Module):
    """What the IK needs besides the observations: body, stacked cameras, patch anchors and
    the keypoints the error is measured on (``joints``, indices into ``body.keypoint_names``);
    ``robust`` the tracker's Cauchy width of the centroid term (inf: the paper's squares);
    ``dof_index`` (role-shared parameters, :class:`IKRoleTheta`): per DOF of ``body`` the DOF
    of the reference body whose variances it takes, -1 for the defaults ``default_var``."""

    body: BodyModel
    cams: Camera
    anchors: PatchAnchors
    joints: Int[Array, " n_joints"]
    rtol: Float[Array, ""]  # tolerances of every IK solve (traced)
    atol: Float[Array, ""]
    robust: Float[Array, ""] | None = None
    dof_index: Int[Array, " n_dof"] | None = None
    default_var: Float[Array, " 2"] | None = None  # (blend, prior) variance without a match


def ik_setup(
    body: BodyModel, cams: Camera, anchors: PatchAnchors, joints: Sequence[str] | None = None,
    rtol: float = DEFAULT_RTOL, atol: float = DEFAULT_ATOL, robust: float | None = None,
    dof_index: ArrayLike | None = None, default_var: tuple[float, float] | None = None,
) -> IKSetup:  # fmt: skip
    """Validated :class:`IKSetup`; ``joints`` keypoint names (default all); ``rtol``/``atol``
    of the IK solves (tighter than the tracker's when checking gradients); ``robust`` the
    tracker's ``Rounds.robust``; ``dof_index`` / ``default_var`` for :class:`IKRoleTheta`
    (:func:`jaxmocap.trackers.shirt.covariances.transfer_index`)."""
    names = list(body.keypoint_names)
    joints = names if joints is None else list(joints)
    bad = [j for j in joints if j not in names]
    if bad or not joints:
        raise TuneError(f"ik_setup: joints {bad or joints} not among the keypoints {names}")
    if cams.K.ndim != 3:
        raise TuneError("ik_setup: cams must be stacked (jaxmocap.camera.stack_cameras)")
    dt = cams.K.dtype
    idx = jnp.asarray([names.index(j) for j in joints], jnp.int32)
    rob = None if robust is None else jnp.asarray(robust, dt)
    if dof_index is not None:
        dof_index = jnp.asarray(dof_index, jnp.int32)
        if dof_index.shape != (body.n_dof,):
            raise TuneError(f"ik_setup: dof_index has shape {dof_index.shape}, the body "
                            f"{body.n_dof} DOFs")
        default_var = jnp.asarray(default_var, dt)
    return IKSetup(body, cams, anchors, idx, jnp.asarray(rtol, dt), jnp.asarray(atol, dt), rob,
                   dof_index, default_var)  # fmt: skip


class IKObservations(eqx.Module):
    """Per-frame inputs of the IK step and the ground truth, over windows of T frames:
    ``centroids`` (pixels; anything, NaN included, where not ``visible``), ``visible``, the
    blended database pose ``q_b`` and the true pose ``q_gt``; ``scored`` (optional) the frames
    the loss counts besides needing ``MIN_VALID_PATCHES`` centroids, e.g. those the tracker
    reported valid (held fixed: its validity is discrete), as the experiment's per-joint error
    counts them. ``q_start`` (optional) the pose each frame's LM solve starts from instead of
    ``q_b``: the tracker's own estimate, so that the re-run descends into the basin the tracker
    ended in (the tracker tries several starts and keeps the best-agreeing one; a re-run from
    ``q_b`` alone lands metres away where ``q_b`` is far off). ``view_offset`` / ``view_shift``
    (optional, both or neither) per-frame per-view anchors (:func:`jaxmocap.ik.view_anchors`,
    the tracker's ``Rounds.view_anchors``) held fixed, instead of ``setup``'s shared ones: with
    the shared 3D anchors the re-run's solutions moved up to 0.5-0.7 rad from the tracker's own
    on the test world's dev split (shirt_03: 5-10 cm per frame against its 2-4 cm). With
    ``q_start`` given, ``scored`` also says after which frames the temporal prior is the
    previous solution (:func:`ik_track`'s ``prior_from``; the tracker's ``q_h``)."""

    centroids: Float[Array, "n_windows t n_cams n_patches 2"]
    visible: Bool[Array, "n_windows t n_cams n_patches"]
    q_b: Float[Array, "n_windows t n_dof"]
    q_gt: Float[Array, "n_windows t n_dof"]
    scored: Bool[Array, "n_windows t"] | None = None
    q_start: Float[Array, "n_windows t n_dof"] | None = None
    view_offset: Float[Array, "n_windows t n_cams n_patches 3"] | None = None
    view_shift: Float[Array, "n_windows t n_cams n_patches 2"] | None = None


def _windows(a: np.ndarray, length: int) -> np.ndarray:
    n = a.shape[0] // length
    return a[: n * length].reshape((n, length) + a.shape[1:])


def ik_observations(
    sequences: Sequence[tuple[ArrayLike, ...]],
    window: int,
    dtype=None,
) -> IKObservations:
    """Stack sequences ``(centroids (T, C, P, 2), visible (T, C, P), q_b (T, n), q_gt (T,
    n)[, scored (T,)[, q_start (T, n)]])`` into windows of ``window`` consecutive frames (a
    sequence's tail shorter than a window is dropped; windows never straddle two sequences);
    ``scored`` and ``q_start`` each given for every sequence or none (a non-finite row of
    ``q_start``: that frame starts from ``q_b``)."""
    if window < 2:
        raise TuneError(f"ik_observations: window must be >= 2 frames, got {window}")
    parts: list[list[np.ndarray]] = [[], [], [], [], [], []]
    n_scored = n_start = 0
    for s, seq in enumerate(sequences):
        c, v, qb, qg = (np.asarray(a) for a in seq[:4])
        if len(seq) > 4:
            sc = np.asarray(seq[4], bool)
            if sc.shape != (c.shape[0],):
                raise TuneError(f"ik_observations: sequence {s}: scored has shape {sc.shape}, "
                                f"expected ({c.shape[0]},)")
            parts[4].append(_windows(sc, window))
            n_scored += 1
        if len(seq) > 5:
            qs = np.asarray(seq[5])
            if qs.shape != np.shape(seq[2]):
                raise TuneError(f"ik_observations: sequence {s}: q_start has shape {qs.shape}, "
                                f"expected {np.shape(seq[2])} (as q_b)")
            qs = np.where(np.isfinite(qs).all(axis=-1, keepdims=True), qs, np.asarray(seq[2]))
            parts[5].append(_windows(qs, window))
            n_start += 1
        T = c.shape[0]
        if c.ndim != 4 or c.shape[-1] != 2 or v.shape != c.shape[:3] or qb.shape != qg.shape:
            raise TuneError(
                f"ik_observations: sequence {s}: expected centroids (T, C, P, 2), visible "
                f"(T, C, P), q_b and q_gt (T, n_dof); got {c.shape}, {v.shape}, {qb.shape}, "
                f"{qg.shape}"
            )
        if qb.shape[0] != T:
            raise TuneError(
                f"ik_observations: sequence {s}: {T} centroid frames, {qb.shape[0]} poses"
            )
        for p, a in zip(parts[:4], (c, v.astype(bool), qb, qg), strict=True):
            p.append(_windows(a, window))
    if not parts[0] or sum(p.shape[0] for p in parts[0]) == 0:
        raise TuneError(f"ik_observations: no sequence has {window} frames")
    if n_scored not in (0, len(parts[0])) or n_start not in (0, len(parts[0])):
        raise TuneError("ik_observations: scored or q_start given for some sequences, not all")
    dt = dtype or jnp.result_type(float)
    c, v, qb, qg = (np.concatenate(p) for p in parts[:4])
    sc = jnp.asarray(np.concatenate(parts[4])) if n_scored else None
    qs = jnp.asarray(np.concatenate(parts[5]), dt) if n_start else None
    return IKObservations(
        jnp.asarray(c, dt), jnp.asarray(v), jnp.asarray(qb, dt), jnp.asarray(qg, dt), sc, qs
    )


def ik_observations_from_tracker(out, q_gt: ArrayLike):
    """The tuple ``(centroids, visible, q_b, q_gt)`` of one tracked sequence (stacked
    :class:`jaxmocap.trackers.shirt.ShirtOutput`) for :func:`ik_observations`."""
    return (np.asarray(out.centroids), np.asarray(out.visible), np.asarray(out.q_blend),
            np.asarray(q_gt))  # fmt: skip


def _joint_error(setup: IKSetup, q: Array, q_gt: Array) -> tuple[Array, Array]:
    """(mean per-joint error (m), joint positions (J, 3)) at pose q."""
    x = keypoints(setup.body, q)[setup.joints]
    g = keypoints(setup.body, q_gt)[setup.joints]
    e = jnp.sqrt(jnp.sum(jnp.square(x - g), axis=-1) + NORM_EPS)
    return jnp.mean(e), x - g


def ik_track(
    cov: IKCovariances,
    setup: IKSetup,
    centroids: Float[Array, "t n_cams n_patches 2"],
    visible: Bool[Array, "t n_cams n_patches"],
    q_b: Float[Array, "t n_dof"],
    q_start: Float[Array, "t n_dof"] | None = None,
    view: tuple[Array, Array] | None = None,
    prior_from: Bool[Array, " t"] | None = None,
) -> tuple[Float[Array, "t n_dof"], Bool[Array, " t"]]:
    """The tracker's step 4 over one window (``lax.scan``): poses q*_t and frame validity.

    The first frame has no temporal prior (``q_h = q_b``, as after a loss); an invalid frame
    (< ``MIN_VALID_PATCHES`` centroids) holds the previous pose (the window's first: q_b).
    Each solve starts from ``q_start`` (default ``q_b``) and, with ``view`` = (offsets (t, C,
    P, 3), shifts (t, C, P, 2)), uses those per-view anchors (:class:`IKObservations`).
    ``prior_from`` (optional): the frames after which the next frame's temporal prior is the
    previous solution (else its q_b), as the tracker's ``q_h`` is its previous output only
    after a frame it reported valid.
    """
    chain = setup.body.chain
    T = q_b.shape[0]
    if view is None:  # placeholders, unused
        view = (jnp.zeros((T, 1, 1, 3), q_b.dtype), jnp.zeros((T, 1, 1, 2), q_b.dtype))
        per_view = False
    else:
        per_view = True

    if prior_from is None:
        prior_from = jnp.ones((T,), bool)

    def step(carry, frame):
        q_prev, ok_prev = carry
        c, v, qb, q0, off, sh, pf = frame
        q_h = jnp.where(ok_prev, q_prev, qb)
        anchors = PatchAnchors(setup.anchors.link, off, sh) if per_view else setup.anchors
        sol = solve_ik(chain, setup.cams, anchors, c, v, qb, q_h, cov, q0,
                       rtol=setup.rtol, atol=setup.atol, robust=setup.robust)  # fmt: skip
        ok = jnp.sum(v) >= MIN_VALID_PATCHES
        q = jnp.where(ok, sol.q, q_prev)
        return (q, ok & pf), (q, ok)

    init = (q_b[0], jnp.array(False))
    q0s = q_b if q_start is None else q_start
    _, (q, ok) = jax.lax.scan(step, init, (centroids, visible, q_b, q0s, *view, prior_from))
    return q, ok


def _window_loss(cov, setup, c, v, qb, qg, sc, jitter_weight, q0=None, view=None,
                 pf=None) -> tuple[Array, Array]:
    q, ok = ik_track(cov, setup, c, v, qb, q0, view, pf)
    err, dx = jax.vmap(lambda a, b: _joint_error(setup, a, b))(q, qg)
    w = (ok & sc).astype(err.dtype)
    total = jnp.sum(w * err)
    n = jnp.sum(w)
    if jitter_weight:
        jit = jnp.sqrt(jnp.sum(jnp.square(dx[1:] - dx[:-1]), axis=-1) + NORM_EPS).mean(-1)
        pair = w[1:] * w[:-1]
        total = total + jitter_weight * jnp.sum(pair * jit) * n / jnp.maximum(jnp.sum(pair), 1)
    return total, n


def ik_loss_parts(
    theta: IKTheta, setup: IKSetup, obs: IKObservations, jitter_weight: float = 0.0
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """``(sum of the per-frame errors, number of valid frames)`` over ``obs``'s windows:
    :func:`ik_loss` is their ratio. Both add over disjoint sets of windows (clips), and the
    count does not depend on ``theta`` (validity is the measured centroids'), so the loss and
    its gradient over many clips are ``sum_c total_c / sum_c n_c`` and ``sum_c grad total_c /
    sum_c n_c`` -- what :mod:`jaxmocap.experiment.tune_dask` computes per clip on workers."""
    cov = ik_covariances(theta, setup)
    scored = jnp.ones(obs.q_b.shape[:2], bool) if obs.scored is None else obs.scored
    q0 = obs.q_b if obs.q_start is None else obs.q_start
    # with the tracker's own starts (q_start), its reported validity also gates the prior
    pf = jnp.ones_like(scored) if obs.q_start is None else scored
    if obs.view_offset is None:
        total, n = jax.vmap(
            lambda c, v, qb, qg, sc, q0, pf: _window_loss(cov, setup, c, v, qb, qg, sc,
                                                          jitter_weight, q0, None, pf)
        )(obs.centroids, obs.visible, obs.q_b, obs.q_gt, scored, q0, pf)
    else:
        total, n = jax.vmap(
            lambda c, v, qb, qg, sc, q0, off, sh, pf: _window_loss(
                cov, setup, c, v, qb, qg, sc, jitter_weight, q0, (off, sh), pf)
        )(obs.centroids, obs.visible, obs.q_b, obs.q_gt, scored, q0, obs.view_offset,
          obs.view_shift, pf)
    return jnp.sum(total), jnp.sum(n)


def ik_loss(
    theta: IKTheta, setup: IKSetup, obs: IKObservations, jitter_weight: float = 0.0
) -> Float[Array, ""]:
    """Mean per-joint position error (m) of the IK track over all windows' valid (and scored)
    frames
    (+ ``jitter_weight`` x mean error of the joints' frame-to-frame displacement), as a
    function of the unconstrained covariances. Windows are vmapped."""
    total, n = ik_loss_parts(theta, setup, obs, jitter_weight)
    return total / jnp.maximum(n, 1.0)


def ik_closed_form(setup: IKSetup, obs: IKObservations) -> IKCovariances:
    """The paper's estimate (:func:`jaxmocap.ik.estimate_covariances`, shared Sigma_c) pooled
    over windows: per-window estimates averaged with weights = visible centroids (Sigma_c),
    frames (Sigma_b) and frame pairs (Sigma_p) — every window has the same T, so this is the
    pooled second moment (up to the estimator's tiny ridge), and Sigma_p never spans a gap
    between two windows."""
    est = jax.vmap(
        lambda c, v, qb, qg: estimate_covariances(
            setup.cams, setup.body.chain, setup.anchors, qg, c, v, qb
        )  # fmt: skip
    )(obs.centroids, obs.visible, obs.q_b, obs.q_gt)
    wc = obs.visible.sum(axis=(1, 2, 3)).astype(est.centroid.dtype)
    wc = wc / jnp.maximum(wc.sum(), 1.0)
    return IKCovariances(
        centroid=jnp.einsum("w,wij->ij", wc, est.centroid),
        blend=est.blend.mean(0),
        prior=est.prior.mean(0),
    )


# ----------------------------------------------------------------------------- 2. colour model


class ColorTheta(eqx.Module):
    """Unconstrained colour parameters (:data:`COLOR_PARAMETERS`): log-Cholesky (k, 6) of the
    Sigma_k, log T."""

    cov: Float[Array, "k 6"]
    threshold: Float[Array, ""]


def color_theta(model: ColorModel, threshold: float | ArrayLike) -> ColorTheta:
    t = jnp.asarray(threshold, model.cov.dtype)
    return ColorTheta(
        cov=BATCH_LOG_CHOLESKY.to_unconstrained(model.cov), threshold=LOG.to_unconstrained(t)
    )


def color_model(theta: ColorTheta, base: ColorModel) -> tuple[ColorModel, Float[Array, ""]]:
    """(the colour model with tuned covariances, threshold T)."""
    v = _constrain(theta, COLOR_PARAMETERS)
    return ColorModel(base.mean, v["cov"], base.names), v["threshold"]


class ColorData(eqx.Module):
    """Labelled pixels: ``pixels`` (n_images, n, 3) RGB 0..255, ``labels`` (n_images, n) the
    ground-truth colour ids (0 background), ``W`` (n_images, 3, 3) each image's white balance."""

    pixels: Float[Array, "n_images n 3"]
    labels: Int[Array, "n_images n"]
    W: Float[Array, "n_images 3 3"]


def color_data(
    images: ArrayLike, colour_ids: ArrayLike, W: ArrayLike, n_pixels: int, seed: int = 0,
    dtype=None,
) -> ColorData:  # fmt: skip
    """A fixed random subset of ``n_pixels`` pixels per image (half of them from the
    foreground, id > 0, where an image has enough), labels from its colour-id map."""
    images, ids, W = np.asarray(images), np.asarray(colour_ids), np.asarray(W)
    if images.ndim != 4 or ids.shape != images.shape[:3] or W.shape != (images.shape[0], 3, 3):
        raise TuneError(
            f"color_data: expected images (N, H, W, 3), colour_ids (N, H, W) and W (N, 3, 3); "
            f"got {images.shape}, {ids.shape}, {W.shape}"
        )
    rng = np.random.default_rng(seed)
    pix, lab = [], []
    for im, idm in zip(images, ids, strict=True):
        flat, fl = im.reshape(-1, 3), idm.reshape(-1)
        fg = np.flatnonzero(fl > 0)
        n_fg = min(fg.size, n_pixels // 2)
        pick = np.concatenate(
            [rng.choice(fg, n_fg, replace=False),
             rng.choice(fl.size, n_pixels - n_fg, replace=False)]
        )  # fmt: skip
        pix.append(flat[pick]), lab.append(fl[pick])
    dt = dtype or jnp.result_type(float)
    return ColorData(jnp.asarray(np.stack(pix), dt), jnp.asarray(np.stack(lab), jnp.int32),
                     jnp.asarray(W, dt))  # fmt: skip


def color_loss(
    theta: ColorTheta,
    base: ColorModel,
    data: ColorData,
    temperature: float | Float[Array, ""] = SOFT_TEMPERATURE,
) -> Float[Array, ""]:
    """Mean cross-entropy ``-log p(r = label)`` of the soft classifier over the pixels."""
    model, T = color_model(theta, base)

    def per_image(px, lab, W):
        p = soft_classify(model, W, px[:, None, :], T, temperature)[:, 0, :]
        return -jnp.log(jnp.take_along_axis(p, lab[:, None], axis=1)[:, 0] + 1e-30)

    return jnp.mean(jax.vmap(per_image)(data.pixels, data.labels, data.W))


# ----------------------------------------------------------------------------- 3. stereo PF cues

PF_WINDOW = 10  # frames a gradient crosses back in the stereo filter's loss (module docstring)


class PFTheta(eqx.Module):
    """Unconstrained cue widths (:data:`PF_PARAMETERS`): log sigma_g, log sigma_d (m)."""

    sigma_g: Float[Array, ""]
    sigma_d: Float[Array, ""]


def pf_theta(sigma_g: float, sigma_d: float, dtype=None) -> PFTheta:
    dt = dtype or jnp.result_type(float)
    return PFTheta(jnp.log(jnp.asarray(sigma_g, dt)), jnp.log(jnp.asarray(sigma_d, dt)))


def pf_with_widths(params, theta: PFTheta):
    """The stereo filter's parameters (:class:`jaxmocap.trackers.stereo_pf.StereoPFParams`)
    with the cue widths of ``theta``: every :class:`StereoLikelihood` in them -- the filter's
    ``loglik``, ``params.likelihood`` and the guided proposal's bound residuals (which read
    sigma_d where the distance cue is anisotropic) -- gets the same sigma_g, sigma_d, as
    :func:`jaxmocap.trackers.stereo_pf.make_params` would build them."""
    v = _constrain(theta, PF_PARAMETERS)

    def widths(x):
        if not isinstance(x, StereoLikelihood):
            return x
        dt = x.sigma_g.dtype
        return eqx.tree_at(lambda m: (m.sigma_g, m.sigma_d), x,
                           (v["sigma_g"].astype(dt), v["sigma_d"].astype(dt)))

    return jax.tree.map(widths, params, is_leaf=lambda x: isinstance(x, StereoLikelihood))


class PFSequence(eqx.Module):
    """One sequence's held-fixed inputs of :func:`pf_loss`: what the filter's likelihood read
    per frame (``obs``, leading time axis T), the frame the tracker initialised on
    (``first``: ``obs`` at the start frame) and its anchor (``start``: a
    :class:`jaxmocap.trackers.stereo_pf.start.Start`, or None for the head prior), the random
    key the tracker ran with (or a batch of keys (K,): :func:`pf_loss` is then the mean of the
    K runs), the ground-truth keypoints ``gt`` (T, J, 3) m of the scored
    joints and their indices ``joints`` (J,) in the filter's body; ``scored`` (T,) the frames
    with a ground truth."""

    obs: Observation
    first: Observation
    start: object
    key: Array
    gt: Float[Array, "t j 3"]
    joints: Int[Array, " j"]
    scored: Bool[Array, " t"]


def _cut(tree, cut: Bool[Array, ""]):
    """``tree`` with no gradient flowing back through its float leaves where ``cut``."""
    return jax.tree.map(
        lambda a: jnp.where(cut, jax.lax.stop_gradient(a), a) if eqx.is_inexact_array(a) else a,
        tree)  # fmt: skip


def pf_frame_errors(theta: PFTheta, params, seq: PFSequence,
                    window: int | Int[Array, ""] = PF_WINDOW) -> Float[Array, " t"]:
    """Per frame the mean per-joint error (m) of the stereo filter's estimate, run as the
    tracker runs it (:func:`jaxmocap.trackers.stereo_pf.init` on ``seq.first`` with
    ``seq.key``, then :func:`~jaxmocap.trackers.stereo_pf.filter.filter_step` over every frame
    from 0) with the cue widths of ``theta`` (module docstring). Gradients: through each frame's
    weights and, by the filter's stop-gradient resampling, its ancestors'; through the
    adaptive noise and the proposals' moves; back over at most ``window`` frames (the state's
    gradient is cut at frames 0, window, 2 window, ...: truncated backpropagation through
    time) and not into the annealed initialisation. Each frame is rematerialised in the
    backward pass (``jax.checkpoint``), so memory holds one frame's intermediates."""
    from jaxmocap.trackers.stereo_pf.filter import filter_step, init

    if isinstance(window, int) and window < 1:  # traced: the caller's (tune_dataset: 10)
        raise TuneError(f"pf_frame_errors: window must be >= 1, got {window}")
    window = jnp.asarray(window)
    p = pf_with_widths(params, theta)
    state, _ = init(p, seq.key, seq.first, seq.start)
    state = _cut(state, jnp.asarray(True))
    model = params.likelihood.model

    @jax.checkpoint
    def frame(state, inputs):
        t, z, g, ok = inputs
        state = _cut(state, t % window == 0)
        state, est = filter_step(p, state, z)
        x = keypoints(model, est.q)[seq.joints]
        g = jnp.where(ok, g, x)  # a frame without ground truth: 0 error, then masked
        e = jnp.mean(jnp.sqrt(jnp.sum(jnp.square(x - g.astype(x.dtype)), -1) + NORM_EPS))
        return state, jnp.where(ok, e, jnp.nan)

    t = jnp.arange(seq.scored.shape[0])
    return jax.lax.scan(frame, state, (t, seq.obs, seq.gt, seq.scored))[1]


def pf_loss(theta: PFTheta, params, seq: PFSequence,
            window: int | Int[Array, ""] = PF_WINDOW) -> Float[Array, ""]:
    """Mean per-joint error (m) of the stereo filter over every scored frame of ``seq``
    (:func:`pf_frame_errors`): the experiment's all-frames error of the run with these
    widths. With a batch of keys in ``seq.key`` the mean over the K runs (vmapped): the
    filter's error is a random variable of its key, and the mean of K runs estimates its
    expectation -- the quantity a tuning should rank widths by -- with 1/K of one run's
    variance (the gradient likewise)."""
    if seq.key.ndim == 1:
        one = lambda k: pf_loss(theta, params, eqx.tree_at(lambda q: q.key, seq, k), window)
        return jnp.mean(jax.vmap(one)(seq.key))
    e = pf_frame_errors(theta, params, seq, window)
    ok = seq.scored
    return jnp.sum(jnp.where(ok, e, 0.0)) / jnp.maximum(jnp.sum(ok), 1)


# ----------------------------------------------------------------------------- optimiser

OPTIMISERS = ("adam", "lbfgs")
ADAM_LEARNING_RATE = 0.05  # Adam's step in the log-Cholesky / log parameters (tuning.md's runs)


def make_optimiser(name: str, learning_rate: float | None = None) -> optax.GradientTransformation:
    """An optax optimiser by name: ``"adam"`` (Kingma & Ba 2015, optax's defaults, the
    ``learning_rate``) or ``"lbfgs"`` (``optax.lbfgs`` with its default zoom linesearch:
    strong Wolfe conditions, at most 20 evaluations, each search starting from a unit step --
    ``initial_guess_strategy="one"``; starting from the previous step instead stalled 0.8%
    above the minimum of a 3 x 3 covariance fit in 40 steps, where the default reaches it to
    1e-15; ``learning_rate`` None: the linesearch picks the step)."""
    if name == "adam":
        if learning_rate is None or not learning_rate > 0:
            raise TuneError(f"fit: Adam needs a learning rate > 0, got {learning_rate}")
        return optax.adam(learning_rate)
    if name == "lbfgs":
        return optax.lbfgs(learning_rate)
    raise TuneError(f"fit: optimiser {name!r} is not one of {', '.join(OPTIMISERS)}")


class FitState(NamedTuple):
    """Where :func:`fit` is: ``step`` the index of the next iterate to evaluate, ``theta`` that
    iterate, the optax state, the best iterate so far and its loss, and ``losses`` of the
    iterates 0..step-1. Saved by :func:`save_fit_state`, a run continues from it and ends
    where an uninterrupted run of the same total steps ends (the loop is deterministic)."""

    step: int
    theta: object
    opt_state: object
    best: object
    best_loss: float
    losses: tuple[float, ...]


def fit(
    loss: Callable,
    theta,
    steps: int,
    learning_rate: float | None = ADAM_LEARNING_RATE,
    callback: Callable | None = None,
    value_and_grad: bool = False,
    optimiser: str | optax.GradientTransformation = "adam",
    start: FitState | None = None,
    checkpoint: Callable[[FitState], None] | None = None,
):
    """Minimise ``loss(theta)`` by ``steps`` steps of an optax ``optimiser`` (a name of
    :data:`OPTIMISERS` or a ``GradientTransformation``). ``loss`` returns the scalar (it is
    differentiated and jitted here), or with ``value_and_grad=True`` already ``(value,
    gradient)`` (e.g. a jitted ``jax.value_and_grad`` shared with other calls, or gradients
    summed over Dask workers); ``"lbfgs"`` needs the scalar (its linesearch evaluates the loss
    along the search direction inside the jitted update). Returns (theta with the lowest loss
    seen, losses (steps + 1,); the last is the final iterate's). ``callback(i, loss, theta)``
    is called after each evaluation; ``checkpoint(state)`` after each update with the
    :class:`FitState` to resume from (``start``)."""
    if steps < 0:
        raise TuneError(f"fit: steps must be >= 0, got {steps}")
    is_lbfgs = optimiser == "lbfgs"
    opt = optimiser if not isinstance(optimiser, str) else make_optimiser(
        optimiser, None if is_lbfgs else learning_rate)
    extra = is_lbfgs  # the linesearch: value, grad and value_fn to the update
    if extra and value_and_grad:
        raise TuneError("fit: an optimiser with a linesearch (L-BFGS) needs the scalar loss, "
                        "not value_and_grad=True")
    if extra:
        scalar = loss
        vg = eqx.filter_jit(optax.value_and_grad_from_state(scalar))

        @eqx.filter_jit
        def update(g, s, th, value):
            u, s = opt.update(g, s, th, value=value, grad=g, value_fn=scalar)
            return optax.apply_updates(th, u), s
    else:
        vg = loss if value_and_grad else eqx.filter_jit(jax.value_and_grad(loss))

        @eqx.filter_jit
        def update(g, s, th, value):
            u, s = opt.update(g, s, th)
            return optax.apply_updates(th, u), s

    if start is None:
        start = FitState(0, theta, opt.init(theta), theta, np.inf, ())
    elif start.step > steps + 1:
        raise TuneError(f"fit: the checkpoint is at step {start.step}, past steps={steps}")
    i, theta, state = start.step, start.theta, start.opt_state
    best, best_loss, losses = start.best, start.best_loss, list(start.losses)
    while i <= steps:
        value, grad = vg(theta, state=state) if extra else vg(theta)
        value = float(value)
        losses.append(value)
        if callback is not None:
            callback(i, value, theta)
        if value < best_loss:
            best, best_loss = theta, value
        if i < steps:
            theta, state = update(grad, state, theta, jnp.asarray(value))
        i += 1
        if checkpoint is not None and i <= steps:
            checkpoint(FitState(i, theta, state, best, best_loss, tuple(losses)))
    return best, np.asarray(losses)


def save_fit_state(path, state: FitState, meta: dict | None = None) -> None:
    """Write a :class:`FitState` to ``path`` (an ``.npz``: the leaves of theta, the optax
    state and the best iterate; ``meta`` as JSON), atomically (temporary file, renamed)."""
    import json
    import os

    arrays = {"step": np.int64(state.step), "best_loss": np.float64(state.best_loss),
              "losses": np.asarray(state.losses, np.float64),
              "meta": np.asarray(json.dumps(meta or {}))}  # fmt: skip
    for tag, tree in (("theta", state.theta), ("opt", state.opt_state), ("best", state.best)):
        for k, leaf in enumerate(jax.tree.leaves(tree)):
            arrays[f"leaf_{tag}_{k}"] = np.asarray(leaf)
    tmp = f"{path}.tmp.npz"
    np.savez(tmp, **arrays)
    os.replace(tmp, path)


def load_fit_state(path, theta, opt: optax.GradientTransformation) -> tuple[FitState, dict]:
    """(the :class:`FitState` of :func:`save_fit_state`, its meta); ``theta`` and the optax
    optimiser ``opt`` give the trees' structure (a fresh ``init``)."""
    import json

    with np.load(path) as z:
        f = {k: z[k] for k in z.files}

    def tree(tag, like):
        leaves, treedef = jax.tree.flatten(like)
        n = sum(1 for k in f if k.startswith(f"leaf_{tag}_"))
        if n != len(leaves):
            raise TuneError(f"{path}: field {tag!r} has {n} arrays, this run's has "
                            f"{len(leaves)} (another optimiser or parameters)")
        return jax.tree.unflatten(treedef, [
            jnp.asarray(f[f"leaf_{tag}_{k}"], jnp.asarray(leaf).dtype)
            for k, leaf in enumerate(leaves)])

    opt_like = opt.init(theta)
    state = FitState(int(f["step"]), tree("theta", theta), tree("opt", opt_like),
                     tree("best", theta), float(f["best_loss"]),
                     tuple(float(x) for x in f["losses"]))  # fmt: skip
    return state, json.loads(str(f["meta"]))
