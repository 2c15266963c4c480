"""The one tracker driver: set-up, the frame loop, diagnostics and interrupts, shared by
``jaxmocap track``, ``jaxmocap experiment`` and ``jaxmocap demo``.

Any tracker is driven through a small **frame protocol** (:class:`FrameTracker`):

* ``start(frames)`` — called once with the first readable frame (uint8 (n_cams, H, W, 3)
  RGB) before it is stepped: set up the state (white balance, particle set, ...);
* ``step(frames) -> FrameResult`` — one frame: the pose ``q`` (n_dof,) of the body model
  (:mod:`jaxmocap.body` layout) the tracker estimated for this frame, valid or not (NaN only
  where it has no estimate: e.g. a filter not started yet), whether it is ``valid`` (the
  tracker's rule says the estimate can be trusted), a flat ``diagnostics`` dict of floats
  whose keys are fixed by ``diagnostic_names`` (the signals behind the flag), and the
  tracker's own ``output`` (host arrays) for callers that want more;
* ``draw(frames, result) -> frames`` — RGB images with what the tracker saw drawn over them.

Two adapters implement it: :class:`ShirtFrameTracker` (Wang et al. 2011,
:mod:`jaxmocap.trackers.shirt`; its parameters from :func:`shirt_params`) and
:class:`StereoPFFrameTracker` (Azad et al. 2007, :mod:`jaxmocap.trackers.stereo_pf`, live).
:func:`drive` runs the frame loop over any iterable of ``(t, frames or None)`` (an unreadable
instant is not stepped: its row is NaN; every stepped frame keeps its estimate beside its
validity flag) with a progress bar, per-frame timing and interrupt
handling (an interrupt after the first tracked frame ends the loop and keeps what was tracked).
:func:`stereo_offline` is the stereo filter's offline run (observations on the host, the
filter as one scan), with its cold and warm timings.
"""

from __future__ import annotations

import functools
import sys
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any, NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np

from jaxmocap.body import BodyModel, keypoints
from jaxmocap.camera import Camera, stack_cameras
from jaxmocap.errors import InputError
from jaxmocap.io.overlay import OVERLAY_ALPHA, draw_skeleton

MAX_PARTICLES = 100_000
# The joints each tracker observes, on which its accuracy is reported (demo, experiment cells):
# the shirt's patches see the shoulders, elbows, wrists, neck and chest (Wang Fig. 9); Azad's
# filter reports shoulders, elbows and hands (the 14-DOF arm model).
SHIRT_JOINTS = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist",
                "neck", "chest")
PF_JOINTS = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand")

# The shirt tracker's per-frame validity rules (``shirt.validity_rule`` keywords): "paper"
# (§5.2: the agreement gate engages once step 1 classifies 20% of a crop); "footage" and
# "learned", calibrated on the dev split of the independent test world: the tracker's own gate
# at agreement 0.2 always and 20 measured patch centroids (no hold: the frame's own estimate),
# and the reported flag's centroids, per-camera centroid residual (crop sides) and recall --
# "footage" for the colour model (docs/results/shirt.md; world_shirt.toml's "validated"),
# "learned" for the learned observation (learned.md: 94% of test's > 15 cm frames flagged).
_GATE = {"min_agreement": 0.2, "gate_min_fraction": 0.0, "min_patches": 20, "hold_invalid": False}
VALIDITY = {
    "paper": {},
    "footage": {**_GATE, "report_patches": 26, "max_residual": 0.053, "min_recall": 0.31},
    "learned": {**_GATE, "report_patches": 30, "max_residual": 0.045, "min_recall": 0.6},
}


class FrameResult(NamedTuple):
    """One frame's answer of a tracker (module docstring)."""

    q: np.ndarray
    valid: bool
    diagnostics: dict[str, float]
    output: Any = None


@runtime_checkable
class FrameTracker(Protocol):
    """The frame protocol the driver runs (module docstring)."""

    body: BodyModel
    diagnostic_names: tuple[str, ...]

    def start(self, frames: np.ndarray) -> None: ...

    def step(self, frames: np.ndarray) -> FrameResult: ...

    def draw(self, frames: np.ndarray, result: FrameResult) -> np.ndarray: ...


_keypoints_jit = jax.jit(keypoints)


