"""``jaxmocap calibrate``: checkerboard images or videos of 1..N cameras -> ``cameras.json``.

Per camera, OpenCV finds the inner corners and Zhang's method (``cv2.calibrateCamera``, via
:func:`jaxmocap.calibration.calibrate_camera`) gives K, the distortion (k1 k2 p1 p2 k3) and
the board pose in every view. Cameras c > 0 are placed relative to camera 0 by composing the
board poses of the instants both saw (chordal mean of ``R_c<-b R_0<-b^T`` and mean
translation). Then :func:`bundle_adjust` refines everything jointly — all intrinsics and
distortions, the cameras' poses and every board pose — by Levenberg–Marquardt
(``optimistix.least_squares``, float64) on the reprojection error of all detected corners,
starting from these OpenCV estimates. Camera 0 fixes the gauge (its frame is the world unless
``--world board``); the known square size fixes the scale.
"""

from __future__ import annotations

import argparse
import functools
import sys
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxmocap.body import so3_exp
from jaxmocap.calibration import (
    MIN_VIEWS,
    CalibrationError,
    CameraCalibration,
    board_points,
    calibrate_camera,
    find_corners,
)
from jaxmocap.camera import Camera, project
from jaxmocap.errors import InputError
from jaxmocap.io.atomic import check_output_file
from jaxmocap.io.cameras import save_cameras
from jaxmocap.io.preflight import check_outputs, int_range, positive_float
from jaxmocap.io.sync import check_frame_rates
from jaxmocap.io.video import VideoError, open_source, quiet_ffmpeg

__all__ = ["BundleResult", "add_parser", "bundle_adjust", "parse_board", "run"]

BA_MAX_STEPS = 100  # Levenberg-Marquardt iterations of the joint refinement
BA_TOL = 1e-10  # optimistix rtol/atol (float64)
MIN_SQUARE, MAX_SQUARE = 0.002, 1.0  # metres: plausible checkerboard squares
MIN_CHARUCO_CORNERS = 6  # ChArUco corners a view needs (a homography needs 4; margin for noise)

EPILOG = """examples:
  jaxmocap calibrate calib/cam0 calib/cam1 --board 9x6 --square 0.025 --out cameras.json
  jaxmocap calibrate left.mp4 right.mp4 --board 9x6 --square 0.025 --every 10 --world board
  jaxmocap calibrate cam0/ --charuco DICT_4X4_50 --board 7x5 --square 0.04 --marker 0.03

Each input is one camera (a folder of images or a video); image/frame v of every camera must
show the same instant. For a checkerboard --board counts INNER corners (a board of 10x7
squares has 9x6); for a ChArUco board (--charuco) it counts squares.
"""


class BundleResult(NamedTuple):
    """Refined cameras (world = camera 0), RMS reprojection error (pixels) over all corners
    before and after, per camera after, and the optimistix result."""

    cameras: list[Camera]
    board_R: np.ndarray  # (n_instants, 3, 3) board -> world
    board_t: np.ndarray  # (n_instants, 3)
    rms_before: float
    rms_after: float
    rms_per_camera: list[float]
    steps: int
    converged: bool


def parse_board(text: str) -> tuple[int, int]:
    """'9x6' -> (9, 6) inner corners (columns, rows)."""
    try:
        cols, rows = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise InputError(f"--board {text!r}: expected COLSxROWS inner corners, e.g. 9x6") from None
    if cols < 2 or rows < 2:
        raise InputError(f"--board {text!r}: need at least 2x2 inner corners")
    return cols, rows


def _chordal_mean(Rs: list[np.ndarray]) -> np.ndarray:
    u, _, vt = np.linalg.svd(np.sum(Rs, axis=0))
    R = u @ vt
    if np.linalg.det(R) < 0:
        R = u @ np.diag([1.0, 1.0, -1.0]) @ vt
    return R


def _rotvec(R: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(R, np.float64))[0].ravel()


