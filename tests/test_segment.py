"""Tests for jaxmocap.segment: the JAX image processing line against OpenCV (the oracle)."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import segment as S

H, W = 48, 64  # one image size for every test: one compilation per jitted function

SHIRT_RGB = (30, 60, 200)  # blue: in the default shirt interval
SKIN_RGB = (224, 172, 105)  # in the default skin interval


def scene(rng: np.random.Generator, shift: int = 0) -> np.ndarray:
    """A cluttered RGB image: noisy background, a blue 'shirt', skin ellipses, distractors."""
    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    img = cv2.GaussianBlur(img, (5, 5), 0)
    cv2.rectangle(img, (20 + shift, 14), (44 + shift, 40), SHIRT_RGB, -1)
    cv2.ellipse(img, (32 + shift, 8), (6, 7), 0, 0, 360, SKIN_RGB, -1)  # head
    cv2.ellipse(img, (12 + shift, 30), (4, 3), 30, 0, 360, (141, 85, 36), -1)  # dark hand
    cv2.circle(img, (55, 40), 4, (255, 219, 172), -1)  # light skin distractor
    cv2.circle(img, (55, 10), 5, (200, 30, 90), -1)  # crimson (H ~ 169), not skin
    noise = rng.integers(-12, 13, (H, W, 3))
    return np.clip(img.astype(np.int32) + noise, 0, 255).astype(np.uint8)


def test_gaussian_blur_3x3_bit_exact(rng):
    img = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    ours = np.asarray(jax.jit(S.gaussian_blur_3x3)(jnp.asarray(img)))
    np.testing.assert_array_equal(ours, cv2.GaussianBlur(img, (3, 3), 0))


def test_rgb_to_hsv_bit_exact_over_colour_grid(rng):
    # every 5th level per channel (incl. 0 and 255: greys, pure and saturated colours)
    levels = np.unique(np.r_[np.arange(0, 256, 5), 1, 254, 255]).astype(np.uint8)
    grid = np.stack(np.meshgrid(levels, levels, levels, indexing="ij"), -1).reshape(-1, 1, 3)
    rand = rng.integers(0, 256, (4096, 1, 3), dtype=np.uint8)
    rgb = np.concatenate([grid, rand])
    ours = np.asarray(jax.jit(S.rgb_to_hsv)(jnp.asarray(rgb)))
    ref = cv2.cvtColor(rgb, cv2.COLOR_RGB2HSV)
    np.testing.assert_array_equal(ours, ref)
    assert ours[..., 0].max() < 180  # OpenCV's hue range [0, 180)


@pytest.mark.parametrize(
    "low,high", [((0, 40, 60), (25, 230, 255)), ((170, 50, 50), (10, 255, 255))]
)
def test_in_range_matches_opencv_with_hue_wrap(rng, low, high):
    hsv = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    hsv[..., 0] = rng.integers(0, 180, (H, W))
    interval = S.HSVInterval(low, high)
    ours = np.asarray(S.in_range(jnp.asarray(hsv), interval))
    lo, hi = np.array(low, np.uint8), np.array(high, np.uint8)
    if low[0] <= high[0]:
        ref = cv2.inRange(hsv, lo, hi) > 0
    else:  # wrap: [low_h, 179] u [0, high_h]
        ref = (cv2.inRange(hsv, lo, np.r_[179, hi[1:]].astype(np.uint8)) > 0) | (
            cv2.inRange(hsv, np.r_[0, lo[1:]].astype(np.uint8), hi) > 0
        )
    np.testing.assert_array_equal(ours, ref)
    assert 0 < ref.sum() < ref.size


def test_gaussian_kernel_matches_opencv():
    for k, s in ((3, 0.8), (9, 1.5), (11, 2.5)):
        np.testing.assert_allclose(
            np.asarray(S.gaussian_kernel(k, s)), cv2.getGaussianKernel(k, s)[:, 0], atol=1e-7
        )


def test_segment_equals_opencv_pipeline(rng):
    params = S.SegmentParams()
    seg_jit = jax.jit(S.segment)
    for i in range(3):
        img = scene(rng, shift=3 * i)
        ours = seg_jit(params, jnp.asarray(img))
        ref = S.segment_cv(params, img)
        # bit-exact blur + HSV: the masks are identical, not just close
        np.testing.assert_array_equal(np.asarray(ours.skin), ref.skin)
        np.testing.assert_array_equal(np.asarray(ours.foreground), ref.foreground)
        np.testing.assert_allclose(np.asarray(ours.edges), ref.edges, atol=2e-6)
        assert ours.edges.dtype == jnp.float32 and ref.edges.dtype == np.float32
        # the scene is really found: shirt ~ its rectangle, skin = head, hand, distractor
        shirt = np.zeros((H, W), np.uint8)
        cv2.rectangle(shirt, (20 + 3 * i, 14), (44 + 3 * i, 40), 1, -1)
        assert np.sum(ref.foreground != shirt.astype(bool)) < 0.15 * shirt.sum()
        assert ref.skin[8, 32 + 3 * i] and ref.skin[30, 12 + 3 * i] and ref.skin[40, 55]
        assert not ref.skin[10, 55]  # the crimson disc is not skin


def test_segment_external_foreground(rng):
    params = S.SegmentParams(edge_sigma=1.0, edge_ksize=5)
    img = scene(rng)
    fg = np.zeros((H, W), bool)
    cv2.circle(fg.view(np.uint8), (30, 24), 12, 1, -1)
    ours = jax.jit(S.segment)(params, jnp.asarray(img), jnp.asarray(fg))
    ref = S.segment_cv(params, img, fg)
    np.testing.assert_array_equal(np.asarray(ours.foreground), fg)
    np.testing.assert_array_equal(np.asarray(ours.skin), ref.skin)
    np.testing.assert_allclose(np.asarray(ours.edges), ref.edges, atol=2e-6)


def test_edge_map_peaks_on_silhouette_boundary():
    fg = np.zeros((H, W), np.uint8)
    cv2.ellipse(fg, (30, 24), (16, 11), 20, 0, 360, 1, -1)
    g = np.asarray(jax.jit(S.edge_map)(jnp.asarray(fg.astype(bool))))
    assert g.dtype == np.float32 and g.min() >= 0.0 and g.max() == pytest.approx(1.0)
    # oracle for the distance to the silhouette boundary: OpenCV distance transforms of the
    # mask and its complement (the boundary lies between a pixel with d_in=1 and d_out=1)
    d_in = cv2.distanceTransform(fg, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d_out = cv2.distanceTransform(1 - fg, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    d = np.maximum(d_in, d_out)  # 1 next to the boundary, grows away from it
    assert g[d <= 1].mean() > 0.6  # high on the boundary
    assert g[d >= 4].max() < 0.15  # spread decays (sigma 1.5 px)
    # compact support: +-k//2 px per axis around gradient pixels, which lie <= 1 px from d = 1
    assert np.all(g[d > np.sqrt(2) * (S.EDGE_KSIZE // 2) + 2] == 0)
    # monotone fall-off with the distance from the boundary
    means = [g[(d > r - 0.5) & (d <= r + 0.5)].mean() for r in (1, 2, 3, 4)]
    assert all(a > b for a, b in zip(means, means[1:], strict=False))


def test_edge_map_without_edges_is_zero():
    for fill in (False, True):
        g = np.asarray(S.edge_map(jnp.full((H, W), fill)))
        assert not np.any(g) and np.all(np.isfinite(g))


def test_segment_views_vmap_equals_per_camera(rng):
    params = S.SegmentParams()
    pair = np.stack([scene(rng), scene(rng, shift=4)])
    both = S.segment_views(params, jnp.asarray(pair))
    assert both.edges.shape == (2, H, W)
    for c in range(2):
        one = S.segment_cv(params, pair[c])
        np.testing.assert_array_equal(np.asarray(both.skin[c]), one.skin)
        np.testing.assert_array_equal(np.asarray(both.foreground[c]), one.foreground)
        np.testing.assert_allclose(np.asarray(both.edges[c]), one.edges, atol=2e-6)
    # changing the thresholds does not change the traced program's structure (arrays)
    other = S.SegmentParams(skin=S.HSVInterval((0, 10, 10), (30, 255, 255)))
    assert (
        np.asarray(S.segment_views(other, jnp.asarray(pair)).skin).sum()
        >= np.asarray(both.skin).sum()
    )


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(low=(180, 0, 0), high=(10, 255, 255)), r"H in \[0, 180\)"),
        (dict(low=(0, 100, 0), high=(10, 50, 255)), "low <= high"),
        (dict(low=(0, 0), high=(10, 50, 255)), "3 integers"),
        (dict(low=(0.5, 0, 0), high=(10, 50, 255)), "3 integers"),
    ],
)
def test_hsv_interval_validation(kwargs, match):
    with pytest.raises(ValueError, match=match):
        S.HSVInterval(**kwargs)


def test_params_validation_and_cv_input_check():
    with pytest.raises(ValueError, match="edge_ksize"):
        S.SegmentParams(edge_ksize=4)
    with pytest.raises(ValueError, match="edge_sigma"):
        S.SegmentParams(edge_sigma=0.0)
    with pytest.raises(ValueError, match="uint8 RGB"):
        S.segment_cv(S.SegmentParams(), np.zeros((H, W), np.uint8))
