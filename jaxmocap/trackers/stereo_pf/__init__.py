"""The stereo particle-filter tracker of Azad, Ude, Asfour & Dillmann (2007).

Files, one per stage: :mod:`.params` (settings, ``make_params``, state), :mod:`.swivel`
(elbow-swivel jumps for any shoulder), :mod:`.observation`
(the host's image line and blobs), :mod:`.filter` (initialisation, the jitted step, the scan),
:mod:`.sequence` (live loops and whole sequences), :mod:`.checks` (per-frame validity, reach),
:mod:`.adapt` (on-line colour adaptation), :mod:`.head` (the head as a fitted sphere),
:mod:`.search` (guided search for missed blobs), :mod:`.hands` (the hands gated by the
particle cloud's prediction) and :mod:`.parts` (per-part colours, the seeded search).

Per stereo frame (320x240 pair in the paper, §V):

1. **image processing line** on the host (OpenCV, :func:`jaxmocap.segment.segment_cv`, both
   images): blur, HSV, skin and shirt masks, gradient of the foreground, spread edge map g;
2. **hands and head** (§IV): skin blobs matched across the pair, triangulated and tracked with
   a linear motion model (:mod:`jaxmocap.blobs`) -> c_head, c_lhand, c_rhand and a valid mask;
3. **particle filter** (§II, §III-D), one jitted call: resample, first-order motion model with
   adaptive Gaussian noise (:mod:`jaxmocap.pf`), then weigh each of the N = 1000 particles
   with p(z|s) = p_g'(left) p_g'(right) p_d' (:class:`jaxmocap.pf.cues.StereoLikelihood`).

The state is the 14-DOF configuration of §I (root 6, shoulders 3+3, elbows 1+1;
:func:`jaxmocap.body.stereo_dofs`); any subset of the body's DOFs can be filtered, the others
are held at ``default_q``. Estimates are the weighted particle mean.

**Automatic initialisation** (§V, Fig. 4: "no initial configuration is given"): particles are
drawn from a broad prior -- the root placed so that the model's head lies on the triangulated
head, a random turn about the vertical in +-``INIT_YAW`` and small tilts, arm joints uniform in
their limits -- and refined by ``len(init_betas)`` annealing layers (Deutscher et al. 2000) on
the first frame (in :func:`track`: the first frame with a triangulated head). When no head is
triangulated within :data:`START_WAIT` frames (skin the colour model does not find), the
filter starts from what it has (:mod:`.start`, beyond the paper): the shirt silhouette of both
views places the torso, else the mean of the hand blobs stands in for the head. Tracking runs
one Condensation step per frame (Azad §II), or ``len(step_betas)`` annealing layers per frame
when ``step_betas`` has several entries (better search, one likelihood pass per layer).

**Guided proposal** (an extension beyond the paper, :class:`Proposals` ``guided=True``, the
default; ``guided=False`` is Azad's filter): after the prediction, half of the particles take
two damped minimum-norm Gauss-Newton steps on the distance cue's residuals f_i(s) - c_i
(missing points masked) toward the triangulated head and hands
(:class:`jaxmocap.pf.guided.GuidedProposal`): the directions the points do not fix (the
elbow swivel, the torso's turn about the head-hands configuration) keep their random noise and
are decided by the edge cue. The importance weights are not corrected for this proposal (nor
is anything corrected in Azad's filter). With the two extensions below it lowers the mean
joint error on the held-out clips from Azad's filter's 17.4 / 17.5 / 7.1 cm to 10.8 / 7.8 /
3.1 cm (punch / dance_b / turn_left0, ``docs/results/stereo_pf.md``) for ~4 ms per frame.

**Out-of-image contours and hidden hands** (also beyond the paper, on by default):
contour samples outside the image read the constant ``edge_outside`` instead of Azad's zero
padding, so a limb that truly leaves the image (a punch) is not pulled back in; and the
*hand-support cue* (:func:`jaxmocap.pf.cues.support_loglik`) keeps a hand without a
triangulated point off plain background -- it is hidden behind the shirt, inside a skin blob,
or outside the image -- which holds a hand hidden behind the torso during a turn.

**Elbow-swivel jumps** (beyond the paper, on by default; :class:`SwivelProposal`):
each frame 10% of the particles have their arms turned, each with probability 1/2, by an angle
uniform in [-pi, pi) about the line from the shoulder to the hand. The hand does not move, so
the distance cue is unchanged and the edge cue chooses the side of the elbow: a filter that
initialised on the wrong side (a single-colour silhouette cannot tell the sides apart in some
poses) crosses over within a few frames once the images tell them apart. Any shoulder of
three or more filtered revolute hinges swivels (:mod:`.swivel`: dm_control's CMU clavicle +
humerus included).
``make_params(cams, **AZAD_FILTER)`` is Azad's filter.

**Fixed-lag smoothing** (offline, :func:`run` / :func:`track` ``smooth_lag``): the estimate of
frame t from the particles of frame t + L (:mod:`jaxmocap.pf.smooth`).

Sequences with precomputed observations run as one ``lax.scan`` (:func:`run`); a live loop
calls :func:`step` per frame (host image processing + one jitted filter step), or runs
:func:`live` over a stream of frames: the jitted step with the parameters closed over
(:func:`compile_step`), and the host's image processing of frame t+1 overlapping the filter
step of frame t (JAX dispatches asynchronously). Deterministic given the key.
"""

from __future__ import annotations

from jaxmocap.pf.cues import Observation
from jaxmocap.trackers.stereo_pf.checks import (
    REACH_MARGIN,
    frame_validity,
    hand_reach,
    head_residual,
)
from jaxmocap.trackers.stereo_pf.filter import (
    COMPILER_OPTIONS,
    compile_step,
    filter_step,
    init,
    init_top_level,
    online_frame,
    run,
    run_top_level,
)
from jaxmocap.trackers.stereo_pf.observation import (
    observe,
    observe_sequence,
    support_map,
)
from jaxmocap.trackers.stereo_pf.params import (
    AZAD_FILTER,
    BLOB_PARAMS,
    N_PARTICLES,
    SIGMA_MAX,
    SIGMA_MIN,
    SWIVEL_FRACTION,
    SYNTH_SKIN_HSV,
    Cues,
    HandParams,
    Images,
    Initialisation,
    Motion,
    Proposals,
    SeedParams,
    StereoEstimate,
    StereoPFParams,
    SwivelProposal,
    TrackerState,
    make_params,
)
from jaxmocap.trackers.stereo_pf.sequence import (
    anchor_frame,
    live,
    step,
    track,
)
from jaxmocap.trackers.stereo_pf.start import START_WAIT, Start, start_frame

__all__ = [
    "AZAD_FILTER",
    "BLOB_PARAMS",
    "COMPILER_OPTIONS",
    "Cues",
    "HandParams",
    "Images",
    "Initialisation",
    "Motion",
    "N_PARTICLES",
    "Observation",
    "Proposals",
    "REACH_MARGIN",
    "SIGMA_MAX",
    "SIGMA_MIN",
    "START_WAIT",
    "SWIVEL_FRACTION",
    "SYNTH_SKIN_HSV",
    "SeedParams",
    "Start",
    "StereoEstimate",
    "StereoPFParams",
    "SwivelProposal",
    "TrackerState",
    "anchor_frame",
    "compile_step",
    "filter_step",
    "frame_validity",
    "hand_reach",
    "head_residual",
    "init",
    "init_top_level",
    "live",
    "make_params",
    "observe",
    "observe_sequence",
    "online_frame",
    "run",
    "run_top_level",
    "start_frame",
    "step",
    "support_map",
    "track",
]
