"""Colour under spot lamps (issue 17): the shading-invariant distance against SciPy's bounded
minimisation, its fit on shaded scribbles, the scene's colour Gaussians as background, and the
scribble frames a user picks when a colour is hidden at the start."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import minimize_scalar

from jaxmocap.color import (
    ColorModel,
    classify,
    fit_color_model,
    fit_scene_colors,
    mahalanobis_sq,
    nearest_sq,
)
from jaxmocap.color.pose_assisted import pose_assisted_classify

GAIN = (0.5, 4.0)


def _model(rng, k=5):
    mean = rng.uniform(40, 220, (k, 3))
    a = rng.normal(size=(k, 3, 3)) * rng.uniform(2, 8, (k, 1, 1))
    return ColorModel(mean=jnp.asarray(mean), cov=jnp.asarray(a @ np.swapaxes(a, 1, 2) +
                                                              4 * np.eye(3)))


def test_gain_distance_matches_scipy_bounded_minimum(rng):
    model = _model(rng)
    W = np.eye(3) + 0.05 * rng.normal(size=(3, 3))
    img = rng.uniform(0, 255, (6, 7, 3))
    got = np.asarray(jax.jit(lambda im: mahalanobis_sq(model, jnp.asarray(W), im, GAIN))(
        jnp.asarray(img)))
    inv = np.linalg.inv(np.asarray(model.cov))
    for n, x in enumerate(img.reshape(-1, 3)[:20]):
        for k in range(model.n_colors):
            d = np.asarray(model.mean[k])

            def f(a, x=x, d=d, k=k):
                r = a * (W @ x) - d
                return r @ inv[k] @ r

            ref = minimize_scalar(f, bounds=GAIN, method="bounded",
                                  options={"xatol": 1e-10}).fun
            assert got.reshape(-1, model.n_colors)[n, k] == pytest.approx(ref, rel=1e-6, abs=1e-6)
    # never above the paper's distance (a = 1 is inside the range)
    plain = np.asarray(mahalanobis_sq(model, jnp.asarray(W), jnp.asarray(img)))
    assert np.all(got <= plain + 1e-6)


def _shaded(rng, mean, n, sd=3.0):
    """Pixels of one colour under shading: a (mean + noise), a in [0.3, 1.3], clipped."""
    a = rng.uniform(0.3, 1.3, (n, 1))
    return np.clip(a * (mean + rng.normal(0, sd, (n, 3))), 0, 255)


def test_shading_invariant_fit_and_classification(rng):
    """Shaded scribbles: the gain fit keeps the chromatic spread only (covariance ~ the noise,
    not the shading), and held-out shaded pixels are classified right with it where the
    paper's Gaussians of the same scribbles confuse the colours or miss them."""
    means = np.array([[200.0, 40, 40], [200, 120, 30], [60, 160, 60], [50, 70, 200],
                      [200, 150, 170]])
    train = [_shaded(rng, m, 800) for m in means]
    img = np.concatenate(train)[None]
    lab = np.repeat(np.arange(1, 6), 800)[None]
    plain = fit_color_model([img], [lab], 5)
    gain = fit_color_model([img], [lab], 5, gain=GAIN)
    for k in range(5):  # noise sd 3 x shading up to 1.3: chromatic variances ~ 9..25 + floor
        ev = np.linalg.eigvalsh(np.asarray(gain.cov[k]))
        assert ev.max() < 0.1 * np.linalg.eigvalsh(np.asarray(plain.cov[k])).max() or \
            ev.max() < 60, (k, ev)
    test = np.concatenate([_shaded(rng, m, 400) for m in means])[None]
    truth = np.repeat(np.arange(1, 6), 400)
    ids_g = np.asarray(classify(gain, jnp.eye(3), jnp.asarray(test), gain=GAIN)[0]).ravel()
    ids_p = np.asarray(classify(plain, jnp.eye(3), jnp.asarray(test))[0]).ravel()
    assert np.mean(ids_g == truth) > 0.95
    assert 1 - np.mean(ids_g == truth) < 0.3 * (1 - np.mean(ids_p == truth))  # 0.3% vs 3.4%
    # black and near-grey pixels stay background (brightness is bounded, chroma is kept)
    dark = np.array([[[3.0, 3, 3], [128, 128, 128], [250, 250, 250]]])
    assert np.all(np.asarray(classify(gain, jnp.eye(3), jnp.asarray(dark), gain=GAIN)[0]) == 0)


