"""Where the automatic initialisation starts: its **anchor**.

Azad's initialisation (:func:`jaxmocap.trackers.stereo_pf.init`) places the root prior so that
the model's head lies on the triangulated head. On footage whose skin the colour model does not
find, no head is ever triangulated; the filter then starts from what it has instead of waiting
for it. The anchors, in order of preference:

* ``"head"``: the triangulated head (Azad's prior, :func:`~.filter.init` without a ``start``);
* ``"shirt"``: the shirt silhouette of both views (the foreground the edge cue is computed
  from): the centre of the thick core of the largest shirt region of each view (the torso:
  limbs in the shirt's colour are thinner) at the depth of the plane that best maps one view's
  region onto the other's, pushed back by half the torso's half depth (the sweep's plane lies
  between the body's visible surface and its axis), places the model's torso centre
  (:func:`shirt_start`). The core moves with the pose and the depth is coarse on a short
  baseline, so the root's spread about it is wider than about a head (:data:`SHIRT_ROOT_STD`,
  :data:`SHIRT_DEPTH_STD`). The initialisation's annealing reads the place of the model's head
  above the anchor (the anchor plus the model's head-to-torso offset at rest) as the head in
  the distance cue: the edge cue's torso lines are parallel to its axis and leave the torso
  free to slide along it. The hands found, if any, pull the annealing as on a head start
  (without a head the blob tracker seldom names any, :mod:`jaxmocap.blobs`);
* ``"hands"``: no shirt region but hand blobs: the mean of the valid blobs stands in for the
  head (the prior's own rule);
* ``"none"``: nothing seen: the fallback root, 10x the spread (offline only, on frame 0).

On line (:class:`Starter`) the filter waits up to :data:`START_WAIT` frames for a head (the
blob tracker needs a few frames to acquire its entities, :mod:`jaxmocap.blobs`) and then starts
on the first frame with any anchor. Offline (:func:`start_frame`) the same rule picks the frame.
"""

from __future__ import annotations

import cv2
import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxmocap import camera as camlib
from jaxmocap.body.roles import rest_transforms
from jaxmocap.pf.cues import Observation

START_WAIT = 5  # frames waited for a triangulated head before starting from the shirt (0.2 s)
SHIRT_MIN_PX = 60  # px of the largest shirt region in each view for a shirt anchor
JOIN_PX = 4  # shirt pieces this close (px, half the gap) belong to one region
SWEEP_DEPTH_M = (0.5, 10.0)  # the silhouettes' plane sweep: nearest and farthest depth, m
SWEEP_STEP_PX = 0.5  # its planes' spacing in disparity, px
CORE_SHARE = 0.5  # the torso's core: pixels this share of the region's thickest point deep
# std of the root (m) about the shirt-derived one: world x, y, z across the rig's view, and
# along it (from the cameras' midpoint to the anchor; the sweep's depth is the coarse one). Dev
# split (as below): the anchor within 5 cm across, 7 cm up, 12 cm along the view
SHIRT_ROOT_STD = (0.04, 0.04, 0.05)
SHIRT_DEPTH_STD = 0.08
# the sweep's plane lies between the body's visible surface and the torso's axis: this share of
# the torso's half depth behind it (dev split pf_00/03/06/09/13, first 6 frames: the anchor's
# depth error -5 +- 6 cm with 1.0, +7 +- 5 cm with 0)
SURFACE_TO_AXIS = 0.5
ANCHORS = ("head", "shirt", "hands", "none")


class Start(eqx.Module):
    """A non-head anchor of the root prior (:func:`~.filter.init`'s ``start``): the root is
    drawn so that the model point ``rest`` (root frame, rest pose) lies on ``point`` (world),
    with a Gaussian spread of covariance ``cov`` (3x3, m^2) about it."""

    point: Float[Array, " 3"]
    rest: Float[Array, " 3"]
    cov: Float[Array, "3 3"]


def _largest_region(mask: np.ndarray) -> np.ndarray | None:
    """The shirt pixels of ``mask`` (bool) in its largest region, or None when they are fewer
    than :data:`SHIRT_MIN_PX`: regions are the 8-connected ones of the mask closed over gaps of
    up to 2 :data:`JOIN_PX` pixels, so a silhouette the segmentation breaks into pieces (a
    chest, a belly and the legs apart) stays one region; only its own pixels count (uint8)."""
    m = mask.astype(np.uint8)
    k = np.ones((2 * JOIN_PX + 1, 2 * JOIN_PX + 1), np.uint8)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(
        cv2.morphologyEx(m, cv2.MORPH_CLOSE, k), 8)
    if n < 2:
        return None
    areas = np.bincount(labels[m > 0], minlength=n)[1:]  # the mask's own pixels per region
    i = 1 + int(np.argmax(areas))
    if areas[i - 1] < SHIRT_MIN_PX:
        return None
    return m * (labels == i)


