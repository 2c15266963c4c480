"""Parameters and state of the colour-shirt tracker (Wang et al. 2011 §4–5): the paper's
constants and the extensions' defaults, :class:`ShirtParams`, :class:`ShirtState`,
:class:`ShirtOutput`, :func:`make_params` and :func:`init`."""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from jaxmocap.appearance import LOST_FRAMES, PartColours, init_parts
from jaxmocap.body import BodyModel
from jaxmocap.camera import Camera
from jaxmocap.color import (
    ColorModel,
    ReferenceIlluminations,
    init_references,
)
from jaxmocap.color.model import shading_problem
from jaxmocap.garment import Garment
from jaxmocap.ik import (
    IKCovariances,
    PatchAnchors,
)
from jaxmocap.observe import Observer
from jaxmocap.posedb._sample import canonical_camera
from jaxmocap.posedb._search import PoseDB
from jaxmocap.trackers.shirt.skin import SkinTerms, make_skin_terms

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
# Not in the paper: with ``patch_colours`` a camera's colour states learn from a valid frame
# only where the final pose explains its crop: centroid residual <= 5.3% of the crop side and
# >= 31% of the rendered shirt pixels classified as their colour in step 1 (the reported
# validity calibrated on the dev split's ground truth, world_shirt.toml "validated"). States
# that learn from a wrong pose learn the wrong patches and lead the next frames there.
# issue 49: the step-3 prior's weight on the learned model's -log p, a multiple of Wang's C = 6/s
# (dev split, learned_ladder.py --prior-scale: docs/results/learned.md)
OBSERVER_PRIOR = 1.0
COLOUR_MAX_RESIDUAL = 0.053
COLOUR_MIN_RECALL = 0.31


def scales_for_width(width: int, stride: int = 6) -> tuple[int, ...]:
    """The histogram search's six scales (Wang §4) for an image ``width`` pixels wide: the
    640-pixel defaults of :data:`jaxmocap.color.DEFAULT_SCALES` scaled, each a multiple of
    ``2 stride`` (at least one per size)."""
    from jaxmocap.color import DEFAULT_SCALES

    step = 2 * stride
    out = sorted({max(step, int(round(s * width / 640 / step)) * step) for s in DEFAULT_SCALES})
    return tuple(out)


class Search(eqx.Module):
    """Where the shirt is and the crop the later steps work on (Wang §4).

    * ``work_size`` (static: every later shape): side of the resampled square crop, working
      pixels (not in the paper, whose steps run on the full frame);
    * ``scales`` (static: the search's programme): the histogram search's six window sizes,
      pixels; ``()``: :func:`scales_for_width` of the cameras' width (the 640-pixel defaults of
      :data:`jaxmocap.color.DEFAULT_SCALES` scaled);
    * ``crop_factor`` (static): the crop's side over the search's scale ``s'`` (the shirt's
      extent is about 2 ``s'`` with the arms out; not in the paper); a constant of the program
      because a traced factor changed the demo's poses in the last bits (XLA folds it into
      the crop's arithmetic).
    """

    work_size: int = eqx.field(static=True, default=WORK_SIZE)
    scales: tuple[int, ...] = eqx.field(static=True, default=())
    crop_factor: float = eqx.field(static=True, default=CROP_FACTOR)


