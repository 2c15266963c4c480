"""`jaxmocap calibrate` on synthetic checkerboard images of a known 2-camera rig: intrinsics
and relative pose recovered, the joint refinement's RMS checked against cv2.projectPoints and
never worse than its OpenCV start; clear refusals of bad boards and inputs."""

import re

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from test_cli import assert_refused, run_cli

from jaxmocap.calibration import board_points, render_checkerboard
from jaxmocap.camera import Camera, project
from jaxmocap.commands.calibrate import bundle_adjust
from jaxmocap.io.cameras import load_cameras

W, H = 200, 150
PATTERN, SQUARE = (5, 4), 0.05
N_VIEWS = 6
K0 = np.array([[190.0, 0, 101], [0, 192, 74], [0, 0, 1]])
K1 = np.array([[185.0, 0, 98], [0, 184, 77], [0, 0, 1]])
D0 = np.array([-0.1, 0.03, 0.0, 0.0, 0.0])
D1 = np.array([-0.05, 0.01, 0.0, 0.0, 0.0])
R1 = Rotation.from_rotvec([0.01, 0.2, -0.02]).as_matrix()
T1 = -R1 @ np.array([0.15, 0.0, 0.0])


@pytest.fixture(scope="module")
def rig(tmp_path_factory):
    cams = [Camera(K0, np.eye(3), np.zeros(3), D0, W, H), Camera(K1, R1, T1, D1, W, H)]
    rng = np.random.default_rng(0)
    obj = board_points(PATTERN, SQUARE)
    Rs, ts = [], []
    while len(Rs) < N_VIEWS:
        R = Rotation.from_rotvec(rng.uniform(-0.5, 0.5, 3) * [1, 1, 0.3]).as_matrix()
        c = np.array([rng.uniform(0.03, 0.12), rng.uniform(-0.04, 0.04), rng.uniform(0.55, 0.7)])
        t = c - R @ obj.mean(0)
        uv = [np.asarray(project(cam, obj @ R.T + t)) for cam in cams]
        if all(np.all((u > 12) & (u < [W - 12, H - 12])) for u in uv):
            Rs.append(R)
            ts.append(t)
    root = tmp_path_factory.mktemp("calib")
    for i, cam in enumerate(cams):
        ims = np.asarray(render_checkerboard(cam, PATTERN, SQUARE, np.array(Rs), np.array(ts)))
        (root / f"cam{i}").mkdir()
        for v, im in enumerate(ims):
            cv2.imwrite(str(root / f"cam{i}" / f"{v:02d}.png"), im[..., ::-1])
    return root, cams


def test_calibrate_two_cameras(rig, tmp_path, capsys):
    root, truth = rig
    out = tmp_path / "cameras.json"
    rc, stdout, err = run_cli(capsys, "calibrate", root / "cam0", root / "cam1", "--board", "5x4",
                              "--square", SQUARE, "--out", out)
    assert rc == 0 and err == [], err
    assert "cam1: board found in 6 of 6 views, OpenCV RMS reprojection error" in stdout
    before, after = map(float, re.search(r"RMS ([\d.]+) px -> ([\d.]+) px", stdout).groups())
    assert after <= before + 1e-9 and after < 0.2
    cams, names = load_cameras(out, dtype=np.float64)
    assert names == ["cam0", "cam1"]
    for cam, ref in zip(cams, truth, strict=True):
        K = np.asarray(cam.K)
        np.testing.assert_allclose(K[[0, 1, 0, 1], [0, 1, 2, 2]],
                                   np.asarray(ref.K)[[0, 1, 0, 1], [0, 1, 2, 2]], rtol=0.03)
    np.testing.assert_allclose(np.asarray(cams[0].R), np.eye(3), atol=1e-12)
    dR = Rotation.from_matrix(np.asarray(cams[1].R) @ R1.T).magnitude()
    assert dR < 0.01  # rad
    np.testing.assert_allclose(np.asarray(cams[1].t), T1, atol=0.006)  # metres (15 cm baseline)


def test_bundle_adjust_rms_matches_opencv_projection(rig):
    """The RMS bundle_adjust reports equals the one recomputed with cv2.projectPoints from
    the cameras and board poses it returns; a perturbed start converges back."""
    root, truth = rig
    from jaxmocap.calibration import find_corners

    det = []
    for i in range(2):
        ims = [cv2.imread(str(p))[..., ::-1] for p in sorted((root / f"cam{i}").iterdir())]
        det.append({v: find_corners(im, PATTERN) for v, im in enumerate(ims)})
    # start: the truth perturbed (focal +3%, baseline +1 cm), board poses by solvePnP in cam0
    obj = board_points(PATTERN, SQUARE)
    bR, bt = [], []
    for v in range(N_VIEWS):
        _, r, t = cv2.solvePnP(obj, det[0][v], K0, D0)
        bR.append(cv2.Rodrigues(r)[0])
        bt.append(t.ravel())
    start = [Camera(K0 * [[1.03], [1.03], [1]], np.eye(3), np.zeros(3), D0, W, H),
             Camera(K1, R1, T1 + [0.01, 0, 0], D1, W, H)]
    res = bundle_adjust(start, det, np.array(bR), np.array(bt), obj)
    assert res.converged and res.rms_after < 0.2 < res.rms_before
    sq = []
    for c, cam in enumerate(res.cameras):
        for v in range(N_VIEWS):
            R = np.asarray(cam.R) @ res.board_R[v]
            t = np.asarray(cam.R) @ res.board_t[v] + np.asarray(cam.t)
            uv, _ = cv2.projectPoints(obj, cv2.Rodrigues(R)[0], t, np.asarray(cam.K),
                                      np.asarray(cam.dist))
            sq.append(((uv.reshape(-1, 2) - det[c][v]) ** 2).sum(-1))
    assert np.sqrt(np.mean(sq)) == pytest.approx(res.rms_after, rel=1e-6)
    assert np.asarray(res.cameras[1].t) == pytest.approx(T1, abs=0.006)


