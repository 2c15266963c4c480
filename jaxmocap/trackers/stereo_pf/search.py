"""Prediction-guided search for the head and hands of the stereo particle filter (issue 18; not in
Azad et al. 2007).

Azad's blob line (:mod:`jaxmocap.blobs`) finds a hand only where its skin blob passes the
global skin threshold and the stereo tests of whole blobs (area and aspect ratio, not cut by the
border, not merged). On footage of another renderer (the independent test world's dev split)
a visible hand reaches the skin map on ~65% of the frames and becomes a triangulated candidate
on only 40-50%: at 320x240 a hand is a small, elongated, shaded blob whose two views differ;
a face turning under a lamp leaves the skin class for tens of frames. The filter, however,
knows where the head and hands should be. :func:`search_entities` looks for each entity the
blob line did not measure **in a window around the filter's prediction** projected into both
views, with relaxed colour tests inside the window only:

1. *relaxed skin* (:func:`relaxed_skin`, :func:`jaxmocap.pf.colors.hysteresis_masks`'s
   relaxed map): skin-class distance below ``skin_scale`` x the capture's threshold, closer
   to skin than to the shirt, a log ratio against the background histogram above
   ``min_log_ratio``, within ``near_px`` of the shirt (:func:`jaxmocap.pf.colors.masks`,
   looser); a component must hold ``seed_px`` pixels of the capture's own skin map;
2. per view, the connected components of that map inside a disc of ``window_m`` (metres at the
   prediction's depth) around the projected prediction; for a hand the head's disc
   (:data:`HEAD_EXCLUDE_M`) and the discs of the hands already measured are left out (the
   face and the other hand are no candidate);
3. left/right components paired by the symmetric epipolar distance of their centroids
   (lens distortion removed) -- no area / aspect test, the views of a small hand differ --
   triangulated (:func:`jaxmocap.blobs._frame_geometry`, the blob line's own kernel) and
   accepted nearest to the prediction within ``gate_m`` of it, in front of both cameras, and
   for a hand within the arms' reach of the head (:func:`~jaxmocap.trackers.stereo_pf.checks.
   hand_reach`, not closer than the neck).

:func:`observe_search` runs the filter alongside the host's image line (as
:func:`jaxmocap.trackers.stereo_pf.adapt.observe_adaptive` does) and fills the observation of
frame t with what the search finds around the prediction from the estimates of frames t - 1
and t - 2 (constant velocity, damped).

**Measured: not an improvement; opt-in** (experiment option ``search``). Dev split, mean error
over 3 seeds, with the hysteresis skin map (``skin_grow = 4``) at 28.0 cm: searching head and
hands 29.3 cm (a component must hold 2 px of the capture's skin map), hands with a 10 cm gate
and 4 seed px 27.5, the head only 27.7 -- within the seed spread. Of the hands the search
added only 27 of 65 (11 of 34 with the tighter gate) were within 8 cm of the true hand: where
the blob line finds no hand the filter's own arm is usually off too, and the window then holds
the shirt's rim or the neck, not the hand. A lost head found again: median 4 cm from the true
head on pf_09, 4-12 cm on the others (``docs/results/stereo_pf.md``).
"""

from __future__ import annotations

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray, UInt8

from jaxmocap import blobs as bloblib
from jaxmocap import camera as camlib
from jaxmocap.body import keypoint_index, keypoints
from jaxmocap.errors import InputError
from jaxmocap.pf.colors import CaptureColors, hysteresis_masks
from jaxmocap.pf.cues import Observation
from jaxmocap.trackers.stereo_pf.filter import compile_step, online_frame
from jaxmocap.trackers.stereo_pf.observation import observe
from jaxmocap.trackers.stereo_pf.params import BLOB_PARAMS, StereoPFParams

ENTITIES = bloblib.ENTITY_NAMES  # head, l_hand, r_hand (keypoint names)


@dataclasses.dataclass(frozen=True)
class SearchParams:
    """Thresholds of the guided search (module docstring)."""

    window_m: float = 0.15  # search radius around the projected prediction, metres
    gate_m: float = 0.2  # triangulated point within this of the prediction, metres
    skin_scale: float = 2.0  # relaxed skin threshold: this x the capture's
    min_log_ratio: float = -5.0  # log p(skin) - log p(background) above this
    min_area: int = 3  # px per view
    seed_px: int = 0  # a component holds at least this many pixels of the capture's skin map
    max_epipolar_px: float = 3.0
    head_exclude_m: float = 0.12  # hands: the head's disc is not searched, metres
    hand_exclude_m: float = 0.05  # hands: nor the disc of a hand already measured
    velocity_damping: float = 0.5  # weight of the last estimated velocity in the prediction
    entities: tuple[bool, bool, bool] = (True, True, True)  # head, l_hand, r_hand searched

    def __post_init__(self):
        for name in ("window_m", "gate_m", "skin_scale", "max_epipolar_px"):
            if not getattr(self, name) > 0:
                raise InputError(f"SearchParams.{name}: expected > 0, got {getattr(self, name)!r}")
        if not 0 <= self.velocity_damping <= 1:
            raise InputError(f"SearchParams.velocity_damping: expected a value in [0, 1], got "
                             f"{self.velocity_damping!r}")
        if len(self.entities) != 3:
            raise InputError("SearchParams.entities: expected 3 flags (head, l_hand, r_hand)")


