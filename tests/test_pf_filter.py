"""Generic particle filter: Kalman-filter reference on a linear-Gaussian model, resampling
statistics, motion model, box constraints, adaptive noise, degeneracy, annealing, jit/vmap/scan."""

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import pf
from jaxmocap.pf import filter as pf_filter

# --- linear-Gaussian toy model: the first-order motion model with fixed noise -----------------
DAMP = 0.4
Q_STD = np.array([0.3, 0.2])  # process noise std (the filter's fixed sigma)
H = np.array([[1.0, 0.5], [0.0, 1.0]])
R_STD = np.array([0.25, 0.3])
M0 = np.array([0.5, -1.0])
S0 = np.array([0.8, 0.6])
T = 8


def _gauss_loglik(s, y):
    r = (y - jnp.asarray(H) @ s) / jnp.asarray(R_STD)
    return -0.5 * jnp.sum(r * r)


def _kalman_params():
    d = 2
    inf = np.full(d, np.inf)
    return pf.PFParams(
        _gauss_loglik, lower=-inf, upper=inf, sigma_min=Q_STD, sigma_max=Q_STD, damping=DAMP
    )


def _simulate(rng):
    x, xp = M0 + S0 * rng.standard_normal(2), None
    xp = x.copy()
    ys = []
    for _ in range(T):
        x, xp = x + DAMP * (x - xp) + Q_STD * rng.standard_normal(2), x
        ys.append(H @ x + R_STD * rng.standard_normal(2))
    return np.array(ys)


def _kalman(ys):
    """Exact filter on the augmented state z = [s_t, s_{t-1}] (4-d); returns means, variances."""
    eye, zero = np.eye(2), np.zeros((2, 2))
    F = np.block([[(1 + DAMP) * eye, -DAMP * eye], [eye, zero]])
    Q = np.block([[np.diag(Q_STD**2), zero], [zero, zero]])
    Ha = np.hstack([H, zero])
    R = np.diag(R_STD**2)
    S = np.diag(S0**2)
    m, P = np.concatenate([M0, M0]), np.block([[S, S], [S, S]])  # at rest: s_{-1} = s_0
    means, variances = [], []
    for y in ys:
        m, P = F @ m, F @ P @ F.T + Q
        K = P @ Ha.T @ np.linalg.inv(Ha @ P @ Ha.T + R)
        m, P = m + K @ (y - Ha @ m), (np.eye(4) - K @ Ha) @ P
        means.append(m[:2])
        variances.append(np.diag(P)[:2])
    return np.array(means), np.array(variances)


def _filter(obs, key, n):
    """init at rest around M0, then run over obs (T, 2); returns the estimates."""
    params = _kalman_params()
    k0, k1 = jax.random.split(key)
    state = pf.init(k0, params, jnp.asarray(M0), jnp.asarray(S0), n)
    return pf.run(params, state, obs, k1)[1]


# one compiled program per particle count, shared by the tests: vmap over (sequence, key)
_filter_batch = jax.jit(jax.vmap(_filter, in_axes=(0, 0, None)), static_argnums=2)


def test_matches_kalman_filter_and_converges(rng):
    ys = _simulate(rng)
    km, kv = _kalman(ys)
    keys = jax.random.split(jax.random.key(0), 4)
    errs = {}
    for n in (100, 10_000):
        est = _filter_batch(jnp.asarray(np.stack([ys] * 4)), keys, n)
        e_mean = np.abs(np.asarray(est.mean) - km[None]) / np.sqrt(kv[None])  # posterior stds
        e_var = np.abs(np.asarray(est.var) / kv[None] - 1)
        errs[n] = (e_mean.mean(), e_var.mean())
    # exact reference reached at large N; error falls like 1/sqrt(N) (10x here, asked >= 3x)
    assert errs[10_000][0] < 0.05 and errs[10_000][1] < 0.06, errs
    assert errs[10_000][0] < errs[100][0] / 3 and errs[10_000][1] < errs[100][1] / 3, errs