def _skeleton_views(body: BodyModel, cams: list[Camera], images, result: FrameResult):
    kp = np.asarray(_keypoints_jit(body, jnp.asarray(result.q)), np.float64) \
        if result.valid else np.full((len(body.keypoint_names), 3), np.nan)
    return np.stack([draw_skeleton(f, c, kp, body.keypoint_names)
                     for f, c in zip(images, cams, strict=True)])


# ----------------------------------------------------------------------------- shirt


def shirt_diagnostics(out, W: np.ndarray, names: list[str], gate) -> dict[str, float]:
    """The colour-shirt tracker's per-frame diagnostics (host arrays of a
    :class:`~jaxmocap.trackers.shirt.ShirtOutput`): per camera ``c`` step 1's classified
    fraction ``fraction_c``, the white balance's diagonal ``W_c_rr/gg/bb``, ``reference_used_c``,
    ``reference_added_c``, and how well the final pose explains the crop, ``residual_c``,
    ``recall_c``, ``coverage_c`` (:class:`~jaxmocap.trackers.shirt.FrameSignals`); ``agreement``
    (render vs step-1 classification), ``patches`` (centroids measured, all cameras), the
    frame's ``blend_distance``, ``db_spread`` (rad), ``root_jump`` (m) (FrameSignals); ``gate``,
    the tracker's own validity (what its state kept: the smoother's weights, issue 49; the
    reported ``valid`` may follow a stricter rule)."""
    d = {}
    for c, n in enumerate(names):
        d[f"fraction_{n}"] = float(out.fraction[c])
        for i, k in enumerate(("rr", "gg", "bb")):
            d[f"W_{n}_{k}"] = float(W[c, i, i])
        d[f"reference_used_{n}"] = float(out.used_reference[c])
        d[f"reference_added_{n}"] = float(out.added_reference[c])
        d[f"residual_{n}"] = float(out.signals.residual[c])
        d[f"recall_{n}"] = float(out.signals.recall[c])
        d[f"coverage_{n}"] = float(out.signals.coverage[c])
    d["agreement"] = float(out.agreement)
    d["patches"] = float(np.sum(out.visible))
    d.update({k: float(getattr(out.signals, k)) for k in ("blend_distance", "db_spread",
                                                           "root_jump")}, gate=float(gate))
    patch_colours = getattr(out, "relight_ok", None) is not None
    if patch_colours:
        for c, n in enumerate(names):
            d[f"colour_updated_{n}"] = float(out.colour_updated[c])
            d[f"relight_ok_{n}"] = float(out.relight_ok[c])
            d[f"relight_rms_{n}"] = float(out.relight_rms[c])
    return {k: d[k] for k in shirt_diagnostic_names(names, patch_colours)}  # in column order


def shirt_diagnostic_names(names: Sequence[str], patch_colours: bool = False) -> tuple[str, ...]:
    """The keys of :func:`shirt_diagnostics`, in column order; with ``patch_colours`` per
    camera also the patches whose colour state was updated, whether the relight was applied
    (a rejected one is 0) and its RMS log residual. Cached: every frame's row shares these
    strings (a long capture's rows grew by ~1 KB a frame of new key strings, issue 52)."""
    return _diagnostic_names(tuple(names), bool(patch_colours))


@functools.cache
def _diagnostic_names(names: tuple[str, ...], patch_colours: bool) -> tuple[str, ...]:
    cam = lambda *ks: [f"{k}_{n}" for k in ks for n in names]  # noqa: E731
    return (*cam("fraction"), *[f"W_{n}_{c}" for n in names for c in ("rr", "gg", "bb")],
            *cam("reference_used", "reference_added", "residual", "recall", "coverage"),
            "agreement", "patches", "blend_distance", "db_spread", "root_jump", "gate",
            *(cam("colour_updated", "relight_ok", "relight_rms") if patch_colours else ()))


