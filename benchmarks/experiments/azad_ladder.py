"""Oracle ladder of the stereo particle filter (Azad et al. 2007): which stage limits accuracy?

On a held-out synthetic stereo sequence (320x240 pair, N = 1000, automatic initialisation) the
tracker is run with its real observations and with stages replaced by ground truth:

* ``pipeline``     -- the tracker as shipped: shirt-colour edge map + skin-blob tracker;
* ``gt_points``    -- (a) the distance cue reads the ground-truth 3D head / hands (always valid)
  instead of the blob tracker's triangulated points;
* ``gt_silhouette``-- (b) the edge map of the ground-truth shirt silhouette (the renderer's
  patch ids > 0, i.e. a perfect shirt segmentation), same gradient + spreading;
* ``gt_parts``     -- (b') the edge map of the ground-truth *part* boundaries: the gradient of
  the renderer's label map (torso, each upper arm, each forearm), i.e. the silhouette plus the
  edges where an arm lies in front of the torso or of the other arm -- what an ideal edge
  detector could see, and what a single-colour shirt segmentation cannot;
* ``gt_points+gt_silhouette``, ``gt_points+gt_parts`` -- (c) both;
* ``gt_init+...`` -- the same with the particles started at the ground-truth pose (no automatic
  initialisation), separating initialisation from drift.

Metric: mean per-joint error (cm) over shoulders, elbows and hands (as ``azad_accuracy.py``),
per frame. The blob tracker's own error (cm, valid entities) and its valid fraction are
reported beside. The cue functions are never given ground truth inside the tracker: the ladder
only swaps the *observation* the filter reads.

    python benchmarks/experiments/azad_ladder.py [clip] [n_frames]
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

import cv2
import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from azad_accuracy import JOINTS  # noqa: E402
from azad_render import config, load  # noqa: E402

from jaxmocap.body import default_body, keypoint_index, keypoints  # noqa: E402
from jaxmocap.pf import PFState  # noqa: E402
from jaxmocap.segment import HSVInterval, SegmentParams  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402
from jaxmocap.trackers import stereo_pf as sp  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
# patch ids of the single-colour garment (garment_for("single").patch_names order, 1-based):
# pelvis, abdomen, thorax, shoulders -> torso; then l_upper_arm, l_forearm, r_upper_arm, r_forearm
PART_OF_PATCH = np.array([0, 1, 1, 1, 1, 2, 3, 4, 5], np.uint8)
RUNGS = (
    "pipeline",
    "gt_points",
    "gt_silhouette",
    "gt_parts",
    "gt_points+gt_silhouette",
    "gt_points+gt_parts",
    "gt_init",
    "gt_init+gt_points+gt_parts",
)


def label_edges(labels: np.ndarray, seg: SegmentParams) -> np.ndarray:
    """Edge map g of a label image (h, w): the 2x1 + 1x2 gradient (label change), spread with
    the pipeline's Gaussian and remapped to [0, 1] -- :func:`jaxmocap.segment.segment_cv` with
    "foreground boundary" generalised to "label boundary"."""
    grad = np.zeros(labels.shape, np.float32)
    grad[:, :-1] = labels[:, 1:] != labels[:, :-1]
    grad[:-1, :] = np.maximum(grad[:-1, :], labels[1:, :] != labels[:-1, :])
    s = float(seg.edge_sigma)
    k = seg.edge_ksize
    spread = cv2.GaussianBlur(grad, (k, k), s, sigmaY=s, borderType=cv2.BORDER_REFLECT_101)
    peak = spread.max()
    return (spread / peak if peak > 0 else spread).astype(np.float32)


def oracle_observations(params: sp.StereoPFParams, d: dict, obs: sp.Observation, rung: str):
    """The pipeline's observations ``obs`` with the stages named in ``rung`` replaced."""
    model = params.model
    dt = params.prior_lower.dtype
    if "gt_points" in rung:
        idx = keypoint_index(model, ("head", "l_hand", "r_hand"))
        obs = sp.Observation(
            edges=obs.edges,
            points=jnp.asarray(d["keypoints"][:, idx], dt),
            valid=jnp.ones(obs.valid.shape, bool),
            foreground=obs.foreground,
            support=obs.support,
        )
    if "gt_silhouette" in rung or "gt_parts" in rung:
        ids = d["patch_ids"]
        lab = PART_OF_PATCH[ids] if "gt_parts" in rung else (ids > 0).astype(np.uint8)
        edges = np.stack(
            [[label_edges(lab[t, c], params.segment) for c in range(2)] for t in range(len(ids))]
        )
        obs = sp.Observation(
            edges=jnp.asarray(edges, dt),
            points=obs.points,
            valid=obs.valid,
            foreground=jnp.asarray(ids > 0, dt),
            support=obs.support,
        )
    return obs