def torso_core(region: np.ndarray) -> np.ndarray:
    """The centre (x, y) px of the torso in one view's shirt region (uint8 0 / 1): the
    centroid of its thick core, the pixels at least :data:`CORE_SHARE` of the region's largest
    distance to the border inside it. Arms, legs and sleeves in the shirt's colour are thinner
    than the torso and fall out of the core; a plain centroid moves with them."""
    dist = cv2.distanceTransform(region, cv2.DIST_L2, 5)
    y, x = np.nonzero(dist >= CORE_SHARE * dist.max())
    return np.array([x.mean(), y.mean()], np.float64)


def silhouette_depth(cams: list, regions: list[np.ndarray]) -> float | None:
    """The depth (m, along camera 0's axis) of the fronto-parallel plane through which view
    0's shirt region best maps onto view 1's (a plane sweep of the silhouettes: the
    intersection over union of the warped region with view 1's, over planes evenly spaced in
    disparity, :data:`SWEEP_STEP_PX` apart, refined by a parabola through the best three).
    All the region's pixels vote, so the depth is steadier than that of two triangulated
    centroids, whose disparity moves by pixels when the two views' regions differ (one pixel
    of disparity is ~13 cm of depth at 2 m on a 10 cm baseline). Lens distortion is ignored
    (a plane maps by a homography only without it). None when no plane overlaps."""
    K0, K1 = (np.asarray(c.K, np.float64) for c in cams)
    R0, R1 = (np.asarray(c.R, np.float64) for c in cams)
    t0, t1 = (np.asarray(c.t, np.float64) for c in cams)
    R = R1 @ R0.T
    t = t1 - R @ t0
    base = float(np.linalg.norm(t))
    fb = 0.5 * (K0[0, 0] + K1[0, 0]) * base  # disparity (px) x depth (m)
    inv = np.arange(1.0 / SWEEP_DEPTH_M[1], 1.0 / SWEEP_DEPTH_M[0], SWEEP_STEP_PX / fb)
    a = regions[0].astype(np.float32)
    b = regions[1].astype(np.float32)
    h, w = b.shape
    n = np.array([0.0, 0.0, 1.0])
    K0_inv = np.linalg.inv(K0)
    scores = []
    for u in inv:  # the plane z = 1 / u in camera 0: X1 = (R + t n^T u) X0
        H = K1 @ (R + np.outer(t, n) * u) @ K0_inv
        warped = cv2.warpPerspective(a, H, (w, h), flags=cv2.INTER_LINEAR)
        inter = float(np.sum(np.minimum(warped, b)))
        scores.append(inter / max(float(np.sum(np.maximum(warped, b))), 1.0))
    scores = np.asarray(scores)
    k = int(np.argmax(scores))
    if scores[k] <= 0:
        return None
    u = inv[k]
    if 0 < k < len(inv) - 1:  # the parabola's vertex through the best three
        s0, s1, s2 = scores[k - 1 : k + 2]
        den = s0 - 2 * s1 + s2
        if den < 0:
            u += 0.5 * (s0 - s2) / den * (inv[1] - inv[0])
    return float(1.0 / u)


def torso_rest(params) -> tuple[np.ndarray, float] | None:
    """The model's torso at rest (root at the origin, all joints 0): the centre of its contour
    cylinder (root frame, m) and its half depth (m; front to back); None when the contour
    model has no limb named ``torso`` (explicit limbs: nothing to place on the shirt)."""
    lm = params.likelihood.limbs
    if "torso" not in lm.names:
        return None
    k = lm.names.index("torso")
    rest = rest_transforms(params.model.chain)[lm.link[k]]
    ends = [rest[:3, :3] @ np.asarray(p[k], np.float64) + rest[:3, 3] for p in (lm.p0, lm.p1)]
    return 0.5 * (ends[0] + ends[1]), float(lm.depth[k])


