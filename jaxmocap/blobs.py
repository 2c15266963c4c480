"""Hand and head tracking from skin-colour blobs in a calibrated stereo pair (Azad et al. 2007,
§IV and §III-C).

Per stereo frame, on the host (OpenCV + NumPy, one small jitted geometry call):

1. **blobs**: connected components of each skin map (``cv2.connectedComponentsWithStats``,
   8-connectivity) with at least ``min_area`` pixels, largest first;
2. **merges**: the tracked entities' predicted 3D positions are projected into both images; a
   blob that holds the projections of two entities is a *merged* blob (hands and head "fall
   together", §IV) -- it is not used, and the entities in it are carried by their motion model;
3. **stereo matching** (§IV): left/right blob pairs are accepted when their symmetric epipolar
   distance (pixels, lens distortion removed), their area ratio ``min/max`` and their
   bounding-box aspect-ratio ratio pass the thresholds and the triangulated point lies in front
   of both cameras; pairs are taken one-to-one, cheapest first. Blobs without a consistent
   partner -- skin-coloured background seen in one view -- are discarded;
4. **triangulation** of the matched blob centroids (:func:`jaxmocap.camera.triangulate`);
5. **tracking** with a linear motion model per entity (head, left hand, right hand):
   ``x_pred = x + v`` (metres, per frame). A candidate within ``gate`` metres of an entity's
   prediction updates it (``v`` from the difference of successive positions, exponentially
   smoothed); an entity without a candidate -- occluded or merged -- is *predicted* for up to
   ``max_coast`` frames and then declared *missing*. A missing entity -- or a coasting one
   whose prediction found no candidate in its gate -- is re-acquired by the nearest unclaimed
   candidate within ``reacquire`` metres of where it was last seen. A blob touching the image
   border is not matched (its centroid is biased by the cut: on a punch leaving the image it
   triangulated 45 cm off). ``coast_damping`` < 1 decays the velocity while coasting (the
   default 1.0 is Azad's plain linear model).

We track the matched (triangulated) blobs in 3D rather than each image's blobs in 2D: it is the
same linear motion model for the same entities, but gating in metres is independent of the
image and the identity of an entity is the same in both views by construction.

Identities (§III-C uses c_1, c_2, c_3 for left hand, right hand, head; we order them
``head, l_hand, r_hand`` as the body keypoints) are assigned once, at initialisation: of the
three largest candidates the highest (world Z up) is the head, and of the two others the hand
on the subject's left -- the camera's right when the subject faces the cameras -- is the left
hand. From then on the identities are kept by tracking (a hand crossing to the other side stays
the same hand). When all three are missing the tracker initialises again. With the
plausibility gate of :func:`update` (``reach``; not in the paper) the tracker may start on the
head alone, and a missing hand is re-acquired from any candidate within reach on its side of
the head.

Output per frame: ``points3d`` (3, 3) metres and ``valid`` (3,) bool. Invalid entities have
``points3d = 0``, Azad's convention for a missing c_i (§III-D), so the distance cue ignores them.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Sequence

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxmocap import camera as camlib
from jaxmocap._config import side_device

ENTITY_NAMES = ("head", "l_hand", "r_hand")  # the body model's keypoint names
HEAD, LEFT_HAND, RIGHT_HAND = 0, 1, 2
MISSING, MEASURED, PREDICTED = 0, 1, 2  # per-entity status codes

# --- defaults (Azad §IV names the steps but gives no thresholds; ours are for 320x240) -------
MIN_BLOB_AREA = 15  # px; a hand 2.5 m away at f = 300 px covers ~100 px
MAX_BLOBS = 8  # blobs kept per image, largest first (fixed size of the geometry kernel)
MAX_EPIPOLAR_PX = 2.5  # symmetric epipolar distance of blob centroids, px
MIN_AREA_RATIO = 0.5  # min(area_l, area_r) / max(area_l, area_r)
MIN_ASPECT_RATIO = 0.6  # same for the bounding-box height / width ratios
MIN_DEPTH_M = 0.2  # triangulated point in front of both cameras, metres
MAX_DEPTH_M = 10.0
GATE_M = 0.15  # association radius around the predicted position, metres
GATE_GROWTH_M = 0.03  # gate growth per predicted (coasting) frame, metres
MAX_COAST = 8  # frames carried by the motion model before "missing" (0.32 s at 25 Hz)
REACQUIRE_M = 0.6  # radius around the last seen position for re-acquiring a missing entity
VELOCITY_SMOOTHING = 0.6  # weight of the newest difference in the velocity estimate
# two views and ~0.1 px centroid noise: the DLT on undistorted normalised coordinates is within
# a fraction of a millimetre of the reprojection-error minimiser, and compiles in half the time
REFINE_TRIANGULATION = False
MAX_AREA_CHANGE = 0.3  # a matched blob pair shrinking/growing more than this per frame is
# treated as (partly) occluded: its centroid is biased, the entity is predicted instead ...
AREA_PATIENCE = 2  # ... unless the new size persists: after this many consecutive rejected
# frames the blob is accepted at its new size (a hand turning or nearing the cameras; without
# it a dance_b hand was coasted for 8 frames while seen, 85 cm off at the end)
REPORT_COAST = MAX_COAST  # coasting frames for which the predicted position is still output as
# valid (the entity is tracked internally up to max_coast either way); fewer hands the distance
# cue only measured points -- a hand hidden behind the torso drifts with its old velocity
COAST_DAMPING = 1.0  # velocity factor per coasting frame: a hand hidden mid-swing stops near
# where it vanished instead of flying on (undamped, 8 coasting frames of a 25 Hz punch carried
# the hand 1-1.7 m away on our held-out clips; the distance cue then pulls the arm off)


@dataclasses.dataclass(frozen=True)
class BlobParams:
    """Thresholds of blob detection, stereo matching and tracking (defaults above)."""

    min_area: int = MIN_BLOB_AREA
    max_blobs: int = MAX_BLOBS
    max_epipolar_px: float = MAX_EPIPOLAR_PX
    min_area_ratio: float = MIN_AREA_RATIO
    min_aspect_ratio: float = MIN_ASPECT_RATIO
    min_depth: float = MIN_DEPTH_M
    max_depth: float = MAX_DEPTH_M
    gate: float = GATE_M
    gate_growth: float = GATE_GROWTH_M
    max_coast: int = MAX_COAST
    report_coast: int = REPORT_COAST
    reacquire: float = REACQUIRE_M
    velocity_smoothing: float = VELOCITY_SMOOTHING
    max_area_change: float = MAX_AREA_CHANGE
    coast_damping: float = COAST_DAMPING
    area_patience: int = AREA_PATIENCE
    subject_faces_cameras: bool = True
    refine_triangulation: bool = REFINE_TRIANGULATION

    def __post_init__(self):
        for name in ("min_area", "max_blobs", "max_coast", "report_coast", "area_patience"):
            v = getattr(self, name)
            if not isinstance(v, int) or v < (1 if name == "max_blobs" else 0):
                raise ValueError(f"BlobParams.{name}: expected a non-negative int, got {v!r}")
        for name in ("max_epipolar_px", "gate", "reacquire", "max_depth"):
            if not getattr(self, name) > 0:
                raise ValueError(f"BlobParams.{name}: expected > 0, got {getattr(self, name)!r}")
        for name in ("min_area_ratio", "min_aspect_ratio", "velocity_smoothing", "coast_damping"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(
                    f"BlobParams.{name}: expected a value in [0, 1], got {getattr(self, name)!r}"
                )
        if not 0 <= self.max_area_change < 1:
            raise ValueError(
                f"BlobParams.max_area_change: expected a value in [0, 1), got "
                f"{self.max_area_change!r}"
            )


@dataclasses.dataclass(frozen=True)
class Blobs:
    """Skin blobs of one image, largest first (``n <= max_blobs``)."""

    centroid: Float[np.ndarray, "n 2"]  # (u, v) px, OpenCV pixel centres
    area: Int[np.ndarray, " n"]  # px
    bbox: Int[np.ndarray, "n 4"]  # x, y, width, height px
    labels: Int[np.ndarray, "h w"]  # 0 background, i + 1 for blob i, -1 small/dropped blobs

    @property
    def aspect(self) -> Float[np.ndarray, " n"]:
        """Bounding-box height / width."""
        return self.bbox[:, 3] / self.bbox[:, 2]


def detect_blobs(mask: np.ndarray, params: BlobParams = BlobParams()) -> Blobs:
    """Connected components (8-connected) of a skin mask (h, w) with >= ``min_area`` px."""
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise ValueError(f"detect_blobs: mask: expected an (h, w) array, got shape {mask.shape}")
    binary = (mask != 0).astype(np.uint8)
    labels = np.zeros(binary.shape, np.int32)
    rows, cols = np.flatnonzero(binary.any(1)), np.flatnonzero(binary.any(0))
    if rows.size == 0:
        return Blobs(np.zeros((0, 2)), np.zeros(0, np.int64), np.zeros((0, 4), np.int64), labels)
    # labelling runs on the bounding box of the skin pixels only: OpenCV's component
    # statistics cost ~0.6 ms on a whole 320x240 image even when it is empty, ~0.1 ms on the
    # box (same components, offsets added back)
    y0, y1, x0, x1 = rows[0], rows[-1] + 1, cols[0], cols[-1] + 1
    n, sub, stats, centroids = cv2.connectedComponentsWithStats(
        binary[y0:y1, x0:x1], connectivity=8, ltype=cv2.CV_32S
    )
    area = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero(area >= params.min_area)
    keep = keep[np.argsort(-area[keep], kind="stable")][: params.max_blobs]
    lut = np.full(n, -1, np.int32)
    lut[0] = 0
    lut[keep + 1] = np.arange(1, keep.size + 1, dtype=np.int32)
    labels[y0:y1, x0:x1] = lut[sub]
    return Blobs(
        centroid=centroids[keep + 1].astype(np.float64) + [x0, y0],
        area=area[keep].astype(np.int64),
        bbox=stats[keep + 1, :4].astype(np.int64) + [x0, y0, 0, 0],
        labels=labels,
    )


@dataclasses.dataclass(frozen=True)
class BlobState:
    """Tracking state of head / left hand / right hand (rows in ``ENTITY_NAMES`` order)."""

    params: BlobParams
    position: Float[np.ndarray, "3 3"]  # current estimate (measured or predicted), metres
    velocity: Float[np.ndarray, "3 3"]  # metres per frame
    last_seen: Float[np.ndarray, "3 3"]  # last measured position, metres
    status: Int[np.ndarray, " 3"]  # MISSING / MEASURED / PREDICTED
    coast: Int[np.ndarray, " 3"]  # consecutive frames without a measurement
    n_measured: Int[np.ndarray, " 3"]  # measurements since (re-)acquisition
    area: Float[np.ndarray, " 3"]  # left + right blob area of the last measurement, px
    frame: int = 0
    candidates: Float[np.ndarray, "k 3"] = dataclasses.field(
        default_factory=lambda: np.zeros((0, 3))
    )  # this frame's stereo-matched, triangulated blobs (for inspection)
    area_rejected: Int[np.ndarray, " 3"] = dataclasses.field(
        default_factory=lambda: np.zeros(3, np.int64)
    )  # consecutive frames whose candidate failed the area test

    @property
    def valid(self) -> Bool[np.ndarray, " 3"]:
        """Measured, or predicted for at most ``params.report_coast`` frames."""
        return (self.status == MEASURED) | (
            (self.status == PREDICTED) & (self.coast <= self.params.report_coast)
        )

    @property
    def points3d(self) -> Float[np.ndarray, "3 3"]:
        """Positions with missing entities set to the zero vector (Azad §III-D)."""
        return np.where(self.valid[:, None], self.position, 0.0)


def init(params: BlobParams = BlobParams()) -> BlobState:
    """A tracker with no entity acquired yet; the first frame with >= 3 candidates starts it."""
    z = np.zeros((3, 3))
    zi = np.zeros(3, np.int64)
    return BlobState(params, z, z, z, zi, zi, zi, np.zeros(3))


@functools.partial(jax.jit, static_argnames="refine")
def _frame_geometry_packed(
    cams: camlib.Camera, points: Float[Array, " p"], refine: bool
) -> tuple[
    Float[Array, "m m"], Float[Array, "m m 3"], Float[Array, "2 m m"], Float[Array, "2 3 2"]
]:
    """Epipolar distances, triangulated points and depths of all (left, right) blob pairs, and
    the projections of the predicted entities into both views. One compiled call per frame;
    ``points`` (4 m + 9,) = the left and right centroids (m, 2) and the predicted entities (3, 3),
    flattened into one array (one host-to-device copy)."""
    cam_l, cam_r = camlib.unstack_cameras(cams)
    m = (points.shape[0] - 9) // 4
    uv_l, uv_r = points[: 2 * m].reshape(m, 2), points[2 * m : 4 * m].reshape(m, 2)
    predicted = points[4 * m :].reshape(3, 3)
    a = jnp.broadcast_to(uv_l[:, None, :], (m, m, 2))
    b = jnp.broadcast_to(uv_r[None, :, :], (m, m, 2))
    epi = camlib.epipolar_distance_undistorted(cam_l, cam_r, a, b)
    X = camlib.triangulate(cams, jnp.stack([a, b]), refine=refine)
    depth = jnp.stack([camlib.to_camera(cam_l, X)[..., 2], camlib.to_camera(cam_r, X)[..., 2]])
    pred_uv = jax.vmap(camlib.project, in_axes=(0, None))(cams, predicted)
    return epi, X, depth, pred_uv


def _frame_geometry(
    cams: camlib.Camera,
    uv_l: Float[np.ndarray, "m 2"],
    uv_r: Float[np.ndarray, "m 2"],
    predicted: Float[np.ndarray, "3 3"],
    refine: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`_frame_geometry_packed` on the host's arrays, on the side CPU device when JAX has
    one (:func:`jaxmocap._config.side_device`: off the device of a filter step that may be
    computing in a live loop); NumPy results."""
    points = np.concatenate([np.ravel(uv_l), np.ravel(uv_r), np.ravel(predicted)])
    side = side_device()
    if side is not None:
        cams, points = _side_cameras(cams, side), jax.device_put(points, side)
    return tuple(np.asarray(a) for a in _frame_geometry_packed(cams, points, refine))