class Rounds(eqx.Module):
    """Steps 3–4 (§5.2): the rounds of (render, pose-assisted classification, IK) per frame,
    their starts, and the reacquisition after a loss. None of it is in the paper, which
    renders ``r^b`` once at ``q_b`` and solves the IK once from it. The counts are static
    (they shape the rounds' loop and the prior's widening), as are the switches.

    * ``ik_passes`` (static, >= 1): rounds per frame, each with the model re-rendered at the
      previous round's pose;
    * ``robust`` (static; ``None``: the paper's plain least squares): Cauchy scale of the IK's
      centroid terms, standard deviations of Sigma_c (:func:`jaxmocap.ik.solve_ik`, which also
      takes it traced); a constant of the program because a traced scale changed the demo's
      poses in the last bits (XLA folds the constant's ``c^2`` into the residual);
    * ``view_anchors`` (static): predict each patch's centroid from the model's render in the
      camera's crop (:func:`jaxmocap.ik.view_anchors`) instead of the whole patch's fixed 3D
      centroid;
    * ``temporal_start`` (static): the first round runs from two starts, the placed blend
      ``q_b`` and the previous frame's pose, under ``jax.vmap``, keeping the result whose
      render agrees best with the step-1 classification (the paper starts from ``q_b`` only;
      a bad database match then leaves the IK in a wrong basin although the previous frame
      was right);
    * after a loss (the first frame, or any frame after an invalid one) there is no previous
      pose to start from: with ``reacquire_start`` (static; and ``temporal_start``) the second
      start is then the placed blend measured *without* the pose prior (step-1
      classification, each pixel given to the nearer patch of its colour), which a blend in a
      wrong basin cannot mislead; ``reacquire_passes`` (static) extra rounds run on such
      frames (the loop runs longer: no cost on tracked frames); for ``reacquire_frames``
      (static) frames after a loss the temporal term's covariance is ``Sigma_p + Sigma_b``:
      its ``q_h`` comes from a cold start, whose error is of the blend's order, not the
      tracked steady state that ``Sigma_p`` was trained on. All three off
      (``reacquire_start=False, reacquire_passes=0, reacquire_frames=0``): no reacquisition;
    * ``held_start`` (static) adds a third start on those frames (reacquisition and the
      ``reacquire_frames`` after it): the last valid pose measured without the pose prior (a
      subject re-entering fast is far from it, and a prior rendered there misleads the
      pose-assisted classification); on other frames it repeats the blend start;
    * ``static_kinds`` (static): the renders inside the step use the body's geom kinds as
      constants, so that the ray caster tests each geom against its own primitive only; with
      traced kinds it evaluates every primitive kind for every geom and selects (2x slower
      per crop pair). The two paths round differently on a few silhouette pixels; paired over
      8 held-out sequences with the 80,000-pose database the mean error is 4.85 cm static vs
      4.90 traced, within the rounding noise of the tracker
      (docs/results/realtime_profile.md). False: the traced-kinds path.
    * ``orientation_hypotheses`` (static; 0: off): after a loss, every camera's database query
      also returns this many orientation hypotheses (the nearest maps split into orientation
      clusters, each blended on its own: :func:`jaxmocap.posedb.estimate_hypotheses`), each
      placed from that camera alone, and each joins the first round's starts with its own
      pose as the IK's blend and temporal prior; the best-agreeing start in every camera is
      kept as before (issue 38 item 2; frame.orientation_starts). Side and back views make
      the nearest maps disagree about which way the body faces.
    * ``own_start`` (static): after an invalid frame whose own estimate was measured and near
      its placement (what the output's ``q`` shows with ``hold_invalid`` off), that estimate
      joins the next frame's starts
      (with the pose prior; the temporal prior stays the blend), chosen like the others by
      its agreement (issue 38 item 3: a frame flagged invalid is often right, and without it
      the next frame starts only from the blend and the last valid pose). On the dev split
      (world2_shirt.toml "robust") the all-frames mean went 21.1 -> 15.6 cm (frame-weighted;
      first-round dev 15.5/7.4/21.3/23.8 -> 12.6/7.1/12.6/16.3, shirt_12 30.0 -> 30.6,
      shirt_13 41.9 -> 30.3; docs/results/shirt_views.md). False: the starts of before.
    * ``skin_terms`` (static): head and hands observed as skin (issue 38 item 1,
      :mod:`jaxmocap.trackers.shirt.skin`): on a frame after a valid one every round's IK also
      fits the centroids of the skin pixels near each of head, left and right hand predicted
      by the round's render, gated by size and by agreement between cameras (a failing gate:
      weight 0). The skin colour is ``make_params``'s ``skin_colour`` (scribbles) or the
      garment's skin albedo (:func:`~jaxmocap.trackers.shirt.skin.skin_colour_from_garment`).
      On the dev split with the skin scribbled (world2_shirt_skin.toml) 15.60 -> 14.90 cm
      over all frames (head 10.1 -> 9.1, hands 26.3 -> 25.6; shirt_13 30.3 -> 35.0;
      docs/results/shirt_skin.md). Off by default: the albedo's skin, what a capture without
      skin scribbles gets, is not measured.
    """

    ik_passes: int = eqx.field(static=True, default=IK_PASSES)
    robust: float | None = eqx.field(static=True, default=ROBUST_SCALE)
    view_anchors: bool = eqx.field(static=True, default=True)
    temporal_start: bool = eqx.field(static=True, default=True)
    reacquire_start: bool = eqx.field(static=True, default=True)
    reacquire_passes: int = eqx.field(static=True, default=REACQUIRE_PASSES)
    reacquire_frames: int = eqx.field(static=True, default=REACQUIRE_FRAMES)
    held_start: bool = eqx.field(static=True, default=True)
    static_kinds: bool = eqx.field(static=True, default=True)
    orientation_hypotheses: int = eqx.field(static=True, default=0)
    own_start: bool = eqx.field(static=True, default=True)
    skin_terms: bool = eqx.field(static=True, default=False)