def shirt_params(color, body: BodyModel, garment, cams: list[Camera], db, cov=None,
                 validity="paper", announce: bool = True, **settings):
    """The colour-shirt tracker's parameters for a capture (:func:`shirt.make_params
    <jaxmocap.trackers.shirt.make_params>`): the garment's patch anchors, the covariances
    (default: the bundled trained ones transferred by role to ``body``, said on stderr when
    some DOFs have no counterpart) and ``validity``, a rule of :data:`VALIDITY` by name or a
    :class:`~jaxmocap.trackers.shirt.ValidityRule`; ``settings`` (the groups ``search``,
    ``rounds``, ``colours``, ``ablations``) go to ``make_params``."""
    from jaxmocap.ik import anchors_from_garment
    from jaxmocap.trackers import shirt

    if color.n_colors != garment.n_colours:
        raise InputError(f"--colors: the colour model has {color.n_colors} colours, the "
                         f"shirt has {garment.n_colours}; fit one colour per shirt colour")
    if cov is None:
        cov, defaults = shirt.covariances_for_body(body)
        if defaults and announce:
            print(f"jaxmocap track: IK covariances transferred by role from the bundled "
                  f"body; {len(defaults)} DOFs without a counterpart use the defaults: "
                  f"{', '.join(defaults)} (train your own: --ik-cov)", file=sys.stderr)
    if isinstance(validity, str):
        validity = shirt.validity_rule(**VALIDITY[validity])
    return shirt.make_params(color, body, garment, stack_cameras(cams),
                             anchors_from_garment(body, garment), cov, db, validity=validity,
                             **settings)


class ShirtFrameTracker:
    """Wang et al. 2011 through the frame protocol (:mod:`jaxmocap.trackers.shirt`), over
    :func:`shirt.compile_step <jaxmocap.trackers.shirt.compile_step>` (the shipped program
    where it applies). A frame's ``q`` is its own IK solution (``ShirtOutput.q_frame``), also
    where the tracker holds its last valid pose (``hold_invalid``) and reports it invalid.
    ``background``: an OpenCV MOG2 foreground mask per camera and frame
    (:class:`jaxmocap.color.BackgroundSubtractor`). ``color`` / ``room``: the colour model
    and the room's colours, for :meth:`draw`'s classified pixels. Diagnostics:
    :func:`shirt_diagnostics`."""

    def __init__(self, params, W0: np.ndarray | None, cams: list[Camera], names: list[str],
                 color=None, room=None, background: bool = False, announce: bool = True):
        from jaxmocap.trackers import shirt

        self._shirt = shirt
        self.params = params
        self.body = params.body
        self.cams, self.names, self.color = cams, names, color
        self.W0 = np.stack([np.eye(3)] * len(cams)) if W0 is None else W0
        self.diagnostic_names = shirt_diagnostic_names(names, params.colours.patch_colours)
        self.background = background
        self.announce = announce
        self.state = None
        self._step = None
        self._subs = None
        self._classify = None
        if color is not None:
            from jaxmocap.color import classify

            self._classify = jax.jit(lambda W, im: classify(
                color, W, im, gain=color.shading, background=room)[0])

    def start(self, frames: np.ndarray) -> None:
        dt = self.params.cams.K.dtype
        self.state = self._shirt.init(self.params, jnp.asarray(self.W0, dt),
                                      jnp.zeros(self.body.n_dof, dt))
        if self._step is None:
            self._step = self._shirt.compile_step(self.params, announce=self.announce)
        if self.background:
            from jaxmocap.color import BackgroundSubtractor

            self._subs = [BackgroundSubtractor() for _ in self.names]

    def step(self, frames: np.ndarray) -> FrameResult:
        if self._subs is None:
            self.state, out = self._step(self.state, frames)
        else:
            masks = np.stack([s.apply(frames[i]) for i, s in enumerate(self._subs)])
            self.state, out = self._step(self.state, frames, masks)
        out, W, gate = jax.device_get((out, self.state.W, self.state.valid))
        return FrameResult(np.asarray(out.q_frame, np.float64), bool(out.valid),
                           shirt_diagnostics(out, W, self.names, gate), out)

    def checkpoint(self) -> dict:
        """What carries over to the next frame, on the host (for ``track``'s journal)."""
        if self._subs is not None:
            raise ValueError("ShirtFrameTracker.checkpoint: OpenCV's background subtractors "
                             "cannot be saved")
        return {"state": jax.device_get(self.state)}

    def restore(self, checkpoint: dict) -> None:
        """Continue from a :meth:`checkpoint` (after :meth:`start`): the same state, bit for
        bit."""
        self.state = jax.tree.map(jnp.asarray, checkpoint["state"])

    def draw(self, frames: np.ndarray, result: FrameResult) -> np.ndarray:
        """Classified pixels tinted with their colour's mean (current W), then the skeleton."""
        images = []
        for c in range(len(self.cams)):
            img = frames[c]
            if self._classify is not None:
                mean = np.clip(np.asarray(self.color.mean), 0, 255).astype(np.float64)
                ids = np.asarray(self._classify(self.state.W[c], jnp.asarray(frames[c])))
                img = frames[c].astype(np.float64)
                hit = ids > 0
                img[hit] = (1 - OVERLAY_ALPHA) * img[hit] + OVERLAY_ALPHA * mean[ids[hit] - 1]
                img = img.astype(np.uint8)
            images.append(img)
        return _skeleton_views(self.body, self.cams, images, result)


