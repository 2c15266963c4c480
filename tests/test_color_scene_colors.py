"""Procedural 2-D scenes: a 20-patch, 10-colour "shirt" under random illuminants on a textured
background with colourful distractors. Checks the histogram search (§4) finds the shirt and that
reference illuminations (§5.2) recover the classification after a lamp is switched off."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _shirt_colours import SHIRT  # noqa: E402  (shared procedural shirt palette)

from jaxmocap.color import (
    classified_fraction,
    classify,
    classify_views_with_references,
    classify_with_references,
    fit_color_model,
    histogram_search,
    init_references,
    maybe_add_reference,
    white_balance_from_ids,
)


def make_scene(rng, h=480, w=640, L=None, shirt_w=None, noise=3.0):
    """RGB uint8 image, colour-id map (0 background, 1..10), shirt centre (x, y) and width."""
    L = np.eye(3) if L is None else L
    # textured, low-saturation background: smoothed noise around a random grey-brown
    base = rng.uniform(60, 160) * np.array([1.0, rng.uniform(0.85, 1.0), rng.uniform(0.7, 0.95)])
    tex = cv2.GaussianBlur(rng.normal(0, 25, (h, w)).astype(np.float32), (0, 0), 4)[..., None]
    img = np.clip(base + tex * np.array([1.0, 0.95, 0.9]), 0, 255)
    ids = np.zeros((h, w), int)
    # the shirt: 4 x 5 grid of 20 patches, each colour twice, per-patch shading; at least
    # 24 px from the borders
    sw = int(rng.integers(130, 190) if shirt_w is None else shirt_w)
    sh = int(1.2 * sw)
    m = min(24, (w - sw) // 2, (h - sh) // 2)
    x0, y0 = int(rng.integers(m, w - sw - m + 1)), int(rng.integers(m, h - sh - m + 1))
    # colourful distractors: 1- or 2-colour boxes and discs in saturated random colours
    # (background objects: they do not overlap the shirt or come within 30 px of it)
    for _ in range(6):
        cols = rng.uniform(0, 255, (2, 3)) * rng.uniform(0.5, 1, (2, 1))
        cols[:, rng.integers(0, 3)] *= 0.2
        bw, bh = rng.integers(40, 140, 2)
        bx, by = rng.integers(0, w - bw), rng.integers(0, h - bh)
        box = np.zeros((h, w), bool)
        if rng.random() < 0.5:
            box[by : by + bh, bx : bx + bw] = True
        else:
            yy, xx = np.mgrid[:h, :w]
            box = ((xx - bx - bw / 2) / (bw / 2)) ** 2 + ((yy - by - bh / 2) / (bh / 2)) ** 2 < 1
        stripe = (np.arange(w) // 15 % 2 == 1)[None, :] & (rng.random() < 0.5)
        box[max(y0 - 30, 0) : y0 + sh + 30, max(x0 - 30, 0) : x0 + sw + 30] = False
        img[box & ~stripe] = cols[0]
        img[box & stripe] = cols[1]
    order = rng.permutation(np.repeat(np.arange(10), 2))
    for n, k in enumerate(order):
        r, c = divmod(n, 4)
        ys = slice(y0 + r * sh // 5, y0 + (r + 1) * sh // 5)
        xs = slice(x0 + c * sw // 4, x0 + (c + 1) * sw // 4)
        img[ys, xs] = SHIRT[k] * rng.uniform(0.85, 1.1)
        ids[ys, xs] = k + 1
    img = img @ L.T + rng.normal(0, noise, img.shape)
    centre = (x0 + (sw - 1) / 2, y0 + (sh - 1) / 2)
    return np.clip(np.round(img), 0, 255).astype(np.uint8), ids, centre, sw


def random_illuminant(rng):
    gains = np.diag(rng.uniform(0.6, 1.25, 3)) * rng.uniform(0.6, 1.1)
    return gains + rng.uniform(-0.08, 0.08, (3, 3))


def test_search_finds_the_shirt(rng):
    search = jax.jit(histogram_search, static_argnames=("scales", "stride"))
    hits, n = 0, 20
    for _ in range(n):
        img, _, (cx, cy), sw = make_scene(rng, L=random_illuminant(rng))
        res = search(jnp.asarray(img))
        hits += np.hypot(float(res.x) - cx, float(res.y) - cy) < sw / 4
    assert hits >= 0.95 * n


@pytest.fixture(scope="module")
def lamp():
    """Colour model from white-balanced scenes; a warm lamp on, then off (dim and bluish)."""
    rng = np.random.default_rng(1)
    scenes = [make_scene(rng, 200, 200, shirt_w=120) for _ in range(3)]
    model = fit_color_model([s[0] for s in scenes], [s[1] for s in scenes], 10)
    on = np.array([[1.15, 0.05, 0.0], [0.03, 0.95, 0.0], [0.0, 0.05, 0.6]])
    off = np.array([[0.45, 0.0, 0.02], [0.0, 0.55, 0.04], [0.0, 0.03, 0.75]])
    return model, on, off, rng


def test_reference_illuminations_recover_a_lamp_switched_off(lamp):
    model, on, off, rng = lamp
    wb = jax.jit(white_balance_from_ids)
    classify_refs = jax.jit(classify_with_references)

    def frame(L):
        img, ids, _, _ = make_scene(rng, 200, 200, L=L, shirt_w=120)
        return jnp.asarray(img), jnp.asarray(ids), jnp.asarray(ids > 0)  # mask: ideal fg

    refs = init_references(jnp.eye(3))
    # earlier in the session the lamp was off for a while: its W joins the references
    img, ids, fg = frame(off)
    W_off = wb(model, img, ids, jnp.eye(3))
    refs, added = maybe_add_reference(refs, W_off)
    assert bool(added)
    # lamp on: W tracks it and is stored too
    img, ids, fg = frame(on)
    W_on = wb(model, img, ids, W_off)
    refs, added = maybe_add_reference(refs, W_on)
    assert bool(added) and int(refs.count) == 3
    r_on = classify_refs(model, refs, W_on, img, fg)
    assert float(r_on.fraction) > 0.7 and not bool(r_on.used_reference)
    # the lamp is switched off: the previous W no longer fits
    img, ids, fg = frame(off)
    plain, _ = classify(model, W_on, img, fg)
    collapsed = float(classified_fraction(plain, fg))
    print("lamp off without references:", collapsed)
    assert collapsed < 0.4  # collapses without references
    out = classify_refs(model, refs, W_on, img, fg)
    assert bool(out.used_reference)
    np.testing.assert_allclose(out.W, W_off)
    # dim light: noise and quantisation are amplified by W (about 2x), so fewer pixels fall
    # within T = 3 of a model trained in good light than with the lamp on
    print("lamp off with references:", float(out.fraction))
    assert float(out.fraction) > 0.5
    got, truth = np.asarray(out.ids), np.asarray(ids)
    assert np.mean(got[got > 0] == truth[got > 0]) > 0.95  # classified pixels are right
    # without the lamp-off reference, nothing stored can help: the collapse remains
    alone = classify_refs(model, init_references(W_on), W_on, img, fg)
    assert float(alone.fraction) < 0.4


def test_classify_views_with_references_equals_each_view_alone(lamp):
    """Two views, one classified well with its W (no fallback) and one after the lamp went off
    (its fallback picks a stored reference): the batched call gives each view what
    ``classify_with_references`` gives it alone; with no view below ``min_fraction`` neither
    uses a reference."""
    model, on, off, rng = lamp
    wb = jax.jit(white_balance_from_ids)
    img_on, ids_on, _, _ = make_scene(rng, 160, 160, L=on, shirt_w=100)
    img_off, ids_off, _, _ = make_scene(rng, 160, 160, L=off, shirt_w=100)
    W_on = wb(model, jnp.asarray(img_on), jnp.asarray(ids_on), jnp.eye(3))
    W_off = wb(model, jnp.asarray(img_off), jnp.asarray(ids_off), jnp.eye(3))
    refs = init_references(W_on)
    refs, _ = maybe_add_reference(refs, W_off)
    stacked = jax.tree.map(lambda a: jnp.stack([a, a]), refs)
    images = jnp.stack([jnp.asarray(img_on), jnp.asarray(img_off)])
    masks = jnp.stack([jnp.asarray(ids_on > 0), jnp.asarray(ids_off > 0)])
    W = jnp.stack([W_on, W_on])  # view 1 still has the lamp-on W: it needs the fallback
    batched = jax.jit(classify_views_with_references)
    for m in (masks, None):
        both = batched(model, stacked, W, images, m)
        if m is not None:  # (without masks the fraction counts the background too)
            assert not bool(both.used_reference[0]) and bool(both.used_reference[1])
        for i in range(2):
            alone = classify_with_references(model, refs, W[i], images[i],
                                             None if m is None else m[i])  # fmt: skip
            for a, b in zip(jax.tree.leaves(alone), jax.tree.leaves(both), strict=True):
                np.testing.assert_allclose(np.asarray(b[i]), np.asarray(a), rtol=1e-6, atol=1e-5)
    # nobody below min_fraction: the fallback's branch is not taken
    none = batched(model, stacked, W, images, masks, min_fraction=0.0)
    assert not bool(jnp.any(none.used_reference))
    np.testing.assert_array_equal(np.asarray(none.W), np.asarray(W))


def test_maybe_add_reference_threshold_and_ring_buffer():
    refs = init_references(jnp.eye(3), capacity=3)
    add = jax.jit(maybe_add_reference)
    refs, added = add(refs, jnp.eye(3) + 0.4 / 3)  # ||.||_F = 0.4 <= 0.5
    assert not bool(added) and int(refs.count) == 1
    refs, added = add(refs, jnp.eye(3) + 0.6 / 3)  # ||.||_F = 0.6 > 0.5
    assert bool(added) and int(refs.count) == 2
    np.testing.assert_allclose(refs.W[1], jnp.eye(3) + 0.2)
    for v in [2.0, 3.0]:  # third fills the buffer, fourth overwrites slot 0
        refs, added = add(refs, v * jnp.eye(3))
        assert bool(added)
    assert int(refs.count) == 4 and bool(jnp.all(refs.valid))
    np.testing.assert_allclose(refs.W[0], 3 * jnp.eye(3))
    np.testing.assert_allclose(refs.W[2], 2 * jnp.eye(3))
    assert add._cache_size() == 1  # traced count: no recompilation as the buffer fills
