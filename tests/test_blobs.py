"""Tests for jaxmocap.blobs: skin blobs, stereo matching, triangulation and tracking of head /
left hand / right hand on synthetic stereo sequences with known 3D trajectories.

Scene: two look_at cameras 11 cm apart (Azad §V), 320x240, f = 300 px, 2.2 m from a subject
who faces them (+x). Head and hands are skin-coloured spheres drawn (painter's order, sub-pixel
cv2.circle) at their projections; the skin masks come from the OpenCV image pipeline.

Accuracy bound from pixel quantisation: the centroid of a digitised disc of radius >= 4 px is
within ~0.1 px of its centre, so the disparity error is <= ~0.2 px; with Z ~ 2.2 m, f = 300 px,
b = 0.11 m the depth error is dZ = Z^2 / (f b) dd ~ 0.147 m/px * 0.2 px ~ 3 cm, the lateral
error Z / f * 0.1 px ~ 1 mm. We assert 4 cm in 3D and 5 mm across the viewing direction.
"""

import cv2
import numpy as np
import pytest

from jaxmocap import blobs as B
from jaxmocap import camera as C
from jaxmocap import segment as S

W, H, FX, BASELINE = 320, 240, 300.0, 0.11
EYE = np.array([2.2, 0.0, 1.45])
TARGET = np.array([0.0, 0.0, 1.3])
RADII = np.array([0.10, 0.05, 0.05])  # head, left hand, right hand (m)
SKIN = (224, 172, 105)
Z_BOUND, LATERAL_BOUND = 0.04, 0.005


def stereo_cams() -> list[C.Camera]:
    off = np.array([0.0, BASELINE / 2, 0.0])  # camera image-right is world +y here
    return [C.look_at(EYE + s * off, TARGET + s * off, width=W, height=H, fx=FX) for s in (-1, 1)]


def render(cam: C.Camera, centres: np.ndarray, radii: np.ndarray, rng, extra=()) -> np.ndarray:
    """RGB image: grey noisy background, skin spheres (far first), extra discs (u, v, r).

    Projection by the independent oracle cv2.projectPoints."""
    img = np.clip(rng.normal(90, 6, (H, W, 3)), 0, 255).astype(np.uint8)
    R, t, K = (np.asarray(a, np.float64) for a in (cam.R, cam.t, cam.K))
    uv = cv2.projectPoints(centres, cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0][:, 0]
    depth = (centres @ R.T + t)[:, 2]
    sh = 16  # cv2 sub-pixel drawing: coordinates in 1/16 px
    for i in np.argsort(-depth):
        r = FX * radii[i] / depth[i]
        c = tuple(int(round(x * sh)) for x in uv[i])
        cv2.circle(img, c, int(round(r * sh)), SKIN, -1, lineType=cv2.LINE_8, shift=4)
    for u, v, r in extra:
        cv2.circle(img, (u, v), r, SKIN, -1)
    return img


def skin_masks(cams, centres, rng, extra_left=(), extra_right=()):
    params = S.SegmentParams()
    imgs = [
        render(cams[0], centres, RADII, rng, extra_left),
        render(cams[1], centres, RADII, rng, extra_right),
    ]
    return [S.segment_cv(params, im).skin for im in imgs]


def run(cams, trajectory, rng, params=None, **extra):
    state = B.init(params or B.BlobParams())
    out = []
    for centres in trajectory:
        ml, mr = skin_masks(cams, centres, rng, **extra)
        state, pts, valid = B.update(state, ml, mr, cams)
        out.append((state, pts, valid))
    return out


def assert_close(cams, est, true):
    """3D error within the quantisation bound, tighter across the viewing ray."""
    err = est - true
    ray = true - np.asarray(C.camera_center(cams[0]))
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    along = np.sum(err * ray, axis=-1)
    across = np.linalg.norm(err - along[..., None] * ray, axis=-1)
    assert np.all(np.linalg.norm(err, axis=-1) < Z_BOUND), err
    assert np.all(across < LATERAL_BOUND), across


