"""The stereo filter's head measurement alone (issue 39 item 2): the blob line's triangulated
skin centroid against the head sphere fitted to the skin outline of both views
(:mod:`jaxmocap.trackers.stereo_pf.head`), per sequence, on the frames where the blob line
measures a head and the head is visible in both cameras (``world_pf_parts.visibility``):
the share within 4 cm of the true head keypoint (of the visible frames), the median error,
its depth and lateral parts (along / across the line from the cameras' mid-point), and the
fit's time. The image line is the ``base`` configuration's (the capture's colours from
scribbles, blob plausibility); no filter runs.

    python -m benchmarks.experiments.pf_head_fit OUT.json SEQ_FOLDER... [NAME=VALUE ...]

``NAME=VALUE`` sets a constant of :mod:`jaxmocap.trackers.stereo_pf.head` (the dev sweeps of
its docstring).
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import numpy as np

HEAD_CM = 4.0


def _frames(folder: str):
    from benchmarks.experiments.world_pf_parts import visibility
    from jaxmocap import blobs as bloblib
    from jaxmocap.experiment.cell import _body, _scribbled_capture_colors
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers import stereo_pf as sp
    from jaxmocap.trackers.stereo_pf.observation import _segment

    seq = load_dataset(folder)
    body = _body({"body": "sequence"}, folder)
    params = sp.make_params(list(seq.cameras), model=body, images=sp.Images(
        colors=_scribbled_capture_colors(seq), plausible_blobs=True, head_sphere=True),
        proposals=sp.Proposals(swivel_fraction=0.0))
    g = np.load(Path(folder) / "groundtruth.npz")
    truth = g["keypoints"][:, [str(n) for n in g["keypoint_names"]].index("head")]
    vis = visibility(seq, body)[:, 0]
    state, cams = bloblib.init(sp.BLOB_PARAMS), params.likelihood.cams
    for t in range(seq.frames.shape[0]):
        seg = [_segment(params, seq.frames[t, i]) for i in range(2)]
        state, pts, val = bloblib.update(state, seg[0].skin, seg[1].skin, cams,
                                         reach=params.reach)
        yield params, seg, pts[0].copy(), bool(val[0]), truth[t], bool(vis[t])


def measure(folder: str) -> dict:
    from jaxmocap.trackers.stereo_pf import head

    rows, n_vis = [], 0
    for params, seg, start, measured, truth, visible in _frames(folder):
        n_vis += visible
        if not (measured and visible):
            continue
        radius, offset = params.head_sphere
        cams = params.likelihood.cams
        mid = -np.einsum("vji,vj->vi", np.asarray(cams.R, np.float64),
                         np.asarray(cams.t, np.float64)).mean(axis=0)
        u = (truth - mid) / np.linalg.norm(truth - mid)
        t0 = time.perf_counter()
        c = head.fit_head(cams, [s.skin for s in seg], [s.foreground for s in seg], start,
                          radius)
        dt = time.perf_counter() - t0
        fit = start if c is None else c + np.asarray(offset)
        row = {"fitted": c is not None, "ms": 1e3 * dt}
        for name, p in (("centroid", start), ("sphere", fit)):
            d = 100 * (p - truth)
            row[name] = [float(np.linalg.norm(d)), float(d @ u),
                         float(np.linalg.norm(d - (d @ u) * u))]
        rows.append(row)
    out = {"folder": folder, "visible": int(n_vis), "measured": len(rows)}
    for name in ("centroid", "sphere"):
        e = np.array([r[name] for r in rows]).reshape(-1, 3)
        out[name] = {"within": float((e[:, 0] < HEAD_CM).sum() / max(n_vis, 1)),
                     "median_cm": float(np.median(e[:, 0])),
                     "median_depth_cm": float(np.median(e[:, 1])),
                     "median_abs_depth_cm": float(np.median(np.abs(e[:, 1]))),
                     "median_lateral_cm": float(np.median(e[:, 2]))}
    out["fitted"] = float(np.mean([r["fitted"] for r in rows]))
    out["fit_ms_median"] = float(np.median([r["ms"] for r in rows[1:]]))
    return out


def main() -> int:
    from jaxmocap.trackers.stereo_pf import head

    args = sys.argv[1:]
    for a in [a for a in args if "=" in a]:
        k, v = a.split("=")
        setattr(head, k, type(getattr(head, k))(float(v)))
    path, folders = args[0], [a for a in args[1:] if "=" not in a]
    res = [measure(f) for f in folders]
    vis = sum(r["visible"] for r in res)
    pooled = {n: sum(r[n]["within"] * r["visible"] for r in res) / max(vis, 1)
              for n in ("centroid", "sphere")}
    for r in res:
        c, s = r["centroid"], r["sphere"]
        print(f"{Path(r['folder']).name}: visible {r['visible']}, measured {r['measured']}: "
              f"within {HEAD_CM:g} cm {c['within']:.0%} -> {s['within']:.0%}; median "
              f"{c['median_cm']:.1f} -> {s['median_cm']:.1f} cm (|depth| "
              f"{c['median_abs_depth_cm']:.1f} -> {s['median_abs_depth_cm']:.1f}, lateral "
              f"{c['median_lateral_cm']:.1f} -> {s['median_lateral_cm']:.1f}); "
              f"{r['fit_ms_median']:.1f} ms")
    print(f"pooled within {HEAD_CM:g} cm: centroid {pooled['centroid']:.0%}, sphere "
          f"{pooled['sphere']:.0%}")
    Path(path).write_text(json.dumps({"sequences": res, "pooled": pooled}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
