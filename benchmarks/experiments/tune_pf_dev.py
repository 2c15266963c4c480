"""Issue 51, decision 4 at a reduced size: the stereo filter's cue widths tuned on the dev
sequences by gradient (Adam through the filter's recursion, :func:`jaxmocap.tune.pf_loss`) and
by the black-box baseline (CMA-ES on the same loss's value) with the same budget of loss
evaluations, then each result checked with the **real filter** on seeds the tuning never saw.

The observations, the cut to the first ``--frames`` frames and the real filter's error are
those of ``tune_faithfulness.py`` (:func:`dev_observations`, :func:`real_errors`); the loss's
terms are ``jaxmocap tune --tracker pf``'s (``_pf_setups``, ``_pf_losses``, ``pf_value``,
``cma_search``). Writes ``--out``/tune_pf_dev.json.

    python benchmarks/experiments/tune_pf_dev.py /work/world --frames 40 --particles 300 \\
        --steps 8 --eval-seeds 1 2 3
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import numpy as np
from tune_faithfulness import CONFIG, DEV, dev_observations, real_errors


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("world")
    ap.add_argument("--sequences", nargs="+", default=list(DEV))
    ap.add_argument("--config", default=str(CONFIG))
    ap.add_argument("--name", default="jaxmocap")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--particles", type=int, default=300)
    ap.add_argument("--steps", type=int, default=8)
    ap.add_argument("--learning-rate", type=float, default=0.1)
    ap.add_argument("--eval-seeds", type=int, nargs="+", default=[5, 6, 7],
                    help="the real filter's seeds of the check (not the loss's)")
    ap.add_argument("--loss-seeds", type=int, default=1, help="--pf-seeds of the loss")
    ap.add_argument("--out", default="benchmarks/results")
    args = ap.parse_args(argv)

    import jax.numpy as jnp

    from jaxmocap import tune
    from jaxmocap.experiment.tuning import _pf_losses, _pf_setups, cma_search, pf_value

    t0 = time.perf_counter()
    cfg, seqs, data, obs_cache = dev_observations(args.world, args.sequences, args.config,
                                                  args.name, args.frames, args.particles)
    c = cfg.to_dict()
    terms, theta0, _, _ = _pf_setups(cfg, seqs, obs_cache, args.loss_seeds)
    _, vg = _pf_losses(terms)
    widths = lambda th: (float(jnp.exp(th.sigma_g)), float(jnp.exp(th.sigma_d)))
    say = lambda tag: lambda i, v, th: print(f"{tag} {i:2d}: loss {100 * v:.3f} cm"
                                             + (f"  widths {widths(th)}" if th is not None
                                                else ""), flush=True)
    t1 = time.perf_counter()
    best_adam, curve_adam = tune.fit(vg, theta0, args.steps, args.learning_rate,
                                     callback=say("adam"), value_and_grad=True)
    t_adam = time.perf_counter() - t1
    t1 = time.perf_counter()
    with tempfile.TemporaryDirectory() as tmp:
        best_cma, curve_cma = cma_search(pf_value(terms), theta0, args.steps + 1,
                                         Path(tmp) / "cma.pkl", "tune_pf_dev", callback=say("cma"))
    t_cma = time.perf_counter() - t1
    results = {}
    for tag, th in (("defaults", theta0), ("adam", best_adam), ("cma", best_cma)):
        sg, sd = widths(th)
        real = real_errors(c, seqs, data, sg, sd, args.eval_seeds)
        per_seq = np.mean([real[s] for s in args.eval_seeds], axis=0)
        results[tag] = {"sigma_g": sg, "sigma_d": sd,
                        "real_cm": 100 * float(per_seq.mean()),
                        "real_per_seed_cm": {str(s): 100 * float(np.mean(real[s]))
                                             for s in args.eval_seeds},
                        "real_per_sequence_cm": dict(zip(args.sequences,
                                                         (100 * per_seq).tolist(), strict=True))}
        print(f"{tag}: sigma_g {sg:.3f} sigma_d {100 * sd:.2f} cm -> real filter "
              f"{results[tag]['real_cm']:.2f} cm (seeds {args.eval_seeds})", flush=True)
    doc = {"world": str(Path(args.world).resolve()), "split": "dev", "sequences": args.sequences,
           "config": c, "frames": args.frames, "particles": args.particles,
           "steps": args.steps, "learning_rate": args.learning_rate,
           "loss_seeds": list(range(args.loss_seeds)), "eval_seeds": args.eval_seeds,
           "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
           "curves_cm": {"adam": (100 * np.asarray(curve_adam)).tolist(),
                         "cma": (100 * np.asarray(curve_cma)).tolist()},
           "results": results,
           "wall_s": {"adam": t_adam, "cma": t_cma, "total": time.perf_counter() - t0}}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "tune_pf_dev.json").write_text(json.dumps(doc, indent=1) + "\n")
    return doc


if __name__ == "__main__":
    main()