# ----------------------------------------------------------------------------- stereo PF


class StereoPFFrameTracker:
    """Azad et al. 2007 through the frame protocol (see :mod:`jaxmocap.trackers.stereo_pf`):
    the filter initialises on the first frame with a triangulated head, or, when none is
    triangulated within :data:`~jaxmocap.trackers.stereo_pf.start.START_WAIT` frames, on the
    first frame with a shirt silhouette in both views (else with a hand blob;
    :mod:`jaxmocap.trackers.stereo_pf.start`, as the offline ``track``). Frames before it are
    invalid, ``waiting_for_head`` 1, and have no estimate: NaN; then one step per frame (the
    filter's mean, valid or not). The start is announced once (``announce``).

    Diagnostics: ``ess`` (effective sample size), ``best_loglik``, ``degenerate``,
    ``spread_root_m`` (particle spread of the root position, metres, sqrt of the trace of its
    covariance), ``blobs`` (head/hands triangulated this frame, 0..3), ``waiting_for_head``
    (not started yet), ``head_residual_m`` (model head to the triangulated head; empty when not
    triangulated), ``calibrating`` (``pf_colors="auto"``: the first
    :data:`jaxmocap.pf.colors.AUTO_FRAMES` frames calibrate the capture's colours and are not
    tracked), ``start_anchor`` (what the running filter was started from: 1 the head, 2 the
    shirt silhouette, 3 hand blobs; 0 not started; :data:`START_ANCHOR_CODES`). A frame is
    valid when :func:`jaxmocap.trackers.stereo_pf.frame_validity` says so."""

    diagnostic_names = ("ess", "best_loglik", "degenerate", "spread_root_m", "blobs",
                        "waiting_for_head", "head_residual_m", "calibrating", "start_anchor")

    def __init__(self, cams: list[Camera], n_particles: int, seed: int, skin: str = "default",
                 body: BodyModel | None = None, pf_colors: str | None = None,
                 skin_grow: int = 0, swivel: float | None = None, announce: bool = True,
                 cue_widths: dict | None = None):
        from jaxmocap import blobs
        from jaxmocap.segment import HSVInterval, SegmentParams
        from jaxmocap.trackers import stereo_pf

        if len(cams) != 2:
            raise InputError(f"--method pf needs exactly 2 cameras (a stereo pair), "
                             f"cameras.json has {len(cams)}")
        if not 10 <= n_particles <= MAX_PARTICLES:
            raise InputError(f"--particles must be between 10 and {MAX_PARTICLES:,}, got "
                             f"{n_particles}")
        self._pf, self._blobs = stereo_pf, blobs
        segment, colors = None, None
        self._calibration: list[np.ndarray] | None = None
        if pf_colors == "auto":
            self._calibration = []
        elif pf_colors is not None:
            from jaxmocap.pf.colors import load_capture_colors

            colors = load_capture_colors(pf_colors)
        elif skin == "synth":
            lo, hi = stereo_pf.SYNTH_SKIN_HSV
            segment = SegmentParams(skin=HSVInterval(jnp.asarray(lo), jnp.asarray(hi)))
        proposals = (stereo_pf.Proposals() if swivel is None
                     else stereo_pf.Proposals(swivel_fraction=swivel))
        self._make = lambda colors: stereo_pf.make_params(
            cams, model=body, motion=stereo_pf.Motion(n_particles=n_particles),
            cues=stereo_pf.Cues(hand_swap=colors is not None, **(cue_widths or {})),
            proposals=proposals,
            images=stereo_pf.Images(segment=segment, colors=colors,
                                    plausible_blobs=colors is not None,
                                    skin_grow=skin_grow if colors is not None else 0))
        self.params = self._make(colors)
        self._step = stereo_pf.compile_step(self.params)
        self.body = self.params.model
        self.cams = cams
        self.key = jax.random.PRNGKey(seed)
        self.state = None
        self.announce = announce
        self.anchor: str | None = None  # what the running filter started from

    def start(self, frames: np.ndarray) -> None:
        from jaxmocap.trackers.stereo_pf.start import Starter

        self.blob_state = self._blobs.init(self._pf.BLOB_PARAMS)
        self.state, self.anchor = None, None
        self._starter = Starter(self.params)
        self._t = -1

    def step(self, frames: np.ndarray) -> FrameResult:
        self._t += 1
        if self._calibration is not None:
            from jaxmocap.pf.colors import AUTO_FRAMES, calibrate_from_frames

            self._calibration.append(np.asarray(frames[0]))
            if len(self._calibration) < AUTO_FRAMES:
                return FrameResult(np.full(self.body.n_dof, np.nan), False,
                                   {"calibrating": 1.0, "start_anchor": 0.0})
            self._auto_colors = calibrate_from_frames(self._calibration)
            self.params = self._make(self._auto_colors)
            self._step = self._pf.compile_step(self.params)
            self._calibration = None
            self._starter.params = self.params
        obs, self.blob_state = self._pf.observe(self.params, frames, self.blob_state)
        valid_blobs = np.asarray(obs.valid)
        if self.state is None:
            got = self._starter(obs)
            if got is None:  # no head yet (and, after the wait, no shirt nor hand either)
                return FrameResult(np.full(self.body.n_dof, np.nan), False,
                                   {"waiting_for_head": 1.0, "blobs": float(valid_blobs.sum()),
                                    "start_anchor": 0.0})
            self.anchor, start = got
            self.state, est = self._pf.init_top_level(self.params, self.key, obs, start)
            if self.announce:
                print(f"jaxmocap track: the stereo filter started on frame {self._t} from "
                      f"{START_ANCHOR_WORDS[self.anchor]}")
        else:
            self.state, est = self._step(self.state, obs)
        est, parts = jax.device_get((est, self.state.particles.particles))
        root = np.asarray(parts[:, :3], np.float64)
        q = np.asarray(est.q, np.float64)
        res = self._pf.head_residual(self.params, q[None], np.asarray(obs.points)[None],
                                     valid_blobs[None])[0]
        ok = bool(np.all(np.isfinite(q))) and bool(
            self._pf.frame_validity(self.params, q[None], np.asarray(obs.points)[None],
                                    valid_blobs[None])[0])
        d = {"ess": float(est.ess), "best_loglik": float(est.best_loglik),
             "degenerate": float(est.degenerate),
             "spread_root_m": float(np.sqrt(np.trace(np.cov(root.T)))),
             "blobs": float(np.sum(valid_blobs)), "waiting_for_head": 0.0,
             "head_residual_m": float(res), "calibrating": 0.0,
             "start_anchor": float(START_ANCHOR_CODES[self.anchor])}
        return FrameResult(q, ok, d, est)

    def checkpoint(self) -> dict:
        """What carries over to the next frame, on the host (``track``'s journal): the filter
        state (particles, RNG key), blob tracks, start search, frame count and the
        ``pf_colors="auto"`` calibration (its frames so far, or the colours from them)."""
        return jax.device_get({
            "state": self.state, "blob_state": self.blob_state, "anchor": self.anchor,
            "t": self._t, "waited": self._starter.waited, "calibration": self._calibration,
            "auto_colors": getattr(self, "_auto_colors", None)})

    def restore(self, checkpoint: dict) -> None:
        """Continue from a :meth:`checkpoint` (after :meth:`start`), bit for bit."""
        if checkpoint["auto_colors"] is not None:  # calibrated before the checkpoint
            self._auto_colors = checkpoint["auto_colors"]
            self.params = self._starter.params = self._make(self._auto_colors)
            self._step = self._pf.compile_step(self.params)
        state = checkpoint["state"]  # the filter's state lives on the device, the blob
        self.state = None if state is None else jax.tree.map(jnp.asarray, state)
        self.blob_state = checkpoint["blob_state"]  # tracks on the host (float64)
        self._calibration, self.anchor = checkpoint["calibration"], checkpoint["anchor"]
        self._t, self._starter.waited = int(checkpoint["t"]), int(checkpoint["waited"])

    def draw(self, frames: np.ndarray, result: FrameResult) -> np.ndarray:
        return _skeleton_views(self.body, self.cams, frames, result)


