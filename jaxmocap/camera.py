"""Pinhole cameras with OpenCV distortion: projection, back-projection, N-view triangulation,
epipolar geometry and the ``cameras.json`` file format.

Both papers work with calibrated cameras: Wang et al. 2011 (§5, multi-camera IK) project body
points into every view, Azad et al. 2007 (§III) triangulate skin blobs from a stereo pair and
score particles with epipolar-consistent projections. Everything here follows OpenCV:

    x_cam = R @ X_world + t                     (metres, camera looks along +z_cam)
    x = x_cam[0] / x_cam[2],  y = x_cam[1] / x_cam[2]          (normalised, unitless)
    r^2 = x^2 + y^2,  L = 1 + k1 r^2 + k2 r^4 + k3 r^6
    x_d = x L + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y L + p1 (r^2 + 2 y^2) + 2 p2 x y
    [u, v, 1]^T = K @ [x_d, y_d, 1]^T           (pixels; pixel centres at integer coordinates)

so ``project`` equals ``cv2.projectPoints`` (which ignores the skew entry K[0, 1]; we honour it,
identical when it is zero).

``cameras.json`` schema (version 1)::

    {"version": 1,
     "cameras": [
        {"name": "cam0",                 # unique, non-empty string
         "width": 640, "height": 480,    # image size in pixels, positive integers
         "K": [[fx, s, cx], [0, fy, cy], [0, 0, 1]],   # fx, fy > 0
         "dist": [k1, k2, p1, p2, k3],   # OpenCV order; 4 values allowed (k3 = 0)
         "R": [[...], [...], [...]],     # world -> camera rotation (orthonormal, det +1)
         # or instead of "R": "rvec": [rx, ry, rz]   (Rodrigues vector, radians)
         "t": [tx, ty, tz]}              # world -> camera translation, metres
     ]}

Files written by other tools load when their fields are OpenCV's: ``"version"`` may be left
out (if present it must be 1); the cameras may be the top-level list, the ``"cameras"`` list
or an object keyed by camera name; each camera may spell its fields as OpenCV's and common
calibration tools do (:data:`FIELD_ALIASES`: ``camera_matrix``/``matrix``/``mtx`` for ``K``,
``dist_coeffs``/``distortions``/``D`` for ``dist``, ``rvec``/``rotation`` (a 3-vector
Rodrigues or a 3x3 matrix), ``tvec``/``translation``/``T`` for ``t``, ``size``/``image_size``
``[width, height]``), with 4, 5, 8, 12 or 14 OpenCV distortion values (the terms past ``k3``
must be zero: the model here is OpenCV's 5-term one). A TOML file is read as the
calibration file of Pose2Sim / anipose / FreeMoCap (``[cam_1] name, size, matrix,
distortions, rotation, translation``; ``[metadata]`` skipped), and an OpenCV FileStorage
YAML/XML (``cv2.FileStorage``: ``camera_matrix``, ``dist_coeffs`` / ``distortion_coefficients``,
``R`` (3x3 or a Rodrigues 3x1), ``T``, ``image_width`` / ``image_height``; one camera at the
top level, named after the file, or one map per camera). The kind is told by the content
(a FileStorage header, a JSON object, a TOML table header), by the suffix where the content
allows two; a file that is none of them is one line.

Malformed files raise :class:`CameraFileError` naming the file, the camera, the field and
what was expected. ``save_cameras`` writes atomically (temporary file + ``os.replace``).
"""

import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxmocap.errors import InputError
from jaxmocap.rotations import rodrigues, skew

ArrayIn = Array | np.ndarray  # inputs accept NumPy arrays too
VectorLike = ArrayLike | Sequence  # also nested lists of numbers

__all__ = [
    "Camera",
    "CameraFileError",
    "camera_center",
    "distort_normalized",
    "epipolar_distance",
    "epipolar_distance_undistorted",
    "fundamental_matrix",
    "load_cameras",
    "look_at",
    "pixel_rays",
    "project",
    "save_cameras",
    "stack_cameras",
    "to_camera",
    "triangulate",
    "undistort_normalized",
    "undistort_pixels",
    "unstack_cameras",
]

UNDISTORT_FIXED_POINT_ITERS = 4  # OpenCV-style fixed-point steps (cv::undistortPoints)
UNDISTORT_NEWTON_ITERS = 5  # then Newton steps on the 2x2 distortion Jacobian
DLT_INVERSE_ITERS = 3  # inverse-iteration steps of the homogeneous DLT (see _dlt)
TRIANGULATE_GN_ITERS = 5  # Gauss-Newton steps on the reprojection error
CAMERAS_JSON_VERSION = 1
ROTATION_TOLERANCE = 1e-4  # max |R R^T - I| and |det R - 1| accepted from cameras.json


def _as_float(x: VectorLike) -> Array:
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.inexact):
        x = x.astype(jnp.result_type(float))
    return x


