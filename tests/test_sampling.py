"""Image sampling and crops (jaxmocap.sampling) against OpenCV: bilinear (zero outside: the
stereo filter's edge maps; edge-clamped: the shirt's colour crops), nearest, the crop window,
the id-map erosion; jit, vmap and grad."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from jaxmocap import sampling


def test_sample_bilinear_clamped_matches_cv2_remap(rng):
    img = rng.integers(0, 256, size=(30, 40, 3), dtype=np.uint8)
    uv = rng.uniform([1, 1], [38, 28], size=(7, 9, 2))
    ours = np.asarray(sampling.sample_bilinear_clamped(jnp.asarray(img), jnp.asarray(uv)))
    ref = cv2.remap(
        img.astype(np.float32),
        uv[..., 0].astype(np.float32),
        uv[..., 1].astype(np.float32),
        cv2.INTER_LINEAR,
    )
    np.testing.assert_allclose(ours, ref, atol=2e-2)  # cv2 uses 5-bit fixed-point weights


def test_crop_windows_map_back_to_image():
    """A window in working pixels maps to the image positions its pixels sample."""
    crop = jnp.asarray([10.0, 20.0, 64.0, 64.0])
    n = 32
    uv = np.asarray(sampling.crop_uv(crop, n))
    win_c = jnp.asarray([3.5, 5.5, 8.0, 8.0])  # covers working pixels 4..11 x 6..13
    win = np.asarray(sampling.crop_to_image(win_c, crop, n))
    k = 64.0 / n
    np.testing.assert_allclose(win[:2], uv[6, 4] - k / 2)  # left/top edge of pixel (6, 4)
    np.testing.assert_allclose(win[2:], [8 * k, 8 * k])


def test_sample_bilinear_vs_opencv_remap(rng):
    img = rng.random((30, 40)).astype(np.float32)
    uv = rng.uniform(-3, 43, size=(500, 2))
    uv[:, 1] = rng.uniform(-3, 33, size=500)
    ours = np.asarray(sampling.sample_bilinear(jnp.asarray(img, jnp.float64), jnp.asarray(uv)))
    ref = cv2.remap(
        img.astype(np.float64),
        uv[:, 0].astype(np.float32)[None],
        uv[:, 1].astype(np.float32)[None],
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=0,
    )[0]
    # OpenCV quantises the sub-pixel fraction to 1/32
    np.testing.assert_allclose(ours, ref, atol=1.5 / 32)
    inner = (uv[:, 0] > 0) & (uv[:, 0] < 39) & (uv[:, 1] > 0) & (uv[:, 1] < 29)
    x0, y0 = np.floor(uv[inner, 0]).astype(int), np.floor(uv[inner, 1]).astype(int)
    fx, fy = uv[inner, 0] - x0, uv[inner, 1] - y0
    exact = (
        img[y0, x0] * (1 - fx) * (1 - fy)
        + img[y0, x0 + 1] * fx * (1 - fy)
        + img[y0 + 1, x0] * (1 - fx) * fy
        + img[y0 + 1, x0 + 1] * fx * fy
    )
    np.testing.assert_allclose(ours[inner], exact, rtol=1e-6)


def test_sample_nearest_and_outside(rng):
    img = rng.integers(0, 5, size=(12, 17)).astype(np.int32)
    uv = rng.uniform([-3, -3], [20, 15], size=(300, 2))
    ours = np.asarray(sampling.sample_nearest(jnp.asarray(img), jnp.asarray(uv)))
    xi, yi = np.round(uv[:, 0]).astype(int), np.round(uv[:, 1]).astype(int)
    inside = (xi >= 0) & (xi < 17) & (yi >= 0) & (yi < 12)
    np.testing.assert_array_equal(ours[inside], img[yi[inside], xi[inside]])
    assert np.all(ours[~inside] == 0)
    mask = jnp.asarray(img > 2)  # masks read False outside
    got = np.asarray(sampling.sample_nearest(mask, jnp.asarray(uv)))
    assert got.dtype == bool and not got[~inside].any()


def test_erode_ids_is_a_per_id_cross_erosion(rng):
    ids = np.zeros((20, 24), np.int32)
    ids[2:12, 3:15] = 1
    ids[8:18, 10:22] = 2
    ids[5, 5] = 3  # a single pixel vanishes
    ours = np.asarray(sampling.erode_ids(jnp.asarray(ids)))
    cross = cv2.getStructuringElement(cv2.MORPH_CROSS, (3, 3))
    ref = np.zeros_like(ids)
    for k in (1, 2, 3):  # OpenCV per id, the border counting as another id
        m = cv2.erode((ids == k).astype(np.uint8), cross, borderType=cv2.BORDER_CONSTANT,
                      borderValue=0)
        ref[m > 0] = k
    np.testing.assert_array_equal(ours, ref)


def test_transformations(rng):
    img = jnp.asarray(rng.random((16, 20)))
    uv = jnp.asarray(rng.uniform(1, 14, size=(8, 2)))
    f = sampling.sample_bilinear
    np.testing.assert_allclose(jax.jit(f)(img, uv), f(img, uv), rtol=1e-12)
    batched = jax.vmap(f, in_axes=(None, 0))(img, uv[None].repeat(3, 0))
    np.testing.assert_allclose(batched[1], f(img, uv), rtol=1e-12)
    # d/du of bilinear sampling = the image's difference across the pixel (finite differences)
    g = jax.grad(lambda p: f(img, p[None])[0])(uv[0])
    eps = 1e-6
    fd = [(f(img, (uv[0] + eps * e)[None])[0] - f(img, (uv[0] - eps * e)[None])[0]) / (2 * eps)
          for e in jnp.eye(2)]
    np.testing.assert_allclose(g, fd, rtol=1e-5, atol=1e-8)