def _counts(idx, n):
    return np.stack([np.bincount(np.asarray(i), minlength=n) for i in idx])


def test_systematic_counts_within_one():
    n = 50
    logw = jax.random.normal(jax.random.key(1), (n,)) * 2.0
    logw = logw.at[3].set(-jnp.inf)  # a zero-weight particle is never picked
    w = np.asarray(jax.nn.softmax(logw))
    lw = jnp.log(jnp.asarray(w))
    # every offset u on a fine grid of [0, 1): expected counts N w_i within one, unbiased in u
    u = jnp.broadcast_to(((np.arange(400) + 0.5) / 400)[:, None], (400, n))
    counts = _counts(jax.jit(jax.vmap(pf.resample.systematic_from_uniforms, (None, 0)))(lw, u), n)
    assert np.all(np.abs(counts - n * w[None]) < 1.0)
    assert np.all(counts[:, 3] == 0)
    np.testing.assert_allclose(counts.mean(0), n * w, atol=0.01)
    # the public entry point (own key, unnormalised log-weights)
    c = _counts(pf.systematic(jax.random.key(2), logw + 7.0)[None], n)
    assert np.all(np.abs(c - n * w[None]) < 1.0)


def test_multinomial_unbiased(rng):
    n, draws = 20, 400
    w = np.arange(1.0, n + 1.0)
    w /= w.sum()
    u = jnp.asarray(rng.random((draws, n)))
    idx = jax.jit(jax.vmap(pf.resample.multinomial_from_uniforms, (None, 0)))(jnp.log(w), u)
    counts = _counts(idx, n)
    # multinomial: mean N w_i, variance N w_i (1 - w_i); 5-sigma bound on the mean over draws
    se = np.sqrt(n * w * (1 - w) / draws)
    assert np.all(np.abs(counts.mean(0) - n * w) < 5 * se)
    np.testing.assert_allclose(counts.var(0), n * w * (1 - w), rtol=0.35)


def test_normalize_and_ess():
    lw, deg = jax.jit(pf.normalize_log_weights)(jnp.array([0.0, jnp.nan, -jnp.inf, np.log(3.0)]))
    np.testing.assert_allclose(np.exp(np.asarray(lw)), [0.25, 0, 0, 0.75], atol=1e-12)
    assert not bool(deg)
    np.testing.assert_allclose(
        float(jax.jit(pf.effective_sample_size)(lw)), 1 / (0.25**2 + 0.75**2)
    )
    lw, deg = jax.jit(pf.normalize_log_weights)(jnp.array([jnp.nan, -jnp.inf, -jnp.inf]))
    assert bool(deg)
    np.testing.assert_allclose(np.asarray(lw), -np.log(3.0))


def _const_loglik(s, z):
    return -z * jnp.ones((), s.dtype)


def test_motion_model_box_and_adaptive_noise():
    d, n = 3, 6
    lower, upper = jnp.array([-1.0, -1.0, -1.0]), jnp.array([1.0, 1.0, 1.0])
    x = jnp.linspace(-0.9, 0.9, n * d).reshape(n, d)
    xp = x - 0.6 * x / 0.9  # outward velocities: the outer particles leave the box
    state = pf.PFState(
        particles=x, previous=xp, log_weights=jnp.full(n, -jnp.log(n)), sigma=jnp.zeros(d)
    )
    params = pf.PFParams(
        _const_loglik,
        lower=lower,
        upper=upper,
        sigma_min=jnp.full(d, 0.1),
        sigma_max=jnp.full(d, 0.5),
        damping=0.7,
        error_scale=2.0,
        resample_threshold=0.0,
        boundary="reflect",
    )
    new, est = pf.step(params, state, jnp.asarray(3.0), jax.random.key(0))
    free = np.asarray(x + 0.7 * (x - xp))  # sigma = 0: s_t = s + delta (s - s_prev)
    assert np.any(np.abs(free) > 1)  # the box is exercised
    want = np.where(free > 1, 2 - free, np.where(free < -1, -2 - free, free))  # reflected
    np.testing.assert_allclose(np.asarray(new.particles), want, atol=1e-12)
    np.testing.assert_allclose(np.asarray(new.previous), np.asarray(x))
    clipped = pf_filter._constrain(jnp.asarray(free), dataclasses.replace(params, boundary="clip"))
    np.testing.assert_allclose(np.asarray(clipped), np.clip(free, -1, 1))
    # sigma = s_min + (s_max - s_min)(1 - exp(-e / e0)), e = -best loglik = 3
    np.testing.assert_allclose(np.asarray(new.sigma), 0.1 + 0.4 * (1 - np.exp(-1.5)))
    np.testing.assert_allclose(np.asarray(est.mean), want.mean(0), atol=1e-12)
    assert float(est.ess) == pytest.approx(n)
    # a perfect fit shrinks the noise to sigma_min, a poor one grows it towards sigma_max
    small = pf.step(params, state, jnp.asarray(0.0), jax.random.key(0))[0].sigma
    large = pf.step(params, state, jnp.asarray(1e3), jax.random.key(0))[0].sigma
    np.testing.assert_allclose(np.asarray(small), 0.1)
    np.testing.assert_allclose(np.asarray(large), 0.5)