class Camera(eqx.Module):
    """A calibrated pinhole camera with OpenCV (k1, k2, p1, p2, k3) distortion.

    Fields may carry leading batch axes (see :func:`stack_cameras`); a single camera has
    ``K`` (3, 3), ``R`` (3, 3) world -> camera rotation, ``t`` (3,) world -> camera
    translation in metres, ``dist`` (5,) and the image size ``width`` x ``height`` pixels.
    """

    K: Float[Array, "*batch 3 3"] = eqx.field(converter=_as_float)
    R: Float[Array, "*batch 3 3"] = eqx.field(converter=_as_float)
    t: Float[Array, "*batch 3"] = eqx.field(converter=_as_float)
    dist: Float[Array, "*batch 5"] = eqx.field(converter=_as_float)
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    def __check_init__(self):
        for name, tail in (("K", (3, 3)), ("R", (3, 3)), ("t", (3,)), ("dist", (5,))):
            shape = getattr(self, name).shape
            if shape[len(shape) - len(tail) :] != tail or len(shape) < len(tail):
                raise ValueError(f"Camera.{name}: expected shape (..., {tail}), got {shape}")
        batch = self.K.shape[:-2]
        for name, nd in (("R", 2), ("t", 1), ("dist", 1)):
            if getattr(self, name).shape[: getattr(self, name).ndim - nd] != batch:
                raise ValueError(
                    f"Camera.{name}: batch shape {getattr(self, name).shape[:-nd]} differs "
                    f"from K's {batch}"
                )
        for name in ("width", "height"):
            v = getattr(self, name)
            if not isinstance(v, (int, np.integer)) or isinstance(v, bool) or v <= 0:
                raise ValueError(f"Camera.{name}: expected a positive integer, got {v!r}")
        if not isinstance(self.K, jax.core.Tracer):
            f = np.asarray(jnp.stack([self.K[..., 0, 0], self.K[..., 1, 1]]))
            if not np.all(f > 0):
                raise ValueError(f"Camera.K: focal lengths K[0,0], K[1,1] must be > 0, got {f}")


class CameraFileError(InputError):
    """A ``cameras.json`` file that does not follow the schema in this module's docstring."""


# ----------------------------------------------------------------------------- projection


def _vec(a: Array, x: Array) -> Array:
    """Broadcast a trailing-axis vector ``a`` (d,) against ``x`` (..., d) without rank promotion."""
    return jnp.reshape(a, (1,) * (x.ndim - 1) + a.shape)


def to_camera(cam: Camera, X: Float[ArrayIn, "*n 3"]) -> Float[Array, "*n 3"]:
    """World points X (metres) in the camera frame: ``R X + t``; depth is ``[..., 2]``."""
    X = jnp.asarray(X)
    return jnp.einsum("ij,...j->...i", cam.R, X) + _vec(cam.t, X)


def camera_center(cam: Camera) -> Float[Array, "3"]:
    """Camera centre C in world coordinates (metres): ``C = -R^T t``."""
    return -cam.R.T @ cam.t


