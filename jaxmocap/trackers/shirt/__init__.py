"""The colour-shirt tracker of Wang et al. 2011 (§4–5): ``init`` and the per-frame ``step``.

Files, one per stage of the paper: :mod:`.params` (constants, parameters, state, ``make_params``,
``init``), :mod:`.frame` (the frame step, one function
per paper step), :mod:`.sequence` (``step``, ``compile_step``, ``run``, ``run_scan``),
:mod:`.session` (the capture-session set-up of §5.1), :mod:`.covariances` (the bundled trained
IK covariances, by role for any body) and :mod:`.export` (the step shipped already traced for
the demo's set-up).

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

from jaxmocap.sampling import crop_uv, crop_window, sample_nearest
from jaxmocap.sampling import sample_bilinear_clamped as sample_bilinear
from jaxmocap.trackers.shirt.covariances import (
    TRAINED_COV_FILE,
    covariances_for_body,
    trained_covariances,
)
from jaxmocap.trackers.shirt.frame import (
    DatabasePose,
    RoundContext,
    Views,
    agreement,
    database_pose,
    frame_signals,
    frame_validity,
    global_placement,
    ik_round,
    locate_and_classify,
    model_centroids,
    near_placement,
    pose_assisted_centroids,
    render_views,
    reported_validity,
    round_context,
    rounds,
    starts_of,
    white_balance_refit,
)
from jaxmocap.trackers.shirt.params import (
    CROP_FACTOR,
    GATE_MIN_FRACTION,
    IK_PASSES,
    MAX_ROOT_OFFSET,
    MIN_AGREEMENT,
    MIN_VALID_PATCHES,
    REACQUIRE_FRAMES,
    REACQUIRE_PASSES,
    REFERENCE_PIXELS,
    ROBUST_SCALE,
    TIE_BREAK_WEIGHT,
    WORK_SIZE,
    Ablations,
    Colours,
    FrameSignals,
    Rounds,
    Search,
    ShirtOutput,
    ShirtParams,
    ShirtState,
    ValidityRule,
    init,
    make_params,
    scales_for_width,
    validity_rule,
)
from jaxmocap.trackers.shirt.sequence import (
    TRACE_COUNT,
    compile_step,
    run,
    run_scan,
    step,
)
from jaxmocap.trackers.shirt.session import (
    SCRIBBLE_EROSION,
    SCRIBBLE_INTENSITIES,
    SCRIBBLE_NOISE,
    fit_color_model_from_renders,
    initial_white_balance,
    scribbles,
    setup_for_sequence,
)

__all__ = [
    "Ablations",
    "CROP_FACTOR",
    "Colours",
    "DatabasePose",
    "FrameSignals",
    "GATE_MIN_FRACTION",
    "IK_PASSES",
    "MAX_ROOT_OFFSET",
    "MIN_AGREEMENT",
    "MIN_VALID_PATCHES",
    "REACQUIRE_FRAMES",
    "REACQUIRE_PASSES",
    "REFERENCE_PIXELS",
    "ROBUST_SCALE",
    "RoundContext",
    "Rounds",
    "SCRIBBLE_EROSION",
    "SCRIBBLE_INTENSITIES",
    "SCRIBBLE_NOISE",
    "Search",
    "ShirtOutput",
    "ShirtParams",
    "ShirtState",
    "ValidityRule",
    "TIE_BREAK_WEIGHT",
    "TRACE_COUNT",
    "TRAINED_COV_FILE",
    "Views",
    "WORK_SIZE",
    "agreement",
    "compile_step",
    "covariances_for_body",
    "crop_uv",
    "crop_window",
    "database_pose",
    "fit_color_model_from_renders",
    "frame_signals",
    "frame_validity",
    "global_placement",
    "ik_round",
    "init",
    "initial_white_balance",
    "locate_and_classify",
    "make_params",
    "model_centroids",
    "near_placement",
    "pose_assisted_centroids",
    "render_views",
    "reported_validity",
    "round_context",
    "rounds",
    "run",
    "run_scan",
    "sample_bilinear",
    "sample_nearest",
    "scales_for_width",
    "scribbles",
    "setup_for_sequence",
    "starts_of",
    "step",
    "trained_covariances",
    "validity_rule",
    "white_balance_refit",
]