def test_degenerate_frame_is_flagged_and_recovers():
    d, n = 2, 32
    box = jnp.full(d, 2.0)

    def loglik(s, z):  # NaN / -inf everywhere when z says so
        return jnp.where(z > 0, jnp.nan, -jnp.sum(s * s))

    params = pf.PFParams(
        loglik, lower=-box, upper=box, sigma_min=jnp.full(d, 0.05), sigma_max=jnp.full(d, 0.3)
    )
    x0 = jnp.asarray(np.random.default_rng(0).uniform(-1, 1, (n, d)))
    state = pf.PFState(x0, x0, jnp.full(n, -np.log(n)), jnp.full(d, 0.3))
    obs = jnp.array([0.0, 1.0, 0.0])
    final, est = pf.run(params, state, obs, jax.random.key(1))
    np.testing.assert_array_equal(np.asarray(est.degenerate), [False, True, False])
    assert np.all(np.isfinite(np.asarray(est.mean)))
    np.testing.assert_allclose(float(est.ess[1]), n)  # uniform weights after the reset
    assert np.all(np.isfinite(np.asarray(final.log_weights)))


def test_scan_equals_step_loop_deterministic_and_vmaps_over_sequences(rng):
    n = 100
    ys = jnp.asarray(np.stack([_simulate(rng) for _ in range(4)]))  # 4 sequences
    keys = jax.random.split(jax.random.key(7), 4)
    batched = _filter_batch(ys, keys, n)  # vmap over sequences (same program as above)
    again = _filter_batch(ys, keys, n)  # determinism: same keys, same result
    np.testing.assert_array_equal(np.asarray(again.mean), np.asarray(batched.mean))
    other = _filter_batch(ys, keys[::-1], n)
    assert not np.allclose(np.asarray(other.mean[1]), np.asarray(batched.mean[1]))
    # vmap(init + lax.scan(step)) == a plain Python loop of step, for one of the sequences
    params = _kalman_params()
    k0, k1 = jax.random.split(keys[1])
    state = pf.init(k0, params, jnp.asarray(M0), jnp.asarray(S0), n)
    for t, kt in enumerate(jax.random.split(k1, T)):
        state, e = pf.step(params, state, ys[1, t], kt)
        np.testing.assert_allclose(np.asarray(e.mean), np.asarray(batched.mean[1, t]), atol=1e-12)
        np.testing.assert_allclose(float(e.ess), float(batched.ess[1, t]), rtol=1e-12)