def fit_subset(model, dofs: np.ndarray, q: np.ndarray, kp: np.ndarray) -> np.ndarray:
    """The ground truth as the filter's model can represent it: per frame, the DOF subset
    ``dofs`` (others 0) minimising the squared distance of all keypoints to the ground-truth
    ``kp`` (T, n_kp, 3) (scipy least squares, JAX Jacobian, started at ``q[t, dofs]``).
    Returns (T, len(dofs)). Its joint error is the model's floor (< 1 cm on our clips)."""
    from scipy.optimize import least_squares

    def res(s, target):
        full = jnp.zeros(model.n_dof, s.dtype).at[dofs].set(s)
        return (keypoints(model, full) - target).reshape(-1)

    f, jac = jax.jit(res), jax.jit(jax.jacfwd(res))
    out = []
    for t in range(len(q)):
        x = jnp.asarray(kp[t])
        r = least_squares(
            lambda s, x=x: np.asarray(f(jnp.asarray(s), x)),
            q[t, dofs].astype(np.float64),
            jac=lambda s, x=x: np.asarray(jac(jnp.asarray(s), x)),
        )
        out.append(r.x)
    return np.array(out)


def gt_state(params: sp.StereoPFParams, s0: np.ndarray, key) -> sp.TrackerState:
    """All particles at the (model-fitted) ground-truth configuration ``s0`` (subset DOFs)."""
    s = jnp.asarray(s0, params.prior_lower.dtype)
    x = jnp.broadcast_to(s, (params.n_particles, s.shape[0]))
    n = params.n_particles
    ps = PFState(
        particles=x,
        previous=x,
        log_weights=jnp.full((n,), -jnp.log(n), x.dtype),
        sigma=params.filter.sigma_min.astype(x.dtype),
    )
    return sp.TrackerState(ps, key)


def joint_errors(model, q: np.ndarray, kp_gt: np.ndarray) -> np.ndarray:
    """(T, len(JOINTS)) per-joint errors (m) of the estimated poses q (T, n_dof)."""
    idx = keypoint_index(model, JOINTS)
    kp = np.asarray(jax.jit(jax.vmap(lambda x: keypoints(model, x)))(jnp.asarray(q)))
    return np.linalg.norm(kp[:, idx] - kp_gt[:, idx], axis=-1)


def blob_quality(model, obs: sp.Observation, kp_gt: np.ndarray) -> dict:
    """Valid fraction and error (cm, over valid frames) of the blob tracker per entity."""
    idx = keypoint_index(model, ("head", "l_hand", "r_hand"))
    v = np.asarray(obs.valid)
    e = np.linalg.norm(np.asarray(obs.points) - kp_gt[:, idx], axis=-1)
    out = {}
    for i, name in enumerate(("head", "l_hand", "r_hand")):
        out[name] = {
            "valid": float(v[:, i].mean()),
            "err_cm_median": float(100 * np.median(e[v[:, i], i])) if v[:, i].any() else None,
            "err_cm_max": float(100 * e[v[:, i], i].max()) if v[:, i].any() else None,
        }
    return out


