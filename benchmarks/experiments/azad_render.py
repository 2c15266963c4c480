"""Render the held-out stereo sequences of the Azad experiments (320x240 pair, single-colour
shirt, plain background) once, cached under /tmp (not committed: regenerate from the config).

The cache holds the frames, the ground-truth poses and keypoints, and the renderer's per-pixel
patch ids (``patch_ids`` (T, 2, H, W): 0 background / skin, 1.. the shirt's geoms in
``jaxmocap.synth.sequence.garment_for("single").patch_names`` order) for the oracle ladder of
``azad_ladder.py``.

    python benchmarks/experiments/azad_render.py [n_frames]
"""

import sys
from pathlib import Path

import numpy as np

from jaxmocap.synth.motion import HELDOUT_CLIPS
from jaxmocap.synth.scene import SceneConfig
from jaxmocap.synth.sequence import render_sequence

CACHE = Path("/tmp/azad_sequences")
# punch (Azad Fig. 5 tracks a punch), dance_b (arm waves), walker/turn_left0 (a walking turn)
CLIPS = HELDOUT_CLIPS[:3]
KEYS = ("frames", "q", "keypoints", "patch_ids")


def config(clip: str, n_frames: int) -> SceneConfig:
    return SceneConfig(
        clip=clip,
        rig="stereo",
        garment="single",
        background="plain",
        n_frames=n_frames,
        fps=25.0,
        noise_sigma=0.01,
        seed=0,
    )


def path(clip: str, n_frames: int) -> Path:
    return CACHE / f"{clip.replace('/', '_')}_{n_frames}.npz"


def load(clip: str, n_frames: int) -> dict:
    p = path(clip, n_frames)
    if p.exists():
        d = dict(np.load(p))
        if all(k in d for k in KEYS):
            return d
    CACHE.mkdir(parents=True, exist_ok=True)
    seq = render_sequence(config(clip, n_frames))
    gt = seq.groundtruth
    np.savez(p, frames=seq.frames, q=gt["q"], keypoints=gt["keypoints"], patch_ids=gt["patch_ids"])
    return dict(np.load(p))


if __name__ == "__main__":
    n = int(sys.argv[1]) if len(sys.argv) > 1 else 40
    for clip in CLIPS:
        d = load(clip, n)
        print(clip, d["frames"].shape, flush=True)
