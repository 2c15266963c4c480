"""The head placed as a sphere fitted to the skin outline of both views (issue 39 decision 2;
not in Azad's paper, whose head is the triangulated centroid of the face's skin blob).

A lamp from one side lights part of the head: the skin map holds the lit part, and its
centroid lies on the lit front of the face, 3-6 cm off the head's centre in depth on the
test world's dev sequences (``docs/results/world_pf_parts.md``). The outline of the head
against the background, where it is lit, is the projection of the head itself, whatever the
light. So the head is a sphere of the body's head radius (the largest geom of the ``head``
link role, :func:`head_sphere`) whose centre C (world) is fitted to the outline of the
head's skin region in both views: the midpoints between the region's border pixels and their
neighbours that are neither skin nor shirt (:func:`outline_pixels`). A point with unit ray d
(camera frame) lies on the outline when the angle between d and the ray to C equals the
sphere's angular radius asin(r / |C_cam|); the residual is that angle difference times the
focal length (px, exact anywhere in the image, not a circle approximation).

Part of that border is the terminator between the lit and the dark side, inside the disc.
So: (1) each view's disc centre is found first by a Hough vote of the border points along
their inward normals at the projected radius (:func:`hough_centre`: the rim's points agree,
the terminator's scatter); (2) the start is the direction of the two Hough centres
triangulated, at the distance of the skin centroid pushed back by half a radius (a
whole-pixel Hough disparity is 5-10 cm of depth); (3) Gauss-Newton with Tukey's biweight
(scales :data:`INSIDE_PX` / :data:`OUTSIDE_PX`: the terminator and the neck drop out), the
radius's log-scale and the start held by priors (:func:`fit_centre`, jitted, a fixed number of
steps). Dev split of the test world (pf_00, 03, 06, 09, 12, 13), the measured head within
4 cm of the truth on the frames it is visible in both views: 9% (centroid) -> 48% (this);
its lateral error 2.3-4.3 -> 0.7-3.2 cm, depth 3.8-5.9 -> 1.8-4.8 cm (medians per sequence,
``docs/results/stereo_pf_round2.md``).
"""

from __future__ import annotations

import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxmocap.body import BodyModel, keypoint_index, keypoints, require_roles
from jaxmocap.body.chain import fk
from jaxmocap.body.roles import geom_roles, geom_support, geom_volume
from jaxmocap.camera import Camera

MAX_POINTS = 256  # outline pixels per view (subsampled evenly beyond)
MIN_POINTS = 12  # fewer in a view: no fit (the centroid stays)
# Tukey scales of outline points inside the disc (terminator, shadow) and outside it (neck,
# hands); dev split, measured head within 4 cm: inside 2 / 3 / 4 px -> 47 / 48 / 47%, outside
# 4 / 8 px -> 48 / 47%
INSIDE_PX = 3.0
OUTSIDE_PX = 4.0
ITERATIONS = 20
MAX_STEP_M = 0.02  # the longest Gauss-Newton step
# std of the start (its depth: the pushed-back centroid's); dev: 0.03 / 0.06 / 0.15 / 0.3 / 1 m
# -> 47 / 48 / 48 / 43 / 17% of the heads within 4 cm (the outlines alone hold depth weakly)
PRIOR_M = 0.06
PRIOR_PX = 1.0
RADIUS_STD = 0.3  # prior std of the head's log radius around the body's
WINDOW = 2.5  # search window half-size in projected head radii
MAX_SHIFT_M = 0.25  # a fit this far from the centroid's start is refused (centroid stays)