_SIDE_CAMERAS: list[tuple[camlib.Camera, jax.Device, camlib.Camera]] = []


def _side_cameras(cams: camlib.Camera, side: jax.Device) -> camlib.Camera:
    """``cams`` copied to the side device once per camera object (a live loop passes the
    same one every frame; a copy per frame cost ~0.1 ms)."""
    if not (_SIDE_CAMERAS and _SIDE_CAMERAS[0][0] is cams and _SIDE_CAMERAS[0][1] == side):
        _SIDE_CAMERAS[:] = [(cams, side, jax.device_put(cams, side))]
    return _SIDE_CAMERAS[0][2]


def _blob_under(blobs: Blobs, uv: np.ndarray) -> int:
    """Index of the blob containing pixel uv (rounded), or -1."""
    u, v = np.round(uv).astype(np.int64)
    h, w = blobs.labels.shape
    if not (np.all(np.isfinite(uv)) and 0 <= u < w and 0 <= v < h):
        return -1
    return int(blobs.labels[v, u]) - 1


def _greedy(cost: np.ndarray) -> list[tuple[int, int]]:
    """One-to-one pairs (row, col) of finite cost, cheapest first."""
    pairs, rows, cols = [], set(), set()
    for flat in np.argsort(cost, axis=None, kind="stable"):
        i, j = np.unravel_index(flat, cost.shape)
        if not np.isfinite(cost[i, j]):
            break
        if i not in rows and j not in cols:
            pairs.append((int(i), int(j)))
            rows.add(i)
            cols.add(j)
    return pairs


