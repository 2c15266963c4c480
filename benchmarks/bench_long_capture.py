"""Long captures through ``jaxmocap track`` (issue 52 item 1): peak resident memory and
throughput of the whole command at 1k, 10k and 50k frames of two 640x480 cameras, both trackers.

The capture is generated: a short clip rendered by ``jaxmocap synth`` (two cameras, the
punch clip), played forwards and backwards into two H.264 videos of N frames each (the
trackers see motion all along; a real hour would only differ in content). The shirt tracker
gets its colour model from scribbles made of the synthetic colour ids and a small pose
database (``--db-size``), as in docs/USER_GUIDE.md's walk-through; the particle filter runs
with ``--skin synth`` and its default 1000 particles.

Each (tracker, N) is one ``jaxmocap track`` process (the journal on, as a user runs it) whose
own peak RSS (``ru_maxrss``) and wall time are recorded; throughput is reported twice: over
the whole run (compile and set-up included) and at the margin between two lengths
((N2 - N1) / (t2 - t1): the steady frame rate, set-up cancelled). RSS that grows with N is
what the streaming promise of the issue rules out.

Run: python -m benchmarks.bench_long_capture                  # 1k, 10k, 50k (hours)
     python -m benchmarks.bench_long_capture --quick          # 60 and 120 frames of 320x240
     python -m benchmarks.bench_long_capture --quick --methods pf   # about a minute
     python -m benchmarks.bench_long_capture --sizes 1000 --methods pf
Quick runs write into a temporary folder unless --out is given.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from benchmarks import _common
from benchmarks._common import QUICK_ENV, Row, write_results

FULL = {"sizes": (1000, 10000, 50000), "width": 640, "height": 480, "clip_frames": 48,
        "db_size": 3000, "particles": 1000}
QUICK = {"sizes": (60, 120), "width": 320, "height": 240, "clip_frames": 8, "db_size": 300,
         "particles": 100}
NAMES = ("red", "orange", "yellow", "lime", "green", "cyan", "blue", "purple", "magenta", "pink")

# the child: one `jaxmocap track` in this process, then its own peak RSS (Linux: KiB)
_CHILD = """
import json, resource, sys, time
from jaxmocap.cli import main
t0 = time.perf_counter()
rc = main(sys.argv[1:])
wall = time.perf_counter() - t0
print("RESULT " + json.dumps({"rc": rc, "wall_s": wall,
      "max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


def _cli(*argv, env=None) -> subprocess.CompletedProcess:
    p = subprocess.run([sys.executable, "-m", "jaxmocap.cli", *map(str, argv)],
                       capture_output=True, text=True, env=env, check=False)
    if p.returncode != 0:
        raise SystemExit(f"bench_long_capture: jaxmocap {argv[0]} failed:\n{p.stderr[-2000:]}")
    return p


def make_clip(work: Path, cfg: dict, shirt: bool = True) -> Path:
    """The short rendered clip and (``shirt``) its colour model, white balance and pose
    database."""
    import cv2

    from jaxmocap.trackers.shirt import scribbles

    clip = work / "clip"
    _cli("synth", clip, "--preset", "webcams", "--cameras", "2", "--width", cfg["width"],
         "--height", cfg["height"], "--frames", cfg["clip_frames"], "--png", "--no-video",
         "--colour-ids", "--quiet")
    if not shirt:
        return clip
    with np.load(clip / "groundtruth.npz") as z:
        ids = z["colour_ids"]
    images, masks = [], []
    for t in range(min(4, ids.shape[0])):
        for c in range(2):
            m = work / f"scribble_{c}_{t}.png"
            cv2.imwrite(str(m), scribbles(ids[t, c], 1).astype(np.uint8))
            images.append(sorted((clip / f"cam{c}").iterdir())[t])
            masks.append(m)
    _cli("colors", "--images", *images, "--masks", *masks, "--names", *NAMES,
         "--out", work / "colors.json")
    _cli("colors", "--white-balance", "--colors", work / "colors.json", "--images",
         images[0], images[1], "--masks", masks[0], masks[1], "--out", work / "wb.json")
    _cli("build-db", "--size", cfg["db_size"], "--out", work / "db.npz", "--quiet")
    return clip


def make_capture(clip: Path, work: Path, n: int) -> list[Path]:
    """Two H.264 videos of ``n`` frames: the clip forwards, backwards, forwards, ..."""
    import cv2

    from jaxmocap.io.video import VideoWriter

    videos = []
    for c in range(2):
        frames = [cv2.imread(str(p))[..., ::-1] for p in sorted((clip / f"cam{c}").iterdir())]
        loop = frames + frames[-2:0:-1]
        path = work / f"cam{c}_{n}.mp4"
        h, w = frames[0].shape[:2]
        writer = VideoWriter(path, 30.0, w, h)
        try:
            for t in range(n):
                writer.write(np.ascontiguousarray(loop[t % len(loop)]))
        finally:
            writer.close()
        videos.append(path)
    return videos


def track(method: str, videos: list[Path], clip: Path, work: Path, cfg: dict) -> dict:
    out = work / f"out_{method}_{len(videos)}_{time.monotonic_ns()}"
    argv = ["track", "--method", method, "--cameras", clip / "cameras.json", *videos,
            "--out", out, "--quiet", "--formats", "npz,csv"]
    if method == "pf":
        argv += ["--skin", "synth", "--particles", cfg["particles"]]
    else:
        argv += ["--colors", work / "colors.json", "--white-balance", work / "wb.json",
                 "--db", work / "db.npz"]
    p = subprocess.run([sys.executable, "-c", _CHILD, *map(str, argv)], capture_output=True,
                       text=True, check=False)
    lines = [s for s in p.stdout.splitlines() if s.startswith("RESULT ")]
    if not lines:
        raise SystemExit(f"bench_long_capture: track --method {method} failed:\n"
                         f"{p.stderr[-2000:]}")
    res = json.loads(lines[0][len("RESULT "):])
    run = json.loads((out / "run.json").read_text())
    res["frames"] = run["frames_written"]
    shutil.rmtree(out, ignore_errors=True)
    return res


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="small sizes (about a minute)")
    ap.add_argument("--sizes", type=int, nargs="+", help="frame counts (default 1k 10k 50k)")
    ap.add_argument("--methods", nargs="+", choices=("pf", "shirt"), default=["pf", "shirt"])
    ap.add_argument("--out", type=Path, help="results folder (default benchmarks/results; "
                    "a temporary folder with --quick)")
    a = ap.parse_args()
    quick = a.quick or os.environ.get(QUICK_ENV, "").strip() == "1"
    if quick:
        os.environ[QUICK_ENV] = "1"
    cfg = dict(_common.sized(full=FULL, quick=QUICK))
    sizes = tuple(a.sizes or cfg["sizes"])
    if a.out is not None or quick:
        _common.RESULTS = a.out or Path(tempfile.gettempdir()) / "jaxmocap-bench-quick"
    rows, summary = [], []
    with tempfile.TemporaryDirectory(prefix="jaxmocap-long-") as tmp:
        work = Path(tmp)
        t0 = time.perf_counter()
        clip = make_clip(work, cfg, shirt="shirt" in a.methods)
        made = (f", colours, {cfg['db_size']}-pose database" if "shirt" in a.methods else "")
        summary.append(f"set-up (render {cfg['clip_frames']} frames{made}): "
                       f"{time.perf_counter() - t0:.0f} s; {cfg['width']}x{cfg['height']}, "
                       f"pf with {cfg['particles']} particles")
        warm = make_capture(clip, work, 10)  # fills the compilation cache: every timed run
        for m in a.methods:                   # then starts alike (compiled programs loaded)
            track(m, warm, clip, work, cfg)
        results = {m: [] for m in a.methods}
        for n in sizes:
            videos = make_capture(clip, work, n)
            for m in a.methods:
                r = track(m, videos, clip, work, cfg)
                results[m].append((n, r))
                rows.append(Row(kernel=f"track {m}, {n} frames", implementation="jaxmocap track",
                                median_ms=1e3 * r["wall_s"] / n, min_ms=1e3 * r["wall_s"] / n,
                                n=1, notes=f"peak RSS {r['max_rss_mb']:.0f} MB, "
                                f"{n / r['wall_s']:.1f} frames/s overall",
                                extra={**r, "width": cfg["width"], "height": cfg["height"]}))
                print(f"{m:5s} {n:6d} frames: {r['wall_s']:8.1f} s, "
                      f"peak RSS {r['max_rss_mb']:7.0f} MB", flush=True)
            for v in videos:
                v.unlink()
    for m, rs in results.items():
        for (n1, r1), (n2, r2) in zip(rs, rs[1:], strict=False):
            dt = r2["wall_s"] - r1["wall_s"]
            rate = f"{(n2 - n1) / dt:.1f} frames/s" if dt > 0 else "n/a (noise exceeds it)"
            summary.append(f"{m}: {n1} -> {n2} frames: {rate} at the margin, "
                           f"peak RSS {r1['max_rss_mb']:.0f} -> {r2['max_rss_mb']:.0f} MB")
    path = write_results("bench_long_capture", rows, summary)
    print("\n".join(summary))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
