"""The stereo filter's capture-colour skin / shirt maps (``pf.colors.masks``, the image line of
``--pf-colors``): the fused XLA evaluation against the direct NumPy one, same run, per 320x240
pair, with the number of pixel decisions where they differ; Azad's fixed HSV line beside them;
and the whole live frame (image line + blobs + compiled filter step, N = 1000) and the live
stream (``stereo_pf.live``) with the capture's colours, direct vs compiled.

Colours: ``calibrate_from_frames`` on camera 0 of the synthetic clip of ``bench_stereo_pf``;
with ``--world DIR`` (a test-world sequence: ``cam0.mp4``, ``cam1.mp4``) also the maps on its
first 40 frame pairs with colours calibrated on its camera 0.
Run: python -m benchmarks.bench_pf_colors [--world /path/to/pf_00]
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent / "experiments"))
from azad_render import config, load  # noqa: E402

from benchmarks._common import Row, sized, time_call, write_results  # noqa: E402
from jaxmocap import blobs  # noqa: E402
from jaxmocap._config import enable_side_device  # noqa: E402
from jaxmocap.pf import colors as pc  # noqa: E402
from jaxmocap.segment import HSVInterval, SegmentParams, segment_cv  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402
from jaxmocap.trackers import stereo_pf as sp  # noqa: E402
from jaxmocap.trackers.stereo_pf import observation as sp_observation  # noqa: E402

CLIP, FRAMES = "humanoid3d_punch", 40


def _read_pairs(folder: Path, n: int) -> np.ndarray:
    caps = [cv2.VideoCapture(str(folder / f"cam{i}.mp4")) for i in (0, 1)]
    pairs = []
    for _ in range(n):
        got = [c.read() for c in caps]
        if not all(ok for ok, _ in got):
            break
        pairs.append([cv2.cvtColor(f, cv2.COLOR_BGR2RGB) for _, f in got])
    return np.asarray(pairs)


def _map_rows(name: str, pairs: np.ndarray, colors: pc.CaptureColors, n: int) -> list[Row]:
    """Per pair: direct vs compiled maps (both images), decisions that differ over all
    pairs, and Azad's HSV line on the same pair."""
    differ, total = 0, 0
    for pair in pairs:
        for img in pair:
            a, b = pc.masks(colors, img, compiled=False), pc.masks(colors, img)
            differ += sum(int(np.sum(x != y)) for x, y in zip(a, b, strict=True))
            total += 2 * a[0].size
    pair = pairs[min(5, len(pairs) - 1)]
    direct = time_call(lambda: [pc.masks(colors, i, compiled=False) for i in pair], n=n)
    fast = time_call(lambda: [pc.masks(colors, i) for i in pair], n=n)
    seg = SegmentParams()
    hsv = time_call(lambda: [segment_cv(seg, i) for i in pair], n=n)
    kernel = f"capture-colour maps (skin, shirt), {pair.shape[2]}x{pair.shape[1]} pair, {name}"
    agree = (f"{differ} of {total} pixel decisions differ from the direct evaluation "
             f"({len(pairs)} pairs x 2 images x 2 maps)")  # fmt: skip
    return [
        Row(kernel, "pf.colors.masks, direct NumPy (compiled=False)", *direct, n),
        Row(kernel, "pf.colors.masks, fused XLA (default)", *fast, n, None,
            f"{agree}; direct/this {direct[0] / fast[0]:.2f}x"),
        Row(kernel, "Azad's fixed HSV line (segment_cv x2, incl. edges)", *hsv, n),
    ]  # fmt: skip


def _frame_rows(d, colors: pc.CaptureColors, n: int) -> list[Row]:
    """Whole live frame and live stream of the stereo filter with the capture's colours."""
    cams = make_cameras(config(CLIP, FRAMES), jnp.float32)
    seg = SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))
    params = sp.make_params(cams, images=sp.Images(segment=seg, colors=colors))
    rows = []
    frame = d["frames"][5]
    obs = sp.observe_sequence(params, d["frames"])
    first = jax.tree.map(lambda a: a[0], obs)
    state, _ = sp.init(params, jax.random.key(0), first)
    step_fn = sp.compile_step(params)
    step_fn(state, first)
    orig = pc.masks
    for label, compiled in (("direct NumPy maps", False), ("fused XLA maps", True)):
        # stereo_pf.observation._segment calls pf.colors.masks through its module-level name
        sp_observation.color_masks = lambda c, i, compiled=compiled: orig(c, i, compiled=compiled)
        bstate = {"s": blobs.init(sp.BLOB_PARAMS)}

        def live_closed(bstate=bstate):
            o, bstate["s"] = sp.observe(params, frame, bstate["s"])
            return step_fn(state, o)

        rows.append(
            Row(
                "whole frame with capture colours: image line + blobs + compiled step "
                "(N = 1000, 320x240 pair)",
                label,
                *time_call(live_closed, n=n),
                n,
            )
        )
        per_frame = []
        t0 = sp.anchor_frame(obs)
        for _ in range(sized(full=3, quick=2)):
            stamps = []
            for _t, est in sp.live(params, jax.random.key(0), iter(list(d["frames"]))):
                if est is not None:
                    jax.block_until_ready(est.q)
                stamps.append(time.perf_counter())
            per_frame.append(np.diff(stamps[t0 + 1 :]))
        per_frame = np.concatenate(per_frame[1:])  # the first pass compiles
        rows.append(Row("live stream with capture colours (stereo_pf.live, host/device "
                        "overlap), per frame", label, 1e3 * float(np.median(per_frame)),
                        1e3 * float(np.min(per_frame)), len(per_frame)))  # fmt: skip
    sp_observation.color_masks = orig
    return rows


def main() -> None:
    enable_side_device()  # as the CLI: live's host-side calls on a second CPU device
    ap = argparse.ArgumentParser()
    ap.add_argument("--world", type=Path, default=None, help="a test-world sequence folder")
    a = ap.parse_args()
    load0 = os.getloadavg()[0]
    n = sized(full=50, quick=5)
    d = load(CLIP, FRAMES)
    colors = pc.calibrate_from_frames(list(d["frames"][:, 0]))
    rows = _map_rows(f"synthetic clip {CLIP}", d["frames"], colors, n)
    if a.world is not None:
        pairs = _read_pairs(a.world, 40)  # calibration looks at the first 30
        rows += _map_rows(f"test world {a.world.name}", pairs,
                          pc.calibrate_from_frames(list(pairs[:, 0])), n)  # fmt: skip
    rows += _frame_rows(d, colors, n)
    summary = [
        "The maps' per-pixel work (grey-world features, two Mahalanobis distances, background "
        "histogram) is one fused XLA program (float32) in `masks`; the 3x3 blur and the "
        "shirt-proximity dilation stay OpenCV. Decisions can differ only for pixels within "
        "float32 rounding of a threshold or a histogram bin edge.",
        f"Load average (1 min) at the start {load0:.2f}, at the end {os.getloadavg()[0]:.2f} "
        "(2 cores).",
    ]
    path = write_results("bench_pf_colors", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    main()
