"""Where the colour-shirt tracker's all-frames error comes from on side and back views and after
a loss (issue 38 items 2-3; DEV split only).

    python -m benchmarks.experiments.shirt_views ladder /work/world --out x.json [--only ...]
    python -m benchmarks.experiments.shirt_views query /work/world --out y.json

``ladder`` tracks each dev sequence with one configuration of an experiment file (default
``world2_shirt.toml``'s ``robust``, through the experiment's own set-up,
:func:`jaxmocap.experiment.cell._track_shirt`) and rungs of oracles swapped in, one at a time:

* ``tracker``: as configured; its all-frames error split into the frames before the first
  invalid one and after it, the valid and the invalid frames, and the error of the placed
  database blend ``q_blend`` (step 2's start of every lost frame);
* ``true_start``: every frame starts from the ground truth of the frame before (state ``q``
  the true pose, ``valid`` and tracked): what the tracker does when it is never lost, i.e.
  how much of the all-frames error re-acquisition could win back;
* ``true_colours`` (``--rungs``): the capture with every shirt pixel (ground-truth colour id
  > 0) painted with its colour's median RGB over the sequence in that camera
  (:func:`paint_true_colours`), the rest of the image as it is, set-up and tracking alike:
  the shirt's appearance without shading, lamps or mixed pixels, so that step 1 classifies
  the shirt as well as the colour model can separate its colours -- what a colour layer that
  gives every shirt pixel its right label (issue 37) would leave.

Per frame it also keeps each camera's classified tiny map (step 1 on the tracker's own crop
and white balance). ``query`` then scores the database query (:func:`jaxmocap.posedb.
estimate_pose`, the 10-NN blend) from the ground-truth colour-id maps and from those
classified maps, by the torso's yaw to that camera (0-45, 45-90, 90-180 degrees: facing it,
turned, side-on or the back), two ways: the blend's joint angles on the true root (the
articulation alone, as ``shirt_validity.py database``) and the blend's own orientation placed
at the true root position (:func:`jaxmocap.posedb.pose_in_camera`: what step 2 hands the
IK). With ``--hypotheses`` it also scores the orientation hypotheses of
:func:`jaxmocap.posedb.estimate_hypotheses` (issue 38 item 2): the first, the best of them
(an oracle of the choice) and the one whose rendered tiny map agrees best with the query (the
tracker's choice criterion in one camera). Errors are cm over issue 17's ten joints.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from shirt_validity import track_wrapped  # noqa: E402

JOINTS = ["head", "neck", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist",
          "r_wrist", "l_hand", "r_hand"]
DEV = ["shirt_00", "shirt_03", "shirt_06", "shirt_09", "shirt_12", "shirt_13"]
YAW_BINS = (0, 45, 90, 180.01)
CONFIG = "benchmarks/experiments/world2_shirt.toml"


def torso_yaw(kp: np.ndarray, names: list[str], cams) -> np.ndarray:
    """(T, n_cams) facing angle (deg) of the true torso to each camera
    (:func:`jaxmocap.metrics.facing_angle`): 0 facing it, 90 side-on, 180 the back."""
    from jaxmocap.camera import camera_center
    from jaxmocap.metrics import facing_angle

    centres = np.stack([np.asarray(camera_center(c)) for c in cams])
    return facing_angle(kp[:, names.index("l_shoulder")], kp[:, names.index("r_shoulder")],
                        kp[:, names.index("neck")], centres)


def paint_true_colours(frames: np.ndarray, colour_ids: np.ndarray, stride: int = 5
                       ) -> np.ndarray:
    """``frames`` (T, n_cams, H, W, 3) uint8 with each pixel of colour id k > 0 (``colour_ids``
    (T, n_cams, H, W)) replaced by the median RGB of colour k's pixels in that camera (over
    every ``stride``-th frame); a colour never seen in a camera keeps its pixels."""
    out = np.array(frames, copy=True)
    for c in range(frames.shape[1]):
        ids, px = colour_ids[::stride, c], frames[::stride, c]
        for k in np.unique(colour_ids[:, c]):
            if k == 0 or not (ids == k).any():
                continue
            out[:, c][colour_ids[:, c] == k] = np.median(px[ids == k], axis=0).astype(np.uint8)
    return out


def _track(seq, folder, cfg, mode, tiny_maps):
    """One tracker run; ``mode`` "tracker", "true_start" or "true_colours". Returns per-frame
    q, q_blend, valid (and fills ``tiny_maps`` with the classified tiny maps when given a list)."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.render import TINY_SIZE, resample_ids, window_from_mask
    from jaxmocap.trackers.shirt.frame import locate_and_classify

    gq = np.asarray(seq.groundtruth["q"])
    if mode == "true_colours":
        seq = seq._replace(frames=paint_true_colours(np.asarray(seq.frames),
                                                     np.asarray(seq.groundtruth["colour_ids"])))
    rec = []

    def tiny_of(params, state, frames):
        views = locate_and_classify(params, state, frames, None)
        return jax.vmap(lambda ids: resample_ids(ids, window_from_mask(ids > 0), TINY_SIZE))(
            views.cls.ids)

    tiny_jit = jax.jit(tiny_of)

    def wrap(params, step0):
        def step(state, frames, *args):
            t = len(rec)
            if mode == "true_start":
                state = dataclasses.replace(
                    state, q=jnp.asarray(gq[max(t - 1, 0)], state.q.dtype),
                    valid=jnp.array(True), tracked=jnp.array(10, jnp.int32))
            if tiny_maps is not None:
                tiny_maps.append(np.asarray(tiny_jit(params, state, jnp.asarray(frames))))
            new, o = step0(state, frames, *args)
            rec.append(jax.device_get((o.q, o.q_blend, o.valid)))
            return new, o

        return step

    res = track_wrapped(seq, cfg, folder, wrap)
    q = np.stack([np.asarray(r[0], np.float64) for r in rec])
    qb = np.stack([np.asarray(r[1], np.float64) for r in rec])
    valid = np.array([bool(r[2]) for r in rec])
    return q, qb, valid, res["body"], res["times"]


