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
    board_points,
    calibrate_camera,
    find_corners,
)
from jaxmocap.camera import Camera, project, save_cameras
from jaxmocap.errors import InputError
from jaxmocap.io.atomic import check_output_file
from jaxmocap.io.video import VideoError, open_source, quiet_ffmpeg

__all__ = ["BundleResult", "add_parser", "bundle_adjust", "parse_board", "run"]

BA_MAX_STEPS = 100  # Levenberg-Marquardt iterations of the joint refinement
BA_TOL = 1e-10  # optimistix rtol/atol (float64)
MIN_SQUARE, MAX_SQUARE = 0.002, 1.0  # metres: plausible checkerboard squares

EPILOG = """examples:
  jaxmocap calibrate calib/cam0 calib/cam1 --board 9x6 --square 0.025 --out cameras.json
  jaxmocap calibrate left.mp4 right.mp4 --board 9x6 --square 0.025 --every 10 --world board

Each input is one camera (a folder of images or a video); image/frame v of every camera must
show the same instant. --board counts INNER corners (a board of 10x7 squares has 9x6).
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
    pattern_size: tuple[int, int],
    square_size: float,
    *,
    fix_k3: bool = False,
    max_steps: int = BA_MAX_STEPS,
) -> BundleResult:
    """Joint refinement of all cameras and board poses (module docstring).

    ``cameras[0]`` must be the world (R = I, t = 0); ``detections[c][v]`` are camera c's
    corners (n, 2) at instant v (``0 <= v < len(board_R)``); ``board_R[v], board_t[v]`` the
    initial board -> world poses. Minimises ``sum_{c,v,i} ||pi_c(R_v P_i + t_v) - u_cvi||^2``
    over fx, fy, cx, cy, k1..k3, p1, p2 of every camera, (R_c, t_c) of cameras c > 0 and
    (R_v, t_v) of every instant. Rotations are rotation vectors (:func:`so3_exp`).
    """
    with jax.enable_x64(True):
        return _bundle_adjust(cameras, detections, board_R, board_t, pattern_size, square_size,
                              fix_k3, max_steps)


def _bundle_adjust(cameras, detections, board_R, board_t, pattern_size, square_size, fix_k3,
                   max_steps):
    f64 = jnp.float64
    n_cams, n_views = len(cameras), len(board_R)
    n_pts = pattern_size[0] * pattern_size[1]
    obs = np.zeros((n_cams, n_views, n_pts, 2))
    mask = np.zeros((n_cams, n_views), bool)
    for c, det in enumerate(detections):
        for v, uv in det.items():
            obs[c, v], mask[c, v] = uv, True
    obs, maskj = jnp.asarray(obs), jnp.asarray(mask)
    P = jnp.asarray(board_points(pattern_size, square_size), f64)
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

    def unpack(y):
        """Stacked camera parameters (K, R, t, dist), leading axis = cameras."""
        dist = y["dist"].at[:, 4].set(k3_fixed) if fix_k3 else y["dist"]
        fx, fy, cx, cy = y["f_c"].T
        zero, one = jnp.zeros_like(fx), jnp.ones_like(fx)
        K = jnp.stack([fx, zero, cx, zero, fy, cy, zero, zero, one], -1).reshape(-1, 3, 3)
        R = jnp.concatenate([jnp.eye(3, dtype=f64)[None], so3_exp(y["cam_r"])])
        t = jnp.concatenate([jnp.zeros((1, 3), f64), y["cam_t"]])
        return K, R, t, dist

    def residuals(y, args):
        obs, maskj = args
        K, R, t, dist = unpack(y)
        Rb = so3_exp(y["board_r"])  # (v, 3, 3)
        X = jnp.einsum("vij,pj->vpi", Rb, P) + y["board_t"][:, None, :]

        def proj(K, R, t, d):  # width/height do not enter the projection
            return project(Camera(K=K, R=R, t=t, dist=d, width=1, height=1), X)

        r = jax.vmap(proj)(K, R, t, dist) - obs  # (c, v, p, 2)
        return jnp.where(maskj[:, :, None, None], r, 0.0).reshape(-1)

    n_obs = float(mask.sum() * n_pts)

    @jax.jit
    def solve(y0, args):
        r0 = residuals(y0, args)
        sol = optx.least_squares(residuals, optx.LevenbergMarquardt(rtol=BA_TOL, atol=BA_TOL),
                                 y0, args, max_steps=max_steps, throw=False)
        y = sol.value
        cams = unpack(y)
        ok = sol.result == optx.RESULTS.successful
        return r0, residuals(y, args), cams, so3_exp(y["board_r"]), y["board_t"], \
            sol.stats["num_steps"], ok

    r0, r1, cams, bR, bt, steps, ok = jax.device_get(solve(y0, (obs, maskj)))
    r0 = np.asarray(r0).reshape(n_cams, n_views, n_pts, 2)
    r1 = np.asarray(r1).reshape(n_cams, n_views, n_pts, 2)
    per_cam = [float(np.sqrt((r1[c] ** 2).sum() / (mask[c].sum() * n_pts)))
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


def _read_views(spec: str, every: int) -> list[np.ndarray | None]:
    src = open_source(spec)
    if src.live:
        src.close()
        raise VideoError(f"{spec}: calibration needs recorded images or a video, not a live "
                         "camera index")
    frames = []
    try:
        for t in range(src.n_frames):
            try:
                f = src.read()
            except StopIteration:
                break
            if t % every == 0:
                frames.append(f)
    finally:
        src.close()
    return frames


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
    views = [_read_views(s, args.every) for s in args.inputs]
    counts = {len(v) for v in views}
    if len(counts) > 1:
        listing = ", ".join(f"{n} {len(v)}" for n, v in zip(names, views, strict=True))
        raise InputError(f"cameras have different numbers of views ({listing}); view v of every "
                         "camera must show the same instant")
    keep = [v for v in range(len(views[0])) if all(vs[v] is not None for vs in views)]
    dropped = len(views[0]) - len(keep)
    views = [[vs[v] for v in keep] for vs in views]
    calibs = []
    for name, ims in zip(names, views, strict=True):
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
    report = {
        "opencv_rms": [c.rms for c in calibs],
        "views_used": [len(c.used) for c in calibs],
        "n_views": len(keep),
        "dropped": dropped,
    }
    if args.no_refine:
        final, bR, bt = cams, np.array(board_R), np.array(board_t)
    else:
        ba = bundle_adjust(cams, detections, np.array(board_R), np.array(board_t), pattern,
                           args.square, fix_k3=args.fix_k3)
        final, bR, bt = ba.cameras, ba.board_R, ba.board_t
        report.update(rms_before=ba.rms_before, rms_after=ba.rms_after,
                      rms_per_camera=ba.rms_per_camera, steps=ba.steps, converged=ba.converged)
    if args.world == "board":
        Rw, tw = bR[0], bt[0]  # board of the first used instant -> world
        final = [Camera(K=c.K, R=jnp.asarray(np.asarray(c.R) @ Rw),
                        t=jnp.asarray(np.asarray(c.R) @ tw + np.asarray(c.t)), dist=c.dist,
                        width=c.width, height=c.height) for c in final]
    return final, names, report


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
                   help="inner corners of the checkerboard, e.g. 9x6 (required)")
    p.add_argument("--square", type=float, required=True, metavar="METRES",
                   help="side of one square in metres, e.g. 0.025 (required)")
    p.add_argument("--out", default="cameras.json", help="output file (default: %(default)s)")
    p.add_argument("--names", nargs="+", help="camera names (default: cam0 cam1 ...)")
    p.add_argument("--every", type=int, default=1, metavar="N",
                   help="use every N-th frame of videos/folders (default: %(default)s)")
    p.add_argument("--min-views", type=int, default=MIN_VIEWS,
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