def distort_normalized(cam: Camera, xy: Float[ArrayIn, "*n 2"]) -> Float[Array, "*n 2"]:
    """Apply the OpenCV distortion model to ideal normalised coordinates (x, y)."""
    x, y = xy[..., 0], xy[..., 1]
    k1, k2, p1, p2, k3 = (cam.dist[i] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return jnp.stack([xd, yd], axis=-1)


def _distortion_and_jacobian(dist: Array, x: Array, y: Array):
    """Distorted (x_d, y_d) and the symmetric Jacobian d(x_d, y_d)/d(x, y) as (jxx, jxy, jyy).

    ``dist`` (..., 5) broadcasts against x, y by its leading axes (same rank as x minus zero
    or with trailing singleton axes added by the caller).
    """
    k1, k2, p1, p2, k3 = (dist[..., i] for i in range(5))
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    dradial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # dL / d(r^2)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    jxx = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
    jxy = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y
    jyy = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
    return xd, yd, jxx, jxy, jyy


def _normalized_to_pixels(cam: Camera, xy: Array) -> Array:
    K = cam.K
    u = K[0, 0] * xy[..., 0] + K[0, 1] * xy[..., 1] + K[0, 2]
    v = K[1, 1] * xy[..., 1] + K[1, 2]
    return jnp.stack([u, v], axis=-1)


def _pixels_to_normalized(cam: Camera, uv: Array) -> Array:
    K = cam.K
    y = (uv[..., 1] - K[1, 2]) / K[1, 1]
    x = (uv[..., 0] - K[0, 2] - K[0, 1] * y) / K[0, 0]
    return jnp.stack([x, y], axis=-1)


def project(cam: Camera, X: Float[ArrayIn, "*n 3"]) -> Float[Array, "*n 2"]:
    """Project world points X (..., 3) in metres to distorted pixels (..., 2).

    Equals ``cv2.projectPoints(X, rvec(R), t, K, dist)``. Points behind the camera are
    projected through the same formula (as OpenCV does); check ``to_camera(...)[..., 2] > 0``
    where that matters. Differentiable; vmap over a stacked camera for many views.
    """
    xc = to_camera(cam, X)
    xy = xc[..., :2] / xc[..., 2:3]
    return _normalized_to_pixels(cam, distort_normalized(cam, xy))


def undistort_normalized(cam: Camera, uv: Float[ArrayIn, "*n 2"]) -> Float[Array, "*n 2"]:
    """Ideal normalised coordinates (x, y) of distorted pixels uv: the inverse of ``project``.

    Solves ``distort(x, y) = K^-1 uv`` with a fixed number of steps (jit-friendly, no
    data-dependent exit): ``UNDISTORT_FIXED_POINT_ITERS`` steps of OpenCV's fixed-point
    iteration, then ``UNDISTORT_NEWTON_ITERS`` Newton steps with the analytic 2x2 Jacobian.
    Matches ``cv2.undistortPoints`` run to convergence.
    """
    uv = jnp.asarray(uv)
    xy0 = _pixels_to_normalized(cam, uv)
    x0, y0 = xy0[..., 0], xy0[..., 1]
    k1, k2, p1, p2, k3 = (cam.dist[i] for i in range(5))

    def fixed_point(_, xy):
        x, y = xy
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return (x0 - dx) / radial, (y0 - dy) / radial

    def newton(_, xy):
        x, y = xy
        xd, yd, jxx, jxy, jyy = _distortion_and_jacobian(cam.dist, x, y)
        fx, fy = xd - x0, yd - y0
        det = jxx * jyy - jxy * jxy
        return x - (jyy * fx - jxy * fy) / det, y - (jxx * fy - jxy * fx) / det

    xy = jax.lax.fori_loop(0, UNDISTORT_FIXED_POINT_ITERS, fixed_point, (x0, y0))
    x, y = jax.lax.fori_loop(0, UNDISTORT_NEWTON_ITERS, newton, xy)
    return jnp.stack([x, y], axis=-1)


def undistort_pixels(cam: Camera, uv: Float[ArrayIn, "*n 2"]) -> Float[Array, "*n 2"]:
    """Distorted pixels -> ideal (distortion-free) pixels of the same K."""
    return _normalized_to_pixels(cam, undistort_normalized(cam, uv))


def pixel_rays(
    cam: Camera, uv: Float[ArrayIn, "*n 2"]
) -> tuple[Float[Array, "*n 3"], Float[Array, "*n 3"]]:
    """World-space rays through distorted pixels uv: (origins, unit directions), metres.

    Every origin is the camera centre; ``project(cam, o + s d) == uv`` for any depth s > 0.
    """
    xy = undistort_normalized(cam, uv)
    d_cam = jnp.concatenate([xy, jnp.ones_like(xy[..., :1])], axis=-1)
    d = jnp.einsum("ji,...j->...i", cam.R, d_cam)  # R^T d_cam
    d = d / jnp.linalg.norm(d, axis=-1, keepdims=True)
    origins = jnp.broadcast_to(_vec(camera_center(cam), d), d.shape)
    return origins, d


# ----------------------------------------------------------------------------- construction


def look_at(
    eye: VectorLike,
    target: VectorLike,
    up: VectorLike = (0.0, 0.0, 1.0),
    *,
    width: int,
    height: int,
    K: VectorLike | None = None,
    fx: float | None = None,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
    dist: VectorLike | None = None,
) -> Camera:
    """A camera at ``eye`` (metres) looking at ``target`` with world ``up`` (Z-up default).

    Give either ``K`` or ``fx`` (``fy`` defaults to ``fx``; ``cx, cy`` default to the image
    centre ``((width - 1) / 2, (height - 1) / 2)``). Image x points right, y down.
    """
    eye, target, up = _as_float(eye), _as_float(target), _as_float(up)
    z = target - eye
    nz = jnp.linalg.norm(z)
    x = jnp.cross(z, up)
    nx = jnp.linalg.norm(x)
    if not isinstance(nz, jax.core.Tracer) and (nz == 0 or nx <= 1e-9 * nz * jnp.linalg.norm(up)):
        raise ValueError("look_at: eye == target or viewing direction parallel to up")
    z, x = z / nz, x / nx
    y = jnp.cross(z, x)
    R = jnp.stack([x, y, z])
    if K is None:
        if fx is None:
            raise ValueError("look_at: give K or fx")
        fy = fx if fy is None else fy
        cx = (width - 1) / 2 if cx is None else cx
        cy = (height - 1) / 2 if cy is None else cy
        K = jnp.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], dtype=R.dtype)
    dist = jnp.zeros(5, R.dtype) if dist is None else dist
    return Camera(K=K, R=R, t=-R @ eye, dist=dist, width=int(width), height=int(height))