def head_sphere(model: BodyModel) -> tuple[float, np.ndarray]:
    """(radius m, offset m (3,) from the sphere's centre to the ``head`` keypoint at the rest
    pose, world frame) from the largest geom of the ``head`` link role: its radius is the
    median of its half-extents along its own axes (a sphere's radius; an ellipsoid's or a
    capsule's middle one)."""
    roles = require_roles(model, "stereo_pf.head")
    geo = model.geometry
    gs = geom_roles(model.chain, geo, dict(roles.links), roles.skin_geoms).get("head", [])
    if not gs:
        from jaxmocap.errors import InputError

        raise InputError(f"{roles.source}: head_sphere: the head link role has no geometry")
    kinds, sizes = np.asarray(geo.kind), np.asarray(geo.size, np.float64)
    g = max(gs, key=lambda i: geom_volume(int(kinds[i]), sizes[i]))
    pose = np.asarray(geo.pose, np.float64)[g]
    ext = [geom_support(int(kinds[g]), sizes[g], pose[:3, :3], pose[:3, k]) for k in range(3)]
    tr = np.asarray(fk(model.chain, jnp.zeros(model.n_dof)), np.float64)
    centre = (tr[int(np.asarray(geo.link)[g])] @ pose)[:3, 3]
    kp = np.asarray(keypoints(model, jnp.zeros(model.n_dof)), np.float64)
    head = kp[keypoint_index(model, "head")[0]]
    return float(np.median(ext)), head - centre


def _residual(c, rays, rot, t, f, radius):
    """Per view and pixel: f (angle(d, C_cam) - asin(r / |C_cam|)), px."""
    cc = jnp.einsum("vij,j->vi", rot, c) + t  # (2, 3)
    n = jnp.linalg.norm(cc, axis=-1, keepdims=True)
    u = cc / n
    cos = jnp.einsum("vni,vi->vn", rays, u)
    # (the padding's zero rays: a safe norm, no 0/0 in the Jacobian)
    sin = jnp.sqrt(jnp.sum(jnp.cross(rays, u[:, None, :]) ** 2, axis=-1) + 1e-12)
    ang = jnp.arctan2(sin, cos)
    return f[:, None] * (ang - jnp.arcsin(jnp.clip(radius / n, 0.0, 0.99)))


@functools.partial(jax.jit, static_argnames=("iterations",))
def fit_centre(
    rays: Float[Array, "2 n 3"], weight: Float[Array, "2 n"], rot: Float[Array, "2 3 3"],
    t: Float[Array, "2 3"], f: Float[Array, " 2"], radius: Float[Array, ""],
    c0: Float[Array, " 3"], prior_m: Float[Array, ""], radius_std: Float[Array, ""],
    iterations: int = ITERATIONS,
) -> Float[Array, " 3"]:
    """The sphere centre (world) whose outline in both views passes through the outline
    pixels ``rays`` (unit, camera frames; ``weight`` 0 for padding), from ``c0``:
    iteratively reweighted, damped Gauss-Newton with the redescending weights of the module
    docstring. The radius is fitted too (log-scale, prior std ``radius_std`` around
    ``radius``): a head not quite the body's sphere would otherwise bend the depth to fit
    its apparent size; the depth then comes from the two outlines' disparity."""

    def res(p):
        return _residual(p[:3], rays, rot, t, f, radius * jnp.exp(p[3]))

    n = jnp.maximum(jnp.sum(weight), 1.0)
    # priors in px^2 units: one px per prior_m of centre, per radius_std of log radius, n times
    lam = n * jnp.stack([1.0 / prior_m**2] * 3 + [1.0 / radius_std**2]) * PRIOR_PX**2
    p0 = jnp.concatenate([c0, jnp.zeros(1, c0.dtype)])

    def step(_, p):
        e = res(p)
        z = e / jnp.where(e > 0, OUTSIDE_PX, INSIDE_PX)
        w = weight * jnp.where(jnp.abs(z) < 1.0, (1.0 - z**2) ** 2, 0.0)  # Tukey's biweight
        jac = jax.jacfwd(res)(p).reshape(-1, 4)
        wv, ev = w.reshape(-1), e.reshape(-1)
        eye = jnp.eye(4, dtype=p.dtype)
        a = jac.T @ (wv[:, None] * jac) + jnp.diag(lam) + 1e-6 * eye * jnp.sum(wv)
        delta = jnp.linalg.solve(a, jac.T @ (wv * ev) + lam * (p - p0))
        # a trust region of MAX_STEP_M per step: depth is weakly held (a short baseline)
        return p - delta * jnp.minimum(1.0, MAX_STEP_M / (jnp.linalg.norm(delta[:3]) + 1e-12))

    return jax.lax.fori_loop(0, iterations, step, p0)[:3]


