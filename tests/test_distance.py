"""Exact EDT vs OpenCV (DIST_L2, DIST_MASK_PRECISE) and SciPy's distance_transform_edt."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import ndimage

from jaxmocap.distance import edt, edt_to_zero, empty_distance, id_map_distances

TOL = 1e-3  # pixels


def _cv2_to_nearest_true(masks: np.ndarray) -> np.ndarray:
    """Reference: OpenCV measures distance to the nearest zero pixel, so feed it ~mask."""
    return np.stack(
        [
            cv2.distanceTransform((~m).astype(np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
            for m in masks
        ]
    )


def _scipy_to_nearest_true(masks: np.ndarray) -> np.ndarray:
    return np.stack([ndimage.distance_transform_edt(~m) for m in masks])


def _random_stack(rng: np.random.Generator, h: int, w: int) -> np.ndarray:
    """Sparse, dense, single-pixel, corner, blob, full, row, hole and (last) empty masks."""
    sparse = rng.random((h, w)) < 0.01
    sparse[rng.integers(h), rng.integers(w)] = True
    dense = rng.random((h, w)) < 0.6
    single = np.zeros((h, w), bool)
    single[rng.integers(h), rng.integers(w)] = True
    corner = np.zeros((h, w), bool)
    corner[h - 1, 0] = True
    yy, xx = np.mgrid[:h, :w]
    blob = (yy - h / 3) ** 2 + (xx - w / 2) ** 2 < (min(h, w) / 4) ** 2
    full = np.ones((h, w), bool)
    row = np.zeros((h, w), bool)
    row[h // 2] = True
    empty = np.zeros((h, w), bool)
    return np.stack([sparse, dense, single, corner, blob, full, row, ~blob, empty])


@pytest.mark.parametrize("shape", [(40, 40), (61, 17)])
def test_edt_matches_opencv_and_scipy(rng, shape):
    h, w = shape
    masks = _random_stack(rng, h, w)
    d = np.asarray(edt(jnp.asarray(masks)))
    assert d.dtype == np.float64  # default float dtype (tests run with x64)
    got, empty = d[:-1], d[-1]
    np.testing.assert_allclose(got, _cv2_to_nearest_true(masks[:-1]), atol=TOL, rtol=0)
    np.testing.assert_allclose(got, _scipy_to_nearest_true(masks[:-1]), atol=TOL, rtol=0)
    # an empty mask: a finite value larger than any true distance, everywhere
    np.testing.assert_array_equal(empty, empty_distance(h, w))
    assert empty_distance(h, w) > np.hypot(h - 1, w - 1)
    # OpenCV / SciPy convention: distance to the nearest False pixel (the full mask [5] has
    # none, so it is the empty case of this convention)
    got0 = np.asarray(edt_to_zero(jnp.asarray(masks)))
    keep = [i for i in range(len(masks)) if i != 5]
    np.testing.assert_allclose(
        got0[keep],
        np.stack([ndimage.distance_transform_edt(masks[i]) for i in keep]),
        atol=TOL,
        rtol=0,
    )
    np.testing.assert_array_equal(got0[5], h + w)
    np.testing.assert_array_equal(got0[-1], 0.0)


def test_dtype_follows_request(rng):
    masks = jnp.asarray(rng.random((2, 12, 10)) < 0.1)
    d32 = edt(masks, dtype=jnp.float32)
    assert d32.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(d32), np.asarray(edt(masks)), atol=1e-5)


def test_jit_vmap(rng):
    masks = rng.random((3, 2, 12, 10)) < 0.1  # (batch, n, h, w)
    ref = np.stack([_scipy_to_nearest_true(b) for b in masks])
    mj = jnp.asarray(masks)
    np.testing.assert_allclose(np.asarray(jax.vmap(edt)(mj)), ref, atol=TOL)
    np.testing.assert_allclose(np.asarray(jax.jit(jax.vmap(edt))(mj)), ref, atol=TOL)


def test_id_map_distances(rng):
    h, w, n_ids = 20, 26, 5
    id_map = rng.integers(0, n_ids - 1, size=(h, w))  # id 4 is absent
    id_map[:, :10] = 0
    d = np.asarray(jax.jit(id_map_distances, static_argnums=1)(jnp.asarray(id_map), n_ids))
    assert d.shape == (n_ids, h, w)
    for k in range(n_ids - 1):
        ref = ndimage.distance_transform_edt(id_map != k)
        np.testing.assert_allclose(d[k], ref, atol=TOL)
    np.testing.assert_array_equal(d[n_ids - 1], h + w)
    # brute-force definition of Wang's d_xy(r, k) at a few pixels
    for y, x, k in [(0, 0, 1), (13, 25, 2), (7, 3, 3)]:
        vs, us = np.nonzero(id_map == k)
        assert abs(d[k, y, x] - np.min(np.hypot(us - x, vs - y))) < TOL


def test_input_validation():
    # wrong rank: a ValueError (or the jaxtyping shape check, when enabled) names the shape
    with pytest.raises((ValueError, TypeError), match="n h w|\\(n, h, w\\)"):
        edt(jnp.zeros((4, 4), bool))
    with pytest.raises(ValueError, match="exceeds"):
        edt(jnp.zeros((1, 1, 4200), bool))
    with pytest.raises((ValueError, TypeError), match="h w|\\(h, w\\)"):
        id_map_distances(jnp.zeros((2, 4, 4), jnp.int32), 3)


def _span_stack(h: int, w: int) -> np.ndarray:
    """Masks whose column spans differ widely inside one stack (the row pass runs to the
    widest): two pixels at the far ends of a row (span w), a short bar, a single pixel in the
    last column, a full-height column, a patch-like blob, and an empty mask."""
    ends = np.zeros((h, w), bool)
    ends[1, 0] = ends[h - 2, w - 1] = True
    bar = np.zeros((h, w), bool)
    bar[h // 3, w // 2 : w // 2 + 5] = True
    last = np.zeros((h, w), bool)
    last[h // 2, w - 1] = True
    column = np.zeros((h, w), bool)
    column[:, 3] = True
    yy, xx = np.mgrid[:h, :w]
    blob = (yy - 0.7 * h) ** 2 + (xx - 0.3 * w) ** 2 < 9.0
    return np.stack([ends, bar, last, column, blob, np.zeros((h, w), bool)])


@pytest.mark.parametrize("shape", [(23, 37), (37, 23), (16, 16)])
def test_edt_column_spans(shape):
    """Spans from 1 column to the full width (and 0) in one stack: each exact vs OpenCV."""
    h, w = shape
    masks = _span_stack(h, w)
    d = np.asarray(edt(jnp.asarray(masks)))
    np.testing.assert_allclose(d[:-1], _cv2_to_nearest_true(masks[:-1]), atol=TOL, rtol=0)
    np.testing.assert_array_equal(d[-1], empty_distance(h, w))
    # one mask alone gives the same as inside the stack (the loop count is the stack's max)
    for k in (1, 2, 4):
        np.testing.assert_array_equal(np.asarray(edt(jnp.asarray(masks[k : k + 1])))[0], d[k])
    # all empty: the row pass runs zero times
    np.testing.assert_array_equal(np.asarray(edt(jnp.zeros((2, h, w), bool))), h + w)


def test_vmap_members_with_different_spans(rng):
    """vmap folds the batch into the stack: a member with a narrow span next to one spanning
    the image, nested vmap, jit, and a gradient through a cost that uses the distances."""
    h, w = 14, 19
    s = _span_stack(h, w)
    batch = np.stack([s[[1, 2, 4]], s[[0, 3, 5]]])  # (2, 3, h, w): spans 5/1/~6 vs w/1/0
    want = np.stack([_scipy_to_nearest_true(b) for b in batch])
    want[1, 2] = h + w
    got = np.asarray(jax.jit(jax.vmap(edt))(jnp.asarray(batch)))
    np.testing.assert_allclose(got, want, atol=TOL, rtol=0)
    nested = jax.vmap(jax.vmap(lambda m: edt(m[None])[0]))(jnp.asarray(batch))
    np.testing.assert_allclose(np.asarray(nested), want, atol=TOL, rtol=0)
    inner = jax.vmap(edt, in_axes=1, out_axes=1)(jnp.asarray(batch.swapaxes(0, 1)))
    np.testing.assert_allclose(np.asarray(inner).swapaxes(0, 1), want, atol=TOL, rtol=0)
    x = jnp.asarray(rng.random((h, w)))

    def cost(x):  # the distances enter like Wang's C * d term: constants for the gradient
        return jnp.sum(x * edt((x > 0.9)[None])[0])

    np.testing.assert_allclose(
        np.asarray(jax.grad(cost)(x)), _scipy_to_nearest_true(np.asarray(x > 0.9)[None])[0],
        atol=TOL,
    )  # fmt: skip


@pytest.mark.parametrize(
    ("shape", "regime"),
    [
        ((48, 64), "uint16"),  # (h-1)^2 + (w-1)^2 below the none code N: no fallback
        ((160, 160), "uint16 + fallback"),  # a true d^2 may reach N: checked per call
        ((260, 40), "float32"),  # (h-1)^2 does not fit below N: the float32 pass
    ],
)
def test_uint16_row_pass_is_exact(rng, shape, regime):
    """The row pass in uint16 (wrapping differences and squares, "none" code N) gives the
    same integers as the float32 pass and SciPy on every kind of mask; on 160^2 a single
    pixel in a corner (d up to 225 px > sqrt(N) = 198) sends the call to the float32 pass,
    a stack without such far pixels stays in uint16, both exact."""
    from jaxmocap import distance as dist

    h, w = shape
    masks = _random_stack(rng, h, w)
    got = np.asarray(edt(jnp.asarray(masks)))
    want = _scipy_to_nearest_true(masks[:-1])
    np.testing.assert_allclose(got[:-1], want, atol=TOL, rtol=0)
    np.testing.assert_array_equal(got[-1], empty_distance(h, w))
    ref = np.asarray(jax.jit(dist._edt_sq_float)(jnp.asarray(masks)))
    np.testing.assert_array_equal(np.asarray(jax.jit(dist._edt_sq)(jnp.asarray(masks))), ref)
    near = masks[[0, 1, 4, 5, 6, 7, 8]]  # no corner / single pixel: all distances small
    np.testing.assert_array_equal(
        np.asarray(jax.jit(dist._edt_sq)(jnp.asarray(near))),
        np.asarray(jax.jit(dist._edt_sq_float)(jnp.asarray(near))),
    )
    none = 2**16 - 1 - (w - 2 + dist._BLOCK) ** 2
    if regime == "uint16 + fallback":
        assert (h - 1) ** 2 + (w - 1) ** 2 >= none and ref.max() >= none > want[:-1].min()
    elif regime == "uint16":
        assert (h - 1) ** 2 + (w - 1) ** 2 < none
    else:
        assert (h - 1) ** 2 >= none