class Colours(eqx.Module):
    """How pixels are compared with the shirt's colours beyond the paper's Gaussian distance
    under one white balance per camera (all off by default).

    Footage under spot lamps (issue 17):

    * ``shading`` (static: it goes with the colour model, which should be fitted with the same
      ``gain``, :func:`jaxmocap.color.fit_color_model`): ``(lo, hi)`` compares every pixel to
      every colour at its best brightness in ``[lo, hi]`` (steps 1 and 3;
      :func:`jaxmocap.color.classify` ``gain``); ``None``: the paper's Gaussian distance;
    * ``scene_colors`` (arrays): Gaussians of the room's colours
      (:func:`jaxmocap.color.fit_scene_colors`); a pixel nearer one of them than every shirt
      colour is background in steps 1 and 3.

    The learned observation (issue 49, :mod:`jaxmocap.observe`):

    * ``observer``: a model trained on our own renders (``jaxmocap learn``) gives every crop
      pixel a probability over background, the garment's colours and skin. Step 1's colour ids
      are its most probable class (skin and background: 0); step 3 gives a pixel to the patch
      ``p`` minimising ``-log p(colour(p)) + observer_prior * C d(r^b, p)`` unless ``-log
      p(not shirt)`` is lower (Wang's cost with the model's negative log-probability in place
      of the Mahalanobis distance); the white balance is neither used nor re-fitted. It
      replaces ``shading``, ``scene_colors`` and ``patch_colours`` (refused together).

    Colour states per patch (issue 37):

    * ``patch_colours`` (static): a colour state per patch and camera
      (:mod:`jaxmocap.appearance`) starts from the colour model (each patch its colour's
      Gaussian, in the colour space of the initial white balance ``W0``), classifies steps 1
      and 3 per patch (a pixel's colour is its patch's) and is relit by a two-illuminant
      mixture and updated from the final pose's render in step 5 (valid frames only); the
      per-camera ``W`` and reference illuminations are then not used;
    * a camera's states learn from a valid frame only where the final pose explains its crop:
      centroid residual <= ``learn_max_residual`` crop sides and >= ``learn_min_recall`` of
      the rendered shirt pixels classified as their colour in step 1 (traced; the reported
      validity calibrated on the dev split's ground truth, world_shirt.toml "validated").
      States that learn from a wrong pose learn the wrong patches and lead the next frames
      there;
    * ``follow_light`` (static): on the first invalid frame after one a camera learned from,
      relight its states from the held pose's render (:func:`jaxmocap.appearance.follow_light`):
      it keeps a lamp switched on over half the image followed (tests), but on the dev split
      it took the occluder's colours into the states (shirt_03: 7.1 -> 20.1 cm over all
      frames; shirt_00's lamp switched off: 12.6 -> 14.0; shirt_06: 18.6 -> 16.5;
      docs/results/appearance.md).
    """

    shading: tuple[float, float] | None = eqx.field(static=True, default=None)
    scene_colors: ColorModel | None = None
    observer: Observer | None = None
    observer_prior: Float[ArrayLike, ""] = OBSERVER_PRIOR
    patch_colours: bool = eqx.field(static=True, default=False)
    follow_light: bool = eqx.field(static=True, default=False)
    learn_max_residual: Float[ArrayLike, ""] = COLOUR_MAX_RESIDUAL
    learn_min_recall: Float[ArrayLike, ""] = COLOUR_MIN_RECALL


class Ablations(eqx.Module):
    """The paper's own ablations (Wang Fig. 9–10; static switches, both on by default):
    ``pose_prior=False`` skips step 3's prior -- centroids come from the step-1
    classification (``T = 3``), each pixel given to the nearer of the two patches of its
    colour in ``r^b`` (that tie-break only, no cost); ``adaptive_white_balance=False`` keeps
    ``W = W0`` and no reference illuminations. Both off is the WP09-like baseline."""

    pose_prior: bool = eqx.field(static=True, default=True)
    adaptive_white_balance: bool = eqx.field(static=True, default=True)