def bundle_adjust(
    cameras: list[Camera],
    detections: list[dict[int, np.ndarray]],
    board_R: np.ndarray,
    board_t: np.ndarray,
    object_points: np.ndarray,
    *,
    fix_k3: bool = False,
    max_steps: int = BA_MAX_STEPS,
) -> BundleResult:
    """Joint refinement of all cameras and board poses (module docstring).

    ``cameras[0]`` must be the world (R = I, t = 0); ``object_points`` (n, 3) the board's
    corners in its frame (metres); ``detections[c][v]`` camera c's corners (n, 2) at instant v
    (``0 <= v < len(board_R)``), NaN where a corner was not detected (ChArUco views of part of
    the board); ``board_R[v], board_t[v]`` the initial board -> world poses. Minimises
    ``sum_{c,v,i} ||pi_c(R_v P_i + t_v) - u_cvi||^2`` over the detected corners, over fx, fy,
    cx, cy, k1..k3, p1, p2 of every camera, (R_c, t_c) of cameras c > 0 and (R_v, t_v) of every
    instant. Rotations are rotation vectors (:func:`so3_exp`).
    """
    with jax.enable_x64(True):
        return _bundle_adjust(cameras, detections, board_R, board_t, object_points, fix_k3,
                              max_steps)


def _unpack(y, k3_fixed, fix_k3: bool):
    """Stacked camera parameters (K, R, t, dist) of the solver's pytree, leading axis =
    cameras; camera 0 is the world (R = I, t = 0)."""
    f64 = y["f_c"].dtype
    dist = y["dist"].at[:, 4].set(k3_fixed) if fix_k3 else y["dist"]
    fx, fy, cx, cy = y["f_c"].T
    zero, one = jnp.zeros_like(fx), jnp.ones_like(fx)
    K = jnp.stack([fx, zero, cx, zero, fy, cy, zero, zero, one], -1).reshape(-1, 3, 3)
    R = jnp.concatenate([jnp.eye(3, dtype=f64)[None], so3_exp(y["cam_r"])])
    t = jnp.concatenate([jnp.zeros((1, 3), f64), y["cam_t"]])
    return K, R, t, dist


def _residuals(y, args, fix_k3: bool):
    """Masked reprojection errors (c, v, p, 2), flattened."""
    obs, mask, P, k3_fixed = args
    K, R, t, dist = _unpack(y, k3_fixed, fix_k3)
    Rb = so3_exp(y["board_r"])  # (v, 3, 3)
    X = jnp.einsum("vij,pj->vpi", Rb, P) + y["board_t"][:, None, :]

    def proj(K, R, t, d):  # width/height do not enter the projection
        return project(Camera(K=K, R=R, t=t, dist=d, width=1, height=1), X)

    r = jax.vmap(proj)(K, R, t, dist) - obs
    return jnp.where(mask[..., None], r, 0.0).reshape(-1)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _solve(y0, args, fix_k3: bool, max_steps: int):
    fn = functools.partial(_residuals, fix_k3=fix_k3)
    sol = optx.least_squares(fn, optx.LevenbergMarquardt(rtol=BA_TOL, atol=BA_TOL), y0, args,
                             max_steps=max_steps, throw=False)
    y = sol.value
    ok = sol.result == optx.RESULTS.successful
    return (fn(y0, args), fn(y, args), _unpack(y, args[3], fix_k3), so3_exp(y["board_r"]),
            y["board_t"], sol.stats["num_steps"], ok)


