"""The offline RTS smoother (jaxmocap.kalman): against the closed-form minimiser of the same
quadratic energy (one sparse linear system, numpy.linalg.solve) with missing and down-weighted
frames, its posterior variances against the inverse Hessian, its Jacobian (grad) against the
oracle's linear map, vmap against single calls; its frequency response against the Wiener
filter's closed form; a noisy sequence brought closer to the truth; poses with a root turning
through 180 degrees (rotation-vector unwrapping)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap.kalman import (
    PRIOR_VARIANCE,
    process_ratio,
    rts_smooth,
    smooth_poses,
    unwrap_rotvec,
    wrap_rotvec,
)
from jaxmocap.rotations import rodrigues

F = np.array([[1.0, 1.0], [0.0, 1.0]])
QN = np.array([[1 / 3, 1 / 2], [1 / 2, 1.0]])


def batch_oracle(y, w, lam):
    """argmin over x_0..x_{T-1} ([p, u]) of (x_0 - m0)^T P0^-1 (x_0 - m0)
    + sum_t w_t (y_t - p_t)^2 + sum_t (x_{t+1} - F x_t)^T (lam QN)^-1 (x_{t+1} - F x_t),
    solved as one linear system; returns (p, Var p) (the inverse Hessian's diagonal)."""
    T = len(y)
    ok = np.isfinite(y) & (w > 0)
    w = np.where(ok, w, 0.0)
    y = np.where(ok, y, 0.0)
    m0 = np.array([y[np.argmax(ok)], 0.0])
    H = np.zeros((2 * T, 2 * T))
    b = np.zeros(2 * T)
    H[:2, :2] += np.eye(2) / PRIOR_VARIANCE
    b[:2] += m0 / PRIOR_VARIANCE
    for t in range(T):
        H[2 * t, 2 * t] += w[t]
        b[2 * t] += w[t] * y[t]
    Qi = np.linalg.inv(lam * QN)
    D = np.hstack([-F, np.eye(2)])  # x_{t+1} - F x_t = D [x_t; x_{t+1}]
    for t in range(T - 1):
        H[2 * t:2 * t + 4, 2 * t:2 * t + 4] += D.T @ Qi @ D
    x = np.linalg.solve(H, b)
    return x[0::2], np.diag(np.linalg.inv(H))[0::2]


def test_matches_the_batch_least_squares_oracle():
    rng = np.random.default_rng(1)
    T, D = 40, 3
    y = np.cumsum(rng.normal(0, 0.2, (T, D)), axis=0)
    w = rng.uniform(0.2, 3.0, (T, D))
    w[5:9, 0] = 0.0  # missing observations
    y[20, 1] = np.nan  # no estimate: missing whatever its weight
    w[0:3, 2] = 0.0  # the first observation of a DOF later than frame 0
    lam = np.array([0.05, 1.0, 8.0])
    got = rts_smooth(jnp.asarray(y), jnp.asarray(w), jnp.asarray(lam))
    for d in range(D):
        mean, var = batch_oracle(y[:, d], w[:, d], lam[d])
        np.testing.assert_allclose(np.asarray(got.mean[:, d]), mean, rtol=1e-8, atol=1e-9)
        np.testing.assert_allclose(np.asarray(got.var[:, d]), var, rtol=1e-7, atol=1e-9)
    # per-frame weights (T,) broadcast over the DOFs
    one = rts_smooth(jnp.asarray(y[:, :1]), jnp.asarray(w[:, 0]), 0.3)
    np.testing.assert_allclose(np.asarray(one.mean[:, 0]), batch_oracle(y[:, 0], w[:, 0], 0.3)[0],
                               rtol=1e-8, atol=1e-9)


def test_grad_and_vmap():
    """The smoothed mean is linear in y: its Jacobian (reverse mode) is the oracle's map,
    column by column; vmap over sequences equals one call each."""
    rng = np.random.default_rng(2)
    T = 25
    y = rng.normal(0, 1, T)
    w = np.ones(T)
    w[7] = 0.0
    w[12] = 0.25
    lam = 0.4
    J = jax.jacrev(lambda v: rts_smooth(v[:, None], jnp.asarray(w), lam).mean[:, 0])(
        jnp.asarray(y))
    ref = np.stack([batch_oracle(e, w, lam)[0] for e in np.eye(T)], axis=1)
    np.testing.assert_allclose(np.asarray(J), ref, rtol=1e-7, atol=1e-9)
    assert np.allclose(np.asarray(J)[:, 7], 0.0)  # a missing frame has no influence
    g = jax.grad(lambda v: jnp.sum(rts_smooth(v[:, None], jnp.asarray(w), lam).mean ** 2))(
        jnp.asarray(y))
    np.testing.assert_allclose(np.asarray(g), 2 * ref.T @ (ref @ y), rtol=1e-7, atol=1e-9)
    batch = rng.normal(0, 1, (4, T, 2))
    many = jax.vmap(lambda v: rts_smooth(v, jnp.asarray(w), lam).mean)(jnp.asarray(batch))
    for i in range(4):
        np.testing.assert_allclose(np.asarray(many[i]),
                                   np.asarray(rts_smooth(jnp.asarray(batch[i]), jnp.asarray(w),
                                                         lam).mean), rtol=1e-12, atol=1e-12)


def test_frequency_response_is_the_wiener_filters():
    """Away from the ends a sinusoid of frequency f comes out scaled by about
    1 / (1 + (f / f_c)^4) (the non-causal Wiener filter of the constant-velocity model; exact
    in continuous time, the sampled model close to it at f << fps), with no phase lag."""
    fps, fc = 30.0, 4.0
    t = np.arange(900) / fps
    for f in (1.0, 4.0, 6.0):
        x = np.sin(2 * np.pi * f * t)
        out = np.asarray(rts_smooth(jnp.asarray(x[:, None]), jnp.ones(len(t)),
                                    process_ratio(fc, fps)).mean[:, 0])
        mid = slice(300, 600)
        # least-squares fit of out = a sin + b cos over the middle
        A = np.stack([np.sin(2 * np.pi * f * t[mid]), np.cos(2 * np.pi * f * t[mid])], 1)
        a, b = np.linalg.lstsq(A, out[mid], rcond=None)[0]
        assert a == pytest.approx(1 / (1 + (f / fc) ** 4), abs=0.03), (f, a)
        assert abs(b) < 1e-6  # zero phase


def test_noisy_sequence_comes_closer_to_the_truth():
    """Smooth joint-angle-like motion (under 2 Hz) observed with 3-degree noise at 30 fps,
    a tenth of the frames rejected as outliers 0.5 rad off: the smoother, which treats them as
    missing, is at least twice as close to the truth as the valid raw estimates, and bridges
    the rejected frames closer than a valid raw estimate."""
    rng = np.random.default_rng(3)
    fps, T, D = 30.0, 240, 6
    t = np.arange(T) / fps
    freqs = rng.uniform(0.2, 1.8, (3, D))
    truth = sum(0.3 * np.sin(2 * np.pi * freqs[k] * t[:, None] + k) for k in range(3))
    y = truth + rng.normal(0, np.deg2rad(3), truth.shape)
    bad = rng.random(T) < 0.1
    y[bad] += 0.5
    out = np.asarray(rts_smooth(jnp.asarray(y), jnp.asarray(~bad, float),
                                process_ratio(4.0, fps)).mean)
    rms = lambda e: np.sqrt(np.mean(e ** 2))  # noqa: E731
    raw = rms((y - truth)[~bad])
    assert rms(out - truth) < 0.5 * raw, (rms(out - truth), raw)
    # the rejected frames, bridged by the model, are closer than a valid raw estimate
    assert rms((out - truth)[bad]) < 0.75 * raw


def test_rotation_vector_unwrap_and_wrap():
    r = np.array([[0, 0, np.pi - 0.05], [0, 0, -(np.pi - 0.05)], [0, 0, -(np.pi - 0.15)]])
    u = unwrap_rotvec(r)
    np.testing.assert_allclose(u[:, 2], [np.pi - 0.05, np.pi + 0.05, np.pi + 0.15], atol=1e-12)
    for a, b in zip(u, r, strict=True):  # the same rotations
        np.testing.assert_allclose(rodrigues(a), rodrigues(b), atol=1e-12)
    np.testing.assert_allclose(wrap_rotvec(u), r, atol=1e-12)


def test_smooth_poses_root_turning_through_180_degrees():
    """A root yawing steadily through 180 degrees (its rotation vector flips sign there) with
    noisy estimates: the smoothed rotations follow the truth; frames outside the span of
    valid frames keep their own estimate; an impossible cut-off is refused."""
    rng = np.random.default_rng(4)
    fps, T = 30.0, 60
    yaw = np.linspace(np.pi - 1.0, np.pi + 1.0, T)
    q = np.zeros((T, 8))
    truth_R = [rodrigues(np.array([0.0, 0.0, a])) for a in yaw]
    noisy = yaw + rng.normal(0, 0.03, T)
    q[:, 3:6] = wrap_rotvec(np.stack([np.zeros(T), np.zeros(T), noisy], 1))
    q[:, 6:] = 0.2 * np.sin(np.arange(T) / 5.0)[:, None] + rng.normal(0, 0.03, (T, 2))
    valid = np.ones(T, bool)
    valid[[0, 1, 30, 31, T - 1]] = False
    q[40] = np.nan  # no estimate: stays without one
    out = smooth_poses(q, valid, fps, 3.0)
    np.testing.assert_array_equal(out[[0, 1, T - 1]], q[[0, 1, T - 1]])  # outside the span
    assert np.isnan(out[40]).all() and np.isfinite(np.delete(out, 40, axis=0)).all()
    assert np.nanmax(np.linalg.norm(out[:, 3:6], axis=1)) <= np.pi + 1e-9
    frames = [t for t in range(2, T - 1) if t != 40]
    err = [np.linalg.norm(rodrigues(out[t, 3:6]) - truth_R[t]) for t in frames]
    raw = [np.linalg.norm(rodrigues(q[t, 3:6]) - truth_R[t]) for t in frames]
    assert max(err) < 0.06 and np.mean(err) < 0.6 * np.mean(raw)
    assert np.array_equal(smooth_poses(q, np.eye(T)[0], fps), q, equal_nan=True)  # as is
    with pytest.raises(ValueError, match="cutoff_hz"):
        smooth_poses(q, valid, fps, 15.0)
