"""Per-frame signals of the colour-shirt tracker against ground truth (issue 17, DEV split).

    python -m benchmarks.experiments.shirt_validity run /work/tw_dev_shirt \\
        benchmarks/experiments/world_shirt.toml robust --out /work/res_shirtval_sig
    python -m benchmarks.experiments.shirt_validity calibrate /work/res_shirtval_sig
    python -m benchmarks.experiments.shirt_validity yaw /work/tw_dev_shirt /work/res_shirtval_sig
    python -m benchmarks.experiments.shirt_validity database /work/tw_dev_shirt --out x.json
    python -m benchmarks.experiments.shirt_validity lowo /work/world /work/res_sig --out y.json

``run`` tracks every sequence of a dataset folder with one configuration of an experiment
file (the experiment's own set-up, :func:`jaxmocap.experiment.cell._track_shirt`) and writes
per sequence an ``.npz`` of: the per-frame error (cm, the configuration's joints), the
validity flag, agreement, :class:`jaxmocap.trackers.shirt.FrameSignals`, and step 1 scored
against the world's colour-id ground truth on the tracker's own crop and white balance
(``right`` / ``wrong``: share of the visible shirt pixels in the crop given their colour /
another colour; ``room``: pixels of anything else classified as shirt, relative to the
shirt's pixel count; ``oracle_*``: the same with ``W`` fitted to the ground-truth ids of
that crop, one ``W`` for the crop (``oracle_global``) and one per vertical half
(``oracle_halves``): how much a better global or a spatially varying white balance could
give).

``calibrate`` searches the reported validity rule on those files (``shirt.make_params(
report_patches=, max_residual=, min_recall=)``): for each rule the share of the frames
> 15 cm off flagged invalid and of the frames < 5 cm off flagged valid. ``yaw`` bins
``run``'s per-frame error by the subject's yaw to the cameras (:func:`yaw_table`);
``database`` scores the database query on the ground-truth maps of every view, by yaw
(:func:`database_views`); ``lowo`` fits the reported rule's three thresholds (patch-centroid
share, residual, recall) on the dev frames of all worlds but one and scores it on that world's
test frames (:func:`leave_one_world_out`, issue 36 item 5). Results:
docs/results/shirt.md ("A validity flag from the final pose").
"""

from __future__ import annotations

import argparse
import json
import tomllib
from pathlib import Path

import numpy as np

JOINTS = ["head", "neck", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist",
          "r_wrist", "l_hand", "r_hand"]  # issue 17's joints (world_shirt.toml)