class ValidityRule(eqx.Module):
    """When a frame counts as valid (:func:`~jaxmocap.trackers.shirt.frame.frame_validity`)
    and what the output reports (:func:`~jaxmocap.trackers.shirt.frame.reported_validity`).

    The thresholds are traced arrays (:func:`make_params` casts them to the parameters' float
    dtype), so a new value runs the compiled step as it is; which checks apply is static (it
    changes the program). ``ValidityRule()`` is the tracker's own rule with the defaults
    below; :func:`validity_rule` builds one from plain numbers with the checks switched on by
    the thresholds given.

    * the tracker's own rule: ``min_patches`` patch centroids measured (all cameras) and, where
      step 1 classified at least ``gate_min_fraction`` of a crop, the render of the result
      agreeing with the step-1 classification on ``min_agreement`` of its pixels;
    * ``report``: the output's flag has a rule of its own: ``report_patches`` centroids and,
      in every camera that found the shirt, a centroid residual of at most ``max_residual``
      crop sides (``check_residual``) and a recall of at least ``min_recall``
      (``check_recall``; :class:`FrameSignals`);
    * ``hold_invalid``: an invalid frame's output ``q`` is the last valid pose.
    """

    min_agreement: Float[ArrayLike, ""] = MIN_AGREEMENT
    gate_min_fraction: Float[ArrayLike, ""] = GATE_MIN_FRACTION
    min_patches: Int[ArrayLike, ""] = MIN_VALID_PATCHES
    report_patches: Int[ArrayLike, ""] = MIN_VALID_PATCHES
    max_residual: Float[ArrayLike, ""] = 1.0
    min_recall: Float[ArrayLike, ""] = 0.0
    report: bool = eqx.field(static=True, default=False)
    check_residual: bool = eqx.field(static=True, default=False)
    check_recall: bool = eqx.field(static=True, default=False)
    hold_invalid: bool = eqx.field(static=True, default=True)


def validity_rule(dtype=None, min_agreement: float = MIN_AGREEMENT,
                  gate_min_fraction: float = GATE_MIN_FRACTION,
                  min_patches: int = MIN_VALID_PATCHES, report_patches: int | None = None,
                  max_residual: float | None = None, min_recall: float | None = None,
                  hold_invalid: bool = True) -> ValidityRule:
    """A :class:`ValidityRule` from plain numbers (``None``: that check is off); its arrays in
    ``dtype`` (default: jax's default float; :func:`make_params` casts them to the cameras')."""
    for name, v in (("max_residual", max_residual), ("min_recall", min_recall)):
        if v is not None and not 0 <= v <= 1:
            raise ValueError(f"validity_rule: {name} must be None or in [0, 1], got {v}")
    if report_patches is not None and report_patches < 0:
        raise ValueError(
            f"validity_rule: report_patches must be None or >= 0, got {report_patches}")
    report = report_patches is not None or max_residual is not None or min_recall is not None
    return ValidityRule(
        min_agreement=jnp.asarray(min_agreement, dtype),
        gate_min_fraction=jnp.asarray(gate_min_fraction, dtype),
        min_patches=jnp.asarray(min_patches, jnp.int32),
        report_patches=jnp.asarray(min_patches if report_patches is None else report_patches,
                                   jnp.int32),
        max_residual=jnp.asarray(1.0 if max_residual is None else max_residual, dtype),
        min_recall=jnp.asarray(0.0 if min_recall is None else min_recall, dtype),
        report=report, check_residual=max_residual is not None,
        check_recall=min_recall is not None, hold_invalid=bool(hold_invalid))


