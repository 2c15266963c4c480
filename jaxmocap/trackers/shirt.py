"""The colour-shirt tracker of Wang et al. 2011 (§4–5): ``init`` and the per-frame ``step``.

One frame, for 1..n calibrated cameras (all inside one jitted function):

1. **Locate and crop** (§4): histogram search on each full frame (optionally restricted to a
   background-subtraction mask) gives ``(x', y', s')``; the square of side
   ``CROP_FACTOR s'`` around ``(x', y')`` is resampled (bilinear) to ``n x n`` working pixels,
   so every later shape is static whatever the shirt's size.
2. **Classify** (§5.2 step 1): white balance ``W`` and Gaussian classification (``T = 3``);
   when fewer than 40% of the foreground pixels are classified, every stored reference
   illumination is tried and the best kept.
3. **Database pose** (step 2): the classified crop, normalised to a tiny 40 x 40 map, queries
   the pose database (10-NN, blended pose ``q_b`` with joint angles and a root orientation
   relative to the canonical camera).
4. **Global placement** (step 2): ``q_b``'s tiny id map is rendered in the canonical camera;
   its patch centroids, moved into each camera's query window, are 2D constraints for a
   6-DOF IK (:func:`jaxmocap.ik.solve_global`) started from a closed-form guess
   (triangulation + Kabsch with 2+ cameras; otherwise the root read off the query window by
   :func:`jaxmocap.pose_in_camera` at the depth implied by the window's size).
5. **Pose-assisted classification** (step 3): ``r^b`` rendered in each crop, one exact EDT per
   patch, ``argmin_p ||W I - mu_k(p)||_Sigma + C d_p`` with ``C = 6 / s'``, ``T = 5``.
6. **IK** (step 4): patch centroids ``c^{ki}`` in every camera, then
   ``q* = argmin sum ||c^{*i}(q) - c^{ki}||^2_Sc + ||q - q_b||^2_Sb + ||q - q_h||^2_Sp``,
   with ``c^{*i}`` the centroids of the model's render (per-view anchors,
   :func:`jaxmocap.ik.view_anchors`) and a Cauchy-robust centroid term (``robust``).
   Steps 5–6 run ``ik_passes`` times (default 2), the model re-rendered at the last pose;
   the first round from the blend and from the previous pose (``temporal_start``), the
   later ones from the result whose render agrees best with the step-1 classification.
7. **White balance** (step 5): ``q*`` rendered in each crop, ``W*`` refitted on its colour
   ids (eroded by one pixel so that silhouettes off by a pixel do not mix colours), and
   ``W*`` joins the reference illuminations when ``min ||W* - W||_F > 0.5``.

Ablations (static switches of :class:`ShirtParams`): ``pose_prior=False`` skips step 5's
prior — centroids come from the step-1 classification (``T = 3``), each pixel given to the
nearer of the two patches of its colour in ``r^b`` (that tie-break only, no cost);
``adaptive_white_balance=False`` keeps ``W = W0`` and no references (the WP09-like baseline
of Wang Fig. 9–10 is both switches off).

**Loss and recovery.** A frame is *valid* when the shirt was found in some camera and at
least ``MIN_VALID_PATCHES`` patch centroids were measured, and (when step 1 classified at least
``GATE_MIN_FRACTION`` of a crop) the render of the result agrees with the step-1
classification on ``min_agreement`` of its pixels; otherwise ``q*`` holds the previous pose
and ``W`` is not updated. After an invalid frame the temporal prior is dropped
(``q_h := q_b``), so the next valid frame starts afresh from the database; on such a
*reacquisition* frame (and the first frame) the second start is the blend measured without
the pose prior and extra rounds run; on it and a few frames after it the temporal prior is
widened by Sigma_b and a third start, the last valid pose measured without the pose prior,
joins the other two (``make_params``: ``reacquire_*``, ``held_start``; not in the paper).

**Live vs scan.** ``step`` is pure and jit-compiled once per (camera count, image size,
settings); ``run`` loops over frames in Python (live video, optionally with OpenCV's MOG2
masks computed on the host per frame), ``run_scan`` runs a whole sequence under
``jax.lax.scan`` (masks, if any, precomputed).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from jaxmocap.body import BodyModel
from jaxmocap.camera import Camera, camera_center, pixel_rays, to_camera
from jaxmocap.color import (
    ColorModel,
    ReferenceIlluminations,
    classify_views_with_references,
    histogram_search,
    init_references,
    maybe_add_reference,
    white_balance_from_ids,
)
from jaxmocap.color.classify import THRESHOLD
from jaxmocap.color.illumination import MIN_CLASSIFIED_FRACTION, ReferenceClassification
from jaxmocap.color.model import shading_problem
from jaxmocap.color.pose_assisted import (
    POSE_THRESHOLD,
    PRIOR_SCALE,
    PatchCentroids,
    patch_centroids,
    patch_distance_maps,
    pose_assisted_classify,
)
from jaxmocap.garment import Garment
from jaxmocap.ik import (
    IKCovariances,
    PatchAnchors,
    initial_root,
    solve_global,
    solve_ik,
)
from jaxmocap.ik import view_anchors as _view_anchors
from jaxmocap.posedb._sample import canonical_camera, pose_in_camera
from jaxmocap.posedb._search import PoseDB, estimate_pose
from jaxmocap.render import (
    TINY_SIZE,
    Hits,
    render_rays,
    render_uv,
    resample_ids,
    tiny_hits,
    window_from_mask,
)

# IK covariances trained the paper's way (§5.2 step 4: the covariance of each term over
# ground-truth sequences) on the TRAIN clips dance_a + walk + kick pooled, default body and
# garment, 320x240 webcams (``benchmarks/experiments/wang_accuracy.py full`` writes it; numbers
# in docs/results/shirt.md). The held-out clips were not used. Other bodies: by role.
from jaxmocap.trackers.shirt_covariances import TRAINED_COV_FILE as TRAINED_COV_FILE
from jaxmocap.trackers.shirt_covariances import covariances_for_body as covariances_for_body
from jaxmocap.trackers.shirt_covariances import trained_covariances as trained_covariances
from jaxmocap.trackers.shirt_image import (
    _crop_to_image,
    _erode,
    crop_uv,
    crop_window,
    sample_bilinear,
    sample_nearest,
)

# Not in the paper: crop side relative to the histogram search's scale s' (the shirt's
# extent is about 2 s' with the arms out) and the working size of the resampled crop.
CROP_FACTOR = 2.6
WORK_SIZE = 128
MIN_VALID_PATCHES = 4  # measured patch centroids (all cameras) for a frame to count
# Ablation without pose prior: the per-pixel cost of distance that only breaks colour ties
# between the two patches of one colour (standard deviations per working pixel).
TIE_BREAK_WEIGHT = 1e-4
# Not in the paper: rounds of (render, pose-assisted classification, IK) per frame, each with
# the model re-rendered at the previous round's pose (the paper renders r^b once, at q_b).
IK_PASSES = 2
# Not in the paper: Cauchy scale (standard deviations of Sigma_c) of the IK's centroid terms
# (jaxmocap.ik.solve_ik(robust=...)); None: the paper's plain least squares.
ROBUST_SCALE = 3.0
# Not in the paper: a frame is valid only if the render of its first-round pose agrees with the
# step-1 colour classification on at least this share of the rendered shirt pixels (agreeing
# minus disagreeing): when the subject has left the view the search finds some clutter, and
# tracking it would corrupt W and the temporal prior.
MIN_AGREEMENT = 0.25
# Not in the paper: after a loss (first frame, or after an invalid frame) the second start's
# first round uses the step-1 classification (no pose prior) and this many extra rounds run.
REACQUIRE_PASSES = 2
# Not in the paper: frames after a loss during which the temporal prior is widened by Sigma_b.
REACQUIRE_FRAMES = 3
MAX_ROOT_OFFSET = 1.0  # metres: an invalid frame's estimate this far from the blend is not shown
GATE_MIN_FRACTION = 0.2  # the gate applies only if step 1 classified this share in some camera
REFERENCE_PIXELS = 30  # colour-id pixels of r* a colour needs to enter the W* refit


def scales_for_width(width: int, stride: int = 6) -> tuple[int, ...]:
    """The histogram search's six scales (Wang §4) for an image ``width`` pixels wide: the
    640-pixel defaults of :data:`jaxmocap.color.DEFAULT_SCALES` scaled, each a multiple of
    ``2 stride`` (at least one per size)."""
    from jaxmocap.color import DEFAULT_SCALES

    step = 2 * stride
    out = sorted({max(step, int(round(s * width / 640 / step)) * step) for s in DEFAULT_SCALES})
    return tuple(out)


class ShirtParams(eqx.Module):
    """Everything the tracker needs that does not change over a sequence.

    ``cams`` is a stacked :class:`~jaxmocap.camera.Camera` (leading axis = cameras); ``db`` a
    :class:`jaxmocap.PoseDB`. Static switches select the ablations (module docstring).
    """

    color: ColorModel
    body: BodyModel
    garment: Garment
    cams: Camera
    anchors: PatchAnchors
    cov: IKCovariances
    db: PoseDB
    canon: Camera  # the database's canonical camera
    scene_colors: ColorModel | None = None  # Gaussians of the room (jaxmocap.color.scene_colors)
    pose_prior: bool = eqx.field(static=True, default=True)
    adaptive_white_balance: bool = eqx.field(static=True, default=True)
    work_size: int = eqx.field(static=True, default=WORK_SIZE)
    scales: tuple[int, ...] = eqx.field(static=True, default=())
    crop_factor: float = eqx.field(static=True, default=CROP_FACTOR)
    view_anchors: bool = eqx.field(static=True, default=True)
    ik_passes: int = eqx.field(static=True, default=IK_PASSES)
    robust: float | None = eqx.field(static=True, default=ROBUST_SCALE)
    temporal_start: bool = eqx.field(static=True, default=True)
    min_agreement: float = eqx.field(static=True, default=MIN_AGREEMENT)
    reacquire_start: bool = eqx.field(static=True, default=True)
    reacquire_passes: int = eqx.field(static=True, default=REACQUIRE_PASSES)
    reacquire_frames: int = eqx.field(static=True, default=REACQUIRE_FRAMES)
    held_start: bool = eqx.field(static=True, default=True)
    # ``static_kinds``: the renders inside the step use the body's geom kinds as constants
    # (``geom_kinds``), so that the ray caster tests each geom against its own primitive only;
    # with traced kinds it evaluates every primitive kind for every geom and selects (2x slower
    # per crop pair: 19.4 vs 9.8 ms). The two paths round differently on a few silhouette
    # pixels; paired over 8 held-out sequences with the 80,000-pose database the mean error is
    # 4.85 cm static vs 4.90 traced, within the rounding noise of the tracker
    # (docs/results/realtime_profile.md, session 10). False: the traced-kinds path.
    static_kinds: bool = eqx.field(static=True, default=True)
    geom_kinds: tuple[int, ...] = eqx.field(static=True, default=())
    # ``shading``: (lo, hi) brightness range of the shading-invariant colour distance
    # (jaxmocap.color.classify ``gain``); None: the paper's Gaussian distance.
    shading: tuple[float, float] | None = eqx.field(static=True, default=None)
    # ``hold_invalid``: an invalid frame's output ``q`` is the last valid pose (default); off:
    # this frame's own estimate where MIN_VALID_PATCHES centroids were measured and its root is
    # near the placed blend's (near_placement; still flagged invalid; the state keeps the last
    # valid pose).
    hold_invalid: bool = eqx.field(static=True, default=True)
    # the validity rule's counts (frame_validity): measured centroids, and the step-1 share
    # from which on the agreement gate applies (0: always)
    min_patches: int = eqx.field(static=True, default=MIN_VALID_PATCHES)
    gate_min_fraction: float = eqx.field(static=True, default=GATE_MIN_FRACTION)
    # the reported flag's own rule (reported_validity; the state still follows
    # frame_validity): measured centroids and the final pose's image checks (frame_signals)
    # in every camera that found the shirt; all None: the tracker's own flag is reported
    report_patches: int | None = eqx.field(static=True, default=None)
    max_residual: float | None = eqx.field(static=True, default=None)
    min_recall: float | None = eqx.field(static=True, default=None)

    @property
    def n_cams(self) -> int:
        return self.cams.K.shape[0]

    @property
    def render_body(self) -> BodyModel:
        """``body`` with its geom kinds as constants (``geom_kinds``) for the ray caster's
        per-kind tests inside the jitted step (the same body; traced kinds otherwise)."""
        if not self.static_kinds or len(self.geom_kinds) != self.body.geometry.kind.shape[0]:
            return self.body
        kinds = np.asarray(self.geom_kinds, self.body.geometry.kind.dtype)
        return eqx.tree_at(lambda b: b.geometry.kind, self.body, kinds)


class ShirtState(eqx.Module):
    """What carries over between frames: per-camera white balance and reference
    illuminations, the previous pose and whether the previous frame was valid."""

    W: Float[Array, "n_cams 3 3"]
    refs: ReferenceIlluminations  # batched over cameras
    q: Float[Array, " n_dof"]
    valid: Bool[Array, ""]
    tracked: Int[Array, ""]  # consecutive valid frames up to the previous one (0: lost)


class FrameSignals(NamedTuple):
    """How well the final pose ``q*`` explains the frame (:func:`frame_signals`; the inputs
    of the reported validity rule, :func:`reported_validity`), per camera where marked.

    ``residual``: mean distance of the measured patch centroids from the centroids of ``q*``'s
    render (the IK's reprojection residual) over the crop side (a crop is ``CROP_FACTOR``
    shirt sizes), 0 without centroids; ``coverage``: share of the step-1 classified crop pixels
    that lie on ``q*``'s render of the same colour (shirt pixels the pose does not explain
    lower it); ``recall``: share of ``q*``'s rendered shirt pixels that step 1 classified as
    the rendered colour; ``blend_distance``: RMS joint-angle difference (rad) of ``q*`` and
    the placed database blend; ``db_spread``: RMS joint-angle difference (rad) of the two
    first cameras' database poses (0 with one camera); ``root_jump``: root displacement (m)
    from the previous frame's pose (0 after a loss)."""

    residual: Float[Array, " n_cams"]
    coverage: Float[Array, " n_cams"]
    recall: Float[Array, " n_cams"]
    blend_distance: Float[Array, ""]
    db_spread: Float[Array, ""]
    root_jump: Float[Array, ""]