def test_annealing_finds_a_narrow_mode_from_a_uniform_start():
    d, n = 2, 200
    target = jnp.array([1.3, -2.1])

    def loglik(s, c):  # narrow likelihood (std 0.05) in a 10 x 10 box
        return -0.5 * jnp.sum(jnp.square((s - c) / 0.05))

    params = pf.PFParams(
        loglik,
        lower=jnp.full(d, -5.0),
        upper=jnp.full(d, 5.0),
        sigma_min=jnp.full(d, 0.005),
        sigma_max=jnp.full(d, 1.0),
    )
    key = jax.random.key(11)
    state = pf.init_uniform(key, params, n)
    assert np.all(np.abs(np.asarray(state.particles)) <= 5.0)
    betas = jnp.geomspace(1e-3, 1.0, 8)
    _, annealed = pf.anneal_step(params, state, target, key, betas)
    # a plain frame can at best pick the initial particle nearest the target
    err_start = np.min(np.linalg.norm(np.asarray(state.particles) - np.asarray(target), axis=1))
    err_anneal = float(jnp.linalg.norm(annealed.best - target))
    assert err_anneal < 0.05
    assert err_anneal < err_start / 3
    np.testing.assert_allclose(float(jnp.linalg.norm(annealed.mean - target)), 0.0, atol=0.05)
    assert not bool(annealed.degenerate)


def test_params_validation():
    ok = dict(lower=jnp.zeros(2), upper=jnp.ones(2), sigma_min=jnp.zeros(2), sigma_max=jnp.ones(2))
    with pytest.raises(ValueError, match="resampling"):
        pf.PFParams(_const_loglik, resampling="stratified-ish", **ok)
    with pytest.raises(ValueError, match="boundary"):
        pf.PFParams(_const_loglik, boundary="wrap", **ok)
    with pytest.raises((ValueError, TypeError), match="sigma_max|shape"):
        pf.PFParams(_const_loglik, **{**ok, "sigma_max": jnp.ones(3)})


def test_guided_proposal_is_the_weighted_min_norm_solution(rng):
    """Linear residual r(s) = A s - c (k < d): with lambda -> 0 one step lands on A s = c by the
    smallest change in the metric W = diag(scale^2) -- NumPy's minimum-norm least squares
    (lstsq) of the scaled system is the oracle; components in the null space of A are kept;
    the unguided particles are untouched; masked rows constrain nothing; jit == eager."""
    k, d, n = 3, 6, 40
    a = rng.standard_normal((k, d))
    c = rng.standard_normal(k)
    scale = np.array([0.5, 1.0, 2.0, 1.0, 0.3, 1.5])
    mask = jnp.array([True, True, False])

    def residual(s, z):
        cc, m = z
        return jnp.where(m, jnp.asarray(a) @ s - cc, 0.0)

    x = rng.standard_normal((n, d))
    prop = pf.GuidedProposal(residual, scale=scale, damping=1e-12, fraction=0.5, n_steps=1)
    key = jax.random.key(3)
    out = np.asarray(prop(jnp.asarray(x), (jnp.asarray(c), mask), key))
    out_jit = np.asarray(eqx.filter_jit(prop)(jnp.asarray(x), (jnp.asarray(c), mask), key))
    np.testing.assert_allclose(out_jit, out, atol=1e-12)
    moved = np.any(out != x, axis=1)
    assert moved.sum() == prop.n_guided(n) == 20
    am = a[:2]  # the valid rows
    for i in np.flatnonzero(moved):
        # oracle: delta = S lstsq(A_m S, c_m - A_m x) (minimum norm in the scaled coordinates)
        z_min = np.linalg.lstsq(am * scale[None, :], c[:2] - am @ x[i], rcond=None)[0]
        np.testing.assert_allclose(out[i] - x[i], scale * z_min, atol=1e-9)
        np.testing.assert_allclose(am @ out[i], c[:2], atol=1e-9)
    # null-space components (scaled coordinates) keep their spread exactly
    null = np.linalg.svd(am * scale[None, :])[2][2:]  # (d - 2, d) orthonormal basis
    zb, za = (x[moved] / scale) @ null.T, (out[moved] / scale) @ null.T
    np.testing.assert_allclose(za, zb, atol=1e-9)
    # several steps of a linear residual change nothing more; damping shortens the step
    three = pf.min_norm_steps(residual, jnp.asarray(x[0]), (jnp.asarray(c), mask), scale, 1e-12, 3)
    one = pf.min_norm_steps(residual, jnp.asarray(x[0]), (jnp.asarray(c), mask), scale, 1e-12, 1)
    np.testing.assert_allclose(np.asarray(three), np.asarray(one), atol=1e-9)
    damped = pf.min_norm_steps(residual, jnp.asarray(x[0]), (jnp.asarray(c), mask), scale, 10.0, 1)
    assert 0 < np.linalg.norm(np.asarray(damped) - x[0]) < np.linalg.norm(np.asarray(one) - x[0])
    with pytest.raises(ValueError, match="fraction"):
        pf.GuidedProposal(residual, scale=scale, fraction=1.5)


