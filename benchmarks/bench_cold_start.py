"""The shirt tracker's first frame on an empty compilation cache (issue 21: <= 20 s), on the demo's
set-up (two 320x240 webcams, bundled body and shirt, 3,000-pose database): the program shipped
ahead of time (``shirt.compile_step``, :mod:`jaxmocap.trackers.shirt.export`: XLA's compile
only) against tracing the step (``shirt.step``: trace + lower + compile), each in a fresh
process with no persistent compilation cache, alternated (A, B, A, B, ...): this machine's
speed drifts by tens of per cent over minutes. Both give bit-identical poses (checked in each
run: the first two frames' ``q``). The set-up itself (render, database, colour model) is not
timed; the database comes from the jaxmocap cache.

Run: python -m benchmarks.bench_cold_start [--pairs N]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

import numpy as np

from benchmarks._common import Row, write_results

_CHILD = """
import json, sys, time, jax, numpy as np
from jaxmocap.trackers import shirt
from jaxmocap.trackers.shirt import export as shirt_export
params, state, frames = shirt_export._demo_inputs()
mode = sys.argv[1]
t0 = time.perf_counter(); c0 = time.process_time()
step = shirt.compile_step(params) if mode == "shipped" else (
    lambda s, f: shirt.step(params, s, f))
s, out = step(state, frames[0]); jax.block_until_ready(out.q)
first = time.perf_counter() - t0; cpu = time.process_time() - c0
t1 = time.perf_counter(); s, out2 = step(s, frames[1]); jax.block_until_ready(out2.q)
second = time.perf_counter() - t1
print("RESULT " + json.dumps({"first_s": first, "first_cpu_s": cpu, "second_ms": 1e3 * second,
      "q": np.asarray(out.q).tolist() + np.asarray(out2.q).tolist()}))
"""


def _run(mode: str) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_COMPILATION_CACHE_DIR",)}
    p = subprocess.run([sys.executable, "-c", _CHILD, mode], capture_output=True, text=True,
                       env=env, check=False)  # fmt: skip
    lines = [s for s in p.stdout.splitlines() if s.startswith("RESULT ")]
    if p.returncode != 0 or not lines:
        raise SystemExit(f"bench_cold_start: the {mode} run failed:\n{p.stderr[-2000:]}")
    return json.loads(lines[0][len("RESULT "):])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--pairs", type=int, default=3)
    a = ap.parse_args()
    load0 = os.getloadavg()
    runs: dict[str, list[dict]] = {"shipped": [], "traced": []}
    for i in range(a.pairs):
        for mode in ("shipped", "traced") if i % 2 == 0 else ("traced", "shipped"):
            runs[mode].append(_run(mode))
            print(mode, round(runs[mode][-1]["first_s"], 1), "s", file=sys.stderr)
    same = all(r["q"] == runs["traced"][0]["q"] for r in runs["shipped"] + runs["traced"])
    rows = []
    for mode, label in (("shipped", "shirt.compile_step: the program shipped for the set-up"),
                        ("traced", "shirt.step: trace + lower + compile (baseline)")):
        first = np.array([r["first_s"] for r in runs[mode]]) * 1e3
        rows.append(Row("first shirt step, empty compilation cache, demo set-up (2 x 320x240)",
                        label, float(np.median(first)), float(first.min()), len(first),
                        notes="ms; each run a fresh process",
                        extra={"first_s": [round(r["first_s"], 2) for r in runs[mode]],
                               "first_cpu_s": [round(r["first_cpu_s"], 2) for r in runs[mode]],
                               "second_step_ms": [round(r["second_ms"], 1)
                                                  for r in runs[mode]]}))  # fmt: skip
    ratio = rows[1].median_ms / rows[0].median_ms
    load1 = os.getloadavg()
    summary = [
        f"Issue 21 target: first tracked frame <= 20 s on an empty cache. Shipped program "
        f"{rows[0].median_ms / 1e3:.1f} s median ({rows[0].min_ms / 1e3:.1f} min), traced "
        f"{rows[1].median_ms / 1e3:.1f} s ({rows[1].min_ms / 1e3:.1f} min): {ratio:.2f}x.",
        f"Poses of the first two frames identical in every run, both ways: {same}.",
        f"{a.pairs} alternated pairs of fresh processes. Load average (1, 5, 15 min) at the start "
        + ", ".join(f"{x:.2f}" for x in load0) + ", at the end "
        + ", ".join(f"{x:.2f}" for x in load1) + " (2 cores).",
    ]
    path = write_results("bench_cold_start", rows, summary)
    print(path.read_text())


if __name__ == "__main__":
    main()
