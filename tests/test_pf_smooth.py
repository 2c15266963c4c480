"""Fixed-lag genealogy smoothing (jaxmocap.pf.smooth) and the filters' lineage outputs:
the parents reproduce the resampling, the smoother matches a NumPy loop and, on a
linear-Gaussian model, the Rauch-Tung-Striebel fixed-lag smoother; jit/vmap/grad."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import pf

Q, R, M0, S0, T = 0.3, 0.25, 0.5, 0.8, 6  # 1-D random walk, noisy direct observations


def _loglik(s, y):
    return -0.5 * jnp.sum(jnp.square((s - y) / R))


def _params(sigma=Q, damping=0.0):
    inf = np.full(1, np.inf)
    return pf.PFParams(
        _loglik, lower=-inf, upper=inf, sigma_min=np.full(1, sigma), sigma_max=np.full(1, sigma),
        damping=damping,
    )  # fmt: skip


def _rts_fixed_lag(ys, lag):
    """E[x_t | y_1..y_min(t+lag, T)] of the Kalman model: RTS on each truncated record."""
    out = []
    for t in range(len(ys)):
        u = min(t + lag, len(ys) - 1)
        m, p, mf, pf_, mp, pp = M0, S0**2, [], [], [], []
        for y in ys[: u + 1]:
            mp.append(m)
            pp.append(p + Q**2)
            k = pp[-1] / (pp[-1] + R**2)
            m, p = mp[-1] + k * (y - mp[-1]), (1 - k) * pp[-1]
            mf.append(m)
            pf_.append(p)
        ms = mf[-1]
        for j in range(u - 1, t - 1, -1):
            ms = mf[j] + pf_[j] / pp[j + 1] * (ms - mp[j + 1])
        out.append(ms)
    return np.array(out)


def _numpy_smooth(x, lw, parents, lag):
    t_len, n = lw.shape
    out = []
    for t in range(t_len):
        s = min(t + lag, t_len - 1)
        lin = np.arange(n)
        for k in range(s, t, -1):
            lin = parents[k][lin]
        out.append(np.exp(lw[s]) @ x[t][lin])
    return np.array(out)


def test_parents_reproduce_the_resampling(rng):
    """With zero process noise and no motion, every new particle IS its parent."""
    params = _params(sigma=0.0)
    n = 64
    x = jnp.asarray(rng.normal(size=(n, 1)))
    lw = jnp.asarray(rng.normal(size=n))
    state = pf.PFState(x, x, lw - jax.scipy.special.logsumexp(lw), jnp.zeros(1))
    new, est, parent = pf.step_lineage(params, state, jnp.array([0.3]), jax.random.key(0))
    np.testing.assert_array_equal(new.particles, x[parent])
    ref_state, ref_est = pf.step(params, state, jnp.array([0.3]), jax.random.key(0))
    np.testing.assert_array_equal(new.particles, ref_state.particles)
    np.testing.assert_array_equal(est.mean, ref_est.mean)
    assert len(np.unique(np.asarray(parent))) < n  # it did resample
    # no resampling (threshold 0): the identity
    keep = pf.PFParams(
        _loglik, lower=params.lower, upper=params.upper, sigma_min=params.sigma_min,
        sigma_max=params.sigma_max, damping=0.0, resample_threshold=0.0,
    )  # fmt: skip
    _, _, parent = pf.step_lineage(keep, state, jnp.array([0.3]), jax.random.key(0))
    np.testing.assert_array_equal(parent, np.arange(n))
    # annealing: parents composed through the layers; still the same numbers as anneal_step
    betas = jnp.array([0.2, 0.5, 1.0])
    zero_spread = pf.PFParams(
        _loglik, lower=params.lower, upper=params.upper, sigma_min=np.zeros(1),
        sigma_max=np.zeros(1), damping=0.0,
    )  # fmt: skip
    new, _, parent = pf.anneal_step_lineage(zero_spread, state, jnp.array([0.3]),
                                            jax.random.key(1), betas)  # fmt: skip
    np.testing.assert_array_equal(new.particles, x[parent])
    ref, _ = pf.anneal_step(zero_spread, state, jnp.array([0.3]), jax.random.key(1), betas)
    np.testing.assert_array_equal(new.particles, ref.particles)


def test_run_lineage_equals_run_and_smoother_matches_numpy(rng):
    params = _params()
    ys = jnp.asarray(rng.normal(size=(T, 1)))
    state = pf.init(jax.random.key(0), params, jnp.array([M0]), S0, 300)
    ref_final, ref_est = pf.run(params, state, ys, jax.random.key(1))
    final, est, lin = pf.run_lineage(params, state, ys, jax.random.key(1))
    np.testing.assert_array_equal(est.mean, ref_est.mean)
    np.testing.assert_array_equal(final.particles, ref_final.particles)
    assert lin.particles.shape == (T, 300, 1) and lin.parents.shape == (T, 300)
    x, lw, par = (np.asarray(a) for a in (lin.particles, lin.log_weights, lin.parents))
    for lag in (0, 1, 3, 10):
        got = jax.jit(pf.fixed_lag_smooth, static_argnums=1)(lin, lag)
        np.testing.assert_allclose(got, _numpy_smooth(x, lw, par, lag), rtol=1e-12)
    # lag 0 is the filter; the last frame is always the filter's
    np.testing.assert_allclose(pf.fixed_lag_smooth(lin, 0), est.mean, rtol=1e-12)
    np.testing.assert_allclose(pf.fixed_lag_smooth(lin, 4)[-1], est.mean[-1], rtol=1e-12)
    with pytest.raises(ValueError, match="lag"):
        pf.fixed_lag_smooth(lin, -1)


def test_smoother_matches_rts_on_a_linear_gaussian_model(rng):
    """Against the exact (Rauch-Tung-Striebel) fixed-lag smoother; the filter's means are
    measurably further from it, so the test sees the smoothing."""
    params = _params()
    x, ys = M0 + S0 * rng.normal(), []
    for _ in range(T):
        x = x + Q * rng.normal()
        ys.append(x + R * rng.normal())
    ys = np.array(ys)
    n = 20000
    state = pf.init(jax.random.key(2), params, jnp.array([M0]), S0, n)
    _, est, lin = pf.run_lineage(params, state, jnp.asarray(ys[:, None]), jax.random.key(3))
    exact_filter = _rts_fixed_lag(ys, 0)
    np.testing.assert_allclose(np.asarray(est.mean)[:, 0], exact_filter, atol=0.02)
    for lag in (1, 2, T):
        got = np.asarray(pf.fixed_lag_smooth(lin, lag))[:, 0]
        exact = _rts_fixed_lag(ys, lag)
        np.testing.assert_allclose(got, exact, atol=0.03)
        assert np.abs(exact - exact_filter).max() > 0.05  # smoothing changes the answer


def test_smoother_vmaps_and_differentiates(rng):
    t_len, n, d = 5, 7, 2
    x = jnp.asarray(rng.normal(size=(t_len, n, d)))
    lw = jax.nn.log_softmax(jnp.asarray(rng.normal(size=(t_len, n))), axis=-1)
    par = jnp.asarray(rng.integers(0, n, size=(t_len, n)))
    lin = pf.Lineage(x, lw, par)
    # vmap over a batch of lineages equals the loop
    batch = pf.Lineage(jnp.stack([x, 2 * x]), jnp.stack([lw, lw]), jnp.stack([par, par]))
    got = jax.vmap(lambda b: pf.fixed_lag_smooth(b, 2))(batch)
    np.testing.assert_allclose(got[1], 2 * pf.fixed_lag_smooth(lin, 2), rtol=1e-12)

    # gradient in the particles and the log-weights against central finite differences
    def f(x, lw):
        return jnp.sum(jnp.sin(pf.fixed_lag_smooth(pf.Lineage(x, lw, par), 2)))

    gx, gw = jax.grad(f, argnums=(0, 1))(x, lw)
    eps = 1e-6
    for idx in [(0, 3, 1), (2, 0, 0), (4, 6, 1)]:
        e = jnp.zeros_like(x).at[idx].set(eps)
        fd = (f(x + e, lw) - f(x - e, lw)) / (2 * eps)
        np.testing.assert_allclose(gx[idx], fd, rtol=1e-6, atol=1e-9)
    for idx in [(2, 1), (4, 5)]:
        e = jnp.zeros_like(lw).at[idx].set(eps)
        fd = (f(x, lw + e) - f(x, lw - e)) / (2 * eps)
        np.testing.assert_allclose(gw[idx], fd, rtol=1e-6, atol=1e-9)
