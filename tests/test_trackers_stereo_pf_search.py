"""Tests for the prediction-guided head / hand search of the stereo particle filter
(``jaxmocap.trackers.stereo_pf.search``).

Scene (OpenCV drawing; projections by ``cv2.projectPoints``, the oracle): the stereo pair of
``test_blobs`` (11 cm baseline, 320x240, f = 300 px, 2.2 m away), a blue shirt quad, a skin head
sphere on top and a **small** skin hand sphere (1.5 cm radius: ~13 px, below the blob line's
``min_area``) beside the shirt. Colours: the capture's model fitted from scribbles on the
left image."""

import cv2
import numpy as np
import pytest
from test_blobs import FX, SKIN, H, W, stereo_cams

from jaxmocap import blobs as B
from jaxmocap.errors import InputError
from jaxmocap.pf import colors as PC
from jaxmocap.trackers import stereo_pf as sp
from jaxmocap.trackers.stereo_pf import search as SS

SHIRT = (40, 70, 190)
HEAD = np.array([0.0, 0.0, 1.6])
HAND = np.array([0.0, 0.28, 1.05])
TORSO = np.array([[0.0, -0.2, 1.48], [0.0, 0.2, 1.48], [0.0, 0.2, 1.0], [0.0, -0.2, 1.0]])


def _uv(cam, X):
    R, t, K = (np.asarray(a, np.float64) for a in (cam.R, cam.t, cam.K))
    uv = cv2.projectPoints(np.atleast_2d(X), cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0][:, 0]
    depth = (np.atleast_2d(X) @ R.T + t)[:, 2]
    return uv, depth


def render(cam, rng, hand_r=0.015):
    img = np.clip(rng.normal(90, 5, (H, W, 3)), 0, 255).astype(np.uint8)
    quad, _ = _uv(cam, TORSO)
    cv2.fillPoly(img, [np.round(quad).astype(np.int32)], SHIRT)
    for X, r in ((HEAD, 0.1), (HAND, hand_r)):
        (uv,), (z,) = _uv(cam, X)
        cv2.circle(img, tuple(int(round(c * 16)) for c in uv), int(round(FX * r / z * 16)),
                   SKIN, -1, shift=4)
    return img


@pytest.fixture
def setup(rng):
    cams = stereo_cams()
    imgs = np.stack([render(c, rng) for c in cams])
    yy, xx = np.mgrid[:H, :W]
    (hu, hv), _ = _uv(cams[0], HEAD)[0][0], None
    skin = (xx - hu) ** 2 + (yy - hv) ** 2 <= 5**2
    (su, sv) = _uv(cams[0], TORSO.mean(0))[0][0]
    shirt = (np.abs(xx - su) <= 10) & (np.abs(yy - sv) <= 10)
    colors = PC.fit_capture_colors([imgs[0]], [skin], [shirt])
    params = sp.make_params(
        cams,
        images=sp.Images(colors=colors, plausible_blobs=True),
        motion=sp.Motion(n_particles=10),
    )
    return cams, imgs, params


def test_search_finds_a_hand_too_small_for_the_blob_line(setup):
    cams, imgs, params = setup
    near, far = params.reach
    assert near < np.linalg.norm(HAND - HEAD) < far  # precondition: a plausible hand
    masks = [PC.masks(params.colors, im)[0] for im in imgs]
    state, pts, valid = B.update(B.init(sp.BLOB_PARAMS), *masks, cams, reach=params.reach)
    assert not any(np.linalg.norm(c - HAND) < 0.1 for c in state.candidates)  # the blob line
    # misses it; the search around a prediction 6 cm off finds it
    predicted = np.stack([HEAD, HAND + [0.03, -0.04, 0.03], [0.0, -0.5, 1.0]])
    points = np.stack([HEAD, np.zeros(3), np.zeros(3)])
    out, found = SS.search_entities(params, imgs, predicted, points, np.array([1, 0, 0], bool))
    np.testing.assert_array_equal(found, [True, True, False])
    np.testing.assert_allclose(out[0], HEAD)  # measured entities are kept as given
    assert np.linalg.norm(out[1] - HAND) < 0.05  # 11 cm baseline: depth to a few cm
    assert np.linalg.norm((out[1] - HAND)[1:]) < 0.01  # lateral / vertical to 1 cm


def test_search_keeps_to_its_window_and_off_the_head(setup):
    cams, imgs, params = setup
    valid = np.array([1, 0, 0], bool)
    points = np.stack([HEAD, np.zeros(3), np.zeros(3)])
    far_off = np.stack([HEAD, HAND + [0.0, 0.35, 0.0], HAND + [0.0, 0.35, 0.0]])
    _, found = SS.search_entities(params, imgs, far_off, points, valid)
    assert not found[1:].any()  # the hand lies outside the 15 cm window
    on_head = np.stack([HEAD, HEAD + [0.0, 0.05, -0.05], HEAD + [0.0, -0.05, -0.05]])
    out, found = SS.search_entities(params, imgs, on_head, points, valid)
    assert not found[1:].any()  # the face is no hand
    # a lost head is searched around its prediction with the same colours
    head_only = SS.SearchParams(entities=(True, False, False))
    out, found = SS.search_entities(
        params, imgs, on_head, np.zeros((3, 3)), np.zeros(3, bool), head_only
    )
    assert found[0] and np.linalg.norm(out[0] - HEAD) < 0.06
    with pytest.raises(InputError, match="colours"):
        SS.search_entities(
            sp.make_params(cams, motion=sp.Motion(n_particles=10)), imgs, on_head, points, valid
        )


def test_observe_search_without_entities_is_the_blob_line(setup):
    """The loop with the filter alongside changes nothing when nothing is searched; with the
    search on, only entities the blob line left unmeasured can be added."""
    import jax

    cams, imgs, params = setup
    frames = np.stack([imgs] * 3)
    base = sp.observe_sequence(params, frames)
    off, log = SS.observe_search(
        params, jax.random.key(0), frames, search=SS.SearchParams(entities=(False, False, False))
    )
    np.testing.assert_array_equal(np.asarray(off.valid), np.asarray(base.valid))
    np.testing.assert_allclose(np.asarray(off.points), np.asarray(base.points))
    assert not log["found"].any()
    on, log = SS.observe_search(params, jax.random.key(0), frames)
    bv, ov = np.asarray(base.valid), np.asarray(on.valid)
    assert np.all(ov[bv]) and np.array_equal(log["found"], ov & ~bv)
    np.testing.assert_allclose(np.asarray(on.points)[bv], np.asarray(base.points)[bv])
