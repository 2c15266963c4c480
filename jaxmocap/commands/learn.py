"""``jaxmocap learn``: train (or find in the cache) the learned observation model for a body and
shirt (:mod:`jaxmocap.observe`): our own renders of the body in pose-database poses under
randomised light, a small network trained with optax; a progress bar, resumable after a kill,
cached by the inputs' digests. ``track --observer FILE`` reads the file it writes.

By default the bundled body and shirt get the shipped model; a body or shirt of your own with
as many colours is fine-tuned from it (``observe.FINE_TUNE``: fewer renders and steps), any
other from scratch (``observe.Settings``). ``--start``, ``--poses``, ``--steps`` choose
otherwise. ``--tracker pf`` trains for the stereo filter's learned parts (research, not yet a
``track`` option: docs/results/learned_pf.md): crops framed like a rig's whole frames
(``observe.scenes.FRAMINGS``), Azad's one-colour shirt (``--garment`` a one-colour
garment.json; without it Azad's blue shirt on the body), from scratch."""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxmocap.commands._body import (
    add_body_args,
    body_from_args,
    garment_from_args,
    inputs_of,
    pf_garment,
)
from jaxmocap.errors import UsageError
from jaxmocap.io.atomic import check_output_file
from jaxmocap.io.preflight import check_outputs, int_range


def add_parser(sub) -> None:
    p = sub.add_parser("learn", help="train the learned observation model (pixels -> shirt "
                       "colours, head and hand skin, background) for a body and shirt")
    p.add_argument("--out", default=None, help="also write the model here (.eqx; default: only "
                   "the user's cache folder)")
    p.add_argument("--start", metavar="MODEL_EQX", help="start from this trained model (any "
                   "body, as many shirt colours; default: the bundled model where it fits)")
    p.add_argument("--poses", type=int_range(8, 100_000), metavar="N",
                   help="rendered training crops (default: 600 from scratch, 300 fine-tuning)")
    p.add_argument("--steps", type=int_range(1, 1_000_000), metavar="N",
                   help="training steps (default: 1200 from scratch, ~8 min on 2 cores; 400 "
                   "fine-tuning)")
    p.add_argument("--seed", type=int_range(0, 2**31 - 1), default=0,
                   help="seed of poses, cameras, lamps and every batch (default: %(default)s)")
    p.add_argument("--tracker", choices=("shirt", "pf"), default="shirt",
                   help="what the model is for: the colour shirt's crop (track --method shirt) "
                   "or a stereo rig's whole frames for the particle filter's learned parts "
                   "(--garment a one-colour shirt, Azad's blue without it; from scratch; "
                   "research: experiment option skin = \"learned\", measured worse than the "
                   "capture's colours, docs/results/learned_pf.md) (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    add_body_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from jaxmocap.observe import FINE_TUNE, Settings, fit, learn
    from jaxmocap.observe.classes import classes_of
    from jaxmocap.observe.fit import start_model

    if args.out is not None:
        if Path(args.out).suffix != ".eqx":
            raise UsageError(f"--out {args.out}: expected a path ending in .eqx")
        check_output_file(args.out)
        check_outputs([Path(args.out)], [*inputs_of(args), args.start])
    model = body_from_args(args)
    framing = "frame" if args.tracker == "pf" else "crop"
    garment = pf_garment(args, model) if args.tracker == "pf" else garment_from_args(args, model)
    if args.start:
        start_model(args.start, classes_of(model, garment))  # refused before any work
    chosen = args.poses is not None or args.steps is not None or args.seed != 0
    settings = None
    if chosen or args.start:
        base = FINE_TUNE if args.start else Settings()
        settings = base._replace(framing=framing, **{k: v for k, v in (("poses", args.poses),
                                                      ("steps", args.steps),
                                                      ("seed", args.seed)) if v is not None})
    if args.start:
        _, head, path = fit(model, garment, settings, out=args.out, progress=not args.quiet,
                            start=args.start)
    else:
        _, head, path = learn(model, garment, settings, out=args.out, progress=not args.quiet,
                              framing=framing)
    rec = head["record"]
    curve = rec["loss_every_10"]
    print(f"observation model: {len(head['classes'])} classes, key {head['key']}, "
          f"loss {curve[0]:.3f} -> {curve[-1]:.3f} over {rec['steps']} steps, {path}"
          + (f", also {args.out}" if args.out else ""))
    return 0