# The stereo filter's start anchors (jaxmocap.trackers.stereo_pf.start.ANCHORS) as the
# ``start_anchor`` diagnostics column codes them (0: not started) and as the run says them.
START_ANCHOR_CODES = {"head": 1, "shirt": 2, "hands": 3, "none": 4}
START_ANCHOR_WORDS = {
    "head": "the triangulated head",
    "shirt": "the shirt silhouette (no head triangulated in its first frames)",
    "hands": "the hand blobs (no head triangulated in its first frames, no shirt region)",
    "none": "no anchor (nothing seen: the fallback root)",
}


class StereoRun(NamedTuple):
    """:func:`stereo_offline`'s result: the estimates (T, ...), the observations fed to the
    filter, the frame it initialised on, the filter's state after the initialisation, and
    timings (s): ``observe_first`` / ``observe``
    (the host line, cold and warm), ``filter_first`` / ``filter`` (initialisation + scan,
    cold (compile) and warm; warm ones only with ``repeat``); ``anchor``: what the
    initialisation started from (:mod:`jaxmocap.trackers.stereo_pf.start`: ``"head"``,
    ``"shirt"``, ``"hands"`` or ``"none"``)."""

    estimate: Any
    observations: Any
    init_frame: int
    initial_state: Any
    timings: dict[str, float]
    anchor: str = "head"


