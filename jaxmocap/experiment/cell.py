"""One cell of an experiment: a tracker configuration and a seed on one sequence.

:func:`compute_cell` runs on a worker (or in-process): it loads the sequence, sets the tracker
up the way a user sets up a capture session, tracks every frame and returns the raw poses,
validity flags, per-frame diagnostics and timings. :func:`cell_metrics` turns them into the
metrics (in the driver, which writes the cell's folder):

* per-joint error (cm) through :func:`jaxmocap.metrics.evaluate` (the frames the
  tracker reported valid) on the method's evaluated joints (the shirt: what its patches observe,
  ``jaxmocap.trackers.driver.SHIRT_JOINTS``; the stereo filter: Azad's shoulders, elbows and
  hands, ``jaxmocap.trackers.driver.PF_JOINTS``);
* the mean error over *all* frames of the raw estimate (what the accuracy scripts report: the
  shirt tracker holds its last pose on an invalid frame), the share of frames whose reported
  pose is within ``good_cm`` of the truth; that error split into its component along the line
  of sight from the cameras' centre to the true joint (``depth_error_cm``) and across it
  (``lateral_error_cm``; :func:`jaxmocap.metrics.depth_lateral`);
* validity against the ground truth (issues 17/18): of the frames more than ``bad_cm`` off,
  the share flagged invalid (recall) and of the frames flagged invalid the share more than
  ``good_cm`` off (precision); of the frames less than ``good_cm`` off, the share flagged
  valid;
* time per frame (median of the steady-state frames; the first, with compilation, apart).

Every number except the timings is a deterministic function of the inputs and the seed.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import time
from pathlib import Path

import numpy as np

from jaxmocap.errors import InputError
from jaxmocap.experiment.config import tracker_settings
from jaxmocap.trackers.driver import PF_JOINTS, SHIRT_JOINTS

ISOTROPIC_COV = (2.0, 0.3, 0.5)  # px, blend std, prior std (setup_for_sequence's default)
SCRIBBLE_FRAMES = 3  # colors = "scribbles": frames of the capture the user scribbles on
SCRIBBLE_MIN_PIXELS = 20  # a colour with fewer scribbled pixels is scribbled on a later frame
FACE_SCRIBBLE_PX = 4  # pf skin = "scribbles": radius of the face scribble (a head is ~25 px)


def eval_joints(cfg: dict) -> tuple[str, ...]:
    if cfg.get("joints"):
        return tuple(cfg["joints"])
    return SHIRT_JOINTS if cfg["method"] == "shirt" else PF_JOINTS


def _sequence_file(cfg: dict, key: str, folder) -> str | None:
    """The body / garment file of a configuration for the sequence in ``folder``."""
    from jaxmocap.experiment.config import SEQUENCE, ExperimentError

    value = cfg.get(key)
    if value != SEQUENCE:
        return value
    if folder is None:
        raise ExperimentError(f"{key} = {SEQUENCE!r} needs the sequence's folder")
    p = Path(folder) / ("body.urdf" if key == "body" else "garment.json")
    if not p.is_file():
        raise ExperimentError(f"{folder}: no {p.name} in the sequence folder "
                              f"(configuration {cfg['name']!r}: {key} = {SEQUENCE!r})")
    return str(p)


def _body(cfg: dict, folder=None):
    from jaxmocap.body import default_body, load_body
    from jaxmocap.experiment.config import SEQUENCE

    if cfg.get("body") == SEQUENCE and folder is not None:
        from jaxmocap.synth.world.render import sequence_body_file

        path, kw = sequence_body_file(folder)  # body.urdf, or a package body's own file
        return load_body(path, **kw)
    path = _sequence_file(cfg, "body", folder)
    return default_body() if path is None else load_body(path)


def _garment(cfg: dict, body, folder=None):
    from jaxmocap.garment import default_garment
    from jaxmocap.io.garment_file import load_garment

    path = _sequence_file(cfg, "garment", folder)
    return default_garment(body) if path is None else load_garment(path, body)


def scribble_frames(colour_ids: np.ndarray, n_colours: int, n_frames: int = SCRIBBLE_FRAMES,
                    min_pixels: int = SCRIBBLE_MIN_PIXELS) -> list[int]:
    """The frames a user scribbles: the first ``n_frames``, and for a colour with fewer than
    ``min_pixels`` scribbled pixels there (hidden at the start: a patch on the back), the first
    later frame where it shows with that many (``colour_ids`` (T, n_cams, H, W))."""
    from jaxmocap.trackers import shirt

    def scribbled(t):  # scribbled pixels per colour id in frame t, all cameras
        return sum(np.bincount(shirt.scribbles(np.asarray(m, np.int32)).ravel(),
                               minlength=n_colours + 1) for m in colour_ids[t])

    T = colour_ids.shape[0]
    frames = list(range(min(n_frames, T)))
    counts = sum((scribbled(t) for t in frames), np.zeros(n_colours + 1, np.int64))
    for t in range(len(frames), T):
        missing = np.nonzero(counts[1:] < min_pixels)[0] + 1
        if missing.size == 0:
            break
        if not np.isin(missing, colour_ids[t]).any():  # cheap test before the erosion
            continue
        c_t = scribbled(t)
        if np.any(c_t[missing] >= min_pixels):
            frames.append(t)
            counts += c_t
    return frames


def _scribbled_color_model(seq, garment, n_frames: int = SCRIBBLE_FRAMES, gain=None):
    """The colour model a user makes from scribbles on the capture (``jaxmocap colors``): the
    frames of :func:`scribble_frames` of every camera, each pixel of the ground-truth colour ids
    eroded by ``shirt.scribbles`` (no pixel near a patch border) labelled with its colour;
    ``gain``: fitted for the shading-invariant distance."""
    from jaxmocap.color import fit_color_model
    from jaxmocap.trackers import shirt

    cids = seq.groundtruth["colour_ids"]
    images, labels = [], []
    for t in scribble_frames(cids, garment.n_colours, n_frames):
        for c in range(seq.frames.shape[1]):
            images.append(np.asarray(seq.frames[t, c]))
            labels.append(shirt.scribbles(np.asarray(cids[t, c])))
    return fit_color_model(images, labels, garment.n_colours, garment.colour_names, gain=gain)


def _scribbled_skin_colour(seq, body, garment, n_frames: int = SCRIBBLE_FRAMES, gain=None):
    """The shirt tracker's skin class (``skin_terms``) from a user's scribbles on the capture's
    first frames: the body's skin (the garment's skin geoms, the ray caster's ids at the true
    pose: the ground truth labels no skin) eroded by ``shirt.scribbles`` as the shirt's
    colours are, one Gaussian (``gain``: fitted for the shading-invariant distance)."""
    import jax.numpy as jnp

    from jaxmocap.color import fit_color_model
    from jaxmocap.render import render_ids
    from jaxmocap.trackers import shirt

    skin = np.asarray(garment.skin)
    images, labels = [], []
    for t in range(min(n_frames, seq.frames.shape[0])):
        q = jnp.asarray(seq.groundtruth["q"][t])
        for c, cam in enumerate(seq.cameras):
            g = np.asarray(render_ids(body, garment, q, cam).geom)
            m = (g >= 0) & skin[np.maximum(g, 0)]
            images.append(np.asarray(seq.frames[t, c]))
            labels.append(shirt.scribbles(m.astype(np.int32)))
    return fit_color_model(images, labels, 1, ("skin",), gain=gain)


def _scene_colors(seq, W0, n_clusters: int, n_frames: int = SCRIBBLE_FRAMES):
    """Gaussians of the room a user scribbles beside the shirt: the pixels of the first frames
    that are not shirt, ``SCRIBBLE_EROSION`` pixels away from it, white-balanced by ``W0``."""
    from jaxmocap.color import fit_scene_colors
    from jaxmocap.trackers import shirt

    images, masks, Ws = [], [], []
    for t in range(min(n_frames, seq.frames.shape[0])):
        for c in range(seq.frames.shape[1]):
            room = (np.asarray(seq.groundtruth["colour_ids"][t, c]) == 0).astype(np.int32)
            images.append(np.asarray(seq.frames[t, c]))
            masks.append(shirt.scribbles(room, shirt.SCRIBBLE_EROSION + 2) > 0)
            Ws.append(np.asarray(W0[c]))
    return fit_scene_colors(images, masks, Ws, n_clusters)


def _scribbled_capture_colors(seq, n_frames: int = SCRIBBLE_FRAMES):
    """The particle filter's skin and shirt colours from a user's scribbles on the capture's
    first frames (:mod:`jaxmocap.pf.colors`): the shirt's ground-truth colour ids eroded
    (``shirt.scribbles``), and on the face a disc of radius :data:`FACE_SCRIBBLE_PX` around
    the projected head keypoint (the ground truth labels no skin)."""
    import jax.numpy as jnp

    from jaxmocap.camera import project
    from jaxmocap.pf.colors import fit_capture_colors
    from jaxmocap.trackers import shirt

    g = seq.groundtruth
    head = list(g["keypoint_names"]).index("head")
    images, skin, shirt_m = [], [], []
    for t in range(min(n_frames, seq.frames.shape[0])):
        for c, cam in enumerate(seq.cameras):
            h, w = seq.frames.shape[2:4]
            u, v = np.asarray(project(cam, jnp.asarray(g["keypoints"][t, head])), np.float64)
            yy, xx = np.mgrid[:h, :w]
            images.append(np.asarray(seq.frames[t, c]))
            skin.append((xx - u) ** 2 + (yy - v) ** 2 <= FACE_SCRIBBLE_PX**2)
            shirt_m.append(shirt.scribbles(np.asarray(g["colour_ids"][t, c])) > 0)
    return fit_capture_colors(images, skin, shirt_m)


# ----------------------------------------------------------------------------- the trackers


def _observer(option, body, garment, framing: str = "crop"):
    """The ``observer`` option: ``"learn"`` trains (or loads from the cache) the default model
    for the sequence's own body and shirt (``jaxmocap learn``; ``framing`` "frame" for the
    stereo filter); a path loads that file (refused if trained for another body or shirt)."""
    from jaxmocap.observe import learn, load

    if option == "learn":
        return learn(body, garment, progress=False, framing=framing)[0]
    return load(option, body, garment)[0]


def _track_shirt(seq, cfg: dict, seed: int, folder=None) -> dict:

    from jaxmocap.ik import IKCovariances
    from jaxmocap.posedb import SamplingConfig, load_database, load_or_build
    from jaxmocap.trackers import shirt
    from jaxmocap.trackers.driver import ShirtFrameTracker, drive, sequence_frames, shirt_params

    opts = dict(cfg["options"])
    body = _body(cfg, folder)
    garment = _garment(cfg, body, folder)
    if "db" in opts:
        db = load_database(opts.pop("db"))
    else:
        size = opts.pop("db_size", None)
        db = load_or_build(None if size is None else SamplingConfig(size=size), body, garment,
                           progress=False)
    cov_opt = opts.pop("covariances", "trained")
    tuned = opts.pop("tuned", None)
    if tuned is not None:  # checked against the body and shirt (also before any cell)
        from jaxmocap.tuned import load_tuned

        cov = load_tuned(tuned, "shirt", body, garment).ik_covariances(body)
    elif cov_opt == "trained":  # the bundled ones, transferred by role to another body
        cov, _ = shirt.covariances_for_body(body)
    elif cov_opt == "isotropic":
        cov = IKCovariances.isotropic(*ISOTROPIC_COV, body.n_dof)
    else:
        cov = IKCovariances.load(cov_opt)
    names = list(seq.camera_names)
    shading = opts.get("shading")
    scene_clusters = int(opts.pop("scene_clusters", 0))
    skin_colour = None
    if opts.get("colors") == "scribbles":
        opts.pop("colors")
        color = _scribbled_color_model(seq, garment, gain=None if shading is None else
                                       tuple(shading))
        if opts.get("skin_terms"):  # the skin scribbled too
            skin_colour = _scribbled_skin_colour(seq, body, garment, gain=None if shading is
                                                 None else tuple(shading))
    elif "colors" in opts:
        from jaxmocap.color import load_color_model

        color = load_color_model(opts.pop("colors"))
    else:  # the session set-up of shirt.setup_for_sequence (§5.1), the seed on its renders
        q_model = np.asarray(db.poses[:5], np.float64).copy()
        q_model[:, :3] = np.asarray(seq.groundtruth["q"][0, :3])
        color = shirt.fit_color_model_from_renders(body, garment, q_model, seq.cameras[0],
                                                   seed=seed)
    if "white_balance" in opts:
        from jaxmocap.io.white_balance import load_white_balance

        W0 = load_white_balance(opts.pop("white_balance"), names)
    else:
        labels = np.stack([shirt.scribbles(m) for m in seq.groundtruth["colour_ids"][0]])
        W0 = shirt.initial_white_balance(color, seq.frames[0], labels)
    background = opts.pop("background", False)
    observer = opts.pop("observer", None)
    settings = tracker_settings("shirt", opts)
    if observer is not None:  # the learned observation (issue 49): trained for this body + shirt
        settings["colours"] = dataclasses.replace(
            settings.get("colours", shirt.Colours()), observer=_observer(observer, body, garment))
    if scene_clusters:
        settings["colours"] = dataclasses.replace(settings.get("colours", shirt.Colours()),
                                                  scene_colors=_scene_colors(seq, W0,
                                                                             scene_clusters))
    if skin_colour is not None:
        settings["skin_colour"] = skin_colour
    params = shirt_params(color, body, garment, list(seq.cameras), db, cov, announce=False,
                          **settings)
    tracker = ShirtFrameTracker(params, W0, list(seq.cameras), names, background=background,
                                announce=False)
    run = drive(tracker, sequence_frames(seq.frames), progress=False, keep_outputs=True)
    # every frame's own estimate, valid or not (the cell scores both)
    q = np.stack([np.asarray(o.q, np.float64) for o in run.outputs])
    # the IK step's inputs as the tracker measured them (jaxmocap tune holds them fixed)
    ik = {k: np.stack([np.asarray(getattr(o, k)) for o in run.outputs])
          for k in ("centroids", "visible", "q_blend")}
    rob = params.rounds.robust
    ik["robust"] = np.float64(np.inf if rob is None else rob)
    return {"q": q, "valid": run.valid, "times": run.times,
            "diagnostics": [r[3] for r in run.rows], "body": body, "ik_observations": ik}


def pf_setup(seq, cfg: dict, folder=None):
    """The stereo filter's settings of configuration ``cfg`` (a :meth:`TrackerConfig.to_dict`)
    for ``seq``: ``(params, blob, lag, validity, search, start_from_head)`` (also what
    ``jaxmocap tune --tracker pf`` rebuilds its likelihood from)."""
    import jax.numpy as jnp

    from jaxmocap import blobs as bloblib
    from jaxmocap.segment import HSVInterval, SegmentParams
    from jaxmocap.trackers import stereo_pf as sp

    if len(seq.cameras) != 2:
        raise InputError(f"method 'pf' needs a stereo pair; the sequence has "
                         f"{len(seq.cameras)} cameras")
    opts = dict(cfg["options"])
    body = _body(cfg, folder)
    if "tuned" in opts:  # the cue widths (checked against the body, also before any cell)
        from jaxmocap.tuned import load_tuned

        opts.update(load_tuned(opts.pop("tuned"), "pf", body).cue_widths())
    base = dict(sp.AZAD_FILTER) if opts.pop("azad", False) else {}
    if "particles" in opts:
        opts["n_particles"] = opts.pop("particles")
    skin = opts.pop("skin", "synth")
    blob = sp.BLOB_PARAMS if opts.pop("blob_params", "tracker") == "tracker" \
        else bloblib.BlobParams()
    lag = int(opts.pop("smooth_lag", 0))
    validity = opts.pop("validity", True)
    search = opts.pop("search", "off")
    heads = opts.pop("start_from_head", True)
    if "seed_replace" in opts:  # part_colours: which parts the seeded search may replace
        from jaxmocap.trackers.stereo_pf.params import SeedParams

        opts["seed_params"] = SeedParams(replace=tuple(bool(x) for x in opts.pop("seed_replace")))
    observer = opts.pop("observer", None)
    if observer is not None and skin != "learned":
        raise InputError(f"configuration {cfg['name']!r}: observer = {observer!r} is read with "
                         f"skin = \"learned\" only (skin = {skin!r})")
    kw = tracker_settings("pf", opts, base)
    segment, colors, parts = None, None, None
    if skin == "synth":
        segment = SegmentParams(skin=HSVInterval(*(jnp.asarray(v) for v in sp.SYNTH_SKIN_HSV)))
    elif skin == "scribbles":
        colors = _scribbled_capture_colors(seq)
    elif skin == "auto":
        from jaxmocap.pf.colors import calibrate_from_frames

        colors = calibrate_from_frames(seq.frames[:, 0])
    elif skin == "learned":  # the learned observation layer (issue 50)
        from jaxmocap.camera import stack_cameras
        from jaxmocap.observe import classes_of
        from jaxmocap.trackers.stereo_pf.learned import learned_parts

        garment = _garment(cfg, body, folder)
        parts = learned_parts(_observer(observer or "learn", body, garment, "frame"),
                              classes_of(body, garment), stack_cameras(list(seq.cameras)))
    images = dataclasses.replace(kw.pop("images", sp.Images()), segment=segment, colors=colors,
                                 observer=parts)
    params = sp.make_params(list(seq.cameras), model=body, images=images, **kw)
    return params, blob, lag, validity, search, heads


def _track_pf(seq, cfg: dict, seed: int, folder=None) -> dict:
    import jax

    from jaxmocap.trackers import stereo_pf as sp
    from jaxmocap.trackers.driver import START_ANCHOR_CODES, stereo_offline

    params, blob, lag, validity, search, heads = pf_setup(seq, cfg, folder)
    key = jax.random.key(seed)
    if search != "off":  # ... with the prediction-guided search (the filter alongside)
        from jaxmocap.trackers.stereo_pf import search as pfs

        heads, hands = search in ("head", "all"), search in ("hands", "all")
        sparams = pfs.SearchParams(entities=(heads, hands, hands))

        def observe():
            return pfs.observe_search(params, key, seq.frames, blob, sparams)[0]
    elif params.hand_search is not None:  # hands gated by the prediction (filter alongside)
        from jaxmocap.trackers.stereo_pf.hands import observe_hands

        def observe():
            return observe_hands(params, key, seq.frames, blob)[0]
    elif params.part_colours is not None:  # per-part colours, seeded search (filter alongside)
        from jaxmocap.trackers.stereo_pf.parts import observe_parts

        def observe():
            return observe_parts(params, key, seq.frames, blob)[0]
    elif params.adapt is None:
        def observe():  # host image line + blob tracker
            return sp.observe_sequence(params, seq.frames, blob)
    else:  # ... with the colour model re-fitted on line (the filter alongside)
        from jaxmocap.trackers.stereo_pf.adapt import observe_adaptive

        def observe():
            return observe_adaptive(params, key, seq.frames, blob)[0]
    run = stereo_offline(params, key, seq.frames, observe, lag, repeat=True,
                         start_from_head=heads)
    obs, t_init, tm = run.observations, run.init_frame, run.timings
    observe_first, observe_s = tm["observe_first"], tm["observe"]
    first, warm = tm["filter_first"], tm["filter"]
    est = run.estimate
    est = jax.device_get(est)
    n = seq.frames.shape[0]
    q = np.asarray(est.q, np.float64)
    ov = np.asarray(obs.valid)
    valid = sp.frame_validity(params, q, np.asarray(obs.points), ov) if validity \
        else np.isfinite(q).all(axis=1)
    code = float(START_ANCHOR_CODES[run.anchor])  # offline every frame runs from the start
    rows = [{"ess": float(est.ess[t]), "best_loglik": float(est.best_loglik[t]),
             "degenerate": float(est.degenerate[t]), "blobs": float(ov[t].sum()),
             "start_anchor": code} for t in range(n)]
    per_frame = (observe_s + warm) / n
    return {"q": q, "valid": valid, "times": np.full(n, per_frame), "diagnostics": rows,
            "body": params.model, "first_run_s": observe_first + first, "init_frame": t_init,
            "start_anchor": run.anchor,
            "blobs": (np.asarray(obs.points), ov),  # the skin points fed into the filter
            # what its likelihood read (jaxmocap tune --tracker pf; dropped by compute_cell
            # unless the spec asks: MBs per frame)
            "pf_observations": {k: np.asarray(v) for k, v in
                                zip(("edges", "points", "points_valid", "foreground",
                                     "support"),
                                    (obs.edges, obs.points, obs.valid, obs.foreground,
                                     obs.support), strict=True) if v is not None}}


def compute_cell(spec: dict) -> dict:
    """Track one cell (``spec``: ``folder``, ``config`` (a :meth:`TrackerConfig.to_dict`),
    ``seed``, ``x64``). Returns ``q`` (T, n_dof) raw estimates, ``valid`` (T,), ``times``
    (T,) seconds per frame, ``diagnostics`` (T dicts), ``wall_s`` and the method's extras."""
    import jax

    from jaxmocap.synth.dataset import load_dataset

    if bool(jax.config.jax_enable_x64) != bool(spec["x64"]):  # a worker: the driver's precision
        jax.config.update("jax_enable_x64", bool(spec["x64"]))
    t0 = time.perf_counter()
    seq = load_dataset(spec["folder"])
    cfg = spec["config"]
    run = _track_shirt if cfg["method"] == "shirt" else _track_pf
    out = run(seq, cfg, int(spec["seed"]), spec["folder"])
    out.pop("body")
    if not spec.get("keep_observations"):
        out.pop("pf_observations", None)
    out["wall_s"] = time.perf_counter() - t0
    out["fps"] = float(seq.config.fps)
    return out


