"""benchmarks/experiments/tune_faithfulness.py's variance decomposition (issue 51): the share of
the real filter's error that the cue widths explain, recovered on draws of a known share and
checked against the mean squares computed directly."""

import numpy as np

from benchmarks.experiments.tune_faithfulness import seed_variance  # pytest pythonpath "."


def test_seed_variance_recovers_a_known_share():
    rng = np.random.default_rng(0)
    draws, seeds = 40, 8
    effect = rng.normal(0.0, 3.0, draws)  # the widths' effect: variance 9
    real = {s: 30.0 + effect + rng.normal(0.0, 1.0, draws) for s in range(seeds)}  # noise 1
    v = seed_variance(real)
    y = np.array([real[s] for s in range(seeds)]).T  # (draws, seeds)
    msb = seeds * np.var(y.mean(1), ddof=1)  # between draws
    msw = np.mean(np.var(y, axis=1, ddof=1))  # within a draw (the seeds)
    np.testing.assert_allclose([v["ms_between_cm2"], v["ms_within_cm2"]], [msb, msw], rtol=1e-10)
    np.testing.assert_allclose(v["icc"], (msb - msw) / (msb + (seeds - 1) * msw), rtol=1e-10)
    assert abs(v["icc"] - 9.0 / 10.0) < 0.08  # population ICC 0.9
    assert abs(v["seed_sd_cm"] - 1.0) < 0.1 and v["p"] < 1e-10

    flat = {s: 30.0 + rng.normal(0.0, 1.0, draws) for s in range(seeds)}  # widths do nothing
    w = seed_variance(flat)
    assert abs(w["icc"]) < 0.1 and w["p"] > 0.01
    assert seed_variance({0: real[0]}) == {}  # one seed: no replicate, no decomposition