def test_filter_step_with_proposal_pulls_the_set_to_the_measurement():
    """A far-off measurement: the plain prediction leaves the set where it was, the guided
    proposal moves half of it onto the measurement's mode within one frame. Without a proposal
    the step draws exactly the numbers it drew before the hook existed (same key use)."""
    d, n = 2, 200
    target = jnp.array([3.0, -2.0])

    def loglik(s, c):
        return -0.5 * jnp.sum(jnp.square((s - c) / 0.1))

    box = dict(lower=jnp.full(d, -10.0), upper=jnp.full(d, 10.0))
    sig = dict(sigma_min=jnp.full(d, 0.05), sigma_max=jnp.full(d, 0.05))
    plain = pf.PFParams(loglik, **box, **sig)
    prop = pf.GuidedProposal(lambda s, c: s[:1] - c[:1], scale=jnp.ones(d), fraction=0.5)
    guided = pf.PFParams(loglik, **box, **sig, proposal=prop)
    key = jax.random.key(0)
    state = pf.init(key, plain, jnp.zeros(d), 0.05, n)
    s_plain, e_plain = pf.step(plain, state, target, key)
    s_guided, e_guided = pf.step(guided, state, target, key)
    # plain: the particles stay near 0 (the nearest to the target is ~3.6 away)
    assert np.max(np.abs(np.asarray(s_plain.particles))) < 0.5
    # guided: half the particles have x_0 on the target, x_1 (unconstrained) keeps its noise
    xg = np.asarray(s_guided.particles)
    on = np.abs(xg[:, 0] - 3.0) < 1e-3
    assert on.sum() == n // 2
    assert 0.03 < xg[on, 1].std() < 0.08 and np.abs(xg[on, 1]).max() < 0.5
    assert float(e_guided.mean[0]) > 2.9  # weights select the guided half
    # the plain path is unchanged by the hook (the key is not split without a proposal)
    ref_x = pf_filter._predict(plain, state, key)[0]
    np.testing.assert_allclose(np.asarray(s_plain.particles), np.asarray(ref_x), atol=1e-12)


def test_spd_solve_matches_lapack_under_jit_vmap_and_grad(rng):
    """The written-out Cholesky solve of the guided proposal (sizes up to UNROLL_MAX) against
    NumPy's LAPACK solve, batched under vmap and jit, and its gradient against central finite
    differences; above UNROLL_MAX it is jax.scipy's cho_solve."""
    from jaxmocap.pf.guided import UNROLL_MAX, spd_solve

    for k in (1, 3, 9, UNROLL_MAX + 2):
        m = rng.standard_normal((5, k, k))
        a = m @ np.swapaxes(m, 1, 2) + 0.5 * np.eye(k)
        b = rng.standard_normal((5, k))
        x = jax.jit(jax.vmap(spd_solve))(jnp.asarray(a), jnp.asarray(b))
        np.testing.assert_allclose(x, np.linalg.solve(a, b[..., None])[..., 0], rtol=1e-9,
                                   atol=1e-10)  # fmt: skip
    a0, b0 = jnp.asarray(a[0, :9, :9]), jnp.asarray(b[0, :9])

    def f(t):
        return jnp.sum(jnp.sin(spd_solve(a0 + t * jnp.eye(9), b0 * (1 + t))))

    h = 1e-6
    np.testing.assert_allclose(jax.grad(f)(0.0), (f(h) - f(-h)) / (2 * h), rtol=1e-6)


