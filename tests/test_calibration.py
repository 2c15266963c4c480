"""Tests for jaxmocap.calibration: Zhang calibration (through OpenCV) on synthetic checkerboard
images rendered with known cameras must recover them; the renderer must put the corners where
``project`` says."""

import jax
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from jaxmocap.calibration import (
    CalibrationError,
    board_points,
    calibrate_camera,
    calibrate_cameras,
    find_corners,
    render_checkerboard,
)
from jaxmocap.camera import Camera, camera_center, distort_normalized, project

W, H = 640, 480
PATTERN, SQUARE = (9, 6), 0.04  # inner corners (cols, rows), metres
N_VIEWS = 10
BASELINE = 0.2  # metres, camera 1 to the right of camera 0

K0 = np.array([[600.0, 0.0, 322.0], [0.0, 604.0, 238.0], [0.0, 0.0, 1.0]])
K1 = np.array([[585.0, 0.0, 315.0], [0.0, 583.0, 244.0], [0.0, 0.0, 1.0]])
DIST0 = np.array([-0.12, 0.05, 0.001, -0.0008, 0.0])
DIST1 = np.array([-0.08, 0.02, -0.0005, 0.0006, 0.0])


def _rig() -> list[Camera]:
    cam0 = Camera(K0, np.eye(3), np.zeros(3), DIST0, W, H)
    R1 = Rotation.from_rotvec([0.01, 0.14, -0.02]).as_matrix()  # toe-in towards camera 0
    t1 = -R1 @ np.array([BASELINE, 0.0, 0.0])
    return [cam0, Camera(K1, R1, t1, DIST1, W, H)]


def _board_poses(rng, cams, n):
    """Random board -> world poses that every camera sees whole (corners 25 px inside)."""
    obj = board_points(PATTERN, SQUARE)
    centre = obj.mean(0)
    Rs, ts = [], []
    while len(Rs) < n:
        spin = np.pi if len(Rs) == 1 else 0.0  # one upside-down board: order must not flip
        R = Rotation.from_rotvec(rng.uniform(-0.55, 0.55, 3) * [1, 1, 0.3]).as_matrix()
        R = R @ Rotation.from_rotvec([0, 0, spin]).as_matrix()
        c = np.array([rng.uniform(0.02, 0.18), rng.uniform(-0.06, 0.06), rng.uniform(0.6, 0.85)])
        t = c - R @ centre
        X = obj @ R.T + t
        uv = [np.asarray(project(cam, X)) for cam in cams]
        if all(np.all((u > 25) & (u < [W - 25, H - 25])) for u in uv):
            Rs.append(R)
            ts.append(t)
    return np.array(Rs), np.array(ts)


@pytest.fixture(scope="module")
def scene():
    rng = np.random.default_rng(1)
    cams = _rig()
    Rs, ts = _board_poses(rng, cams, N_VIEWS)
    images = [list(np.asarray(render_checkerboard(c, PATTERN, SQUARE, Rs, ts))) for c in cams]
    return cams, Rs, ts, images


def test_rendered_corners_are_where_project_puts_them(scene):
    cams, Rs, ts, images = scene
    obj = board_points(PATTERN, SQUARE)
    assert images[0][0].shape == (H, W, 3) and images[0][0].dtype == np.uint8
    for c, cam in enumerate(cams):
        for v in (0, 1, 2):  # view 1 is the upside-down board
            found = find_corners(images[c][v], PATTERN)
            assert found is not None
            truth = np.asarray(project(cam, obj @ Rs[v].T + ts[v]))
            err = np.linalg.norm(found - truth, axis=-1)
            # residual = sub-pixel detection + 3x3-supersampling aliasing (falls with more)
            assert err.max() < 0.4 and err.mean() < 0.15, (c, v, err.max(), err.mean())
    # a pose whose plane is behind the camera renders pure background
    behind = render_checkerboard(cams[0], PATTERN, SQUARE, np.eye(3), np.array([0, 0, -1.0]))
    assert np.unique(np.asarray(behind)).size == 1


