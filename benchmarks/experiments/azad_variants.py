"""Ad-hoc variant runs of the stereo particle filter over several keys (the session's
comparisons in ``docs/results/stereo_pf.md``): each variant is a set of ``make_params``
keyword arguments (``"_smooth": L``: ``run(smooth_lag=L)``; ``"_blobs": {...}``: overrides
of the tracker's ``stereo_pf.BLOB_PARAMS``; ``"_blobs": {"report_coast": 8}`` is Azad's
carry); prints the mean joint
error (cm, shoulders + elbows + hands) per clip and key
and the mean over keys. Observations are computed once per clip.

    python benchmarks/experiments/azad_variants.py CLIP[,CLIP] KEYS 'name:{"kw": v}' ...
e.g. python benchmarks/experiments/azad_variants.py punch,dance_b 2 'paper:{}' \\
        'guided:{"guided": true}'
"""

import dataclasses
import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from azad_accuracy import JOINTS  # noqa: E402
from azad_render import config, load  # noqa: E402

from jaxmocap.body import default_body, keypoint_index, keypoints  # noqa: E402
from jaxmocap.segment import HSVInterval, SegmentParams  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402
from jaxmocap.trackers import stereo_pf as sp  # noqa: E402

SHORT = {"punch": "humanoid3d_punch", "dance_b": "humanoid3d_dance_b",
         "turn": "walker/turn_left0"}  # fmt: skip
SEG = SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))


def errors(model, q, kp_true) -> np.ndarray:
    idx = keypoint_index(model, JOINTS)
    kp = np.asarray(jax.jit(jax.vmap(lambda q: keypoints(model, q)))(q))
    return 100 * np.linalg.norm(kp[:, idx] - kp_true[:, idx], axis=-1)  # (T, 6) cm


def run_variant(clip, d, obs, kwargs, seed, model):
    kwargs = dict(kwargs)
    lag = kwargs.pop("_smooth", 0)  # run(smooth_lag=...)
    cams = make_cameras(config(clip, len(d["frames"])), jnp.float32)
    params = sp.make_params(cams, images=sp.Images(segment=SEG), **kwargs)
    t0 = sp.anchor_frame(obs)
    state, _ = sp.init(params, jax.random.key(seed), jax.tree.map(lambda a: a[t0], obs))
    _, est = sp.run(params, state, obs, lag)
    return errors(model, est.q, d["keypoints"])


def main(argv):
    clips = [SHORT.get(c, c) for c in argv[0].split(",")]
    keys = int(argv[1])
    variants = [(v.split(":", 1)[0], json.loads(v.split(":", 1)[1])) for v in argv[2:]]
    model = default_body()
    for clip in clips:
        d = load(clip, 40)
        cams = make_cameras(config(clip, 40), jnp.float32)
        cache = {}
        for name, kw in variants:
            kw = dict(kw)
            bkw = kw.pop("_blobs", {})  # BlobParams overrides
            tag = json.dumps(bkw, sort_keys=True)
            if tag not in cache:
                # with the support map (read by the variants that use it)
                cache[tag] = sp.observe_sequence(
                    sp.make_params(cams, images=sp.Images(segment=SEG),
                                   cues=sp.Cues(use_support=True)), d["frames"],
                    dataclasses.replace(sp.BLOB_PARAMS, **bkw),
                )  # fmt: skip
            obs = cache[tag]
            t = time.perf_counter()
            errs = [run_variant(clip, d, obs, kw, s, model) for s in range(keys)]
            means = [float(e.mean()) for e in errs]
            pj = [round(float(v), 1) for v in np.mean([e.mean(0) for e in errs], 0)]
            pf_ = np.mean([e.mean(1) for e in errs], 0)
            blocks = " ".join(f"{pf_[i : i + 10].mean():4.1f}" for i in range(0, len(pf_), 10))
            print(f"{clip:22s} {name:16s} mean {np.mean(means):5.1f}  keys "
                  f"{' '.join(f'{m:5.1f}' for m in means)}  joints {pj}  10-frame blocks {blocks} "
                  f"({time.perf_counter() - t:.0f} s)", flush=True)  # fmt: skip


if __name__ == "__main__":
    main(sys.argv[1:])
