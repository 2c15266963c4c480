"""A/B of the colour-shirt step between two source trees (issue 21): cold compile and the three
kinds of frame, plus the outputs of an 8-frame sequence for an identity check.

Run it once per tree and alternate the trees (A, B, A, B): this machine's speed drifts by
tens of per cent over minutes, so only interleaved pairs compare. The persistent compilation
cache is not enabled here, so the first call is a cold compile.

    git worktree add /tmp/before <commit>
    for src in /tmp/before . /tmp/before .; do
        JAXMOCAP_SRC=$src python -m benchmarks.step_ab --label $(basename $src) --out /tmp/ab
    done

The scene is ``bench_shirt``'s (two 640x480 cameras, 2,000-pose database), stored in
``--setup`` on the first run so that both trees step the same frames (the scene code,
``bench_shirt``, is the current tree's; ``jaxmocap`` is ``$JAXMOCAP_SRC``'s).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True, help="name of this run's outputs")
    ap.add_argument("--out", type=Path, required=True, help="folder for <label>.npz / .json")
    ap.add_argument("--setup", type=Path, default=None,
                    help="the stored scene (default: <out>/setup640.npz, made if missing)")
    ap.add_argument("--reps", type=int, default=9)
    a = ap.parse_args()
    sys.path.insert(0, os.path.abspath(os.environ.get("JAXMOCAP_SRC", ".")))
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    from benchmarks import bench_shirt
    from jaxmocap.trackers import shirt as S

    setup = a.setup or a.out / "setup640.npz"
    if (a.out / f"{a.label}.npz").resolve() == setup.resolve():
        print(f"step_ab: --label {a.label} would write over the scene {setup}; choose another "
              "label", file=sys.stderr)
        sys.exit(2)
    a.out.mkdir(parents=True, exist_ok=True)
    if not setup.exists():
        bench_shirt.save_setup(setup, bench_shirt.setup(640, 480))
    s = bench_shirt.load_setup(setup)
    p, st0, frames = s["params"], s["state"], s["frames"]

    t0 = time.perf_counter()
    jax.block_until_ready(S.step(p, st0, frames)[1].q)
    compile_s = time.perf_counter() - t0

    # 8 frames shifted by 3 px each; before frame 5 the state is marked lost (reacquisition)
    st, outs = st0, []
    for t in range(8):
        if t == 5:
            st = eqx.tree_at(lambda x: x.valid, st, jnp.array(False))
        st, out = S.step(p, st, jnp.roll(frames, 3 * t, axis=2))
        outs.append(jax.tree.map(np.asarray, out))

    def timed(state) -> list[float]:
        ts = []
        for _ in range(a.reps):
            t = time.perf_counter()
            jax.block_until_ready(S.step(p, state, frames)[1].q)
            ts.append(1000 * (time.perf_counter() - t))
        return [round(float(np.median(ts)), 1), round(min(ts), 1)]

    fresh, _ = S.step(p, st0, frames)
    steady = fresh
    for _ in range(p.reacquire_frames):
        steady, _ = S.step(p, steady, frames)
    res = {
        "label": a.label,
        "src": os.environ.get("JAXMOCAP_SRC", "."),
        "compile_plus_first_call_s": round(compile_s, 1),
        "median_min_ms": {"reacquisition": timed(st0), "fresh": timed(fresh),
                          "steady": timed(steady)},
        "load_average": list(os.getloadavg()),
    }  # fmt: skip
    keys = ("q", "valid", "agreement", "centroids", "visible", "window")
    np.savez(a.out / f"{a.label}.npz",
             **{f"{k}_{t}": getattr(o, k) for t, o in enumerate(outs) for k in keys})  # fmt: skip
    (a.out / f"{a.label}.json").write_text(json.dumps(res, indent=1))
    print(json.dumps(res))


if __name__ == "__main__":
    main()
