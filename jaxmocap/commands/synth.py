"""``jaxmocap synth``: render a synthetic sequence with ground truth into a dataset folder
(:mod:`jaxmocap.synth.dataset`), with the trackers' own renderer or, with ``--renderer
mujoco``, the independent test world (:mod:`jaxmocap.synth.world`)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import jax.numpy as jnp

from jaxmocap.errors import InputError
from jaxmocap.synth.dataset import DatasetError, _check_target, write_dataset
from jaxmocap.synth.scene import RIGS, SceneConfig
from jaxmocap.synth.sequence import render_sequence
from jaxmocap.synth.world.spec import GARMENT_LAYOUTS, LAMP_COLOURS, WorldError, WorldSpec

# synth options the MuJoCo world cannot honour (said in one line, not ignored)
UNSUPPORTED = {"k1": "--k1 (MuJoCo renders no lens distortion)",
               "intensity": "--intensity", "drift": "--drift", "lamp_share": "--lamp-share",
               "background": "--background", "leave_view": "--leave-view",
               "colour_ids": "--colour-ids", "cameras": "--cameras (the world has 2)"}
# synth option -> WorldSpec field
SHARED = {"clip": "clip", "fps": "fps", "start": "start", "frames": "n_frames",
          "preset": "rig", "width": "width", "height": "height_px", "baseline": "baseline",
          "distance": "distance", "shirt_rgb": "shirt_rgb", "noise": "noise_sigma",
          "lamp_off": "lamp_off", "blur": "motion_blur", "shutter": "shutter",
          "distractors": "n_clutter", "moving_object": "moving_object", "occluder": "occluder",
          "seed": "seed"}
WORLD_OPTS = {"body_height": "height", "shoulder_width": "shoulder_width",
              "upper_arm": "upper_arm", "forearm": "forearm", "naming": "naming",
              "limbs": "limbs", "layout": "garment", "dim": "dim", "yaw": "yaw",
              "spin": "spin", "jpeg": "jpeg_quality", "camera_height": "camera_height",
              "fov": "fov", "fill": "fill"}


def add_world_options(p: argparse.ArgumentParser) -> None:
    """The ``--renderer mujoco`` options of ``jaxmocap synth``."""
    g = p.add_argument_group("MuJoCo test world (--renderer mujoco; evaluation only)")
    a = g.add_argument
    a("--renderer", choices=("jax", "mujoco"), default="jax",
      help="jax: the trackers' own ray caster (default); mujoco: the independent test world")
    a("--world", metavar="JSON", help="world settings: a world dict, a test_world.json "
      "entry or a dataset's scene.json (its 'world'); other options override them")
    a("--body-height", type=float, metavar="M", help="subject height (scales the body)")
    a("--shoulder-width", type=float, metavar="M", help="between the shoulder joints")
    a("--upper-arm", type=float, metavar="M", help="shoulder to elbow joint")
    a("--forearm", type=float, metavar="M", help="elbow to wrist joint")
    a("--naming", help="link/joint names: jaxmocap, left_right or mixamo")
    a("--limbs", choices=("capsule", "cylinder", "box"), help="limb primitive of the body")
    a("--layout", choices=GARMENT_LAYOUTS, help="shirt: wang, bands (another 20-patch "
      "layout) or single (one colour, --shirt-rgb)")
    a("--lamps", help=f"comma-separated spot lamp colours of {sorted(LAMP_COLOURS)}")
    a("--dim", type=float, nargs=3, metavar=("FIRST", "LAST", "LEVEL"),
      help="dim lamp 1 to LEVEL over frames FIRST..LAST")
    a("--yaw", type=float, metavar="DEG", help="turn the motion about the vertical")
    a("--spin", type=float, metavar="DEG_PER_S", help="an extra turn growing with time")
    a("--jpeg", type=int, metavar="Q", help="JPEG-compress every frame at quality Q")
    a("--camera-height", type=float, metavar="M", help="height of the cameras")
    a("--fov", type=float, metavar="DEG", help="horizontal field of view")
    a("--fill", type=float, help="shadowless fill light level in [0, 1]")


def _read_world(path: str) -> dict:
    p = Path(path)
    from jaxmocap.io.preflight import read_json

    doc = read_json(p, "a world JSON (a 'world' object, or a scene.json)", WorldError)
    if isinstance(doc, dict) and isinstance(doc.get("world"), dict):
        return dict(doc["world"])
    if isinstance(doc, dict) and "scene" not in doc:
        return doc
    raise WorldError(f"{p}: field 'world': expected an object of world settings")


def spec_from_args(args: argparse.Namespace) -> WorldSpec:
    for opt, text in UNSUPPORTED.items():
        if getattr(args, opt, None) not in (None, False, 0.0):
            raise InputError(f"{text}: not supported by --renderer mujoco")
    if args.scene:
        raise InputError("--scene: not supported by --renderer mujoco; use --world")
    d = _read_world(args.world) if args.world else {}
    if args.garment is not None:
        d["garment"] = "wang" if args.garment == "shirt" else "single"
    for table in (SHARED, WORLD_OPTS):
        for opt, field in table.items():
            v = getattr(args, opt, None)
            if v is not None:
                d[field] = tuple(v) if isinstance(v, list) else v
    if d.get("dim") is not None:
        a, b, level = d["dim"]
        d["dim"] = (int(a), int(b), float(level))
    if args.lamps is not None:
        d["lamps"] = tuple(s.strip() for s in args.lamps.split(",") if s.strip())
    return WorldSpec.from_dict({k: list(v) if isinstance(v, tuple) else v
                                for k, v in d.items()}, args.world or "command line")


def run_mujoco(args: argparse.Namespace) -> int:
    from jaxmocap.synth.world.render import render_world, write_world

    if args.no_video and not args.png:
        raise InputError("--no-video needs --png (otherwise no frames would be written)")
    spec = spec_from_args(args)
    _check_target(Path(args.out))
    seq = render_world(spec, progress=not args.quiet)
    folder = write_world(seq, args.out, video=not args.no_video, png=args.png,
                         sheet=args.contact_sheet)
    t, n_cams, h, w, _ = seq.frames.shape
    print(f"jaxmocap synth: wrote {t} frames x {n_cams} cameras ({w}x{h}, MuJoCo) to {folder} "
          f"in {seq.seconds:.1f} s (frame loop {1000 * seq.render_seconds / t:.0f} ms per "
          "frame, all cameras)")
    return 0



# option -> SceneConfig field
_SCENE_OPTIONS = {
    "clip": "clip", "fps": "fps", "start": "start", "frames": "n_frames", "preset": "rig",
    "cameras": "n_cameras", "width": "width", "height": "height", "baseline": "baseline",
    "distance": "distance", "k1": "k1", "garment": "garment", "shirt_rgb": "shirt_rgb",
    "intensity": "intensity", "noise": "noise_sigma", "drift": "drift", "lamp_off": "lamp_off",
    "lamp_share": "lamp_share",
    "blur": "motion_blur", "shutter": "shutter", "background": "background",
    "distractors": "n_distractors", "moving_object": "moving_object", "occluder": "occluder",
    "leave_view": "leave_view", "colour_ids": "colour_ids", "seed": "seed",
}  # fmt: skip


def add_parser(sub) -> None:
    p = sub.add_parser(
        "synth", help="render a synthetic sequence with ground truth into a dataset folder",
        description="Render a retargeted mocap clip with a camera rig and the papers' "
        "nuisances into OUT: one video per camera, cameras.json, groundtruth.npz, scene.json. "
        "Unset options take SceneConfig's defaults (or the --scene file's values).")
    p.add_argument("out", help="dataset folder to create (must not exist or be empty)")
    p.add_argument("--scene", help="scene.json of an earlier dataset: regenerate it; other "
                   "options override its settings")
    a = p.add_argument
    a("--clip", help="DeepMimic clip name (default humanoid3d_punch, held out)")
    a("--fps", type=float)
    a("--start", type=int, help="first clip frame")
    a("--frames", type=int, help="number of frames (default: the whole clip)")
    a("--preset", choices=sorted(RIGS), help="camera rig: stereo (Azad) or webcams (Wang)")
    a("--cameras", type=int, help="number of cameras, 1-4")
    a("--width", type=int)
    a("--height", type=int)
    a("--baseline", type=float, help="metres between neighbouring cameras")
    a("--distance", type=float, help="metres from the subject")
    a("--k1", type=float, help="radial distortion k1")
    a("--garment", choices=("shirt", "single"))
    a("--shirt-rgb", type=float, nargs=3, metavar=("R", "G", "B"))
    a("--intensity", type=float, help="light intensity (1 normal, <1 dim)")
    a("--noise", type=float, help="sensor noise sigma, fraction of 255")
    a("--drift", type=float, help="relative amplitude of the lamp's smooth drift")
    a("--lamp-off", type=int, metavar="FRAME", help="switch the lamp off at this frame")
    a("--lamp-share", type=float, metavar="S",
      help="the switched lamp's share of the light in (0, 1) (default: the mild built-in mix; "
           "0.7 makes switching it off a sudden, strongly bluer and darker change)")
    a("--blur", type=int, metavar="S", help="motion blur: odd number of sub-frames")
    a("--shutter", type=float, help="exposure as a fraction of the frame interval")
    a("--background", choices=("plain", "clutter"))
    a("--distractors", type=int)
    a("--moving-object", action=argparse.BooleanOptionalAction, default=None)
    a("--occluder", type=int, nargs=2, metavar=("FIRST", "LAST"))
    a("--leave-view", type=int, nargs=2, metavar=("FIRST", "LAST"))
    a("--colour-ids", action=argparse.BooleanOptionalAction, default=None)
    a("--seed", type=int)
    a("--png", action="store_true", help="also write lossless PNG frames")
    a("--no-video", action="store_true", help="do not write the mp4 videos (needs --png)")
    a("--quiet", action="store_true", help="no progress bar")
    a("--contact-sheet", action="store_true", help="also write contact_sheet.png (8 frames)")
    add_world_options(p)
    p.set_defaults(func=run)


def config_from_args(args: argparse.Namespace) -> SceneConfig:
    """The SceneConfig of the command line (over a ``--scene`` file when given)."""
    base: dict = {}
    if args.scene:
        from jaxmocap.io.preflight import read_json

        path = Path(args.scene)
        doc = read_json(path, "a scene.json of `jaxmocap synth`", DatasetError)
        if not isinstance(doc, dict) or not isinstance(doc.get("scene"), dict):
            raise DatasetError(f"{path}: field 'scene': expected an object of settings")
        base = dict(doc["scene"])
    for opt, field in _SCENE_OPTIONS.items():
        v = getattr(args, opt)
        if v is not None:
            base[field] = tuple(v) if isinstance(v, list) else v
    return SceneConfig.from_dict(base, args.scene or "command line")


def run(args: argparse.Namespace) -> int:

    if getattr(args, "renderer", "jax") == "mujoco":
        return run_mujoco(args)
    world_only = [o for o in ("world", "body_height", "shoulder_width", "upper_arm", "forearm",
                              "naming", "limbs", "layout", "lamps", "dim", "yaw", "spin",
                              "jpeg", "camera_height", "fov", "fill")
                  if getattr(args, o, None) is not None]
    if world_only:
        raise DatasetError(f"--{world_only[0].replace('_', '-')}: needs --renderer mujoco")
    if args.no_video and not args.png:
        raise DatasetError("--no-video needs --png (otherwise no frames would be written)")
    config = config_from_args(args)
    _check_target(Path(args.out))
    from jaxmocap.io.atomic import check_output_folder

    check_output_folder(args.out)
    t0 = time.perf_counter()
    seq = render_sequence(config, progress=not args.quiet)
    dt = time.perf_counter() - t0
    folder = write_dataset(seq, args.out, video=not args.no_video, png=args.png,
                           dtype_name=str(jnp.dtype(jnp.result_type(float))),
                           sheet=args.contact_sheet)
    t, n_cams, h, w, _ = seq.frames.shape
    print(f"jaxmocap synth: wrote {t} frames x {n_cams} cameras ({w}x{h}) to {folder} "
          f"in {dt:.1f} s ({t / dt:.1f} frames/s)")
    return 0
