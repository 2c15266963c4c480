"""The shared appearance layer (jaxmocap.appearance, issue 37) against closed-form cases."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import appearance as ap

MEANS = np.array([[180.0, 60.0, 50.0], [60.0, 160.0, 70.0], [70.0, 80.0, 170.0],
                  [170.0, 160.0, 60.0]])


def _covs(n, sd=6.0):
    return np.tile(np.eye(3) * sd**2, (n, 1, 1))


def _image(rng, means, covs, side=24):
    """One ``side`` x ``side`` block per part, pixels drawn from its Gaussian; part map."""
    blocks, ids = [], []
    for i, (m, c) in enumerate(zip(means, covs, strict=True)):
        x = rng.multivariate_normal(m, c, size=(side, side))
        blocks.append(x)
        ids.append(np.full((side, side), i + 1))
    return jnp.asarray(np.concatenate(blocks, 1)), jnp.asarray(np.concatenate(ids, 1))


def test_known_light_change_is_recovered_and_relights_unseen_parts():
    """Parts 0, 1 lit by lamp 0, parts 2, 3 by lamp 1; lamp 0 turns warmer and dimmer by a
    known gain. Seeing one part of each lamp recovers the gain on the seen part and relights
    the unseen part of the same lamp by it; the other lamp's unseen part stays."""
    rng = np.random.default_rng(0)
    state = ap.init_parts(jnp.asarray(MEANS), jnp.asarray(_covs(4)),
                          mix=jnp.asarray([0.98, 0.98, 0.02, 0.02]))
    g0 = np.array([0.9, 0.6, 0.4])
    true = MEANS * np.array([g0, g0, [1, 1, 1], [1, 1, 1]])
    img, ids = _image(rng, true, _covs(4, 2.0))
    ids = jnp.where((ids == 1) | (ids == 3), ids, 0)  # parts 1 and 3 (0-based 0, 2) seen
    stats = ap.part_statistics(state, img, ids, gate=1e9)
    new, used, fit = ap.update_parts(state, stats, jnp.array(True), rate=1.0)
    assert bool(fit.ok)
    np.testing.assert_array_equal(np.asarray(used), [True, False, True, False])
    np.testing.assert_allclose(np.asarray(new.mean[0]), true[0], rtol=0.02)
    # the unseen part of lamp 0 follows lamp 0's change (brightness unknown: chroma checked)
    got = np.asarray(new.mean[1]) / MEANS[1]
    np.testing.assert_allclose(got / got.sum(), g0 / g0.sum(), atol=0.03)
    np.testing.assert_allclose(np.asarray(new.mean[3]), MEANS[3], rtol=0.05)


def test_static_scene_does_not_drift_over_300_frames():
    rng = np.random.default_rng(1)
    covs = _covs(4)
    state = ap.init_parts(jnp.asarray(MEANS), jnp.asarray(covs))
    step = jax.jit(lambda s, img, ids: ap.update_parts(
        s, ap.part_statistics(s, img, ids), jnp.array(True))[0])
    for _ in range(300):
        img, ids = _image(rng, MEANS, covs, side=12)
        state = step(state, img, ids)
    np.testing.assert_allclose(np.asarray(state.mean), MEANS, atol=2.0)
    # spreads stay within the bounds of the calibration (condition number bounded)
    w = np.linalg.eigvalsh(np.asarray(state.cov)) / 36.0
    assert w.min() >= ap.MIN_SPREAD**2 - 1e-3 and w.max() <= ap.MAX_SPREAD**2 + 1e-3


