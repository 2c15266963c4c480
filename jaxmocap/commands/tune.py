"""``jaxmocap tune``: a tracker's weighting tuned by gradient on a dataset's dev sequences,
written as a tuned-parameters file (:mod:`jaxmocap.experiment.tuning`, :mod:`jaxmocap.tuned`)."""

from __future__ import annotations

import argparse

from jaxmocap.experiment.config import ExperimentError

EPILOG = """examples:
  jaxmocap tune /work/world --tracker shirt --config benchmarks/experiments/world_shirt.toml \\
      --name robust --split split.json --subset dev --steps 30 --out tuned_shirt
  jaxmocap tune data/ --tracker shirt --optimiser lbfgs --steps 10 --out tuned
  jaxmocap tune /work/world --tracker pf --config benchmarks/experiments/world_pf.toml \\
      --name jaxmocap --split dev_pf.json --steps 10 --out tuned_pf
  jaxmocap tune /work/world --tracker pf --config benchmarks/experiments/world_pf.toml \\
      --name jaxmocap --split dev_pf.json --optimiser cma --steps 10 --out cma_pf
  jaxmocap track --tuned tuned_shirt/tuned.json ...      # or experiment option tuned = "..."

outputs in --out: tuned.json (the parameters, the body / garment digests they were tuned for,
the sequences, the loss before / after), observations/<sequence>.npz (the tracker's held-fixed
observations, reused by a rerun), checkpoint.npz (every --every steps: a rerun with the same
--out resumes from it; CMA-ES: checkpoint_cma.pkl), tune_run.json (wall times).
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "tune", help="tune a tracker's weighting by gradient on a dataset's dev sequences",
        description="Track every sequence of DATASET once with the tracker configuration "
        "(its observations held fixed), then tune the parameters that weight the tracker's "
        "terms by gradient descent through the differentiable step (shirt: the IK term "
        "covariances; pf: the edge and distance cue widths sigma_g, sigma_d, through the "
        "filter re-run over every frame with stop-gradient resampling) and write "
        "them as a tuned-parameters file for `jaxmocap track --tuned`, "
        "`jaxmocap experiment` (option tuned) and the Python API (jaxmocap.tuned). Tune on "
        "dev sequences only.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", help="a `jaxmocap synth` folder, or a folder of them")
    p.add_argument("--tracker", choices=("shirt", "pf"), default="shirt",
                   help="the tracker whose parameters are tuned (default: %(default)s)")
    p.add_argument("--config", metavar="TOML", help="an experiment configuration file "
                   "(`jaxmocap experiment`): the tracker settings the observations are made "
                   "with (default: the tracker's defaults on the bundled body)")
    p.add_argument("--name", help="the configuration of --config to tune (needed when it "
                   "holds several)")
    p.add_argument("--split", metavar="JSON", help="the sequences: a JSON list of names, or an "
                   "object of lists (see --subset)")
    p.add_argument("--subset", metavar="NAME", help="the split file's list (dev)")
    p.add_argument("--optimiser", choices=("adam", "lbfgs", "cma"), default="adam",
                   help="optax Adam, or L-BFGS with its zoom linesearch (in this process "
                   "only), or CMA-ES (--tracker pf: the black-box baseline, the same loss's "
                   "value without gradients, --steps + 1 evaluations) (default: %(default)s)")
    p.add_argument("--steps", type=int, default=20, help="optimiser steps; CMA-ES: the "
                   "budget, --steps + 1 loss evaluations, as many as the gradient descent's "
                   "(default: %(default)s)")
    p.add_argument("--learning-rate", type=float, default=None, metavar="LR",
                   help="Adam's step size (default: jaxmocap.tune.ADAM_LEARNING_RATE, "
                   "0.05); L-BFGS takes its step from the linesearch and refuses one")
    p.add_argument("--pf-seeds", type=int, default=1, metavar="K",
                   help="--tracker pf: the loss is the mean of K filter runs (the keys of seeds "
                   "0..K-1): K times the cost, 1/K of one run's variance (default: %(default)s)")
    p.add_argument("--every", type=int, default=5, metavar="N",
                   help="write a checkpoint every N steps (default: %(default)s)")
    p.add_argument("--out", default="tune_out", metavar="FOLDER",
                   help="output folder (default: %(default)s)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local Dask worker processes for the tracking and the per-sequence "
                   "gradients (default 0: in this process)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler (e.g. tcp://host:8786)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from jaxmocap.experiment.tuning import tune_dataset

    if args.scheduler is not None and args.workers is not None:
        raise ExperimentError("give --workers (a local cluster) or --scheduler, not both")
    if args.optimiser == "lbfgs" and args.learning_rate is not None:
        raise ExperimentError("--learning-rate is Adam's step size; --optimiser lbfgs takes its "
                              "step from the linesearch: drop --learning-rate")
    if args.optimiser == "cma" and args.learning_rate is not None:
        raise ExperimentError("--learning-rate is Adam's step size; --optimiser cma adapts its "
                              "own step: drop --learning-rate")
    doc = tune_dataset(args.dataset, args.config, args.out, split=args.split,
                       subset=args.subset, name=args.name, tracker=args.tracker,
                       optimiser=args.optimiser, steps=args.steps,
                       learning_rate=args.learning_rate, workers=args.workers or 0,
                       scheduler=args.scheduler, every=args.every, progress=not args.quiet,
                       pf_seeds=args.pf_seeds)
    loss, wall = doc["loss"], doc["wall_s"]
    print(f"jaxmocap tune: {len(doc['tuned_on']['sequences'])} sequences, {loss['steps']} "
          f"{loss['optimiser']} steps: loss {100 * loss['before']:.2f} -> "
          f"{100 * loss['after']:.2f} cm (step {loss['best_step']}) in {wall['total']:.1f} s "
          f"(tracking {wall['observations']:.1f} s) -> {args.out}/tuned.json")
    return 0