# ----------------------------------------------------------------------------- metrics


def diagnostics_csv(rows: list[dict], valid: np.ndarray) -> str:
    names = list(rows[0]) if rows else []
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(["frame", "valid", *names])
    for t, d in enumerate(rows):
        w.writerow([t, int(valid[t]), *(f"{d[k]:.6g}" for k in names)])
    return buf.getvalue()


def _share(num: np.ndarray, den: np.ndarray) -> float | None:
    n = int(den.sum())
    return None if n == 0 else float((num & den).sum() / n)


def joint_errors_cm(body, q: np.ndarray, gt_folder: str, joints):
    """``(err, kp, gt_kp)`` of the estimates ``q`` (T, n_dof) against ``gt_folder``'s
    ground truth: the per-joint error (T, J) cm of ``joints`` (NaN rows where ``q`` has no
    estimate), their keypoints (T, J, 3) and the truth's (T, J, 3) -- the error every cell's
    metrics are made of."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.body import keypoints
    from jaxmocap.io.export import load_track

    gt = load_track(Path(gt_folder) / "groundtruth.npz")
    names = list(body.keypoint_names)
    missing = [j for j in joints if j not in names or j not in gt.keypoint_names]
    if missing:
        raise InputError(f"joints {missing}: not keypoints of both the tracker's body and "
                         f"{gt_folder}/groundtruth.npz")
    q_fill = np.where(np.isfinite(q), q, 0.0)
    kp = np.asarray(jax.jit(jax.vmap(lambda x: keypoints(body, x)))(jnp.asarray(q_fill)))
    ip = [names.index(j) for j in joints]
    ig = [list(gt.keypoint_names).index(j) for j in joints]
    err = np.linalg.norm(kp[:, ip] - gt.keypoints[:, ig], axis=-1) * 100.0  # (T, J) cm
    err[~np.isfinite(q).all(axis=1)] = np.nan
    return err, kp[:, ip], gt.keypoints[:, ig]


def cell_metrics(body, result: dict, poses_path: Path, gt_folder: str, joints,
                 good_cm: float, bad_cm: float) -> tuple[dict, np.ndarray]:
    """Metrics of a computed cell whose poses were written to ``poses_path`` (module
    docstring). Returns (metrics, per-frame error (T,) cm of the raw estimate)."""
    from jaxmocap.metrics import evaluate

    q, valid = result["q"], result["valid"]
    err, kp, gt_kp = joint_errors_cm(body, q, gt_folder, joints)
    ev = evaluate(poses_path, gt_folder) if valid.any() else None
    depth_cm, lateral_cm = _depth_lateral_cm(kp, gt_kp, gt_folder, err)
    frame_err = err.mean(axis=1)
    known = np.isfinite(frame_err)
    bad = known & (frame_err > bad_cm)
    good = known & (frame_err < good_cm)
    flagged = ~valid
    times = result["times"]
    per_joint = None
    if ev is not None:
        per_joint = {j: ev["joints"][j]["mpjpe_cm"] for j in joints}
    m = {
        "frames": int(len(valid)),
        "frames_valid": int(valid.sum()),
        "mpjpe_cm": None if per_joint is None else float(np.mean(list(per_joint.values()))),
        "per_joint_cm": per_joint,
        "jitter_cm_per_frame2": None if ev is None else ev["jitter_cm_per_frame2"],
        "mean_error_all_frames_cm": float(np.nanmean(frame_err)) if known.any() else None,
        # the same frames' error split along the rig's line of sight and across it
        "depth_error_cm": depth_cm,
        "lateral_error_cm": lateral_cm,
        "frames_below_good_cm": float(np.mean(good & valid)),  # valid and < good_cm
        "validity": {
            "good_cm": good_cm, "bad_cm": bad_cm,
            "frames_bad": int(bad.sum()), "frames_good": int(good.sum()),
            "bad_flagged_invalid": _share(flagged, bad),  # recall of the invalid flag
            "invalid_are_not_good": _share(~good, flagged),  # its precision
            "good_flagged_valid": _share(valid, good),  # recall of the valid flag
            "valid_are_not_bad": _share(~bad, valid),  # its precision
        },
        "ms_per_frame": float(1e3 * np.median(times[1:] if len(times) > 1 else times)),
        "first_frame_s": float(result.get("first_run_s", times[0])),
        "wall_s": float(result["wall_s"]),
    }
    m["world"] = _world_metrics(gt_folder, frame_err, valid, good_cm, result)
    return m, frame_err


def _depth_lateral_cm(pred: np.ndarray, truth: np.ndarray, gt_folder: str, err: np.ndarray
                      ) -> tuple[float | None, float | None]:
    """Mean per-joint error (cm) along the line of sight from the cameras' mean centre to the
    true joint and across it (:func:`jaxmocap.metrics.depth_lateral`), over the frames with an
    estimate (``err`` finite); (None, None) without ``cameras.json`` or such a frame."""
    from jaxmocap.camera import camera_center
    from jaxmocap.io.cameras import load_cameras
    from jaxmocap.metrics import depth_lateral

    cam_file = Path(gt_folder) / "cameras.json"
    known = np.isfinite(err).all(axis=1)
    if not cam_file.is_file() or not known.any():
        return None, None
    origin = np.mean([np.asarray(camera_center(c), np.float64)
                      for c in load_cameras(cam_file)[0]], axis=0)
    depth, lateral = depth_lateral(pred[known], truth[known], origin)
    return float(depth.mean() * 100.0), float(lateral.mean() * 100.0)


def _world_metrics(gt_folder: str, frame_err, valid, good_cm: float, result: dict):
    """:func:`jaxmocap.experiment.world_metrics.world_metrics` of the cell (None without
    visibility ground truth)."""
    from jaxmocap.experiment.world_metrics import RECOVER_CM, world_metrics
    from jaxmocap.io.cameras import load_cameras

    with np.load(Path(gt_folder) / "groundtruth.npz") as z:
        gt = {k: z[k] for k in ("occluded_fraction", "visible", "keypoints", "keypoint_names",
                                "lamp_levels") if k in z.files}
    cam_file = Path(gt_folder) / "cameras.json"
    cams = load_cameras(cam_file)[0] if cam_file.is_file() else None
    return world_metrics(gt, frame_err, np.asarray(valid, bool), recover_cm=RECOVER_CM,
                         good_cm=good_cm, cameras=cams,
                         blobs=result.get("blobs"))