def test_invalid_frames_leave_the_state_untouched():
    rng = np.random.default_rng(2)
    state = ap.init_parts(jnp.asarray(MEANS), jnp.asarray(_covs(4)))
    img, ids = _image(rng, MEANS * 0.5, _covs(4))
    stats = ap.part_statistics(state, img, ids, gate=1e9)
    new, used, fit = ap.update_parts(state, stats, jnp.array(False))
    for a, b in ((new.mean, state.mean), (new.cov, state.cov), (new.mix, state.mix)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.asarray(used).any() and not bool(fit.ok)
    assert int(new.lost) == 1


def test_long_loss_relaxes_toward_the_calibration():
    state = ap.init_parts(jnp.asarray(MEANS), jnp.asarray(_covs(4)))
    state = ap.relit(state, ap.Relight(jnp.full((4, 3), 0.5), state.mix, jnp.array(True),
                                       jnp.zeros(()), jnp.ones((2, 3))))
    stats = ap.PartStats(jnp.zeros(4), jnp.zeros((4, 3)), jnp.zeros((4, 3)), jnp.zeros((4, 3, 3)))
    d0 = np.abs(np.asarray(state.mean) - MEANS).max()
    for _ in range(ap.LOST_FRAMES + 20):
        state, _, _ = ap.update_parts(state, stats, jnp.array(False))
    assert np.abs(np.asarray(state.mean) - MEANS).max() < 0.2 * d0


def test_unphysical_relight_is_rejected_and_not_applied():
    """A frame whose colours no positive, bounded illuminant change explains (one part's
    blue up 30x while another's drops) is rejected: the state is not relit."""
    rng = np.random.default_rng(3)
    state = ap.init_parts(jnp.asarray(MEANS), jnp.asarray(_covs(4)))
    wild = MEANS * np.array([[1, 1, 30.0], [1, 1, 0.02], [30.0, 0.03, 1], [1, 1, 1]])
    img, ids = _image(rng, np.clip(wild, 1, 2000), _covs(4, 1.0))
    stats = ap.part_statistics(state, img, ids, gate=1e9)
    fit = ap.fit_relight(state, stats)
    assert not bool(fit.ok)
    new = ap.relit(state, fit)
    np.testing.assert_array_equal(np.asarray(new.mean), np.asarray(state.mean))


def test_jit_vmap_grad_through_the_relight_fit():
    rng = np.random.default_rng(4)
    state = ap.init_parts(jnp.asarray(MEANS), jnp.asarray(_covs(4)))
    img, ids = _image(rng, MEANS * np.array([1.2, 1.0, 0.8]), _covs(4, 2.0))
    stats = ap.part_statistics(state, img, ids, gate=1e9)

    def gain0(obs):
        return ap.fit_relight(state, stats._replace(raw_mean=obs)).gains[0, 2]

    g = jax.jit(jax.grad(gain0))(stats.raw_mean)
    eps = 0.5
    e = jnp.zeros_like(stats.raw_mean).at[0, 2].set(eps)
    fd = (gain0(stats.raw_mean + e) - gain0(stats.raw_mean - e)) / (2 * eps)
    np.testing.assert_allclose(float(g[0, 2]), float(fd), rtol=0.05, atol=1e-5)
    # two cameras' states under vmap equal the one-by-one results
    states = jax.tree.map(lambda x: jnp.stack([x, x]), state)
    statss = jax.tree.map(lambda x: jnp.stack([x, x * 1.0]), stats)
    out = jax.vmap(lambda s, t: ap.update_parts(s, t, jnp.array(True))[0])(states, statss)
    one = ap.update_parts(state, stats, jnp.array(True))[0]
    np.testing.assert_allclose(np.asarray(out.mean[1]), np.asarray(one.mean), rtol=1e-5)


@pytest.mark.parametrize("shading", [None, (0.5, 4.0)])
def test_trimmed_statistics_drop_pixels_outside_the_gate(shading):
    rng = np.random.default_rng(5)
    state = ap.init_parts(jnp.asarray(MEANS), jnp.asarray(_covs(4)))
    img, ids = _image(rng, MEANS, _covs(4, 3.0))
    img = img.at[:4, :4].set(jnp.asarray([0.0, 255.0, 255.0]))  # 16 cyan outliers in part 1
    st = ap.part_statistics(state, img, ids, shading=shading)
    assert float(st.count[0]) == 24 * 24 - 16
    np.testing.assert_allclose(np.asarray(st.mean[0]), MEANS[0], atol=1.5)