# --- gradients through the recursion: stop-gradient resampling (Scibior & Wood 2021) ---------


class _NoisyObservation(eqx.Module):
    """The toy's observation density y ~ N(H s, diag(r^2)), normalised (an evidence needs
    it), with log r traced: the parameter a gradient is taken for."""

    log_r: jax.Array

    def __call__(self, s, y):
        z = (y - jnp.asarray(H) @ s) * jnp.exp(-self.log_r)
        return -0.5 * jnp.sum(z * z) - jnp.sum(self.log_r) - np.log(2 * np.pi)


def _toy_params(log_q, log_r, gradient="stop"):
    inf = np.full(2, np.inf)
    q = jnp.exp(log_q)
    return pf.PFParams(_NoisyObservation(log_r), lower=-inf, upper=inf, sigma_min=q,
                       sigma_max=q, damping=DAMP, resampling_gradient=gradient)


def _pf_log_evidence(theta, ys, key, n, gradient="stop"):
    """The filter's log-marginal-likelihood estimate sum_t log p^(y_t | y_{1:t-1})."""
    params = _toy_params(theta[:2], theta[2:], gradient)
    k0, k1 = jax.random.split(key)
    state = pf.init(k0, params, jnp.asarray(M0), jnp.asarray(S0), n)
    return jnp.sum(pf.run(params, state, ys, k1)[1].log_evidence)


def _kalman_log_evidence(theta, ys):
    """Exact log p(y_{1:T}) of the toy (the augmented-state Kalman filter of :func:`_kalman`),
    in JAX so that its gradient is exact."""
    q, r = jnp.exp(theta[:2]), jnp.exp(theta[2:])
    eye, zero = jnp.eye(2), jnp.zeros((2, 2))
    F = jnp.block([[(1 + DAMP) * eye, -DAMP * eye], [eye, zero]])
    Q = jnp.block([[jnp.diag(q**2), zero], [zero, zero]])
    Ha = jnp.hstack([jnp.asarray(H), zero])
    S0m = jnp.diag(jnp.asarray(S0) ** 2)
    m, P = jnp.concatenate([jnp.asarray(M0)] * 2), jnp.block([[S0m, S0m], [S0m, S0m]])

    def frame(carry, y):
        m, P = carry
        m, P = F @ m, F @ P @ F.T + Q
        S = Ha @ P @ Ha.T + jnp.diag(r**2)
        v = y - Ha @ m
        ll = -0.5 * (v @ jnp.linalg.solve(S, v) + jnp.linalg.slogdet(2 * np.pi * S)[1])
        K = P @ Ha.T @ jnp.linalg.inv(S)
        return (m + K @ v, (jnp.eye(4) - K @ Ha) @ P), (ll, m + K @ v)

    ll, means = jax.lax.scan(frame, (m, P), ys)[1]
    return jnp.sum(ll), means[:, :2]


THETA = np.log(np.concatenate([Q_STD, R_STD]))


def test_kalman_reference_of_the_gradient_test(rng):
    """The JAX Kalman filter equals the NumPy one's means, and its gradient central
    differences: the oracle below is exact."""
    ys = jnp.asarray(_simulate(rng))
    ll, means = _kalman_log_evidence(jnp.asarray(THETA), ys)
    np.testing.assert_allclose(means, _kalman(np.asarray(ys))[0], atol=1e-12)
    g = jax.grad(lambda t: _kalman_log_evidence(t, ys)[0])(jnp.asarray(THETA))
    h = 1e-6
    for i in range(4):
        e = np.zeros(4)
        e[i] = h
        fd = (_kalman_log_evidence(jnp.asarray(THETA + e), ys)[0]
              - _kalman_log_evidence(jnp.asarray(THETA - e), ys)[0]) / (2 * h)
        assert abs(float(g[i]) - float(fd)) < 1e-6 * max(1.0, abs(float(fd)))


_grad_batch = jax.jit(
    jax.vmap(jax.grad(_pf_log_evidence), in_axes=(None, None, 0, None, None)),
    static_argnums=(3, 4))