def _as_stacked(cams: camlib.Camera | Sequence[camlib.Camera]) -> camlib.Camera:
    if isinstance(cams, camlib.Camera):
        if cams.K.ndim != 3 or cams.K.shape[0] != 2:
            raise ValueError(f"blobs.update: cams: expected 2 stacked views, got {cams.K.shape}")
        return cams
    if len(cams) != 2:
        raise ValueError(f"blobs.update: cams: expected (left, right), got {len(cams)} cameras")
    return camlib.stack_cameras(cams)


def update(
    state: BlobState,
    mask_left: np.ndarray,
    mask_right: np.ndarray,
    cams: camlib.Camera | Sequence[camlib.Camera],
    reach: float | tuple[float, float] | None = None,
) -> tuple[BlobState, Float[np.ndarray, "3 3"], Bool[np.ndarray, " 3"]]:
    """One stereo frame: skin masks (h, w) of the left and right image -> new state,
    ``points3d`` (3, 3) metres (zeros where missing) and ``valid`` (3,).

    ``reach`` (metres; not in the paper): candidates farther than this from the head -- its
    prediction while it is tracked, the chosen head at initialisation -- cannot be a hand (a
    skin-coloured prop) and are dropped before association; ``reach = (near, far)`` also
    drops the candidates other than the head's own (the nearest) closer than ``near`` to it:
    the neck, seen as a blob of its own under the head, is no hand either."""
    near_m, reach = (None, reach) if reach is None or np.isscalar(reach) else reach
    p = state.params
    cams = _as_stacked(cams)
    masks = (np.asarray(mask_left), np.asarray(mask_right))
    for name, mk in zip(("mask_left", "mask_right"), masks, strict=True):
        if mk.shape != (cams.height, cams.width):
            raise ValueError(
                f"blobs.update: {name}: expected shape {(cams.height, cams.width)} "
                f"(the cameras' image size), got {mk.shape}"
            )
    bl, br = detect_blobs(masks[0], p), detect_blobs(masks[1], p)
    tracked = state.status != MISSING
    predicted = np.where(tracked[:, None], state.position + state.velocity, state.last_seen)

    m = p.max_blobs
    uv_l, uv_r = np.zeros((m, 2)), np.zeros((m, 2))
    uv_l[: len(bl.area)] = bl.centroid
    uv_r[: len(br.area)] = br.centroid
    epi, X, depth, pred_uv = _frame_geometry(cams, uv_l, uv_r, predicted,
                                             p.refine_triangulation)  # fmt: skip

    # merges: blobs holding the projections of two tracked entities, in either view
    merged = np.zeros(3, bool)
    usable = [np.ones(len(bl.area), bool), np.ones(len(br.area), bool)]
    for view, blobs in enumerate((bl, br)):
        owner = np.array(
            [_blob_under(blobs, pred_uv[view, e]) if tracked[e] else -1 for e in range(3)]
        )
        for k in set(owner[owner >= 0].tolist()):
            if np.sum(owner == k) >= 2:
                merged |= owner == k
                usable[view][k] = False

    # a blob cut by the image border has a biased centroid (and area): not matched
    for view, blobs in enumerate((bl, br)):
        x, y, w, h = blobs.bbox.T
        usable[view] &= (x > 0) & (y > 0) & (x + w < cams.width) & (y + h < cams.height)

    # stereo matching: epipolar distance, size and aspect ratio, depth (Azad §IV)
    nl, nr = len(bl.area), len(br.area)
    area_ratio = np.minimum.outer(bl.area, br.area) / np.maximum.outer(bl.area, br.area)
    aspect_ratio = np.minimum.outer(bl.aspect, br.aspect) / np.maximum.outer(bl.aspect, br.aspect)
    e, d = epi[:nl, :nr], depth[:, :nl, :nr]
    ok = (
        usable[0][:, None]
        & usable[1][None, :]
        & (e <= p.max_epipolar_px)
        & (area_ratio >= p.min_area_ratio)
        & (aspect_ratio >= p.min_aspect_ratio)
        & np.all((d > p.min_depth) & (d < p.max_depth), axis=0)
        & np.all(np.isfinite(X[:nl, :nr]), axis=-1)
    )
    cost = np.where(ok, e / p.max_epipolar_px + (1 - area_ratio) + (1 - aspect_ratio), np.inf)
    pairs = _greedy(cost)
    cand = np.array([X[i, j] for i, j in pairs]).reshape(-1, 3)
    cand_area = np.array([bl.area[i] + br.area[j] for i, j in pairs])
    if reach is not None and tracked[HEAD] and len(cand):
        dist = np.linalg.norm(cand - predicted[HEAD], axis=1)
        keep = dist <= reach
        if near_m is not None:
            keep &= (dist >= near_m) | (np.arange(len(cand)) == np.argmin(dist))
        cand, cand_area = cand[keep], cand_area[keep]

    # association of candidates with entities
    assigned: dict[int, int] = {}  # entity -> candidate
    if not np.any(tracked):
        if len(cand) >= (1 if reach is not None else 3):
            assigned = _initial_identities(cand, cand_area, cams, p, reach, near_m or 0.0)
    else:
        gate = p.gate + p.gate_growth * state.coast
        live = [e for e in range(3) if tracked[e] and not merged[e]]
        dist = np.linalg.norm(predicted[live][:, None] - cand[None], axis=-1)
        dist = np.where(dist <= gate[live][:, None], dist, np.inf)
        assigned = {live[r]: c for r, c in _greedy(dist)}
        # missing entities, and coasting ones whose prediction found nothing in the gate, take
        # the nearest unclaimed candidate within `reacquire` of where they were last measured
        lost = [e for e in range(3) if e not in assigned and not (tracked[e] and merged[e])]
        free = [c for c in range(len(cand)) if c not in assigned.values()]
        if lost and free:
            dist = np.linalg.norm(state.last_seen[lost][:, None] - cand[free][None], axis=-1)
            dist = np.where(dist <= p.reacquire, dist, np.inf)
            assigned.update({lost[r]: free[c] for r, c in _greedy(dist)})
        if reach is not None and tracked[HEAD] and not merged[HEAD]:
            # with the plausibility gate every candidate left is within reach of the head: a
            # hand missing (or never acquired at a head-only start) takes the largest free one,
            # on its side of the head (a hand lost far from where it was last seen would
            # otherwise never come back)
            right_axis = np.asarray(cams.R[0, 0])
            for ent in (LEFT_HAND, RIGHT_HAND):
                if ent in assigned or state.status[ent] != MISSING:
                    continue
                free = [c for c in range(len(cand)) if c not in assigned.values()]
                head_pos = predicted[HEAD]
                sides = [((cand[c] - head_pos) @ right_axis > 0) == p.subject_faces_cameras
                         for c in free]
                mine = [c for c, left in zip(free, sides, strict=True)
                        if left == (ent == LEFT_HAND)]
                if mine:
                    assigned[ent] = max(mine, key=lambda c: cand_area[c])

    # linear motion model update
    position, velocity = predicted.copy(), state.velocity.copy()
    last_seen, status = state.last_seen.copy(), state.status.copy()
    coast, n_meas, area = state.coast + 1, state.n_measured.copy(), state.area.copy()
    lo = 1 - p.max_area_change
    rejected = np.zeros(3, np.int64)
    for ent in range(3):
        if ent in assigned and status[ent] != MISSING:
            ratio = cand_area[assigned[ent]] / state.area[ent]
            if not lo <= ratio <= 1 / lo:  # partly occluded: the centroid is biased
                rejected[ent] = state.area_rejected[ent] + 1
                if rejected[ent] <= p.area_patience:
                    del assigned[ent]  # (the candidate stays claimed)
                else:  # the new size has persisted: accept it
                    rejected[ent] = 0
    for ent in range(3):
        if ent in assigned:
            x = cand[assigned[ent]]
            area[ent] = cand_area[assigned[ent]]
            if status[ent] == MISSING:  # (re-)acquired: no velocity yet
                velocity[ent], n_meas[ent] = 0.0, 0
            else:
                step = x - state.position[ent]  # metres per frame
                w = 1.0 if n_meas[ent] == 1 else p.velocity_smoothing
                velocity[ent] = w * step + (1 - w) * state.velocity[ent]
            position[ent] = last_seen[ent] = x
            status[ent], coast[ent] = MEASURED, 0
            n_meas[ent] += 1
        elif status[ent] != MISSING:
            status[ent] = PREDICTED if coast[ent] <= p.max_coast else MISSING
            velocity[ent] = p.coast_damping * velocity[ent]
            if status[ent] == MISSING:
                velocity[ent] = 0.0
    new = BlobState(
        p,
        position,
        velocity,
        last_seen,
        status,
        coast,
        n_meas,
        area,
        state.frame + 1,
        cand,
        rejected,
    )
    return new, new.points3d, new.valid