def test_calibrate_one_camera(scene):
    cams, _, _, images = scene
    res = calibrate_camera(images[0], PATTERN, SQUARE)
    K = np.asarray(res.camera.K)
    assert res.used == list(range(N_VIEWS))
    np.testing.assert_allclose(np.diag(K)[:2], np.diag(K0)[:2], rtol=0.005)
    np.testing.assert_allclose(K[:2, 2], K0[:2, 2], atol=3.0)
    assert res.rms < 0.2
    # the lens distortion (k1..k3 trade off; compare its effect) within 0.5 px over the view
    xy = np.stack(np.meshgrid(np.linspace(-0.4, 0.4, 9), np.linspace(-0.3, 0.3, 7)), -1)
    true_cam = scene[0][0]
    shift = distort_normalized(res.camera, xy) - distort_normalized(true_cam, xy)
    assert np.abs(np.asarray(shift)).max() * K0[0, 0] < 0.5
    assert (res.camera.width, res.camera.height) == (W, H)


def test_calibrate_stereo_rig(scene):
    cams, Rs, ts, images = scene
    rig = calibrate_cameras(images, PATTERN, SQUARE)
    for est, true in zip(rig.cameras, cams, strict=True):
        np.testing.assert_allclose(np.diag(np.asarray(est.K))[:2], np.diag(true.K)[:2], rtol=0.005)
    np.testing.assert_allclose(np.asarray(rig.cameras[0].R), np.eye(3), atol=1e-12)
    baseline = np.linalg.norm(camera_center(rig.cameras[1]))
    assert abs(baseline - BASELINE) < 0.01 * BASELINE
    R_err = Rotation.from_matrix(np.asarray(rig.cameras[1].R) @ np.asarray(cams[1].R).T)
    assert np.degrees(R_err.magnitude()) < 0.2
    assert max(rig.rms) < 0.2 and rig.stereo_rms[1] < 0.3

    # world at the board of the first instant: the board's corners land where they were seen
    rig_b = calibrate_cameras(images, PATTERN, SQUARE, world="board")
    obj = board_points(PATTERN, SQUARE)
    for c, cam in enumerate(rig_b.cameras):
        truth = np.asarray(project(cams[c], obj @ Rs[0].T + ts[0]))
        np.testing.assert_allclose(np.asarray(project(cam, obj)), truth, atol=0.5)
    # jit-able cameras: the stacked result projects the same
    uv = jax.jit(project)(rig_b.cameras[1], obj)
    np.testing.assert_allclose(uv, project(rig_b.cameras[1], obj), atol=1e-9)


def test_calibration_errors(scene):
    _, _, _, images = scene
    blank = [np.full((H, W, 3), 110, np.uint8)] * 4
    with pytest.raises(CalibrationError, match=r"found in 0 of 4 images, need at least 3"):
        calibrate_camera(blank, PATTERN, SQUARE, name="left")
    with pytest.raises(CalibrationError, match=r"left: .*9x6 inner corners"):
        calibrate_camera(blank, PATTERN, SQUARE, name="left")
    with pytest.raises(CalibrationError, match=r"found in 2 of 2"):  # too few views
        calibrate_camera(images[0][:2], PATTERN, SQUARE)
    with pytest.raises(CalibrationError, match="different numbers of images"):
        calibrate_cameras([images[0], images[1][:5]], PATTERN, SQUARE)
    # the second camera sees the board in only 3 of the instants camera 0 saw it
    second = images[1][:3] + blank[:1] * (N_VIEWS - 3)
    with pytest.raises(CalibrationError, match=r"cam1: the board was seen together"):
        calibrate_cameras([images[0], second], PATTERN, SQUARE, min_shared_views=4)
    with pytest.raises(CalibrationError, match="uint8"):
        calibrate_camera([np.zeros((H, W), np.float32)] * 3, PATTERN, SQUARE)
