"""Issue 49: the learned shirt path's per-frame estimates smoothed offline (``track --smooth``,
its default on that path) -- mean error over all frames, from an experiment's recorded cells.

``jaxmocap.kalman.smooth_poses`` (forward-backward RTS smoother, constant velocity per DOF)
over each cell's per-frame estimates (``poses.npz`` ``q_raw``), with as weights the tracker's
own gate (the frames its state kept: the cell's ``gate`` diagnostics column; cells recorded
before that column existed and run without a reporting rule report it as ``valid``), the
reported flag, or every frame. Errors: issue 17's 10 keypoints against the world's ground
truth by the experiment's own ``joint_errors_cm`` (checked against each cell's ``error_cm``).

The stereo filter's cells (method "pf") are read the same way with its own joints (PF_JOINTS)
and no ``gate`` column (its weights: the reported flag or every frame).

Run: python -m benchmarks.experiments.learned_smooth OUT --config learned --hz 4 --json x.json
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

from jaxmocap.experiment.cell import _body, eval_joints, joint_errors_cm
from jaxmocap.kalman import smooth_poses

JOINTS = ["head", "neck", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist",
          "r_wrist", "l_hand", "r_hand"]


def cell_rows(cell: Path, world: Path, hz: list[float]) -> dict:
    doc = json.loads((cell / "result.json").read_text())
    folder = world / doc["sequence"]
    shirt = doc.get("method", "shirt") == "shirt"  # the stereo filter: its own joints
    cfg = {"body": "sequence", "method": "shirt" if shirt else "pf",
           "joints": JOINTS if shirt else None, "options": {}}
    body, joints = _body(cfg, str(folder)), eval_joints(cfg)

    def err(q):  # the experiment's own per-frame error (cell_metrics)
        return joint_errors_cm(body, q, str(folder), joints)[0].mean(axis=1)

    with np.load(cell / "poses.npz") as z:
        q, fps, recorded = z["q_raw"], float(z["fps"]), z["error_cm"]
    with open(cell / "diagnostics.csv") as f:
        rows = list(csv.DictReader(f))
    col = lambda k: np.array([float(r[k]) if r.get(k) not in (None, "") else 0.0 for r in rows])  # noqa: E731
    has = np.isfinite(q).all(1)
    gate = col("gate" if "gate" in rows[0] else "valid") > 0
    e0 = err(q)
    np.testing.assert_allclose(e0[has], recorded[has], atol=1e-2)  # the experiment's own error
    out = {"sequence": doc["sequence"], "raw": float(np.nanmean(e0)),
           "gate_share": float(np.mean(gate & has))}
    for h in hz:
        for name, w in (("gate", gate & has), ("reported", (col("valid") > 0) & has),
                        ("all", has)):
            out[f"{name}@{h:g}"] = float(np.nanmean(err(smooth_poses(q, w.astype(float), fps,
                                                                      h))))
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path, help="an experiment's output folder")
    ap.add_argument("--config", default="learned")
    ap.add_argument("--world", type=Path, default=Path("/work/world"))
    ap.add_argument("--hz", type=float, nargs="+", default=[4.0])
    ap.add_argument("--json", type=Path)
    a = ap.parse_args()
    cells = sorted((a.out / "cells").glob(f"*__{a.config}__*"))
    if not cells:
        raise SystemExit(f"{a.out}: no cells of configuration {a.config!r}")
    rows = [cell_rows(c, a.world, a.hz) for c in cells]
    keys = [k for k in rows[0] if k != "sequence"]
    mean = {k: float(np.mean([r[k] for r in rows])) for k in keys}
    for r in [*rows, {"sequence": "mean", **mean}]:
        print(f"{r['sequence']:<10}" + "".join(f" {k} {r[k]:.2f}" for k in keys))
    if a.json:
        a.json.write_text(json.dumps({"cells": str(a.out), "config": a.config, "rows": rows,
                                      "mean": mean}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
