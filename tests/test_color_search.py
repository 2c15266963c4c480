"""Histogram search (Wang §4): bins, integral histogram vs cv2.calcHist / brute force,
uniformity, and the whole search against an independent NumPy brute-force implementation."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap.color import search as S

SMALL_SCALES = (24, 36, 48)


def np_bins(img: np.ndarray) -> np.ndarray:
    """Independent oracle: exact integer chromaticity bins (10 x 10 over (r, g))."""
    x = img.astype(np.int64)
    tot = x.sum(-1)
    safe = np.maximum(tot, 1)
    ir = np.minimum(10 * x[..., 0] // safe, 9)
    ig = np.minimum(10 * x[..., 1] // safe, 9)
    ir = np.where(tot == 0, 3, ir)
    ig = np.where(tot == 0, 3, ig)
    return ir * 10 + ig


def brute_force_search(
    img,
    mask,
    scales,
    stride=6,
    tau=0.1,
    min_fg=S.MIN_FOREGROUND_FRACTION,
    min_intensity=S.MIN_INTENSITY,
):
    """Full-resolution windows at the same centres, histograms by np.bincount."""
    bins = np_bins(img)
    h, w = img.shape[0] // stride, img.shape[1] // stride
    fg = np.ones(img.shape[:2], bool) if mask is None else mask.copy()
    fg &= img.astype(int).sum(-1) >= min_intensity
    heat = np.zeros((len(scales), h + 1, w + 1))
    valid = np.zeros(heat.shape, bool)
    for k, s in enumerate(scales):
        m = s // stride
        for a in range(m // 2, h + 1 - m // 2):
            for b in range(m // 2, w + 1 - m // 2):
                y0, x0 = (a - m // 2) * stride, (b - m // 2) * stride
                win = bins[y0 : y0 + s, x0 : x0 + s][fg[y0 : y0 + s, x0 : x0 + s]]
                if len(win) < min_fg * s * s or len(win) == 0:
                    continue
                hist = np.bincount(win, minlength=100) / len(win)
                heat[k, a, b] = np.minimum(hist, tau).sum()
                valid[k, a, b] = True
    umax = heat.max()
    wgt = np.where(valid, np.exp(-(((heat - umax) / (0.1 * umax)) ** 2)), 0)
    ys = stride * np.arange(h + 1) - 0.5
    xs = stride * np.arange(w + 1) - 0.5
    x = (wgt.sum((0, 1)) * xs).sum() / wgt.sum()
    y = (wgt.sum((0, 2)) * ys).sum() / wgt.sum()
    s = (wgt.sum((1, 2)) * np.asarray(scales)).sum() / wgt.sum()
    return heat, (x, y, s)


def test_chroma_bins_exact(rng):
    img = rng.integers(0, 256, (50, 60, 3)).astype(np.uint8)
    img[0, :6] = [[0, 0, 0], [3, 3, 4], [255, 0, 0], [0, 255, 0], [1, 2, 7], [30, 30, 40]]
    np.testing.assert_array_equal(np.asarray(S.chroma_bins(jnp.asarray(img))), np_bins(img))
    assert S.chroma_bins(jnp.asarray(img))[0, 1] == 33  # r/S = 0.3 exactly -> row 3
    assert len(S.REACHABLE_BINS) == 64
    assert set(np.unique(np_bins(rng.integers(0, 256, (200, 200, 3))))) <= set(S.REACHABLE_BINS)


@pytest.mark.parametrize("use_mask", [False, True])
def test_window_histograms_match_calchist(rng, use_mask):
    img = rng.integers(0, 256, (72, 90, 3)).astype(np.uint8)
    img[::7, ::5] //= 16  # some dark pixels (r + g + b < 45) that are not counted
    mask = rng.random((72, 90)) < 0.7 if use_mask else None
    integral = jax.jit(S.integral_histogram)(
        jnp.asarray(img), None if mask is None else jnp.asarray(mask)
    )
    assert integral.shape == (13, 16, 65)
    blocks = jax.jit(lambda t: [S.window_histograms(t, m) for m in range(1, 8)])(integral)
    bins_u8 = np_bins(img).astype(np.uint8)
    for _ in range(12):
        m = int(rng.integers(1, 8))
        i, j = int(rng.integers(0, 13 - m)), int(rng.integers(0, 16 - m))
        block = np.asarray(blocks[m - 1][i, j])
        hist = np.zeros(100)
        hist[list(S.REACHABLE_BINS)] = block[:-1]
        y0, x0, s = 6 * i, 6 * j, 6 * m
        roi = np.ascontiguousarray(bins_u8[y0 : y0 + s, x0 : x0 + s])
        counted = img[y0 : y0 + s, x0 : x0 + s].astype(int).sum(-1) >= S.MIN_INTENSITY
        if mask is not None:
            counted &= mask[y0 : y0 + s, x0 : x0 + s]
        roi_mask = counted.astype(np.uint8)
        ref = cv2.calcHist([roi], [0], roi_mask, [100], [0, 100]).reshape(-1)
        np.testing.assert_array_equal(hist, ref)
        sel = roi[counted]
        np.testing.assert_array_equal(hist, np.bincount(sel, minlength=100))
        assert float(block[-1]) == len(sel)


def test_uniformity_single_and_many_colours():
    assert np.asarray(S.expand_bins(jnp.arange(64.0)))[list(S.REACHABLE_BINS)].tolist() == list(
        range(64)
    )
    single = jnp.zeros(100).at[42].set(36.0)
    assert float(S.uniformity(single)) == pytest.approx(S.TAU)
    many = jnp.zeros(100).at[jnp.arange(0, 100, 10)].set(7.0)  # 10 colours, equal parts
    assert float(S.uniformity(many)) == pytest.approx(1.0)
    peaky = jnp.zeros(100).at[3].set(90.0).at[5].set(10.0)
    assert float(S.uniformity(peaky)) == pytest.approx(0.2)
    assert float(S.uniformity(jnp.zeros(100))) == 0.0


@pytest.fixture(scope="module")
def search_fn():
    return jax.jit(S.histogram_search, static_argnames=("scales", "stride"))


def _scene(rng, h=72, w=96):
    img = np.repeat(rng.integers(90, 110, (h, w, 1)), 3, axis=-1)
    img[..., 0] += 20
    img[20:56, 30:66] = rng.integers(0, 256, (36, 36, 3))  # colourful square
    img[2:20, 70:90] = [200, 40, 30]  # a red distractor
    img[60:72, 0:30] = rng.integers(0, 15, (12, 30, 3))  # dark noise (not counted)
    return img.astype(np.uint8)


@pytest.mark.parametrize("use_mask", [False, True])
def test_search_matches_brute_force(rng, search_fn, use_mask):
    img = _scene(rng)
    mask = None
    if use_mask:
        mask = np.zeros(img.shape[:2], bool)
        mask[10:70, 20:80] = rng.random((60, 60)) < 0.9
    res = search_fn(
        jnp.asarray(img), None if mask is None else jnp.asarray(mask), scales=SMALL_SCALES
    )
    heat, (x, y, s) = brute_force_search(img, mask, SMALL_SCALES)
    np.testing.assert_allclose(np.asarray(res.heat), heat, atol=1e-6)
    np.testing.assert_allclose([res.x, res.y, res.s], [x, y, s], rtol=1e-5)
    assert bool(res.found)
    assert abs(float(res.x) - 47.5) < 8 and abs(float(res.y) - 37.5) < 8


def test_search_vmap_and_no_foreground(rng, search_fn):
    imgs = np.stack([_scene(rng), _scene(rng)])
    batched = jax.vmap(lambda im: search_fn(im, scales=SMALL_SCALES))(jnp.asarray(imgs))
    for b in range(2):
        one = search_fn(jnp.asarray(imgs[b]), scales=SMALL_SCALES)
        np.testing.assert_allclose(batched.heat[b], one.heat, atol=1e-6)
        np.testing.assert_allclose([batched.x[b], batched.s[b]], [one.x, one.s], rtol=1e-5)
    none = search_fn(jnp.asarray(imgs[0]), jnp.zeros(imgs.shape[1:3], bool), scales=SMALL_SCALES)
    assert not bool(none.found)
    assert float(none.s) == max(SMALL_SCALES) and float(none.x) == (96 - 1) / 2


def test_search_rejects_bad_scales():
    img = jnp.zeros((72, 96, 3), jnp.uint8)
    with pytest.raises(ValueError, match="multiple of 2 \\* stride"):
        S.histogram_search(img, scales=(30,))
    with pytest.raises(ValueError, match="does not fit"):
        S.histogram_search(img, scales=(96,))
