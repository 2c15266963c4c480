"""``jaxmocap eval``: tracked poses vs ground truth -> per-joint position error and jitter
(the metrics: :mod:`jaxmocap.metrics`)."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from jaxmocap.io.atomic import check_output_file, write_text
from jaxmocap.io.preflight import check_outputs
from jaxmocap.metrics import evaluate, format_table

__all__ = ["add_parser", "evaluate", "run"]

EPILOG = """examples:
  jaxmocap eval results/poses.npz data/groundtruth.npz --out results/eval.json
  jaxmocap eval results/poses.csv data/            # a dataset folder: its groundtruth.npz
"""


def add_parser(sub) -> None:
    p = sub.add_parser(
        "eval", help="compare tracked poses with a ground truth (MPJPE, jitter)",
        description="Mean per-joint position error (cm) per joint and overall, and jitter "
        "(mean second difference, cm/frame^2) of tracked keypoints against a ground truth "
        "(a synthetic dataset's groundtruth.npz). Prints a table, writes JSON.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("prediction", help="tracked poses: poses.npz or poses.csv of `jaxmocap track`")
    p.add_argument("groundtruth", help="groundtruth.npz, or a dataset folder holding one")
    p.add_argument("--out", help="write the metrics as JSON here (default: only print)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    out = check_output_file(args.out) if args.out else None
    if out is not None:
        gt = Path(args.groundtruth)
        check_outputs([out], [args.prediction, gt / "groundtruth.npz" if gt.is_dir() else gt])
    res = evaluate(args.prediction, args.groundtruth)
    print(format_table(res))
    if out is not None:
        write_text(out, json.dumps(res, indent=2) + "\n")
        print(f"wrote {out}")
    return 0