def _bundle_adjust(cameras, detections, board_R, board_t, object_points, fix_k3, max_steps):
    n_cams, n_views = len(cameras), len(board_R)
    n_pts = len(object_points)
    obs = np.zeros((n_cams, n_views, n_pts, 2))
    mask = np.zeros((n_cams, n_views, n_pts), bool)
    for c, det in enumerate(detections):
        for v, uv in det.items():
            ok = np.isfinite(uv).all(axis=1)
            obs[c, v][ok], mask[c, v] = uv[ok], ok
    obs, maskj = jnp.asarray(obs), jnp.asarray(mask)
    P = jnp.asarray(np.asarray(object_points, np.float64))
    sizes = [(int(c.width), int(c.height)) for c in cameras]
    Ks = [np.asarray(c.K, np.float64) for c in cameras]
    y0 = {
        "f_c": jnp.asarray(np.array([[K[0, 0], K[1, 1], K[0, 2], K[1, 2]] for K in Ks])),
        "dist": jnp.asarray(np.stack([np.asarray(c.dist, np.float64) for c in cameras])),
        "cam_r": jnp.asarray(np.array([_rotvec(np.asarray(c.R)) for c in cameras[1:]])
                             .reshape(-1, 3)),
        "cam_t": jnp.asarray(np.array([np.asarray(c.t, np.float64) for c in cameras[1:]])
                             .reshape(-1, 3)),
        "board_r": jnp.asarray(np.array([_rotvec(R) for R in board_R])),
        "board_t": jnp.asarray(np.asarray(board_t, np.float64)),
    }
    k3_fixed = jnp.asarray(np.array([float(c.dist[4]) for c in cameras]))
    n_obs = float(mask.sum())
    r0, r1, cams, bR, bt, steps, ok = jax.device_get(
        _solve(y0, (obs, maskj, P, k3_fixed), fix_k3, max_steps))
    r0 = np.asarray(r0).reshape(n_cams, n_views, n_pts, 2)
    r1 = np.asarray(r1).reshape(n_cams, n_views, n_pts, 2)
    per_cam = [float(np.sqrt((r1[c] ** 2).sum() / mask[c].sum()))
               for c in range(n_cams)]
    cams = [Camera(K=K, R=R, t=t, dist=d, width=w, height=h)
            for K, R, t, d, (w, h) in zip(*cams, sizes, strict=True)]
    return BundleResult(
        cameras=cams,
        board_R=np.asarray(bR),
        board_t=np.asarray(bt),
        rms_before=float(np.sqrt((r0**2).sum() / n_obs)),
        rms_after=float(np.sqrt((r1**2).sum() / n_obs)),
        rms_per_camera=per_cam,
        steps=int(steps),
        converged=bool(ok),
    )


# ----------------------------------------------------------------------------- reading inputs


def _read_views(specs: list[str], every: int) -> list[list[np.ndarray | None]]:
    """Every ``every``-th frame of each camera's recording (videos at one frame rate)."""
    sources = []
    try:
        for spec in specs:
            sources.append(open_source(spec))
            if sources[-1].live:
                raise VideoError(f"{spec}: calibration needs recorded images or a video, not a "
                                 "live camera index")
        check_frame_rates(sources, "view v of every camera must show the same instant: "
                          "record at one rate")
        views = []
        for src in sources:
            frames = []
            for t in range(src.n_frames):
                try:
                    f = src.read()
                except StopIteration:
                    break
                if t % every == 0:
                    frames.append(f)
            views.append(frames)
    finally:
        for src in sources:
            src.close()
    return views


def _board_hint(frames: list[np.ndarray], pattern: tuple[int, int], name: str, n_found: int,
                need: int) -> str:
    """The refusal for too few detections, with a guess at what to change."""
    cols, rows = pattern
    msg = (f"{name}: found the {cols}x{rows} board in {n_found} of {len(frames)} images "
           f"(need {need}): ")
    sample = [f for f in frames if f is not None][:4]
    for alt in ((cols - 1, rows - 1), (rows, cols), (cols + 1, rows + 1)):
        if min(alt) >= 2 and any(find_corners(f, alt) is not None for f in sample):
            return msg + (f"the images show a board with {alt[0]}x{alt[1]} inner corners: use "
                          f"--board {alt[0]}x{alt[1]} (count inner corners, not squares)")
    return msg + (f"check --board {cols}x{rows} (inner corners, not squares), that the whole "
                  "board is visible, sharp and well lit, and add views at varied angles")