def stack_cameras(cams: Sequence[Camera]) -> Camera:
    """Stack cameras of the same image size into one Camera with a leading view axis."""
    cams = list(cams)
    if not cams:
        raise ValueError("stack_cameras: empty list")
    size = (cams[0].width, cams[0].height)
    for i, c in enumerate(cams):
        if (c.width, c.height) != size:
            raise ValueError(
                f"stack_cameras: camera {i} is {c.width}x{c.height}, camera 0 is "
                f"{size[0]}x{size[1]}; stacked cameras must share the image size"
            )
        if c.K.ndim != 2:
            raise ValueError(f"stack_cameras: camera {i} is already batched ({c.K.shape[:-2]})")
    return jax.tree.map(lambda *xs: jnp.stack(xs), *cams)


def unstack_cameras(cams: Camera) -> list[Camera]:
    """The inverse of :func:`stack_cameras` (a single camera gives a one-element list)."""
    if cams.K.ndim == 2:
        return [cams]
    return [jax.tree.map(lambda a, i=i: a[i], cams) for i in range(cams.K.shape[0])]


# ----------------------------------------------------------------------------- triangulation


def _adjugate3(B: Array) -> tuple[Array, Array]:
    """Adjugate (n, 3, 3) and determinant (n,) of batched 3x3 matrices B (n, 3, 3)."""
    c0 = jnp.cross(B[:, 1], B[:, 2])
    c1 = jnp.cross(B[:, 2], B[:, 0])
    c2 = jnp.cross(B[:, 0], B[:, 1])
    return jnp.stack([c0, c1, c2], axis=-1), jnp.sum(B[:, 0] * c0, axis=-1)


def _dlt(xy: Array, R: Array, t: Array, w: Array) -> Array:
    """Homogeneous N-view DLT: xy (v, n, 2) normalised, cameras [R | t] (v, 3, 4), weights
    w (v, n) -> points (n, 3).

    Each view adds the rows ``x P_3 - P_1`` and ``y P_3 - P_2`` of A; the estimate is the unit
    h minimising ``||A h||``, the eigenvector of ``M = A^T A`` with the smallest eigenvalue
    (as ``cv2.triangulatePoints``). Instead of a batched eigen-solver (slow on CPU) we start
    from the inhomogeneous solution (h_4 = 1: ``B X = -b`` with ``M = [[B, b], [b^T, c]]``)
    and run ``DLT_INVERSE_ITERS`` steps of inverse iteration ``h <- M^-1 h``, solved in closed
    form with the Schur complement ``c - b^T B^-1 b``; elementwise, so fast and
    differentiable.
    """
    P = jnp.concatenate([R, t[:, :, None]], axis=2)  # (v, 3, 4), normalised cameras
    rows_x = (xy[..., 0:1] * P[:, None, 2] - P[:, None, 0]) * w[..., None]  # (v, n, 4)
    rows_y = (xy[..., 1:2] * P[:, None, 2] - P[:, None, 1]) * w[..., None]
    M = jnp.einsum("vni,vnj->nij", rows_x, rows_x) + jnp.einsum("vni,vnj->nij", rows_y, rows_y)
    B, b, c = M[:, :3, :3], M[:, :3, 3], M[:, 3, 3]
    adj, det = _adjugate3(B)
    Binv_b = jnp.einsum("nij,nj->ni", adj, b) / det[:, None]
    schur = c - jnp.sum(b * Binv_b, axis=-1)
    tiny = jnp.finfo(M.dtype).eps * jnp.trace(M, axis1=1, axis2=2)
    schur = jnp.where(jnp.abs(schur) < tiny, tiny, schur)  # exact data: M is singular
    h1, h2 = -Binv_b, jnp.ones_like(c)
    for _ in range(DLT_INVERSE_ITERS):
        Binv_h1 = jnp.einsum("nij,nj->ni", adj, h1) / det[:, None]
        y2 = (h2 - jnp.sum(b * Binv_h1, axis=-1)) / schur
        h1 = Binv_h1 - Binv_b * y2[:, None]
        h2 = y2
        scale = jnp.sqrt(jnp.sum(h1 * h1, axis=-1) + h2 * h2)
        h1, h2 = h1 / scale[:, None], h2 / scale
    return h1 / h2[:, None]


def _solve_sym3(A: Array, b: Array) -> Array:
    """Solve batched 3x3 systems A (n, 3, 3) x = b (n, 3) by the adjugate (elementwise)."""
    adj, det = _adjugate3(A)
    return jnp.einsum("nij,nj->ni", adj, b) / det[:, None]


