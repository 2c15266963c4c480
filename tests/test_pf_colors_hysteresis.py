"""Tests for the hysteresis skin map of the stereo particle filter
(``jaxmocap.pf.colors.hysteresis_masks`` / ``grow_into``,
``make_params(images=Images(skin_grow=...))``).

Scene (OpenCV drawing, the oracle): the scene of ``test_pf_colors`` plus a "hand" disc hanging
from the torso whose lower half is shaded (the skin colour darkened: outside the capture's skin
class, inside the relaxed one) and a patch of the same shaded colour on the wall, not touching
any skin."""

import cv2
import numpy as np
import pytest
from scipy import ndimage
from test_pf_colors import SKIN_RGB, H, W, scene, scribbles

from jaxmocap.errors import InputError
from jaxmocap.pf import colors as PC
from jaxmocap.trackers import stereo_pf as sp
from jaxmocap.trackers.stereo_pf import observation as sp_observation

HAND = (40, 100, 7)  # u, v, r: at the torso's lower left corner
SHADE = 0.66  # the shaded half's brightness factor
PATCH = (108, 60, 116, 68)  # x0, y0, x1, y1: a wall patch of the shaded skin colour


def shaded_scene(rng):
    img = scene(rng).astype(np.float64)
    shaded = tuple(SHADE * c for c in SKIN_RGB)
    u, v, r = HAND
    cv2.circle(img, (u, v), r, SKIN_RGB, -1)
    yy, xx = np.mgrid[:H, :W]
    lower = ((xx - u) ** 2 + (yy - v) ** 2 <= r * r) & (yy > v)
    img[lower] = shaded
    x0, y0, x1, y1 = PATCH
    cv2.rectangle(img, (x0, y0), (x1, y1), shaded, -1)
    img += rng.normal(0, 2.0, img.shape)
    hand = (xx - u) ** 2 + (yy - v) ** 2 <= r * r
    patch = (xx >= x0) & (xx <= x1) & (yy >= y0) & (yy <= y1)
    return np.clip(img, 0, 255).astype(np.uint8), hand, lower, patch


@pytest.fixture
def colors(rng):
    skin, shirt = scribbles()
    return PC.fit_capture_colors([scene(rng)], [skin], [shirt])


def test_grow_into_is_scipy_geodesic_dilation(rng):
    seed = rng.random((40, 50)) > 0.995
    region = rng.random((40, 50)) > 0.4
    for steps in (0, 1, 3, 10):
        expect = ndimage.binary_dilation(seed, np.ones((3, 3), bool), iterations=steps,
                                         mask=region | seed) if steps else seed
        np.testing.assert_array_equal(PC.grow_into(seed, region, steps), expect | seed)


def test_hysteresis_takes_the_shaded_half_of_a_hand_not_a_wall_patch(rng, colors):
    img, hand, lower, patch = shaded_scene(rng)
    d = colors.skin.mahalanobis_sq(PC.features(img))
    # preconditions: the shaded half is outside the skin class, inside the relaxed one
    assert np.median(d[lower]) > colors.skin_threshold
    assert np.median(d[lower]) < PC.GROW_SKIN_SCALE * colors.skin_threshold
    strict, _ = PC.masks(colors, img)
    grown, shirt, relaxed = PC.hysteresis_masks(colors, img, grow=8)
    assert strict[lower].mean() < 0.3  # the skin class keeps the lit half only
    assert grown[lower].mean() > strict[lower].mean() + 0.3  # hysteresis: most of the rest
    assert grown[hand].mean() > 0.7
    assert relaxed[patch].mean() > 0.25  # the patch has the relaxed colour ...
    assert not grown[patch].any()  # ... but touches no skin: not grown into
    np.testing.assert_array_equal(PC.hysteresis_masks(colors, img, grow=0)[0], strict)
    np.testing.assert_array_equal(shirt, PC.masks(colors, img)[1])
    assert not (grown & ~relaxed).any() and not (strict & ~grown).any()
    with pytest.raises(InputError, match="grow"):
        PC.hysteresis_masks(colors, img, grow=-1)


def test_make_params_skin_grow_feeds_the_blob_line(rng, colors):
    from test_blobs import stereo_cams

    cams = stereo_cams()
    img = np.zeros((240, 320, 3), np.uint8)
    img[:H, :W] = shaded_scene(rng)[0]
    params = sp.make_params(
        cams, images=sp.Images(colors=colors, skin_grow=8), motion=sp.Motion(n_particles=10)
    )
    seg = sp_observation._segment(params, img)
    np.testing.assert_array_equal(seg.skin, PC.hysteresis_masks(colors, img, 8)[0])
    with pytest.raises(InputError, match="skin_grow"):
        sp.make_params(
            cams, images=sp.Images(skin_grow=4), motion=sp.Motion(n_particles=10)
        )  # no colour model