def relaxed_skin(
    colors: CaptureColors, image: np.ndarray, skin_scale: float, min_log_ratio: float
) -> tuple[Bool[np.ndarray, "h w"], Bool[np.ndarray, "h w"]]:
    """The relaxed skin map of one RGB uint8 image (module docstring, step 1) and the
    capture's own skin map (:func:`jaxmocap.pf.colors.masks`'s)."""
    strict, _, relaxed = hysteresis_masks(colors, image, 0, skin_scale, min_log_ratio)
    return relaxed, strict


@jax.jit
def _project_both(
    cams, X: Float[Array, "k 3"]
) -> tuple[Float[Array, "2 k 2"], Float[Array, "2 k"]]:
    """Projections into both views and depths of world points (k, 3)."""
    uv = jax.vmap(camlib.project, in_axes=(0, None))(cams, X)
    depth = jax.vmap(camlib.to_camera, in_axes=(0, None))(cams, X)[..., 2]
    return uv, depth


def _paired(cams, cands, m: int, predicted: np.ndarray, max_epipolar_px: float,
            gate_m: float):
    """Every pair of the two views' candidate centres (``cands``, at most ``m`` each)
    triangulated: the points (nl, nr, 3), their distance from ``predicted`` and which pairs
    pass the epipolar, in-front-of-both-cameras, gate and finiteness checks; None when a view
    has no candidate. The pairs are padded to ``m`` so that one compiled geometry serves
    every frame."""
    nl, nr = len(cands[0]), len(cands[1])
    if nl == 0 or nr == 0:
        return None
    a, b = np.zeros((m, 2)), np.zeros((m, 2))
    a[:nl], b[:nr] = cands[0], cands[1]
    epi, X, dep, _ = (np.asarray(x) for x in bloblib._frame_geometry(
        cams, a, b, np.zeros((3, 3)), False))
    epi, X, dep = epi[:nl, :nr], X[:nl, :nr], dep[:, :nl, :nr]
    dist = np.linalg.norm(X - predicted, axis=-1)
    ok = (epi <= max_epipolar_px) & np.all(dep > 0, axis=0) & (dist <= gate_m)
    ok &= np.all(np.isfinite(X), axis=-1)
    return X, dist, ok


def _components(mask: np.ndarray, seeds: np.ndarray, centre: np.ndarray, min_area: int,
                seed_px: int, m: int) -> np.ndarray:
    """Centroids (<= m, 2) of the components of ``mask`` with >= min_area px of which
    >= seed_px are in ``seeds``, nearest to ``centre`` first."""
    n, lab, stats, cent = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    n_seed = np.bincount(lab[seeds & mask], minlength=n) if seed_px > 0 else np.zeros(n)
    keep = [i for i in range(1, n)
            if stats[i, cv2.CC_STAT_AREA] >= min_area and n_seed[i] >= seed_px]
    keep.sort(key=lambda i: float(np.sum((cent[i] - centre) ** 2)))
    return cent[keep[:m]].astype(np.float64).reshape(-1, 2)


