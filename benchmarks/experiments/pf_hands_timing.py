"""The live frame's cost of the gated hand search (``jaxmocap.trackers.stereo_pf.hands``) on a
test-world sequence: per frame, the blob line (``observe``: both images' segmentation, blobs,
the observation), the compiled filter step (N = 1000), and the search's parts -- the particle
cloud's prediction (forward kinematics of every particle, jitted), the windows' components and
pairs (``gated_hands``), the motion map of both views -- median and minimum over the frames
after ``--warm``, all compiled, same run.

    python -m benchmarks.experiments.pf_hands_timing /work/world/pf_03 [--out X.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import jax
import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--warm", type=int, default=10)
    ap.add_argument("--out")
    a = ap.parse_args()
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from benchmarks.experiments.world_pf_parts import CONFIGS
    from jaxmocap import blobs as bloblib
    from jaxmocap.experiment.cell import pf_setup
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers.stereo_pf import hands as HS
    from jaxmocap.trackers.stereo_pf.filter import compile_step, online_frame
    from jaxmocap.trackers.stereo_pf.observation import _segment, observe
    from jaxmocap.trackers.stereo_pf.params import BLOB_PARAMS

    seq = load_dataset(a.folder)
    cfg = {"name": "hands", "method": "pf", "body": "sequence",
           "options": dict(CONFIGS["hands-motion"])}
    params = pf_setup(seq, cfg, a.folder)[0]
    hp = params.hand_search
    arms = HS.arm_reach(params.model)
    predict = jax.jit(lambda s, lw: HS.cloud_prediction(params, arms, s, lw))
    step = compile_step(params)
    key = jax.random.key(0)
    blob_state = bloblib.init(BLOB_PARAMS)
    state, out, history = None, [], []
    rows = {k: [] for k in ("observe", "filter_step", "prediction", "gated_hands", "motion_map")}
    for t in range(len(seq.frames)):
        frame = np.asarray(seq.frames[t])
        t0 = time.perf_counter()
        seg = [_segment(params, frame[v]) for v in range(2)]
        obs, blob_state = observe(params, frame, blob_state, segmentation=seg)
        jax.block_until_ready(obs.edges)
        t_obs = time.perf_counter() - t0
        searched = state is not None and len(history) >= 2
        if searched:
            mean, spread = history[-1]
            pred = mean + hp.velocity_damping * (mean - history[-2][0])
            t0 = time.perf_counter()
            _motion = [HS.motion_map(np.asarray(seq.frames[t - 2:t + 1, v]),
                                    np.asarray(seg[v].foreground, bool), hp.motion_threshold)
                      for v in range(2)]
            t_mot = time.perf_counter() - t0
            masks = [np.asarray(s.skin, bool) for s in seg]
            t0 = time.perf_counter()
            HS.gated_hands(params, arms, masks, pred, spread, np.asarray(obs.points),
                           np.asarray(obs.valid), hp)
            t_gate = time.perf_counter() - t0
        out.append(obs)
        t0 = time.perf_counter()
        was = state is not None
        state, est = online_frame(params, key, step, state, out, obs)
        if est is not None:
            jax.block_until_ready(est.q)
        t_step = time.perf_counter() - t0
        if state is None:
            continue
        t0 = time.perf_counter()
        mean, spread = jax.block_until_ready(predict(state.particles.particles,
                                                     state.particles.log_weights))
        t_pred = time.perf_counter() - t0
        history = (history + [(np.asarray(mean, np.float64), np.asarray(spread))])[-2:]
        if searched and was and t >= a.warm:
            for k, v in (("observe", t_obs), ("filter_step", t_step), ("prediction", t_pred),
                         ("gated_hands", t_gate), ("motion_map", t_mot)):
                rows[k].append(1e3 * v)
    res = {k: {"median_ms": float(np.median(v)), "min_ms": float(np.min(v)), "frames": len(v)}
           for k, v in rows.items()}
    res["folder"] = a.folder
    print(json.dumps(res, indent=1))
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