def test_detect_blobs_matches_connected_components(rng):
    mask = np.zeros((H, W), np.uint8)
    cv2.circle(mask, (50, 60), 10, 1, -1)
    cv2.rectangle(mask, (200, 100), (229, 109), 1, -1)  # 30 x 10
    cv2.circle(mask, (150, 200), 2, 1, -1)  # 13 px: below min_area
    b = B.detect_blobs(mask, B.BlobParams(min_area=15))
    assert len(b.area) == 2
    assert b.area[0] > b.area[1]  # largest first
    np.testing.assert_allclose(b.centroid[0], (50, 60), atol=1e-9)  # symmetric disc
    np.testing.assert_allclose(b.centroid[1], (214.5, 104.5), atol=1e-9)
    np.testing.assert_array_equal(b.bbox[1], (200, 100, 30, 10))
    assert b.aspect[1] == pytest.approx(10 / 30)
    assert b.labels[60, 50] == 1 and b.labels[104, 214] == 2 and b.labels[200, 150] == -1
    assert b.area[0] == int(np.sum(b.labels == 1))


def test_detect_blobs_on_the_skin_box_equals_whole_image_labelling(rng):
    """detect_blobs labels only the bounding box of the skin pixels: the same components,
    statistics and label image as OpenCV on the whole image (random masks, blobs touching the
    border included); an empty mask gives no blob."""
    for trial in range(4):
        mask = (rng.random((H, W)) < 0.02).astype(np.uint8)
        mask[:, : 20 * trial] = 0
        for _ in range(5):
            c = (int(rng.integers(0, W)), int(rng.integers(0, H)))
            cv2.circle(mask, c, int(rng.integers(2, 12)), 1, -1)
        b = B.detect_blobs(mask, B.BlobParams(min_area=5, max_blobs=50))
        n, lab, st, ce = cv2.connectedComponentsWithStats(mask, connectivity=8, ltype=cv2.CV_32S)
        big = np.flatnonzero(st[1:, cv2.CC_STAT_AREA] >= 5) + 1
        big = big[np.argsort(-st[big, cv2.CC_STAT_AREA], kind="stable")][:50]
        np.testing.assert_array_equal(b.area, st[big, cv2.CC_STAT_AREA])
        np.testing.assert_allclose(b.centroid, ce[big], atol=1e-9)
        np.testing.assert_array_equal(b.bbox, st[big, :4])
        for i, k in enumerate(big):
            assert np.array_equal(b.labels == i + 1, lab == k)
        assert np.array_equal(b.labels == 0, mask == 0)
    e = B.detect_blobs(np.zeros((H, W), np.uint8))
    assert e.area.shape == (0,) and e.centroid.shape == (0, 2) and not e.labels.any()


def test_static_scene_recovered_and_one_view_false_positives_rejected(rng):
    cams = stereo_cams()
    pose = np.array([[0.0, 0.0, 1.6], [0.15, 0.3, 1.1], [0.1, -0.32, 1.2]])
    traj = [pose + np.array([0.0, 0.01 * k, 0.0]) for k in range(4)]
    # skin-coloured background: a blob in the left image only, another in the right only
    out = run(cams, traj, rng, extra_left=((30, 40, 7),), extra_right=((290, 200, 7),))
    for (state, pts, valid), true in zip(out, traj, strict=True):
        assert valid.all()
        assert np.all(state.status == B.MEASURED)
        assert len(state.candidates) == 3  # the one-view blobs found no partner
        assert_close(cams, pts, true)  # identities: rows are head, left hand, right hand


def test_initial_identities_follow_subject_side():
    cams = stereo_cams()
    pose = np.array([[0.0, 0.0, 1.6], [0.15, 0.3, 1.1], [0.1, -0.32, 1.2]])
    rng = np.random.default_rng(1)
    ml, mr = skin_masks(cams, pose, rng)
    _, pts, _ = B.update(B.init(B.BlobParams(subject_faces_cameras=False)), ml, mr, cams)
    np.testing.assert_allclose(pts[[0, 2, 1]], pose, atol=Z_BOUND)  # hands swapped


