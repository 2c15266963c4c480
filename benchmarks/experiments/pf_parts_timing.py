"""Per-frame cost of the stereo filter's per-part colours and seeded search
(:mod:`jaxmocap.trackers.stereo_pf.parts`) on a test-world dev sequence (320x240 pair,
N = 1000): the blob line (:func:`~jaxmocap.trackers.stereo_pf.observe`), the filter step, and
what the parts add per frame -- the seeded search (the parts' distance maps, components,
triangulation), the render of the estimate's parts and the colour update -- each compiled and
warm, timed in the same run on the same frames (median and minimum over the frames).

    python -m benchmarks.experiments.pf_parts_timing /work/world/pf_03 [--out X.json]
"""

from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("folder")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--out")
    a = ap.parse_args()
    from jaxmocap import blobs as bloblib
    from jaxmocap.body import keypoint_index, keypoints
    from jaxmocap.experiment.cell import _body, _scribbled_capture_colors
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers import stereo_pf as sp
    from jaxmocap.trackers.stereo_pf import parts as P

    seq = load_dataset(a.folder)
    body = _body({"body": "sequence"}, a.folder)
    params = sp.make_params(
        list(seq.cameras),
        model=body,
        images=sp.Images(
            colors=_scribbled_capture_colors(seq), plausible_blobs=True, part_colours=True
        ),
        cues=sp.Cues(hand_swap=True),
    )
    cams = params.likelihood.cams
    scene = P.part_scene(body)
    render = jax.jit(lambda q: P.erode_labels(P.render_parts(scene, cams, q)))
    idx = np.asarray([keypoint_index(body, k)[0] for k in bloblib.ENTITY_NAMES])
    kp_fn = jax.jit(lambda q: keypoints(body, q)[idx])
    step = sp.compile_step(params)
    frames = seq.frames[: a.frames]
    obs_all = sp.observe_sequence(params, frames, sp.BLOB_PARAMS)
    t0 = sp.anchor_frame(obs_all)
    first = jax.tree.map(lambda x: x[t0], obs_all)
    state, est = sp.init_top_level(params, jax.random.key(0), first)
    labels = render(est.q)
    colours = P.calibrate_parts(params.colors, frames[t0], labels)
    blob_state = bloblib.init(sp.BLOB_PARAMS)
    rows = {"observe": [], "filter_step": [], "seeded_search": [], "render": [], "update": []}
    for t in range(len(frames)):
        tic = time.perf_counter()
        obs, blob_state = sp.observe(params, frames[t], blob_state)
        jax.block_until_ready(obs)
        rows["observe"].append(time.perf_counter() - tic)
        tic = time.perf_counter()
        images = np.stack([P.blurred(frames[t][v]) for v in range(2)])
        pred = np.asarray(kp_fn(est.q), np.float64)
        P.seeded_search(
            params,
            colours,
            images,
            pred,
            np.asarray(obs.points),
            np.zeros(3, bool),
            params.part_colours,
        )  # every part searched
        rows["seeded_search"].append(time.perf_counter() - tic)
        tic = time.perf_counter()
        state, est = step(state, obs)
        jax.block_until_ready(est)
        rows["filter_step"].append(time.perf_counter() - tic)
        tic = time.perf_counter()
        labels = jax.block_until_ready(render(est.q))
        rows["render"].append(time.perf_counter() - tic)
        tic = time.perf_counter()
        out = P.update_colours(
            colours, jnp.asarray(images), labels, jnp.ones(4, bool), jnp.asarray(True)
        )
        colours = jax.block_until_ready(out[0])
        rows["update"].append(time.perf_counter() - tic)
    warm = slice(5, None)  # the first frames compile
    res = {
        k: {"median_ms": 1e3 * float(np.median(v[warm])), "min_ms": 1e3 * float(np.min(v[warm]))}
        for k, v in rows.items()
    }
    for s in ("median_ms", "min_ms"):
        base = res["observe"][s] + res["filter_step"][s]
        extra = res["seeded_search"][s] + res["render"][s] + res["update"][s]
        res[f"frame_{s}"] = {"without": base, "with": base + extra, "ratio": (base + extra) / base}
    res["folder"], res["frames"] = a.folder, len(frames) - 5
    print(json.dumps(res, indent=1))
    if a.out:
        with open(a.out, "w") as f:
            json.dump(res, f, indent=1)
            f.write("\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