class ShirtOutput(eqx.Module):
    """Per-frame results. ``q`` the final pose ``q*``, ``q_blend`` the globally placed blended
    database pose; per camera: crop ``window`` (x0, y0, s, s) image pixels, the step-1
    classified ``fraction``, whether a reference illumination was used / added, the measured
    ``centroids`` (pixels) and their ``visible`` flags."""

    q: Float[Array, " n_dof"]
    q_blend: Float[Array, " n_dof"]
    valid: Bool[Array, ""]
    window: Float[Array, "n_cams 4"]
    fraction: Float[Array, " n_cams"]
    used_reference: Bool[Array, " n_cams"]
    added_reference: Bool[Array, " n_cams"]
    centroids: Float[Array, "n_cams n_patches 2"]
    visible: Bool[Array, "n_cams n_patches"]
    agreement: Float[Array, ""]  # render vs step-1 classification (the validity gate)
    signals: FrameSignals  # the final pose checked against the images (frame_signals)


def make_params(
    color: ColorModel,
    body: BodyModel,
    garment: Garment,
    cams: Camera,
    anchors: PatchAnchors,
    cov: IKCovariances,
    db: PoseDB,
    *,
    pose_prior: bool = True,
    adaptive_white_balance: bool = True,
    work_size: int = WORK_SIZE,
    scales: Sequence[int] | None = None,
    crop_factor: float = CROP_FACTOR,
    view_anchors: bool = True,
    ik_passes: int = IK_PASSES,
    robust: float | None = ROBUST_SCALE,
    temporal_start: bool = True,
    min_agreement: float = MIN_AGREEMENT,
    reacquire_start: bool = True,
    reacquire_passes: int = REACQUIRE_PASSES,
    reacquire_frames: int = REACQUIRE_FRAMES,
    held_start: bool = True,
    static_kinds: bool = True,
    shading: Sequence[float] | None = None,
    scene_colors: ColorModel | None = None,
    hold_invalid: bool = True,
    min_patches: int = MIN_VALID_PATCHES,
    gate_min_fraction: float = GATE_MIN_FRACTION,
    report_patches: int | None = None,
    max_residual: float | None = None,
    min_recall: float | None = None,
) -> ShirtParams:
    """Validated :class:`ShirtParams`; ``scales`` default :func:`scales_for_width`.

    ``view_anchors`` (default on) predicts each patch's centroid from the model's render in
    the camera's crop (:func:`jaxmocap.ik.view_anchors`) instead of the whole patch's fixed 3D
    centroid; ``ik_passes`` rounds of pose-assisted classification + IK per frame, each with
    the model re-rendered at the last round's pose; ``robust`` the Cauchy scale of the IK's
    centroid terms (None: plain least squares, as the paper); ``temporal_start`` runs the
    rounds from two starts, the placed blend ``q_b`` and the previous frame's pose, under
    ``jax.vmap``, keeping the result whose render agrees best with the step-1 colour
    classification (the paper starts from ``q_b`` only; a bad database match then leaves
    the IK in a wrong basin although the previous frame was right); a frame is valid only if
    that render agrees with the step-1 classification on ``min_agreement`` of its pixels.

    After a loss (the first frame, or any frame after an invalid one) there is no previous
    pose to start from: with ``reacquire_start`` (and ``temporal_start``) the second start
    is then the placed blend measured *without* the pose prior (step-1 classification, each
    pixel given to the nearer patch of its colour), which a blend in a wrong basin cannot
    mislead; ``reacquire_passes`` extra rounds run on such frames (the loop of the extra
    rounds runs longer: no cost on tracked frames). For the ``reacquire_frames`` frames after
    a loss the temporal term's covariance is ``Sigma_p + Sigma_b``: its ``q_h`` comes from a
    cold start, whose error is of the blend's order, not the tracked steady state that
    ``Sigma_p`` was trained on. All three off (``reacquire_start=False, reacquire_passes=0,
    reacquire_frames=0``): the session-2 behaviour. ``held_start`` adds a third start on
    those frames (reacquisition and the ``reacquire_frames`` after it): the last valid pose
    measured without the pose prior (a subject re-entering fast is far from it, and a prior
    rendered there misleads the pose-assisted classification); on other frames it repeats
    the blend start.
    ``static_kinds`` (default) renders with the body's geom kinds as constants inside the step
    (each geom runs its own primitive's ray test; ``False``: every primitive evaluated and
    selected per geom, 2x slower renders, rounding differs; see :class:`ShirtParams`).

    Footage under spot lamps (not in the paper; both off by default): ``shading = (lo, hi)``
    compares every pixel to every colour at its best brightness in ``[lo, hi]`` (steps 1 and 3;
    the colour model should then be fitted with the same ``gain``,
    :func:`jaxmocap.color.fit_color_model`); ``scene_colors`` (Gaussians of the room's colours,
    :func:`jaxmocap.color.fit_scene_colors`) makes a pixel nearer one of them than every shirt
    colour background in steps 1 and 3.

    A reported validity of its own (not in the paper; off by default): with any of
    ``report_patches``, ``max_residual``, ``min_recall`` the output's ``valid`` is that
    ``report_patches`` (default ``min_patches``) centroids were measured and, in every camera
    that found the shirt, the measured centroids' mean distance from the final pose's
    rendered ones is at most ``max_residual`` crop sides and at least ``min_recall`` of its
    rendered shirt pixels carry the rendered colour in step 1 (:class:`FrameSignals`). The
    state (temporal prior, W re-fit) still follows the tracker's own rule: gating it with the
    stricter rule lost shirt_03 of the dev split (9.4 -> 22.6 cm, docs/results/shirt.md)."""
    if ik_passes < 1:
        raise ValueError(f"make_params: ik_passes must be >= 1, got {ik_passes}")
    if reacquire_frames < 0:
        raise ValueError(f"make_params: reacquire_frames must be >= 0, got {reacquire_frames}")
    if reacquire_passes < 0:
        raise ValueError(f"make_params: reacquire_passes must be >= 0, got {reacquire_passes}")
    if cams.K.ndim != 3:
        raise ValueError("make_params: cams must be stacked (jaxmocap.camera.stack_cameras)")
    if anchors.n_patches != garment.n_patches:
        raise ValueError(
            f"make_params: {anchors.n_patches} patch anchors for a garment with "
            f"{garment.n_patches} patches"
        )
    if color.n_colors != garment.n_colours:
        raise ValueError(
            f"make_params: colour model has {color.n_colors} colours, garment {garment.n_colours}"
        )
    if work_size < 16:
        raise ValueError(f"make_params: work_size must be >= 16, got {work_size}")
    sc = tuple(int(s) for s in scales) if scales is not None else scales_for_width(cams.width)
    if shading is not None:
        problem = shading_problem(shading)
        if problem:
            raise ValueError(f"make_params: shading: {problem}")
        shading = tuple(float(g) for g in shading)
    for name, v in (("max_residual", max_residual), ("min_recall", min_recall)):
        if v is not None and not 0 <= v <= 1:
            raise ValueError(f"make_params: {name} must be None or in [0, 1], got {v}")
    if report_patches is not None and report_patches < 0:
        raise ValueError(f"make_params: report_patches must be None or >= 0, got {report_patches}")
    return ShirtParams(
        color, body, garment, cams, anchors, cov, db, canonical_camera(cams.K.dtype),
        scene_colors, pose_prior, adaptive_white_balance, int(work_size), sc, float(crop_factor),
        bool(view_anchors), int(ik_passes), None if robust is None else float(robust),
        bool(temporal_start), float(min_agreement), bool(reacquire_start),
        int(reacquire_passes), int(reacquire_frames), bool(held_start), bool(static_kinds),
        tuple(int(k) for k in np.asarray(body.geometry.kind)), shading, bool(hold_invalid),
        int(min_patches), float(gate_min_fraction),
        None if report_patches is None else int(report_patches),
        None if max_residual is None else float(max_residual),
        None if min_recall is None else float(min_recall),
    )  # fmt: skip


