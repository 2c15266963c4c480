"""Pinhole cameras with OpenCV distortion: projection, back-projection, N-view triangulation,
epipolar geometry (the ``cameras.json`` file: :mod:`jaxmocap.io.cameras`).

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
"""

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from jaxmocap.rotations import skew

ArrayIn = Array | np.ndarray  # inputs accept NumPy arrays too
VectorLike = ArrayLike | Sequence  # also nested lists of numbers

__all__ = [
    "Camera",
    "camera_center",
    "distort_normalized",
    "epipolar_distance",
    "epipolar_distance_undistorted",
    "fundamental_matrix",
    "look_at",
    "pixel_rays",
    "project",
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