def shirt_anchor(params, foreground: np.ndarray,
                 torso: tuple[np.ndarray, float] | None = None) -> np.ndarray | None:
    """The torso's centre in the world (m) from the two views' foreground (2, h, w): each
    view's :func:`torso_core` back-projected to the shirt's :func:`silhouette_depth` plus
    :data:`SURFACE_TO_AXIS` of the torso's half depth (:func:`torso_rest`: the sweep aligns
    the body's surface, the axis is behind it) -- view 1's at the depth of view 0's point in
    view 1 -- the two points averaged; None when either view has no shirt region of
    :data:`SHIRT_MIN_PX` pixels, no depth is found or the model has no torso limb. ``torso``:
    :func:`torso_rest` where the caller has it already."""
    torso = torso_rest(params) if torso is None else torso
    cams = camlib.unstack_cameras(params.likelihood.cams)
    regions = [_largest_region(np.asarray(foreground[c]) > 0.5) for c in range(2)]
    if torso is None or any(r is None for r in regions):
        return None
    depth = silhouette_depth(cams, regions)
    if depth is None:
        return None
    depth += SURFACE_TO_AXIS * torso[1]
    points = []
    for cam, region in zip(cams, regions, strict=True):
        if points:  # view 1: at the depth of view 0's point
            depth = float(np.asarray(camlib.to_camera(cam, jnp.asarray(points[0])))[2])
        o, d = (np.asarray(a, np.float64)
                for a in camlib.pixel_rays(cam, jnp.asarray(torso_core(region))))
        points.append(o + d * depth / (np.asarray(cam.R, np.float64) @ d)[2])
    return np.mean(points, axis=0)


def shirt_start(params, foreground: np.ndarray) -> Start | None:
    """The root prior's anchor from the shirt silhouette (:func:`shirt_anchor`; None without
    one): the model's counterpart is its torso centre at rest (:func:`torso_rest`); the spread
    is :data:`SHIRT_ROOT_STD` across the rig's view and :data:`SHIRT_DEPTH_STD`
    along it (from the cameras' midpoint to the anchor)."""
    torso = torso_rest(params)
    point = None if torso is None else shirt_anchor(params, foreground, torso)
    if point is None:
        return None
    rest = torso[0]
    cams = camlib.unstack_cameras(params.likelihood.cams)
    mid = np.mean([np.asarray(camlib.camera_center(c), np.float64) for c in cams], axis=0)
    view = point - mid
    view /= np.linalg.norm(view)
    lateral = np.diag(np.square(SHIRT_ROOT_STD))
    proj = np.eye(3) - np.outer(view, view)
    cov = proj @ lateral @ proj + SHIRT_DEPTH_STD**2 * np.outer(view, view)
    dt = params.prior_lower.dtype
    return Start(point=jnp.asarray(point, dt), rest=jnp.asarray(rest, dt),
                 cov=jnp.asarray(cov, dt))


def choose(params, valid, foreground, waited: int, heads: bool = True
           ) -> tuple[str, Start | None] | None:
    """The anchor of a frame on which the filter has not started yet, ``waited`` frames after
    the first (``valid`` (3,) its triangulated head and hands, ``foreground`` (2, h, w) its
    shirt masks): ``("head", None)`` when its head is triangulated; from the
    :data:`START_WAIT`-th frame on without one ``("shirt", start)``, else ``("hands", None)``
    when a hand is; else None (keep waiting). ``heads=False`` never starts from the head (a
    measurement of the other anchors where the head is found)."""
    valid = np.asarray(valid)
    if heads and valid[0]:
        return "head", None
    if waited + 1 < START_WAIT:
        return None
    start = shirt_start(params, np.asarray(foreground))
    if start is not None:
        return "shirt", start
    if valid.any():
        return "hands", None
    return None


class Starter:
    """The on-line start rule (:func:`choose`) frame by frame: :meth:`__call__` returns the
    anchor to initialise on, or None to wait."""

    def __init__(self, params):
        self.params, self.waited = params, 0

    def __call__(self, obs: Observation) -> tuple[str, Start | None] | None:
        out = choose(self.params, obs.valid, obs.foreground, self.waited)
        self.waited += 1
        return out


def start_frame(params, observations: Observation, heads: bool = True
                ) -> tuple[int, str, Start | None]:
    """The offline start of a sequence (observations with a leading time axis): the frame and
    anchor of :func:`choose` (``heads``: its switch) applied frame by frame, as on line; with
    no anchor on any frame, frame 0 and ``"none"`` (the fallback root)."""
    valid = np.asarray(observations.valid)
    n = valid.shape[0]
    for t in range(n):  # a sequence shorter than the wait is waited out at its last frame
        got = choose(params, valid[t], observations.foreground[t],
                     t if t < n - 1 else max(t, START_WAIT - 1), heads)
        if got is not None:
            return t, got[0], got[1]
    return 0, "none", None


__all__ = ["ANCHORS", "START_WAIT", "Start", "Starter", "choose", "shirt_anchor",
           "shirt_start", "silhouette_depth", "start_frame", "torso_core", "torso_rest"]
