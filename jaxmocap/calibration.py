"""Camera calibration from checkerboard images (Zhang 2000) through OpenCV, and a synthetic
checkerboard renderer to test it.

Both papers assume calibrated cameras (Wang et al. 2011 §6 calibrate their two webcams with a
checkerboard; Azad et al. 2007 §II use a calibrated stereo head). We follow OpenCV:
``findChessboardCorners`` + ``cornerSubPix`` locate the inner corners, ``calibrateCamera``
estimates K and the distortion (k1, k2, p1, p2, k3) per camera, and ``stereoCalibrate`` (with
the intrinsics fixed) the pose of every other camera relative to the first from the views in
which both saw the board.

Board convention: ``pattern_size = (cols, rows)`` counts *inner* corners; the board frame has
x along the columns, y along the rows, z = x cross y, corner (i, j) at ``(i s, j s, 0)`` with
``s = square_size`` metres, and the square diagonally inside corner (0, 0) black. With one of
cols, rows odd and the other even, the corner order is made unambiguous by that colour, so
every camera labels the corners alike (required for the stereo step).
"""

from typing import NamedTuple

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, UInt8

from .camera import Camera, pixel_rays
from .errors import InputError

__all__ = [
    "CalibrationError",
    "CameraCalibration",
    "RigCalibration",
    "board_points",
    "calibrate_camera",
    "calibrate_cameras",
    "find_corners",
    "render_checkerboard",
]

MIN_VIEWS = 3  # Zhang's method needs >= 3 views of a plane for K with skew; more is better
MIN_SHARED_VIEWS = 3  # views both cameras saw, for the stereo extrinsics
SUBPIX_WINDOW_MAX = 11  # half-size of the cornerSubPix window in pixels (OpenCV's usual 11)
SUBPIX_CRITERIA = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_MAX_ITER, 50, 1e-4)
FIND_FLAGS = cv2.CALIB_CB_ADAPTIVE_THRESH | cv2.CALIB_CB_NORMALIZE_IMAGE

# synthetic renderer: grey levels and layout
BOARD_BLACK, BOARD_WHITE, BACKGROUND = 25.0, 230.0, 110.0
BOARD_MARGIN = 0.75  # white border around the squares, in squares


class CalibrationError(InputError):
    """Calibration could not run: too few usable views, inconsistent image sizes, ..."""


class CameraCalibration(NamedTuple):
    """One camera: ``camera`` (R = I, t = 0), RMS reprojection error (pixels), the indices
    of the images where the board was found, the corners (n, 2) found in them and the board
    poses (rvec, tvec, board -> camera) in them."""

    camera: Camera
    rms: float
    used: list[int]
    corners: list[np.ndarray]
    rvecs: list[np.ndarray]
    tvecs: list[np.ndarray]


class RigCalibration(NamedTuple):
    """Several cameras in one world frame; ``rms[i]`` is camera i's intrinsic RMS (pixels),
    ``stereo_rms[i]`` the RMS of the stereo fit of camera i against camera 0 (0 for i = 0)."""

    cameras: list[Camera]
    rms: list[float]
    stereo_rms: list[float]


def board_points(pattern_size: tuple[int, int], square_size: float) -> np.ndarray:
    """Inner corners of the board in its own frame (n, 3), metres, in OpenCV's order."""
    cols, rows = pattern_size
    j, i = np.mgrid[0:rows, 0:cols]
    return np.stack([i.ravel(), j.ravel(), np.zeros(cols * rows)], -1) * float(square_size)


def _gray(image: np.ndarray) -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise CalibrationError(
            f"expected uint8 images (H, W) or (H, W, 3) RGB, got {image.dtype} {image.shape}"
        )
    return image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)


