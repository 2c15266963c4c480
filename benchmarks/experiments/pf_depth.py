"""Depth on a short baseline (issue 39 decision 3): where the stereo filter's error lies, in
depth (along the line of sight from the cameras' midpoint) and across it, and what holding or
freeing the triangulated points' depth does -- an oracle ladder on the test world's dev split.

Each configuration runs :func:`jaxmocap.trackers.driver.stereo_offline` on the sequence with
the set-up of ``world_pf.toml``'s ``jaxmocap`` configuration (the capture's colours from
scribbles, blob plausibility, hand swap) and one change:

* ``base``: as it is;
* ``depth``: the distance cue's width along each point's line of sight ``Cues.sigma_depth =
  DEPTH_RATIO x sigma_d`` (:mod:`jaxmocap.pf.cues`): depth left to the edge cue and the body's
  bone lengths as far as the triangulation does not hold it;
* ``oracle_depth``: the blob line's points (same ones, same frames) moved along their own line
  of sight to the depth of the nearest true part of their role (head; either hand): perfect
  disparity, the lateral error kept;
* ``oracle_rays``: the true head and hands wherever they are visible in both cameras
  (:func:`benchmarks.experiments.world_pf_parts.visibility`), with ``sigma_depth`` = 100 m:
  each found part as a line of sight only -- whether the edge cue and the body place its
  depth;
* ``oracle_points``: the true head and hands where visible, isotropic: the ceiling;
* ``oracle_identity``: the blob line's points (same ones, same frames), each measured hand
  named by the nearer true hand (a pair named alike keeps the nearer one), without the hand
  swap: the identities right, the points as measured;
* ``oracle_candidates``: each hand the blob line's stereo-matched candidate (every triangulated
  skin-blob pair of the frame that passed the plausibility gate, ``BlobState.candidates``)
  nearest its true position if within 8 cm, else missing, without the hand swap: a perfect
  association of the candidates the blob line already has.

The oracles only replace the *points* the distance cue reads (the image line, edges and
support map are the tracker's).

    python -m benchmarks.experiments.pf_depth run OUT CONFIG SEQ_FOLDER... [--seed 0] [--set K=V]
    python -m benchmarks.experiments.pf_depth report OUT [--md X.md --json X.json]
    python -m benchmarks.experiments.pf_depth timing SEQ_FOLDER   # the step with / without
    python -m benchmarks.experiments.pf_depth skin OUT SEQ_FOLDER... [--figure X.png]

``OUT`` holds one ``CONFIG_SEQ_sSEED.npz`` per run in the format of ``world_pf_parts`` (whose
``base`` runs can be copied in); the report adds the mean joint error over all frames split
into depth and lateral (:func:`jaxmocap.metrics.depth_lateral`) and the measured points'
depth / lateral error.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks.experiments.world_pf_parts import CONFIGS as PARTS_CONFIGS
from benchmarks.experiments.world_pf_parts import estimate_keypoints, pending, visibility
from benchmarks.experiments.world_pf_parts import metrics as parts_metrics

FREE_DEPTH_M = 100.0  # sigma_depth of the ``oracle_rays`` rung: the depth held by nothing
CONFIGS = ("base", "depth", "oracle_depth", "oracle_rays", "oracle_points", "oracle_identity",
           "oracle_candidates")
ASSOCIATE_M = 0.08  # oracle_candidates: a candidate within this of a true hand is that hand
ROLES = ("head", "l_hand", "r_hand")  # the distance cue's points (jaxmocap.blobs order)


def _origin(cams) -> np.ndarray:
    from jaxmocap.camera import camera_center

    return np.mean([np.asarray(camera_center(c), np.float64) for c in cams], axis=0)


def _true_parts(seq) -> np.ndarray:
    """(T, 3, 3) the true head, left and right hand keypoints."""
    g = seq.groundtruth
    names = [str(n) for n in g["keypoint_names"]]
    return np.stack([g["keypoints"][:, names.index(n)] for n in ROLES], axis=1)


def oracle_depth_points(points: np.ndarray, valid: np.ndarray, truth: np.ndarray,
                        origin: np.ndarray) -> np.ndarray:
    """Each valid point moved along its line of sight (from ``origin``) to the depth of the
    nearest true part of its role (the head for the head, the nearer hand for a hand)."""
    out = np.array(points, np.float64, copy=True)
    for t, k in zip(*np.nonzero(valid), strict=True):
        cands = truth[t, :1] if k == 0 else truth[t, 1:]
        near = cands[np.argmin(np.linalg.norm(cands - points[t, k], axis=-1))]
        u = points[t, k] - origin
        u /= np.linalg.norm(u)
        out[t, k] = origin + u * float((near - origin) @ u)
    return out


def oracle_identity_points(points: np.ndarray, valid: np.ndarray, truth: np.ndarray
                           ) -> tuple[np.ndarray, np.ndarray]:
    """The measured hands renamed by the nearer true hand (module docstring): (points, valid)."""
    pts, ok = np.array(points, copy=True), np.array(valid, copy=True)
    for t in range(len(pts)):
        got = {}
        for k in (1, 2):
            if valid[t, k]:
                d = np.linalg.norm(truth[t, 1:] - points[t, k], axis=-1)
                role = 1 + int(np.argmin(d))
                if role not in got or d[role - 1] < got[role][1]:
                    got[role] = (points[t, k], d[role - 1])
        ok[t, 1:] = False
        for role, (p, _) in got.items():
            pts[t, role], ok[t, role] = p, True
    return pts, ok


def _candidate_observations(params, blob, frames, truth):
    """``observe_sequence`` with each hand replaced by the frame's blob candidate nearest its
    true position within :data:`ASSOCIATE_M` (else missing); the head as the blob line's."""
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jaxmocap import blobs as bloblib
    from jaxmocap.trackers import stereo_pf as sp

    state, out = bloblib.init(blob), []
    for t in range(len(frames)):
        obs, state = sp.observe(params, frames[t], state)
        pts, ok = np.array(obs.points, np.float64), np.array(obs.valid)
        cand = np.asarray(state.candidates, np.float64).reshape(-1, 3)
        for k in (1, 2):
            d = np.linalg.norm(cand - truth[t, k], axis=-1) if len(cand) else np.zeros(0)
            ok[k] = bool(len(d)) and d.min() <= ASSOCIATE_M
            pts[k] = cand[np.argmin(d)] if ok[k] else 0.0
        out.append(dataclasses.replace(obs, points=jnp.asarray(pts, obs.points.dtype),
                                       valid=jnp.asarray(ok)))
    return jax.tree.map(lambda *a: jnp.stack(a), *out)