def _calibrate(args) -> tuple[list[Camera], list[str], dict]:
    pattern = parse_board(args.board)
    if not (MIN_SQUARE <= args.square <= MAX_SQUARE):
        raise InputError(f"--square {args.square}: expected the square side in metres "
                         f"({MIN_SQUARE}-{MAX_SQUARE}), e.g. 0.025 for 25 mm")
    if args.every < 1:
        raise InputError(f"--every must be >= 1, got {args.every}")
    names = args.names or [f"cam{i}" for i in range(len(args.inputs))]
    if len(names) != len(args.inputs) or len(set(names)) != len(names):
        raise InputError(f"--names: need {len(args.inputs)} distinct names, got {names}")
    views = _read_views(args.inputs, args.every)
    counts = {len(v) for v in views}
    if len(counts) > 1:
        listing = ", ".join(f"{n} {len(v)}" for n, v in zip(names, views, strict=True))
        raise InputError(f"cameras have different numbers of views ({listing}); view v of every "
                         "camera must show the same instant")
    keep = [v for v in range(len(views[0])) if all(vs[v] is not None for vs in views)]
    dropped = len(views[0]) - len(keep)
    views = [[vs[v] for v in keep] for vs in views]
    charuco = _charuco_board(args, pattern) if args.charuco else None
    calibs = []
    for name, ims in zip(names, views, strict=True):
        if charuco is not None:
            calibs.append(_calibrate_charuco(ims, charuco, name, args))
            continue
        try:
            cal = calibrate_camera(ims, pattern, args.square, min_views=args.min_views,
                                   flags=_flags(args), name=name)
        except CalibrationError as e:
            if "found in" not in str(e):
                raise
            n_found = sum(find_corners(f, pattern) is not None for f in ims)
            raise CalibrationError(_board_hint(ims, pattern, name, n_found, args.min_views)) \
                from None
        calibs.append(cal)
    # cameras c > 0 relative to camera 0 from the instants both saw
    pose = [{v: (_rodrigues(r), np.ravel(t)) for v, r, t in zip(c.used, c.rvecs, c.tvecs,
                                                               strict=True)} for c in calibs]
    cams = [calibs[0].camera]
    rel = [(np.eye(3), np.zeros(3))]
    for c in range(1, len(calibs)):
        shared = [v for v in pose[c] if v in pose[0]]
        if len(shared) < args.min_views:
            raise CalibrationError(f"{names[c]}: the board was seen together with {names[0]} in "
                                   f"{len(shared)} instants (need {args.min_views}): record "
                                   "views where both cameras see the whole board")
        Rs = [pose[c][v][0] @ pose[0][v][0].T for v in shared]
        R = _chordal_mean(Rs)
        t = np.mean([pose[c][v][1] - R @ pose[0][v][1] for v in shared], axis=0)
        rel.append((R, t))
        cams.append(Camera(K=calibs[c].camera.K, R=jnp.asarray(R), t=jnp.asarray(t),
                           dist=calibs[c].camera.dist, width=calibs[c].camera.width,
                           height=calibs[c].camera.height))
    instants = sorted(set().union(*[set(p) for p in pose]))
    index = {v: i for i, v in enumerate(instants)}
    board_R, board_t = [], []
    for v in instants:
        c = next(c for c in range(len(calibs)) if v in pose[c])
        Rcb, tcb = pose[c][v]
        Rc, tc = rel[c]
        board_R.append(Rc.T @ Rcb)
        board_t.append(Rc.T @ (tcb - tc))
    detections = [{index[v]: uv for v, uv in zip(c.used, c.corners, strict=True)} for c in calibs]
    object_points = (board_points(pattern, args.square) if charuco is None
                     else np.asarray(charuco.getChessboardCorners(), np.float64))
    report = {
        "opencv_rms": [c.rms for c in calibs],
        "views_used": [len(c.used) for c in calibs],
        "n_views": len(keep),
        "dropped": dropped,
    }
    if args.no_refine:
        final, bR, bt = cams, np.array(board_R), np.array(board_t)
    else:
        ba = bundle_adjust(cams, detections, np.array(board_R), np.array(board_t),
                           object_points, fix_k3=args.fix_k3)
        final, bR, bt = ba.cameras, ba.board_R, ba.board_t
        report.update(rms_before=ba.rms_before, rms_after=ba.rms_after,
                      rms_per_camera=ba.rms_per_camera, steps=ba.steps, converged=ba.converged)
    if args.world == "board":
        Rw, tw = bR[0], bt[0]  # board of the first used instant -> world
        final = [Camera(K=c.K, R=jnp.asarray(np.asarray(c.R) @ Rw),
                        t=jnp.asarray(np.asarray(c.R) @ tw + np.asarray(c.t)), dist=c.dist,
                        width=c.width, height=c.height) for c in final]
    return final, names, report


