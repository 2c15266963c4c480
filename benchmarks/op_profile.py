"""Where the compiled colour-shirt step spends its time, op by op (issue 21's profile): XLA's
per-op trace of the shipped ``shirt.step`` on ``bench_shirt``'s scene (two 640x480 cameras),
each executed op mapped to the ``jaxmocap`` source function that emitted it.

    python -m benchmarks.op_profile [--setup PATH.npz] [--frame steady|fresh|reacquisition]
                                    [--steps N] [--out PATH.json]

``jax.profiler`` records every op the CPU runtime executes (fusions, library calls, loop
bodies' ops each time they run). Each op's name is looked up in the compiled program's HLO,
whose metadata carries the stack frame of the JAX call that emitted it; the op is charged to
the innermost frame inside ``jaxmocap`` and to a stage (search, classification, 10-NN,
render, EDT, pose-assisted classification, IK, white balance). Ops emitted by a
transformation (the IK's forward-mode Jacobian, optimistix's solver) keep only the frames
of that transformation, so they are charged to the IK by their library frame.

Op time is summed over XLA's threads and inflated by the profiler (~1.5x the step's wall
time here): read the shares, not the absolute sums. The step's wall time without the
profiler is measured in the same run. ``--setup``: a scene stored by
``bench_shirt.save_setup`` (``benchmarks/step_ab.py`` makes one).

Writes ``docs/results/shirt_op_profile.json`` and prints a summary.
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import sys
import tempfile
import time
from pathlib import Path

OUT = Path(__file__).parents[1] / "docs" / "results" / "shirt_op_profile.json"

# innermost jaxmocap file (or library frame) -> stage of the frame (§ of Wang et al. 2011)
STAGES = (
    ("search (§4)", ("color/search",)),
    ("crop + classification (§5.2 step 1)", ("color/classify", "color/illumination",
                                             "sampling", "color/model")),
    ("10-NN + blend (step 2)", ("posedb/",)),
    ("render (ray caster)", ("render/", "garment")),
    ("camera model (ray grids, projection)", ("camera",)),
    ("EDT (step 3)", ("distance",)),
    ("pose-assisted classification + centroids (step 3-4)", ("color/pose_assisted",)),
    ("IK: residual, Jacobian, LM (steps 2, 4)", ("ik", "body/")),
    ("white balance (step 5)", ("color/whitebalance",)),
)


def stage_of(chain: list[tuple[str, str, bool]]) -> str:
    """The stage of the innermost ``jaxmocap`` frame; without one, the IK when a solver
    library emitted the op."""
    for f, _, ours in chain:
        if not ours:
            continue
        for stage, keys in STAGES:
            if any(f.startswith(k) for k in keys):
                return stage
        return "tracker glue (loop carries, selects)" if f.startswith("trackers/") else f
    if any(k in f for f, _, _ in chain for k in ("optimistix", "lineax", "_misc", "equinox")):
        return next(k for k, v in STAGES if "ik" in v)
    return "unattributed (no stack frame)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--setup", type=Path, default=None)
    ap.add_argument("--frame", choices=["steady", "fresh", "reacquisition"], default="steady")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    if a.setup is not None and a.out.resolve() == a.setup.resolve():
        print(f"op_profile: --out {a.out} would write over the scene --setup {a.setup}; "
              "choose another --out", file=sys.stderr)
        sys.exit(2)
    import equinox as eqx
    import jax
    import numpy as np

    from benchmarks import bench_shirt
    from benchmarks._common import machine
    from benchmarks.compile_kernels import HloFrames
    from jaxmocap.trackers import shirt as S

    s = (bench_shirt.load_setup(a.setup) if a.setup else bench_shirt.setup(640, 480))
    p, st0, frames = s["params"], s["state"], s["frames"]
    dyn, stat = eqx.partition(p, eqx.is_array)
    fresh, _ = S.step(p, st0, frames)
    steady = fresh
    for _ in range(p.reacquire_frames):
        steady, _ = S.step(p, steady, frames)
    state = {"steady": steady, "fresh": fresh, "reacquisition": st0}[a.frame]

    def call(d, st, f):
        return S._step(eqx.combine(d, stat), st, f, None)

    t0 = time.perf_counter()
    compiled = jax.jit(call).lower(dyn, state, frames).compile()
    compile_s = time.perf_counter() - t0
    frames_of = HloFrames(getattr(compiled, "compiled", compiled).as_text())
    run = lambda: jax.block_until_ready(compiled(dyn, state, frames)[1].q)  # noqa: E731
    for _ in range(3):
        run()
    wall = []
    for _ in range(3 * a.steps):
        t = time.perf_counter()
        run()
        wall.append(1000 * (time.perf_counter() - t))
    with tempfile.TemporaryDirectory() as tmp:
        jax.profiler.start_trace(tmp, create_perfetto_trace=True)
        for _ in range(a.steps):
            run()
        jax.profiler.stop_trace()
        trace = glob.glob(f"{tmp}/plugins/profile/*/*.trace.json.gz")[0]
        events = json.load(gzip.open(trace))["traceEvents"]
    ops = [e for e in events if e.get("ph") == "X" and "hlo_op" in e.get("args", {})
           and not e["name"].startswith(("while", "conditional", "call"))]  # fmt: skip
    per = 1000.0 * a.steps  # trace us -> ms per step
    by_stage, by_func, by_kind = (collections.Counter() for _ in range(3))
    n_stage = collections.Counter()
    for e in ops:
        c = [(f.removesuffix(".py"), fn, ours)
             for f, fn, ours in frames_of.chain(frames_of.op_frame.get(e["name"], 0))]
        stage = stage_of(c)
        by_stage[stage] += e["dur"] / per
        n_stage[stage] += 1 / a.steps
        inner = next((f"{f}:{fn}" for f, fn, ours in c if ours),
                     "(library only: " + (f"{c[0][0]}:{c[0][1]})" if c else "no frame)"))
        by_func[inner] += e["dur"] / per
        by_kind[re.sub(r"[.\d]+$", "", e["name"])] += e["dur"] / per
    total = sum(by_stage.values())
    res = {
        "frame": a.frame, "setup": str(a.setup) if a.setup else "bench_shirt.setup(640, 480)",
        "compile_s": round(compile_s, 1),
        "step_wall_ms_median_min": [round(float(np.median(wall)), 1), round(min(wall), 1)],
        "op_time_ms_per_step": round(total, 2),
        "ops_per_step": round(len(ops) / a.steps),
        "by_stage_ms": {k: round(v, 2) for k, v in by_stage.most_common()},
        "by_stage_ops": {k: round(n_stage[k]) for k, _ in by_stage.most_common()},
        "by_function_ms": {k: round(v, 2) for k, v in by_func.most_common(30)},
        "by_op_kind_ms": {k: round(v, 2) for k, v in by_kind.most_common(15)},
        "machine": machine(), "load_average": list(os.getloadavg()),
    }  # fmt: skip
    a.out.parent.mkdir(parents=True, exist_ok=True)
    a.out.write_text(json.dumps(res, indent=1))
    print(f"{a.frame} frame: {res['step_wall_ms_median_min'][0]} ms median wall "
          f"({res['step_wall_ms_median_min'][1]} min); op time {total:.1f} ms per step "
          f"in {res['ops_per_step']} ops (summed over threads, under the profiler)")
    print("\n| stage | op ms per step | share | ops per step |\n|---|---|---|---|")
    for k, v in by_stage.most_common():
        print(f"| {k} | {v:.2f} | {100 * v / total:.0f}% | {n_stage[k]:.0f} |")
    print("\n| innermost jaxmocap function | op ms per step |\n|---|---|")
    for k, v in by_func.most_common(15):
        print(f"| {k} | {v:.2f} |")
    print(f"\nwrote {a.out}", file=sys.stderr)


if __name__ == "__main__":
    main()
