"""Issue 51: does the shirt tracker's error move with the parameters ``jaxmocap tune`` tunes?

Before a loss can be faithful to the tracker, the tracker's all-frames error has to depend on
the parameters more than on anything else. The stereo filter's did not (``tuning.md``: over
x0.5-x2 of its cue widths, an analysis of variance found no effect). The shirt tracker is
deterministic (no seed noise), so the question here is how far the error moves: for
``--draws`` draws of three factors, log-uniform in x1/F..xF (F = ``--factor``, the issue's 2),
the standard deviations of the IK covariances (Wang §5.2 step 4: Sigma_c of the centroids,
Sigma_b of the database pose, Sigma_p of the previous pose) are scaled by them (the
covariances by their squares) from the bundled trained ones, and the tracker as ``track`` runs
it by default (the learned observation, ``world_shirt_learned.toml``'s ``learned``) tracks the
dev sequences with each. Draw 0 is the defaults (factors 1), or ``--center``.

Each draw is a tuned-parameters file (``transfer = "role"``: carried to every sequence's
body as the defaults are) read by the experiment's ``tuned`` option, so every number is a real
``jaxmocap experiment`` cell. Reported per draw: the all-frames error of the per-frame estimates
(the cells' ``q_raw``) and of the written, smoothed poses (``track``'s default:
``learned_smooth.cell_rows``, the gate's weights at 4 Hz), mean of sequences.

    python -m benchmarks.experiments.shirt_sensitivity /work/world --split split.json \\
        --draws 8 --out /tmp/sens --json docs/results/shirt_sensitivity_dev.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

CONFIG = Path(__file__).with_name("world_shirt_learned.toml")


def tuned_files(folder: Path, factors: np.ndarray) -> list[Path]:
    """One role-transfer tuned-parameters file per row of ``factors`` (centroid, blend,
    prior standard-deviation scales) around the bundled trained covariances."""
    from jaxmocap.body import body_digest, default_body
    from jaxmocap.trackers.shirt.covariances import trained_covariances
    from jaxmocap.tuned import TunedParameters

    body = default_body()
    cov = trained_covariances(body.n_dof)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, (fc, fb, fp) in enumerate(factors):
        p = TunedParameters(
            tracker="shirt",
            parameters={"ik_centroid": (fc**2 * np.asarray(cov.centroid)).tolist(),
                        "ik_blend": (fb**2 * np.asarray(cov.blend)).tolist(),
                        "ik_prior": (fp**2 * np.asarray(cov.prior)).tolist()},
            body_digest=body_digest(body), transfer="role",
            dof_names=tuple(body.chain.dof_names),
            tuned_on={"what": "shirt_sensitivity draw", "factors": [fc, fb, fp]})
        path = folder / f"draw_{i:02d}.json"
        p.save(path)
        paths.append(path)
    return paths


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("world", type=Path)
    ap.add_argument("--split", type=Path, required=True, help="the world's split file")
    ap.add_argument("--subset", default="dev")
    ap.add_argument("--config", type=Path, default=CONFIG)
    ap.add_argument("--name", default="learned")
    ap.add_argument("--draws", type=int, default=8)
    ap.add_argument("--factor", type=float, default=2.0)
    ap.add_argument("--center", type=float, nargs=3, default=[1.0, 1.0, 1.0],
                    metavar=("FC", "FB", "FP"),
                    help="the draws' centre (draw 0), as factors of the defaults: the "
                         "landscape's roughness around a point with a small --factor")
    ap.add_argument("--out", type=Path, required=True, help="the experiment's folder")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    from jaxmocap.experiment import run_experiment
    from jaxmocap.experiment.config import load_config

    from .learned_smooth import cell_rows

    rng = np.random.default_rng(0)
    lf = np.log(args.factor)
    centre = np.asarray(args.center)
    factors = centre * np.vstack([np.ones(3), np.exp(rng.uniform(-lf, lf, (args.draws, 3)))])
    paths = tuned_files(args.out / "tuned", factors)
    base = next(c for c in load_config(args.config).configs if c.name == args.name).to_dict()
    configs = [{**base, "name": f"d{i:02d}", "options": {**base["options"], "tuned": str(p)}}
               for i, p in enumerate(paths)]
    exp_file = args.out / "sensitivity.json"
    exp_file.write_text(json.dumps({"experiment": {"good_cm": 5.0, "bad_cm": 15.0},
                                    "config": configs}, indent=1))
    t0 = time.perf_counter()
    run_experiment(args.world, exp_file, args.out, workers=0, split=args.split,
                   subset=args.subset)
    rows = []
    for i, f in enumerate(factors):
        cells = sorted((args.out / "cells").glob(f"*__d{i:02d}__*"))
        per = [cell_rows(c, args.world, [4.0]) for c in cells]
        rows.append({"factors": {"centroid": f[0], "blend": f[1], "prior": f[2]},
                     "sequences": [r["sequence"] for r in per],
                     "per_frame_cm": float(np.mean([r["raw"] for r in per])),
                     "written_cm": float(np.mean([r["gate@4"] for r in per])),
                     "per_sequence": per})
        print(f"draw {i:2d}: centroid x{f[0]:.2f} blend x{f[1]:.2f} prior x{f[2]:.2f}: "
              f"per-frame {rows[-1]['per_frame_cm']:.2f} cm, written {rows[-1]['written_cm']:.2f}"
              " cm", flush=True)
    written = np.array([r["written_cm"] for r in rows])
    result = {"world": str(args.world.resolve()), "split": args.subset, "config": base,
              "factor": args.factor, "centre": centre.tolist(),
              "draws": args.draws,
              "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
              "default_written_cm": float(written[0]),
              "draws_written_cm_range": [float(written[1:].min()), float(written[1:].max())],
              "best_vs_default": float(written.min() / written[0] - 1.0),
              "wall_s": time.perf_counter() - t0, "rows": rows}
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(result, indent=1) + "\n")
    return result


if __name__ == "__main__":
    main()
