"""Running the step: ``step`` (jit, traced once per set-up), ``compile_step`` (the shipped
program where it applies, :mod:`.export`), ``run`` (a live Python loop) and ``run_scan``
(a whole sequence under ``lax.scan``)."""

from __future__ import annotations

import sys
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, UInt8

from jaxmocap.trackers.shirt.frame import _step
from jaxmocap.trackers.shirt.params import ShirtOutput, ShirtParams, ShirtState

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
    """One frame of Wang et al. §4–5 for every camera (the frame walk:
    :mod:`jaxmocap.trackers.shirt`); jit-compiled once
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
    params: ShirtParams, announce: bool = True,
) -> Callable[..., tuple[ShirtState, ShirtOutput]]:
    """:func:`step` with ``params`` bound, for frame loops: ``(state, frames, masks=None) ->
    (state, output)``, the same results.

    On its first call without masks it takes the program shipped for the demo's set-up when
    that applies (:mod:`jaxmocap.trackers.shirt.export`: the step traced ahead of time, so the
    first frame only waits for XLA's compile, ~6 s less on an empty cache); otherwise it says
    why in one line on stderr (unless ``announce`` is off) and traces :func:`step` as usual."""
    from jaxmocap.trackers.shirt import export as shirt_export

    chosen: dict[bool, Callable | None] = {}

    def fn(state, frames, masks=None):
        frames, masks = _checked_inputs(params, frames, masks)
        plain = masks is None
        if plain not in chosen:
            program, why = shirt_export.load(params, state, frames, masks)
            if program is None and announce:
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