def init(
    params: ShirtParams, W0: Float[Array, "n_cams 3 3"], q0: Float[Array, " n_dof"]
) -> ShirtState:
    """Initial state: the user-labelled white balance ``W0`` per camera (§5.1), which also
    starts each camera's reference illuminations, and a pose ``q0`` (e.g. the rest pose);
    the first frame is treated as after a loss (no temporal prior)."""
    W0 = jnp.asarray(W0)
    if W0.shape != (params.n_cams, 3, 3):
        raise ValueError(f"init: W0 must be ({params.n_cams}, 3, 3), got {W0.shape}")
    refs = jax.vmap(init_references)(W0)
    return ShirtState(
        W=W0, refs=refs, q=jnp.asarray(q0), valid=jnp.array(False), tracked=jnp.array(0, jnp.int32)
    )


# ----------------------------------------------------------------------------- the frame step
#
# ``_step`` is the paper's steps in order, each a module-level function (per camera lists;
# the bench and the profile time them separately): ``locate_and_classify`` (§4, §5.2 step 1),
# ``database_pose`` (step 2, 10-NN), ``global_placement`` (step 2, 6-DOF IK),
# ``pose_assisted_centroids`` + ``ik_round`` (steps 3 + 4, run from every start of
# ``starts_of`` and ``ik_passes - 1`` more times, all in the one loop of ``rounds``),
# ``frame_validity`` and ``white_balance_refit`` (step 5).


