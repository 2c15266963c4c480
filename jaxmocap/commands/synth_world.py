"""``jaxmocap synth-world``: render the independent test world's dev / test sequences
(:mod:`jaxmocap.synth.world.split`, MuJoCo) into dataset folders."""

from __future__ import annotations

import argparse
import time

from jaxmocap.errors import InputError
from jaxmocap.synth.world.spec import WorldSpec

EPILOG = """examples:
  jaxmocap synth-world world --split dev --blender-python ~/blender-env/bin/python
  jaxmocap synth-world world --split test --tracker shirt
  jaxmocap synth-world quick --split dev --only shirt_00 pf_00 --frames 10
  jaxmocap synth-world world --split test --renderer mujoco     # no Blender needed

The Cycles sequences (renderer "cycles" in the split) need a Python with bpy (Blender as a
module; bpy pins NumPy 1.26, so it lives in an environment of its own:
python3.11 -m venv ~/blender-env && ~/blender-env/bin/pip install bpy).

Sequences already in OUT are kept (delete a folder to render it again).
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "synth-world", help="render the independent test world (dev or test split; MuJoCo and "
        "Blender Cycles)",
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
    p.add_argument("--blender-python", metavar="PYTHON",
                   help="a Python with bpy (Blender as a module) for the sequences rendered by "
                   "Cycles (default $JAXMOCAP_BLENDER_PYTHON, else this Python)")
    p.add_argument("--renderer", choices=("mujoco", "cycles", "both"), default="both",
                   help="only the sequences of this renderer (default both)")
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
            and (args.tracker == "both" or s["tracker"] == args.tracker)
            and (args.renderer == "both"
                 or s["world"].get("renderer", "mujoco") == args.renderer)]
    if args.only:
        known = {s["name"] for s in load_split()}
        bad = sorted(set(args.only) - known)
        if bad:
            raise InputError(f"--only: unknown sequence(s) {bad}; known: {sorted(known)}")
        seqs = [s for s in seqs if s["name"] in args.only]
    todo = [s for s in seqs if not (out / s["name"]).exists()]
    python = None
    if any(s["world"].get("renderer") == "cycles" for s in todo):
        from jaxmocap.synth.world.cycles import blender_python

        python = blender_python(args.blender_python)  # before any work: one line if unusable
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
        seq = render_world(spec, progress=not args.quiet, blender_python=python)
        write_world(seq, out / s["name"], png=args.png)
        t, c = seq.frames.shape[:2]
        print(f"jaxmocap synth-world: {s['name']} ({s['split']}, {t} frames x {c} cameras "
              f"{seq.frames.shape[3]}x{seq.frames.shape[2]}) in {seq.seconds:.1f} s "
              f"(frame loop {1000 * seq.render_seconds / t:.0f} ms per frame)")
    print(f"jaxmocap synth-world: {len(todo)} sequence(s) in {time.perf_counter() - total:.0f} s"
          f" -> {out}")
    return 0