def test_scene_colors_reject_the_room_and_keep_the_shirt(rng):
    """A pale pink colour whose Gaussian covers a grey wall: with the wall's Gaussians
    (fitted from the room's pixels, white-balanced) wall pixels become background, shirt
    pixels keep their ids; the rule is 'nearer a scene Gaussian than every colour', checked
    against nearest_sq; pose-assisted classification applies it too."""
    pink = np.array([170.0, 140, 150])
    model = ColorModel(mean=jnp.asarray([pink, [200.0, 40, 40]]),
                       cov=jnp.asarray([np.eye(3) * 400.0, np.eye(3) * 100.0]))
    wall = np.clip(rng.normal([130, 130, 135], 4, (3000, 3)), 0, 255)
    W = np.diag([1.1, 1.0, 0.9])
    room = (wall @ np.linalg.inv(W).T)[None]  # what the camera sees before white balance
    scene = fit_scene_colors([room], [np.ones(room.shape[:2], bool)], [W], n_clusters=4)
    assert scene.n_colors == 4
    shirt_px = np.concatenate([np.clip(rng.normal(pink, 6, (500, 3)), 0, 255),
                               np.clip(rng.normal([200, 40, 40], 6, (500, 3)), 0, 255)])
    test_wall = np.clip(rng.normal([130, 130, 135], 4, (500, 3)), 0, 255)
    img = jnp.asarray((np.concatenate([shirt_px, test_wall]) @ np.linalg.inv(W).T)[None])
    Wj = jnp.asarray(W)
    ids0 = np.asarray(classify(model, Wj, img)[0]).ravel()
    ids1 = np.asarray(classify(model, Wj, img, background=scene)[0]).ravel()
    assert np.mean(ids0[1000:] > 0) > 0.9  # without: the wall is "pink"
    assert np.mean(ids1[1000:] > 0) < 0.1  # 7% measured: tails of the clusters
    assert np.mean(ids1[:1000] == np.repeat([1, 2], 500)) > 0.95
    d_best = np.asarray(jnp.min(mahalanobis_sq(model, Wj, img), -1)).ravel()
    d_scene = np.asarray(nearest_sq(scene, Wj, img)).ravel()
    np.testing.assert_array_equal(ids1 > 0, (ids0 > 0) & (d_best < d_scene))
    dist = jnp.zeros((2, 1, img.shape[1]))
    pa = pose_assisted_classify(model, Wj, img, dist, jnp.asarray([1, 2]), 0.0, None, 5.0,
                                None, scene)
    np.testing.assert_array_equal(np.asarray(pa.colour).ravel() > 0, ids1 > 0)  # same rule


def test_scribble_frames_take_a_hidden_colour_from_a_later_frame():
    from jaxmocap.experiment.cell import scribble_frames

    ids = np.zeros((8, 2, 30, 40), np.uint8)
    ids[:, :, 2:14, 2:14] = 1
    ids[:, 1, 16:28, 2:14] = 2
    ids[5, 0, 10:25, 20:36] = 3  # colour 3 only in frame 5, camera 0
    assert scribble_frames(ids, 3, 3) == [0, 1, 2, 5]
    assert scribble_frames(ids[:5], 3, 3) == [0, 1, 2]  # never shown: the fit will say so
    ids[1, 1, 20:28, 20:30] = 3
    assert scribble_frames(ids, 3, 3) == [0, 1, 2]