def _crop_stats(shirt, params, state, frames, colour_ids):
    """Step 1 on the tracker's crops with ``state``'s white balance, scored against the
    ground-truth colour ids (module docstring); returns (n_cams, 9) rows."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.color import classify
    from jaxmocap.color.classify import THRESHOLD
    from jaxmocap.color.whitebalance import white_balance_from_ids
    from jaxmocap.sampling import crop_uv

    views = shirt.locate_and_classify(params, state, jnp.asarray(frames), None)
    rows = []
    for i in range(params.n_cams):
        uv = crop_uv(views.windows[i], params.search.work_size)
        ij = jnp.round(uv).astype(jnp.int32)
        h, w = colour_ids[i].shape
        inside = (ij[..., 0] >= 0) & (ij[..., 0] < w) & (ij[..., 1] >= 0) & (ij[..., 1] < h)
        gt = jnp.asarray(colour_ids[i]).astype(jnp.int32)[
            jnp.clip(ij[..., 1], 0, h - 1), jnp.clip(ij[..., 0], 0, w - 1)]
        gt = jnp.where(inside, gt, 0)
        crop = views.crops[i]

        def score(ids, gt=gt):
            n = jnp.maximum(jnp.sum(gt > 0), 1)
            right = jnp.sum((gt > 0) & (ids == gt)) / n
            wrong = jnp.sum((gt > 0) & (ids > 0) & (ids != gt)) / n
            room = jnp.sum((gt == 0) & (ids > 0)) / n
            return right, wrong, room

        def cls(W, image=crop):
            return classify(params.color, W, image, None, THRESHOLD, params.colours.shading,
                            params.colours.scene_colors)[0]

        W = views.cls.W[i]
        r = score(views.cls.ids[i])
        Wg = white_balance_from_ids(params.color, crop, gt, W)
        og = score(cls(Wg))
        half = params.search.work_size // 2
        ids_h = []
        for sl in (np.s_[:, :half], np.s_[:, half:]):
            Wh = white_balance_from_ids(params.color, crop[sl], gt[sl], W)
            ids_h.append(cls(Wh, crop[sl]))
        oh = score(jnp.concatenate(ids_h, axis=1))
        rows.append(jnp.stack([*r, *og, *oh, jnp.sum(gt > 0)]))
    return jax.device_get(jnp.stack(rows))


def track_wrapped(seq, cfg: dict, folder: str, wrap) -> dict:
    """The experiment cell's shirt run (:func:`jaxmocap.experiment.cell._track_shirt`, seed 0)
    with every compiled step replaced by ``wrap(params, step)`` (the program the driver runs,
    shipped or jit): how these scripts record or steer the tracker frame by frame."""
    from jaxmocap.experiment import cell
    from jaxmocap.trackers import shirt

    compile0 = shirt.compile_step

    def compile_step(params, *a, **kw):
        return wrap(params, compile0(params, *a, **kw))

    shirt.compile_step = compile_step
    try:
        return cell._track_shirt(seq, cfg, 0, folder)
    finally:
        shirt.compile_step = compile0


def run(dataset: str, config: str, name: str, out: str, only=None, sets=()) -> None:
    import jax
    import jax.numpy as jnp
    from tqdm import tqdm

    from jaxmocap.body import keypoints
    from jaxmocap.experiment.config import dataset_sequences, load_config
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers import shirt

    cfg = next(c for c in load_config(config).configs if c.name == name).to_dict()
    for kv in sets:  # option overrides, KEY=JSON
        k, v = kv.split("=", 1)
        cfg["options"][k] = json.loads(v)
    Path(out).mkdir(parents=True, exist_ok=True)
    stats_jit = jax.jit(lambda p, s, f, c: _crop_stats(shirt, p, s, f, c))
    for seq_info in dataset_sequences(dataset):
        if only and seq_info.name not in only:
            continue
        folder = str(seq_info.folder)
        seq = load_dataset(folder)
        rec = []

        def wrap(params, step0, _rec=rec):
            def step(state, *args):
                new, o = step0(state, *args)
                _rec.append((params, state, o))
                return new, o

            return step

        res = track_wrapped(seq, cfg, folder, wrap)
        body = res["body"]
        g = seq.groundtruth
        joints = cfg["joints"]
        kp = np.asarray(jax.vmap(lambda x, b=body: keypoints(b, x))(jnp.asarray(res["q"])))
        ip = [list(body.keypoint_names).index(j) for j in joints]
        ig = [list(g["keypoint_names"]).index(j) for j in joints]
        err = np.linalg.norm(kp[:, ip] - g["keypoints"][:, ig], axis=-1).mean(1) * 100
        qb = np.stack([np.asarray(o.q_blend) for _, _, o in rec])
        kpb = np.asarray(jax.vmap(lambda x, b=body: keypoints(b, x))(jnp.asarray(qb)))
        err_blend = np.linalg.norm(kpb[:, ip] - g["keypoints"][:, ig], axis=-1).mean(1) * 100
        sig = jax.tree.map(lambda *a: np.stack(a), *[o.signals for _, _, o in rec])
        stats = []
        for t, (p, s, _) in enumerate(tqdm(rec, desc=f"{seq_info.name} step-1 stats")):
            stats.append(np.asarray(stats_jit(p, s, seq.frames[t], g["colour_ids"][t])))
        np.savez(Path(out) / f"{seq_info.name}.npz", err=err, valid=res["valid"],
                 err_blend=err_blend,
                 agreement=np.array([o.agreement for _, _, o in rec]),
                 patches=np.array([np.sum(o.visible) for _, _, o in rec]),
                 fraction=np.stack([o.fraction for _, _, o in rec]),
                 W=np.stack([s.W for _, s, _ in rec]), stats=np.stack(stats),
                 times=res["times"], **{f"sig_{k}": v for k, v in sig._asdict().items()})
        print(seq_info.name, f"mean {np.nanmean(err):.1f} cm, valid {res['valid'].mean():.0%}")


def _load(folder: str) -> dict[str, dict]:
    return {p.stem: dict(np.load(p)) for p in sorted(Path(folder).glob("*.npz"))}


def _features(cat: dict) -> dict[str, np.ndarray]:
    """Per-frame validity signals; each oriented so that larger = more likely right."""
    return {
        "agreement": cat["agreement"],
        "patches": cat["patches"],
        "-residual_max": -cat["sig_residual"].max(1),
        "coverage_min": cat["sig_coverage"].min(1),
        "coverage_mean": cat["sig_coverage"].mean(1),
        "recall_min": cat["sig_recall"].min(1),
        "recall_mean": cat["sig_recall"].mean(1),
        "-blend_distance": -cat["sig_blend_distance"],
        "-db_spread": -cat["sig_db_spread"],
        "fraction_min": cat["fraction"].min(1),
    }


def calibrate(folder: str, good: float = 5.0, bad: float = 15.0) -> dict:
    """Rates of single-signal thresholds and of two-signal conjunctions on the files of
    ``run`` (module docstring); prints the best and returns them."""
    data = _load(folder)
    cat = {k: np.concatenate([d[k] for d in data.values()]) for k in next(iter(data.values()))
           if k != "W"}
    err = cat["err"]
    isbad, isgood = err > bad, err < good
    print(f"{len(err)} frames: {isbad.sum()} > {bad} cm, {isgood.sum()} < {good} cm")

    def rates(valid):
        return ((~valid & isbad).sum() / max(isbad.sum(), 1),
                (valid & isgood).sum() / max(isgood.sum(), 1))

    bi, gv = rates(cat["valid"].astype(bool))
    print(f"tracker's flag: bad invalid {bi:.3f} good valid {gv:.3f}")
    feats = _features(cat)
    for k, v in feats.items():
        print(f"{k:15s} good median {np.median(v[isgood]):8.3f}  bad median "
              f"{np.median(v[isbad]):8.3f}")
    out = {"frames": int(len(err)), "bad": int(isbad.sum()), "good": int(isgood.sum()),
           "single": {}, "pairs": []}
    grid = {k: np.unique(np.quantile(v, np.linspace(0, 1, 41))) for k, v in feats.items()}
    for k, v in feats.items():  # ROC-ish: the good frames kept at >= 95% of the bad flagged
        best = None
        for th in grid[k]:
            bi, gv = rates(v >= th)
            if bi >= 0.95 and (best is None or gv > best[2]):
                best = (float(th), bi, gv)
        out["single"][k] = best
        print(f"single {k:15s}", best)
    names = list(feats)
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            best = None
            for ta in grid[a]:
                va = feats[a] >= ta
                for tb in grid[b]:
                    bi, gv = rates(va & (feats[b] >= tb))
                    score = min(bi - 0.95, gv - 0.90)
                    if best is None or score > best[0]:
                        best = (score, float(ta), float(tb), bi, gv)
            out["pairs"].append((a, b, *best))
    out["pairs"].sort(key=lambda r: -r[2])
    for r in out["pairs"][:12]:
        print(f"pair {r[0]} >= {r[3]:.4f} & {r[1]} >= {r[4]:.4f}: bad invalid {r[5]:.3f} "
              f"good valid {r[6]:.3f}")
    return out


def yaw_table(dataset: str, folder: str, bins=(0, 30, 60, 90, 120, 180)) -> dict:
    """Per-frame error of ``run``'s files against the subject's yaw relative to the cameras
    (deliverable 3): 0 = facing a camera, 90 = side-on, 180 = back to it; each frame binned by
    its most frontal camera (the one the database query sees best) and by the least frontal.
    The facing direction is the ground truth's shoulder axis x up (no body naming beyond the
    keypoint roles ``l_shoulder`` / ``r_shoulder`` / ``neck``)."""
    from jaxmocap.camera import camera_center
    from jaxmocap.io.cameras import load_cameras
    from jaxmocap.metrics import facing_angle

    rows = []
    for name, d in _load(folder).items():
        seq = Path(dataset) / name
        with np.load(seq / "groundtruth.npz") as z:
            kp, names = z["keypoints"], list(z["keypoint_names"])
        cams = load_cameras(seq / "cameras.json")[0]
        yaws = facing_angle(kp[:, names.index("l_shoulder")], kp[:, names.index("r_shoulder")],
                            kp[:, names.index("neck")],
                            np.stack([np.asarray(camera_center(c)) for c in cams]))
        for t in range(len(d["err"])):
            eb = d["err_blend"][t] if "err_blend" in d else np.nan
            rows.append((name, yaws[t].min(), yaws[t].max(), d["err"][t], bool(d["valid"][t]),
                         eb))
    out = {}
    for label, col in (("most frontal camera", 1), ("least frontal camera", 2)):
        out[label] = []
        for lo, hi in zip(bins[:-1], bins[1:], strict=True):
            e = np.array([r[3] for r in rows if lo <= r[col] < hi])
            v = np.array([r[4] for r in rows if lo <= r[col] < hi])
            eb = np.array([r[5] for r in rows if lo <= r[col] < hi])
            if len(e):
                out[label].append({"yaw": f"{lo}-{hi}", "frames": int(len(e)),
                                   "mean_cm": round(float(np.mean(e)), 1),
                                   "median_cm": round(float(np.median(e)), 1),
                                   "over_15cm": round(float(np.mean(e > 15)), 2),
                                   "valid": round(float(np.mean(v)), 2),
                                   "blend_median_cm": round(float(np.median(eb)), 1)})
            print(label, out[label][-1] if len(e) else (lo, hi, 0))
    return out


def database_views(dataset: str, joints: list[str], bins=(0, 30, 60, 90, 120, 180)) -> dict:
    """The database and its 10-NN blend on the views of the dev sequences, step 1 left out
    (deliverable 3): each camera's ground-truth colour-id map normalised to the tiny map
    (:func:`jaxmocap.posedb.tiny_from_classified`) queries the sequence's database; the
    blended pose's joint angles (10-NN, and the nearest pose alone) are put on the
    ground-truth root and scored (cm, ``joints``), binned by the subject's yaw to that camera
    (0 = facing it, 90 = side-on, 180 = back)."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.body import keypoints
    from jaxmocap.experiment import cell
    from jaxmocap.experiment.config import dataset_sequences
    from jaxmocap.io.cameras import load_cameras
    from jaxmocap.posedb import load_or_build
    from jaxmocap.posedb._search import estimate_pose, tiny_from_classified

    cfg = {"body": "sequence", "garment": "sequence", "options": {}}
    rows = []
    for s in dataset_sequences(dataset):
        body = cell._body(cfg, s.folder)
        garment = cell._garment(cfg, body, s.folder)
        db = load_or_build(None, body, garment, progress=False)
        with np.load(Path(s.folder) / "groundtruth.npz") as z:
            gq, kp, names, cids = z["q"], z["keypoints"], list(z["keypoint_names"]), z["colour_ids"]
        cams = load_cameras(Path(s.folder) / "cameras.json")[0]
        ip = [list(body.keypoint_names).index(j) for j in joints]
        ig = [names.index(j) for j in joints]

        @jax.jit
        def query(ids, q_true, db=db, body=body):
            q10, nb = estimate_pose(db, tiny_from_classified(ids))
            q1 = db.poses[nb.index[0]].astype(q_true.dtype)
            out = []
            for q in (q10.astype(q_true.dtype), q1):
                out.append(keypoints(body, jnp.concatenate([q_true[:6], q[6:]])))
            return jnp.stack(out)

        lat = kp[:, names.index("l_shoulder")] - kp[:, names.index("r_shoulder")]
        fwd = np.cross(lat, [0.0, 0.0, 1.0])[:, :2]
        for c, cam in enumerate(cams):
            centre = -np.asarray(cam.R).T @ np.asarray(cam.t)
            to_cam = centre[None, :2] - kp[:, names.index("neck"), :2]
            cos = np.sum(fwd * to_cam, 1) / (np.linalg.norm(fwd, axis=1)
                                             * np.linalg.norm(to_cam, axis=1))
            yaw = np.degrees(np.arccos(np.clip(cos, -1, 1)))
            for t in range(len(gq)):
                if (cids[t, c] > 0).sum() < 200:
                    continue
                k = np.asarray(query(jnp.asarray(cids[t, c].astype(np.int32)),
                                     jnp.asarray(gq[t])))
                e = np.linalg.norm(k[:, ip] - kp[t, ig][None], axis=-1).mean(1) * 100
                rows.append((yaw[t], e[0], e[1]))
        print(s.name, len(rows), flush=True)
    rows = np.array(rows)
    out = []
    for lo, hi in zip(bins[:-1], bins[1:], strict=True):
        m = (rows[:, 0] >= lo) & (rows[:, 0] < hi)
        if m.any():
            out.append({"yaw": f"{lo}-{hi}", "views": int(m.sum()),
                        "blend_median_cm": round(float(np.median(rows[m, 1])), 1),
                        "blend_mean_cm": round(float(np.mean(rows[m, 1])), 1),
                        "nearest_median_cm": round(float(np.median(rows[m, 2])), 1)})
            print(out[-1])
    return {"bins": out}