def stereo_offline(params, key, frames: np.ndarray,
                   observe: Callable[[], Any] | None = None, smooth_lag: int = 0,
                   repeat: bool = False, start_from_head: bool = True) -> StereoRun:
    """The stereo filter over a whole sequence offline: observations on the host (``observe()``;
    default :func:`stereo_pf.observe_sequence <jaxmocap.trackers.stereo_pf.observe_sequence>`
    with the tracker's blob settings), automatic initialisation on the start frame
    (:func:`~jaxmocap.trackers.stereo_pf.start.start_frame`: a head within the first frames,
    else the shirt silhouette or the hands; ``start_from_head=False``: never the head), the
    filter over
    every frame as one scan (``smooth_lag``: fixed-lag smoothing). With ``repeat`` the host
    line and the filter run a second time, compiled, for the steady-state timings."""
    from jaxmocap.trackers import stereo_pf as sp
    from jaxmocap.trackers.stereo_pf.start import start_frame

    if observe is None:
        def observe():
            return sp.observe_sequence(params, frames)

    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    obs = observe()
    timings["observe_first"] = time.perf_counter() - t0
    if repeat:
        t0 = time.perf_counter()
        observe()
        timings["observe"] = time.perf_counter() - t0
    t_init, anchor, start = start_frame(params, obs, heads=start_from_head)

    def filt():
        state, _ = sp.init_top_level(params, key, jax.tree.map(lambda a: a[t_init], obs), start)
        _, est = sp.run_top_level(params, state, obs, smooth_lag)
        return state, jax.block_until_ready(est)

    t0 = time.perf_counter()
    state, est = filt()
    timings["filter_first"] = time.perf_counter() - t0
    if repeat:
        t0 = time.perf_counter()
        filt()
        timings["filter"] = time.perf_counter() - t0
    return StereoRun(est, obs, t_init, state, timings, anchor)


# ----------------------------------------------------------------------------- the loop


class Tracked(NamedTuple):
    """What :func:`drive` produced: q (T, n_dof) every frame's estimate, valid or not (NaN
    rows where none: an unreadable instant, a tracker without an estimate), valid (T,), the
    diagnostics rows ``(t, read, valid, diagnostics)``, the seconds each stepped frame took
    (T,; NaN where not stepped), the tracker's outputs (``keep_outputs``; else empty) and the
    interrupt that ended the loop early (None: it ran to the end of the input; else "SIGINT"
    or "SIGTERM")."""

    q: np.ndarray
    valid: np.ndarray
    rows: list
    times: np.ndarray
    outputs: list
    interrupted: str | None


def _plain_interrupt(err: BaseException) -> str | None:
    return "SIGINT" if isinstance(err, KeyboardInterrupt) else None


