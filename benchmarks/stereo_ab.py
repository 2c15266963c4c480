"""A/B of the stereo filter's compiled step between two source trees (issue 21): the step of
``stereo_pf.compile_step`` (N = 1000, 14 DOF, 2 x 320x240, the shipped extensions) on one
frame of the punch clip, 150 calls, median / min / 25th percentile ms and the process's CPU ms
per call; then 11 frames tracked, whose last estimate is printed (the trees' arithmetic may
differ at the rounding level).

Run it once per tree and alternate the trees (A, B, A, B): this machine's speed drifts by tens
of per cent over minutes, so only interleaved runs compare.

    git worktree add /tmp/before <commit>
    for src in /tmp/before . /tmp/before .; do
        JAXMOCAP_SRC=$src python -m benchmarks.stereo_ab --label $(basename $src)
    done
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--label", required=True, help="name printed with this run's numbers")
    ap.add_argument("--calls", type=int, default=150)
    a = ap.parse_args()
    src = os.path.abspath(os.environ.get("JAXMOCAP_SRC", "."))
    sys.path.insert(0, src)
    sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "experiments"))
    import jax
    import jax.numpy as jnp
    import numpy as np
    from azad_render import config, load

    import jaxmocap
    from jaxmocap.segment import HSVInterval, SegmentParams
    from jaxmocap.synth.scene import make_cameras
    from jaxmocap.trackers import stereo_pf as sp

    clip = "humanoid3d_punch"
    d = load(clip, 12)
    cams = make_cameras(config(clip, 12), jnp.float32)
    params = sp.make_params(
        cams, images=sp.Images(segment=SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV)))
    )
    obs = sp.observe_sequence(params, d["frames"])
    state, _ = sp.init(params, jax.random.key(0), jax.tree.map(lambda x: x[0], obs))
    frame = jax.tree.map(lambda x: x[5], obs)
    step = sp.compile_step(params)
    jax.block_until_ready(step(state, frame))
    ms = []
    cpu0 = time.process_time()
    for _ in range(a.calls):
        t = time.perf_counter()
        jax.block_until_ready(step(state, frame))
        ms.append((time.perf_counter() - t) * 1e3)
    cpu = (time.process_time() - cpu0) / a.calls * 1e3
    s = state
    for t in range(1, 12):
        s, est = step(s, jax.tree.map(lambda x, t=t: x[t], obs))
    out = {
        "label": a.label,
        "jaxmocap": os.path.dirname(jaxmocap.__file__),
        "median_ms": round(float(np.median(ms)), 3),
        "min_ms": round(float(np.min(ms)), 3),
        "p25_ms": round(float(np.percentile(ms, 25)), 3),
        "cpu_ms_per_call": round(cpu, 3),
        "q_frame_11_first4": [round(float(v), 4) for v in np.asarray(est.q)[:4]],
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