def _charuco_board(args, squares: tuple[int, int]):
    """The OpenCV ChArUco board of ``--charuco DICT --board COLSxROWS (squares) --marker``."""
    import cv2

    if not hasattr(cv2, "aruco"):
        raise InputError("--charuco: this OpenCV build has no aruco module")
    name = args.charuco.upper()
    if not name.startswith("DICT_") or not hasattr(cv2.aruco, name):
        raise InputError(f"--charuco {args.charuco!r}: unknown dictionary; expected an OpenCV "
                         "name such as DICT_4X4_50, DICT_5X5_100, DICT_6X6_250")
    if args.marker is None or not 0 < args.marker < args.square:
        raise InputError(f"--marker {args.marker}: ChArUco needs the marker side in metres, "
                         f"smaller than --square {args.square}")
    dictionary = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, name))
    if squares[0] * squares[1] // 2 > dictionary.bytesList.shape[0]:
        raise InputError(f"--charuco {name}: {dictionary.bytesList.shape[0]} markers, too few "
                         f"for a {squares[0]}x{squares[1]}-square board")
    return cv2.aruco.CharucoBoard(squares, args.square, args.marker, dictionary)


def _find_charuco(image: np.ndarray, board) -> np.ndarray | None:
    """ChArUco inner corners (n, 2) pixels in the board's corner order, NaN where not seen;
    None with fewer than ``MIN_CHARUCO_CORNERS``."""
    import cv2

    gray = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY) if image.ndim == 3 else image
    corners, ids, _, _ = cv2.aruco.CharucoDetector(board).detectBoard(gray)
    if ids is None or len(ids) < MIN_CHARUCO_CORNERS:
        return None
    out = np.full((len(board.getChessboardCorners()), 2), np.nan)
    out[ids.ravel()] = corners.reshape(-1, 2)
    return out


def _calibrate_charuco(images: list[np.ndarray], board, name: str, args) -> CameraCalibration:
    """Zhang calibration (``cv2.calibrateCamera``) from the ChArUco corners of each view."""
    import cv2

    if len({im.shape[:2] for im in images}) > 1:
        raise CalibrationError(f"{name}: images have different sizes")
    det = [_find_charuco(im, board) for im in images]
    used = [v for v, d in enumerate(det) if d is not None]
    if len(used) < args.min_views:
        cols, rows = board.getChessboardSize()
        raise CalibrationError(
            f"{name}: found the ChArUco board in {len(used)} of {len(images)} images (need "
            f"{args.min_views}, each with >= {MIN_CHARUCO_CORNERS} corners): check --charuco "
            f"{args.charuco} (dictionary), --board {cols}x{rows} (squares, for ChArUco) and "
            "--marker, and that the board is sharp and well lit")
    obj = np.asarray(board.getChessboardCorners(), np.float32)
    ok = [np.isfinite(det[v]).all(axis=1) for v in used]
    h, w = images[0].shape[:2]
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [obj[m] for m in ok], [det[v][m].astype(np.float32)[:, None] for v, m in
                               zip(used, ok, strict=True)], (w, h), None, None,
        flags=_flags(args))
    dist = np.pad(np.ravel(dist)[:5], (0, max(0, 5 - np.ravel(dist)[:5].size)))
    cam = Camera(K=jnp.asarray(K), R=jnp.eye(3), t=jnp.zeros(3), dist=jnp.asarray(dist),
                 width=w, height=h)
    return CameraCalibration(cam, float(rms), used, [det[v] for v in used], list(rvecs),
                             list(tvecs))