def run(out: Path, config: str, folders: list[str], seed: int, extra: dict | None = None
        ) -> None:
    import dataclasses

    import jax
    import jax.numpy as jnp

    from jaxmocap.experiment.cell import pf_setup
    from jaxmocap.pf.cues import DEPTH_RATIO, SIGMA_D
    from jaxmocap.trackers import stereo_pf as sp
    from jaxmocap.trackers.driver import stereo_offline

    for folder, dest, seq in pending(out, config, folders, seed):
        name = Path(folder).name
        opts = dict(PARTS_CONFIGS["base"])
        if config == "depth":
            opts["sigma_depth"] = DEPTH_RATIO * SIGMA_D
        elif config == "oracle_rays":
            opts["sigma_depth"] = FREE_DEPTH_M
        elif config in ("oracle_identity", "oracle_candidates"):
            opts["hand_swap"] = False
        opts.update(extra or {})
        cfg = {"name": config, "method": "pf", "body": "sequence", "options": opts}
        params, blob, lag, _, _, heads = pf_setup(seq, cfg, folder)
        vis_file = out / f"visible_{name}.npy"
        if not vis_file.exists():
            np.save(vis_file, visibility(seq, params.model))
        vis = np.load(vis_file)
        truth, origin = _true_parts(seq), _origin(seq.cameras)

        def observe(params=params, blob=blob, seq=seq, vis=vis, truth=truth, origin=origin):
            if config == "oracle_candidates":
                return _candidate_observations(params, blob, seq.frames, truth)
            obs = sp.observe_sequence(params, seq.frames, blob)
            if not config.startswith("oracle"):
                return obs
            dt = obs.points.dtype
            if config == "oracle_depth":
                pts = oracle_depth_points(np.asarray(obs.points, np.float64),
                                          np.asarray(obs.valid), truth, origin)
                return dataclasses.replace(obs, points=jnp.asarray(pts, dt))
            if config == "oracle_identity":
                pts, ok = oracle_identity_points(np.asarray(obs.points), np.asarray(obs.valid),
                                                 truth)
                return dataclasses.replace(obs, points=jnp.asarray(pts, dt),
                                           valid=jnp.asarray(ok))
            return dataclasses.replace(obs, points=jnp.asarray(np.where(vis[..., None], truth, 0),
                                                               dt), valid=jnp.asarray(vis))

        t0 = time.perf_counter()
        res = stereo_offline(params, jax.random.key(seed), seq.frames, observe, lag,
                             start_from_head=heads)
        wall = time.perf_counter() - t0
        est = jax.device_get(res.estimate)
        obs = res.observations
        q = np.asarray(est.q, np.float64)
        valid = sp.frame_validity(params, q, np.asarray(obs.points), np.asarray(obs.valid))
        np.savez(dest, q=q, valid=valid,
                 times=np.full(len(est.q), wall / len(est.q)), points=np.asarray(obs.points),
                 blob_valid=np.asarray(obs.valid), visible=vis, wall_s=wall, folder=str(folder))
        print(f"{dest.name}: {wall:.0f} s", flush=True)