def _square_mean(gray: np.ndarray, corners: np.ndarray, k: int, dx: int, dy: int) -> float:
    """Mean grey level around the centre of the square beside corner k, towards its
    neighbours corner k + dx and corner k + dy (indices into ``corners``)."""
    c = corners[k] + 0.5 * (corners[dx] - corners[k]) + 0.5 * (corners[dy] - corners[k])
    x, y = int(round(c[0])), int(round(c[1]))
    h, w = gray.shape
    x, y = min(max(x, 1), w - 2), min(max(y, 1), h - 2)
    return float(gray[y - 1 : y + 2, x - 1 : x + 2].mean())


def find_corners(
    image: UInt8[np.ndarray | Array, "h w *c"], pattern_size: tuple[int, int]
) -> Float[np.ndarray, "n 2"] | None:
    """Sub-pixel inner-corner positions (n, 2) in pixels, OpenCV order, or None if not found.

    For boards with cols + rows odd, the order is flipped when needed so that the square
    diagonally inside the first corner is the dark one (see the module docstring).
    """
    gray = _gray(image)
    found, corners = cv2.findChessboardCorners(gray, tuple(pattern_size), flags=FIND_FLAGS)
    if not found:
        return None
    corners = corners.reshape(-1, 2).astype(np.float32)
    cols, rows = pattern_size
    spacing = float(
        np.min(np.linalg.norm(np.diff(corners.reshape(rows, cols, 2), axis=1), axis=-1))
    )
    win = int(max(2, min(SUBPIX_WINDOW_MAX, spacing // 2 - 1)))
    corners = cv2.cornerSubPix(
        gray, corners.reshape(-1, 1, 2).copy(), (win, win), (-1, -1), SUBPIX_CRITERIA
    )
    corners = corners.reshape(-1, 2).astype(np.float64)
    if (cols + rows) % 2 == 1:
        n = cols * rows
        first = _square_mean(gray, corners, 0, 1, cols)
        last = _square_mean(gray, corners, n - 1, n - 2, n - 1 - cols)
        if first > last:
            corners = corners[::-1].copy()
    return corners


def _detect_all(images, pattern_size, name: str, min_views: int):
    images = list(images)
    if not images:
        raise CalibrationError(f"{name}: no images given")
    sizes = {_gray(im).shape for im in images}
    if len(sizes) != 1:
        raise CalibrationError(f"{name}: images have different sizes {sorted(sizes)}")
    detections = [find_corners(im, pattern_size) for im in images]
    used = [i for i, d in enumerate(detections) if d is not None]
    if len(used) < min_views:
        cols, rows = pattern_size
        raise CalibrationError(
            f"{name}: checkerboard with {cols}x{rows} inner corners found in {len(used)} of "
            f"{len(images)} images, need at least {min_views}. Check pattern_size (inner "
            "corners: columns x rows, not squares), that the whole board is visible and sharp, "
            "and add views at varied angles."
        )
    h, w = sizes.pop()
    return detections, used, (w, h)


def calibrate_camera(
    images,
    pattern_size: tuple[int, int],
    square_size: float,
    *,
    min_views: int = MIN_VIEWS,
    flags: int = 0,
    name: str = "camera",
) -> CameraCalibration:
    """Zhang calibration of one camera from checkerboard images (uint8 RGB or grey).

    Returns the camera (its frame is the world: R = I, t = 0), the RMS reprojection error in
    pixels and the board poses. ``flags`` are passed to ``cv2.calibrateCamera`` (e.g.
    ``cv2.CALIB_FIX_K3`` with few or frontal views).
    """
    detections, used, size = _detect_all(images, pattern_size, name, min_views)
    obj = board_points(pattern_size, square_size).astype(np.float32)
    rms, K, dist, rvecs, tvecs = cv2.calibrateCamera(
        [obj] * len(used),
        [detections[i].astype(np.float32)[:, None] for i in used],
        size,
        None,
        None,
        flags=flags,
    )
    dist = np.zeros(5) if dist is None else np.ravel(dist)[:5]
    camera = Camera(
        K=jnp.asarray(K),
        R=jnp.eye(3),
        t=jnp.zeros(3),
        dist=jnp.asarray(np.pad(dist, (0, 5 - dist.size))),
        width=size[0],
        height=size[1],
    )
    corners = [detections[i] for i in used]
    return CameraCalibration(camera, float(rms), used, corners, list(rvecs), list(tvecs))


def calibrate_cameras(
    images_per_camera,
    pattern_size: tuple[int, int],
    square_size: float,
    *,
    names=None,
    min_views: int = MIN_VIEWS,
    min_shared_views: int = MIN_SHARED_VIEWS,
    flags: int = 0,
    world: str = "camera0",
) -> RigCalibration:
    """Calibrate a rig: ``images_per_camera[c][v]`` is camera c's image at instant v.

    Intrinsics per camera by :func:`calibrate_camera`; then, for each camera c > 0,
    ``cv2.stereoCalibrate`` with fixed intrinsics on the instants where cameras 0 and c both
    found the board gives x_c = R x_0 + T. ``world="camera0"`` puts the world frame at
    camera 0; ``world="board"`` at the board in the first instant both cameras 0 and 1 (or
    camera 0 alone, for one camera) saw it.
    """
    if world not in ("camera0", "board"):
        raise ValueError(f"calibrate_cameras: world must be 'camera0' or 'board', got {world!r}")
    images_per_camera = [list(ims) for ims in images_per_camera]
    names = [f"cam{i}" for i in range(len(images_per_camera))] if names is None else list(names)
    n_frames = {len(ims) for ims in images_per_camera}
    if len(n_frames) != 1:
        raise CalibrationError(
            f"calibrate_cameras: cameras have different numbers of images {sorted(n_frames)}; "
            "image v of every camera must show the same instant"
        )
    calibs = [
        calibrate_camera(ims, pattern_size, square_size, min_views=min_views, flags=flags, name=n)
        for ims, n in zip(images_per_camera, names, strict=True)
    ]
    obj = board_points(pattern_size, square_size).astype(np.float32)
    c0 = calibs[0]
    det0 = dict(zip(c0.used, c0.corners, strict=True))
    Rs, Ts, stereo_rms, first_shared = [np.eye(3)], [np.zeros(3)], [0.0], None
    for c in range(1, len(calibs)):
        cc = calibs[c]
        shared = [v for v in cc.used if v in det0]
        if len(shared) < min_shared_views:
            raise CalibrationError(
                f"{names[c]}: the board was seen together with {names[0]} in {len(shared)} "
                f"instants, need at least {min_shared_views}; record views where both cameras "
                "see the whole board"
            )
        detc = dict(zip(cc.used, cc.corners, strict=True))
        cam_a, cam_c = c0.camera, cc.camera
        rms, *_, R, T, _, _ = cv2.stereoCalibrate(
            [obj] * len(shared),
            [det0[v].astype(np.float32)[:, None] for v in shared],
            [detc[v].astype(np.float32)[:, None] for v in shared],
            np.array(cam_a.K, np.float64),
            np.array(cam_a.dist, np.float64),
            np.array(cam_c.K, np.float64),
            np.array(cam_c.dist, np.float64),
            (cam_a.width, cam_a.height),
            flags=cv2.CALIB_FIX_INTRINSIC,
        )
        Rs.append(R)
        Ts.append(np.ravel(T))
        stereo_rms.append(float(rms))
        if first_shared is None:
            first_shared = shared[0]
    Rw, tw = np.eye(3), np.zeros(3)  # world -> camera 0
    if world == "board":
        v = c0.used[0] if first_shared is None else first_shared
        k = c0.used.index(v)
        Rw, tw = cv2.Rodrigues(c0.rvecs[k])[0], np.ravel(c0.tvecs[k])
    cameras = [
        eqx.tree_at(
            lambda cam: (cam.R, cam.t), cal.camera, (jnp.asarray(R @ Rw), jnp.asarray(R @ tw + T))
        )
        for cal, R, T in zip(calibs, Rs, Ts, strict=True)
    ]
    return RigCalibration(cameras, [c.rms for c in calibs], stereo_rms)


# ----------------------------------------------------------------------------- synthetic boards


def render_checkerboard(
    cam: Camera,
    pattern_size: tuple[int, int],
    square_size: float,
    R_wb: Float[Array | np.ndarray, "*views 3 3"],
    t_wb: Float[Array | np.ndarray, "*views 3"],
    supersample: int = 3,
) -> UInt8[Array, "*views h w 3"]:
    """Render checkerboards seen by ``cam`` (lens distortion included) as uint8 RGB images.

    The board (conventions in the module docstring) is placed by its board -> world pose
    ``X_world = R_wb X_board + t_wb``; a batch of poses (views, 3, 3), (views, 3) renders a
    batch of images sharing the camera's rays. Each pixel averages ``supersample^2`` rays
    (:func:`jaxmocap.camera.pixel_rays`) intersected with the board plane, so edges are
    anti-aliased like a real sensor's. Squares, a white margin of ``BOARD_MARGIN`` squares
    and a grey background. Computed in float32 (ample for 8-bit images).
    """
    f32 = jnp.float32
    cam32 = jax.tree.map(lambda a: jnp.asarray(a, f32), cam)
    R_wb, t_wb = jnp.asarray(R_wb, f32), jnp.asarray(t_wb, f32)
    batch = R_wb.shape[:-2]
    if t_wb.shape[:-1] != batch:
        raise ValueError(f"render_checkerboard: R_wb {R_wb.shape} and t_wb {t_wb.shape} differ")
    img = _render(
        cam32,
        tuple(pattern_size),
        R_wb.reshape(-1, 3, 3),
        t_wb.reshape(-1, 3),
        jnp.asarray(square_size, f32),
        int(supersample),
    )
    return img.reshape(batch + img.shape[1:])


@eqx.filter_jit
def _render(cam, pattern_size, R_wb, t_wb, square, supersample):
    cols, rows = pattern_size
    h, w = cam.height, cam.width
    v, u = jnp.meshgrid(
        jnp.arange(h, dtype=square.dtype), jnp.arange(w, dtype=square.dtype), indexing="ij"
    )
    uv = jnp.stack([u, v], -1)
    k = (jnp.arange(supersample, dtype=square.dtype) + 0.5) / supersample - 0.5
    offsets = jnp.stack(jnp.meshgrid(k, k, indexing="ij"), -1).reshape(-1, 2)
    m = BOARD_MARGIN * square

    def shade(o, d, pose):
        R, t = pose
        normal = R[:, 2]
        denom = d @ normal
        s = ((t[None, None, :] - o) @ normal) / denom
        hit = (s > 0) & (jnp.abs(denom) > 1e-9)
        b = (o + s[..., None] * d - t[None, None, :]) @ R  # board coordinates R^T (p - t)
        ix, iy = jnp.floor(b[..., 0] / square), jnp.floor(b[..., 1] / square)
        squares = (ix >= -1) & (ix <= cols - 1) & (iy >= -1) & (iy <= rows - 1)
        on_board = (
            (b[..., 0] >= -square - m)
            & (b[..., 0] <= cols * square + m)
            & (b[..., 1] >= -square - m)
            & (b[..., 1] <= rows * square + m)
        )
        black = jnp.mod(ix + iy, 2) == 0
        grey = jnp.where(squares & black, BOARD_BLACK, BOARD_WHITE)
        return jnp.where(hit & on_board, grey, BACKGROUND).astype(square.dtype)

    def per_offset(acc, offset):
        o, d = pixel_rays(cam, uv + offset[None, None, :])
        return acc + jax.lax.map(lambda pose: shade(o, d, pose), (R_wb, t_wb)), None

    acc = jnp.zeros((R_wb.shape[0], h, w), square.dtype)
    acc, _ = jax.lax.scan(per_offset, acc, offsets)
    img = jnp.clip(jnp.round(acc / offsets.shape[0]), 0, 255).astype(jnp.uint8)
    return jnp.broadcast_to(img[..., None], img.shape + (3,))
