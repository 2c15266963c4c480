"""Tests for jaxmocap.pf.colors (the capture's skin and shirt colours of the stereo particle
filter) and the blob tracker's plausibility gate (``blobs.update(reach=...)``).

Scenes are drawn with OpenCV: a shirt-coloured torso rectangle, a skin-coloured head disc on
top of it, a skin-coloured "prop" disc far from the torso and a background of wall colour; the
drawn geometry is the oracle of the masks. Lamp changes are von Kries channel gains applied to
the whole image (a white balance change of the camera or the lamp's colour).
"""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest
from test_blobs import RADII, render, stereo_cams

from jaxmocap import blobs as B
from jaxmocap import segment as S
from jaxmocap.errors import InputError
from jaxmocap.pf import colors as PC

W, H = 160, 120
SKIN_RGB = (200, 150, 120)
SHIRT_RGB = (40, 70, 190)
WALL_RGB = (120, 110, 100)
HEAD = (80, 30, 12)  # u, v, r
TORSO = (60, 44, 100, 110)  # x0, y0, x1, y1
PROP = (12, 100, 7)


def scene(rng, gains=(1.0, 1.0, 1.0), prop_rgb=SKIN_RGB):
    img = np.zeros((H, W, 3), np.float64) + WALL_RGB
    img += np.linspace(-15, 15, W)[None, :, None]  # a gradient across the wall
    x0, y0, x1, y1 = TORSO
    cv2.rectangle(img, (x0, y0), (x1, y1), SHIRT_RGB, -1)
    cv2.circle(img, HEAD[:2], HEAD[2], SKIN_RGB, -1)
    cv2.circle(img, PROP[:2], PROP[2], prop_rgb, -1)
    img = img * np.asarray(gains) + rng.normal(0, 2.0, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def truth():
    yy, xx = np.mgrid[:H, :W]
    head = (xx - HEAD[0]) ** 2 + (yy - HEAD[1]) ** 2 <= HEAD[2] ** 2
    prop = (xx - PROP[0]) ** 2 + (yy - PROP[1]) ** 2 <= PROP[2] ** 2
    x0, y0, x1, y1 = TORSO
    torso = (xx >= x0) & (xx <= x1) & (yy >= y0) & (yy <= y1) & ~head
    return head, prop, torso


def scribbles():
    """A user's strokes: a small disc on the face, a stroke across the shirt."""
    yy, xx = np.mgrid[:H, :W]
    skin = (xx - HEAD[0]) ** 2 + (yy - HEAD[1]) ** 2 <= 4**2
    shirt = (np.abs(yy - 80) <= 2) & (xx > 65) & (xx < 95)
    return skin, shirt


def fitted(rng):
    skin, shirt = scribbles()
    return PC.fit_capture_colors([scene(rng)], [skin], [shirt])


def test_features_are_invariant_to_channel_gains(rng):
    img = scene(rng)
    a = PC.features(img)
    b = PC.features(np.clip(img * np.array([0.7, 0.85, 1.2]), 0, 255).astype(np.uint8))
    # chromaticity of the balanced image: unchanged up to uint8 rounding
    assert np.percentile(np.abs(a[..., :2] - b[..., :2]), 99) < 0.01
    assert np.percentile(np.abs(a[..., 2] - b[..., 2]), 99) < 0.05


@pytest.mark.parametrize("gains", [(1.0, 1.0, 1.0), (1.25, 1.0, 0.7), (0.6, 0.7, 0.95)])
def test_masks_find_head_and_shirt_not_the_far_prop(rng, gains):
    colors = fitted(rng)
    skin, shirt = PC.masks(colors, scene(rng, gains))
    head, prop, torso = truth()
    inner = cv2.erode(head.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert skin[inner].mean() > 0.95  # the face, under another lamp too
    assert not skin[prop].any()  # same colour, but away from the shirt: not a blob
    assert skin[~head].mean() < 0.002
    inner_t = cv2.erode(torso.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert shirt[inner_t].mean() > 0.95 and shirt[~torso].mean() < 0.01


def test_fixed_hsv_interval_fails_where_the_model_does_not(rng):
    """The premise of issue 18: a warm lamp puts the wall into Azad's fixed skin interval."""
    img = scene(rng, (1.3, 1.0, 0.6))
    hsv_skin = S.segment_cv(S.SegmentParams(), img).skin
    head, prop, torso = truth()
    assert hsv_skin[~(head | prop | torso)].mean() > 0.5  # the wall is "skin"
    skin, _ = PC.masks(fitted(rng), img)
    assert skin[~(head | prop | torso)].mean() < 0.002


def test_background_histogram_rejects_skin_coloured_wall_near_the_shirt(rng):
    """A wall of skin-like chromaticity beside the torso passes the skin Gaussian, but it is
    the background's colour, learned from the frame far from the shirt."""
    skin_s, shirt_s = scribbles()
    img = scene(rng)
    wall_like = np.clip(np.asarray(SKIN_RGB) * 0.8, 0, 255)  # same chromaticity, dimmer
    img2 = img.copy()
    img2[:, :40] = wall_like + rng.normal(0, 2.0, img2[:, :40].shape)
    img2[:, 110:] = wall_like + rng.normal(0, 2.0, img2[:, 110:].shape)
    img2 = np.clip(img2, 0, 255).astype(np.uint8)
    c = PC.fit_capture_colors([img2], [skin_s], [shirt_s])
    no_bg = PC.CaptureColors(c.skin, c.shirt, None)
    s_bg, _ = PC.masks(c, img2)
    s_nobg, _ = PC.masks(no_bg, img2)
    band = np.zeros((H, W), bool)
    band[:, 110:125] = True  # within near_px of the torso, right of it
    assert s_nobg[band].mean() > 0.5  # the Gaussian alone takes the wall
    assert s_bg[band].mean() < 0.02
    head, _, _ = truth()
    inner = cv2.erode(head.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert s_bg[inner].mean() > 0.9


def test_save_load_round_trip_and_errors(rng, tmp_path):
    c = fitted(rng)
    p = PC.save_capture_colors(tmp_path / "pf_colors.json", c)
    d = PC.load_capture_colors(p)
    for name in ("skin", "shirt"):
        np.testing.assert_allclose(np.asarray(getattr(d, name).mean),
                                   np.asarray(getattr(c, name).mean), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(d.background), np.asarray(c.background), atol=1e-4)
    img = scene(rng)
    for a, b in zip(PC.masks(c, img), PC.masks(d, img), strict=True):
        assert (a != b).mean() < 1e-3
    bad = tmp_path / "bad.json"
    bad.write_text('{"format": "jaxmocap.pf_colors", "skin": {"mean": [1, 2], "cov": []}}')
    with pytest.raises(InputError, match="bad.json: field 'skin'"):
        PC.load_capture_colors(bad)
    with pytest.raises(InputError, match="no such file"):
        PC.load_capture_colors(tmp_path / "missing.json")
    with pytest.raises(InputError, match="expected >= 10 labelled pixels"):
        PC.fit_capture_colors([img], [np.zeros((H, W), bool)], [scribbles()[1]])


def test_reach_drops_a_distant_skin_candidate(rng):
    """A skin-coloured ball 1 m from the head, seen in both views, is triangulated as a
    candidate; with the arm's reach as the gate it never becomes a hand."""
    cams = stereo_cams()
    centres = np.array([[0.0, 0.0, 1.6], [0.0, 0.3, 1.2], [0.0, -0.3, 1.2]])
    ball = np.array([[0.3, 0.5, 0.75]])  # on a table beside the subject, nearer the cameras
    pts_all = np.concatenate([centres, ball])
    radii = np.concatenate([RADII, [0.09]])
    masks = [S.segment_cv(S.SegmentParams(), render(c, pts_all, radii, rng)).skin for c in cams]
    # without the gate the ball is a candidate; with the ball the biggest, it takes a hand
    state, _, _ = B.update(B.init(), *masks, cams)
    assert np.min(np.linalg.norm(state.candidates - ball, axis=1)) < 0.05
    for reach in (None, 0.9):
        state, pts, valid = B.update(B.init(), *masks, cams, reach=reach)
        d = np.linalg.norm(pts[valid] - ball, axis=1)
        if reach is None:
            assert np.any(d < 0.05)  # Azad's tracker: the ball is a "hand"
        else:
            assert np.all(valid) and np.all(d > 0.5)
            np.testing.assert_allclose(pts, centres, atol=0.05)


def test_calibration_from_moving_frames_without_labels(rng):
    """No scribbles: the subject (shirt torso with the head on top) sways over a static room
    with a skin-coloured and a shirt-coloured prop; the calibration finds the shirt from the
    motion and the face above it, and the masks of a later frame match the drawn geometry."""
    frames, truths = [], []
    for t in range(12):
        dx = int(round(10 * np.sin(t / 2.0)))
        img = np.zeros((H, W, 3), np.float64) + WALL_RGB
        img += np.linspace(-15, 15, W)[None, :, None]
        x0, y0, x1, y1 = TORSO
        cv2.rectangle(img, (x0 + dx, y0), (x1 + dx, y1), SHIRT_RGB, -1)
        cv2.circle(img, (HEAD[0] + dx, HEAD[1]), HEAD[2], SKIN_RGB, -1)
        cv2.circle(img, PROP[:2], PROP[2], SKIN_RGB, -1)
        cv2.circle(img, (145, 20), 8, SHIRT_RGB, -1)  # a static prop of the shirt's colour
        frames.append(np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8))
        yy, xx = np.mgrid[:H, :W]
        truths.append((xx - HEAD[0] - dx) ** 2 + (yy - HEAD[1]) ** 2 <= HEAD[2] ** 2)
    colors = PC.calibrate_from_frames(frames)
    np.testing.assert_allclose(np.asarray(colors.shirt.mean)[:2],
                               PC.features(frames[0])[80, 80, :2], atol=0.01)
    face = PC.features(frames[0])[truths[0]][:, :2].mean(0)
    np.testing.assert_allclose(np.asarray(colors.skin.mean)[:2], face, atol=0.015)
    skin, shirt = PC.masks(colors, frames[-1])
    head = truths[-1]
    inner = cv2.erode(head.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    outer = cv2.dilate(head.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    assert skin[inner].mean() > 0.9 and skin[~outer].mean() < 0.002  # (blurred border)
    _, prop, _ = truth()
    assert not skin[prop].any()


def test_calibration_refuses_a_static_capture(rng):
    frames = [scene(rng) for _ in range(6)]
    with pytest.raises(InputError, match="move over the calibration frames"):
        PC.calibrate_from_frames(frames)


def test_reach_starts_on_the_head_and_acquires_a_hand_seen_later(rng):
    """With the gate the tracker starts on head + one hand; the other hand, never seen
    before, is acquired on its side of the head when it appears (Azad's tracker needs three
    candidates to start and re-acquires only near a last sighting)."""
    cams = stereo_cams()
    centres = np.array([[0.0, 0.0, 1.6], [0.0, 0.3, 1.2], [0.0, -0.3, 1.2]])

    def masks(pts, radii):
        return [S.segment_cv(S.SegmentParams(), render(c, pts, radii, rng)).skin for c in cams]

    state = B.init()
    state, _, valid = B.update(state, *masks(centres[:2], RADII[:2]), cams, reach=(0.2, 0.9))
    np.testing.assert_array_equal(valid, [True, True, False])
    state, pts, valid = B.update(state, *masks(centres, RADII), cams, reach=(0.2, 0.9))
    assert valid.all()
    np.testing.assert_allclose(pts, centres, atol=0.05)
    azad = B.update(B.init(), *masks(centres[:2], RADII[:2]), cams)
    assert not azad[2].any()  # two candidates: Azad's tracker does not start


def test_hand_reach_by_roles_on_a_renamed_and_a_scaled_body():
    """The reach comes from keypoint roles, not link names: a mixamo-renamed body has the
    bundled body's reach; one with 10% longer arms reaches farther, by the NumPy sum of its
    keypoint distances (the oracle) x the margin."""
    from jaxmocap.body import default_body, keypoints
    from jaxmocap.body.scale import measure, rename_body, scale_body
    from jaxmocap.trackers import stereo_pf as sp

    base = default_body()
    near, far = sp.hand_reach(base)
    renamed = rename_body(base, "mixamo")
    assert renamed.chain.link_names != base.chain.link_names
    np.testing.assert_allclose(sp.hand_reach(renamed), (near, far), rtol=1e-6)
    ref = measure(base)
    long = scale_body(base, upper_arm=1.1 * ref["upper_arm"], forearm=1.1 * ref["forearm"])
    long = getattr(long, "model", long)
    names = list(long.keypoint_names)
    kp = np.asarray(keypoints(long, jnp.zeros(long.n_dof)), np.float64)
    chain = [names.index(k) for k in ("head", "l_shoulder", "l_elbow", "l_wrist", "l_hand")]
    expect = sp.REACH_MARGIN * np.sum(np.linalg.norm(np.diff(kp[chain], axis=0), axis=1))
    assert sp.hand_reach(long)[1] == pytest.approx(expect, rel=1e-6) and expect > far


def test_adapt_class_is_the_moment_matched_mixture(rng):
    """Oracle: adapting the class of sample A with sample B at weight |B| / (|A| + |B|) gives
    the Gaussian of A and B pooled (mean, covariance up to the 1/(n-1) of np.cov)."""
    a = rng.normal([0.35, 0.33, 5.0], [0.01, 0.02, 0.2], (4000, 3))
    b = rng.normal([0.40, 0.31, 4.6], [0.02, 0.01, 0.1], (2000, 3))
    zero = (0.0, 0.0, 0.0)
    ca = PC.fit_class(a, zero)
    mixed = PC.adapt_class(ca, b, len(b) / (len(a) + len(b)), zero)
    pooled = PC.fit_class(np.concatenate([a, b]), zero)
    np.testing.assert_allclose(np.asarray(mixed.mean), np.asarray(pooled.mean), atol=1e-12)
    np.testing.assert_allclose(np.asarray(mixed.cov), np.asarray(pooled.cov), rtol=2e-3,
                               atol=1e-9)
    same = PC.adapt_class(ca, b, 0.0, zero)  # rate 0: unchanged
    np.testing.assert_array_equal(np.asarray(same.mean), np.asarray(ca.mean))


def shifted_scene(rng, skin_rgb):
    """The scene with the face in another colour (a lamp on the face only: grey-world balance
    does not absorb it)."""
    img = np.zeros((H, W, 3), np.float64) + WALL_RGB
    img += np.linspace(-15, 15, W)[None, :, None]
    x0, y0, x1, y1 = TORSO
    cv2.rectangle(img, (x0, y0), (x1, y1), SHIRT_RGB, -1)
    cv2.circle(img, HEAD[:2], HEAD[2], tuple(float(c) for c in skin_rgb), -1)
    cv2.circle(img, PROP[:2], PROP[2], SKIN_RGB, -1)
    return np.clip(img + rng.normal(0, 2.0, img.shape), 0, 255).astype(np.uint8)


def test_adaptation_follows_a_face_whose_colour_changes(rng):
    """The face turns from SKIN_RGB to a dimmer, redder colour over 20 frames (the dev split's
    face under a spot lamp: r +0.07, log brightness -0.6). The fixed model loses it; the
    model adapted each frame from the head's pixels keeps it, and the wall and the far prop
    stay rejected. An occluder of the wall's colour in front of the head is not learned."""
    fixed = fitted(rng)
    head, prop, torso = truth()
    inner = cv2.erode(head.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    yy, xx = np.mgrid[:H, :W]
    head_region = (xx - HEAD[0]) ** 2 + (yy - HEAD[1]) ** 2 <= (HEAD[2] - 2) ** 2
    x0, y0, x1, y1 = TORSO
    body = (xx >= x0 - 4) & (xx <= x1 + 4) & (yy >= HEAD[1] - HEAD[2] - 4) & (yy <= y1 + 4)
    end = np.array([190.0, 105.0, 70.0])  # redder and ~0.5 darker in log brightness
    img = shifted_scene(rng, end)
    f = PC.features(img)
    assert np.median(fixed.skin.mahalanobis_sq(f[inner])) > 30  # far outside the fixed class
    s_fixed, _ = PC.masks(fixed, img)
    assert s_fixed[inner].mean() < 0.2  # the fixed model lost the face
    frames = [shifted_scene(rng, np.asarray(SKIN_RGB) + (end - np.asarray(SKIN_RGB)) * k / 20)
              for k in range(1, 21)]
    for spread in (None, 1.0):  # free covariance; covariance never wider than the fitted one
        colors, used = fixed, []
        for frame in frames:
            colors, n_sk, n_sh = PC.adapt_capture_colors(
                colors, [frame], [head_region], [body], rate=0.3, shirt_rate=0.3,
                reference=spread and fixed, max_spread=spread or 1.0)  # time constant ~3 frames
            used.append((n_sk, n_sh))
        assert all(n_sk > 0 and n_sh > 0 for n_sk, n_sh in used)
        s_adapt, sh_adapt = PC.masks(colors, img)
        assert s_adapt[inner].mean() > 0.95  # the adapted one has the face
        assert not s_adapt[prop].any() and s_adapt[~head].mean() < 0.002
        inner_t = cv2.erode(torso.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        assert sh_adapt[inner_t].mean() > 0.95 and sh_adapt[~torso].mean() < 0.01
        if spread:  # the cap: no direction wider than the fitted class's
            li = np.linalg.inv(np.linalg.cholesky(np.asarray(fixed.skin.cov)))
            w = np.linalg.eigvalsh(li @ np.asarray(colors.skin.cov) @ li.T)
            assert w.max() <= 1.0 + 1e-9
    # an occluder of the wall's colour covering the head: no candidate passes the guards
    occluded = shifted_scene(rng, WALL_RGB)
    after, n_sk, _ = PC.adapt_capture_colors(colors, [occluded], [head_region], None)
    assert n_sk == 0
    np.testing.assert_array_equal(np.asarray(after.skin.mean), np.asarray(colors.skin.mean))


def _near_a_boundary(colors, img, rel=1e-4):
    """Pixels whose direct (float64) distances lie within ``rel`` of a decision boundary, or
    with a feature within ``rel`` bins of a background-histogram bin edge."""
    f = PC.features(img)
    d_skin, d_shirt = colors.skin.mahalanobis_sq(f), colors.shirt.mahalanobis_sq(f)
    near = np.abs(d_skin - colors.skin_threshold) < rel * colors.skin_threshold
    near |= np.abs(d_shirt - colors.shirt_threshold) < rel * colors.shirt_threshold
    near |= np.abs(d_skin - d_shirt) < rel * np.maximum(d_skin, 1.0)
    if colors.background is not None:
        lr = PC._skin_log_ratio(colors, f, d_skin) - colors.skin_log_ratio
        near |= np.abs(lr) < rel * np.maximum(np.abs(-0.5 * d_skin), 1.0)
        for k in range(3):
            lo, hi, n = PC.HIST_LOW[k], PC.HIST_HIGH[k], PC.HIST_BINS[k]
            u = (f[..., k].astype(np.float64) - lo) / (hi - lo) * n
            near |= np.abs(u - np.round(u)) < rel
    return near


@pytest.mark.parametrize("gains", [(1.0, 1.0, 1.0), (1.25, 1.0, 0.7), (0.6, 0.7, 0.95)])
def test_compiled_masks_agree_with_the_direct_evaluation(rng, gains):
    """The fused XLA evaluation (float32) against the NumPy one (float64 distances), with and
    without the background histogram, on a skin-coloured wall beside the torso (where the
    histogram decides) under three lamps: the same maps except for pixels within rounding of
    a threshold."""
    skin_s, shirt_s = scribbles()
    base = scene(rng)
    base[:, 110:] = np.clip(np.asarray(SKIN_RGB) * 0.8 + rng.normal(0, 6.0, base[:, 110:].shape),
                            0, 255)  # fmt: skip
    c = PC.fit_capture_colors([base], [skin_s], [shirt_s])
    img = np.clip(base * np.asarray(gains), 0, 255).astype(np.uint8)
    for colors in (c, PC.CaptureColors(c.skin, c.shirt, None)):
        direct = PC.masks(colors, img, compiled=False)
        fast = PC.masks(colors, img)
        assert direct[0].any() and direct[1].any() and (~direct[0]).any()
        near = _near_a_boundary(colors, img)
        for a, b in zip(direct, fast, strict=True):
            assert a.dtype == b.dtype == bool and a.shape == b.shape == (H, W)
            assert not np.any((a != b) & ~near)
            assert (a != b).mean() < 1e-3
    with pytest.raises(InputError, match="uint8"):
        PC.masks(c, img.astype(np.float32))


def test_compiled_masks_on_the_side_device_equal_the_default_device(rng, monkeypatch):
    """The fused maps run on the second CPU device (conftest enables it, as the CLI does; live
    loops keep them off the filter step's device) and give the same maps as on the default
    device."""
    from jaxmocap._config import side_device

    assert side_device() is not None
    skin_s, shirt_s = scribbles()
    base = scene(rng)
    c = PC.fit_capture_colors([base], [skin_s], [shirt_s])
    img = np.clip(base * np.asarray((1.1, 1.0, 0.8)), 0, 255).astype(np.uint8)
    side = PC.masks(c, img)
    monkeypatch.setattr(PC, "side_device", lambda: None)
    one = PC.masks(c, img)
    assert side[0].any() and side[1].any()
    for a, b in zip(side, one, strict=True):
        np.testing.assert_array_equal(a, b)