def _project_views_and_jacobian(cams: Camera, X: Array) -> tuple[Array, Array]:
    """Pixels (v, n, 2) of points X (n, 3) in stacked cameras and d(uv)/dX (v, n, 2, 3)."""
    xc = jnp.einsum("vij,nj->vni", cams.R, X) + cams.t[:, None, :]
    z = xc[..., 2]
    a, b = xc[..., 0] / z, xc[..., 1] / z
    xd, yd, jxx, jxy, jyy = _distortion_and_jacobian(cams.dist[:, None, :], a, b)
    fx, s, cx = cams.K[:, 0, 0:1], cams.K[:, 0, 1:2], cams.K[:, 0, 2:3]
    fy, cy = cams.K[:, 1, 1:2], cams.K[:, 1, 2:3]
    uv = jnp.stack([fx * xd + s * yd + cx, fy * yd + cy], axis=-1)
    d_ab = jnp.stack(
        [  # d(u, v) / d(a, b): (v, n, 2, 2)
            jnp.stack([fx * jxx + s * jxy, fx * jxy + s * jyy], axis=-1),
            jnp.stack([fy * jxy, fy * jyy], axis=-1),
        ],
        axis=-2,
    )
    zero = jnp.zeros_like(z)
    d_xc = jnp.stack(
        [  # d(a, b) / d(x_cam): (v, n, 2, 3)
            jnp.stack([1 / z, zero, -a / z], axis=-1),
            jnp.stack([zero, 1 / z, -b / z], axis=-1),
        ],
        axis=-2,
    )
    J = jnp.einsum("vnck,vnkl,vlj->vncj", d_ab, d_xc, cams.R)
    return uv, J


def triangulate(
    cams: Camera,
    uv: Float[ArrayIn, "n_views *n 2"],
    refine: bool = True,
    weights: Float[ArrayIn, "n_views *n"] | None = None,  # noqa: F821
    n_iter: int = TRIANGULATE_GN_ITERS,
) -> Float[Array, "*n 3"]:
    """Triangulate points seen in several views (metres).

    ``cams`` is a stacked camera (:func:`stack_cameras`) with ``n_views`` views and
    ``uv[i]`` the distorted pixels in view i. The estimate is the homogeneous DLT on the
    undistorted normalised coordinates (the minimiser of the algebraic error, as
    ``cv2.triangulatePoints``); with ``refine`` it is then improved by ``n_iter``
    Gauss-Newton steps on the weighted reprojection error in pixels,
    ``sum_i w_i ||project(cam_i, X) - uv_i||^2`` (distortion included).

    ``weights`` (n_views, ...) >= 0 weight the views per point; 0 marks a missing view (its
    uv may be NaN). Points with fewer than two views of positive weight come back NaN.
    """
    uv = jnp.asarray(uv)
    n_views = cams.K.shape[0] if cams.K.ndim == 3 else 0
    if n_views < 2 or uv.shape[0] != n_views:
        raise ValueError(
            f"triangulate: need a stacked camera with >= 2 views and uv (n_views, ..., 2); "
            f"got {n_views} cameras and uv {uv.shape}"
        )
    batch = uv.shape[1:-1]
    flat = uv.reshape(n_views, -1, 2)
    if weights is None:
        w = jnp.ones(flat.shape[:2], flat.dtype)
    else:
        w = jnp.asarray(weights, flat.dtype).reshape(n_views, -1)
    valid = w > 0
    flat = jnp.where(valid[..., None], flat, 0.0)
    xy = jax.vmap(undistort_normalized)(cams, flat)  # (v, n, 2)
    X = _dlt(xy, cams.R, cams.t, w)  # (n, 3)

    if refine:
        sw = jnp.sqrt(w)

        def gn_step(_, X):
            uv_hat, J = _project_views_and_jacobian(cams, X)
            r = (uv_hat - flat) * sw[..., None]  # (v, n, 2)
            J = J * sw[..., None, None]  # (v, n, 2, 3)
            JtJ = jnp.einsum("vnci,vncj->nij", J, J)
            Jtr = jnp.einsum("vnci,vnc->ni", J, r)
            damp = (
                1e-9
                * jnp.trace(JtJ, axis1=1, axis2=2)[:, None, None]
                * jnp.eye(3, dtype=X.dtype)[None]
            )
            return X - _solve_sym3(JtJ + damp, Jtr)

        X = jax.lax.fori_loop(0, n_iter, gn_step, X)

    enough = jnp.sum(valid, axis=0) >= 2
    X = jnp.where(enough[:, None], X, jnp.nan)
    return X.reshape(batch + (3,))


# ----------------------------------------------------------------------------- epipolar geometry


def fundamental_matrix(cam_a: Camera, cam_b: Camera) -> Float[Array, "3 3"]:
    """Fundamental matrix F with ``x_b^T F x_a = 0`` for ideal (undistorted) pixels.

    From the relative pose R = R_b R_a^T, t = t_b - R t_a: ``F = K_b^-T [t]_x R K_a^-1``,
    scaled to unit Frobenius norm. Distortion is not part of F: undistort pixels first
    (:func:`undistort_pixels`) or use :func:`epipolar_distance_undistorted`.
    """
    R = cam_b.R @ cam_a.R.T
    t = cam_b.t - R @ cam_a.t
    E = skew(t) @ R
    F = jnp.linalg.inv(cam_b.K).T @ E @ jnp.linalg.inv(cam_a.K)
    return F / jnp.linalg.norm(F)


