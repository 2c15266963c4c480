"""Per-frame validity of the shirt tracker on the learned observation (issue 49 "left": 47% of
the > 15 cm frames flagged with the footage rule's thresholds, target 90%): the reported flag's
thresholds calibrated on the DEV split's experiment cells, then applied once to the test
split's cells (no re-run: a cell's ``diagnostics.csv`` holds every signal the rule reads).

The rule family is the footage rule's reporting rule (``jaxmocap.trackers.driver.VALIDITY
["footage"]``, :func:`jaxmocap.trackers.shirt.frame.reported_validity`; it changes what is
reported, not what the tracker does, so it applies to recorded cells): a frame is reported
valid when at least ``patches`` patch centroids were measured and, in every camera that found
the shirt, the centroid residual is at most ``residual`` (fraction of the crop side) and at least
``recall`` of the final pose's rendered shirt pixels carry their colour (under the model: its
labels). Calibration: over a grid, the thresholds that keep the most frames
within :data:`GOOD_CM` valid while flagging at least :data:`TARGET` of the frames beyond
:data:`BAD_CM` on the dev split (all its sequences pooled).

    python -m benchmarks.experiments.learned_validity calibrate DEV_OUT --json X.json
    python -m benchmarks.experiments.learned_validity apply TEST_OUT X.json
"""

from __future__ import annotations

import argparse
import csv
import itertools
import json
import warnings
from pathlib import Path

import numpy as np

GOOD_CM, BAD_CM, TARGET = 5.0, 15.0, 0.9
GRID = {
    "patches": (20, 22, 24, 26, 28, 30, 32, 34),
    "residual": (0.015, 0.02, 0.025, 0.03, 0.035, 0.04, 0.045, 0.053, 1.0),
    "recall": (0.0, 0.2, 0.31, 0.4, 0.45, 0.5, 0.55, 0.6, 0.65, 0.7, 0.75, 0.8),
}


def _all_nan_ok(fn, planes):
    with np.errstate(invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # all-NaN frames stay NaN
        return fn(np.stack(planes), 0)


def load_cells(out: Path, config: str = "learned") -> list[dict]:
    """Per cell of ``config``: its sequence, per-frame error (cm) and the rule's signals."""
    cells = []
    for cell in sorted((out / "cells").glob(f"*__{config}__*")):
        z = np.load(cell / "poses.npz")
        with open(cell / "diagnostics.csv") as f:
            rows = list(csv.DictReader(f))

        def col(name, rows=rows):
            return np.array([float(r[name]) if r.get(name) not in (None, "") else np.nan
                             for r in rows])

        cams = sorted({k.rsplit("_", 1)[1] for k in rows[0] if k.startswith("residual_")})
        cells.append(dict(
            sequence=cell.name.split("__")[0], error=np.asarray(z["error_cm"], float),
            valid=col("valid") > 0, patches=col("patches"),
            residual=_all_nan_ok(np.nanmax, [col(f"residual_{c}") for c in cams]),
            recall=_all_nan_ok(np.nanmin, [col(f"recall_{c}") for c in cams])))
    if not cells:
        raise SystemExit(f"{out}: no cells of configuration {config!r}")
    return cells


def reported(cell: dict, th: dict) -> np.ndarray:
    with np.errstate(invalid="ignore"):  # NaN: no camera found the shirt
        return ((cell["patches"] >= th["patches"]) & (cell["residual"] <= th["residual"])
                & (cell["recall"] >= th["recall"]))


def scores(cells: list[dict], th: dict | None) -> dict:
    """Pooled: share of the > BAD_CM frames flagged, of the < GOOD_CM frames valid, of all
    frames valid, and the mean error of the frames reported valid (``th`` None: the tracker's
    own flag)."""
    v = np.concatenate([c["valid"] if th is None else reported(c, th) for c in cells])
    e = np.concatenate([c["error"] for c in cells])
    bad, good = e > BAD_CM, e < GOOD_CM
    return dict(bad_flagged=float(np.mean(~v[bad])) if bad.any() else None,
                good_valid=float(np.mean(v[good])) if good.any() else None,
                valid=float(np.mean(v)), frames=int(len(v)), bad=int(bad.sum()),
                good=int(good.sum()),
                valid_mean_cm=float(np.nanmean(e[v])) if v.any() else None)


def calibrate(cells: list[dict]) -> tuple[dict, dict]:
    best, best_s = None, None
    for values in itertools.product(*GRID.values()):
        th = dict(zip(GRID, values, strict=True))
        s = scores(cells, th)
        if s["bad_flagged"] is None or s["bad_flagged"] < TARGET:
            continue
        key = (s["good_valid"], s["valid"])
        if best_s is None or key > (best_s["good_valid"], best_s["valid"]):
            best, best_s = th, s
    if best is None:
        raise SystemExit(f"no thresholds of the grid flag {TARGET:.0%} of the bad frames")
    return best, best_s


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    c = sub.add_parser("calibrate")
    c.add_argument("out")
    c.add_argument("--json")
    a = sub.add_parser("apply")
    a.add_argument("out")
    a.add_argument("thresholds", help="a calibrate --json record")
    a.add_argument("--json")
    args = ap.parse_args()
    cells = load_cells(Path(args.out))
    if args.cmd == "calibrate":
        th, s = calibrate(cells)
        rec = dict(split="dev", thresholds=th, dev=s, tracker_flag_dev=scores(cells, None))
    else:
        th = json.loads(Path(args.thresholds).read_text())["thresholds"]
        rec = dict(split="test", thresholds=th, test=scores(cells, th),
                   tracker_flag_test=scores(cells, None),
                   per_sequence={c["sequence"]: scores([c], th) for c in cells})
    print(json.dumps(rec, indent=1))
    if args.json:
        Path(args.json).write_text(json.dumps(rec, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