def ladder(
    clip: str = "humanoid3d_punch",
    n_frames: int = 40,
    rungs=RUNGS,
    seeds=(0,),
    make=None,
    verbose: bool = True,
) -> dict:
    """Run the rungs on ``clip``; ``make(cams)`` builds the tracker params (default: shipped)."""
    d = load(clip, n_frames)
    model = default_body()
    cams = make_cameras(config(clip, n_frames), jnp.float32)
    seg = SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))
    make = make or (lambda c: sp.make_params(c, images=sp.Images(segment=seg)))
    params = make(cams)
    base = sp.observe_sequence(params, d["frames"])
    s_gt = fit_subset(model, params.dofs, d["q"], d["keypoints"])
    floor = joint_errors(model, np.asarray(params.full_q(jnp.asarray(s_gt))), d["keypoints"])
    out = {
        "clip": clip, "frames": n_frames, "model_floor_cm": float(100 * floor.mean()),
        "blobs": blob_quality(model, base, d["keypoints"]),
    }  # fmt: skip
    rows = {}
    for rung in rungs:
        obs = oracle_observations(params, d, base, rung)
        per_frame = []
        t0 = time.perf_counter()
        for seed in seeds:
            key = jax.random.key(seed)
            if rung.startswith("gt_init"):
                state = gt_state(params, s_gt[0], key)
            else:
                t0 = sp.anchor_frame(obs)
                first = jax.tree.map(lambda a, t0=t0: a[t0], obs)
                state, _ = sp.init(params, key, first)
            _, est = sp.run(params, state, obs)
            err = joint_errors(model, np.asarray(est.q), d["keypoints"])
            per_frame.append(100 * err.mean(1))
            ll = jax.vmap(params.likelihood)
            s_est = jnp.asarray(np.asarray(est.q)[:, params.dofs], params.prior_lower.dtype)
            lik_gap = np.asarray(ll(s_est, obs) - ll(jnp.asarray(s_gt, s_est.dtype), obs))
        pf = np.mean(per_frame, 0)
        rows[rung] = {
            "mean_cm": float(pf.mean()),
            "first5_cm": float(pf[:5].mean()),
            "mid_cm": float(pf[10:20].mean()),
            "last10_cm": float(pf[-10:].mean()),
            "per_frame_cm": pf.round(2).tolist(),
            # log p(z | estimate) - log p(z | ground truth), last seed: > 0 where the
            # likelihood prefers the (wrong) estimate, i.e. the cue, not the search, is at fault
            "loglik_gap": lik_gap.round(2).tolist(),
            "frames_estimate_more_likely": float(np.mean(lik_gap > 0)),
            "wall_s": time.perf_counter() - t0,
        }
        if verbose:
            r = rows[rung]
            print(
                f"{clip:20s} {rung:28s} mean {r['mean_cm']:6.1f}  0-4 {r['first5_cm']:5.1f}  "
                f"10-19 {r['mid_cm']:5.1f}  last10 {r['last10_cm']:5.1f}  "
                f"est>gt {r['frames_estimate_more_likely']:.2f}  ({r['wall_s']:.1f} s)",
                flush=True,
            )
    out["rungs"] = rows
    return out


def plot(res: list[dict], path: Path) -> None:
    """Per-frame error of every rung, one panel per clip."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(res), figsize=(5.5 * len(res), 3.4), squeeze=False)
    for ax, r in zip(axes[0], res, strict=True):
        for rung, row in r["rungs"].items():
            ax.plot(row["per_frame_cm"], label=rung, lw=2 if rung == "pipeline" else 1)
        ax.set_title(f"{r['clip']} (model floor {r['model_floor_cm']:.1f} cm)")
        ax.set_xlabel("frame (25 Hz)")
        ax.set_ylabel("mean joint error (cm)")
        ax.legend(fontsize=6)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)


def main(clips=("humanoid3d_punch", "humanoid3d_dance_b"), n_frames: int = 40) -> None:
    res = [ladder(c, n_frames) for c in clips]
    out = ROOT / "docs" / "results" / "stereo_pf_ladder.json"
    out.write_text(json.dumps(res, indent=1) + "\n")
    plot(res, ROOT / "docs" / "images" / "stereo_pf_ladder.png")


if __name__ == "__main__":
    args = sys.argv[1:]
    main(tuple(args[:1]) or ("humanoid3d_punch", "humanoid3d_dance_b"),
         int(args[1]) if len(args) > 1 else 40)  # fmt: skip