def _rodrigues(rvec) -> np.ndarray:
    import cv2

    return cv2.Rodrigues(np.asarray(rvec, np.float64))[0]


def _flags(args) -> int:
    import cv2

    return cv2.CALIB_FIX_K3 if args.fix_k3 else 0


def add_parser(sub) -> None:
    p = sub.add_parser(
        "calibrate", help="calibrate 1..N cameras from checkerboard images/videos -> cameras.json",
        description="Find the checkerboard in every view of every camera, calibrate each camera "
        "(OpenCV, Zhang), place the cameras relative to the first and refine all of them and "
        "the board poses jointly (bundle adjustment, optimistix Levenberg-Marquardt). Prints "
        "each camera's reprojection error and the joint RMS before/after; writes cameras.json.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("inputs", nargs="+", metavar="INPUT",
                   help="one per camera: a folder of images or a video file")
    p.add_argument("--board", required=True, metavar="COLSxROWS",
                   help="checkerboard: inner corners, e.g. 9x6; ChArUco: squares, e.g. 7x5 "
                   "(required)")
    p.add_argument("--square", type=positive_float, required=True, metavar="METRES",
                   help="side of one square in metres, e.g. 0.025 (required)")
    p.add_argument("--charuco", metavar="DICT",
                   help="the board is a ChArUco board with markers of this OpenCV dictionary "
                   "(e.g. DICT_4X4_50); partly visible boards still count")
    p.add_argument("--marker", type=positive_float, metavar="METRES",
                   help="ChArUco marker side in metres (with --charuco)")
    p.add_argument("--out", default="cameras.json", help="output file (default: %(default)s)")
    p.add_argument("--names", nargs="+", help="camera names (default: cam0 cam1 ...)")
    p.add_argument("--every", type=int_range(1), default=1, metavar="N",
                   help="use every N-th frame of videos/folders (default: %(default)s)")
    p.add_argument("--min-views", type=int_range(MIN_VIEWS, why="Zhang's method needs views of "
                                                 "the board at >= 3 angles"), default=MIN_VIEWS,
                   help="views of the board each camera needs (default: %(default)s)")
    p.add_argument("--world", choices=("camera0", "board"), default="camera0",
                   help="world frame: the first camera's, or the board's in the first view "
                   "(default: %(default)s)")
    p.add_argument("--fix-k3", action="store_true",
                   help="keep k3 = 0 (advised with few or frontal views)")
    p.add_argument("--no-refine", action="store_true",
                   help="skip the joint refinement (keep OpenCV's per-camera estimates)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    quiet_ffmpeg()
    out = check_output_file(args.out)
    check_outputs([out], [s for s in args.inputs if Path(s).exists()])
    cams, names, rep = _calibrate(args)
    for n, rms, used in zip(names, rep["opencv_rms"], rep["views_used"], strict=True):
        print(f"{n}: board found in {used} of {rep['n_views']} views, OpenCV RMS reprojection "
              f"error {rms:.3f} px")
    if "rms_after" in rep:
        per = ", ".join(f"{n} {r:.3f}" for n, r in zip(names, rep["rms_per_camera"], strict=True))
        print(f"joint refinement: RMS {rep['rms_before']:.3f} px -> {rep['rms_after']:.3f} px "
              f"({rep['steps']} steps{'' if rep['converged'] else ', NOT converged'}); "
              f"per camera {per}")
    if rep["dropped"]:
        print(f"note: {rep['dropped']} instants skipped (a camera's frame was unreadable)",
              file=sys.stderr)
    save_cameras(out, cams, names)
    print(f"wrote {Path(out)}")
    return 0
