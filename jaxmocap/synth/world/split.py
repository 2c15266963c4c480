"""The test world's sequences and their dev / test split (docs/results/test_world.md).

:func:`world_sequences` derives every sequence from one seed (``WORLD_SEED``): per tracker
(``shirt``: two 640x480 cameras, a 20-patch shirt; ``pf``: a 320x240 stereo head with a
~11 cm baseline, a single-colour shirt) twelve sequences, each a held-out clip of 90 frames at
30 fps on a body of its own proportions (height and limb lengths each within +-15% of the
bundled body's), names (jaxmocap / left_right / mixamo) and limb primitives
(capsule / box / cylinder), shirt layout (Wang's and the banded one, alternately), rig
(distance, height, baseline, convergence, field of view), light (warm, cool or both spot
lamps; one switched off or dimmed mid-sequence), clutter, a moving ball, an occluder panel,
side-on views (``yaw`` +-90 deg), spins, motion blur and JPEG compression. Sequences 0, 3, 6
and 9 of each tracker are **dev** (tune on these only), the other eight **test**.

**Second round** (issue 36): per tracker six more sequences (``shirt_12..17``, ``pf_12..17``)
that the project did not design: bodies that ship in other packages, used as they come
(pybullet's DeepMimic humanoid, dm_control's CMU humanoid; one bundled body scaled for
comparison), shirts generated over the body's geometry (8-14 colours, with and without
shoulder pieces; the stereo filter's single-colour shirt), and four of the six path-traced by
Blender Cycles (24 frames; the others MuJoCo, 60 frames). ``12`` and ``13`` are dev.

``test_world.json`` beside this module is :func:`world_sequences`' output, committed (a test
checks that they agree).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from jaxmocap.body import default_body
from jaxmocap.body.scale import measure
from jaxmocap.synth.world.spec import RIG_PRESETS, WorldSpec

WORLD_SEED = 20261124
SPLIT_JSON = Path(__file__).parent / "test_world.json"
N_PER_TRACKER = 12
N_FRAMES = 90
DEV = (0, 3, 6, 9)
CLIPS = ("humanoid3d_punch", "humanoid3d_dance_b", "walker/turn_left0", "walker/turn_left1")
NAMINGS = ("jaxmocap", "left_right", "mixamo")
LIMBS = ("capsule", "box", "cylinder")
# Nuisances per sequence slot (the same pattern for both trackers; every dev and every test
# subset holds lamp changes, clutter, an occluder and side-on turns).
PATTERN = (
    dict(lamps=("warm", "cool"), lamp_off=45, n_clutter=4),
    dict(lamps=("cool",), n_clutter=6, occluder=(30, 50), yaw=90.0),
    dict(lamps=("warm",), n_clutter=5, moving_object=True, spin=120.0, jpeg_quality=70),
    dict(lamps=("warm", "cool"), dim=(30, 60, 0.2), n_clutter=6, occluder=(40, 58), yaw=-90.0),
    dict(lamps=("cool", "warm"), lamp_off=40, n_clutter=6, motion_blur=3, yaw=45.0),
    dict(lamps=("warm", "neutral"), n_clutter=8, moving_object=True, occluder=(20, 38)),
    dict(lamps=("warm",), n_clutter=6, yaw=90.0, spin=-90.0, jpeg_quality=60),
    dict(lamps=("cool", "warm"), lamp_off=50, n_clutter=3, occluder=(55, 75), yaw=180.0),
    dict(lamps=("warm", "cool"), dim=(20, 40, 0.0), n_clutter=7, motion_blur=3, yaw=-45.0),
    dict(lamps=("cool",), n_clutter=8, moving_object=True, spin=180.0, occluder=(60, 80)),
    dict(lamps=("neutral", "warm"), lamp_off=30, n_clutter=5, yaw=-90.0, jpeg_quality=80),
    dict(lamps=("warm", "cool"), n_clutter=6, occluder=(10, 30), motion_blur=3, spin=60.0),
)
SINGLE_SHIRTS = ((0.1, 0.25, 0.8), (0.05, 0.5, 0.2), (0.55, 0.1, 0.6), (0.1, 0.6, 0.65))
# Second round: (body, renderer, nuisances) per slot 12..17; 12 and 13 are dev.
SECOND = (
    ("deepmimic", "cycles", dict(lamps=("warm", "cool"), lamp_off=12, n_clutter=5)),
    ("cmu", "mujoco", dict(lamps=("cool", "warm"), n_clutter=6, yaw=60.0, jpeg_quality=75)),
    ("scaled", "cycles", dict(lamps=("warm", "cool"), n_clutter=4, yaw=-30.0, motion_blur=3)),
    ("cmu", "cycles", dict(lamps=("cool", "warm"), dim=(6, 18, 0.1), n_clutter=6)),
    ("deepmimic", "mujoco", dict(lamps=("warm",), n_clutter=7, yaw=120.0, spin=40.0)),
    ("deepmimic", "cycles", dict(lamps=("warm", "cool"), n_clutter=5, yaw=90.0,
                                 jpeg_quality=80)),
)
SECOND_DEV = (12, 13)
CYCLES_FRAMES, SECOND_FRAMES, CYCLES_SAMPLES = 24, 60, 16


def _rig(tracker: str, rng: np.random.Generator) -> dict:
    if tracker == "shirt":
        return dict(rig="webcams", distance=round(rng.uniform(2.2, 3.2), 3),
                    camera_height=round(rng.uniform(1.1, 1.8), 3),
                    baseline=round(rng.uniform(0.8, 2.0), 3), fov=round(rng.uniform(50, 64), 2),
                    converge=True, look_height=round(rng.uniform(1.0, 1.3), 3))
    return dict(rig="stereo", distance=round(rng.uniform(1.8, 2.8), 3),
                camera_height=round(rng.uniform(1.3, 1.8), 3),
                baseline=round(rng.uniform(0.09, 0.13), 4), fov=round(rng.uniform(50, 60), 2),
                converge=bool(rng.uniform() < 0.3), look_height=round(rng.uniform(1.05, 1.3), 3))


def world_sequences(seed: int = WORLD_SEED) -> list[dict]:
    """``[{name, split, tracker, world: WorldSpec dict}]`` of the whole test world."""
    ref = measure(default_body())
    out = []
    for t_i, tracker in enumerate(("shirt", "pf")):
        rng = np.random.default_rng([seed, t_i])
        for k in range(N_PER_TRACKER):
            f = rng.uniform(0.85, 1.15, 4)
            body = {name: round(ref[name] * float(f[j]), 4) for j, name in
                    enumerate(("height", "shoulder_width", "upper_arm", "forearm"))}
            spec = dict(
                clip=CLIPS[(k + t_i) % len(CLIPS)], n_frames=N_FRAMES, start=int(
                    rng.integers(0, 20)), **body, naming=NAMINGS[(k + k // 3) % 3],
                limbs=LIMBS[(k // 3) % 3],
                garment=("wang", "bands")[k % 2] if tracker == "shirt" else "single",
                shirt_rgb=SINGLE_SHIRTS[k % len(SINGLE_SHIRTS)],
                noise_sigma=round(float(rng.uniform(0.005, 0.02)), 4),
                seed=int(rng.integers(0, 2**31)), **_rig(tracker, rng), **PATTERN[k])
            if tracker == "pf":
                spec["width"], spec["height_px"] = (RIG_PRESETS["stereo"]["width"],
                                                    RIG_PRESETS["stereo"]["height"])
            world = WorldSpec.from_dict({k2: list(v) if isinstance(v, tuple) else v
                                         for k2, v in spec.items()})
            out.append(dict(name=f"{tracker}_{k:02d}", split="dev" if k in DEV else "test",
                            tracker=tracker, world=world.to_dict()))
    for t_i, tracker in enumerate(("shirt", "pf")):
        rng = np.random.default_rng([seed, 10 + t_i])
        for j, (body, renderer, nuisance) in enumerate(SECOND):
            k = N_PER_TRACKER + j
            cycles = renderer == "cycles"
            spec = dict(
                clip=CLIPS[(k + t_i) % len(CLIPS)], start=int(rng.integers(0, 20)),
                n_frames=CYCLES_FRAMES if cycles else SECOND_FRAMES, body=body,
                garment="generated" if tracker == "shirt" else "single",
                layout_seed=int(rng.integers(0, 2**31)), shoulders=bool(j % 2),
                shirt_rgb=SINGLE_SHIRTS[(j + 1) % len(SINGLE_SHIRTS)],
                noise_sigma=round(float(rng.uniform(0.005, 0.015)), 4), renderer=renderer,
                samples=CYCLES_SAMPLES, seed=int(rng.integers(0, 2**31)),
                **_rig(tracker, rng), **nuisance)
            if body == "scaled":
                f = rng.uniform(0.85, 1.15, 4)
                spec.update({name: round(ref[name] * float(f[i]), 4) for i, name in
                             enumerate(("height", "shoulder_width", "upper_arm", "forearm"))})
            if tracker == "pf":
                spec["width"], spec["height_px"] = (RIG_PRESETS["stereo"]["width"],
                                                    RIG_PRESETS["stereo"]["height"])
            world = WorldSpec.from_dict({k2: list(v) if isinstance(v, tuple) else v
                                         for k2, v in spec.items()})
            out.append(dict(name=f"{tracker}_{k:02d}",
                            split="dev" if k in SECOND_DEV else "test",
                            tracker=tracker, world=world.to_dict()))
    return out


def write_split_json(path: str | Path = SPLIT_JSON) -> Path:
    """Write :func:`world_sequences` as the committed split file."""
    doc = {"version": 1, "seed": WORLD_SEED, "sequences": world_sequences()}
    Path(path).write_text(json.dumps(doc, indent=1) + "\n")
    return Path(path)


def load_split(path: str | Path = SPLIT_JSON) -> list[dict]:
    """The committed sequences (``[{name, split, tracker, world}]``)."""
    return json.loads(Path(path).read_text())["sequences"]