def search_entities(
    params: StereoPFParams,
    images: UInt8[np.ndarray, "2 h w 3"],
    predicted: Float[np.ndarray, "3 3"],
    points: Float[np.ndarray, "3 3"],
    valid: Bool[np.ndarray, " 3"],
    search: SearchParams = SearchParams(),
    skin_maps: list[tuple[np.ndarray, np.ndarray]] | None = None,
) -> tuple[Float[np.ndarray, "3 3"], Bool[np.ndarray, " 3"]]:
    """The guided search of one stereo frame (module docstring): for each entity searched by
    ``search.entities`` and not ``valid``, a point near its ``predicted`` position (3, 3)
    metres. Returns (points, valid) with the found entities filled in (the others as given).
    ``skin_maps``: :func:`relaxed_skin` of both images if already computed."""
    if params.colors is None:
        raise InputError("stereo_pf.search: the guided search needs the capture's colours "
                         "(make_params(images=Images(colors=...)))")
    cams = params.likelihood.cams
    points = np.array(points, np.float64)
    valid = np.array(valid, bool)
    predicted = np.asarray(predicted, np.float64)
    todo = [e for e in range(3) if search.entities[e] and not valid[e]]
    if not todo or not np.all(np.isfinite(predicted)):
        return points, valid
    if skin_maps is None:
        skin_maps = list(relaxed_skin(params.colors, images[v], search.skin_scale,
                                       search.min_log_ratio) for v in range(2))
    h, w = skin_maps[0][0].shape
    f = np.asarray(cams.K, np.float64)[:, 0, 0]
    yy, xx = np.mgrid[:h, :w]
    near, far = params.reach if params.reach is not None else (0.0, np.inf)
    m = BLOB_PARAMS.max_blobs
    for e in todo:
        ref = np.where(valid[:, None], points, predicted)  # where the others are
        uv, depth = (np.asarray(x, np.float64) for x in _project_both(
            cams, jnp.asarray(np.vstack([predicted[e], ref]), jnp.float32)))
        if np.any(depth[:, 0] <= 0):
            continue
        cands = []
        for v in range(2):
            def disc(k, radius_m, v=v, uv=uv, depth=depth):
                r = f[v] * radius_m / max(depth[v, k], 1e-3)
                return (xx - uv[v, k, 0]) ** 2 + (yy - uv[v, k, 1]) ** 2 <= r * r

            region = skin_maps[v][0] & disc(0, search.window_m)
            if e != bloblib.HEAD:
                region &= ~disc(1 + bloblib.HEAD, search.head_exclude_m)
                other = 3 - e  # the other hand
                if valid[other]:
                    region &= ~disc(1 + other, search.hand_exclude_m)
            cands.append(_components(region, skin_maps[v][1], uv[v, 0], search.min_area,
                                     search.seed_px, m))
        pairs = _paired(cams, cands, m, predicted[e], search.max_epipolar_px, search.gate_m)
        if pairs is None:
            continue
        X, dist, ok = pairs
        if e != bloblib.HEAD:
            dh = np.linalg.norm(X - ref[bloblib.HEAD], axis=-1)
            ok &= (dh >= near) & (dh <= far)
        if not ok.any():
            continue
        i, j = np.unravel_index(np.argmin(np.where(ok, dist, np.inf)), ok.shape)
        points[e], valid[e] = X[i, j], True
    return points, valid


def observe_search(
    params: StereoPFParams,
    key: PRNGKeyArray,
    frames: UInt8[np.ndarray, "t 2 h w 3"],
    blob_params: bloblib.BlobParams | None = None,
    search: SearchParams = SearchParams(),
) -> tuple[Observation, dict[str, np.ndarray]]:
    """:func:`~jaxmocap.trackers.stereo_pf.observe_sequence` with the guided search: the
    filter runs alongside from the first frame with a triangulated head (initialised there as
    :func:`~jaxmocap.trackers.stereo_pf.track` does, then stepped from frame 0); from then on
    each frame's unmeasured entities are searched around the prediction from the previous two
    estimates. Returns the stacked observations and a log: ``found`` (T, 3) the entities the
    search added."""
    if params.colors is None:
        raise InputError("stereo_pf.search.observe_search: the guided search needs the "
                         "capture's colours (make_params(images=Images(colors=...)))")
    model = params.model
    idx = np.asarray([keypoint_index(model, k)[0] for k in ENTITIES])
    kp_fn = jax.jit(lambda q: keypoints(model, q)[idx])
    step = compile_step(params)
    blob_state = bloblib.init(blob_params or BLOB_PARAMS)
    n = len(frames)
    log = {"found": np.zeros((n, 3), bool)}
    out: list[Observation] = []
    state, history = None, []  # history: the last two estimates' (3, 3) entity positions
    for t in range(n):
        obs, blob_state = observe(params, frames[t], blob_state)
        valid = np.asarray(obs.valid)
        if state is not None and len(history) >= 1 and not valid.all():
            last = history[-1]
            vel = last - history[-2] if len(history) >= 2 else np.zeros_like(last)
            pred = last + search.velocity_damping * vel
            pts, val = search_entities(params, frames[t], pred, np.asarray(obs.points),
                                       valid, search)
            log["found"][t] = val & ~valid
            dt = obs.points.dtype
            obs = dataclasses.replace(obs, points=jnp.asarray(pts, dt), valid=jnp.asarray(val))
        out.append(obs)
        state, est = online_frame(params, key, step, state, out, obs)
        if est is None:
            continue
        q = np.asarray(est.q)
        if np.all(np.isfinite(q)):
            history = (history + [np.asarray(kp_fn(jnp.asarray(q)), np.float64)])[-2:]
    return jax.tree.map(lambda *a: jnp.stack(a), *out), log