def test_hand_merging_with_head_is_predicted_and_reacquired(rng):
    """The right hand passes behind the head (merged / hidden blobs for several frames) and
    comes out on the subject's left: it is carried by the linear motion model and keeps its
    identity; the left hand keeps being measured."""
    cams = stereo_cams()
    n = 14
    t = np.arange(n)
    head = np.tile([0.0, 0.0, 1.6], (n, 1))
    left = np.stack([0.2 + 0.0 * t, 0.35 - 0.005 * t, 1.05 + 0.004 * t], -1)
    right = np.stack([-0.15 + 0.0 * t, -0.36 + 0.07 * t, 1.6 + 0.0 * t], -1)  # behind the head
    traj = np.stack([head, left, right], 1)
    out = run(cams, traj, rng)
    status = np.array([s.status for s, _, _ in out])
    valid = np.array([v for _, _, v in out])
    pts = np.array([p for _, p, _ in out])
    assert valid.all()  # never declared missing: the occlusion is shorter than max_coast
    merged = status[:, 2] == B.PREDICTED
    assert 3 <= merged.sum() <= B.MAX_COAST  # the hand was carried for several frames ...
    assert np.all(status[merged, 0] == B.PREDICTED)  # ... together with the head it merged with
    assert np.all(status[:, 1] == B.MEASURED)
    assert np.all(status[-3:] == B.MEASURED)  # re-acquired
    assert traj[-1, 2, 1] > 0.2  # the right hand ended on the subject's left side ...
    assert_close(cams, pts[~merged], traj[~merged])  # ... and is still the right hand
    # the linear motion model predicts the constant-velocity hand through the merge
    np.testing.assert_allclose(pts[merged], traj[merged], atol=Z_BOUND)


def test_missing_after_max_coast_and_reacquired(rng):
    cams = stereo_cams()
    params = B.BlobParams(max_coast=2)
    pose = np.array([[0.0, 0.0, 1.6], [0.15, 0.3, 1.1], [0.1, -0.32, 1.2]])
    gone = pose.copy()
    gone[1] = [0.15, 3.0, 1.1]  # left hand far outside both images
    traj = [pose] * 2 + [gone] * 4 + [pose + [0.0, 0.0, 0.02]] * 2
    out = run(cams, traj, rng, params)
    status = np.array([s.status[1] for s, _, _ in out])
    np.testing.assert_array_equal(status, [1, 1, 2, 2, 0, 0, 1, 1])
    _, pts, valid = out[4]
    assert not valid[1] and np.all(pts[1] == 0)  # Azad: a missing c_i is the zero vector
    assert valid[[0, 2]].all()
    assert_close(cams, out[-1][1], traj[-1])  # the left hand comes back as the left hand


def test_epipolar_size_and_aspect_gates(rng):
    cams = stereo_cams()
    pose = np.array([[0.0, 0.0, 1.6], [0.15, 0.3, 1.1], [0.1, -0.32, 1.2]])
    ml, mr = skin_masks(cams, pose, rng)
    _, _, valid = B.update(B.init(), ml, mr, cams)
    assert valid.all()
    # shift the right image down by 6 px: every pair violates the epipolar constraint
    state, _, valid = B.update(B.init(), ml, np.roll(mr, 6, axis=0), cams)
    assert not valid.any() and len(state.candidates) == 0
    # every right blob widened by 30 px fails the size and aspect-ratio tests
    wide = cv2.dilate(mr.astype(np.uint8), np.ones((1, 31), np.uint8))
    state, _, _ = B.update(B.init(), ml, wide, cams)
    assert len(state.candidates) == 0


def test_input_validation():
    cams = stereo_cams()
    with pytest.raises(ValueError, match="mask_left"):
        B.update(B.init(), np.zeros((10, 10)), np.zeros((H, W)), cams)
    with pytest.raises(ValueError, match="left, right"):
        B.update(B.init(), np.zeros((H, W)), np.zeros((H, W)), cams[:1])
    with pytest.raises(ValueError, match="min_area_ratio"):
        B.BlobParams(min_area_ratio=1.5)


def test_partly_occluded_blob_is_predicted_not_measured(rng):
    """A hand blob losing half its pixels in both views (partial occlusion) has a biased
    centroid: the tracker carries the hand by its motion model instead (area test)."""
    cams = stereo_cams()
    pose = np.array([[0.0, 0.0, 1.6], [0.15, 0.3, 1.1], [0.1, -0.32, 1.2]])
    traj = [pose + [0.0, 0.0, 0.01 * k] for k in range(4)]
    state = B.init()
    for k, centres in enumerate(traj):
        ml, mr = skin_masks(cams, centres, rng)
        if k == 2:  # hide the left half of the right hand (row 2) in both views
            for mk, cam in zip((ml, mr), cams, strict=True):
                u, v = np.asarray(C.project(cam, centres[2]))
                mk[:, : int(round(u))] &= np.abs(np.arange(H) - v)[:, None] > 12
        state, pts, valid = B.update(state, ml, mr, cams)
        assert valid.all()
        expected = B.PREDICTED if k == 2 else B.MEASURED
        assert state.status[2] == expected and np.all(state.status[:2] == B.MEASURED)
        assert_close(cams, pts, centres)