def _errors(body, qs, kp_true, ip, ig):
    import jax
    import jax.numpy as jnp

    from jaxmocap.body import keypoints

    k = np.asarray(jax.vmap(lambda x: keypoints(body, x))(jnp.asarray(qs)))
    return np.linalg.norm(k[:, ip] - kp_true[:, ig], axis=-1).mean(-1) * 100


def _cfg(config: str, name: str, sets=()) -> dict:
    from jaxmocap.experiment.config import load_config

    cfg = next(c for c in load_config(config).configs if c.name == name).to_dict()
    for kv in sets:
        k, v = kv.split("=", 1)
        cfg["options"][k] = json.loads(v)
    return cfg


def _mean(x):
    x = np.asarray(x, float)
    return None if x.size == 0 or np.all(np.isnan(x)) else round(float(np.nanmean(x)), 2)


def ladder(dataset: str, out: str, config: str = CONFIG, name: str = "robust", only=None,
           sets=(), maps_dir: str | None = None, rungs=("tracker", "true_start")) -> dict:
    from jaxmocap.body import keypoint_index
    from jaxmocap.synth.dataset import load_dataset

    cfg = _cfg(config, name, sets)
    result = {"config": f"{config}:{name}", "options": cfg["options"], "split": "dev",
              "sequences": {}}
    for s in only or DEV:
        folder = str(Path(dataset) / s)
        seq = load_dataset(folder)
        g = seq.groundtruth
        names = list(g["keypoint_names"])
        row = {}
        for mode in rungs:
            t0 = time.time()
            maps = [] if (mode == "tracker" and maps_dir) else None
            q, qb, valid, body, times = _track(seq, folder, cfg, mode, maps)
            ip = keypoint_index(body, JOINTS)
            ig = [names.index(j) for j in JOINTS]
            e = _errors(body, q, g["keypoints"], ip, ig)
            eb = _errors(body, qb, g["keypoints"], ip, ig)
            yaw = torso_yaw(g["keypoints"], names, seq.cameras).min(1)
            inv = np.flatnonzero(~valid)
            first = int(inv[0]) if len(inv) else len(e)
            r = {"frames": len(e), "all": _mean(e), "valid_share": round(float(valid.mean()), 3),
                 "valid": _mean(e[valid]), "invalid": _mean(e[~valid]),
                 "first_invalid": first, "before_first_invalid": _mean(e[:first]),
                 "from_first_invalid": _mean(e[first:]), "placed_blend": _mean(eb),
                 "placed_blend_root_cm": _mean(np.linalg.norm(qb[:, :3] - g["q"][:, :3], axis=1)
                                               * 100),
                 "by_yaw_most_frontal_camera": {
                     f"{lo:.0f}-{min(hi, 180):.0f}": {"frames": int(m.sum()), "all": _mean(e[m])}
                     for lo, hi in zip(YAW_BINS[:-1], YAW_BINS[1:], strict=True)
                     if (m := (yaw >= lo) & (yaw < hi)).any()},
                 "s": round(time.time() - t0, 1)}
            row[mode] = r
            print(s, mode, {k: r[k] for k in ("all", "valid_share", "valid", "invalid",
                                              "first_invalid", "placed_blend")}, flush=True)
            if maps is not None:
                Path(maps_dir).mkdir(parents=True, exist_ok=True)
                np.savez_compressed(Path(maps_dir) / f"{s}.npz", tiny=np.stack(maps), e=e,
                                    valid=valid)
        result["sequences"][s] = row
        Path(out).write_text(json.dumps(result, indent=1))
    for mode in rungs:
        rows = [result["sequences"][s][mode] for s in result["sequences"]]
        n = sum(r["frames"] for r in rows)
        result[f"mean_{mode}"] = {
            "all_frames_cm (frame-weighted)": round(sum(r["all"] * r["frames"] for r in rows) / n,
                                                    2),
            "all_frames_cm (mean of sequences)": round(float(np.mean([r["all"] for r in rows])),
                                                       2)}
    Path(out).write_text(json.dumps(result, indent=1))
    return result


