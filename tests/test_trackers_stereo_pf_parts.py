"""Tests of the stereo filter's per-part colours and seeded search
(``jaxmocap.trackers.stereo_pf.parts``, issue 37 item 4).

Scene: the stereo pair and drawing of ``test_trackers_stereo_pf_search`` (OpenCV projections,
the oracle): a blue shirt quad, a skin head sphere and a hand sphere; here the hand has a
colour of its own (under another lamp) and is large enough for the blob line."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_blobs import FX, H, W, stereo_cams
from test_trackers_stereo_pf_search import HAND, HEAD, SHIRT, TORSO, _uv

from jaxmocap import appearance as ap
from jaxmocap.body import default_body
from jaxmocap.trackers import stereo_pf as sp
from jaxmocap.trackers.stereo_pf import parts as P

FACE = (222, 171, 140)
HAND_LAMP = (120, 130, 190)  # the hand's skin under a cool second lamp: not the face's colour


def render(cam, rng, hand_rgb, hand_r=0.03):
    img = np.clip(rng.normal(90, 3, (H, W, 3)), 0, 255).astype(np.uint8)
    quad, _ = _uv(cam, TORSO)
    cv2.fillPoly(img, [np.round(quad).astype(np.int32)], SHIRT)
    for X, r, rgb in ((HEAD, 0.1, FACE), (HAND, hand_r, hand_rgb)):
        (uv,), (z,) = _uv(cam, X)
        cv2.circle(img, tuple(int(round(c * 16)) for c in uv), int(round(FX * r / z * 16)),
                   rgb, -1, shift=4)
    return img


def _state(head, hand, shirt=SHIRT, sd=6.0):
    mean = jnp.asarray([head, hand, hand, shirt], jnp.float32)
    return ap.init_parts(mean, jnp.asarray(np.tile(np.eye(3) * sd**2, (4, 1, 1)), jnp.float32))


@pytest.fixture(scope="module")
def params():
    return sp.make_params(stereo_cams(), model=default_body(), motion=sp.Motion(n_particles=10))


def test_seeded_search_finds_a_hand_of_its_own_colour(params, rng):
    imgs = np.stack([P.blurred(render(c, rng, HAND_LAMP)) for c in stereo_cams()])
    # the right hand predicted in plain room beside the body
    pred = np.stack([HEAD, HAND + [0.03, -0.04, 0.02], HAND + [0.0, -0.9, 0.0]])
    none = np.zeros((3, 3)), np.zeros(3, bool)
    own = _state(FACE, HAND_LAMP)
    pts, val, found = P.seeded_search(params, own, imgs, pred, *none)
    assert found[1] and val[1]
    # across the view within 1 cm; in depth a pixel of disparity is ~15 cm at 2.2 m
    assert np.linalg.norm(pts[1, 1:] - HAND[1:]) < 0.01
    assert np.linalg.norm(pts[1] - HAND) < 0.05
    assert not found[2]  # nothing of the right hand's colour near its prediction
    # one skin class for all parts (the face's): the hand is not found
    shared = _state(FACE, FACE)
    _, _, found = P.seeded_search(params, shared, imgs, pred, *none)
    assert not found[1]


def test_hand_under_the_second_lamp_keeps_being_found(params, rng):
    """The hand's light turns from the face's lamp to a cool one over 30 frames; the hand's
    state follows from the estimate's pixels (here: the true hand's disc) and the seeded
    search finds the hand on every frame; the calibrated state loses it."""
    cams = stereo_cams()
    labels = np.zeros((2, H, W), np.int32)
    yy, xx = np.mgrid[:H, :W]
    for v, cam in enumerate(cams):
        for k, (X, r) in enumerate(((HEAD, 0.1), (HAND, 0.03))):
            (uv,), (z,) = _uv(cam, X)
            labels[v][(xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= (FX * r / z) ** 2] = k + 1
    labels = np.asarray(P.erode_labels(jnp.asarray(labels)))
    state = start = _state(FACE, FACE)
    pred = np.stack([HEAD, HAND, HAND + [0.0, -0.9, 0.0]])
    agree = jnp.asarray([True, True, False, False])
    for t in range(31):
        a = t / 30
        rgb = tuple(int(round((1 - a) * f + a * c)) for f, c in zip(FACE, HAND_LAMP, strict=True))
        imgs = np.stack([P.blurred(render(c, rng, rgb)) for c in cams])
        _, _, found = P.seeded_search(params, state, imgs, pred, np.zeros((3, 3)),
                                      np.zeros(3, bool))
        assert found[1], t
        state, used, _ = P.update_colours(state, jnp.asarray(imgs), jnp.asarray(labels), agree,
                                          jnp.asarray(True))
        assert bool(used[1])
    # the statistics are shading-normalised (brought to the state's brightness): the hand's
    # chromaticity follows the lamp, its brightness stays the calibrated one's
    def chroma(x):
        x = np.asarray(x, np.float64)
        return x / x.sum()

    # (atol: the state lags the ramp by ~2 frames at rate 0.3)
    np.testing.assert_allclose(chroma(state.mean[1]), chroma(HAND_LAMP), atol=0.02)
    np.testing.assert_allclose(np.asarray(state.mean[0]), FACE, atol=6)  # the head stays
    _, _, found = P.seeded_search(params, start, imgs, pred, np.zeros((3, 3)), np.zeros(3, bool))
    assert not found[1]


def test_invalid_frame_leaves_the_state_untouched_jit_and_vmap(rng):
    state = _state(FACE, HAND_LAMP)
    imgs = jnp.asarray(rng.normal(100, 20, (2, 24, 32, 3)), jnp.float32)
    labels = jnp.asarray(rng.integers(0, 5, (2, 24, 32)), jnp.int32)
    agree = jnp.ones(4, bool)
    new, used, fit = P.update_colours(state, imgs, labels, agree, jnp.asarray(False))
    for name in ("mean", "cov", "ref_mean", "ref_cov", "mix"):
        np.testing.assert_array_equal(np.asarray(getattr(new, name)),
                                      np.asarray(getattr(state, name)))
    assert not np.asarray(used).any() and not bool(fit.ok)
    np.testing.assert_array_equal(np.asarray(new.age), 1)
    # vmap over two frames (one valid, one not) equals the calls one by one
    batch = jax.tree.map(lambda a: jnp.stack([a, a]), state)
    valid = jnp.asarray([True, False])
    out, _, _ = jax.vmap(P.update_colours, in_axes=(0, None, None, None, 0))(
        batch, imgs, labels, agree, valid)
    one, _, _ = P.update_colours(state, imgs, labels, agree, jnp.asarray(True))
    np.testing.assert_allclose(np.asarray(out.mean[0]), np.asarray(one.mean), rtol=1e-5)
    np.testing.assert_array_equal(np.asarray(out.mean[1]), np.asarray(state.mean))


def test_render_parts_labels_by_roles():
    """Head, hands and shirt of the bundled body at rest, by roles; each part on its own
    pixels, the rest background."""
    model = default_body()
    scene = P.part_scene(model)
    cams = sp.make_params(stereo_cams(), model=model,
                          motion=sp.Motion(n_particles=10)).likelihood.cams
    q = jnp.zeros(model.n_dof).at[2].set(0.9)
    lab = np.asarray(jax.jit(lambda q: P.render_parts(scene, cams, q))(q))
    assert lab.shape == (2, H, W)
    for k in range(1, 5):
        assert (lab == k).sum() > 5, k
    er = np.asarray(P.erode_labels(jnp.asarray(lab)))
    assert all((er == k).sum() < (lab == k).sum() for k in range(1, 5))