def epipolar_distance(
    F: Float[ArrayIn, "3 3"], uv_a: Float[ArrayIn, "*n 2"], uv_b: Float[ArrayIn, "*n 2"]
) -> Float[Array, "*n"]:
    """Symmetric point-to-epipolar-line distance in pixels.

    ``0.5 * (dist(x_b, F x_a) + dist(x_a, F^T x_b))``. Works on ideal pixels: it ignores lens
    distortion, so pass undistorted pixels or use :func:`epipolar_distance_undistorted`.
    """
    uv_a, uv_b = jnp.asarray(uv_a), jnp.asarray(uv_b)
    ha = jnp.concatenate([uv_a, jnp.ones_like(uv_a[..., :1])], axis=-1)
    hb = jnp.concatenate([uv_b, jnp.ones_like(uv_b[..., :1])], axis=-1)
    la = jnp.einsum("ij,...j->...i", F, ha)  # line in b
    lb = jnp.einsum("ji,...j->...i", F, hb)  # line in a
    e = jnp.sum(hb * la, axis=-1)
    da = jnp.abs(e) / jnp.linalg.norm(la[..., :2], axis=-1)
    db = jnp.abs(e) / jnp.linalg.norm(lb[..., :2], axis=-1)
    return 0.5 * (da + db)


def epipolar_distance_undistorted(
    cam_a: Camera, cam_b: Camera, uv_a: Float[ArrayIn, "*n 2"], uv_b: Float[ArrayIn, "*n 2"]
) -> Float[Array, "*n"]:
    """:func:`epipolar_distance` for distorted pixels: undistorts both, then measures (pixels)."""
    F = fundamental_matrix(cam_a, cam_b)
    return epipolar_distance(F, undistort_pixels(cam_a, uv_a), undistort_pixels(cam_b, uv_b))


# ----------------------------------------------------------------------------- cameras.json


