"""The learned observation's cost (issue 49: "a tracked frame <= 1.3x today's"), in one run:

* the colour-shirt step on ``bench_shirt``'s scene (two cameras, the bundled body and shirt)
  with the paper's classification (white balance + Mahalanobis, steps 1 and 3, step 5's
  refit) and with the bundled learned model instead (``Colours(observer=...)``): median ms
  per tracked frame, and the ratio;
* the classification kernels alone on the step's two crops: Mahalanobis (``classify``, the
  paper's step 1) against the model's per-pixel log-probabilities.

``JAXMOCAP_BENCH_QUICK=1``: 320x240 and a 500-pose database.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from benchmarks import bench_shirt
from benchmarks._common import Row, sized, time_call, time_compile, write_results


def main() -> None:
    from jaxmocap.color import classify
    from jaxmocap.observe import BUNDLED, load, log_probs
    from jaxmocap.trackers import shirt

    w, h, n_db = sized(full=(640, 480, bench_shirt.DB_SIZE), quick=(320, 240, 500))
    s = bench_shirt.setup(w, h, n_db)
    p, state, frames = s["params"], s["state"], s["frames"]
    obs, _ = load(BUNDLED, p.body, p.garment)
    q = dataclasses.replace(p, colours=shirt.Colours(observer=obs))
    rows, ms = [], {}
    for name, params in (("paper (white balance + Mahalanobis)", p), ("learned observation", q)):
        st = shirt.init(params, state.W, state.q)
        st, _ = shirt.step(params, st, frames)  # the first frame: acquisition
        fn = lambda params=params, st=st: shirt.step(params, st, frames)  # noqa: E731
        comp = time_compile(fn)
        med, mn = time_call(fn, n=sized(full=15, quick=5))
        ms[name] = med
        rows.append(Row("shirt step, tracked frame", name, med, mn, 5, comp))
    n = p.search.work_size
    crops = jax.random.uniform(jax.random.key(0), (2, n, n, 3), jnp.float32, 0, 255)
    maha = jax.jit(jax.vmap(lambda c, W: classify(p.color, W, c, None, 3.0)[0]))
    learned = jax.jit(jax.vmap(lambda c: log_probs(obs, c)))
    for name, fn in (("Mahalanobis classify (step 1)", lambda: maha(crops, state.W)),
                     ("learned log-probabilities", lambda: learned(crops))):
        comp = time_compile(fn)
        med, mn = time_call(fn, n=sized(full=50, quick=10))
        rows.append(Row(f"classification, 2 crops {n}x{n}", name, med, mn, 50, comp))
    ratio = ms["learned observation"] / ms["paper (white balance + Mahalanobis)"]
    write_results("bench_observe", rows, [
        f"tracked frame, learned / paper: {ratio:.2f}x (issue 49: <= 1.3x)",
        f"scene: bench_shirt, {w}x{h}, two cameras, {n_db}-pose database"])


if __name__ == "__main__":
    main()
