"""Tests for the hands gated by the particle cloud's prediction
(``jaxmocap.trackers.stereo_pf.hands``).

Scene: the stereo pair of ``test_blobs`` (11 cm baseline, 320x240, f = 300 px, 2.2 m away; the
camera's image-right is world +y); skin masks drawn as discs at points projected by
``cv2.projectPoints`` (the oracle). The subject's left side is +y: left shoulder and hand at
+y. Forward kinematics of ``jaxmocap.body.keypoints`` per particle is the oracle of the cloud's
mean and spread."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_blobs import FX, H, W, stereo_cams

from jaxmocap.body import default_body, keypoint_index, keypoints
from jaxmocap.errors import InputError
from jaxmocap.trackers import stereo_pf as sp
from jaxmocap.trackers.stereo_pf import hands as HS

HEAD = np.array([0.0, 0.0, 1.60])
SHOULDERS = np.array([[0.0, 0.18, 1.42], [0.0, -0.18, 1.42]])  # left (+y), right
HANDS = np.array([[0.05, 0.30, 1.05], [-0.05, -0.32, 1.15]])  # left, right
NECK = np.array([0.0, 0.0, 1.47])


def _uv(cam, X):
    R, t, K = (np.asarray(a, np.float64) for a in (cam.R, cam.t, cam.K))
    uv = cv2.projectPoints(np.atleast_2d(X), cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0][:, 0]
    return uv, (np.atleast_2d(X) @ R.T + t)[:, 2]


def _masks(cams, blobs):
    """Skin masks of both views: a disc per (point, radius m)."""
    out = []
    for cam in cams:
        m = np.zeros((H, W), np.uint8)
        for X, r in blobs:
            (uv,), (z,) = _uv(cam, X)
            cv2.circle(m, tuple(int(round(c * 16)) for c in uv), int(round(FX * r / z * 16)),
                       1, -1, shift=4)
        out.append(m > 0)
    return out


@pytest.fixture(scope="module")
def setup():
    cams = stereo_cams()
    params = sp.make_params(cams, motion=sp.Motion(n_particles=10))
    return cams, params, HS.arm_reach(params.model)


def _predicted(hands):
    return np.vstack([HEAD, SHOULDERS, hands])


NONE = (np.zeros((3, 3)), np.zeros(3, bool))  # the blob line found nothing


def test_gated_search_finds_both_hands_near_the_prediction(setup):
    cams, params, arms = setup
    masks = _masks(cams, [(HEAD, 0.1), (HANDS[0], 0.02), (HANDS[1], 0.02)])
    pred = _predicted(HANDS + [[0.03, -0.04, 0.03], [-0.02, 0.04, -0.03]])
    out, found, log = HS.gated_hands(params, arms, masks, pred, np.full(5, 0.05), *NONE)
    np.testing.assert_array_equal(found, [True, True])
    np.testing.assert_array_equal(log["source"], [2, 2])  # from the windows
    for k in range(2):
        assert np.linalg.norm(out[k] - HANDS[k]) < 0.05  # depth: 1 px of disparity ~ 15 cm
        for cam in cams:  # the found point reprojects onto the hand's centre within 0.5 px
            assert np.linalg.norm(_uv(cam, out[k])[0] - _uv(cam, HANDS[k])[0]) < 0.5


def test_neck_skin_is_never_a_hand(setup):
    cams, params, arms = setup
    # the neck's skin blob inside the left hand's window (predicted 12 cm from the neck) and
    # no left hand in the images: the left hand is missing, neither the neck nor the head
    masks = _masks(cams, [(HEAD, 0.1), (NECK, 0.03), (HANDS[1], 0.02)])
    pred = _predicted(np.stack([NECK + [0.0, 0.12, -0.02], HANDS[1]]))
    out, found, _ = HS.gated_hands(params, arms, masks, pred, np.full(5, 0.1), *NONE)
    np.testing.assert_array_equal(found, [False, True])
    np.testing.assert_array_equal(out[0], 0.0)  # missing: Azad's zero point
    # ... nor when the blob line names the neck as the left hand
    blob = np.stack([HEAD, NECK, np.zeros(3)]), np.array([True, True, False])
    out, found, _ = HS.gated_hands(params, arms, masks, pred, np.full(5, 0.1), *blob)
    assert not found[0] and np.linalg.norm(out[1] - HANDS[1]) < 0.05
    # ... nor the face when the blob line's "head" is a skin-coloured prop beside the subject:
    # the predicted head rules it out too
    prop_head = np.array([0.0, 0.9, 1.9])
    blob = np.stack([prop_head, HEAD + [0.0, 0.02, -0.03], np.zeros(3)]), \
        np.array([True, True, False])
    out, found, _ = HS.gated_hands(params, arms, masks, pred, np.full(5, 0.1), *blob)
    assert not found[0]


def test_distractors_outside_the_window_or_the_reach_are_not_taken(setup):
    cams, params, arms = setup
    far_prop = np.array([0.0, 0.75, 1.05])  # 45 cm beside the predicted left hand: in reach
    # of the left shoulder (0.6 m) but outside the window
    assert np.linalg.norm(far_prop - SHOULDERS[0]) < float(arms.reach[0])
    masks = _masks(cams, [(HEAD, 0.1), (far_prop, 0.03)])
    pred = _predicted(HANDS)
    out, found, _ = HS.gated_hands(params, arms, masks, pred, np.full(5, 0.02), *NONE)
    np.testing.assert_array_equal(found, [False, False])
    np.testing.assert_array_equal(out, 0.0)
    # a prop the blob line hands over beyond the arm's reach of either shoulder is dropped; one
    # within reach of the left shoulder is kept (the blob line's hands pass by the body only)
    prop = np.array([0.0, 1.3, 1.0])
    assert np.linalg.norm(prop - SHOULDERS[0]) > float(arms.reach[0])
    assert np.linalg.norm(prop - SHOULDERS[1]) > float(arms.reach[1])
    blob = np.stack([HEAD, far_prop, prop]), np.array([True, True, True])
    out, found, log = HS.gated_hands(params, arms, masks, pred, np.full(5, 0.02), *blob)
    np.testing.assert_array_equal(found, [True, False])
    np.testing.assert_allclose(out[0], far_prop)
    np.testing.assert_array_equal(log["source"], [1, 0])


def test_identities_come_from_the_blob_line_and_the_windows_not_the_prediction(setup):
    cams, params, arms = setup
    # a filter turned the wrong way round: its right hand predicted where the true left hand
    # is. The blob line's left hand stays the left hand (within reach of the left shoulder)
    pred = _predicted(HANDS[::-1])
    pred[1:3] = SHOULDERS
    masks = _masks(cams, [(HEAD, 0.1)])
    blob = np.stack([HEAD, HANDS[0], np.zeros(3)]), np.array([True, True, False])
    out, found, log = HS.gated_hands(params, arms, masks, pred, np.full(5, 0.05), *blob)
    np.testing.assert_array_equal(found, [True, False])
    np.testing.assert_allclose(out[0], HANDS[0])


def test_absent_hands_are_missing_and_an_unknown_prediction_searches_nothing(setup):
    cams, params, arms = setup
    masks = _masks(cams, [(HEAD, 0.1)])
    out, found, log = HS.gated_hands(params, arms, masks, _predicted(HANDS), np.full(5, 0.3),
                                     *NONE)
    np.testing.assert_array_equal(found, [False, False])
    np.testing.assert_array_equal(log["source"], [0, 0])
    masks = _masks(cams, [(HEAD, 0.1), (HANDS[0], 0.02)])
    pred = _predicted(HANDS)
    pred[3] = np.nan
    _, found, _ = HS.gated_hands(params, arms, masks, pred, np.full(5, 0.05), *NONE)
    assert not found.any()


def test_gates_vmap_and_jit_as_one_candidate_at_a_time(setup):
    _, _, arms = setup
    rng = np.random.default_rng(0)
    X = jnp.asarray(rng.normal(0, 0.4, (40, 3)) + [0, 0.2, 1.2], jnp.float32)
    args = (jnp.asarray(_predicted(HANDS), jnp.float32), jnp.asarray(HEAD[None], jnp.float32),
            jnp.float32(0.2))
    ok, cost = jax.jit(HS.hand_gates, static_argnums=2)(arms, X, 0, *args)
    one = jax.vmap(lambda x: HS.hand_gates(arms, x, 0, *args))(X)
    np.testing.assert_array_equal(np.asarray(ok), np.asarray(one[0]))
    # the body's gates by hand: within reach of the left shoulder, farther than the neck
    Xn = np.asarray(X, np.float64)
    want = (np.linalg.norm(Xn - SHOULDERS[0], axis=1) <= float(arms.reach[0])) & \
        (np.linalg.norm(Xn - HEAD, axis=1) >= float(arms.near))
    np.testing.assert_array_equal(np.asarray(ok), want)
    assert 0 < want.sum() < len(want)  # the draw tests both outcomes
    np.testing.assert_allclose(np.asarray(cost)[want],
                               np.linalg.norm(Xn - HANDS[0], axis=1)[want] / 0.2, rtol=1e-5)


def test_cloud_prediction_is_the_weighted_mean_of_the_particles_keypoints(setup):
    _, params, arms = setup
    rng = np.random.default_rng(1)
    n, d = 7, len(params.dofs)
    s = rng.uniform(np.asarray(params.prior_lower), np.asarray(params.prior_upper), (n, d))
    s[:, :3] = rng.normal(0, 0.1, (n, 3)) + [0, 0, 0.9]
    s[:, 3:6] = rng.normal(0, 0.2, (n, 3))
    lw = rng.normal(0, 1, n)
    mean, spread = jax.jit(lambda a, b: HS.cloud_prediction(params, arms, a, b))(
        jnp.asarray(s, jnp.float32), jnp.asarray(lw, jnp.float32))
    model = default_body()
    idx = [keypoint_index(model, k)[0] for k in HS.CLOUD_KEYPOINTS]
    kp = np.stack([np.asarray(keypoints(model, params.full_q(jnp.asarray(x, jnp.float32))))
                   [idx] for x in s])
    w = np.exp(lw - lw.max())
    w /= w.sum()
    want = np.einsum("n,nkc->kc", w, kp)
    np.testing.assert_allclose(np.asarray(mean), want, atol=1e-5)
    var = np.einsum("n,nk->k", w, np.sum((kp - want) ** 2, -1))
    np.testing.assert_allclose(np.asarray(spread), np.sqrt(var), atol=1e-5)
    assert np.all(np.asarray(spread)[3:] > 0.01)  # the arms vary over the draw


def test_motion_map_keeps_moving_skin_off_the_shirt():
    rng = np.random.default_rng(2)
    base = np.clip(rng.normal(90, 2, (H, W, 3)), 0, 255).astype(np.uint8)
    frames = np.stack([base.copy() for _ in range(3)])
    for k, x in enumerate((100, 110, 120)):  # a hand moving right over the background
        cv2.rectangle(frames[k], (x, 50), (x + 6, 56), (220, 170, 110), -1)
        cv2.rectangle(frames[k], (x, 150), (x + 6, 156), (220, 170, 110), -1)  # ... on the shirt
    shirt = np.zeros((H, W), bool)
    shirt[140:170, :] = True
    m = HS.motion_map(frames, shirt, 30.0)
    assert m[50:57, 120:127].all()  # the hand where it is now
    assert not m[50:57, 100:107].any()  # not where it was two frames ago (uncovered wall)
    assert not m[:, :].sum() > 49  # nothing else: the noise and the shirt left out


def test_make_params_options():
    cams = stereo_cams()
    p = sp.make_params(cams, motion=sp.Motion(n_particles=10))
    assert p.hand_search is None  # off by default (docs/results/stereo_pf_hands.md)
    p = sp.make_params(cams, motion=sp.Motion(n_particles=10),
                       images=sp.Images(hand_search=True, hand_motion=True))
    assert isinstance(p.hand_search, HS.HandParams) and p.hand_search.motion
    with pytest.raises(InputError, match="hand_search=True"):
        sp.make_params(cams, images=sp.Images(hand_motion=True))
    with pytest.raises(InputError, match="window_m"):
        HS.HandParams(window_m=0.0)
