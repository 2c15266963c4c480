"""Accuracy of the stereo particle filter on held-out synthetic stereo sequences (Azad §V).

320x240 pair, 11 cm baseline, N = 1000, automatic initialisation on the first frame with a
triangulated head; mean per-joint error (cm) on shoulders, elbows and hands vs the ground-truth
keypoints, with and without the distance cue, with 1 (Azad) or 3 annealing layers per frame,
for the 14-DOF model of the paper and for 17 DOFs (+ the spine). Writes
``docs/results/stereo_pf_accuracy.json`` and ``docs/images/stereo_pf_accuracy.png``.

    python benchmarks/experiments/azad_accuracy.py [n_frames]
"""

import json
import sys
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

sys.path.insert(0, str(Path(__file__).parent))
from azad_render import CLIPS, config, load  # noqa: E402

from jaxmocap.body import default_body, dof_index, keypoint_index, keypoints, stereo_dofs  # noqa: E402
from jaxmocap.segment import HSVInterval, SegmentParams  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402
from jaxmocap.trackers import stereo_pf as sp  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
JOINTS = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand")
LAYER_BETAS = {1: (1.0,), 3: (0.25, 0.5, 1.0)}  # annealing layers per frame


def evaluate(
    clip: str, n_frames: int, use_distance: bool, dofs, seed: int = 0, layers: int = 1
) -> dict:
    d = load(clip, n_frames)
    model = default_body()
    cams = make_cameras(config(clip, n_frames), jnp.float32)
    params = sp.make_params(
        cams, dofs=dofs, use_distance=use_distance,
        segment=SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV)),
        step_betas=LAYER_BETAS[layers],
    )  # fmt: skip
    obs = sp.observe_sequence(params, d["frames"])
    t0 = time.perf_counter()
    state, _ = sp.init(
        params, jax.random.key(seed), jax.tree.map(lambda a: a[sp.anchor_frame(obs)], obs)
    )
    _, est = sp.run(params, state, obs)
    jax.block_until_ready(est)
    wall = time.perf_counter() - t0
    idx = keypoint_index(model, JOINTS)
    kp = np.asarray(jax.jit(jax.vmap(lambda q: keypoints(model, q)))(est.q))
    err = np.linalg.norm(kp[:, idx] - d["keypoints"][:, idx], axis=-1)
    per_joint = dict(zip(JOINTS, (100 * err.mean(0)).round(2).tolist(), strict=True))
    return {
        "clip": clip, "frames": n_frames, "distance_cue": use_distance, "n_dofs": len(dofs),
        "layers_per_frame": layers, "seed": seed,
        "mean_cm": float(100 * err.mean()), "per_joint_cm": per_joint,
        "per_frame_cm": (100 * err.mean(1)).round(2).tolist(),
        "blobs_valid_fraction": float(np.asarray(obs.valid).mean()),
        "wall_s_incl_compile": wall,
    }  # fmt: skip


def main(n_frames: int = 40) -> None:
    model = default_body()
    d14 = stereo_dofs(model)
    d17 = np.sort(np.concatenate([d14, dof_index(model, ["spine_x", "spine_y", "spine_z"])]))
    rows = []
    configs = [(d14, True, 1), (d14, False, 1), (d14, True, 3), (d17, True, 1), (d17, True, 3)]
    for clip in CLIPS:
        for dofs, use_d, layers in configs:
            r = evaluate(clip, n_frames, use_d, dofs, layers=layers)
            print(json.dumps({k: v for k, v in r.items() if k != "per_frame_cm"}), flush=True)
            rows.append(r)
    out = ROOT / "docs" / "results" / "stereo_pf_accuracy.json"
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(rows, indent=1) + "\n")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(CLIPS), figsize=(5 * len(CLIPS), 3.2), squeeze=False)
    for ax, clip in zip(axes[0], CLIPS, strict=True):
        for r in rows:
            if r["clip"] == clip:
                ax.plot(r["per_frame_cm"], label=f"{r['n_dofs']} DOF, "
                        f"{'with' if r['distance_cue'] else 'without'} p_d, "
                        f"{r['layers_per_frame']} layer(s)/frame")  # fmt: skip
        ax.set_title(clip)
        ax.set_xlabel("frame (25 Hz)")
        ax.set_ylabel("mean joint error (cm)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    img = ROOT / "docs" / "images" / "stereo_pf_accuracy.png"
    img.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(img, dpi=100)


if __name__ == "__main__":
    main(int(sys.argv[1]) if len(sys.argv) > 1 else 40)