def test_stop_gradient_resampling_gradient_approaches_the_kalman_gradient(rng):
    """d log p^(y) / d (log q, log r) of the particle filter (stop-gradient resampling) over 32
    keys: its mean is the Kalman filter's exact gradient within a few standard errors, and its
    error falls as N grows; without the correction (``"none"``) the noise gradients are
    biased (each frame's weights see only that frame's effect, not their ancestors')."""
    ys = jnp.asarray(_simulate(rng))
    exact = np.asarray(jax.grad(lambda t: _kalman_log_evidence(t, ys)[0])(jnp.asarray(THETA)))
    keys = jax.random.split(jax.random.key(3), 32)
    th = jnp.asarray(THETA)
    rmse, bias = {}, {}
    for n in (100, 2000):
        g = np.asarray(_grad_batch(th, ys, keys, n, "stop"))
        rmse[n] = np.sqrt(np.mean(np.sum((g - exact) ** 2, axis=1)))
        se = g.std(0) / np.sqrt(len(keys))
        bias[n] = np.abs(g.mean(0) - exact) / np.maximum(se, 1e-12)
    # the PF's log-evidence value itself is close to the exact one at N = 2000
    ll = jax.vmap(_pf_log_evidence, in_axes=(None, None, 0, None))(th, ys, keys, 2000)
    assert abs(float(ll.mean()) - float(_kalman_log_evidence(th, ys)[0])) < 0.1
    assert np.all(bias[2000] < 4.0), (bias, exact)
    assert rmse[2000] < rmse[100] / 2, rmse
    assert rmse[2000] < 0.25 * np.linalg.norm(exact), (rmse, exact)
    none = np.asarray(_grad_batch(th, ys, keys, 2000, "none"))
    none_err = np.sqrt(np.mean(np.sum((none - exact) ** 2, axis=1)))
    assert none_err > 2 * rmse[2000], (none_err, rmse, none.mean(0), exact)


def test_stop_gradient_leaves_the_forward_pass_bit_identical(rng):
    """With and without the stop-gradient correction, the same numbers, bit for bit: a
    Condensation run (with a proposal), an annealing step and their states."""
    ys = jnp.asarray(_simulate(rng))
    th = jnp.asarray(THETA)
    pull = lambda x, z, k: x + 0.1 * (jnp.linalg.solve(jnp.asarray(H), z)[None, :] - x)  # to y

    def outputs(gradient):
        params = dataclasses.replace(_toy_params(th[:2], th[2:], gradient), proposal=pull,
                                     resample_threshold=jnp.asarray(0.7))
        state = pf.init(jax.random.key(0), params, jnp.asarray(M0), jnp.asarray(S0), 300)
        run = pf.run(params, state, ys, jax.random.key(1))
        ann = pf.anneal_step(params, state, ys[0], jax.random.key(2),
                             jnp.asarray([0.1, 0.4, 1.0]))
        return jax.tree.leaves((run, ann))

    for a, b in zip(outputs("stop"), outputs("none"), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_gradient_through_the_filter_under_jit_and_vmap(rng):
    """grad of the log-evidence: jitted equals plain, the vmapped batch equals one key at a
    time, and it is finite."""
    ys = jnp.asarray(_simulate(rng))
    th = jnp.asarray(THETA)
    keys = jax.random.split(jax.random.key(5), 2)
    plain = [jax.grad(_pf_log_evidence)(th, ys, k, 64) for k in keys]
    jitted = jax.jit(jax.grad(_pf_log_evidence), static_argnums=3)
    batch = _grad_batch(th, ys, keys, 64, "stop")
    for i, k in enumerate(keys):
        assert np.all(np.isfinite(np.asarray(plain[i])))
        np.testing.assert_allclose(jitted(th, ys, k, 64), plain[i], rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(batch[i], plain[i], rtol=1e-10, atol=1e-10)
    with pytest.raises(ValueError, match="resampling_gradient"):
        _toy_params(th[:2], th[2:], "soft")