def drive(tracker: FrameTracker, frames: Iterable[tuple[int, np.ndarray | None]],
          n_frames: int | None = None, on_frame: Callable[..., bool | None] | None = None,
          progress: bool = True, interrupt: Callable[[BaseException], str | None] = None,
          keep_outputs: bool = False, desc: str = "tracking", prefix: tuple | None = None,
          restore: Any = None) -> Tracked:
    """Drive ``tracker`` over ``frames`` (``(t, frames)`` pairs, ``None`` for an unreadable
    instant, which is not stepped and gets a NaN row). ``on_frame(t, frames, result)`` is
    called after every instant (``result`` None where unreadable); it returns True to stop.

    An exception during the loop that ``interrupt(err)`` names as an interrupt ("SIGINT" /
    "SIGTERM"; default: any ``KeyboardInterrupt``) ends it, keeping every frame completed
    before it (``interrupted``); one before any frame was stepped propagates (set-up or
    compiling the first step: nothing to keep).

    Resuming (``track --resume``): ``prefix`` = ``(qs, valid, rows, times)`` of the frames
    tracked before, ``restore`` the tracker's checkpoint after them (given to its ``restore``
    after ``start``); ``frames`` yields only the instants after them."""
    from tqdm import tqdm

    interrupt = interrupt or _plain_interrupt
    n_dof = tracker.body.n_dof
    qs, valid, rows, times = ([list(a) for a in prefix] if prefix is not None
                              else ([], [], [], []))
    outputs = [None] * len(qs) if keep_outputs else []
    started = False
    interrupted = None
    try:
        for t, fr in tqdm(frames, total=n_frames, disable=not progress, desc=desc,
                          unit="frame"):
            res = None
            if fr is None:
                qs.append(np.full(n_dof, np.nan))
                valid.append(False)
                rows.append((t, False, False, {}))
                times.append(np.nan)
            else:
                if not started:
                    tracker.start(fr)
                    if restore is not None:
                        tracker.restore(restore)
                    started = True
                t0 = time.perf_counter()
                res = tracker.step(fr)
                times.append(time.perf_counter() - t0)
                qs.append(np.asarray(res.q, np.float64))
                valid.append(res.valid)
                rows.append((t, True, res.valid, res.diagnostics))
                if keep_outputs:
                    outputs.append(res.output)
            if on_frame is not None and on_frame(t, fr, res):
                break
    except BaseException as err:  # e.g. a live capture ended with Ctrl-C
        interrupted = interrupt(err)
        if interrupted is None:
            raise
        n = min(len(qs), len(valid), len(rows), len(times))  # a half-appended frame is dropped
        if not any(r[1] for r in rows[:n]):
            raise  # set-up or compiling the first step: nothing tracked, nothing written
        del qs[n:], valid[n:], rows[n:], times[n:], outputs[n:]
    return Tracked(np.array(qs).reshape(-1, n_dof), np.array(valid, bool), rows,
                   np.asarray(times, np.float64), outputs, interrupted)


def diagnostics_table(rows: list, names: Sequence[str]) -> np.ndarray:
    """The diagnostics of :class:`Tracked` ``rows`` as a (T, len(names)) float array, NaN
    where a frame has no such value (unreadable, or a tracker that skipped it)."""
    out = np.full((len(rows), len(names)), np.nan)
    for i, (_, _, _, d) in enumerate(rows):
        for j, k in enumerate(names):
            if k in d:
                out[i, j] = d[k]
    return out


def sequence_frames(frames: np.ndarray):
    """``(t, frames[t])`` for an in-memory sequence (T, n_cams, H, W, 3): :func:`drive`'s input."""
    return ((t, frames[t]) for t in range(frames.shape[0]))


__all__ = [
    "PF_JOINTS",
    "SHIRT_JOINTS",
    "START_ANCHOR_CODES",
    "START_ANCHOR_WORDS",
    "VALIDITY",
    "FrameResult",
    "FrameTracker",
    "ShirtFrameTracker",
    "StereoPFFrameTracker",
    "StereoRun",
    "Tracked",
    "diagnostics_table",
    "drive",
    "sequence_frames",
    "shirt_diagnostic_names",
    "shirt_diagnostics",
    "shirt_params",
    "stereo_offline",
]