def query(dataset: str, out: str, maps_dir: str | None, only=None, hypotheses: bool = False
          ) -> dict:
    """The database query by yaw bin (module docstring)."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.body import keypoint_index, keypoints
    from jaxmocap.camera import to_camera
    from jaxmocap.experiment import cell
    from jaxmocap.io.cameras import load_cameras
    from jaxmocap.posedb import estimate_pose, load_or_build, pose_in_camera, tiny_from_classified

    cfg = {"body": "sequence", "garment": "sequence", "options": {}}
    rows = []  # (seq, source, yaw, err joints on true root, err placed orientation, hyp...)
    for s in only or DEV:
        folder = Path(dataset) / s
        body = cell._body(cfg, folder)
        garment = cell._garment(cfg, body, folder)
        db = load_or_build(None, body, garment, progress=False)
        with np.load(folder / "groundtruth.npz") as z:
            gq, kp, names, cids = z["q"], z["keypoints"], list(z["keypoint_names"]), z["colour_ids"]
        cams = load_cameras(folder / "cameras.json")[0]
        ip = jnp.asarray(keypoint_index(body, JOINTS))
        ig = [names.index(j) for j in JOINTS]
        yaw = torso_yaw(kp, names, cams)
        classified = None
        if maps_dir and (Path(maps_dir) / f"{s}.npz").exists():
            classified = np.load(Path(maps_dir) / f"{s}.npz")["tiny"]
        hyp_fn = canon = None
        if hypotheses:
            from jaxmocap.posedb import canonical_camera, estimate_hypotheses, map_distance
            from jaxmocap.render import tiny_id_map

            hyp_fn = estimate_hypotheses
            canon = canonical_camera(jnp.float32)

        def scored(q, q_true, cam, kp_true, body=body, ip=ip):
            dt = q_true.dtype
            q = q.astype(dt)
            on_root = keypoints(body, jnp.concatenate([q_true[:6], q[6:]]))
            placed = pose_in_camera(q, cam, to_camera(cam, q_true[:3]))
            placed = keypoints(body, placed)
            return jnp.stack([jnp.linalg.norm(on_root[ip] - kp_true, axis=-1).mean() * 100,
                              jnp.linalg.norm(placed[ip] - kp_true, axis=-1).mean() * 100])

        @jax.jit
        def one(tiny, q_true, cam, kp_true, db=db, body=body, garment=garment, hyp_fn=hyp_fn,
                canon=canon, scored=scored):
            q10, _ = estimate_pose(db, tiny)
            out = [scored(q10, q_true, cam, kp_true)]
            if hyp_fn is not None:
                hq, hd = hyp_fn(db, tiny)
                e = jax.vmap(lambda q: scored(q, q_true, cam, kp_true))(hq)
                # the tracker's criterion in one camera: the hypothesis's own rendered tiny
                # map against the query
                d = jax.vmap(lambda q: map_distance(tiny_id_map(body, garment, q, canon),
                                                    tiny))(hq)
                d = jnp.where(jnp.isfinite(hd), d, jnp.inf)
                out += [e[0], jnp.min(e, axis=0), e[jnp.argmin(d)]]
            return jnp.concatenate(out)

        for c, cam in enumerate(cams):
            for t in range(len(gq)):
                if (cids[t, c] > 0).sum() < 200:
                    continue
                kpt = jnp.asarray(kp[t, ig])
                qt = jnp.asarray(gq[t])
                gt_tiny = tiny_from_classified(jnp.asarray(cids[t, c].astype(np.int32)))
                rows.append((s, "ground truth", yaw[t, c], *np.asarray(one(gt_tiny, qt, cam, kpt))))
                if classified is not None and t < len(classified):
                    ct = jnp.asarray(classified[t, c].astype(np.int32))
                    if int(jnp.sum(ct > 0)) > 0:
                        rows.append((s, "classified", yaw[t, c],
                                     *np.asarray(one(ct, qt, cam, kpt))))
        print(s, len(rows), flush=True)
    cols = ["blend_on_true_root", "blend_placed"]
    if hypotheses:
        cols += [f"{h}_{k}" for h in ("first_hypothesis", "best_hypothesis_oracle",
                                      "chosen_by_render") for k in ("on_true_root", "placed")]
    result = {"split": "dev", "sequences": only or DEV, "columns_cm": cols, "bins": []}
    for src in ("ground truth", "classified"):
        for lo, hi in zip(YAW_BINS[:-1], YAW_BINS[1:], strict=True):
            sel = [r for r in rows if r[1] == src and lo <= r[2] < hi]
            if not sel:
                continue
            a = np.array([r[3:] for r in sel], float)
            b = {"maps": src, "yaw": f"{lo:.0f}-{min(hi, 180):.0f}", "views": len(sel)}
            for j, cname in enumerate(cols):
                b[cname + "_mean"] = round(float(np.mean(a[:, j])), 1)
                b[cname + "_median"] = round(float(np.median(a[:, j])), 1)
            result["bins"].append(b)
            print(b, flush=True)
    Path(out).write_text(json.dumps(result, indent=1))
    return result


def speed(out: str, option: str = "own_start", reps: int = 20) -> dict:
    """The tracked frame's step time with ``rounds.<option>`` off and on (``own_start``,
    ``orientation_hypotheses`` = 2, ``skin_terms``), alternated in one run
    (``benchmarks/bench_shirt.py``'s set-up: two 640x480 cameras, its database, the tracker
    as shipped; ``JAXMOCAP_BENCH_QUICK=1``: its quick set-up). The state is the one after the
    first (valid) frame, so every timed frame is a tracked one."""
    import jax

    from benchmarks import bench_shirt
    from benchmarks._common import sized, time_call
    from jaxmocap.trackers import shirt

    width, height = sized(full=(640, 480), quick=(320, 240))
    s = bench_shirt.setup(width, height, sized(full=bench_shirt.DB_SIZE, quick=500))
    base = s["params"]
    value = True if option in ("own_start", "skin_terms") else 2
    extra = {}
    if option == "skin_terms":  # the skin class from the garment's albedo (no scribbles here)
        from jaxmocap.trackers.shirt.skin import make_skin_terms

        extra["skin"] = make_skin_terms(base.body, base.garment, base.color, None,
                                        base.colours.scene_colors, base.colours.shading)
    other = dataclasses.replace(base, rounds=dataclasses.replace(base.rounds, **{option: value}),
                                **extra)
    runs = {}
    for name, prm in (("off", base), ("on", other)):
        st = shirt.init(prm, s["state"].W, s["state"].q)
        st, o = shirt.step(prm, st, s["frames"])
        assert bool(o.valid), name
        jax.block_until_ready(shirt.step(prm, st, s["frames"]))
        runs[name] = (prm, st)
    times = {"off": [], "on": []}
    for _ in range(reps):  # alternated
        for name, (prm, st) in runs.items():
            med, _ = time_call(lambda prm=prm, st=st: shirt.step(prm, st, s["frames"]), n=3,
                               warmup=0)
            times[name].append(med)
    res = {"option": option, "size": f"{width}x{height}", "reps": reps,
           "median_ms": {k: round(float(np.median(v)), 2) for k, v in times.items()},
           "min_ms": {k: round(float(np.min(v)), 2) for k, v in times.items()}}
    print(res)
    Path(out).write_text(json.dumps(res, indent=1))
    return res


def experiment_yaw(dataset: str, folder: str, out: str) -> dict:
    """Per-frame all-frames error of an experiment's cells (``error_cm`` of each cell's
    ``poses.npz``) by the yaw of the most frontal camera, per configuration, pooled over the
    sequences of the first round and of the second (frames pooled)."""
    from jaxmocap.io.cameras import load_cameras

    acc: dict = {}
    for cell in sorted(Path(folder, "cells").iterdir()):
        seq, config, _ = cell.name.split("__")
        d = np.load(cell / "poses.npz")
        with np.load(Path(dataset) / seq / "groundtruth.npz") as z:
            kp, names = z["keypoints"], list(z["keypoint_names"])
        cams = load_cameras(Path(dataset) / seq / "cameras.json")[0]
        yaw = torso_yaw(kp, names, cams).min(1)
        part = "second round" if int(seq.split("_")[1]) >= 12 else "first round"
        for lo, hi in zip(YAW_BINS[:-1], YAW_BINS[1:], strict=True):
            m = (yaw >= lo) & (yaw < hi)
            key = (config, part, f"{lo:.0f}-{min(hi, 180):.0f}")
            acc.setdefault(key, []).extend(d["error_cm"][m].tolist())
    res = [{"config": c, "part": p, "yaw": y, "frames": len(v),
            "mean_cm": round(float(np.mean(v)), 2) if v else None}
           for (c, p, y), v in sorted(acc.items())]
    for r in res:
        print(r)
    Path(out).write_text(json.dumps(res, indent=1))
    return res


def main() -> None:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    a = sub.add_parser("ladder")
    a.add_argument("dataset")
    a.add_argument("--out", required=True)
    a.add_argument("--config", default=CONFIG)
    a.add_argument("--name", default="robust")
    a.add_argument("--only", nargs="*")
    a.add_argument("--set", nargs="*", default=[])
    a.add_argument("--maps")
    a.add_argument("--rungs", nargs="*", default=["tracker", "true_start"])
    b = sub.add_parser("query")
    b.add_argument("dataset")
    b.add_argument("--out", required=True)
    b.add_argument("--maps")
    b.add_argument("--only", nargs="*")
    b.add_argument("--hypotheses", action="store_true")
    c = sub.add_parser("speed")
    c.add_argument("--out", required=True)
    c.add_argument("--option", default="own_start")
    c.add_argument("--reps", type=int, default=20)
    e = sub.add_parser("yaw")
    e.add_argument("dataset")
    e.add_argument("folder")
    e.add_argument("--out", required=True)
    args = ap.parse_args()
    if args.cmd == "yaw":
        experiment_yaw(args.dataset, args.folder, args.out)
    elif args.cmd == "speed":
        speed(args.out, args.option, args.reps)
    elif args.cmd == "ladder":
        ladder(args.dataset, args.out, args.config, args.name, args.only, args.set, args.maps,
               tuple(args.rungs))
    else:
        query(args.dataset, args.out, args.maps, args.only, args.hypotheses)


if __name__ == "__main__":
    main()
