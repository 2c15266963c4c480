"""The stereo filter's live frame (issue 21: image line + blobs + filter step <= 8 ms, N = 1000,
320x240 pair): ``stereo_pf.live`` per frame with the host-side compiled calls (the blob
tracker's triangulation, the capture colours' maps) on a second CPU device
(``jaxmocap._config.enable_side_device``) against the same calls on the filter step's device,
passes interleaved in the same run; with Azad's HSV line and with the capture's colours
(``pf.colors.masks``). Also the parts: the compiled filter step alone, ``observe`` alone, and
``observe`` dispatched right after a filter step (what the overlap sees). The estimates with
and without the side device are compared (bit-identical expected: the same programs).

Run: python -m benchmarks.bench_stereo_live
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from jaxmocap._config import enable_side_device, side_device

HAS_SIDE = enable_side_device()  # before anything starts JAX's backend

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).parent / "experiments"))
from azad_render import config, load  # noqa: E402

from benchmarks._common import Row, sized, time_call, write_results  # noqa: E402
from jaxmocap import blobs  # noqa: E402
from jaxmocap.pf import colors as pc  # noqa: E402
from jaxmocap.segment import HSVInterval, SegmentParams  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402
from jaxmocap.trackers import stereo_pf as sp  # noqa: E402

CLIP, FRAMES = "humanoid3d_punch", 40


def _use_side(on: bool) -> None:
    """Route the host-side compiled calls to the side device (on) or the default device."""
    fn = side_device if on else (lambda: None)
    blobs.side_device = fn
    pc.side_device = fn


def _live_pass(params, frames, t0):
    stamps, qs = [], []
    for _t, est in sp.live(params, jax.random.key(0), iter(frames)):
        if est is not None:
            qs.append(np.asarray(jax.block_until_ready(est.q)))
        stamps.append(time.perf_counter())
    return np.diff(stamps[t0 + 1 :]) * 1e3, np.stack(qs)


def _rows(label: str, params, d, passes: int, n: int) -> tuple[list[Row], list[str]]:
    frames = list(d["frames"])
    frame = d["frames"][5]
    obs = sp.observe_sequence(params, d["frames"])
    first = jax.tree.map(lambda a: a[0], obs)
    state, _ = sp.init(params, jax.random.key(0), first)
    step_fn = sp.compile_step(params)
    step_fn(state, first)
    t0 = sp.anchor_frame(obs)
    rows, notes = [], []
    times = {True: [], False: []}
    qs = {}
    for on in (True, False):  # warm-up passes (compile on both devices)
        _use_side(on)
        _, qs[on] = _live_pass(params, frames, t0)
    for _ in range(passes):  # interleaved
        for on in (True, False):
            _use_side(on)
            dt, q = _live_pass(params, frames, t0)
            times[on].append(dt)
            assert np.array_equal(q, qs[on])
    same = np.array_equal(qs[True], qs[False])
    diff = float(np.max(np.abs(qs[True] - qs[False])))
    notes.append(f"{label}: estimates with / without the side device bit-identical: {same} "
                 f"(max |q diff| {diff:.1e} over {len(qs[True])} frames)")  # fmt: skip
    for on in (True, False):
        t = np.concatenate(times[on])
        where = "host-side calls on the side CPU device" if on else "all calls on one device"
        rows.append(Row(f"live stream per frame ({label}), stereo_pf.live, N = 1000, 320x240",
                        where, float(np.median(t)), float(np.min(t)), len(t)))  # fmt: skip
    # the parts, with the side device on
    _use_side(True)
    bs = {"s": blobs.init(sp.BLOB_PARAMS)}

    def observe():
        o, bs["s"] = sp.observe(params, frame, bs["s"])
        return o

    rows.append(Row(f"filter step alone ({label}), compile_step", "jit", *time_call(
        lambda: step_fn(state, first), n=n), n))  # fmt: skip
    for on in (True, False):
        _use_side(on)
        where = "side device" if on else "one device"
        rows.append(Row(f"observe alone ({label}): image line + blobs + support maps", where,
                        *time_call(observe, n=n), n))  # fmt: skip
        after = []
        for _ in range(n):
            out = step_fn(state, first)
            t1 = time.perf_counter()
            observe()
            after.append((time.perf_counter() - t1) * 1e3)
            jax.block_until_ready(out)
        rows.append(Row(f"observe dispatched right after a filter step ({label})", where,
                        float(np.median(after)), float(np.min(after)), n))  # fmt: skip
        rows.append(Row(f"whole frame sequential ({label}): observe + compiled step", where,
                        *time_call(lambda: step_fn(state, observe()), n=n), n))  # fmt: skip
    _use_side(True)
    return rows, notes


def main() -> None:
    load0 = os.getloadavg()
    if not HAS_SIDE:
        raise SystemExit("bench_stereo_live: JAX has one CPU device; run it in a fresh process")
    n = sized(full=50, quick=5)
    passes = sized(full=4, quick=1)
    d = load(CLIP, FRAMES)
    cams = make_cameras(config(CLIP, FRAMES), jnp.float32)
    seg = SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))
    hsv = sp.make_params(cams, images=sp.Images(segment=seg))
    rows, notes = _rows("Azad's HSV line", hsv, d, passes, n)
    colors = pc.calibrate_from_frames(list(d["frames"][:, 0]))
    captured = sp.make_params(cams, images=sp.Images(segment=seg, colors=colors))
    r, s = _rows("capture colours", captured, d, passes,
                 n)  # fmt: skip
    rows += r
    notes += s
    load1 = os.getloadavg()
    summary = notes + [
        "Issue 21 target: whole live frame <= 8 ms (image line + blobs + filter step).",
        "Load average (1, 5, 15 min) at the start "
        + ", ".join(f"{x:.2f}" for x in load0)
        + ", at the end "
        + ", ".join(f"{x:.2f}" for x in load1)
        + " (2 cores).",
    ]
    path = write_results("bench_stereo_live", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    main()
