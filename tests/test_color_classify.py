"""Gaussian colour classification (Wang §5.2 step 1): exact agreement with a per-class NumPy /
SciPy reference, masks, jit/vmap, and the soft form's gradients vs finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.distance import mahalanobis

from jaxmocap.color import (
    ColorModel,
    classified_fraction,
    classify,
    cov_from_log_cholesky,
    log_cholesky,
    soft_classify,
)


def random_model(rng, k=10):
    mean = rng.uniform(30, 220, (k, 3))
    a = rng.normal(size=(k, 3, 3)) * rng.uniform(3, 15, (k, 1, 1))
    cov = a @ np.swapaxes(a, 1, 2) + 4 * np.eye(3)
    return ColorModel(mean=jnp.asarray(mean), cov=jnp.asarray(cov))


def reference(model, W, img, T=3.0, mask=None):
    """Per-class reference: d_k = (W I - mu_k)^T Sigma_k^-1 (W I - mu_k) with np.linalg.inv."""
    x = img.reshape(-1, 3).astype(np.float64) @ np.asarray(W).T
    mean, cov = np.asarray(model.mean), np.asarray(model.cov)
    d2 = np.stack(
        [
            np.einsum("ni,ij,nj->n", x - mean[k], np.linalg.inv(cov[k]), x - mean[k])
            for k in range(len(mean))
        ],
        axis=1,
    )
    best = d2.argmin(1)
    dist = np.sqrt(d2.min(1))
    ids = np.where(dist < T, best + 1, 0)
    if mask is not None:
        ids = np.where(mask.reshape(-1), ids, 0)
    return ids.reshape(img.shape[:2]), dist.reshape(img.shape[:2]), x


@pytest.fixture(scope="module")
def classify_jit():
    return jax.jit(classify)


def test_classify_matches_numpy_and_scipy(rng, classify_jit):
    model = random_model(rng)
    W = np.eye(3) + 0.1 * rng.normal(size=(3, 3))
    # pixels near the colours so that many are classified, plus random ones
    near = np.asarray(model.mean)[rng.integers(0, 10, 3000)] + rng.normal(0, 12, (3000, 3))
    px = np.concatenate([near @ np.linalg.inv(W).T, rng.uniform(0, 255, (1800, 3))])
    img = np.clip(np.round(px), 0, 255).astype(np.uint8).reshape(60, 80, 3)
    mask = rng.random((60, 80)) < 0.8
    for T, m in [(3.0, None), (2.0, mask)]:
        ids, dist = classify_jit(
            model, jnp.asarray(W), jnp.asarray(img), None if m is None else jnp.asarray(m), T
        )
        ref_ids, ref_dist, x = reference(model, W, img, T, m)
        assert int(np.sum(np.asarray(ids) != ref_ids)) == 0
        np.testing.assert_allclose(np.asarray(dist), ref_dist, rtol=1e-9, atol=1e-9)
        assert 0.2 < (ref_ids > 0).mean() < 0.8  # a real mix of colour and background
    # the winner's distance equals SciPy's Mahalanobis distance to the chosen colour
    ids, dist = classify_jit(model, jnp.asarray(W), jnp.asarray(img), None, 3.0)
    inv = np.linalg.inv(np.asarray(model.cov))
    flat_ids, flat_d = np.asarray(ids).reshape(-1), np.asarray(dist).reshape(-1)
    for n in np.flatnonzero(flat_ids)[:50]:
        k = flat_ids[n] - 1
        assert flat_d[n] == pytest.approx(mahalanobis(x[n], model.mean[k], inv[k]), rel=1e-9)
    assert float(classified_fraction(ids)) == pytest.approx((flat_ids > 0).mean())
    frac_masked = float(classified_fraction(ids * mask, jnp.asarray(mask)))
    assert frac_masked == pytest.approx(((flat_ids > 0) & mask.reshape(-1)).sum() / mask.sum())


def test_classify_float32_and_vmap(rng, classify_jit):
    model = random_model(rng, k=4)
    imgs = rng.integers(0, 256, (2, 20, 24, 3)).astype(np.uint8)
    W = jnp.eye(3)
    batched = jax.vmap(classify_jit, in_axes=(None, None, 0))(model, W, jnp.asarray(imgs))
    for b in range(2):
        one = classify_jit(model, W, jnp.asarray(imgs[b]))
        np.testing.assert_array_equal(batched[0][b], one[0])
    m32 = jax.tree.map(lambda a: a.astype(jnp.float32), model)
    ids32, d32 = classify_jit(m32, W.astype(jnp.float32), jnp.asarray(imgs[0]))
    assert d32.dtype == jnp.float32 and ids32.dtype == jnp.int32
    ref_ids, ref_dist, _ = reference(model, np.eye(3), imgs[0])
    np.testing.assert_allclose(np.asarray(d32), ref_dist, rtol=1e-3, atol=1e-3)
    near_threshold = np.abs(ref_dist - 3.0) < 1e-3
    assert np.all((np.asarray(ids32) == ref_ids) | near_threshold)


def test_log_cholesky_round_trip(rng):
    cov = np.asarray(random_model(rng, 3).cov)
    np.testing.assert_allclose(
        cov_from_log_cholesky(log_cholesky(jnp.asarray(cov))), cov, rtol=1e-12
    )


def test_soft_classify_limit_and_grad(rng):
    model = random_model(rng, k=3)
    img = np.asarray(model.mean)[rng.integers(0, 3, 30)] + rng.normal(0, 10, (30, 3))
    img = jnp.asarray(img.reshape(5, 6, 3))
    W = jnp.eye(3) + 0.05 * jnp.asarray(rng.normal(size=(3, 3)))
    # zero temperature limit: argmax equals the hard classifier
    resp = soft_classify(model, W, img, 3.0, 1e-3)
    ids, _ = classify(model, W, img)
    np.testing.assert_array_equal(np.asarray(resp.argmax(-1)), np.asarray(ids))
    np.testing.assert_allclose(np.asarray(resp.sum(-1)), 1.0, rtol=1e-12)

    target = jax.nn.one_hot(ids, 4)  # a fixed labelling to fit

    def loss(p):
        m = ColorModel(mean=p["mean"], cov=cov_from_log_cholesky(p["chol"]))
        r = soft_classify(m, p["W"], img, p["T"], 2.0)
        return jnp.sum(target * jnp.log(r + 1e-12))

    p = {"mean": model.mean, "chol": log_cholesky(model.cov), "W": W, "T": jnp.asarray(3.0)}
    loss = jax.jit(loss)
    g = jax.jit(jax.grad(loss))(p)
    flat, unravel = jax.flatten_util.ravel_pytree(p)
    gflat = jax.flatten_util.ravel_pytree(g)[0]
    eps = 1e-6
    for i in rng.choice(flat.size, 12, replace=False).tolist() + [flat.size - 1]:
        e = jnp.zeros_like(flat).at[i].set(eps)
        fd = (loss(unravel(flat + e)) - loss(unravel(flat - e))) / (2 * eps)
        assert float(gflat[i]) == pytest.approx(float(fd), rel=1e-5, abs=1e-6)
    assert float(jnp.abs(g["T"])) > 0