def depth_metrics(path: Path) -> dict:
    """``world_pf_parts.metrics`` plus the joint error (all frames, the experiment's joints)
    split into depth and lateral, and the measured points' depth / lateral error (points
    within 30 cm of the nearest true part of their role)."""
    from jaxmocap.metrics import depth_lateral
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers.driver import PF_JOINTS

    row = parts_metrics(path)
    z, _, g, gnames, kp, names = estimate_keypoints(path)
    seq = load_dataset(str(z["folder"]))
    origin = _origin(seq.cameras)
    pred = kp[:, [names.index(j) for j in PF_JOINTS]]
    true = g["keypoints"][:, [gnames.index(j) for j in PF_JOINTS]]
    d, lat = depth_lateral(pred, true, origin)
    row["depth_cm"], row["lateral_cm"] = float(100 * d.mean()), float(100 * lat.mean())
    truth = _true_parts(seq)
    pts, ok = z["points"], z["blob_valid"]
    dd, ll = [], []
    for t, k in zip(*np.nonzero(ok), strict=True):
        cands = truth[t, :1] if k == 0 else truth[t, 1:]
        near = cands[np.argmin(np.linalg.norm(cands - pts[t, k], axis=-1))]
        if np.linalg.norm(near - pts[t, k]) < 0.3:
            a, b = depth_lateral(pts[t, k], near, origin)
            dd.append(float(a))
            ll.append(float(b))
    row["points_rms_depth_cm"] = float(100 * np.sqrt(np.mean(np.square(dd)))) if dd else None
    row["points_rms_lateral_cm"] = float(100 * np.sqrt(np.mean(np.square(ll)))) if ll else None
    row["points_near"] = len(dd)
    row["config"], row["sequence"] = path.stem.split("_pf_")[0], "pf_" + \
        path.stem.split("_pf_")[1].rsplit("_s", 1)[0]
    row["seed"] = int(path.stem.rsplit("_s", 1)[1])
    return row