def _root_guess(
    params: ShirtParams, cam: Camera, q_db: Array, win_db: Array, win_q: Array
) -> Array:
    """Root (6) of the database pose placed in camera ``cam`` so that its canonical window
    ``win_db`` lands on the query window ``win_q``: the root's pixel keeps its normalised
    position in the window and its depth scales with the window side and focal length."""
    canon = params.canon
    dt = q_db.dtype
    root_c = canon.t.astype(dt)  # root at the origin: its canonical camera-frame position
    p_c = canon.K.astype(dt) @ root_c
    p_c = p_c[:2] / p_c[2]
    p_i = win_q[:2] + (p_c - win_db[:2]) * win_q[2] / win_db[2]
    depth = root_c[2] * (cam.K[0, 0] / canon.K[0, 0]) * (win_db[2] / win_q[2])
    o, d = pixel_rays(cam, p_i)
    X = o + d * depth / to_camera(cam, o + d)[2]
    q = pose_in_camera(q_db, cam, to_camera(cam, X))
    return q[:6]


def _widened(prior: Array, blend: Array, fresh: Array) -> Array:
    """``Sigma_p + Sigma_b`` where ``fresh``, else ``Sigma_p`` (each a matrix or a vector of
    variances; a matrix if either is)."""
    if prior.ndim != blend.ndim:
        prior = jnp.diag(prior) if prior.ndim == 1 else prior
        blend = jnp.diag(blend) if blend.ndim == 1 else blend
    return jnp.where(fresh, prior + blend.astype(prior.dtype), prior)


class Views(NamedTuple):
    """Steps 0–1, stacked over cameras: resampled crops, their foregrounds (or None), crop
    windows, scales ``s'``, whether the search found the shirt, step-1 classification."""

    crops: UInt8[Array, "n_cams n n 3"]
    fgs: Bool[Array, "n_cams n n"] | None
    windows: Float[Array, "n_cams 4"]
    s_found: Float[Array, " n_cams"]
    found: Bool[Array, " n_cams"]
    cls: ReferenceClassification


class DatabasePose(NamedTuple):
    """Step 2, stacked over cameras: blended database pose, query window (image px),
    ``q_db``'s tiny patch map and canonical window; ``okq`` cameras that found the shirt; the
    joint angles averaged over them."""

    q_dbs: Float[Array, "n_cams n_dof"]
    win_qs: Float[Array, "n_cams 4"]
    tiny_patch: Int[Array, "n_cams t t"]
    win_dbs: Float[Array, "n_cams 4"]
    okq: Bool[Array, " n_cams"]
    joints: Array


class RoundContext(NamedTuple):
    """What every round of steps 3–4 shares: the views, ``okq``, the placed blend ``q_g``,
    the temporal prior ``q_h``, the IK covariances, the crops' pixel grids and their rays
    (``(origins, dirs)`` stacked over cameras: every render of the frame casts the same rays,
    so the grid is undistorted once per frame, not once per render)."""

    views: Views
    okq: Array
    q_g: Array
    q_h: Array
    cov: IKCovariances
    uvs: Float[Array, "n_cams n n 2"]
    rays: tuple[Float[Array, "n_cams 3"], Float[Array, "n_cams n n 3"]]


def locate_and_classify(params: ShirtParams, state: ShirtState, frames, masks) -> Views:
    """§4 + §5.2 step 1: histogram search and crop resampling per camera (unrolled: the
    search under vmap ran 9.3 -> 10.8 ms), then the classification of every crop with its
    reference illuminations in one ``vmap`` (:func:`classify_views_with_references`)."""
    n, dt = params.work_size, state.q.dtype
    crops, fgs, windows, s_found, found = [], [], [], [], []
    for i in range(params.n_cams):
        mask_i = None if masks is None else masks[i]
        res = histogram_search(frames[i], mask_i, scales=params.scales)
        win = crop_window(res.x.astype(dt), res.y.astype(dt), res.s.astype(dt), params.crop_factor)
        uv = crop_uv(win, n)
        crops.append(sample_bilinear(frames[i], uv))
        fgs.append(None if masks is None else sample_nearest(masks[i], uv))
        windows.append(win), s_found.append(res.s.astype(dt)), found.append(res.found)
    crops = jnp.stack(crops)
    fgs = None if masks is None else jnp.stack(fgs)
    cls = classify_views_with_references(
        params.color, state.refs, state.W, crops, fgs, THRESHOLD,
        min_fraction=MIN_CLASSIFIED_FRACTION if params.adaptive_white_balance else 0.0,
        gain=params.shading, background=params.scene_colors,
    )  # fmt: skip
    return Views(crops, fgs, jnp.stack(windows), jnp.stack(s_found), jnp.stack(found), cls)


