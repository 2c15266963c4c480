"""``jaxmocap experiment``: tracker configurations x a dataset of sequences, on Dask
(:mod:`jaxmocap.experiment`)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from jaxmocap.experiment import ExperimentError, run_experiment

EPILOG = """examples:
  jaxmocap experiment data/azad benchmarks/experiments/azad_accuracy.toml --out results/azad
  jaxmocap experiment world/ configs.toml --split world/split.json --subset dev --workers 2
  jaxmocap experiment data/ configs.toml --scheduler tcp://10.0.0.5:8786 --out results/x

outputs in --out: cells/<sequence>__<config>__<seed>/{poses.npz,diagnostics.csv,result.json},
summary.md, summary.json, summary.png. Running again resumes: finished cells are read back.
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "experiment", help="run tracker configurations over a dataset of sequences (Dask)",
        description="Track every sequence of DATASET with every configuration and seed of "
        "CONFIG (TOML or JSON), write poses, diagnostics and metrics per cell and a summary "
        "comparing the configurations. Finished cells are not recomputed.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("dataset", help="a `jaxmocap synth` folder, or a folder of them")
    p.add_argument("config", help="configuration file (.toml or .json)")
    p.add_argument("--out", default="experiment_out", metavar="FOLDER",
                   help="output folder (default: %(default)s)")
    p.add_argument("--workers", type=int, default=None, metavar="N",
                   help="local Dask worker processes (default: one per core; 0: in this "
                   "process, one cell after another)")
    p.add_argument("--scheduler", metavar="ADDRESS",
                   help="an existing Dask scheduler (e.g. tcp://host:8786) instead of a "
                   "local cluster")
    p.add_argument("--split", metavar="JSON", help="the sequences to run: a JSON list of "
                   "names, or an object of lists (see --subset)")
    p.add_argument("--subset", metavar="NAME", help="the split file's list to run (dev, test)")
    p.add_argument("--retries", type=int, default=1,
                   help="re-runs of a cell that raised (default: %(default)s)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    workers = (os.cpu_count() or 1) if args.workers is None else args.workers
    if args.scheduler is not None and args.workers is not None:
        raise ExperimentError("give --workers (a local cluster) or --scheduler, not both")
    res = run_experiment(args.dataset, args.config, args.out, workers=workers,
                         scheduler=args.scheduler, split=args.split, subset=args.subset,
                         retries=args.retries, progress=not args.quiet)
    st = res["run"]
    print(f"jaxmocap experiment: {st['cells']} cells ({st['computed']} computed, "
          f"{st['reused']} reused, {st['failed']} failed) in {st['wall_s']:.1f} s -> "
          f"{args.out}/summary.md")
    for line in Path(args.out, "summary.md").read_text().splitlines()[4:]:
        if line.startswith("|"):
            print(line)
    return 1 if st["failed"] else 0