def test_blob_cut_by_the_image_border_is_not_matched(rng):
    """The right hand moves out of the image (its disc cut by the border in one view, then
    in both): a cut blob's centroid is biased, so it is not triangulated; the hand is carried
    by its motion model, never measured off its true position."""
    cams = stereo_cams()
    head, left = [0.0, 0.0, 1.6], [0.15, 0.3, 1.1]
    # image x runs along world -y: the right hand (subject's right = -y) leaves on the left
    ys = [-0.70, -0.76, -0.82, -0.88, -0.94, -1.05, -1.08, -1.11]  # 3-11 cm per frame
    traj = [np.array([head, left, [0.1, y, 1.2]]) for y in ys]
    out = run(cams, traj, rng)
    disc = FX * RADII[2] / 2.1  # px
    for (state, pts, _), true in zip(out, traj, strict=True):
        u_min = min(float(np.asarray(C.project(c, true[2]))[0]) for c in cams)
        assert np.all(state.status[:2] == B.MEASURED)
        if u_min > disc + 1:  # whole disc inside both images: measured
            assert state.status[2] == B.MEASURED
            assert_close(cams, pts[:2], true[:2])
            assert np.linalg.norm(pts[2] - true[2]) < 0.06  # oblique, 0.4 m off-axis
        else:  # cut by the border in a view: not measured (predicted)
            assert u_min < disc - 1
            assert state.status[2] == B.PREDICTED
    assert sum(s.status[2] == B.PREDICTED for s, _, _ in out) == 3


def test_persistent_blob_size_change_is_accepted(rng):
    """A hand whose blob grows for good (e.g. it nears the cameras) is predicted for
    ``area_patience`` frames, then measured again at its new size."""
    cams = stereo_cams()
    pose = np.array([[0.0, 0.0, 1.6], [0.15, 0.3, 1.1], [0.1, -0.32, 1.2]])
    state = B.init()
    statuses = []
    for k in range(6):
        radii = RADII * ([1.0, 1.0, 1.0] if k < 2 else [1.0, 1.0, 1.5])  # area x 2.25
        imgs = [render(c, pose, radii, rng) for c in cams]
        ml, mr = (S.segment_cv(S.SegmentParams(), im).skin for im in imgs)
        state, pts, valid = B.update(state, ml, mr, cams)
        statuses.append(state.status[2])
        assert valid.all()
    patience = B.BlobParams().area_patience
    assert statuses[:2] == [B.MEASURED] * 2
    assert statuses[2 : 2 + patience] == [B.PREDICTED] * patience
    assert all(s == B.MEASURED for s in statuses[2 + patience :])
    assert_close(cams, pts[:2], pose[:2])
    # the bigger disc (r ~ 11 px) quantises differently: its depth is within 5 cm
    assert np.linalg.norm(pts[2] - pose[2]) < 0.05


def test_report_coast_limits_the_predicted_positions_handed_out(rng):
    """``report_coast`` = 1: the same merge as above, but a hand carried by the motion model is
    handed to the distance cue for one frame only (then zero / invalid, Azad's missing c_i)
    while the tracker keeps it internally and re-acquires it with its identity."""
    cams = stereo_cams()
    n = 14
    t = np.arange(n)
    head = np.tile([0.0, 0.0, 1.6], (n, 1))
    left = np.stack([0.2 + 0.0 * t, 0.35 - 0.005 * t, 1.05 + 0.004 * t], -1)
    right = np.stack([-0.15 + 0.0 * t, -0.36 + 0.07 * t, 1.6 + 0.0 * t], -1)
    traj = np.stack([head, left, right], 1)
    out = run(cams, traj, rng, B.BlobParams(report_coast=1))
    status = np.array([s.status for s, _, _ in out])
    coast = np.array([s.coast for s, _, _ in out])
    valid = np.array([v for _, _, v in out])
    pts = np.array([p for _, p, _ in out])
    predicted = status[:, 2] == B.PREDICTED
    assert predicted.sum() >= 3
    np.testing.assert_array_equal(valid[:, 2], ~predicted | (coast[:, 2] <= 1))
    assert np.all(pts[~valid[:, 2], 2] == 0)
    assert np.all(status[-3:, 2] == B.MEASURED) and valid[-3:].all()  # re-acquired
    with pytest.raises(ValueError, match="report_coast"):
        B.BlobParams(report_coast=-1)
