"""``jaxmocap synth --renderer mujoco`` (one sequence) and ``jaxmocap synth-world`` (the
dev / test sets of :mod:`jaxmocap.synth.world.split`)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from jaxmocap.errors import InputError
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
    from jaxmocap.synth.dataset import _check_target
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


# ----------------------------------------------------------------------------- synth-world


EPILOG = """examples:
  jaxmocap synth-world world --split dev
  jaxmocap synth-world world --split test --tracker shirt
  jaxmocap synth-world quick --split dev --only shirt_00 pf_00 --frames 10

Sequences already in OUT are kept (delete a folder to render it again).
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "synth-world", help="render the independent test world (dev or test split, MuJoCo)",
        description="Render the test world's sequences of one split (jaxmocap/synth/world/"
        "test_world.json; docs/results/test_world.md) into OUT/<name>/, each a jaxmocap "
        "synth dataset folder. Tune on dev only.", epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", help="folder to write the sequences into (created)")
    p.add_argument("--split", choices=("dev", "test", "all"), required=True,
                   help="which sequences: dev (tune on these), test (report on these) or all")
    p.add_argument("--tracker", choices=("shirt", "pf", "both"), default="both",
                   help="shirt (2 x 640x480), pf (320x240 stereo) or both (default)")
    p.add_argument("--only", nargs="+", metavar="NAME", help="only these sequences")
    p.add_argument("--frames", type=int, metavar="N", help="at most N frames per sequence "
                   "(quick checks; the split's numbers are for the full length)")
    p.add_argument("--png", action="store_true", help="also write lossless PNG frames")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from jaxmocap.io.atomic import check_output_folder
    from jaxmocap.synth.world.render import render_world, write_world
    from jaxmocap.synth.world.split import load_split

    out = check_output_folder(args.out)
    if args.frames is not None and args.frames < 1:
        raise InputError(f"--frames {args.frames}: expected a number of frames >= 1")
    seqs = [s for s in load_split()
            if (args.split == "all" or s["split"] == args.split)
            and (args.tracker == "both" or s["tracker"] == args.tracker)]
    if args.only:
        known = {s["name"] for s in load_split()}
        bad = sorted(set(args.only) - known)
        if bad:
            raise InputError(f"--only: unknown sequence(s) {bad}; known: {sorted(known)}")
        seqs = [s for s in seqs if s["name"] in args.only]
    todo = [s for s in seqs if not (out / s["name"]).exists()]
    if len(todo) < len(seqs):
        print(f"jaxmocap synth-world: {len(seqs) - len(todo)} sequence(s) already in {out}, "
              "kept")
    out.mkdir(parents=True, exist_ok=True)
    total = time.perf_counter()
    for s in todo:
        spec_d = dict(s["world"])
        if args.frames is not None:
            spec_d["n_frames"] = min(args.frames, spec_d["n_frames"] or args.frames)
        spec = WorldSpec.from_dict(spec_d, s["name"])
        seq = render_world(spec, progress=not args.quiet)
        write_world(seq, out / s["name"], png=args.png)
        t, c = seq.frames.shape[:2]
        print(f"jaxmocap synth-world: {s['name']} ({s['split']}, {t} frames x {c} cameras "
              f"{seq.frames.shape[3]}x{seq.frames.shape[2]}) in {seq.seconds:.1f} s "
              f"(frame loop {1000 * seq.render_seconds / t:.0f} ms per frame)")
    print(f"jaxmocap synth-world: {len(todo)} sequence(s) in {time.perf_counter() - total:.0f} s"
          f" -> {out}")
    return 0