def database_pose(params: ShirtParams, views: Views, dt) -> DatabasePose:
    """§5.2 step 2: the database pose of every camera (one ``vmap``), joint angles averaged
    over the cameras that found the shirt."""
    n = params.work_size

    def one(ids, window, found):
        win_c = window_from_mask(ids > 0)
        tiny = resample_ids(ids, win_c, TINY_SIZE)
        q_db = estimate_pose(params.db, tiny)[0].astype(dt)
        hits, win_db = tiny_hits(params.body, params.garment, q_db, params.canon)
        ok = found & (jnp.sum(ids > 0) > 0)
        return q_db, _crop_to_image(win_c, window, n), hits.patch, win_db, ok

    q_dbs, win_qs, tiny_patch, win_dbs, okq = jax.vmap(one)(
        views.cls.ids, views.windows, views.found
    )
    wq = okq.astype(dt) / jnp.maximum(jnp.sum(okq), 1)
    joints = jnp.sum(wq[:, None] * q_dbs[:, 6:], axis=0)
    return DatabasePose(q_dbs, win_qs, tiny_patch, win_dbs, okq, joints)


def global_placement(params: ShirtParams, db: DatabasePose, dt) -> Array:
    """§5.2 step 2 (global): the centroids of ``r^b``'s patches in each query window are 2D
    constraints of a 6-DOF IK from a closed-form root guess; returns the placed blend ``q_g``."""
    P, cams = params.garment.n_patches, params.cams
    cons = jax.vmap(lambda t, w: patch_centroids(t, P, w, min_pixels=2, dtype=dt))(
        db.tiny_patch, db.win_qs
    )
    c_xy, c_vis = cons.xy, cons.valid & db.okq[:, None]
    best = jnp.argmax(db.okq)  # first camera that found the shirt
    guesses = jax.vmap(lambda *a: _root_guess(params, *a))(cams, db.q_dbs, db.win_dbs, db.win_qs)
    q_b = jnp.concatenate([jnp.zeros(6, dt), db.joints])
    root0, _ = initial_root(
        cams, params.body.chain, params.anchors, c_xy, c_vis, q_b, guesses[best]
    )
    glob = solve_global(
        params.body.chain, cams, params.anchors, c_xy, c_vis, q_b, root0, params.cov.centroid
    )
    return glob.q


def round_context(params: ShirtParams, state: ShirtState, views: Views, okq, q_g) -> RoundContext:
    """The shared inputs of steps 3–4; the temporal prior widened by Sigma_b for
    ``reacquire_frames`` frames after a loss (its ``q_h`` comes from a cold start)."""
    uvs = jax.vmap(lambda w: crop_uv(w, params.work_size))(views.windows)
    q_h = jnp.where(state.valid, state.q, q_g)
    cov = params.cov
    if params.reacquire_frames:
        fresh = state.tracked < params.reacquire_frames
        cov = eqx.tree_at(lambda c: c.prior, cov, _widened(cov.prior, cov.blend, fresh))
    rays = jax.vmap(lambda cam, uv: (camera_center(cam), pixel_rays(cam, uv)[1]))(params.cams, uvs)
    return RoundContext(views, okq, q_g, q_h, cov, uvs, rays)


def render_views(params: ShirtParams, ctx: RoundContext, q) -> Hits:
    """The model at ``q`` rendered on every camera's crop grid (patch, colour, 3D point), one
    ``vmap`` over the cameras; Hits stacked over cameras."""
    body, garment = params.render_body, params.garment
    return jax.vmap(lambda o, d, z: render_rays(body, garment, q, o, d, z))(
        *ctx.rays, params.cams.R[:, 2]
    )


def pose_assisted_centroids(
    params: ShirtParams, ctx: RoundContext, patch_maps, plain
) -> PatchCentroids:
    """§5.2 step 3 in every camera (one ``vmap``): one exact EDT per patch of the rendered
    ``patch_maps`` (n_cams, n, n), the pose-assisted classification (``C = 6/s'``, ``T = 5``;
    with ``plain`` the ablation's measurement: step-1 threshold, distance only a tie-break)
    and its patch centroids, stacked over cameras."""
    n, P, dt = params.work_size, params.garment.n_patches, ctx.q_g.dtype
    v = ctx.views
    patch_colour = params.garment.patch_colour

    def one(patch_map, W, crop, fg, s_found, window):
        dist = patch_distance_maps(patch_map, P, dt)
        if params.pose_prior:
            weight = PRIOR_SCALE / s_found * (window[2] / n)  # C = 6/s', d in image px
            weight = jnp.where(plain, jnp.asarray(TIE_BREAK_WEIGHT, dt), weight)
            thr = jnp.where(plain, jnp.asarray(THRESHOLD, dt), jnp.asarray(POSE_THRESHOLD, dt))
        else:
            weight, thr = TIE_BREAK_WEIGHT, THRESHOLD
        pa = pose_assisted_classify(
            params.color, W, crop, dist, patch_colour, weight, fg, thr, params.shading,
            params.scene_colors,
        )  # fmt: skip
        return patch_centroids(pa.patch, P, window, dtype=dt)

    fg_ax = None if v.fgs is None else 0
    c = jax.vmap(one, in_axes=(0, 0, 0, fg_ax, 0, 0))(
        patch_maps, v.cls.W, v.crops, v.fgs, v.s_found, v.windows
    )
    return PatchCentroids(c.xy, c.count, c.valid & ctx.okq[:, None])


def ik_round(params: ShirtParams, ctx: RoundContext, q, hits: Hits, plain=False):
    """One round of steps 3 + 4 with the model rendered at ``q`` (``hits``, stacked over
    cameras): measured centroids in every camera, then the full IK (per-view anchors from
    ``hits``)."""
    meas = pose_assisted_centroids(params, ctx, hits.patch, plain)
    c_obs, v_obs = meas.xy, meas.valid
    chain = params.body.chain
    if params.view_anchors:
        anchors = _view_anchors(chain, params.anchors, params.cams, q, hits.patch, hits.point,
                                ctx.uvs)  # fmt: skip
    else:
        anchors = params.anchors
    sol = solve_ik(chain, params.cams, anchors, c_obs, v_obs, ctx.q_g, ctx.q_h, ctx.cov, q,
                   robust=params.robust)  # fmt: skip
    return sol.q, c_obs, v_obs


def agreement(params: ShirtParams, ctx: RoundContext, hits: Hits) -> Array:
    """Agreement of a render ``hits`` (stacked over cameras) with the step-1 classification:
    agreeing minus disagreeing pixels over the rendered shirt pixels of the cameras that found
    the shirt (shared by all starts, so comparable between them)."""
    dt = ctx.q_g.dtype
    c1, r = ctx.views.cls.ids, hits.colour
    ok = ctx.okq[:, None, None]
    both = (r > 0) & (c1 > 0) & ok
    score = jnp.sum(both & (r == c1)) - jnp.sum(both & (r != c1))
    shown = jnp.sum((r > 0) & ok)
    return score.astype(dt) / jnp.maximum(shown, 1).astype(dt)


