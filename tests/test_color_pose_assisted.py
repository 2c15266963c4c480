"""Pose-assisted classification (Wang et al. 2011 §5.2 step 3) and patch centroids (step 4).

Oracles: a NumPy/SciPy implementation of the paper's formula (Mahalanobis distances by
``np.linalg.solve``, distance transforms by ``scipy.ndimage.distance_transform_edt``) and
hand-made id maps whose answers are known.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from jaxmocap.color import ColorModel, classify
from jaxmocap.color.pose_assisted import (
    POSE_THRESHOLD,
    patch_centroids,
    patch_distance_maps,
    pose_assisted_classify,
    prior_weight,
)

H, W = 24, 32
MEANS = np.array([[200.0, 40.0, 40.0], [40.0, 190.0, 50.0], [50.0, 60.0, 200.0]])
# patches 1..4: colours 1, 2, 3, 1 (colour 1 is printed twice, as on the shirt)
PATCH_COLOUR = np.array([1, 2, 3, 1])


def _model() -> ColorModel:
    rng = np.random.default_rng(1)
    covs = []
    for _ in range(3):
        A = rng.normal(size=(3, 3)) * 3
        covs.append(A @ A.T + 60 * np.eye(3))
    return ColorModel(mean=jnp.asarray(MEANS), cov=jnp.asarray(np.stack(covs)))


def _prior() -> np.ndarray:
    """Hand-made prior patch map: patch 1 top-left, 2 top-right, 3 bottom, 4 far right."""
    r = np.zeros((H, W), np.int32)
    r[2:9, 2:12] = 1
    r[2:9, 14:22] = 2
    r[14:22, 4:20] = 3
    r[10:20, 26:31] = 4
    return r


def _numpy_reference(model, Wb, img, prior, C, T):
    mu, cov = np.asarray(model.mean), np.asarray(model.cov)
    x = img.reshape(-1, 3).astype(np.float64) @ np.asarray(Wb).T
    m = np.stack(
        [
            np.sqrt(np.sum((x - mu[k]) * np.linalg.solve(cov[k], (x - mu[k]).T).T, -1))
            for k in range(3)
        ],
        -1,
    )
    d = np.stack([ndimage.distance_transform_edt(prior != p) for p in range(1, 5)], -1)
    cost = m[:, PATCH_COLOUR - 1] + C * d.reshape(-1, 4)
    best = cost.argmin(-1)
    keep = cost.min(-1) < T
    patch = np.where(keep, best + 1, 0).reshape(H, W)
    return patch, np.where(patch > 0, PATCH_COLOUR[np.maximum(patch - 1, 0)], 0), cost.min(-1)


def test_matches_numpy_reference(rng):
    model = _model()
    prior = _prior()
    # colours of the prior's patches with noise, plus random clutter in the background
    img = rng.uniform(0, 255, size=(H, W, 3))
    for p in range(1, 5):
        sel = prior == p
        img[sel] = MEANS[PATCH_COLOUR[p - 1] - 1] + rng.normal(0, 12, size=(sel.sum(), 3))
    img = np.clip(img, 0, 255)
    Wb = np.eye(3) + rng.normal(0, 0.02, (3, 3))
    C = float(prior_weight(40.0))
    dist = patch_distance_maps(jnp.asarray(prior), 4)
    out = pose_assisted_classify(
        model, jnp.asarray(Wb), jnp.asarray(img), dist, jnp.asarray(PATCH_COLOUR), C
    )
    ref_patch, ref_colour, ref_score = _numpy_reference(model, Wb, img, prior, C, POSE_THRESHOLD)
    np.testing.assert_allclose(np.asarray(out.score).reshape(-1), ref_score, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(np.asarray(out.patch), ref_patch)
    np.testing.assert_array_equal(np.asarray(out.colour), ref_colour)
    assert (ref_patch > 0).sum() > 200  # the test exercises real assignments
    # jit and vmap (over two "cameras") agree with the plain call
    f = jax.jit(pose_assisted_classify)
    jit_out = f(model, jnp.asarray(Wb), jnp.asarray(img), dist, jnp.asarray(PATCH_COLOUR), C)
    np.testing.assert_array_equal(np.asarray(jit_out.patch), ref_patch)
    imgs = jnp.stack([jnp.asarray(img), jnp.asarray(img[::-1])])
    dists = jnp.stack([dist, dist[:, ::-1]])
    v = jax.vmap(pose_assisted_classify, in_axes=(None, None, 0, 0, None, None))(
        model, jnp.asarray(Wb), imgs, dists, jnp.asarray(PATCH_COLOUR), C
    )
    np.testing.assert_array_equal(np.asarray(v.patch[0]), ref_patch)
    np.testing.assert_array_equal(np.asarray(v.patch[1]), ref_patch[::-1])


def test_prior_removes_far_away_classification():
    """A clutter pixel with exactly a shirt colour, far from that colour in r^b, is rejected."""
    model = _model()
    prior = _prior()
    img = np.full((H, W, 3), 128.0)
    img[prior == 2] = MEANS[1]
    img[0, 31] = MEANS[2]  # colour 3; patch 3 (rows 14..21, cols 4..19) is 18 px away
    Wb = jnp.eye(3)
    base_ids, _ = classify(model, Wb, jnp.asarray(img))
    assert int(base_ids[0, 31]) == 3  # the Gaussian classifier accepts it (distance 0)
    C = 6.0 / 20.0  # s = 20 px: 18 px away costs 5.5 standard deviations > T
    out = pose_assisted_classify(
        model, Wb, jnp.asarray(img), patch_distance_maps(jnp.asarray(prior), 4),
        jnp.asarray(PATCH_COLOUR), C,
    )  # fmt: skip
    assert int(out.patch[0, 31]) == 0
    assert np.all(np.asarray(out.patch)[prior == 2] == 2)  # real patch pixels stay
    # a foreground mask removes them all
    mask = jnp.zeros((H, W), bool)
    masked = pose_assisted_classify(
        model, Wb, jnp.asarray(img), patch_distance_maps(jnp.asarray(prior), 4),
        jnp.asarray(PATCH_COLOUR), C, mask=mask,
    )  # fmt: skip
    assert int(jnp.sum(masked.patch)) == 0


def test_same_colour_pixels_go_to_the_nearer_patch():
    model = _model()
    prior = _prior()
    img = np.full((H, W, 3), 128.0)
    img[:, :] = MEANS[0]  # every pixel has colour 1 (patches 1 and 4)
    out = pose_assisted_classify(
        model, jnp.eye(3), jnp.asarray(img), patch_distance_maps(jnp.asarray(prior), 4),
        jnp.asarray(PATCH_COLOUR), 0.01, threshold=100.0,
    )  # fmt: skip
    patch = np.asarray(out.patch)
    d1 = ndimage.distance_transform_edt(prior != 1)
    d4 = ndimage.distance_transform_edt(prior != 4)
    expect = np.where(d1 <= d4, 1, 4)  # ties go to the lower patch id (first argmin)
    np.testing.assert_array_equal(patch, expect)
    assert set(np.unique(patch)) == {1, 4}
    assert np.all(np.asarray(out.colour) == 1)


@pytest.mark.parametrize("use_window", [False, True])
def test_centroids_match_numpy(rng, use_window):
    ids = rng.integers(0, 6, size=(H, W)).astype(np.int32)  # patch ids 0..5; 5 is > P = 4
    ids[ids == 3] = 0  # patch 3 absent
    ids[0, 0] = 3  # ... but for one pixel: below min_pixels
    window = np.array([100.5, 40.25, 64.0, 48.0])
    out = patch_centroids(jnp.asarray(ids), 4, jnp.asarray(window) if use_window else None)
    for p in range(1, 5):
        rows, cols = np.nonzero(ids == p)
        if use_window:
            xs = window[0] + (cols + 0.5) * window[2] / W
            ys = window[1] + (rows + 0.5) * window[3] / H
        else:
            xs, ys = cols, rows
        assert float(out.count[p - 1]) == len(rows)
        assert bool(out.valid[p - 1]) == (len(rows) >= 4)
        np.testing.assert_allclose(np.asarray(out.xy[p - 1]), [xs.mean(), ys.mean()], rtol=1e-12)


def test_score_gradient_and_scene_colours_match_references(rng):
    """The score is differentiable in W (central finite differences), and with the scene's
    colours (``background``) a pixel nearer a scene colour than every shirt colour is
    background, as the Gaussian classifier decides (:func:`jaxmocap.color.classify`)."""
    model = _model()
    prior = _prior()
    img = np.clip(rng.uniform(0, 255, size=(H, W, 3)), 0, 255)
    for p in range(1, 5):
        sel = prior == p
        img[sel] = MEANS[PATCH_COLOUR[p - 1] - 1] + rng.normal(0, 12, size=(sel.sum(), 3))
    img = jnp.asarray(np.clip(img, 0, 255))
    dist = patch_distance_maps(jnp.asarray(prior), 4)
    pc = jnp.asarray(PATCH_COLOUR)

    def total(Wb):
        return jnp.sum(pose_assisted_classify(model, Wb, img, dist, pc, 0.2).score)

    Wb = jnp.eye(3) + 0.01 * jnp.asarray(rng.normal(size=(3, 3)))
    g = jax.grad(total)(Wb)
    h = 1e-6
    fd = np.array([[(total(Wb.at[i, j].add(h)) - total(Wb.at[i, j].add(-h))) / (2 * h)
                    for j in range(3)] for i in range(3)])  # fmt: skip
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5, atol=1e-4)

    scene = ColorModel(mean=jnp.asarray([[128.0, 128.0, 128.0], MEANS[1] + 5.0]),
                       cov=jnp.asarray(np.stack([100 * np.eye(3)] * 2)))  # fmt: skip
    out = pose_assisted_classify(model, Wb, img, dist, pc, 0.2, threshold=50.0, background=scene)
    plain = pose_assisted_classify(model, Wb, img, dist, pc, 0.2, threshold=50.0)
    ids, _ = classify(model, Wb, img, threshold=1e9, background=scene)
    patch, plain_patch = np.asarray(out.patch), np.asarray(plain.patch)
    np.testing.assert_array_equal(patch, np.where(np.asarray(ids) > 0, plain_patch, 0))
    assert 0 < (patch > 0).sum() < (plain_patch > 0).sum()  # the scene colours removed some