def report(out: Path, md: str | None, js: str | None) -> None:
    rows = [depth_metrics(p) for p in sorted(out.glob("*_pf_*_s*.npz"))]
    configs = [c for c in CONFIGS if any(r["config"] == c for r in rows)]
    seqs = sorted({r["sequence"] for r in rows})
    lines = ["| config | " + " | ".join(seqs) + " | mean | depth / lateral cm |",
             "|---|" + "---|" * (len(seqs) + 2)]
    summary = {}
    for c in configs:
        cells, allr = [], [r for r in rows if r["config"] == c]
        for s in seqs:
            v = [r["mean_joint_cm"] for r in allr if r["sequence"] == s]
            cells.append(f"{np.mean(v):.1f} ({len(v)})" if v else "-")
        seeds = sorted({r["seed"] for r in allr})
        # the mean over the sequences per seed, then over the seeds (as `jaxmocap experiment`)
        per_seed = [np.mean([r["mean_joint_cm"] for r in allr if r["seed"] == k]) for k in seeds]
        dl = (np.mean([r["depth_cm"] for r in allr]), np.mean([r["lateral_cm"] for r in allr]))
        summary[c] = {"mean_cm": float(np.mean(per_seed)), "seed_means": per_seed,
                      "depth_cm": float(dl[0]), "lateral_cm": float(dl[1])}
        lines.append(f"| {c} | " + " | ".join(cells) + f" | {np.mean(per_seed):.2f} "
                     f"({min(per_seed):.2f}-{max(per_seed):.2f}) | {dl[0]:.1f} / {dl[1]:.1f} |")
    text = "\n".join(lines) + "\n"
    print(text)
    if md:
        Path(md).write_text(text)
    if js:
        Path(js).write_text(json.dumps({"summary": summary, "runs": rows}, indent=1) + "\n")


def timing(folder: str, calls: int, rounds: int) -> dict:
    """The compiled filter step (``compile_step``, N = 1000) with and without ``sigma_depth``
    on the sequence's observations, ``rounds`` interleaved rounds of ``calls`` frames each
    (this machine's speed drifts: only interleaved runs compare); median ms per step."""
    import jax

    from jaxmocap.experiment.cell import pf_setup
    from jaxmocap.pf.cues import DEPTH_RATIO, SIGMA_D
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers import stereo_pf as sp

    seq = load_dataset(folder)
    variants, blob = {}, None
    for k, extra in (("isotropic", {}), ("sigma_depth", {"sigma_depth": DEPTH_RATIO * SIGMA_D})):
        cfg = {"name": k, "method": "pf", "body": "sequence",
               "options": {**PARTS_CONFIGS["base"], **extra}}
        variants[k], blob, *_ = pf_setup(seq, cfg, folder)
    obs = sp.observe_sequence(variants["isotropic"], seq.frames, blob)
    frames = [jax.tree.map(lambda a, t=t: a[t], obs) for t in range(obs.points.shape[0])]
    steps, states = {}, {}
    for k, p in variants.items():
        steps[k] = sp.compile_step(p)
        states[k], _ = sp.init_top_level(p, jax.random.key(0), frames[0])
        jax.block_until_ready(steps[k](states[k], frames[0]))
    ms = {k: [] for k in variants}
    for _ in range(rounds):
        for k in variants:
            st = states[k]
            for i in range(calls):
                t0 = time.perf_counter()
                st, est = steps[k](st, frames[i % len(frames)])
                jax.block_until_ready(est)
                ms[k].append(1e3 * (time.perf_counter() - t0))
    out = {k: {"median_ms": float(np.median(v)), "min_ms": float(np.min(v))}
           for k, v in ms.items()}
    print(json.dumps(out, indent=1))
    return out


HAND_DISC_M = 0.05  # skin diagnostic: the disc searched around a true hand (m at its depth)