WORLD_CONFIG = Path(__file__).with_name("world_shirt.toml")


def world_rule(config: Path = WORLD_CONFIG) -> tuple:
    """The first round's reported rule as (share of the 40 patch centroids of a 20-patch shirt
    in two cameras, residual, recall), read from the ``validated`` configuration of
    ``world_shirt.toml`` so that the thresholds live in one place."""
    cfg = next(c for c in tomllib.loads(config.read_text())["config"]
               if c["name"] == "validated")["options"]
    return (cfg["report_patches"] / 40, cfg["max_residual"], cfg["min_recall"])


def world_family(spec: dict) -> str:
    """The test world a sequence belongs to for leave-one-world-out (issue 36 item 5), from its
    spec: Blender Cycles, MuJoCo with a body from another package, or the first round (MuJoCo,
    the bundled body scaled)."""
    if spec.get("renderer") == "cycles":
        return "cycles"
    return "package bodies" if spec.get("body", "scaled") != "scaled" else "first round"


def _rule_features(dataset: str, data: dict) -> dict:
    """Per sequence: the three signals of the reported rule in a form that carries across
    shirts (the share of the shirt's patch centroids measured in all cameras, not a count),
    the error, the flag, the family and the split."""
    from jaxmocap.synth.world.split import load_split

    split = {s["name"]: s for s in load_split()}
    out = {}
    for name, d in data.items():
        doc = json.loads((Path(dataset) / name / "garment.json").read_text())
        n_cams = d["sig_recall"].shape[1]
        out[name] = dict(
            share=d["patches"] / (n_cams * len(doc["patches"])),
            residual=d["sig_residual"].max(1), recall=d["sig_recall"].min(1), err=d["err"],
            family=world_family(split[name]["world"]), split=split[name]["split"])
    return out


