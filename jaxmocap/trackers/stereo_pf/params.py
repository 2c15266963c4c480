"""Parameters and state of the stereo particle filter (Azad et al. 2007): the paper's settings
and the extensions' defaults, the elbow-swivel proposal, :class:`StereoPFParams` and
:func:`make_params`, :class:`TrackerState`, :class:`StereoEstimate`."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from jaxmocap import blobs as bloblib
from jaxmocap import pf
from jaxmocap.body import (
    BodyModel,
    default_body,
    keypoint_index,
    keypoints,
    stereo_dofs,
)
from jaxmocap.body.chain import ROOT_DOFS
from jaxmocap.camera import Camera, stack_cameras
from jaxmocap.errors import InputError
from jaxmocap.pf import cues as cuelib
from jaxmocap.pf import guided as pf_guided
from jaxmocap.pf.colors import ADAPT_MAX_SPREAD, ADAPT_RATE, CaptureColors
from jaxmocap.pf.cues import StereoLikelihood
from jaxmocap.segment import SegmentParams
from jaxmocap.trackers.stereo_pf.checks import (
    hand_reach,
)
from jaxmocap.trackers.stereo_pf.learned import LearnedParts
from jaxmocap.trackers.stereo_pf.swivel import SwivelProposal, swivel_arms

N_PARTICLES = 1000  # Azad §V
# Adaptive noise range (std per frame at 25-30 Hz; Azad give none): root translation (m), root
# rotation (rad), arm joints (rad). The minimum keeps the set alive, the maximum re-finds a
# lost limb within a few frames.
SIGMA_MIN = (0.004, 0.01, 0.02)
SIGMA_MAX = (0.02, 0.05, 0.15)
# Energy e = -max log p (both edge cues + distance cue) at which the noise is 63% of the way to
# the maximum: a good fit of a 320x240 pair has a mean edge value ~0.6 per camera, i.e.
# e ~ 2 x 0.4 / (2 sigma_g^2) = 10 with sigma_g = 0.2.
ERROR_SCALE = 15.0
DAMPING = 0.5  # first-order motion model: s_t = s_{t-1} + delta (s_{t-1} - s_{t-2}) + noise
# Initialisation prior (radians / metres) and annealing schedule
INIT_YAW = 0.8  # the subject roughly faces the cameras: turn about the vertical in +-0.8 rad
INIT_TILT = 0.1  # std of the lean about the horizontal axes
INIT_ROOT_STD = 0.03  # std of the root position around the head-derived one
INIT_BETAS = tuple(float(b) for b in np.geomspace(0.02, 1.0, 12))  # 12 annealing layers
# Annealing layers per tracked frame (Deutscher et al. 2000, Azad's ref. [4]): (1.0,) is the
# plain Condensation step of Azad §II; more layers search the 14-D space better at a cost of one
# likelihood evaluation of the N particles per layer (see docs/results/stereo_pf.md).
STEP_BETAS = (1.0,)
# Distance-cue-guided proposal (an extension beyond Azad, jaxmocap.pf.guided): after the
# prediction a fraction of the particles takes a few damped minimum-norm Gauss-Newton steps
# toward the triangulated head / hands; the metric's unit per DOF is the noise maximum.
GUIDED = True
GUIDED_INIT = False  # the proposal also in the initialisation's annealing (see make_params)
# Hand-support cue (ours, jaxmocap.pf.cues.support_loglik): a hand without a triangulated point
# is hidden (behind the shirt or in a skin blob) or outside the image, not on plain background.
USE_SUPPORT = True
# Elbow-swivel jumps (SwivelProposal; not in the paper): the fraction of the particles whose
# arms are turned about their shoulder-hand lines each frame. 3 clips x 4 keys (stereo_pf.md):
# dance_b 10.6 -> 7.8 cm, punch 11.4 -> 10.8, turn 3.1 -> 3.1 (0.05 and 0.2 tried as well).
SWIVEL_FRACTION = 0.1
# The tracker's blob tracker hands the distance cue a hand carried by its motion model for one
# frame only (then missing: the support cue holds it), instead of Azad's max_coast = 8 frames:
# a hand hidden behind the torso in a turn coasted 11-52 cm off and pulled the arm with it.
# bloblib.BlobParams() is Azad's carry (observe_sequence(..., blob_params=BlobParams())).
BLOB_PARAMS = bloblib.BlobParams(report_coast=1)
FALLBACK_ROOT = (0.0, 0.0, 0.9)  # root prior mean when no skin blob is seen in frame 0
# A skin interval for jaxmocap.synth's scenes: their beige wall and floor (H 16-19, S 52) fall
# inside segment.SKIN_HSV_*; rendered skin has S ~ 80. Pass SegmentParams(skin=...) with it.
SYNTH_SKIN_HSV = ((5, 65, 60), (25, 230, 255))
# The head as a sphere fitted to its skin outline in both views (jaxmocap.trackers.stereo_pf.head)
# instead of the skin centroid: off (docs/results/stereo_pf_round2.md)
HEAD_SPHERE = False
# The hands from a search gated by the particle cloud's prediction (jaxmocap.trackers.stereo_pf.
# hands) instead of the blob line's. Dev split, 3 seeds: 29.18 -> 26.79 cm (mostly pf_09, the
# seeds' ranges touch), test split not yet run: off (docs/results/stereo_pf_hands.md)
HAND_SEARCH = False


@dataclasses.dataclass(frozen=True)
class SeedParams:
    """Settings of the per-part colours and their seeded search
    (:mod:`jaxmocap.trackers.stereo_pf.parts`)."""

    window_m: float = 0.15  # search radius around the projected prediction, metres
    gate_m: float = 0.2  # the triangulated point within this of the prediction, metres
    threshold: float = 16.0  # squared shading-invariant distance to the part's colour
    min_area: int = 3  # px per view (as the prediction-guided search, stereo_pf.search)
    max_epipolar_px: float = 3.0
    head_exclude_m: float = 0.12  # hands: the head's disc (measured, else predicted) is left out
    velocity_damping: float = 0.5  # weight of the last estimated velocity in the prediction
    # per skin part (head, left hand, right hand): a part found replaces the blob line's
    # measurement of it (True) or is searched only where the blob line missed it (False, the
    # default). Dev split (pf_03, 50 frames): the search's hands replacing the blob line's
    # were within 8 cm of the true hand on 0 of 45 / 49 frames (the filter's hands were off,
    # the window around them held the face's rim or the shirt's); a head replaced by the
    # search pulled the filter off and its head then confirmed the search
    replace: tuple[bool, bool, bool] = (False, False, False)
    # the update's two-illuminant relight (parts.update_colours); dev: off (the hands, seen on
    # few frames, were relit by every frame's fit of the head and shirt and drifted to the
    # colour cube's bound)
    relight: bool = False


@dataclasses.dataclass(frozen=True)
class HandParams:
    """Thresholds of the gated hand search (:mod:`jaxmocap.trackers.stereo_pf.hands`)."""

    window_m: float = 0.12  # window radius around the predicted hand, metres ...
    spread_k: float = 1.0  # ... plus this x the particle cloud's spread of the hand
    max_window_m: float = 0.25  # ... at most
    gate_m: float = 0.10  # a window candidate within this of the predicted hand, metres ...
    gate_k: float = 0.5  # ... plus this x the spread
    head_exclude_m: float = 0.11  # the head's disc, metres at its depth, cut out of the windows
    neck_exclude_m: float = 0.07  # the neck's disc (between head and shoulders' centre)
    min_area: int = 3  # px of a candidate component per view
    max_epipolar_px: float = 3.0
    velocity_damping: float = 0.5  # weight of the mean's last velocity in the prediction
    motion: bool = False  # the motion map adds candidates (motion_map)
    motion_threshold: float = 30.0  # sum of |RGB differences| of a moving pixel (0..765)
    blob_hands: bool = True  # the blob line's hand points are candidates too

    def __post_init__(self):
        for name in ("window_m", "max_window_m", "gate_m", "max_epipolar_px",
                     "motion_threshold"):
            if not getattr(self, name) > 0:
                raise InputError(f"HandParams.{name}: expected > 0, got {getattr(self, name)!r}")
        for name in ("spread_k", "gate_k", "head_exclude_m", "neck_exclude_m"):
            if not getattr(self, name) >= 0:
                raise InputError(f"HandParams.{name}: expected >= 0, got {getattr(self, name)!r}")
        if not 0 <= self.velocity_damping <= 1:
            raise InputError(f"HandParams.velocity_damping: expected a value in [0, 1], got "
                             f"{self.velocity_damping!r}")


# keypoints the gated hand search needs (by role)
HAND_KEYPOINTS = ("head", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand")


class Motion(eqx.Module):
    """The particle set and its motion model (Azad §II, §V).

    * ``n_particles`` (static: the set's shape): particles, 1000 in Azad §V;
    * ``damping`` (traced): first-order motion model ``s_t = s_{t-1} + damping (s_{t-1} -
      s_{t-2}) + noise``;
    * ``error_scale`` (traced): the energy ``e = -max log p`` (both edge cues + distance cue)
      at which the adaptive noise is 63% of the way from its minimum to its maximum (Azad give
      none): a good fit of a 320x240 pair has a mean edge value ~0.6 per camera, i.e. e ~ 2 x
      0.4 / (2 sigma_g^2) = 10 with sigma_g = 0.2;
    * ``step_betas`` (traced; their number static): annealing layers per tracked frame
      (Deutscher et al. 2000, Azad's ref. [4]): ``(1.0,)`` is the plain Condensation step of
      Azad §II; more layers search the 14-D space better at a cost of one likelihood
      evaluation of the N particles per layer (docs/results/stereo_pf.md).
    """

    n_particles: int = eqx.field(static=True, default=N_PARTICLES)
    damping: float = DAMPING
    error_scale: float = ERROR_SCALE
    step_betas: tuple[float, ...] = STEP_BETAS


class Cues(eqx.Module):
    """The likelihood's cues (Azad §III; :class:`~jaxmocap.pf.cues.StereoLikelihood`).

    * ``use_distance``, ``use_region`` (static): the distance cue to the triangulated head and
      hands (on) and the region cue (off, as Azad's final filter);
    * ``edge_form`` (static): ``"sad"`` (p_g', the paper's final choice) or ``"ssd"`` (p_g);
    * ``sigma_g``, ``sigma_d``, ``sigma_r``, ``sigma_s`` (traced): the widths of the edge,
      distance, region and hand-support cues (:mod:`jaxmocap.pf.cues`);
    * ``points_per_line`` (static: a shape): samples per projected contour line;
    * ``edge_outside`` (traced; ``None``, static: Azad's zero padding, which pulls a limb that
      leaves the image back in): the edge value of contour samples outside the image;
    * ``use_support`` (static; not in the paper): the hand-support cue
      (:func:`jaxmocap.pf.cues.support_loglik`): a hand without a triangulated point is hidden
      (behind the shirt or in a skin blob) or outside the image, not on plain background; on
      every hand with ``support_all``; :func:`observe` then adds the support map to the
      observation;
    * ``hand_swap`` (static; not in the paper): each particle pairs its hands with the
      triangulated ones in the nearer pairing, robust to swapped blob identities;
    * ``sigma_depth`` (traced; ``None``, static: ``sigma_d`` in every direction, as Azad's): the
      distance cue's width along each triangulated point's line of sight (not in the paper;
      :mod:`jaxmocap.pf.cues`): a short baseline measures depth coarsely, so depth is left to
      the edge cue and the body's bone lengths as far as the point does not hold it
      (``sigma_d * cuelib.DEPTH_RATIO``: the dev split's measured ratio; issue 39 decision 3,
      docs/results/stereo_pf_depth.md).
    """

    use_distance: bool = eqx.field(static=True, default=True)
    use_region: bool = eqx.field(static=True, default=False)
    edge_form: str = eqx.field(static=True, default="sad")
    sigma_g: float = cuelib.SIGMA_G
    sigma_d: float = cuelib.SIGMA_D
    sigma_r: float = cuelib.SIGMA_R
    sigma_s: float = cuelib.SIGMA_S
    points_per_line: int = eqx.field(static=True, default=cuelib.POINTS_PER_LINE)
    edge_outside: float | None = cuelib.EDGE_OUTSIDE
    use_support: bool = eqx.field(static=True, default=USE_SUPPORT)
    support_all: bool = eqx.field(static=True, default=False)
    hand_swap: bool = eqx.field(static=True, default=False)
    sigma_depth: float | None = None


class Proposals(eqx.Module):
    """Where the particles go besides the motion model (extensions beyond Azad's paper;
    ``Proposals(guided=False, swivel_fraction=0.0)`` is Azad's filter).

    * ``guided`` (static): the distance-cue-guided proposal (:mod:`jaxmocap.pf.guided`): after
      the prediction ``guided_fraction`` (static: a count of particles) of the particles take
      ``guided_steps`` (static) damped minimum-norm Gauss-Newton steps (Levenberg damping
      ``guided_damping``, m^2, traced) toward the triangulated head / hands; the metric's unit
      per DOF is the noise maximum;
    * ``guided_init`` (static): the guided proposal also in the initialisation's annealing;
    * ``swivel_fraction`` (static: a count of particles): the fraction of the particles whose
      elbows jump about their shoulder-hand lines each frame (:class:`SwivelProposal`; 0
      disables). 3 clips x 4 keys (stereo_pf.md): dance_b 10.6 -> 7.8 cm, punch 11.4 -> 10.8,
      turn 3.1 -> 3.1 (0.05 and 0.2 tried as well).
    """

    guided: bool = eqx.field(static=True, default=GUIDED)
    guided_fraction: float = eqx.field(static=True, default=pf_guided.GUIDED_FRACTION)
    guided_steps: int = eqx.field(static=True, default=pf_guided.GUIDED_STEPS)
    guided_damping: float = pf_guided.GUIDED_DAMPING
    guided_init: bool = eqx.field(static=True, default=GUIDED_INIT)
    swivel_fraction: float = eqx.field(static=True, default=SWIVEL_FRACTION)


class Initialisation(eqx.Module):
    """The automatic initialisation's prior and annealing (Azad give none; :func:`init`).

    * ``init_betas`` (traced; their number static): the annealing layers, 12 from 0.02 to 1;
    * ``init_yaw`` (traced): the turn about the vertical, uniform in +-``init_yaw`` rad (the
      subject roughly faces the cameras; pi: any facing). The lean's std :data:`INIT_TILT`, the
      root's :data:`INIT_ROOT_STD` around the head-derived position.
    """

    init_betas: tuple[float, ...] = INIT_BETAS
    init_yaw: float = INIT_YAW


class Images(eqx.Module):
    """The host image line: skin and shirt segmentation, blobs, colour models (Azad §IV and
    this library's options; all host-side, outside the jitted step).

    * ``segment``: Azad's HSV intervals (:class:`~jaxmocap.segment.SegmentParams`; ``None``:
      the defaults; :data:`SYNTH_SKIN_HSV` for :mod:`jaxmocap.synth`'s scenes);
    * ``colors``: the capture's skin and shirt colour model (:mod:`jaxmocap.pf.colors`) used
      for the skin map and the foreground instead of ``segment``'s intervals;
    * ``plausible_blobs``: drop hand candidates farther from the head than the arms reach
      (:func:`hand_reach`, by keypoint roles) before they reach the distance cue;
    * ``skin_grow`` (px, needs ``colors``): the skin map grown into a relaxed skin map by up to
      this many pixels (:func:`jaxmocap.pf.colors.hysteresis_masks`);
    * ``adapt_colors`` (needs ``colors``): re-fit the skin and shirt classes on line from the
      tracked head and body on the frames where the filter agrees with the triangulated head
      (:mod:`jaxmocap.trackers.stereo_pf.adapt`; one frame weighs ``adapt_rate`` /
      ``adapt_shirt_rate``, 0 leaves that class fixed; a class's spread stays within
      ``adapt_spread`` x the fitted one's); :func:`track` then observes the frames with the
      filter alongside;
    * ``part_colours`` (needs ``colors``): a colour state per part (head, each hand, shirt)
      updated from the estimate's render, and each skin part searched near its prediction with
      its own colour (:mod:`jaxmocap.trackers.stereo_pf.parts`; ``seed_params`` its
      :class:`SeedParams`). Off by default: on the dev split of the test world it found no
      more hands within 8 cm and cost ~8x per frame (the module's docstring).
    * ``head_sphere`` (not in the paper): the triangulated head replaced by a sphere of the
      body's head radius fitted to the outline of the head's skin region in both views
      (:mod:`jaxmocap.trackers.stereo_pf.head`), instead of the lit skin's centroid;
    * ``hand_search`` (not in the paper): once the filter runs, the hands handed to the
      distance cue come from a search gated by the particle cloud's prediction (windows around
      the predicted hands without the head and neck, skin components paired across the views,
      each hand within its arm's reach of its predicted shoulder; the blob line's hands are
      candidates too) and a hand that passes no gate is missing
      (:mod:`jaxmocap.trackers.stereo_pf.hands`; ``hand_motion``: the motion map adds
      candidates; ``hand_params``: its :class:`~.hands.HandParams`);
    * ``observer`` (not in the paper): the learned observation layer
      (:class:`~jaxmocap.trackers.stereo_pf.learned.LearnedParts`): skin, shirt and the named
      head and hands from a model trained on the project's own renders instead of ``segment``
      / ``colors`` and the blob tracker (:mod:`jaxmocap.trackers.stereo_pf.learned`).
    """

    segment: SegmentParams | None = None
    colors: CaptureColors | None = None
    plausible_blobs: bool = eqx.field(static=True, default=False)
    skin_grow: int = eqx.field(static=True, default=0)
    adapt_colors: bool = eqx.field(static=True, default=False)
    adapt_rate: float = eqx.field(static=True, default=ADAPT_RATE)
    adapt_shirt_rate: float = eqx.field(static=True, default=ADAPT_RATE)
    adapt_spread: float = eqx.field(static=True, default=ADAPT_MAX_SPREAD)
    part_colours: bool = eqx.field(static=True, default=False)
    seed_params: SeedParams | None = eqx.field(static=True, default=None)
    head_sphere: bool = eqx.field(static=True, default=HEAD_SPHERE)
    hand_search: bool = eqx.field(static=True, default=HAND_SEARCH)
    hand_motion: bool = eqx.field(static=True, default=False)
    hand_params: HandParams | None = eqx.field(static=True, default=None)
    observer: LearnedParts | None = None


# make_params(cams, **AZAD_FILTER): the paper's filter, without this library's extensions
AZAD_FILTER = dict(cues=Cues(edge_outside=None, use_support=False),
                   proposals=Proposals(guided=False, swivel_fraction=0.0))


class StereoPFParams(eqx.Module):
    """Everything fixed over a sequence: the likelihood (body, cameras, cues), the particle
    filter's box and noise, the image pipeline's parameters and the initialisation prior."""

    likelihood: StereoLikelihood
    filter: pf.PFParams
    segment: SegmentParams
    prior_lower: Float[Array, " d"]  # uniform prior box of the joints (subset DOFs)
    prior_upper: Float[Array, " d"]
    init_betas: Float[Array, " m"]
    step_betas: Float[Array, " k"]  # annealing layers per frame; (1.0,) = plain step
    head_rest: Float[Array, " 3"]  # head keypoint in the root frame at default_q
    init_yaw: Float[Array, ""]
    init_tilt: Float[Array, ""]
    init_root_std: Float[Array, ""]
    fallback_root: Float[Array, " 3"]
    n_particles: int = eqx.field(static=True)
    guided_init: bool = eqx.field(static=True, default=False)
    # the capture's colour model (jaxmocap.pf.colors) instead of the HSV intervals; None: Azad's
    colors: CaptureColors | None = None
    # blob plausibility (hand_reach): (near, far) head-to-hand distances, m; None: off
    reach: tuple[float, float] | None = eqx.field(static=True, default=None)
    # on-line colour adaptation (jaxmocap.trackers.stereo_pf.adapt): (skin rate, shirt rate)
    # of one frame's pixels, spread cap; None: the colour model stays as fitted
    adapt: tuple[float, float, float] | None = eqx.field(static=True, default=None)
    # hysteresis skin (pf.colors.hysteresis_masks): px grown into the relaxed skin map; 0: off
    skin_grow: int = eqx.field(static=True, default=0)
    # per-part colours and the seeded search (jaxmocap.trackers.stereo_pf.parts): its
    # thresholds; None: off
    part_colours: SeedParams | None = eqx.field(static=True, default=None)
    # the head as a fitted sphere (jaxmocap.trackers.stereo_pf.head): (radius m, offset m from
    # its centre to the head keypoint); None: the skin centroid
    head_sphere: tuple[float, tuple[float, float, float]] | None = eqx.field(
        static=True, default=None)
    # the gated hand search (jaxmocap.trackers.stereo_pf.hands): its HandParams; None: the blob
    # line's hands
    hand_search: HandParams | None = eqx.field(static=True, default=None)
    # the learned observation layer (jaxmocap.trackers.stereo_pf.learned); None: Azad's line
    observer: LearnedParts | None = None

    @property
    def dofs(self) -> np.ndarray:
        return np.asarray(self.likelihood.dofs)

    @property
    def model(self) -> BodyModel:
        return self.likelihood.model

    def full_q(self, s: Float[Array, "*b d"]) -> Float[Array, "*b n_dof"]:
        base = jnp.broadcast_to(
            self.likelihood.default_q.astype(s.dtype), s.shape[:-1] + (self.model.n_dof,)
        )
        return base.at[..., self.dofs].set(s)


def make_params(
    cams: Sequence[Camera] | Camera,
    model: BodyModel | None = None,
    dofs: Sequence[int] | np.ndarray | None = None,
    *,
    motion: Motion | None = None,
    cues: Cues | None = None,
    proposals: Proposals | None = None,
    initialisation: Initialisation | None = None,
    images: Images | None = None,
    default_q: ArrayLike | None = None,
    dtype=jnp.float32,
) -> StereoPFParams:
    """Tracker parameters for a calibrated stereo pair ``cams`` (left, right).

    ``dofs``: indices of the filtered DOFs (default the 14 of :func:`stereo_dofs`; the six root
    DOFs must be among them); the others stay at ``default_q`` (default the rest pose). The
    settings come in groups, ``None`` the group's defaults (the paper's constants and this
    library's measured extensions): :class:`Motion`, :class:`Cues`, :class:`Proposals`,
    :class:`Initialisation`, :class:`Images`. Azad's filter: ``**AZAD_FILTER``. The numbers
    the jitted step reads become arrays of ``dtype`` (a new value runs the compiled
    :func:`filter_step` as it is); switches and shapes are static.
    """
    motion = Motion() if motion is None else motion
    cues = Cues() if cues is None else cues
    proposals = Proposals() if proposals is None else proposals
    initialisation = Initialisation() if initialisation is None else initialisation
    images = Images() if images is None else images
    n_particles = motion.n_particles
    colors, skin_grow = images.colors, images.skin_grow
    part_colours, adapt_colors = images.part_colours, images.adapt_colors
    adapt_rate, adapt_shirt_rate = images.adapt_rate, images.adapt_shirt_rate
    adapt_spread = images.adapt_spread
    guided_fraction, guided_steps = proposals.guided_fraction, proposals.guided_steps
    guided_damping, swivel_fraction = proposals.guided_damping, proposals.swivel_fraction
    model = default_body() if model is None else model
    cams = stack_cameras(list(cams)) if isinstance(cams, (list, tuple)) else cams
    if cams.K.ndim != 3:
        raise InputError(
            f"stereo_pf.make_params: cams: expected a list of cameras, got {cams.K.shape}"
        )
    dofs = stereo_dofs(model) if dofs is None else np.sort(np.asarray(dofs, dtype=np.int64))
    if not set(range(ROOT_DOFS)) <= set(dofs.tolist()) or dofs.max() >= model.n_dof:
        raise InputError(
            f"stereo_pf.make_params: dofs: expected indices < {model.n_dof} including the root "
            f"DOFs 0..5, got {dofs.tolist()}"
        )
    if (skin_grow != 0 and colors is None) or not isinstance(skin_grow, int) or skin_grow < 0:
        raise InputError(f"stereo_pf.make_params: skin_grow: expected an int >= 0 with the "
                         f"capture's colours (Images(colors=...)), got {skin_grow!r}")
    if images.observer is not None and (colors is not None or part_colours or adapt_colors
                                        or images.hand_search or skin_grow):
        raise InputError("stereo_pf.make_params: observer: the learned parts replace the "
                         "capture's colours and the colour options built on them (colors, "
                         "skin_grow, adapt_colors, part_colours, hand_search); give one")
    if part_colours and colors is None:
        raise InputError("stereo_pf.make_params: part_colours: needs the capture's colour model "
                         "(Images(colors=...)) for the parts' calibrated start")
    if part_colours and adapt_colors:
        raise InputError("stereo_pf.make_params: part_colours and adapt_colors both adapt the "
                         "colours; give one")
    if adapt_colors and colors is None:
        raise InputError("stereo_pf.make_params: adapt_colors: needs the capture's colour model "
                         "(Images(colors=...)); the HSV intervals are not adapted")
    if not (0.0 <= adapt_rate <= 1.0 and 0.0 <= adapt_shirt_rate <= 1.0 and adapt_spread > 0):
        raise InputError("stereo_pf.make_params: adapt_rate / adapt_shirt_rate / adapt_spread: "
                         f"expected in [0, 1] / [0, 1] / > 0, got {adapt_rate} / "
                         f"{adapt_shirt_rate} / {adapt_spread}")
    if n_particles < 2:
        raise InputError(f"stereo_pf.make_params: n_particles: expected >= 2, got {n_particles}")
    if cues.sigma_depth is not None and not float(cues.sigma_depth) > 0:
        raise InputError(f"stereo_pf.make_params: sigma_depth: expected > 0 (m) or None, got "
                         f"{cues.sigma_depth}")
    default_q = (
        jnp.zeros(model.n_dof, dtype) if default_q is None else jnp.asarray(default_q, dtype)
    )
    if default_q.shape != (model.n_dof,):
        raise InputError(
            f"stereo_pf.make_params: default_q: expected shape ({model.n_dof},), got "
            f"{default_q.shape}"
        )
    lik = StereoLikelihood(
        model=model, limbs=cuelib.limb_model(model), cams=cams, default_q=default_q,
        sigma_g=jnp.asarray(cues.sigma_g, dtype), sigma_d=jnp.asarray(cues.sigma_d, dtype),
        sigma_r=jnp.asarray(cues.sigma_r, dtype), dofs=tuple(int(i) for i in dofs),
        points_per_line=cues.points_per_line, edge_form=cues.edge_form,
        use_distance=cues.use_distance, use_region=cues.use_region,
        sigma_s=jnp.asarray(cues.sigma_s, dtype), use_support=cues.use_support,
        support_all=cues.support_all, hand_swap=cues.hand_swap,
        edge_outside=None if cues.edge_outside is None else jnp.asarray(cues.edge_outside, dtype),
        sigma_depth=None if cues.sigma_depth is None else jnp.asarray(cues.sigma_depth, dtype),
    )  # fmt: skip
    lower = np.asarray(model.chain.lower, np.float64)[dofs]
    upper = np.asarray(model.chain.upper, np.float64)[dofs]
    kind = np.where(dofs < 3, 0, np.where(dofs < ROOT_DOFS, 1, 2))
    if not 0.0 <= guided_fraction <= 1.0:
        raise InputError(
            f"stereo_pf.make_params: guided_fraction: expected in [0, 1], got {guided_fraction}"
        )
    if guided_steps < 1 or guided_damping <= 0:
        raise InputError(
            "stereo_pf.make_params: guided_steps / guided_damping: expected >= 1 / > 0, got "
            f"{guided_steps} / {guided_damping}"
        )
    proposal = None
    if proposals.guided:
        proposal = pf.GuidedProposal(
            residual=lik.distance_residual,
            linearize=lik.distance_linearize,
            scale=jnp.asarray(np.asarray(SIGMA_MAX)[kind], dtype),
            damping=jnp.asarray(guided_damping, dtype),
            fraction=float(guided_fraction),
            n_steps=int(guided_steps),
        )
    if not 0.0 <= swivel_fraction <= 1.0:
        raise InputError(
            f"stereo_pf.make_params: swivel_fraction: expected in [0, 1], got {swivel_fraction}"
        )
    arms, fits = (swivel_arms(model, dofs, np.asarray(default_q)) if swivel_fraction > 0
                  else ((), None))
    if arms:  # no filtered shoulder: nothing to turn
        proposal = SwivelProposal(
            inner=proposal, model=model, default_q=default_q, dofs=tuple(int(i) for i in dofs),
            arms=arms, fraction=float(swivel_fraction), fits=fits,
        )  # fmt: skip
    filt = pf.PFParams(
        loglik=lik,
        lower=jnp.asarray(lower, dtype),
        upper=jnp.asarray(upper, dtype),
        sigma_min=jnp.asarray(np.asarray(SIGMA_MIN)[kind], dtype),
        sigma_max=jnp.asarray(np.asarray(SIGMA_MAX)[kind], dtype),
        damping=jnp.asarray(motion.damping, dtype),
        error_scale=jnp.asarray(motion.error_scale, dtype),
        boundary="reflect",
        proposal=proposal,
    )
    q0 = default_q.at[:ROOT_DOFS].set(0.0)
    head_rest = keypoints(model, q0)[keypoint_index(model, "head")[0]]
    return StereoPFParams(
        likelihood=lik,
        filter=filt,
        segment=SegmentParams() if images.segment is None else images.segment,
        prior_lower=jnp.asarray(np.where(np.isfinite(lower), lower, 0.0), dtype),
        prior_upper=jnp.asarray(np.where(np.isfinite(upper), upper, 0.0), dtype),
        init_betas=jnp.asarray(initialisation.init_betas, dtype),
        step_betas=jnp.asarray(motion.step_betas, dtype),
        head_rest=head_rest.astype(dtype),
        init_yaw=jnp.asarray(initialisation.init_yaw, dtype),
        init_tilt=jnp.asarray(INIT_TILT, dtype),
        init_root_std=jnp.asarray(INIT_ROOT_STD, dtype),
        fallback_root=jnp.asarray(FALLBACK_ROOT, dtype),
        n_particles=int(n_particles),
        guided_init=bool(proposals.guided and proposals.guided_init),
        colors=colors,
        reach=hand_reach(model) if images.plausible_blobs else None,
        adapt=(float(adapt_rate), float(adapt_shirt_rate), float(adapt_spread)) if adapt_colors
        else None,
        skin_grow=int(skin_grow),
        part_colours=_seed_params(images.seed_params) if part_colours else None,
        head_sphere=_head_sphere(model) if images.head_sphere else None,
        hand_search=_hand_params(images, model, adapt_colors or part_colours),
        observer=images.observer,
    )


def _hand_params(images, model, other):
    if not images.hand_search:
        if images.hand_motion or images.hand_params is not None:
            raise InputError("stereo_pf.make_params: hand_motion / hand_params: set "
                             "hand_search=True for them")
        return None
    if other:
        raise InputError("stereo_pf.make_params: hand_search runs its own observation loop; "
                         "give it without adapt_colors / part_colours")
    hp = HandParams() if images.hand_params is None else images.hand_params
    if not isinstance(hp, HandParams):
        raise InputError(f"stereo_pf.make_params: hand_params: expected a HandParams, got "
                         f"{type(hp).__name__}")
    if not set(HAND_KEYPOINTS) <= set(model.keypoint_names):
        raise InputError(f"stereo_pf.make_params: hand_search needs the keypoints "
                         f"{list(HAND_KEYPOINTS)}; the body has {list(model.keypoint_names)}; "
                         "give hand_search=False")
    return dataclasses.replace(hp, motion=hp.motion or images.hand_motion)


def _head_sphere(model):
    from jaxmocap.trackers.stereo_pf.head import head_sphere

    radius, offset = head_sphere(model)
    return float(radius), tuple(float(x) for x in offset)


def _seed_params(seed):
    if seed is None:
        return SeedParams()
    if not isinstance(seed, SeedParams):
        raise InputError(f"stereo_pf.make_params: seed_params: expected a SeedParams, got "
                         f"{type(seed).__name__}")
    return seed


class TrackerState(eqx.Module):
    """The particle set and the PRNG key of the next frame."""

    particles: pf.PFState
    key: PRNGKeyArray


class StereoEstimate(eqx.Module):
    """Per-frame output: full pose vectors (weighted mean and best particle), diagnostics.

    With :func:`run`'s ``smooth_lag`` L > 0, ``q`` is the fixed-lag smoothed mean
    (:func:`jaxmocap.pf.smooth.fixed_lag_smooth`) and ``q_filtered`` the filter's own mean
    (None otherwise)."""

    q: Float[Array, "*t n_dof"]
    q_best: Float[Array, "*t n_dof"]
    best_loglik: Float[Array, "*t"]
    ess: Float[Array, "*t"]
    degenerate: Bool[Array, "*t"]
    q_filtered: Float[Array, "*t n_dof"] | None = None