class ShirtParams(eqx.Module):
    """Everything the tracker needs that does not change over a sequence (:func:`make_params`).

    ``cams`` is a stacked :class:`~jaxmocap.camera.Camera` (leading axis = cameras); ``db`` a
    :class:`jaxmocap.PoseDB`; the settings are grouped in :class:`Search`, :class:`Rounds`,
    :class:`Colours`, :class:`ValidityRule` and :class:`Ablations`, their numbers traced
    arrays (a new value runs the compiled step as it is), their switches static.
    """

    color: ColorModel
    body: BodyModel
    garment: Garment
    cams: Camera
    anchors: PatchAnchors
    cov: IKCovariances
    db: PoseDB
    canon: Camera  # the database's canonical camera
    search: Search
    rounds: Rounds
    colours: Colours
    validity: ValidityRule
    ablations: Ablations
    geom_kinds: tuple[int, ...] = eqx.field(static=True, default=())  # body's, for renders
    skin: SkinTerms | None = None  # with ``rounds.skin_terms`` (:mod:`.skin`)

    def __check_init__(self):
        # one switch: the program reads ``rounds.skin_terms``, the terms must come with it
        if self.rounds.skin_terms != (self.skin is not None):
            raise ValueError("ShirtParams: rounds.skin_terms and skin go together (skin terms "
                             f"on: {self.rounds.skin_terms}, skin given: {self.skin is not None})"
                             "; make_params builds both")

    @property
    def n_cams(self) -> int:
        return self.cams.K.shape[0]

    @property
    def render_body(self) -> BodyModel:
        """``body`` with its geom kinds as constants (``geom_kinds``) for the ray caster's
        per-kind tests inside the jitted step (the same body; traced kinds otherwise)."""
        if not self.rounds.static_kinds or len(self.geom_kinds) != self.body.geometry.kind.shape[0]:
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
    # with ``patch_colours``: per camera, each patch's colour state (in the colour space of
    # the camera's initial white balance ``look_W``, fixed: the scene colours live there)
    look: PartColours | None = None
    look_W: Float[Array, "n_cams 3 3"] | None = None
    # with ``rounds.own_start``: the last frame's own estimate where it had one (else the
    # one before)
    q_own: Float[Array, " n_dof"] | None = None


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
    """Per-frame results. ``q`` the final pose ``q*`` (on an invalid frame the held pose, see
    ``ValidityRule.hold_invalid``), ``q_frame`` this frame's own IK solution whether valid or
    not (NaN where there was nothing to fit: the shirt found in no camera or fewer than
    ``MIN_VALID_PATCHES`` centroids measured, on a frame not valid), ``q_blend`` the globally
    placed blended database pose; per camera: crop ``window`` (x0, y0, s, s) image pixels, the
    step-1 classified ``fraction``, whether a reference illumination was used / added, the
    measured ``centroids`` (pixels) and their ``visible`` flags."""

    q: Float[Array, " n_dof"]
    q_frame: Float[Array, " n_dof"]
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
    # with ``patch_colours``, per camera: the patches whose colour state this frame updated,
    # whether the two-illuminant relight was physical and applied, and its RMS log residual
    colour_updated: Int[Array, " n_cams"] | None = None
    relight_ok: Bool[Array, " n_cams"] | None = None
    relight_rms: Float[Array, " n_cams"] | None = None