def _initial_identities(
    cand: np.ndarray, area: np.ndarray, cams: camlib.Camera, p: BlobParams,
    reach: float | None = None, near: float = 0.0,
) -> dict[int, int]:
    """Head = highest (Z) of the three largest candidates; hands by side of the head. With
    ``reach``, the hands are the (up to) two largest candidates within reach of the head; a
    single one is the hand on its side of the head."""
    top3 = np.argsort(-area, kind="stable")[:3]
    head = int(top3[np.argmax(cand[top3, 2])])
    if reach is not None:
        within = [int(c) for c in np.argsort(-area, kind="stable")
                  if c != head and near <= np.linalg.norm(cand[c] - cand[head]) <= reach]
        if len(within) < 2:
            out = {HEAD: head}
            if within:
                side = (cand[within[0]] - cand[head]) @ np.asarray(cams.R[0, 0])
                hand = LEFT_HAND if (side > 0) == p.subject_faces_cameras else RIGHT_HAND
                out[hand] = within[0]
            return out
        top3 = np.array([head, *within[:2]])
    hands = [int(c) for c in top3 if c != head]
    right_axis = np.asarray(cams.R[0, 0])  # left camera's image-x axis in the world
    side = [(cand[c] - cand[head]) @ right_axis for c in hands]
    # facing the cameras, the subject's left hand is on the camera's right (larger side)
    left_first = (side[0] > side[1]) == p.subject_faces_cameras
    left, right = (hands[0], hands[1]) if left_first else (hands[1], hands[0])
    return {HEAD: head, LEFT_HAND: left, RIGHT_HAND: right}