def _field_array(path, name, entry, key, shape) -> np.ndarray:
    where = f"{path}: camera {name!r}: field {key!r}"
    if key not in entry:
        raise CameraFileError(f"{where}: missing (expected {_shape_text(shape)} numbers)")
    try:
        a = np.asarray(entry[key], dtype=float)
    except (TypeError, ValueError):
        raise CameraFileError(f"{where}: expected {_shape_text(shape)} numbers") from None
    if a.shape != shape:
        raise CameraFileError(f"{where}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CameraFileError(f"{where}: contains non-finite values")
    return a


def _shape_text(shape) -> str:
    return "x".join(str(s) for s in shape)


def _parse_camera(path, i, entry, dtype) -> tuple[str, Camera]:
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise CameraFileError(f"{path}: cameras[{i}]: field 'name': expected a non-empty string")
    size = {}
    for key in ("width", "height"):
        v = entry.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise CameraFileError(
                f"{path}: camera {name!r}: field {key!r}: expected a positive integer, got {v!r}"
            )
        size[key] = v
    K = _field_array(path, name, entry, "K", (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CameraFileError(
            f"{path}: camera {name!r}: field 'K': focal lengths K[0][0], K[1][1] must be > 0"
        )
    if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise CameraFileError(
            f"{path}: camera {name!r}: field 'K': expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]"
        )
    if "dist" not in entry:
        raise CameraFileError(
            f"{path}: camera {name!r}: field 'dist': missing (expected 5 numbers)"
        )
    n_dist = np.shape(entry["dist"]) if isinstance(entry["dist"], list) else None
    dist = _field_array(path, name, entry, "dist", (4,) if n_dist == (4,) else (5,))
    dist = np.concatenate([dist, np.zeros(5 - dist.size)])
    if ("R" in entry) == ("rvec" in entry):
        raise CameraFileError(
            f"{path}: camera {name!r}: field 'R'/'rvec': give exactly one of 'R' (3x3) or "
            "'rvec' (3)"
        )
    if "R" in entry:
        R = _field_array(path, name, entry, "R", (3, 3))
        err = max(np.abs(R @ R.T - np.eye(3)).max(), abs(np.linalg.det(R) - 1))
        if err > ROTATION_TOLERANCE:
            raise CameraFileError(
                f"{path}: camera {name!r}: field 'R': expected a rotation (orthonormal, det +1); "
                f"off by {err:.2g}"
            )
    else:
        R = rodrigues(_field_array(path, name, entry, "rvec", (3,)))
    t = _field_array(path, name, entry, "t", (3,))
    cam = Camera(
        K=jnp.asarray(K, dtype),
        R=jnp.asarray(R, dtype),
        t=jnp.asarray(t, dtype),
        dist=jnp.asarray(dist, dtype),
        width=size["width"],
        height=size["height"],
    )
    return name, cam


# Other tools' spellings of the fields of one camera (OpenCV's FileStorage names, Pose2Sim /
# anipose calibration.toml, common JSON dumps) -> ours. "rotation" may be a 3x3 or a rvec.
FIELD_ALIASES = {
    "K": ("camera_matrix", "cameraMatrix", "matrix", "mtx", "intrinsics", "intrinsic"),
    "dist": ("dist_coeffs", "distCoeffs", "distortion", "distortions", "D", "dist_coef",
             "distortion_coefficients"),
    "R": ("rotation_matrix", "R_mat"),
    "rvec": ("rotation_vector", "rvecs"),
    "t": ("tvec", "translation", "T", "tvecs"),
}
SIZE_ALIASES = ("size", "image_size", "imageSize", "resolution")  # [width, height]


def _canonical_entry(path, i: int, entry, key_name: str | None):
    """One camera entry with the field names of our schema (other tools' names mapped)."""
    if not isinstance(entry, dict):
        raise CameraFileError(
            f"{path}: cameras[{i}]: expected an object, got {type(entry).__name__}"
        )
    e = dict(entry)
    if "name" not in e and key_name is not None:
        e["name"] = key_name
    for ours, theirs in FIELD_ALIASES.items():
        for alias in theirs:
            if alias in e and ours not in e:
                e[ours] = e.pop(alias)
    for ours, theirs in (("width", "image_width"), ("height", "image_height")):
        if theirs in e and ours not in e:
            e[ours] = e.pop(theirs)
    if "R" in e and "rvec" not in e and np.shape(e["R"]) in ((3,), (3, 1), (1, 3)):
        e["rvec"] = e.pop("R")  # OpenCV's extrinsics as a Rodrigues vector
    if "rotation" in e and "R" not in e and "rvec" not in e:
        rot = e.pop("rotation")
        e["R" if np.shape(rot) == (3, 3) else "rvec"] = rot
    if "rvec" in e and np.shape(e["rvec"]) in ((3, 1), (1, 3)):
        e["rvec"] = np.asarray(e["rvec"], float).ravel().tolist()
    if "t" in e and np.shape(e["t"]) in ((3, 1), (1, 3)):
        e["t"] = np.asarray(e["t"], float).ravel().tolist()
    for alias in SIZE_ALIASES:
        if alias in e and ("width" not in e or "height" not in e):
            size = e.pop(alias)
            if not (isinstance(size, list | tuple) and len(size) == 2):
                raise CameraFileError(
                    f"{path}: camera {e.get('name')!r}: field {alias!r}: expected [width, height]"
                )
            w, h = size
            e["width"] = int(w) if isinstance(w, float) and w.is_integer() else w
            e["height"] = int(h) if isinstance(h, float) and h.is_integer() else h
    if isinstance(e.get("dist"), list):
        flat = np.asarray(e["dist"], dtype=object).ravel().tolist()
        if len(flat) in (8, 12, 14):
            try:
                extra = np.asarray(flat[5:], float)
            except (TypeError, ValueError):
                extra = np.ones(1)
            if np.any(extra != 0):
                raise CameraFileError(
                    f"{path}: camera {e.get('name')!r}: field 'dist': {len(flat)} OpenCV terms "
                    "with non-zero rational/thin-prism/tilt terms; jaxmocap's model is the "
                    "5-term one (k1 k2 p1 p2 k3): recalibrate with those terms fixed at 0"
                )
            flat = flat[:5]
        e["dist"] = flat
    return e


def _camera_entries(path: Path, data) -> list[dict]:
    """The list of camera entries of a parsed file, whichever layout it uses."""
    if isinstance(data, list):
        entries, keys = data, [None] * len(data)
    elif isinstance(data, dict):
        if "version" in data and data["version"] != CAMERAS_JSON_VERSION:
            raise CameraFileError(
                f"{path}: field 'version': expected {CAMERAS_JSON_VERSION} (or no version), "
                f"got {data['version']!r}"
            )
        if "cameras" in data:
            entries = data["cameras"]
            if isinstance(entries, dict):
                entries, keys = list(entries.values()), list(entries)
            else:
                keys = [None] * len(entries) if isinstance(entries, list) else []
        else:  # {name: camera, ...} (Pose2Sim / anipose / OpenCV dumps); "metadata" skipped
            items = [(k, v) for k, v in data.items()
                     if isinstance(v, dict) and k not in ("metadata", "meta")]  # fmt: skip
            entries, keys = [v for _, v in items], [str(v.get("name", k)) for k, v in items]
    else:
        raise CameraFileError(f"{path}: expected a JSON object with 'cameras' (or a list)")
    if not isinstance(entries, list) or not entries:
        raise CameraFileError(f"{path}: field 'cameras': expected a non-empty list")
    return [_canonical_entry(path, i, e, k) for i, (e, k) in enumerate(zip(entries, keys,
                                                                         strict=True))]


def _filestorage_value(node):
    """A cv2.FileNode as plain Python (matrices as nested lists, maps as dicts)."""
    if node.isMap():
        if "dt" in node.keys() and "data" in node.keys():
            return np.asarray(node.mat(), float).tolist()
        return {k: _filestorage_value(node.getNode(k)) for k in node.keys()}
    if node.isSeq():
        return [_filestorage_value(node.at(i)) for i in range(node.size())]
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return float(node.real())
    if node.isString():
        return node.string()
    return None


def _read_filestorage(path: Path) -> dict:
    """An OpenCV FileStorage file (YAML or XML, as ``cv2.FileStorage`` writes): one camera
    (``camera_matrix``, ``dist_coeffs``/``distortion_coefficients``, ``R``, ``T``,
    ``image_width``/``image_height`` at the top level, named after the file) or one map per
    camera."""
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file ({e.err})") \
            from None
    if not fs.isOpened():
        raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file")
    root = fs.root()
    data = {k: _filestorage_value(root.getNode(k)) for k in root.keys()}
    fs.release()
    k_names = ("K",) + FIELD_ALIASES["K"]
    if any(k in data for k in k_names):
        return {"cameras": [{"name": path.stem, **data}]}
    return data


def _file_kind(path: Path, head: str) -> str:
    """``json``, ``toml`` or ``filestorage``: by the file's content where it tells (an OpenCV
    FileStorage header, a JSON object, a TOML table header ``[cam_0]`` or ``key = value``),
    else by the suffix; one line if neither fits."""
    text = head.lstrip("\ufeff \t\r\n")
    first = text.split("\n", 1)[0].strip()
    suffix = path.suffix.lower()
    if text.startswith("%YAML") or (text.startswith("<?xml") and "<opencv_storage>" in head):
        return "filestorage"
    if suffix in (".json", ".toml"):
        return suffix[1:]
    if text.startswith("{"):
        return "json"
    if re.fullmatch(r"\[[A-Za-z_][\w.-]*\]", first) or re.match(r"[A-Za-z_][\w.-]*\s*=", first):
        return "toml"
    if text.startswith("[") or text[:1] in ('"', "-") or text[:1].isdigit():
        return "json"
    if suffix in (".yml", ".yaml", ".xml"):
        return "filestorage"
    raise CameraFileError(
        f"{path}: not a camera file jaxmocap reads: expected cameras.json (JSON), a "
        "calibration TOML (anipose / Pose2Sim / FreeMoCap) or an OpenCV FileStorage YAML/XML")


def _read_toml(path: Path) -> dict:
    import tomllib

    from jaxmocap.io.preflight import read_text

    text = read_text(path, "a calibration TOML (anipose / Pose2Sim / FreeMoCap)", CameraFileError)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise CameraFileError(f"{path}: not valid TOML: {e}") from None


def load_cameras(path: str | os.PathLike, dtype=None) -> tuple[list[Camera], list[str]]:
    """Read ``cameras.json`` (schema and accepted variants in the module docstring), a
    calibration TOML or an OpenCV FileStorage YAML/XML, told apart by content.

    Returns (cameras, names). Arrays get ``dtype`` (default: JAX's default float, float32
    unless x64 is on). Raises :class:`CameraFileError` naming the file, camera and field on
    any problem.
    """
    path = Path(path)
    dtype = jnp.result_type(float) if dtype is None else dtype
    try:
        with open(path, "rb") as f:
            head = f.read(4096).decode("utf-8", errors="replace")
        kind = _file_kind(path, head)
    except OSError:
        kind = "json"  # read_json says why it cannot be read
    if kind == "toml":
        data = _read_toml(path)
    elif kind == "filestorage":
        data = _read_filestorage(path)
    else:
        from jaxmocap.io.preflight import read_json

        data = read_json(path, "a cameras.json of `jaxmocap calibrate`", CameraFileError)
    cams, names = [], []
    for i, entry in enumerate(_camera_entries(path, data)):
        name, cam = _parse_camera(path, i, entry, dtype)
        if name in names:
            raise CameraFileError(f"{path}: camera {name!r}: field 'name': duplicate name")
        cams.append(cam)
        names.append(name)
    return cams, names


def save_cameras(
    path: str | os.PathLike, cams: Sequence[Camera] | Camera, names: Sequence[str] | None = None
) -> None:
    """Write cameras (a list or a stacked Camera) to ``cameras.json`` atomically.

    ``names`` default to ``cam0, cam1, ...``; they must be unique non-empty strings.
    """
    path = Path(path)
    cams = unstack_cameras(cams) if isinstance(cams, Camera) else list(cams)
    names = [f"cam{i}" for i in range(len(cams))] if names is None else list(names)
    if len(names) != len(cams):
        raise ValueError(f"save_cameras: {len(cams)} cameras but {len(names)} names")
    if len(set(names)) != len(names) or not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"save_cameras: names must be unique non-empty strings, got {names}")
    entries = []
    for name, cam in zip(names, cams, strict=True):
        if cam.K.ndim != 2:
            raise ValueError(f"save_cameras: camera {name!r} is batched; pass a list")
        entries.append(
            {
                "name": name,
                "width": int(cam.width),
                "height": int(cam.height),
                "K": np.asarray(cam.K, float).tolist(),
                "dist": np.asarray(cam.dist, float).tolist(),
                "R": np.asarray(cam.R, float).tolist(),
                "t": np.asarray(cam.t, float).tolist(),
            }
        )
    text = json.dumps({"version": CAMERAS_JSON_VERSION, "cameras": entries}, indent=2) + "\n"
    from jaxmocap.io.atomic import write_text  # one atomic-write mechanism for the package

    write_text(path, text)