def test_refusals(rig, tmp_path, capsys):
    root, _ = rig
    out = tmp_path / "c.json"
    base = ["--square", SQUARE, "--out", out, "--no-refine"]
    msg = assert_refused(capsys, "cam0: found the 6x5 board in 0 of 6 images (need 3)",
                         "calibrate", root / "cam0", "--board", "6x5", *base, leaves=[out])
    assert "use --board 5x4 (count inner corners, not squares)" in msg
    few = tmp_path / "few"
    few.mkdir()
    for v in range(2):
        (few / f"{v}.png").write_bytes((root / "cam0" / f"0{v}.png").read_bytes())
    assert_refused(capsys, "found the 5x4 board in 2 of 2 images (need 3)", "calibrate", few,
                   "--board", "5x4", *base, leaves=[out])
    assert_refused(capsys, "cameras have different numbers of views (cam0 6, cam1 2)",
                   "calibrate", root / "cam0", few, "--board", "5x4", *base, leaves=[out])
    assert_refused(capsys, "--square 25.0: expected the square side in metres", "calibrate",
                   root / "cam0", "--board", "5x4", "--square", "25", "--out", out, leaves=[out])
    assert_refused(capsys, "--board 'nine': expected COLSxROWS", "calibrate", root / "cam0",
                   "--board", "nine", *base, leaves=[out])
    assert_refused(capsys, "no such video file, frame folder or camera index", "calibrate",
                   tmp_path / "nothing", "--board", "5x4", *base, leaves=[out])
    (tmp_path / "afile").write_text("")
    assert_refused(capsys, "the output folder is a file", "calibrate", root / "cam0", "--board",
                   "5x4", "--square", SQUARE, "--out", tmp_path / "afile" / "c.json")
    assert_refused(capsys, "is a folder", "calibrate", root / "cam0", "--board", "5x4",
                   "--square", SQUARE, "--out", tmp_path)


def test_charuco_partial_views(tmp_path, capsys):
    """A ChArUco board (OpenCV's own image of it) warped into a known pinhole camera, one view
    showing only part of the board: K is recovered."""
    board = cv2.aruco.CharucoBoard((6, 5), 0.04, 0.03,
                                   cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50))
    ppm = 2500.0  # pixels per metre of the generated board image
    flat = board.generateImage((int(6 * 0.04 * ppm), int(5 * 0.04 * ppm)), marginSize=0)
    K = np.array([[300.0, 0, 161], [0, 305.0, 118], [0, 0, 1]])
    rng = np.random.default_rng(5)
    folder = tmp_path / "cam0"
    folder.mkdir()
    for v in range(6):
        R = Rotation.from_rotvec(rng.uniform(-0.45, 0.45, 3) * [1, 1, 0.3]).as_matrix()
        shift = 0.12 if v == 0 else 0.0  # view 0: the board runs off the image's right edge
        t = np.array([shift - 0.12, -0.1, 0.55]) + rng.uniform(-0.02, 0.02, 3)
        Hm = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ np.diag([1 / ppm, 1 / ppm, 1.0])
        img = cv2.warpPerspective(flat, Hm, (320, 240), flags=cv2.INTER_AREA,
                                  borderValue=140)
        cv2.imwrite(str(folder / f"{v}.png"), img)
    out = tmp_path / "cameras.json"
    rc, stdout, err = run_cli(capsys, "calibrate", folder, "--charuco", "DICT_4X4_50", "--board",
                              "6x5", "--square", "0.04", "--marker", "0.03", "--fix-k3", "--out",
                              out)
    assert rc == 0 and err == [], err
    assert "board found in 6 of 6 views" in stdout
    cam = load_cameras(out, dtype=np.float64)[0][0]
    np.testing.assert_allclose(np.asarray(cam.K)[[0, 1, 0, 1], [0, 1, 2, 2]],
                               K[[0, 1, 0, 1], [0, 1, 2, 2]], rtol=0.02)
    assert_refused(capsys, "found the ChArUco board in 0 of 6 images", "calibrate", folder,
                   "--charuco", "DICT_5X5_50", "--board", "6x5", "--square", "0.04", "--marker",
                   "0.03", "--out", tmp_path / "x.json", leaves=[tmp_path / "x.json"])
    assert_refused(capsys, "--charuco 'DICT_NOPE': unknown dictionary", "calibrate", folder,
                   "--charuco", "DICT_NOPE", "--board", "6x5", "--square", "0.04", "--marker",
                   "0.03", "--out", tmp_path / "x.json", leaves=[tmp_path / "x.json"])