FIGURE_CROP_PX = 64  # the skin diagnostic's figure: crops of this side around the true hand
FIGURE_EXAMPLES = 8


def _figure_crop(frame: np.ndarray, component: np.ndarray, uv: np.ndarray) -> np.ndarray | None:
    """The image around ``uv`` beside the same with ``component`` (bool) in magenta and the
    true hand as a green circle (RGB), or None near the border."""
    h = FIGURE_CROP_PX // 2
    x, y = int(round(uv[0])), int(round(uv[1]))
    if not (h <= x < frame.shape[1] - h and h <= y < frame.shape[0] - h):
        return None
    over = frame.copy()
    over[component] = (255, 0, 255)
    cv2.circle(over, (x, y), 4, (0, 255, 0), 1)
    return np.concatenate([frame[y - h:y + h, x - h:x + h], over[y - h:y + h, x - h:x + h]], 1)


def skin_diagnostic(out: Path, folders: list[str], figure: str | None = None) -> dict:
    """Where the blob line loses the visible hands (``base`` runs of seed 0 in ``out`` and their
    visibility): per hand visible in both cameras, whether the skin map (the tracker's own
    segmentation) has >= 3 px in a :data:`HAND_DISC_M` disc around the projected true hand in
    each view, whether the blob line measured it within 8 cm, and -- for a hand with skin in
    both views but not measured -- the first of the blob line's checks its connected component
    fails (another hand's projection in it, < ``MIN_BLOB_AREA`` px, cut by the border, area /
    aspect ratio, epipolar distance of the centroids; else it would pair) and, for those that
    would pair, the triangulated centroid's distance to the true hand."""
    from collections import Counter

    import cv2
    import jax.numpy as jnp

    from jaxmocap import blobs as bloblib
    from jaxmocap.camera import (
        epipolar_distance,
        fundamental_matrix,
        project,
        stack_cameras,
        to_camera,
        triangulate,
    )
    from jaxmocap.experiment.cell import pf_setup
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers.stereo_pf.observation import _segment

    counts, reasons, pair_cm, crops = Counter(), Counter(), [], []
    for folder in folders:
        name = Path(folder).name
        seq = load_dataset(folder)
        cfg = {"name": "base", "method": "pf", "body": "sequence",
               "options": dict(PARTS_CONFIGS["base"])}
        params, *_ = pf_setup(seq, cfg, folder)
        z = np.load(out / f"base_{name}_s0.npz")
        vis, truth = z["visible"], _true_parts(seq)
        cams = list(seq.cameras)
        fmat = fundamental_matrix(cams[0], cams[1])
        for t in range(len(truth)):
            seg = [_segment(params, seq.frames[t, v]) for v in range(2)]
            comps = [cv2.connectedComponentsWithStats(np.asarray(sg.skin).astype(np.uint8), 8)
                     for sg in seg]
            for k in (1, 2):
                if not vis[t, k]:
                    continue
                counts["visible"] += 1
                measured = any(z["blob_valid"][t, j] and
                               np.linalg.norm(z["points"][t, j] - truth[t, k]) < 0.08
                               for j in (1, 2))
                info = []
                for v, cam in enumerate(cams):
                    _, lab, st, cen = comps[v]
                    uv = np.asarray(project(cam, jnp.asarray(truth[t, k])))
                    r = max(2.0, float(cam.K[0, 0]) * HAND_DISC_M / float(
                        np.asarray(to_camera(cam, jnp.asarray(truth[t, k])))[2]))
                    h, w = lab.shape
                    yy, xx = np.mgrid[0:h, 0:w]
                    m = ((xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= r * r) & (lab > 0)
                    if m.sum() < 3:
                        break
                    c = Counter(lab[m].tolist()).most_common(1)[0][0]
                    ouv = np.round(np.asarray(project(cam, jnp.asarray(truth[t, 3 - k]))))
                    ouv = ouv.astype(int)
                    other = 0 <= ouv[0] < w and 0 <= ouv[1] < h and lab[ouv[1], ouv[0]] == c
                    x, y, bw, bh, a = st[c]
                    info.append({"area": int(a), "other": bool(other), "aspect": bh / max(bw, 1),
                                 "border": bool(x == 0 or y == 0 or x + bw == w or y + bh == h),
                                 "centroid": cen[c], "component": lab == c, "uv": uv})
                both = len(info) == 2
                counts["skin in both views"] += both
                counts["measured within 8 cm"] += measured
                counts["measured, skin in both"] += measured and both
                if measured or not both:
                    continue
                a = [i["area"] for i in info]
                asp = [i["aspect"] for i in info]
                if any(i["other"] for i in info):
                    why = "merged with the other hand"
                elif min(a) < bloblib.MIN_BLOB_AREA:
                    why = f"< {bloblib.MIN_BLOB_AREA} px"
                elif any(i["border"] for i in info):
                    why = "cut by the border"
                elif min(a) / max(a) < bloblib.MIN_AREA_RATIO:
                    why = "area ratio"
                elif min(asp) / max(asp) < bloblib.MIN_ASPECT_RATIO:
                    why = "aspect ratio"
                elif float(epipolar_distance(fmat, jnp.asarray(info[0]["centroid"]),
                                             jnp.asarray(info[1]["centroid"]))) > \
                        bloblib.MAX_EPIPOLAR_PX:
                    why = "epipolar distance"
                else:
                    why = "would pair"
                    x3 = np.asarray(triangulate(stack_cameras(cams), jnp.asarray(np.stack(
                        [info[0]["centroid"], info[1]["centroid"]]))))
                    pair_cm.append(float(100 * np.linalg.norm(x3 - truth[t, k])))
                    if figure and len(crops) < FIGURE_EXAMPLES:
                        crop = _figure_crop(np.asarray(seq.frames[t, 0]), info[0]["component"],
                                            info[0]["uv"])
                        crops += [] if crop is None else [crop]
                reasons[why] += 1
        print(name, dict(counts), flush=True)
    res = {"counts": dict(counts), "skin in both, not measured: first check failed": dict(reasons),
           "would pair: centroid to true hand cm, quartiles": np.percentile(
               pair_cm, [25, 50, 75]).tolist() if pair_cm else None}
    print(json.dumps(res, indent=1))
    if figure and crops:
        rows = [np.concatenate(crops[i:i + 2], 1) for i in range(0, len(crops) - 1, 2)]
        cv2.imwrite(figure, cv2.cvtColor(np.concatenate(rows, 0), cv2.COLOR_RGB2BGR))
    return res


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("out")
    r.add_argument("config", choices=CONFIGS)
    r.add_argument("folders", nargs="+")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("--set", action="append", default=[], metavar="OPTION=JSON",
                   help="a further experiment option of the configuration (e.g. init_yaw=3.1416)")
    k = sub.add_parser("skin")
    k.add_argument("out")
    k.add_argument("folders", nargs="+")
    k.add_argument("--figure", help="PNG of examples that would pair (camera 0)")
    t = sub.add_parser("timing")
    t.add_argument("folder")
    t.add_argument("--calls", type=int, default=60)
    t.add_argument("--rounds", type=int, default=4)
    p = sub.add_parser("report")
    p.add_argument("out")
    p.add_argument("--md")
    p.add_argument("--json")
    a = ap.parse_args()
    if a.cmd == "skin":
        skin_diagnostic(Path(a.out), a.folders, a.figure)
    elif a.cmd == "timing":
        timing(a.folder, a.calls, a.rounds)
    elif a.cmd == "run":
        extra = {k: json.loads(v) for k, v in (x.split("=", 1) for x in a.set)}
        run(Path(a.out), a.config, a.folders, a.seed, extra)
    else:
        report(Path(a.out), a.md, a.json)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