def _rates(f: dict, rule, good: float, bad: float) -> dict:
    ok = (f["share"] >= rule[0]) & (f["residual"] <= rule[1]) & (f["recall"] >= rule[2])
    err = f["err"]
    isbad, isgood = err > bad, err < good
    return {"frames": int(len(err)),
            "bad_invalid": float((~ok & isbad).sum() / max(isbad.sum(), 1)),
            "good_valid": float((ok & isgood).sum() / max(isgood.sum(), 1)),
            "valid": float(ok.mean()), "valid_cm": float(np.mean(err[ok])) if ok.any() else None,
            "all_cm": float(np.mean(err)), "bad_frames": int(isbad.sum()),
            "good_frames": int(isgood.sum())}


def fit_rule(f: dict, good: float = 5.0, bad: float = 15.0) -> tuple:
    """The three thresholds (share >=, residual <=, recall >=) that best reach >= 95% of the
    bad frames invalid and >= 90% of the good ones valid (max of the smaller margin) on a grid
    of each signal's quantiles, as ``calibrate``."""
    isbad, isgood = f["err"] > bad, f["err"] < good
    qs = np.linspace(0, 1, 31)
    grid = [np.unique(np.quantile(f[k], qs)) for k in ("share", "residual", "recall")]
    best = None
    for a in grid[0]:
        va = f["share"] >= a
        for b in grid[1]:
            vab = va & (f["residual"] <= b)
            ok = vab[None] & (f["recall"][None] >= grid[2][:, None])
            bi = (~ok & isbad).sum(1) / max(isbad.sum(), 1)
            gv = (ok & isgood).sum(1) / max(isgood.sum(), 1)
            score = np.minimum(bi - 0.95, gv - 0.90)
            i = int(np.argmax(score))
            if best is None or score[i] > best[0]:
                best = (float(score[i]), float(a), float(b), float(grid[2][i]))
    return best[1:]


