"""Running the filter over a capture: ``step`` (host line + one jitted step), ``compile_step``,
``live`` (host work of frame t+1 beside the step of frame t), ``anchor_frame`` and ``track``
(a whole sequence, automatic initialisation on its start frame, :mod:`.start`)."""

from __future__ import annotations

from collections.abc import Iterable, Iterator

import jax
import numpy as np
from jaxtyping import PRNGKeyArray, UInt8

from jaxmocap import blobs as bloblib
from jaxmocap.pf.cues import Observation
from jaxmocap.trackers.stereo_pf.filter import (
    compile_step,
    filter_step,
    init_top_level,
    run_top_level,
)
from jaxmocap.trackers.stereo_pf.observation import observe, observe_sequence
from jaxmocap.trackers.stereo_pf.params import (
    BLOB_PARAMS,
    StereoEstimate,
    StereoPFParams,
    TrackerState,
)
from jaxmocap.trackers.stereo_pf.start import Starter, start_frame


def step(
    params: StereoPFParams,
    state: TrackerState,
    frame_pair: UInt8[np.ndarray, "2 h w 3"],
    blob_obs: tuple[np.ndarray, np.ndarray],
) -> tuple[TrackerState, StereoEstimate]:
    """One live frame: the image processing line on the host, then one jitted filter step.

    ``blob_obs`` = (points3d (3, 3) m, valid (3,)) from :func:`jaxmocap.blobs.update`.
    """
    obs, _ = observe(params, frame_pair, None, blob_obs)
    return filter_step(params, state, obs)


def live(
    params: StereoPFParams,
    key: PRNGKeyArray,
    frames: Iterable[UInt8[np.ndarray, "2 h w 3"]],
    blob_params: bloblib.BlobParams | None = None,
) -> Iterator[tuple[int, StereoEstimate | None]]:
    """Online tracking of a stream of stereo frames: yields ``(t, estimate)`` for every frame.

    Frames before the start frame yield ``None``: the first with a triangulated head, or after
    :data:`~.start.START_WAIT` frames without one the first with a shirt silhouette or a hand
    (:class:`~.start.Starter`); the tracker initialises on that frame
    (:func:`init`, its estimate is that frame's) and then takes one :func:`compile_step` step
    per frame. Host and device overlap: frame t's filter step is dispatched (asynchronously)
    before frame t-1's estimate is handed out, and frame t+1's image processing and blob
    tracking run on the host while the step computes, so each estimate is yielded one frame
    late (the last one at the end of the stream). The estimates equal those of :func:`init` +
    :func:`filter_step` on the same observations (tested)."""
    step_fn = compile_step(params)
    blob_state = bloblib.init(blob_params or BLOB_PARAMS)
    state: TrackerState | None = None
    pending: tuple[int, StereoEstimate | None] | None = None
    starter = Starter(params)
    for t, pair in enumerate(frames):
        obs, blob_state = observe(params, pair, blob_state)
        if state is None:
            got = starter(obs)
            if got is not None:
                state, est = init_top_level(params, key, obs, got[1])
                out: tuple[int, StereoEstimate | None] = (t, est)
            else:
                out = (t, None)
        else:
            state, est = step_fn(state, obs)
            out = (t, est)
        if pending is not None:
            yield pending
        pending = out
    if pending is not None:
        yield pending


def anchor_frame(observations: Observation) -> int:
    """Azad's frame to initialise on, from the blobs alone: the first whose head is
    triangulated, else the first with any hand / head point, else 0. The blob tracker acquires
    its entities only once it sees three candidates (:mod:`jaxmocap.blobs`), which can take a
    few frames; initialising on a frame without any point would leave the root prior
    unanchored. The trackers (:func:`track`, :func:`live`, the driver) start by
    :func:`~.start.start_frame` instead, which also starts from the shirt silhouette."""
    valid = np.asarray(observations.valid)
    for col in (valid[:, 0], valid.any(axis=1)):
        if col.any():
            return int(np.argmax(col))
    return 0


def track(
    params: StereoPFParams,
    key: PRNGKeyArray,
    frames: UInt8[np.ndarray, "t 2 h w 3"],
    blob_params: bloblib.BlobParams | None = None,
    smooth_lag: int = 0,
) -> StereoEstimate:
    """Track a whole stereo sequence: observations on the host, automatic initialisation on
    the :func:`~.start.start_frame` (a head, else the shirt silhouette or the hands), then the
    filter over frames 0..T-1 in one ``lax.scan`` (``smooth_lag``: see :func:`run`).
    Estimates (T, ...). With ``params.adapt`` the observations come from
    :func:`jaxmocap.trackers.stereo_pf.adapt.observe_adaptive` (the colour model re-fitted on
    line); with ``params.part_colours`` from
    :func:`jaxmocap.trackers.stereo_pf.parts.observe_parts` (per-part colours, seeded search);
    with ``params.hand_search`` from :func:`jaxmocap.trackers.stereo_pf.hands.observe_hands`.
    The filter over them is the same."""
    if params.hand_search is not None:
        from jaxmocap.trackers.stereo_pf.hands import observe_hands

        obs, _ = observe_hands(params, key, frames, blob_params)
    elif params.part_colours is not None:
        from jaxmocap.trackers.stereo_pf.parts import observe_parts

        obs, _ = observe_parts(params, key, frames, blob_params)
    elif params.adapt is not None:
        from jaxmocap.trackers.stereo_pf.adapt import observe_adaptive

        obs, _ = observe_adaptive(params, key, frames, blob_params)
    else:
        obs = observe_sequence(params, frames, blob_params)
    t0, _, start = start_frame(params, obs)
    state, _ = init_top_level(params, key, jax.tree.map(lambda a: a[t0], obs), start)
    _, est = run_top_level(params, state, obs, smooth_lag)
    return est
