"""Where the colour-shirt tracker's error comes from: an oracle ladder (diagnostic).

On a held-out clip, two cameras, clean scene (no lamp step, no occluder), each rung replaces
one stage's input by ground truth and measures the mean per-joint error (cm) of the IK
result:

* ``ik_truth``: IK started at the true pose, true priors, observed centroids = centroids of
  the **ground-truth** visible patch pixels. What is left is the IK model's own bias (its
  predicted centroid vs the centroid of the visible part of a patch).
* ``ik_perturbed``: same centroids, start and priors a perturbed truth (0.15 rad, 3 cm).
* ``ik_blend``: same centroids, start and blend prior = the tracker's globally placed
  database blend ``q_blend``.
* ``tracker``: the whole tracker.

Also: the pixel error of the tracker's measured centroids against the ground-truth ones.

    python benchmarks/experiments/wang_ladder.py [n_frames]
"""

from __future__ import annotations

import os
import sys

import jax
import jax.numpy as jnp
import numpy as np

from jaxmocap.body import default_body, keypoints
from jaxmocap.color.pose_assisted import patch_centroids
from jaxmocap.garment import default_garment
from jaxmocap.ik import IKCovariances, solve_ik, view_anchors
from jaxmocap.posedb import SamplingConfig, load_or_build
from jaxmocap.render import pixel_grid, render_uv
from jaxmocap.synth import HELDOUT_CLIPS, SceneConfig, render_sequence
from jaxmocap.trackers import shirt


def gt_centroids(patch_ids: np.ndarray, n_patches: int, min_pixels: int = 4):
    """(T, C, P, 2) centroids and (T, C, P) validity of ground-truth patch-id maps."""
    f = jax.jit(jax.vmap(jax.vmap(lambda m: patch_centroids(m, n_patches, None, min_pixels))))
    c = f(jnp.asarray(patch_ids))
    return np.asarray(c.xy), np.asarray(c.valid)


def main(
    n_frames: int = 8,
    clip: str = HELDOUT_CLIPS[0],
    db_size: int = 3000,
    cov: IKCovariances | None = None,
    dtype=jnp.float32,
) -> dict:
    body = default_body()
    garment = default_garment(body)
    P = garment.n_patches
    cfg = SceneConfig(
        clip=clip,
        n_frames=n_frames,
        n_cameras=2,
        width=320,
        height=240,
        background="clutter",
        noise_sigma=0.01,
        seed=2,
    )
    seq = render_sequence(cfg, dtype)
    db = load_or_build(SamplingConfig(size=db_size), body, garment, progress=False)
    params, W0, _ = shirt.setup_for_sequence(seq, db, cov)
    kp = jax.jit(jax.vmap(lambda q: keypoints(body, q)))
    truth = seq.groundtruth["keypoints"]
    q_gt = jnp.asarray(seq.groundtruth["q"], dtype)
    c_gt, v_gt = gt_centroids(seq.groundtruth["patch_ids"], P)

    def err(q, per_joint=False):
        e = 100 * np.linalg.norm(np.asarray(kp(q)) - truth, axis=-1)
        return e.mean(0) if per_joint else e.mean(1)

    ik = jax.jit(
        jax.vmap(
            lambda c, v, qb, qh, q0: (
                solve_ik(body.chain, params.cams, params.anchors, c, v, qb, qh, params.cov, q0).q
            )
        )
    )
    ikv = jax.jit(
        jax.vmap(
            lambda a, c, v, qb, qh, q0: (
                solve_ik(body.chain, params.cams, a, c, v, qb, qh, params.cov, q0).q
            )
        )
    )
    uv = pixel_grid(cfg.width, cfg.height, dtype=dtype)

    @jax.jit
    @jax.vmap
    def render_anchors(q):
        hits = [
            render_uv(body, garment, q, jax.tree.map(lambda a, i=i: a[i], params.cams), uv)
            for i in range(params.n_cams)
        ]
        return view_anchors(
            body.chain,
            params.anchors,
            params.cams,
            q,
            jnp.stack([h.patch for h in hits]),
            jnp.stack([h.point for h in hits]),
            jnp.stack([uv] * params.n_cams),
        )

    res = {"clip": clip, "frames": n_frames, "db_size": db_size}
    res["ik_truth"] = err(ik(c_gt, v_gt, q_gt, q_gt, q_gt))
    a_gt = render_anchors(q_gt)
    res["ik_truth_view"] = err(ikv(a_gt, c_gt, v_gt, q_gt, q_gt, q_gt))
    key = jax.random.key(0)
    noise = jax.random.normal(key, q_gt.shape, dtype)
    scale = jnp.where(jnp.arange(q_gt.shape[1]) < 3, 0.03, 0.15).astype(dtype)
    q_pert = q_gt + noise * scale
    res["ik_perturbed_start"] = err(q_pert)
    res["ik_perturbed"] = err(ik(c_gt, v_gt, q_pert, q_pert, q_pert))
    q1 = ikv(render_anchors(q_pert), c_gt, v_gt, q_pert, q_pert, q_pert)
    res["ik_perturbed_view"] = err(q1)
    res["ik_perturbed_view2"] = err(ikv(render_anchors(q1), c_gt, v_gt, q_pert, q_pert, q1))
    state = shirt.init(params, W0, jnp.zeros(body.n_dof, dtype))
    _, out = shirt.run(params, state, seq.frames)
    res["blend"] = err(out.q_blend)
    res["ik_blend"] = err(ik(c_gt, v_gt, out.q_blend, out.q_blend, out.q_blend))
    qb = out.q_blend
    q1 = ikv(render_anchors(qb), c_gt, v_gt, qb, qb, qb)
    res["ik_blend_view"] = err(q1)
    res["ik_blend_view2"] = err(ikv(render_anchors(q1), c_gt, v_gt, qb, qb, q1))
    res["tracker"] = err(out.q)
    res["per_joint_tracker"] = dict(
        zip(body.keypoint_names, err(out.q, True).round(1).tolist(), strict=True)
    )
    res["per_joint_ik_blend_view2"] = dict(
        zip(body.keypoint_names, err(q1, True).round(1).tolist(), strict=True)
    )
    both = np.asarray(out.visible) & v_gt
    d = np.linalg.norm(np.asarray(out.centroids) - c_gt, axis=-1)
    if os.environ.get("LADDER_DUMP"):
        np.savez(
            os.environ["LADDER_DUMP"],
            q=np.asarray(out.q),
            q_blend=np.asarray(out.q_blend),
            centroids=np.asarray(out.centroids),
            visible=np.asarray(out.visible),
            c_gt=c_gt,
            v_gt=v_gt,
            q_gt=np.asarray(q_gt),
            window=np.asarray(out.window),
        )
    res["centroid_px_median"] = float(np.median(d[both]))
    res["centroid_px_mean"] = float(d[both].mean())
    res["centroid_missing"] = float((v_gt & ~np.asarray(out.visible)).sum() / v_gt.sum())
    res["centroid_extra"] = float((~v_gt & np.asarray(out.visible)).sum() / max(1, (~v_gt).sum()))
    out_json = {
        k: (np.round(v, 2).tolist() if isinstance(v, np.ndarray) else v) for k, v in res.items()
    }
    for k, v in res.items():
        if isinstance(v, np.ndarray):
            print(f"{k:20s} mean {v.mean():6.2f} cm  per frame {np.round(v, 1).tolist()}")
        else:
            print(f"{k:20s} {v}")
    return out_json


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 8)