def leave_one_world_out(dataset: str, folder: str, good: float = 5.0, bad: float = 15.0
                        ) -> dict:
    """For each world: the rule fitted on the **dev** frames of the other worlds, scored on the
    held-out world's **test** frames; beside it the first-round rule (``validated``,
    calibrated on the first round's dev) on every world's test frames."""
    feats = _rule_features(dataset, _load(folder))

    def pool(pred):
        rows = [v for v in feats.values() if pred(v)]
        return {k: np.concatenate([r[k] for r in rows]) for k in
                ("share", "residual", "recall", "err")} if rows else None

    out = {"good_cm": good, "bad_cm": bad, "worlds": {}}
    for w in sorted({v["family"] for v in feats.values()}):
        train = pool(lambda v, w=w: v["family"] != w and v["split"] == "dev")
        test = pool(lambda v, w=w: v["family"] == w and v["split"] == "test")
        if test is None:
            continue
        row = {"first_round_rule": _rates(test, world_rule(), good, bad)}
        if train is not None:
            rule = fit_rule(train, good, bad)
            row |= {"rule": rule, "held_out": _rates(test, rule, good, bad)}
        out["worlds"][w] = row
        print(w, json.dumps(row))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run")
    r.add_argument("dataset")
    r.add_argument("config")
    r.add_argument("name")
    r.add_argument("--out", required=True)
    r.add_argument("--only", nargs="*")
    r.add_argument("--set", nargs="*", default=[])
    c = sub.add_parser("calibrate")
    c.add_argument("folder")
    y = sub.add_parser("yaw")
    y.add_argument("dataset")
    y.add_argument("folder")
    lo = sub.add_parser("lowo")
    lo.add_argument("dataset")
    lo.add_argument("folder")
    lo.add_argument("--out")
    v = sub.add_parser("database")
    v.add_argument("dataset")
    v.add_argument("--out")
    a = ap.parse_args()
    if a.cmd == "run":
        run(a.dataset, a.config, a.name, a.out, a.only, a.set)
    elif a.cmd == "yaw":
        yaw_table(a.dataset, a.folder)
    elif a.cmd == "lowo":
        res = leave_one_world_out(a.dataset, a.folder)
        if a.out:
            Path(a.out).write_text(json.dumps(res, indent=1))
    elif a.cmd == "database":
        res = database_views(a.dataset, JOINTS)
        if a.out:
            Path(a.out).write_text(json.dumps(res, indent=1))
    else:
        calibrate(a.folder)


if __name__ == "__main__":
    main()
