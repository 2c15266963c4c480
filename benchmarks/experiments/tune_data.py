"""Data for the tuning experiments (docs/results/tuning.md): rendered clips tracked by the
real trackers, cached as ``.npz`` under ``$JAXMOCAP_CACHE_DIR/tune`` (float32, no x64).

``python benchmarks/experiments/tune_data.py shirt`` renders each clip of ``SHIRT_TRAIN`` and
``SHIRT_HELDOUT`` with the two-webcam rig (320x240, clutter, sensor noise; one training clip
with an occluder so that some frames miss patches), sets up the colour-shirt tracker as the
demo does (the demo's cached 3,000-pose database built from TRAIN_CLIPS, a colour model from
scribbles on white-light renders, W0 from one scribbled frame) and tracks every frame. Saved per
clip: the tracker's per-frame centroids, visibility and blended pose ``q_blend`` (the IK
inputs), its final pose, the true pose, frames and ground-truth colour ids (for the colour
tuning), and W0. (The stereo filter's one-step study that used a ``stereo`` mode here was
superseded by issue 51's loss through the running filter, ``jaxmocap tune --tracker pf``.)
"""

from __future__ import annotations

import sys
import time

import numpy as np

SIZE = (320, 240)
N_FRAMES = 30
SHIRT_TRAIN = ("humanoid3d_walk", "humanoid3d_kick", "humanoid3d_dance_a", "walker/turn_right0")
SHIRT_HELDOUT = ("humanoid3d_punch", "humanoid3d_dance_b", "walker/turn_left0")
OCCLUDED = {"humanoid3d_kick": (10, 16)}  # frames during which a panel hides part of the body
DB_SIZE = 3000  # the demo's database (jaxmocap.trackers.shirt.export.DEMO_DB_SIZE)
WORK_SIZE = 96


def cache_folder():
    from jaxmocap._config import cache_dir

    folder = cache_dir() / "tune"
    folder.mkdir(parents=True, exist_ok=True)
    return folder


def clip_file(kind: str, clip: str):
    return cache_folder() / f"{kind}-{clip.replace('/', '_')}-{N_FRAMES}.npz"


def shirt_clip(clip: str) -> None:
    import jax.numpy as jnp

    from jaxmocap.body import default_body
    from jaxmocap.garment import default_garment
    from jaxmocap.ik import IKCovariances
    from jaxmocap.posedb import SamplingConfig, load_or_build
    from jaxmocap.synth import SceneConfig, render_sequence
    from jaxmocap.trackers import shirt

    config = SceneConfig(
        clip=clip,
        n_frames=N_FRAMES,
        rig="webcams",
        width=SIZE[0],
        height=SIZE[1],
        noise_sigma=0.01,
        occluder=OCCLUDED.get(clip),
        seed=0,
    )
    t0 = time.perf_counter()
    seq = render_sequence(config)
    model = default_body()
    garment = default_garment(model)
    db = load_or_build(SamplingConfig(size=DB_SIZE), model, garment, progress=False)
    cov = IKCovariances.isotropic(2.0, 0.3, 0.5, model.n_dof)  # the demo's settings
    params, W0, color = shirt.setup_for_sequence(seq, db, cov, work_size=WORK_SIZE)
    _, out = shirt.run(params, shirt.init(params, W0, jnp.zeros(model.n_dof)), seq.frames)
    np.savez_compressed(
        clip_file("shirt", clip),
        centroids=np.asarray(out.centroids), visible=np.asarray(out.visible),
        q_blend=np.asarray(out.q_blend), q_track=np.asarray(out.q), valid=np.asarray(out.valid),
        q_gt=seq.groundtruth["q"], frames=seq.frames, colour_ids=seq.groundtruth["colour_ids"],
        W0=np.asarray(W0), color_mean=np.asarray(color.mean), color_cov=np.asarray(color.cov),
    )  # fmt: skip
    print(
        f"shirt {clip}: {time.perf_counter() - t0:.0f} s, valid {int(out.valid.sum())}/{N_FRAMES}",
        flush=True,
    )


def main(kind: str) -> None:
    from jaxmocap._config import enable_compilation_cache

    enable_compilation_cache()
    if kind != "shirt":
        raise SystemExit(f"tune_data.py: kind {kind!r}: only 'shirt' (the stereo study was "
                         "superseded, docs/results/tuning.md section 3)")
    for clip in SHIRT_TRAIN + SHIRT_HELDOUT:
        if not clip_file(kind, clip).exists():
            shirt_clip(clip)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else "shirt")