def make_params(
    color: ColorModel,
    body: BodyModel,
    garment: Garment,
    cams: Camera,
    anchors: PatchAnchors,
    cov: IKCovariances,
    db: PoseDB,
    *,
    search: Search | None = None,
    rounds: Rounds | None = None,
    colours: Colours | None = None,
    validity: ValidityRule | None = None,
    ablations: Ablations | None = None,
    skin_colour: ColorModel | None = None,
) -> ShirtParams:
    """Validated :class:`ShirtParams`: the capture (colour model, body, garment, stacked
    cameras, patch anchors, IK covariances, pose database) and the settings, each group's
    defaults the paper's constants and the extensions' measured choices (:class:`Search`,
    :class:`Rounds`, :class:`Colours`, :class:`ValidityRule`, :class:`Ablations`). Every
    number is cast to an array (floats in the cameras' dtype, counts int32), so that
    replacing one (``dataclasses.replace(params, rounds=...)``, or another
    ``make_params``) reuses the compiled step; a switch changes the program. ``skin_colour``
    (one Gaussian, e.g. from scribbles on the capture's skin) is the skin class of
    ``rounds.skin_terms`` (default: from the garment's skin albedo)."""
    dt = cams.K.dtype
    search = Search() if search is None else search
    rounds = Rounds() if rounds is None else rounds
    colours = Colours() if colours is None else colours
    validity = ValidityRule() if validity is None else validity
    ablations = Ablations() if ablations is None else ablations
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
    for name, v, lo in (("ik_passes", rounds.ik_passes, 1),
                        ("orientation_hypotheses", rounds.orientation_hypotheses, 0),
                        ("reacquire_passes", rounds.reacquire_passes, 0),
                        ("reacquire_frames", rounds.reacquire_frames, 0)):
        if int(v) != v or int(v) < lo:
            raise ValueError(f"make_params: rounds.{name} must be an integer >= {lo}, got {v}")
    if search.work_size < 16:
        raise ValueError(f"make_params: search.work_size must be >= 16, got {search.work_size}")
    sc = tuple(int(s) for s in search.scales) or scales_for_width(cams.width)
    shading = colours.shading
    if shading is not None:
        problem = shading_problem(shading)
        if problem:
            raise ValueError(f"make_params: colours.shading: {problem}")
        shading = tuple(float(g) for g in shading)
    ints = lambda x: jnp.asarray(x, jnp.int32)  # noqa: E731
    floats = lambda x: jnp.asarray(x, dt)  # noqa: E731
    search = Search(int(search.work_size), sc, float(search.crop_factor))
    rounds = dataclasses.replace(
        rounds, ik_passes=int(rounds.ik_passes),
        robust=None if rounds.robust is None else float(rounds.robust),
        reacquire_passes=int(rounds.reacquire_passes),
        reacquire_frames=int(rounds.reacquire_frames),
        orientation_hypotheses=int(rounds.orientation_hypotheses))
    if colours.observer is not None:
        mixed = [n for n, on in (("shading", shading is not None),
                                 ("scene_colors", colours.scene_colors is not None),
                                 ("patch_colours", colours.patch_colours)) if on]
        if mixed:
            raise ValueError(f"make_params: colours.observer replaces colours.{mixed[0]} "
                             "(the learned model classifies the pixels); give one of them")
        want = garment.n_colours + 4
        if colours.observer.n_classes != want:
            raise ValueError(f"make_params: colours.observer gives {colours.observer.n_classes} "
                             f"classes, this garment needs {want} (background, its "
                             f"{garment.n_colours} colours, head, two hands)")
    colours = dataclasses.replace(
        colours, shading=shading, learn_max_residual=floats(colours.learn_max_residual),
        observer_prior=floats(colours.observer_prior),
        learn_min_recall=floats(colours.learn_min_recall))
    validity = dataclasses.replace(
        validity, min_agreement=floats(validity.min_agreement),
        gate_min_fraction=floats(validity.gate_min_fraction),
        min_patches=ints(validity.min_patches), report_patches=ints(validity.report_patches),
        max_residual=floats(validity.max_residual), min_recall=floats(validity.min_recall))
    skin = None
    if rounds.skin_terms:
        skin = make_skin_terms(body, garment, color, skin_colour, colours.scene_colors, shading)
    return ShirtParams(
        color, body, garment, cams, anchors, cov, db, canonical_camera(dt), search, rounds,
        colours, validity, ablations, tuple(int(k) for k in np.asarray(body.geometry.kind)),
        skin,
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
    look = look_W = None
    if params.colours.patch_colours:
        k = jnp.asarray(params.garment.patch_colour) - 1
        one = init_parts(params.color.mean[k], params.color.cov[k])
        # no frame learned from yet: nothing to follow the light from (frame.colour_update)
        one = eqx.tree_at(lambda s: (s.age, s.lost), one,
                          (jnp.ones_like(one.age), jnp.asarray(LOST_FRAMES, jnp.int32)))
        look = jax.tree.map(lambda x: jnp.stack([x] * params.n_cams), one)
        look_W = W0
    q_own = jnp.asarray(q0) if params.rounds.own_start else None
    return ShirtState(
        W=W0, refs=refs, q=jnp.asarray(q0), valid=jnp.array(False),
        tracked=jnp.array(0, jnp.int32), look=look, look_W=look_W, q_own=q_own,
    )


# ----------------------------------------------------------------------------- the frame step
#
# ``_step`` is the paper's steps in order, each a module-level function (per camera lists;
# the bench and the profile time them separately): ``locate_and_classify`` (§4, §5.2 step 1),
# ``database_pose`` (step 2, 10-NN), ``global_placement`` (step 2, 6-DOF IK),
# ``pose_assisted_centroids`` + ``ik_round`` (steps 3 + 4, run from every start of
# ``starts_of`` and ``ik_passes - 1`` more times, all in the one loop of ``rounds``),
# ``frame_validity`` and ``white_balance_refit`` (step 5).