def outline_pixels(skin: np.ndarray, foreground: np.ndarray, uv: np.ndarray, rho: float
                   ) -> np.ndarray:
    """(n, 2) points (u, v) on the border of the skin region around ``uv`` (the one holding
    most skin within ``rho`` px of it, in a window of :data:`WINDOW` rho): the midpoints
    between a region pixel and each of its 4-neighbours that is neither skin nor shirt
    (``foreground``)."""
    h, w = skin.shape
    half = int(np.ceil(WINDOW * rho)) + 2
    x0, y0 = max(int(uv[0]) - half, 0), max(int(uv[1]) - half, 0)
    x1, y1 = min(int(uv[0]) + half + 1, w), min(int(uv[1]) + half + 1, h)
    if x1 - x0 < 3 or y1 - y0 < 3:
        return np.zeros((0, 2))
    crop = np.asarray(skin[y0:y1, x0:x1], np.uint8)
    n, lab = cv2.connectedComponents(crop, connectivity=8)
    if n < 2:
        return np.zeros((0, 2))
    yy, xx = np.mgrid[y0:y1, x0:x1]
    near = (xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= rho**2
    counts = np.bincount(lab[near], minlength=n)
    counts[0] = 0
    k = int(np.argmax(counts))
    if counts[k] == 0:
        return np.zeros((0, 2))
    region = np.pad(lab == k, 1)
    free = np.pad(~np.asarray(skin[y0:y1, x0:x1], bool) & ~np.asarray(
        foreground[y0:y1, x0:x1], bool), 1)
    inner = region[1:-1, 1:-1]
    pts = []
    # the rim lies between a region pixel and its free neighbour: the midpoint of each such
    # pair (the border pixels' own centres lie half a pixel inside: on the dev sequences'
    # 12-20 px heads that is 3-4% of the radius, 5-10 cm of depth)
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        nb = free[1 + dy:1 + dy + inner.shape[0], 1 + dx:1 + dx + inner.shape[1]]
        ys, xs = np.nonzero(inner & nb)
        # the crop's own edge is no outline (the region may continue beyond it)
        keep = (xs + x0 > 0) & (ys + y0 > 0) & (xs + x0 < w - 1) & (ys + y0 < h - 1)
        pts.append(np.stack([xs[keep] + x0 + 0.5 * dx, ys[keep] + y0 + 0.5 * dy], axis=1))
    return np.concatenate(pts).astype(np.float64)


def hough_centre(skin: np.ndarray, px: np.ndarray, rho: float) -> np.ndarray | None:
    """The image centre (u, v) of the disc whose rim the outline pixels ``px`` follow: each
    votes at ``rho`` (+-15%) along its inward normal (the gradient of the blurred skin map).
    The rim's pixels agree on the disc's centre; the terminator's (lit / dark side) curve the
    other way or not at all, and scatter their votes."""
    if len(px) == 0:
        return None
    blur = cv2.GaussianBlur(np.asarray(skin, np.float32), (0, 0), 1.5)
    gx = cv2.Sobel(blur, cv2.CV_32F, 1, 0, ksize=3)
    gy = cv2.Sobel(blur, cv2.CV_32F, 0, 1, ksize=3)
    iu = np.clip(np.round(px[:, 0]).astype(int), 0, skin.shape[1] - 1)
    iv = np.clip(np.round(px[:, 1]).astype(int), 0, skin.shape[0] - 1)
    g = np.stack([gx[iv, iu], gy[iv, iu]], axis=1).astype(np.float64)
    g /= np.maximum(np.linalg.norm(g, axis=1, keepdims=True), 1e-9)
    lo = px.min(axis=0) - 2 * rho
    size = (np.ceil(px.max(axis=0) + 2 * rho - lo) + 1).astype(int)
    acc = np.zeros((size[1], size[0]), np.float32)
    for scale in np.linspace(0.85, 1.15, 7):
        votes = np.round(px + scale * rho * g - lo).astype(int)
        np.add.at(acc, (votes[:, 1], votes[:, 0]), 1.0)
    acc = cv2.GaussianBlur(acc, (0, 0), 1.0)
    y, x = np.unravel_index(int(np.argmax(acc)), acc.shape)
    return np.array([x, y], np.float64) + lo


def fit_head(cams: Camera, skins, foregrounds, start: np.ndarray, radius: float,
             prior_m: float | None = None) -> np.ndarray | None:
    """The head sphere's centre (world, m) fitted to the outline of the head's skin region in
    both views (stacked ``cams``), started from the triangulated skin centroid ``start``
    pushed back by half a radius and held to that start with a std of ``prior_m`` (depth is
    weakly seen at a short baseline); None where a view has fewer than :data:`MIN_POINTS`
    outline pixels or the fit runs off (the centroid then stays)."""
    rot, t, K = np.asarray(cams.R, np.float64), np.asarray(cams.t, np.float64), \
        np.asarray(cams.K, np.float64)
    dist = np.asarray(cams.dist, np.float64)
    prior_m = PRIOR_M if prior_m is None else prior_m
    centres = -np.einsum("vji,vj->vi", rot, t)
    back = start - centres.mean(axis=0)
    c0 = start + 0.5 * radius * back / max(np.linalg.norm(back), 1e-9)
    rays = np.zeros((2, MAX_POINTS, 3))
    weight = np.zeros((2, MAX_POINTS))
    hough = []
    for v in range(2):
        xc = rot[v] @ c0 + t[v]
        if xc[2] <= radius:
            return None
        rho = K[v, 0, 0] * radius / xc[2]
        uv = cv2.projectPoints(xc[None], np.zeros(3), np.zeros(3), K[v], dist[v])[0][0, 0]
        px = outline_pixels(skins[v], foregrounds[v], uv, rho)
        if len(px) < MIN_POINTS:
            return None
        hough.append(hough_centre(skins[v], px, rho))
        if len(px) > MAX_POINTS:
            px = px[np.linspace(0, len(px) - 1, MAX_POINTS).astype(int)]
        xy = cv2.undistortPoints(px[:, None, :], K[v], dist[v])[:, 0, :]
        d = np.concatenate([xy, np.ones((len(xy), 1))], axis=1)
        rays[v, : len(d)] = d / np.linalg.norm(d, axis=1, keepdims=True)
        weight[v, : len(d)] = 1.0
    # the start: the two views' Hough centres triangulated (the lit centroid lies on the lit
    # side; the rim's centre does not), at the start's depth if they disagree
    uv = np.stack(hough)
    xy = np.stack([cv2.undistortPoints(uv[v][None, None], K[v], dist[v])[0, 0] for v in range(2)])
    rays_c = [rot[v].T @ np.array([xy[v, 0], xy[v, 1], 1.0]) for v in range(2)]
    a = np.stack([rays_c[0], -rays_c[1]], axis=1)
    depth, *_ = np.linalg.lstsq(a, centres[1] - centres[0], rcond=None)
    tri = 0.5 * (centres[0] + depth[0] * rays_c[0] + centres[1] + depth[1] * rays_c[1])
    if np.all(depth > 0) and np.linalg.norm(tri - c0) < MAX_SHIFT_M:
        # the direction from the rims, the distance from the centroid (a whole-pixel Hough
        # disparity is 5-10 cm of depth; the centroid's is sub-pixel, its bias the half radius)
        mid = centres.mean(axis=0)
        c0 = mid + (tri - mid) / np.linalg.norm(tri - mid) * np.linalg.norm(c0 - mid)
    dt = np.dtype(cams.K.dtype)
    c = np.asarray(fit_centre(*(jnp.asarray(a, dt) for a in (
        rays, weight, rot, t, K[:, 0, 0], radius, c0, prior_m, RADIUS_STD)),
        iterations=ITERATIONS),
        np.float64)
    if not np.all(np.isfinite(c)) or np.linalg.norm(c - c0) > MAX_SHIFT_M:
        return None
    return c


__all__ = ["fit_centre", "fit_head", "head_sphere", "outline_pixels"]
