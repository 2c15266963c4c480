"""``jaxmocap tune``'s library call: a tracker's weighting tuned by gradient on a dataset's dev
sequences, written as a tuned-parameters file (:mod:`jaxmocap.tuned`).

Why one file: both trackers' tunes run through the one loop of :func:`tune_dataset` (the
observations and their cache, the split, the resumable checkpoints, the optimisers: Adam,
L-BFGS and the CMA-ES baseline on the same loss and budget); the shirt's and the stereo
filter's set-ups (:func:`_setups`, :func:`_pf_setups`) are the two halves of that one call.

**Observations, held fixed** (:func:`observations`): every sequence is tracked once by the
real tracker with the configuration's settings (an experiment cell,
:func:`jaxmocap.experiment.cell.compute_cell`: in this process, on a local Dask cluster of
``workers`` processes or on an existing ``scheduler``, :mod:`jaxmocap.experiment.cluster`), and
what its tuned step consumes is kept in ``OUT/observations/<sequence>.npz``, keyed by the
configuration's hash and the sequence's content digest (a rerun reads them back):

* ``shirt``: per frame the measured patch centroids and their validity and the globally
  placed blended database pose ``q_b`` (``ShirtOutput.centroids / visible / q_blend``), with
  the true pose, the tracker's valid flags and its own estimates. The loss is
  :func:`jaxmocap.tune.ik_loss`: the IK step re-run over windows of ``window`` frames (the
  temporal prior is the previous solution), mean per-joint error over the configuration's
  evaluated joints on the frames the tracker reported valid (the experiment's per-joint
  error). Why not every frame: where the tracker is lost its blended database pose is far
  off (dev shirt_03, 13: 140 and 258 cm mean over all frames) and the re-run's LM, started
  from it, ends metres away (mean 605 cm on shirt_03, median 11 cm) where the tracker kept a
  better start or flagged the frame: those frames would swamp the loss. To be the tracker's
  last IK round (docs/results/tuning.md, issue 40: the re-run started at 172 cm on the test
  world's dev split against the tracker's own 9.05 cm on the same frames, 9.22 cm now), each
  solve starts at the tracker's own estimate (``IKObservations.q_start``), predicts the
  centroids from per-view anchors (``Rounds.view_anchors``, the default: rendered at that
  estimate by :func:`_view_anchors_at`, held fixed) and takes the previous solution as its
  temporal prior only after a frame the tracker reported valid (else ``q_b``, as the
  tracker's ``q_h``). Held fixed besides: the tracker's histogram search, classification,
  database blend and choice among its starts (all discrete), the feedback of the pose into
  the next frame's white balance and crop, and the crop the per-view anchors are rendered on
  (the tracker's is not kept: the projected keypoints' box); the tracker's Cauchy width
  ``Rounds.robust`` is kept.

* ``pf``: what the stereo filter's likelihood read per frame (``Observation``: the edge maps
  of both cameras, the foreground, the triangulated head / hands and their validity, stored
  as ``edges, foreground, points, points_valid``), with the true pose, the filter's valid
  flags and its own estimates (``StereoRun.observations``, ``estimate.q``). The loss is
  :func:`jaxmocap.tune.pf_loss`: **the filter itself re-run with the candidate widths** -- its
  annealed initialisation on the tracker's start frame (:func:`~jaxmocap.trackers.stereo_pf.
  start.start_frame` of these observations) with the key of seed :data:`PF_SEED` (or the mean
  of ``pf_seeds`` runs, seeds 0, 1, ...: ``--pf-seeds``), then its
  frame step over every frame -- scored on every frame with a ground truth: the mean
  per-joint error of its estimate over the configuration's evaluated joints against the
  sequence's ground-truth keypoints (the experiment's all-frames error of that run), averaged
  over the sequences. Gradients through the recursion by the filter's stop-gradient
  resampling, truncated to windows of :data:`PF_WINDOW` frames (:mod:`jaxmocap.tune`).
  Held fixed: only the observations (the host image line and the blob tracker; where a
  configuration feeds the filter's estimate back into its observations -- the gated hand
  search, per-part colours, on-line colour adaptation, the prediction-guided search -- that
  feedback is cut). In the filter's float32, in this process (the tracking may run on Dask).
  The loss's forward pass is the tracker's programs compiled into one: the same arithmetic,
  but not bit for bit the tracker's run (XLA may round a fused program differently, and a
  particle filter's resampling amplifies a rounding difference over frames); how far the loss
  predicts the tracker's own all-frames error over widths is measured by
  ``benchmarks/experiments/tune_faithfulness.py`` (docs/results/tuning.md).

  ``optimiser="cma"``: the black-box baseline, CMA-ES (Hansen's ``cma`` package) over the
  same two log-widths, evaluating the same loss's value (filter runs, no gradient): the start,
  then whole generations of its default population while they fit in ``steps + 1``
  evaluations -- the number of loss evaluations a gradient descent of ``steps`` steps makes.

**Parameters.** When every sequence has the same body and shirt, the full matrices
Sigma_c, Sigma_b, Sigma_p of that body (:class:`jaxmocap.tune.IKTheta`; the file's
``transfer`` is ``"none"``). When the bodies differ (the test world: one body per sequence)
the parameters are shared through the bodies' roles: Sigma_c and the diagonal variances of
the bundled body's DOFs, each body's DOF taking its counterpart's
(:class:`jaxmocap.tune.IKRoleTheta`; ``transfer = "role"``, read as the bundled trained
covariances are). The start is what the configuration tracked with (default: the bundled
trained covariances, transferred by role).

For ``pf`` the parameters are log sigma_g, log sigma_d (:class:`jaxmocap.tune.PFTheta`),
starting from the configuration's; they do not depend on the body, so the file always says
``transfer = "role"`` (any body with roles accepts it: the test split's bodies are others).

**Optimisation** (:func:`jaxmocap.tune.fit`, optax): Adam, or L-BFGS with its zoom
linesearch (in this process only: the linesearch evaluates the loss inside its jitted
update). Under Dask the gradient of each sequence is computed on a worker and summed
(:mod:`jaxmocap.experiment.tune_dask`). Every ``every`` steps the optimiser's state is written
to ``OUT/checkpoint.npz``; a rerun with the same ``OUT`` continues from it and ends where an
uninterrupted run ends. The best iterate is written to ``OUT/tuned.json``.

**Why one file** (over 600 lines): the command's one pipeline — pick the configuration, track
and cache the observations, build each tracker's loss from them (the shirt's per-view anchors
included), descend, write the file — whose parts share the cache layout, the run key and the
held-fixed record; split, each part would import the others' private layout.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np

from jaxmocap.experiment.config import (
    ExperimentConfig,
    ExperimentError,
    TrackerConfig,
    config_hash,
    dataset_sequences,
    digest_folder,
    load_config,
)

TRACKERS = ("shirt", "pf")  # tuned by this module
OBSERVATIONS = "observations"
CHECKPOINT = "checkpoint.npz"
TUNED = "tuned.json"
RUN_RECORD = "tune_run.json"
WINDOW = 10  # frames per IK window (docs/results/tuning.md)
PF_SEED = 0  # the stereo filter's loss runs the filter with the key of this seed (seed 0's cell)
CHECKPOINT_EVERY = 5
CACHE_VERSION = 2  # observations/<sequence>.npz: + the tracker's valid flags and poses


PF_HELD_FIXED = ("the filter's observations (edge maps, foreground, triangulated head/hands "
                 "and their validity; tracked once with the configuration), hence any "
                 "feedback of the estimate into them; the random key (seed 0); the "
                 "initialisation's annealing is run with the widths but not differentiated")
PF_LOSS = ("mean per-joint position error (m) of the stereo filter re-run with the widths "
           "(annealed initialisation on the tracker's start frame, then every frame), all "
           "frames, mean over sequences; gradients by stop-gradient resampling, truncated to "
           "windows of PF_WINDOW frames")
OPTIMISERS = ("adam", "lbfgs", "cma")
CMA_SIGMA0 = 0.35  # CMA-ES's initial step in log-width: +-2 sigma0 spans x0.5-x2 (log 2 = 0.69)
CMA_CHECKPOINT = "checkpoint_cma.pkl"


def _pick_config(config, name: str | None, tracker: str | None) -> TrackerConfig:
    """The tracker configuration tuned: ``name`` of ``config`` (a file or an
    :class:`ExperimentConfig`), else its only one; without ``config`` the tracker's defaults
    (the bundled body and shirt)."""
    if config is None:
        if tracker is None:
            raise ExperimentError("tune: give a tracker (shirt, pf) or a configuration file")
        return TrackerConfig(name=tracker, method=tracker, seeds=(0,))
    exp = config if isinstance(config, ExperimentConfig) else load_config(config)
    names = [c.name for c in exp.configs]
    if name is None:
        if len(names) != 1:
            raise ExperimentError(f"{exp.path}: {len(names)} configurations ({', '.join(names)})"
                                  "; name the one to tune (--name)")
        cfg = exp.configs[0]
    else:
        if name not in names:
            raise ExperimentError(f"{exp.path}: no configuration {name!r} (have "
                                  f"{', '.join(names)})")
        cfg = exp.configs[names.index(name)]
    if tracker is not None and cfg.method != tracker:
        raise ExperimentError(f"{exp.path}: configuration {cfg.name!r} is method "
                              f"{cfg.method!r}, not {tracker!r}")
    if cfg.method not in TRACKERS:
        raise ExperimentError(f"tune: method {cfg.method!r} is not tuned here (tuned: "
                              f"{', '.join(TRACKERS)})")
    return cfg


# ----------------------------------------------------------------------------- observations


def observations(cfg: TrackerConfig, seqs, out: Path, workers: int = 0,
                 scheduler: str | None = None, retries: int = 1,
                 progress: bool = True) -> dict[str, dict]:
    """Per sequence name the held-fixed observations (module docstring): tracked with
    ``cfg`` (seed 0), cached in ``out/observations``. Returns ``{name: {centroids, visible,
    q_blend, q_gt, robust}}`` (numpy)."""
    from tqdm import tqdm

    from jaxmocap.experiment._guard import _one_line, guarded
    from jaxmocap.experiment.cell import compute_cell

    folder = out / OBSERVATIONS
    folder.mkdir(parents=True, exist_ok=True)
    h = config_hash(cfg, 0.0, 0.0)
    specs, have = [], {}
    for s in seqs:
        spec = {"cell": s.name.replace("/", "_"), "sequence": s.name, "folder": s.folder,
                "config": cfg.to_dict(), "seed": 0, "config_hash": h,
                "dataset_digest": digest_folder(s.folder), "x64": False,  # the tracker's f32
                "keep_observations": cfg.method == "pf"}
        got = _read_cached(folder / f"{spec['cell']}.npz", spec)
        if got is None:
            specs.append(spec)
        else:
            have[s.name] = got
    errors = []
    bar = tqdm(total=len(specs), desc="observations (tracking)", unit="seq",
               disable=not progress or not specs)

    def accept(spec, res=None, err=None):
        if err is None and "error" in res:
            err = res["error"]
        if err is not None:
            errors.append(f"{spec['sequence']}: {err}")
        else:
            have[spec["sequence"]] = _write_cached(folder / f"{spec['cell']}.npz", spec, res)
        bar.update(1)

    if specs and workers == 0 and scheduler is None:
        import jax

        x64 = bool(jax.config.jax_enable_x64)
        try:
            for spec in specs:
                try:
                    accept(spec, guarded(compute_cell, spec))
                except Exception as e:  # one line per sequence, reported together
                    accept(spec, err=_one_line(e))
        finally:
            jax.config.update("jax_enable_x64", x64)  # compute_cell set the tracker's
    elif specs:
        from jaxmocap.experiment.cluster import run_on_cluster

        run_on_cluster(specs, compute_cell, accept, workers, scheduler, retries, {})
    bar.close()
    if errors:
        raise ExperimentError("tune: tracking failed on " + "; ".join(errors))
    return {s.name: have[s.name] for s in seqs}


def _read_cached(path: Path, spec: dict) -> dict | None:
    try:
        with np.load(path) as z:
            meta = json.loads(str(z["meta"]))
            if (meta.get("config_hash"), meta.get("dataset_digest"), meta.get("version")) != (
                    spec["config_hash"], spec["dataset_digest"], CACHE_VERSION):
                return None
            return {k: z[k] for k in z.files if k != "meta"}
    except (OSError, ValueError, KeyError):
        return None


def _write_cached(path: Path, spec: dict, res: dict) -> dict:
    from jaxmocap.io.atomic import atomic_path

    obs = dict(res["ik_observations"] if "ik_observations" in res else res["pf_observations"])
    obs["valid"] = np.asarray(res["valid"], bool)  # the tracker's reported validity
    obs["q_tracker"] = np.asarray(res["q"], np.float64)  # its own estimates
    with np.load(Path(spec["folder"]) / "groundtruth.npz") as z:
        obs["q_gt"] = np.asarray(z["q"], np.float64)
    meta = {k: spec[k] for k in ("sequence", "config_hash", "dataset_digest")}
    meta["version"] = CACHE_VERSION
    with atomic_path(path) as tmp:
        np.savez_compressed(tmp, meta=np.asarray(json.dumps(meta)), **obs)
    return obs


# ----------------------------------------------------------------------------- the loss


def _setups(cfg: TrackerConfig, seqs, obs: dict, dtype):
    """(per-sequence :class:`jaxmocap.tune.IKSetup`, per-sequence windows, the start theta,
    the file's transfer mode, body digest, dof names, garment digest, per-sequence body
    digests)."""
    import equinox as eqx
    import jax.numpy as jnp

    from jaxmocap import tune
    from jaxmocap.body import body_digest, default_body
    from jaxmocap.camera import stack_cameras
    from jaxmocap.experiment.cell import _body, _garment, eval_joints
    from jaxmocap.garment import garment_digest
    from jaxmocap.ik import IKCovariances, anchors_from_garment
    from jaxmocap.io.cameras import load_cameras
    from jaxmocap.trackers.shirt import covariances as shc
    from jaxmocap.trackers.shirt.params import WORK_SIZE

    c = cfg.to_dict()
    loaded = []
    for s in seqs:
        body = _body(c, s.folder)
        garment = _garment(c, body, s.folder)
        loaded.append((body, garment))
    digests = {s.name: body_digest(b) for s, (b, _) in zip(seqs, loaded, strict=True)}
    g_digests = {garment_digest(g) for _, g in loaded}
    shared = len(set(digests.values())) == 1 and len(g_digests) == 1
    opt = cfg.options
    ref = default_body()
    if shared:
        body, garment = loaded[0]
        if "tuned" in opt:
            from jaxmocap.tuned import load_tuned

            cov = load_tuned(opt["tuned"], "shirt", body, garment).ik_covariances(body)
        elif opt.get("covariances", "trained") == "trained":
            cov, _ = shc.covariances_for_body(body)
        elif opt["covariances"] == "isotropic":
            from jaxmocap.experiment.cell import ISOTROPIC_COV

            cov = IKCovariances.isotropic(*ISOTROPIC_COV, body.n_dof)
        else:
            cov = IKCovariances.load(opt["covariances"])
        theta = tune.ik_theta(jax_cast(cov, dtype))
    else:
        if "tuned" in opt:
            from jaxmocap.tuned import TunedParameters

            t = TunedParameters.load(opt["tuned"])
            if t.transfer != "role":
                raise ExperimentError(f"{t.path}: field 'transfer' is {t.transfer!r}; the "
                                      "sequences' bodies differ, a start shared by role needed")
            p = t.parameters
            cov = IKCovariances(jnp.asarray(p["ik_centroid"]), jnp.asarray(p["ik_blend"]),
                                jnp.asarray(p["ik_prior"]))
        elif opt.get("covariances", "trained") == "trained":
            cov = shc.trained_covariances(ref.n_dof)
        elif opt["covariances"] == "isotropic":
            from jaxmocap.experiment.cell import ISOTROPIC_COV

            cov = IKCovariances.isotropic(*ISOTROPIC_COV, ref.n_dof)
        else:
            raise ExperimentError(f"tune: covariances {opt['covariances']} are for one body; "
                                  "the sequences' bodies differ (tuned by role from the "
                                  "bundled body's: leave covariances out)")
        theta = tune.ik_role_theta(jax_cast(cov, dtype))
    setups, clips = [], []
    for s, (body, garment) in zip(seqs, loaded, strict=True):
        o = obs[s.name]
        cams, _ = load_cameras(Path(s.folder) / "cameras.json", dtype)
        names = list(body.keypoint_names)
        joints = [j for j in eval_joints(c) if j in names]
        rob = float(o["robust"])
        kw = {}
        if not shared:
            kw = dict(dof_index=shc.transfer_index(ref, body),
                      default_var=(shc.DEFAULT_BLEND_STD**2, shc.DEFAULT_PRIOR_STD**2))
        setups.append(tune.ik_setup(body, stack_cameras(cams),
                                    anchors_from_garment(body, garment, dtype), joints,
                                    robust=None if not np.isfinite(rob) else rob, **kw))
        n = min(len(o["q_blend"]), len(o["q_gt"]))
        clip = tune.ik_observations(
            [(o["centroids"][:n], o["visible"][:n], o["q_blend"][:n], o["q_gt"][:n],
              o["valid"][:n], o["q_tracker"][:n])], WINDOW, dtype)
        clip = _scored_windows(clip)  # before the renders: a dropped window needs none
        if opt.get("view_anchors", True) and clip.q_b.shape[0]:  # the tracker's per-view
            off, sh = _view_anchors_at(setups[-1], garment, clip.q_start.reshape(  # anchors
                -1, clip.q_start.shape[-1]), int(opt.get("work_size", WORK_SIZE)))
            w = clip.q_b.shape[:2]
            clip = eqx.tree_at(lambda o: (o.view_offset, o.view_shift), clip,
                               (off.reshape(w + off.shape[1:]), sh.reshape(w + sh.shape[1:])),
                               is_leaf=lambda x: x is None)
        clips.append(clip)
    # a sequence without any scored frame adds 0 / 0: no gradient to compile for it
    keep = [i for i, c in enumerate(clips) if c.q_b.shape[0]]
    if not keep:
        raise ExperimentError("tune: the tracker reported no frame valid in any window of "
                              f"{WINDOW} frames; nothing to tune on")
    setups, clips = [setups[i] for i in keep], [clips[i] for i in keep]
    if shared:
        b, g = loaded[0]
        ident = ("none", body_digest(b), tuple(b.chain.dof_names), garment_digest(g))
    else:
        ident = ("role", body_digest(ref), tuple(ref.chain.dof_names), None)
    return setups, clips, theta, ident, digests


def _pf_setups(cfg: TrackerConfig, seqs, obs: dict, pf_seeds: int = 1):
    """The stereo filter's loss terms (module docstring): per sequence ``(params,
    jaxmocap.tune.PFSequence)`` with the keys of seeds ``PF_SEED .. PF_SEED + pf_seeds - 1``
    (one: seed 0's key, the loss is that run; several: the mean of their runs); the start
    theta (the configuration's widths), the file's identity, per-sequence body digests."""
    import jax
    import jax.numpy as jnp

    from jaxmocap import tune
    from jaxmocap.body import body_digest, default_body, keypoint_index
    from jaxmocap.experiment.cell import eval_joints, pf_setup
    from jaxmocap.io.export import load_track
    from jaxmocap.pf.cues import Observation
    from jaxmocap.synth.dataset import load_dataset
    from jaxmocap.trackers.stereo_pf.start import start_frame

    c = cfg.to_dict()
    terms, digests, widths = [], {}, None
    for s in seqs:
        params, _, lag, _, _, heads = pf_setup(load_dataset(s.folder), c, s.folder)
        if lag:
            raise ExperimentError(f"tune --tracker pf: configuration {cfg.name!r} smooths "
                                  f"(smooth_lag = {lag}); the loss scores the filter's own "
                                  "estimate: tune a configuration without smooth_lag")
        lik, body = params.likelihood, params.model
        digests[s.name] = body_digest(body)
        if widths is None:
            widths = (float(lik.sigma_g), float(lik.sigma_d))
        o = obs[s.name]
        gt = load_track(Path(s.folder) / "groundtruth.npz")
        names = list(body.keypoint_names)
        joints = [j for j in eval_joints(c) if j in names and j in gt.keypoint_names]
        n = min(len(o["edges"]), len(gt.keypoints))
        ig = [list(gt.keypoint_names).index(j) for j in joints]
        g = np.asarray(gt.keypoints[:n][:, ig], np.float64)
        z = Observation(*(jnp.asarray(o[k][:n]) for k in
                          ("edges", "points", "points_valid", "foreground")),
                        support=jnp.asarray(o["support"][:n]) if "support" in o else None)
        t0, _, start = start_frame(params, z, heads=heads)
        dt = lik.default_q.dtype
        seq = tune.PFSequence(
            obs=z, first=jax.tree.map(lambda a, t0=t0: a[t0], z), start=start,
            key=jax.random.key(PF_SEED) if pf_seeds == 1 else jnp.stack(
                [jax.random.key(PF_SEED + i) for i in range(pf_seeds)]),
            gt=jnp.asarray(np.nan_to_num(g), dt),
            joints=jnp.asarray(keypoint_index(body, joints)),
            scored=jnp.asarray(np.isfinite(g).all(axis=(1, 2))))
        terms.append((params, seq))
    theta = tune.pf_theta(*widths, dtype=terms[0][0].likelihood.default_q.dtype)
    # the cue widths do not depend on the body: shared by any body with roles, also when the
    # dev sequences share one body (the test split's bodies are others)
    ref = default_body()
    ident = ("role", body_digest(ref), tuple(ref.chain.dof_names), None)
    return terms, theta, ident, digests


def _pf_losses(terms, window: int | None = None):
    """(scalar loss, value-and-gradient) over the sequences' terms: the mean over sequences of
    :func:`jaxmocap.tune.pf_loss` (each sequence's all-frames mean, as the experiments'
    **all** row)."""
    import equinox as eqx
    import jax

    from jaxmocap import tune

    window = tune.PF_WINDOW if window is None else window
    w = 1.0 / len(terms)
    vg = eqx.filter_jit(jax.value_and_grad(tune.pf_loss))

    def loss(theta):
        return sum(w * tune.pf_loss(theta, p, s, window) for p, s in terms)

    def value_and_grad(theta):
        total, grad = 0.0, None
        for p, s in terms:
            v, g = vg(theta, p, s, window)
            total = total + w * v
            g = jax.tree.map(lambda a: w * a, g)
            grad = g if grad is None else jax.tree.map(lambda a, b: a + b, grad, g)
        return total, grad

    return loss, value_and_grad


def pf_value(terms, window: int | None = None):
    """``theta -> loss`` over the sequences without its gradient (the filter runs only):
    one compiled program per sequence, what the black-box baseline evaluates."""
    import equinox as eqx

    from jaxmocap import tune

    window = tune.PF_WINDOW if window is None else window
    f = eqx.filter_jit(tune.pf_loss)

    def value(theta):
        return sum(float(f(theta, p, s, window)) for p, s in terms) / len(terms)

    return value


def jax_cast(cov, dtype):
    import jax

    return jax.tree.map(lambda a: a.astype(dtype), cov)


# ----------------------------------------------------------------------------- the run


def _scored_windows(obs):
    """``obs`` without the windows where no frame is scored: windows are independent scans and
    such a window adds 0 to both sums of :func:`jaxmocap.tune.ik_loss_parts`, so dropping it
    leaves the loss and its gradient unchanged and saves its LM solves (on the test world's
    dev split the tracker reports ~40% of frames valid; whole sequences have none)."""
    import jax

    keep = np.flatnonzero(np.asarray(obs.scored).any(axis=1))
    return jax.tree.map(lambda a: a[keep], obs)  # None fields stay None


def _view_anchors_at(setup, garment, q, work_size: int, margin: float = 1.3):
    """Per frame the per-view anchors (:func:`jaxmocap.ik.view_anchors`) of a render of the
    model at the tracker's own estimate ``q`` (T, n), on a ``work_size``-square grid over the
    box of the projected keypoints (``margin`` times its larger side) in each camera -- the
    tracker renders on its crop of the found shirt at the last round's start; its crop window
    is not kept, and its estimate is where its last round converged. Held fixed (not
    differentiated)."""
    import jax
    import jax.numpy as jnp

    from jaxmocap.body import keypoints
    from jaxmocap.camera import camera_center, pixel_rays, project
    from jaxmocap.ik import view_anchors
    from jaxmocap.render import render_rays
    from jaxmocap.sampling import crop_uv

    body, cams = setup.body, setup.cams

    def one(qt):
        kp = keypoints(body, qt)

        def grid(cam):
            uv = project(cam, kp)
            lo, hi = uv.min(0), uv.max(0)
            side = margin * jnp.max(hi - lo)
            c = (lo + hi) / 2
            return crop_uv(jnp.stack([c[0] - side / 2, c[1] - side / 2, side, side]), work_size)

        uvs = jax.vmap(grid)(cams)
        hits = jax.vmap(lambda cam, uv: render_rays(body, garment, qt, camera_center(cam),
                                                    pixel_rays(cam, uv)[1], cam.R[2]))(cams, uvs)
        a = view_anchors(body.chain, setup.anchors, cams, qt, hits.patch, hits.point, uvs)
        return a.offset, a.shift

    off, sh = jax.jit(lambda qs: jax.lax.map(one, qs))(q)
    return np.asarray(off), np.asarray(sh)


def tune_dataset(dataset, config=None, out="tune_out", split=None, subset: str | None = None,
                 name: str | None = None, tracker: str | None = None,
                 optimiser: str = "adam", steps: int = 20, learning_rate: float | None = None,
                 workers: int = 0, scheduler: str | None = None, every: int = CHECKPOINT_EVERY,
                 progress: bool = True, pf_seeds: int = 1) -> dict:
    """Tune (or resume tuning) a tracker configuration on ``dataset``'s sequences (module
    docstring); writes ``out/tuned.json`` and returns its content (plus ``wall_s``).
    ``learning_rate``: Adam's step (None: :data:`jaxmocap.tune.ADAM_LEARNING_RATE`); L-BFGS
    takes its step from the linesearch and ignores it. ``pf_seeds``: the stereo filter's loss
    is the mean of that many runs (keys of seeds 0, 1, ...; :func:`jaxmocap.tune.pf_loss`)."""
    import jax

    from jaxmocap import tune
    from jaxmocap.experiment.runner import output_folder
    from jaxmocap.io.atomic import write_text
    from jaxmocap.io.preflight import check_outputs
    from jaxmocap.tuned import TunedParameters

    if learning_rate is None:
        learning_rate = tune.ADAM_LEARNING_RATE
    if optimiser not in OPTIMISERS:
        raise ExperimentError(f"--optimiser: expected one of {', '.join(OPTIMISERS)}, "
                              f"got {optimiser!r}")
    if steps < 0 or every < 1 or workers < 0 or pf_seeds < 1:
        raise ExperimentError(f"tune: steps >= 0, every >= 1, workers >= 0, pf_seeds >= 1 "
                              f"expected; got {steps}, {every}, {workers}, {pf_seeds}")
    if optimiser == "lbfgs" and (workers or scheduler):
        raise ExperimentError("--optimiser lbfgs runs in this process (its linesearch "
                              "evaluates the loss inside the jitted update); give --workers 0")
    cfg = _pick_config(config, name, tracker)
    if optimiser == "cma" and cfg.method != "pf":
        raise ExperimentError("--optimiser cma is the stereo filter's black-box baseline "
                              "(--tracker pf); tune the shirt with adam or lbfgs")
    if pf_seeds != 1 and cfg.method != "pf":
        raise ExperimentError("--pf-seeds is the stereo filter's (--tracker pf): the shirt "
                              "tracker is deterministic")
    seqs = dataset_sequences(dataset, split, subset)
    out = output_folder(out, seqs, dataset)
    # no file it writes may be one it reads (a config, split or tuned file kept in --out)
    check_outputs([out / TUNED, out / RUN_RECORD, out / CHECKPOINT],
                  [None if isinstance(config, ExperimentConfig) else config,
                   None if split is None or not isinstance(split, (str, os.PathLike)) else split,
                   cfg.options.get("tuned")])
    if "tuned" in cfg.options:  # refused before any tracking
        from jaxmocap.experiment.runner import _check_tuned

        _check_tuned(ExperimentConfig((cfg,)), seqs)
    t0 = time.perf_counter()
    obs = observations(cfg, seqs, out, workers, scheduler, progress=progress)
    t_obs = time.perf_counter() - t0
    x64 = bool(jax.config.jax_enable_x64)
    pf = cfg.method == "pf"
    # shirt: gradients through the LM solves in float64; pf: the filter's float32
    jax.config.update("jax_enable_x64", not pf)
    try:
        import jax.numpy as jnp

        if pf:
            terms, theta0, ident, digests = _pf_setups(cfg, seqs, obs, pf_seeds)
            frames = int(sum(int(np.asarray(t[1].scored).sum()) for t in terms))
        else:
            setups, clips, theta0, ident, digests = _setups(cfg, seqs, obs, jnp.float64)
            frames = int(sum(_n(c) for c in clips))
        key = _run_key(cfg, seqs, obs, optimiser, learning_rate, ident, pf_seeds)
        ckpt = out / (CMA_CHECKPOINT if optimiser == "cma" else CHECKPOINT)
        opt = None if optimiser == "cma" else tune.make_optimiser(
            optimiser, None if optimiser == "lbfgs" else learning_rate)
        start = None
        if ckpt.is_file() and optimiser != "cma":
            try:
                start, meta = tune.load_fit_state(ckpt, theta0, opt)
            except (OSError, ValueError, KeyError, tune.TuneError):
                raise ExperimentError(f"{ckpt}: not a checkpoint of this tuning run; remove "
                                      "it or choose another --out") from None
            if meta.get("key") != key:
                raise ExperimentError(f"{ckpt}: field 'meta.key' says another run (other "
                                      "sequences, configuration, optimiser or rate); remove it "
                                      "or choose another --out")
        bar_done = 0 if start is None else start.step
        from tqdm import tqdm

        bar = tqdm(total=steps + 1, initial=min(bar_done, steps + 1), desc=f"tune {optimiser}",
                   unit="eval" if optimiser == "cma" else "step", disable=not progress)

        def callback(i, value, th):
            bar.update(1)
            bar.set_postfix(loss_cm=f"{100 * value:.3f}")

        def checkpoint(state):
            if state.step % every == 0 or state.step == steps:
                tune.save_fit_state(ckpt, state, {"key": key})

        client = cluster = None
        t1 = time.perf_counter()
        try:
            if optimiser == "cma":  # the black-box baseline: filter runs only
                best, losses = cma_search(pf_value(terms), theta0, steps + 1, ckpt, key,
                                          every, callback)
            elif pf:  # in this process (the tracking may have run on Dask)
                scalar, pf_vg = _pf_losses(terms)
                loss, vg = (scalar, False) if optimiser == "lbfgs" else (pf_vg, True)
            elif workers or scheduler:
                from jaxmocap.experiment.cluster import client_for
                from jaxmocap.experiment.tune_dask import dask_value_and_grad

                client, cluster = client_for(workers, scheduler)
                if cluster is not None:
                    client.wait_for_workers(max(1, workers), timeout="120s")
                loss, vg = dask_value_and_grad(client, setups, clips), True
            elif optimiser == "lbfgs":
                from jaxmocap.experiment.tune_dask import clip_loss

                loss, vg = clip_loss(setups, clips), False
            else:
                from jaxmocap.experiment.tune_dask import clip_value_and_grad

                loss, vg = clip_value_and_grad(setups, clips), True
            if optimiser != "cma":
                best, losses = tune.fit(loss, theta0, steps, learning_rate, callback=callback,
                                        value_and_grad=vg, optimiser=optimiser, start=start,
                                        checkpoint=checkpoint)
        finally:
            bar.close()
            if client is not None:
                client.close()
            if cluster is not None:
                cluster.close()
        t_fit = time.perf_counter() - t1
        if pf:
            params = {k: np.asarray(np.exp(getattr(best, k)), np.float64)
                      for k in ("sigma_g", "sigma_d")}
        else:
            cov = tune.ik_covariances(best)
            params = {"ik_centroid": np.asarray(cov.centroid),
                      "ik_blend": np.asarray(cov.blend), "ik_prior": np.asarray(cov.prior)}
    finally:
        jax.config.update("jax_enable_x64", x64)
    transfer, b_digest, dofs, g_digest = ident
    i_best = int(np.argmin(losses))
    result = TunedParameters(
        tracker=cfg.method, parameters=params, body_digest=b_digest, transfer=transfer,
        dof_names=dofs, garment_digest=g_digest,
        tuned_on={"dataset": str(Path(dataset).resolve()),
                  "split": None if split is None else str(split), "subset": subset,
                  "sequences": [s.name for s in seqs], "config": cfg.to_dict(),
                  "config_path": None if config is None or isinstance(config, ExperimentConfig)
                  else str(Path(config).resolve()),
                  "body_digests": digests, "frames": frames, **(
                      {"window": tune.PF_WINDOW, "seeds": list(range(PF_SEED, PF_SEED
                                                                       + pf_seeds))} if pf
                      else {"window": WINDOW}),
                  "held_fixed": PF_HELD_FIXED if pf else "the tracker's centroids, their "
                  "validity, q_blend and its valid flags (tracked once with the "
                  "configuration); each frame's LM start (the tracker's own estimate); "
                  "the white-balance and crop feedback; per-view anchors "
                  "(shared 3D anchors in the loss)"},
        loss={"what": PF_LOSS if pf else "mean per-joint position error (m) of the IK re-run "
              "over the tracker's observations, on the frames the tracker reported valid",
              "before": float(losses[0]),
              "after": float(losses[i_best]), "best_step": i_best, "steps": steps,
              "optimiser": optimiser,
              "learning_rate": learning_rate if optimiser == "adam" else None,
              "curve": [float(x) for x in losses]},
        path=str(out / TUNED))
    result.save(out / TUNED)
    doc = result.to_json()
    doc["wall_s"] = {"observations": t_obs, "fit": t_fit, "total": time.perf_counter() - t0}
    write_text(out / RUN_RECORD, json.dumps(doc["wall_s"], indent=1) + "\n")
    return doc


def _n(clip) -> float:
    from jaxmocap.experiment.tune_dask import _frames

    return _frames(clip)


def _run_key(cfg, seqs, obs, optimiser, learning_rate, ident, pf_seeds: int = 1) -> str:
    """What a checkpoint belongs to: configuration, sequences (their cached observations'
    content), optimiser and rate, parameter kind."""
    h = hashlib.sha256()
    h.update(json.dumps([cfg.to_dict(), [s.name for s in seqs], optimiser,
                         learning_rate if optimiser == "adam" else None, list(ident[:2]),
                         WINDOW], sort_keys=True, default=str).encode())
    keys = ("centroids", "visible", "q_blend", "q_gt", "valid")
    if cfg.method == "pf":
        keys = ("edges", "points", "points_valid", "valid", "q_tracker", "q_gt")
    if cfg.method == "pf":
        from jaxmocap.tune import PF_WINDOW

        h.update(json.dumps([PF_WINDOW, PF_SEED, pf_seeds, CMA_SIGMA0]).encode())
    for s in seqs:
        for k in keys:
            h.update(np.ascontiguousarray(obs[s.name][k]).tobytes())
    return h.hexdigest()[:16]


def cma_search(value, theta0, budget: int, ckpt: Path, key: str, every: int = 1,
               callback=None, sigma0: float = CMA_SIGMA0, seed: int = 0):
    """CMA-ES (Hansen's ``cma``, its default population for the dimension) minimising
    ``value(theta)`` over the flattened unconstrained parameters, started at ``theta0`` with
    step ``sigma0``: ``theta0`` is evaluated first, then whole generations while the total
    stays within ``budget`` evaluations. Returns (theta with the lowest value seen, every
    evaluation's value in order). Every ``every`` generations the search (the ``cma`` object,
    pickled, with NumPy's global random state, from which ``cma`` samples) is written to
    ``ckpt`` with ``key``; a rerun with the same key restores both and continues, so it ends
    where an uninterrupted one ends."""
    import pickle

    import cma
    import jax
    import jax.numpy as jnp

    from jaxmocap.io.atomic import atomic_path

    leaves, treedef = jax.tree.flatten(theta0)
    sizes = [int(np.size(x)) for x in leaves]
    dt = jnp.asarray(leaves[0]).dtype

    def unflat(x):
        parts = np.split(np.asarray(x, np.float64), np.cumsum(sizes)[:-1])
        return jax.tree.unflatten(treedef, [jnp.asarray(p.reshape(np.shape(leaf)), dt)
                                            for p, leaf in zip(parts, leaves, strict=True)])

    x0 = np.concatenate([np.ravel(np.asarray(x, np.float64)) for x in leaves])
    state = None
    if ckpt.is_file():
        try:
            with open(ckpt, "rb") as f:
                state = pickle.load(f)
        except (OSError, pickle.UnpicklingError, EOFError, AttributeError):
            state = None
        if state is None or state.get("key") != key:
            raise ExperimentError(f"{ckpt}: not a checkpoint of this CMA-ES run (other "
                                  "sequences, configuration or start); remove it or choose "
                                  "another --out")
    if state is None:
        es = cma.CMAEvolutionStrategy(x0, sigma0, {"seed": seed + 1, "verbose": -9})
        v = float(value(theta0))
        state = {"key": key, "es": es, "losses": [v], "best_x": x0, "best": v}
        if callback is not None:
            callback(0, v, theta0)
    else:
        np.random.set_state(state["np_random"])  # noqa: NPY002 (cma samples from it)
    es = state["es"]
    pop = es.popsize
    generation = 0
    while len(state["losses"]) + pop <= budget:
        xs = es.ask()
        vs = []
        for x in xs:
            v = float(value(unflat(x)))
            vs.append(v)
            state["losses"].append(v)
            if v < state["best"]:
                state["best"], state["best_x"] = v, np.asarray(x, np.float64)
            if callback is not None:
                callback(len(state["losses"]) - 1, v, None)
        es.tell(xs, vs)
        generation += 1
        if generation % every == 0 or len(state["losses"]) + pop > budget:
            state["np_random"] = np.random.get_state()  # noqa: NPY002
            with atomic_path(ckpt) as tmp, open(tmp, "wb") as f:
                pickle.dump(state, f)
    return unflat(state["best_x"]), np.asarray(state["losses"])


__all__ = ["OPTIMISERS", "TRACKERS", "cma_search", "observations", "tune_dataset"]

