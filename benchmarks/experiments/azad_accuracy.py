"""Accuracy of the stereo particle filter on held-out synthetic stereo sequences (Azad §V).

320x240 pair, 11 cm baseline, N = 1000, automatic initialisation on the first frame with a
triangulated head; mean per-joint error (cm) on shoulders, elbows and hands vs the ground-truth
keypoints, for Azad's filter with and without the distance cue and for the distance-cue-guided
proposal (``Proposals(guided=True)``, the default), with and without session 4's out-of-image
edge value and hand-support cue (``ext``), session 5's elbow-swivel jumps (``swivel``; all
three the defaults) and the fixed-lag smoother (``smooth_lag``), over ``keys`` keys (14 DOF,
one layer per frame). Writes
``docs/results/stereo_pf_accuracy.json`` and ``docs/images/stereo_pf_accuracy.png``.

    python benchmarks/experiments/azad_accuracy.py [n_frames] [keys]

The same table runs through ``jaxmocap experiment`` with ``azad_accuracy.toml`` (the dataset
commands are in its header); this script remains for what the command does not do: one image
line + blob tracker per clip shared by all rows (the command observes per cell), and the
per-frame error plot ``docs/images/stereo_pf_accuracy.png``.
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

from jaxmocap import blobs as bloblib  # noqa: E402
from jaxmocap.body import default_body, keypoint_index, keypoints, stereo_dofs  # noqa: E402
from jaxmocap.pf import cues  # noqa: E402
from jaxmocap.segment import HSVInterval, SegmentParams  # noqa: E402
from jaxmocap.synth.scene import make_cameras  # noqa: E402
from jaxmocap.trackers import stereo_pf as sp  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
JOINTS = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand")
LAYER_BETAS = {1: (1.0,), 3: (0.25, 0.5, 1.0)}  # annealing layers per frame


def observations(clip: str, n_frames: int, ext: bool = True) -> sp.Observation:
    """The image line + blob tracker once per clip (with the support map, read only by the
    configurations that use the hand-support cue): the tracker's blob parameters
    (``sp.BLOB_PARAMS``) with session 4's extensions, Azad's carry (``BlobParams()``) without."""
    cams = make_cameras(config(clip, n_frames), jnp.float32)
    params = sp.make_params(
        cams,
        images=sp.Images(segment=SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))),
        cues=sp.Cues(use_support=True),
    )
    blob = sp.BLOB_PARAMS if ext else bloblib.BlobParams()
    return sp.observe_sequence(params, load(clip, n_frames)["frames"], blob)


def evaluate(
    clip: str, n_frames: int, use_distance: bool, dofs, seed: int = 0, layers: int = 1,
    guided: bool = True, obs=None, ext: bool = True, swivel: bool = True, smooth_lag: int = 0,
) -> dict:  # fmt: skip
    d = load(clip, n_frames)
    model = default_body()
    cams = make_cameras(config(clip, n_frames), jnp.float32)
    params = sp.make_params(
        cams, dofs=dofs,
        cues=sp.Cues(use_distance=use_distance, edge_outside=cues.EDGE_OUTSIDE if ext else None,
                     use_support=ext),
        images=sp.Images(segment=SegmentParams(skin=HSVInterval(*sp.SYNTH_SKIN_HSV))),
        motion=sp.Motion(step_betas=LAYER_BETAS[layers]),
        proposals=sp.Proposals(guided=guided,
                               swivel_fraction=sp.SWIVEL_FRACTION if swivel else 0.0),
    )  # fmt: skip
    obs = sp.observe_sequence(params, d["frames"]) if obs is None else obs
    t0 = time.perf_counter()
    state, _ = sp.init(
        params, jax.random.key(seed), jax.tree.map(lambda a: a[sp.anchor_frame(obs)], obs)
    )
    _, est = sp.run(params, state, obs, smooth_lag)
    jax.block_until_ready(est)
    wall = time.perf_counter() - t0
    idx = keypoint_index(model, JOINTS)
    kp = np.asarray(jax.jit(jax.vmap(lambda q: keypoints(model, q)))(est.q))
    err = np.linalg.norm(kp[:, idx] - d["keypoints"][:, idx], axis=-1)
    per_joint = dict(zip(JOINTS, (100 * err.mean(0)).round(2).tolist(), strict=True))
    return {
        "clip": clip, "frames": n_frames, "distance_cue": use_distance, "n_dofs": len(dofs),
        "layers_per_frame": layers, "guided": guided, "ext": ext, "swivel": swivel,
        "smooth_lag": smooth_lag, "seed": seed,
        "mean_cm": float(100 * err.mean()), "per_joint_cm": per_joint,
        "per_frame_cm": (100 * err.mean(1)).round(2).tolist(),
        "blobs_valid_fraction": float(np.asarray(obs.valid).mean()),
        "wall_s_incl_compile": wall,
    }  # fmt: skip


def label(r: dict) -> str:
    ext = ", +out/support" if r.get("ext") else ""
    ext += ", +swivel" if r.get("swivel") else ""
    ext += f", smoothed L={r['smooth_lag']}" if r.get("smooth_lag") else ""
    return (f"{r['n_dofs']} DOF, {'guided' if r['guided'] else 'Azad'}{ext}, "
            f"{'with' if r['distance_cue'] else 'without'} p_d")  # fmt: skip


def main(n_frames: int = 40, keys: int = 4) -> None:
    model = default_body()
    d14 = stereo_dofs(model)
    rows = []
    # (distance cue, guided proposal, session 4 extensions, session 5 swivel jumps, smoothing
    # lag); 14 DOF, 1 layer per frame (3 layers and 17 DOF: session 4's table in the doc)
    configs = [(True, False, False, False, 0), (False, False, False, False, 0),
               (True, True, False, False, 0), (True, True, True, False, 0),
               (True, True, True, True, 0), (False, True, True, True, 0),
               (True, True, True, True, 5)]  # fmt: skip
    for clip in CLIPS:
        # the same image line + blob tracker for all rows (per blob-parameter set)
        obs = {ext: observations(clip, n_frames, ext) for ext in (False, True)}
        for use_d, guided, ext, swivel, lag in configs:
            for seed in range(keys):
                r = evaluate(clip, n_frames, use_d, d14, seed, 1, guided, obs[ext], ext, swivel,
                             lag)  # fmt: skip
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
            if r["clip"] == clip and r["seed"] == 0:
                ax.plot(r["per_frame_cm"], label=label(r))
        ax.set_title(f"{clip} (key 0)")
        ax.set_xlabel("frame (25 Hz)")
        ax.set_ylabel("mean joint error (cm)")
        ax.legend(fontsize=7)
    fig.tight_layout()
    img = ROOT / "docs" / "images" / "stereo_pf_accuracy.png"
    img.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(img, dpi=100)


if __name__ == "__main__":
    main(*(int(a) for a in sys.argv[1:3]))