def starts_of(params: ShirtParams, state: ShirtState, ctx: RoundContext):
    """The starts of the first round, ``(starts, plain, n)``: the placed blend and the previous
    pose (after a loss: the blend measured without the pose prior); on (re)acquisition frames
    and ``reacquire_frames`` after, a third: the last valid pose measured without the pose
    prior. ``n`` (2 or 3) is traced; without ``temporal_start`` the blend alone."""
    q_g = ctx.q_g
    if not params.temporal_start:
        return q_g[None], jnp.zeros((1,), bool), jnp.asarray(1)
    reacquire = ~state.valid
    starts = [q_g, jnp.where(state.valid, state.q, q_g)]
    plain = [jnp.array(False), reacquire & params.reacquire_start]
    n = jnp.asarray(2)
    if params.held_start:
        starts.append(state.q)
        plain.append(jnp.array(True))
        fresh = reacquire | (state.tracked < params.reacquire_frames)
        n = n + fresh.astype(n.dtype)
    return jnp.stack(starts), jnp.stack(plain), n


def rounds(params: ShirtParams, state: ShirtState, ctx: RoundContext, n_more):
    """Steps 3–4 of the frame: the first round from every start (:func:`starts_of`), the
    best-agreeing result kept (the first of equals), then ``n_more`` (traced) more rounds from
    it, each with the model re-rendered at the last pose. Returns ``(q, c_obs, v_obs, hits,
    agreement)``: the last round's pose and centroids, the render of the pose, and the
    agreement of the kept start's first round.

    One loop of ``2 n + n_more`` iterations, each one render and at most one IK round (under
    ``lax.cond``, which runs one branch on CPU): iteration ``2s`` renders start ``s`` and runs
    its round, ``2s + 1`` renders the result and scores it; after the last start's score and
    after each extra render the next round runs from the kept result. XLA compiles one render
    and one round for the whole frame where a loop per phase compiled three renders and two
    rounds: cold compile + first call 39.4 / 37.9 -> 32.4 / 25.6 s, steady frame 86.3 / 65.5 ->
    64.1 / 56.2 ms in interleaved runs (docs/results/step_ab_session12.json)."""
    starts, plain, n = starts_of(params, state, ctx)
    total = 2 * n + n_more
    dt = ctx.q_g.dtype
    P = params.garment.n_patches
    hits0 = jax.tree.map(lambda x: jnp.zeros(x.shape, x.dtype),
                         jax.eval_shape(lambda: render_views(params, ctx, ctx.q_g)))  # fmt: skip
    c0 = jnp.zeros((params.n_cams, P, 2), dt)
    v0 = jnp.zeros((params.n_cams, P), bool)
    pick = lambda b, x, y: jax.tree.map(lambda u, w: jnp.where(b, u, w), x, y)  # noqa: E731

    def body(k, carry):
        pose, ik_out, best = carry
        hits = render_views(params, ctx, pose)
        s = jnp.minimum(k // 2, starts.shape[0] - 1)
        in_starts = k < 2 * n
        is_start = in_starts & (k % 2 == 0)
        is_check = in_starts & (k % 2 == 1)
        score = agreement(params, ctx, hits)
        # a start's first round scored: kept if it agrees better than every earlier start
        best = pick(is_check & (score > best[-1]), (*ik_out, hits, score), best)
        # an extra round's render: that round's result is the frame's (agreement kept)
        best = pick(~in_starts, (*ik_out, hits, best[-1]), best)
        last_check = is_check & (s == n - 1)
        more = k + 1 < total
        do_ik = is_start | ((last_check | ~in_starts) & more)
        q_src = jnp.where(is_start, pose, best[0])
        hits_src = pick(is_start, hits, best[3])
        plain_k = is_start & plain[s]
        ik_out = jax.lax.cond(
            do_ik,
            lambda: ik_round(params, ctx, q_src, hits_src, plain_k),
            lambda: ik_out,
        )
        nxt = starts[jnp.minimum(s + 1, starts.shape[0] - 1)]
        pose = jnp.where(is_check & ~last_check, nxt, ik_out[0])
        return pose, ik_out, best

    init = (starts[0], (ctx.q_g, c0, v0), (ctx.q_g, c0, v0, hits0, jnp.asarray(-jnp.inf, dt)))
    _, _, best = jax.lax.fori_loop(0, total, body, init)
    return best


def frame_validity(params: ShirtParams, ctx: RoundContext, v_obs, agreement) -> Array:
    """Found in some camera, ``min_patches`` centroids measured, and (when step 1
    classified ``gate_min_fraction`` of some crop: after a sudden lighting change it
    classifies almost nothing until W is re-fitted) the agreement gate passed."""
    valid = jnp.any(ctx.okq) & (jnp.sum(v_obs) >= params.min_patches)
    frac = jnp.max(ctx.views.cls.fraction * ctx.okq)
    seen = frac >= params.gate_min_fraction
    return valid & ((agreement >= params.min_agreement) | ~seen)


def reported_validity(
    params: ShirtParams, ctx: RoundContext, v_obs, signals: FrameSignals, valid, own
) -> Array:
    """The ``valid`` flag reported for the frame: ``valid`` (the tracker's own, which also
    decides what the state keeps) unless ``make_params`` set a reporting rule: then
    ``report_patches`` centroids measured and, in every camera that found the shirt, the
    final pose's centroid residual at most ``max_residual`` and its recall at least
    ``min_recall`` (:class:`FrameSignals`; calibrated on ground truth, issue 17), and the
    output pose is this frame's own solution (``own``: the signals describe it; a held pose,
    ``hold_invalid``, is never reported valid by them)."""
    if params.report_patches is None and params.max_residual is None \
            and params.min_recall is None:
        return valid
    n = params.min_patches if params.report_patches is None else params.report_patches
    ok = jnp.any(ctx.okq) & (jnp.sum(v_obs) >= n)
    if params.max_residual is not None:
        ok = ok & jnp.all((signals.residual <= params.max_residual) | ~ctx.okq)
    if params.min_recall is not None:
        ok = ok & jnp.all((signals.recall >= params.min_recall) | ~ctx.okq)
    return ok & own


def frame_signals(
    params: ShirtParams, state: ShirtState, ctx: RoundContext, db: DatabasePose, q, c_obs,
    v_obs, hits,
) -> FrameSignals:
    """:class:`FrameSignals` of the final pose ``q`` (``hits`` its render on the crops,
    ``c_obs`` / ``v_obs`` the last round's measured centroids)."""
    P, dt = params.garment.n_patches, q.dtype

    def one(patch_map, window, c_obs_i, v_obs_i, c1, r):
        model = patch_centroids(patch_map, P, window, dtype=dt)
        use = v_obs_i & model.valid
        d = jnp.linalg.norm(c_obs_i - model.xy, axis=-1)
        mean_d = jnp.sum(jnp.where(use, d, 0.0)) / jnp.maximum(jnp.sum(use), 1)
        same = jnp.sum((c1 > 0) & (r == c1)).astype(dt)
        return (mean_d / window[2], same / jnp.maximum(jnp.sum(c1 > 0), 1),
                same / jnp.maximum(jnp.sum(r > 0), 1))  # fmt: skip

    res, cov, rec = jax.vmap(one)(hits.patch, ctx.views.windows, c_obs, v_obs,
                                  ctx.views.cls.ids, hits.colour)  # fmt: skip
    rms = lambda a: jnp.sqrt(jnp.mean(jnp.square(a)))  # noqa: E731
    spread = rms(db.q_dbs[0][6:] - db.q_dbs[1][6:]) if params.n_cams > 1 else jnp.zeros((), dt)
    jump = jnp.where(state.valid, jnp.linalg.norm(q[:3] - state.q[:3]), 0.0)
    return FrameSignals(res, cov, rec,
                        rms(q[6:] - ctx.q_g[6:]), spread.astype(dt), jump.astype(dt))


def near_placement(ctx: RoundContext, q) -> Array:
    """Whether ``q`` is finite and its root within ``MAX_ROOT_OFFSET`` of the placed blend's
    (step 2's root, from where and how large the shirt appears in the crops): an IK that ran
    off (too few or wrong centroids) lands metres away."""
    off = jnp.linalg.norm(q[:3] - ctx.q_g[:3])
    return jnp.all(jnp.isfinite(q)) & (off < MAX_ROOT_OFFSET)


def white_balance_refit(params: ShirtParams, state: ShirtState, ctx: RoundContext, hits, valid):
    """§5.2 step 5: ``W*`` per camera refitted on ``r*`` (the final pose's render, eroded by
    one pixel), joining the reference illuminations when new. Returns ``(W, refs, added)``
    stacked over cameras."""
    v = ctx.views
    if not params.adaptive_white_balance:
        return state.W, state.refs, jnp.zeros(params.n_cams, bool)

    def one(refs_i, colour, crop, W_i, fg, ok_cam):
        r_star = _erode(colour)  # q* rendered in the crop (unused if not valid)
        W_star = white_balance_from_ids(
            params.color, crop, r_star, W_i, fg, min_pixels=REFERENCE_PIXELS
        )
        ok = valid & ok_cam & jnp.all(jnp.isfinite(W_star))
        W_star = jnp.where(ok, W_star, W_i)
        refs_i2, add = maybe_add_reference(refs_i, W_star)
        refs_i = jax.tree.map(lambda a, b: jnp.where(ok, a, b), refs_i2, refs_i)
        return W_star, refs_i, add & ok

    fg_ax = None if v.fgs is None else 0
    return jax.vmap(one, in_axes=(0, 0, 0, 0, fg_ax, 0))(
        state.refs, hits.colour, v.crops, v.cls.W, v.fgs, ctx.okq
    )


def _step(params: ShirtParams, state: ShirtState, frames, masks) -> tuple[ShirtState, ShirtOutput]:
    dt = state.q.dtype
    views = locate_and_classify(params, state, frames, masks)
    db = database_pose(params, views, dt)
    q_g = global_placement(params, db, dt)
    ctx = round_context(params, state, views, db.okq, q_g)
    # ik_passes - 1 more rounds, and reacquire_passes more after a loss
    n_more = params.ik_passes - 1 + jnp.where(state.valid, 0, params.reacquire_passes)
    q_sol, c_obs, v_obs, hits, agree = rounds(params, state, ctx, n_more)
    valid = frame_validity(params, ctx, v_obs, agree)
    q_star = jnp.where(valid, q_sol, state.q)
    W_new, refs, added = white_balance_refit(params, state, ctx, hits, valid)
    tracked = jnp.where(valid, state.tracked + 1, 0).astype(jnp.int32)
    new_state = ShirtState(W=W_new, refs=refs, q=q_star, valid=valid, tracked=tracked)
    if params.hold_invalid:
        q_out, own = q_star, valid
    else:  # this frame's estimate where there was something to fit (else it is unconstrained)
        measured = jnp.any(ctx.okq) & (jnp.sum(v_obs) >= MIN_VALID_PATCHES)
        own = measured & near_placement(ctx, q_sol)
        q_out = jnp.where(own, q_sol, state.q)
    signals = frame_signals(params, state, ctx, db, q_sol, c_obs, v_obs, hits)
    out = ShirtOutput(
        q=q_out,
        q_blend=q_g,
        valid=reported_validity(params, ctx, v_obs, signals, valid, own),
        window=views.windows,
        fraction=views.cls.fraction,
        used_reference=views.cls.used_reference,
        added_reference=added,
        centroids=c_obs,
        visible=v_obs,
        agreement=agree,
        signals=signals,
    )
    return new_state, out


@eqx.filter_jit
def model_centroids(
    params: ShirtParams, q: Float[Array, " n_dof"], windows: Float[Array, "n_cams 4"]
) -> PatchCentroids:
    """The model's patch centroids at pose ``q`` as the tracker sees them: ``q`` rendered on
    each camera's ``params.work_size`` crop grid of ``windows`` (e.g. ``ShirtOutput.window``),
    centroids in image pixels, batched over cameras. With ``q`` the ground truth these are
    what per-view anchors predict there, the model term of covariance training
    (:func:`jaxmocap.ik.estimate_covariances` ``predicted=``)."""
    n, P = params.work_size, params.garment.n_patches

    def one(cam, win):
        ids = render_uv(params.render_body, params.garment, q, cam, crop_uv(win, n)).patch
        return patch_centroids(ids, P, win, dtype=q.dtype)

    return jax.vmap(one)(params.cams, windows.astype(q.dtype))


TRACE_COUNT = {"step": 0}  # incremented each time ``step`` is traced (tests count recompiles)


@eqx.filter_jit
def _step_jit(params, state, frames, masks):
    TRACE_COUNT["step"] += 1
    return _step(params, state, frames, masks)


def step(
    params: ShirtParams,
    state: ShirtState,
    frames: UInt8[Array, "n_cams h w 3"] | UInt8[np.ndarray, "n_cams h w 3"],
    masks: Bool[Array, "n_cams h w"] | Bool[np.ndarray, "n_cams h w"] | None = None,
) -> tuple[ShirtState, ShirtOutput]:
    """One frame of Wang et al. §4–5 for every camera (module docstring); jit-compiled once
    per camera count, image size and settings. ``frames`` RGB ``uint8``; ``masks`` optional
    foreground masks (e.g. :class:`jaxmocap.color.BackgroundSubtractor`)."""
    frames, masks = _checked_inputs(params, frames, masks)
    return _step_jit(params, state, frames, masks)


def _checked_inputs(params: ShirtParams, frames, masks):
    frames = jnp.asarray(frames)
    if frames.ndim != 4 or frames.shape[0] != params.n_cams or frames.shape[-1] != 3:
        raise ValueError(f"step: frames must be ({params.n_cams}, H, W, 3) RGB, got {frames.shape}")
    if frames.dtype != jnp.uint8:
        raise ValueError(f"step: frames must be uint8, got {frames.dtype}")
    if masks is not None:
        masks = jnp.asarray(masks, bool)
        if masks.shape != frames.shape[:3]:
            raise ValueError(f"step: masks must be {frames.shape[:3]}, got {masks.shape}")
    return frames, masks


def compile_step(
    params: ShirtParams,
) -> Callable[..., tuple[ShirtState, ShirtOutput]]:
    """:func:`step` with ``params`` bound, for frame loops: ``(state, frames, masks=None) ->
    (state, output)``, the same results.

    On its first call without masks it takes the program shipped for the demo's set-up when
    that applies (:mod:`jaxmocap.trackers.shirt_export`: the step traced ahead of time, so the
    first frame only waits for XLA's compile, ~6 s less on an empty cache); otherwise it says
    why in one line on stderr and traces :func:`step` as usual."""
    from jaxmocap.trackers import shirt_export

    chosen: dict[bool, Callable | None] = {}

    def fn(state, frames, masks=None):
        frames, masks = _checked_inputs(params, frames, masks)
        plain = masks is None
        if plain not in chosen:
            program, why = shirt_export.load(params, state, frames, masks)
            if program is None:
                print(f"jaxmocap: shirt step: {why}; tracing it", file=sys.stderr)
            chosen[plain] = program
        program = chosen[plain]
        if program is None:
            return _step_jit(params, state, frames, masks)
        return program(state, frames)

    return fn


def run(
    params: ShirtParams,
    state: ShirtState,
    frames: UInt8[np.ndarray, "t n_cams h w 3"],
    background: bool = False,
) -> tuple[ShirtState, ShirtOutput]:
    """Track a sequence frame by frame (the live loop). With ``background`` each camera gets
    an OpenCV MOG2 subtractor on the host. Outputs are stacked over frames."""
    from jaxmocap.color import BackgroundSubtractor

    subs = [BackgroundSubtractor() for _ in range(params.n_cams)] if background else None
    outs = []
    for t in range(frames.shape[0]):
        masks = None
        if subs is not None:
            masks = np.stack([s.apply(np.asarray(frames[t, i])) for i, s in enumerate(subs)])
        state, out = step(params, state, frames[t], masks)
        outs.append(out)
    return state, jax.tree.map(lambda *a: jnp.stack(a), *outs)


@eqx.filter_jit
def run_scan(
    params: ShirtParams,
    state: ShirtState,
    frames: UInt8[Array, "t n_cams h w 3"],
    masks: Bool[Array, "t n_cams h w"] | None = None,
) -> tuple[ShirtState, ShirtOutput]:
    """Track a whole sequence under ``jax.lax.scan`` (offline; masks precomputed if any)."""
    if masks is None:
        return jax.lax.scan(lambda s, f: _step(params, s, f, None), state, frames)
    return jax.lax.scan(lambda s, fm: _step(params, s, fm[0], fm[1]), state, (frames, masks))


# ----------------------------------------------------------------------------- set-up (§5.1)

SCRIBBLE_EROSION = 2  # pixels removed from every colour region to make "scribbles"


def scribbles(colour_ids: Int[np.ndarray, "h w"], erosion: int = SCRIBBLE_EROSION) -> np.ndarray:
    """Scribble labels from a colour-id map: every colour region eroded by ``erosion`` pixels
    (OpenCV, 3x3 cross), so labels stay well inside the patches as a user's strokes would."""
    import cv2

    ids = np.asarray(colour_ids)
    out = np.zeros(ids.shape, np.int32)
    kernel = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    for k in np.unique(ids[ids > 0]):
        m = cv2.erode((ids == k).astype(np.uint8), kernel, iterations=int(erosion))
        out[m > 0] = k
    return out


SCRIBBLE_INTENSITIES = (0.7, 0.85, 1.0, 1.15, 1.3)  # light levels of the five model images
SCRIBBLE_NOISE = 0.02  # sensor noise of the model images (fraction of 255)


def fit_color_model_from_renders(
    body: BodyModel,
    garment: Garment,
    poses: Float[np.ndarray, "n n_dof"],
    cam: Camera,
    erosion: int = SCRIBBLE_EROSION,
    intensities: Sequence[float] = SCRIBBLE_INTENSITIES,
    noise_sigma: float = SCRIBBLE_NOISE,
    background: int = 128,
    seed: int = 0,
) -> ColorModel:
    """The offline colour model (Wang §5.1, Fig. 5): "scribbles" on white-balanced images.

    Pose ``i`` is rendered by ``cam`` under white light (identity illuminant) of intensity
    ``intensities[i % len]`` with sensor noise, over a grey background (the paper's five
    images are photographs; the varied light level stands in for their exposure and shading
    differences); its ground-truth colour-id map eroded by ``erosion`` pixels
    (:func:`scribbles`) labels the pixels; the Gaussians are their ML fit
    (:func:`jaxmocap.color.fit_color_model`).
    """
    from jaxmocap.color import fit_color_model
    from jaxmocap.render import default_lighting, render_rgb

    dt = cam.K.dtype
    bg = jnp.full((cam.height, cam.width, 3), background, jnp.uint8)

    @jax.jit
    def render(q, intensity, key):
        light = eqx.tree_at(lambda lt: lt.intensity, default_lighting(dt), intensity)
        return render_rgb(body, garment, q, cam, bg, light, noise_sigma=noise_sigma, key=key)

    images, labels = [], []
    for i, q in enumerate(np.asarray(poses)):
        level = jnp.asarray(intensities[i % len(intensities)], dt)
        rgb, hits = render(jnp.asarray(q, dt), level, jax.random.fold_in(jax.random.key(seed), i))
        images.append(np.asarray(rgb))
        labels.append(scribbles(np.asarray(hits.colour), erosion))
    return fit_color_model(images, labels, garment.n_colours, garment.colour_names)


def initial_white_balance(
    color: ColorModel,
    frames: UInt8[np.ndarray, "n_cams h w 3"],
    labels: Int[np.ndarray, "n_cams h w"],
) -> Float[Array, "n_cams 3 3"]:
    """``W0`` per camera from one scribbled frame of the capture's light (Wang §5.1):
    ``labels`` 0 = unlabelled, ``1..k`` colour ids (e.g. :func:`scribbles` of a ground-truth
    map)."""
    from jaxmocap.color import white_balance_from_scribbles

    return jnp.stack(
        [
            white_balance_from_scribbles(color, [f], [lab])
            for f, lab in zip(frames, labels, strict=True)
        ]
    )


def setup_for_sequence(
    seq,
    db: PoseDB,
    cov: IKCovariances | None = None,
    work_size: int = WORK_SIZE,
) -> tuple[ShirtParams, Float[Array, "n_cams 3 3"], ColorModel]:
    """Tracker set-up for a rendered :class:`jaxmocap.synth.Sequence` the way a user sets up a
    capture session (§5.1): the colour model from scribbles on white-light renders of five
    database poses placed at the subject's first position in front of camera 0
    (:func:`fit_color_model_from_renders`), ``W0`` from one scribbled frame of the scene (the
    first frame's ground-truth colour ids, eroded: :func:`scribbles`), patch anchors of the
    default garment, and ``cov`` (default: isotropic 2 px / 0.3 / 0.5). Returns
    ``(params, W0, color)``."""
    from jaxmocap.body import default_body
    from jaxmocap.camera import stack_cameras
    from jaxmocap.garment import default_garment
    from jaxmocap.ik import anchors_from_garment

    body = default_body()
    garment = default_garment(body)
    q_model = np.asarray(db.poses[:5], np.float64).copy()
    q_model[:, :3] = np.asarray(seq.groundtruth["q"][0, :3])
    color = fit_color_model_from_renders(body, garment, q_model, seq.cameras[0])
    labels = np.stack([scribbles(m) for m in seq.groundtruth["colour_ids"][0]])
    W0 = initial_white_balance(color, seq.frames[0], labels)
    cov = cov if cov is not None else IKCovariances.isotropic(2.0, 0.3, 0.5, body.n_dof)
    params = make_params(
        color,
        body,
        garment,
        stack_cameras(list(seq.cameras)),
        anchors_from_garment(body, garment),
        cov,
        db,
        work_size=work_size,
    )
    return params, W0, color
