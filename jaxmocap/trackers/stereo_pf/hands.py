"""Hands found by the filter's prediction: search windows from the particle cloud, skin (and
optionally motion) inside them, two-view consistency and the body's reach (issue 39, decision 1;
not in Azad et al. 2007).

Azad's blob line (:mod:`jaxmocap.blobs`) takes every skin blob pair that passes its stereo tests
and names the hands by tracking. On footage of another renderer (the test world's dev split) a
hand is a few pixels of shaded skin at 320x240: the blob line hands the filter a point within
8 cm of the true hand on only 20-40% of the frames where the hand is visible, and a wrong one on
others (a skin-coloured prop, the neck, the other hand). A wrong hand is worse than none: the
distance cue pulls the arm onto it, while a missing hand leaves the arm to the edge and
hand-support cues. This module replaces the blob line's hands, once the filter runs, by

1. **the particle cloud's prediction** (:func:`cloud_prediction`, jitted and vmapped over the
   particles): each hand's, the head's and the shoulders' keypoints of every particle, their
   weighted mean and spread (root of the trace of the weighted covariance), plus the damped
   velocity of the mean over the last two frames;
2. **a search window per hand and view** (:func:`hand_windows`): a disc around the projected
   predicted hand of ``window_m + spread_k x spread`` metres (clipped to ``max_window_m``) at its
   depth; the head's disc (:attr:`HandParams.head_exclude_m` around the blob line's head if
   measured, else the predicted one) and the neck's (the point between the head and the
   shoulders' centre, :attr:`HandParams.neck_exclude_m`) are cut out, so that face and neck skin
   is never a hand candidate;
3. **candidates**: the connected components of the capture's skin map inside the window
   (optionally also of the *motion map*, :func:`motion_map`: the double frame difference on
   pixels that are not shirt), at least ``min_area`` pixels, nearest to the projected
   prediction first; and the blob line's own hand points (each for the hand its tracker
   named);
4. **two-view consistency and the body** (:func:`hand_gates`, jittable, vmaps over
   candidates): left / right components paired by the symmetric epipolar distance of their
   centroids (lens distortion removed, at most ``max_epipolar_px``), triangulated, in front of
   both cameras; a candidate is a hand only within the arm's reach of *its* shoulder (the
   shoulder-elbow-wrist-hand keypoint lengths at rest x :data:`REACH_MARGIN`, by keypoint roles;
   the shoulder from the prediction), farther from the head than the neck
   (:func:`~jaxmocap.trackers.stereo_pf.checks.hand_reach`'s near distance) -- from the blob
   line's head *and* the predicted one (the blob line's own plausibility test uses its head
   only, which on the dev split was at times a prop: 14 "hands" on the neck of pf_06, 17 on the
   head of pf_09 in 90 frames) -- and, for a window's candidate, within
   ``gate_m + gate_k x spread`` of the predicted hand;
5. **one candidate per hand**: the nearest (in units of the gate) that passes, the two hands
   never on the same point (the pairing of smaller total cost); a blob line's hand is
   preferred to a window's and keeps the identity its tracker gave it, a window's candidate is
   the hand of its window -- identities never come from the prediction (on pf_06 of the dev
   split, hands named by the nearer predicted hand fed a filter turned the wrong way round its
   own turn: 34 -> 66 cm). A hand with no candidate is a
   **missing observation** (``valid`` False, point 0: its distance term drops out; the
   hand-support cue still holds it off plain background).

Before the filter has started (its first frames) the blob line's hands stand as they are.
:func:`observe_hands` runs the filter alongside the host's image line (as
:func:`jaxmocap.trackers.stereo_pf.search.observe_search` does): frame t is searched around the
prediction from the particle sets after frames t - 1 and t - 2.
**Measured (opt-in, ``docs/results/stereo_pf_hands.md``)**: dev split, 3 seeds, against the
same filter with the blob line's hands: measured hands within 8 cm of a true hand 30 -> 33% of
the visible ones, wrong measured hands 41 -> 34%, the mean joint error 29.18 (seeds
27.32-30.39) -> 26.79 cm (26.13-27.74), most of it on pf_09 (the blob line's "hands" on the
head gone); the test split not yet run. The live frame: +3.1 ms (cloud prediction 1.5, search
1.6), +4.1 ms more with the motion map, which added mostly wrong hands on pf_03.
"""

from __future__ import annotations

import dataclasses

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, PRNGKeyArray, UInt8

from jaxmocap import blobs as bloblib
from jaxmocap.body import BodyModel, keypoint_index, keypoints
from jaxmocap.errors import InputError
from jaxmocap.pf.cues import Observation
from jaxmocap.trackers.stereo_pf.checks import REACH_MARGIN, hand_reach
from jaxmocap.trackers.stereo_pf.filter import compile_step, online_frame
from jaxmocap.trackers.stereo_pf.observation import _segment, observe
from jaxmocap.trackers.stereo_pf.params import BLOB_PARAMS, HAND_KEYPOINTS, HandParams
from jaxmocap.trackers.stereo_pf.search import _project_both

__all__ = ["ArmReach", "HandParams", "arm_reach", "cloud_prediction", "gated_hands",
           "hand_gates", "motion_map", "observe_hands"]

# keypoints of the prediction, by role: head, left / right shoulder, left / right hand
CLOUD_KEYPOINTS = ("head", "l_shoulder", "r_shoulder", "l_hand", "r_hand")
ARM_CHAINS = (("l_shoulder", "l_elbow", "l_wrist", "l_hand"),
              ("r_shoulder", "r_elbow", "r_wrist", "r_hand"))


class ArmReach(eqx.Module):
    """What the gates need of the body: keypoint indices of :data:`CLOUD_KEYPOINTS`, each arm's
    reach from its shoulder (m), the nearest a hand may come to the head and the farthest it
    may be from it (m; :func:`~jaxmocap.trackers.stereo_pf.checks.hand_reach`)."""

    index: tuple[int, ...] = eqx.field(static=True)
    reach: Float[Array, " 2"]
    near: Float[Array, ""]
    far: Float[Array, ""]


def arm_reach(model: BodyModel, margin: float = REACH_MARGIN) -> ArmReach:
    """:class:`ArmReach` of ``model`` at rest, by keypoint roles (the wrist optional); one
    line naming the missing keypoints when the body lacks them."""
    names = list(model.keypoint_names)
    need = set(HAND_KEYPOINTS)
    if not need <= set(names):
        raise InputError(f"stereo_pf.hands: the gated hand search needs the keypoints "
                         f"{sorted(need)}; the body has {names}; give hand_search=False")
    kp = np.asarray(keypoints(model, jnp.zeros(model.n_dof)), np.float64)
    reach = []
    for chain in ARM_CHAINS:
        pts = kp[[names.index(k) for k in chain if k in names]]
        reach.append(margin * float(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1))))
    index = tuple(int(keypoint_index(model, k)[0]) for k in CLOUD_KEYPOINTS)
    near, far = hand_reach(model, margin)
    return ArmReach(index, jnp.asarray(reach, jnp.float32), jnp.asarray(near, jnp.float32),
                    jnp.asarray(far, jnp.float32))


def cloud_prediction(
    params, arms: ArmReach, particles: Float[Array, "n d"], log_weights: Float[Array, " n"]
) -> tuple[Float[Array, "5 3"], Float[Array, " 5"]]:
    """Weighted mean (5, 3) and spread (5,) (root of the weighted covariance's trace, m) of
    the :data:`CLOUD_KEYPOINTS` over a particle set (``params``: the tracker's
    :class:`~.params.StereoPFParams`). Keypoints of each particle by forward kinematics,
    vmapped over the particles; jit it (``jax.jit(cloud_prediction, static_argnums=())``
    with the params closed over)."""
    idx = jnp.asarray(arms.index)
    kp = jax.vmap(lambda s: keypoints(params.model, params.full_q(s))[idx])(particles)
    w = jax.nn.softmax(log_weights)
    mean = jnp.einsum("n,nkc->kc", w, kp)
    var = jnp.einsum("n,nk->k", w, jnp.sum((kp - mean[None]) ** 2, axis=-1))
    return mean, jnp.sqrt(var)


def hand_gates(
    arms: ArmReach,
    X: Float[Array, "*c 3"],
    hand: int,
    predicted: Float[Array, "5 3"],
    heads: Float[Array, "k 3"],
    gate: Float[Array, ""],
    reach: bool = True,
) -> tuple[Bool[Array, "*c"], Float[Array, "*c"]]:
    """Which candidate points ``X`` (m) may be hand ``hand`` (0 left, 1 right) by the body
    and their cost (distance to the predicted hand over ``gate``): within the arm's reach of
    the predicted shoulder, not closer to ``head`` than ``arms.near`` (the neck), finite. A
    window candidate must also have cost <= 1 (within ``gate`` of the predicted hand).
    ``reach`` (static) False: instead of the shoulder's reach, within ``arms.far`` of a head
    (the blob line's hands: a filter whose shoulders drifted must not gate out the hands that
    would bring it back).
    Pure jnp: vmaps / jits."""
    def dist(p):
        return jnp.linalg.norm(X - jnp.broadcast_to(p, X.shape), axis=-1)

    d_sh = dist(predicted[1 + hand])
    d_head = jnp.min(jnp.stack([dist(h) for h in heads]), axis=0)
    cost = dist(predicted[3 + hand]) / gate
    ok = d_head >= arms.near
    ok &= (d_sh <= arms.reach[hand]) if reach else (d_head <= arms.far)
    ok &= jnp.all(jnp.isfinite(X), axis=-1)
    return ok, jnp.where(ok, cost, jnp.inf)


def motion_map(
    frames: UInt8[np.ndarray, "k h w 3"], shirt: Bool[np.ndarray, "h w"], threshold: float
) -> Bool[np.ndarray, "h w"]:
    """Moving pixels of the newest of ``frames`` (oldest first, k >= 2): the sum of absolute
    RGB differences to *every* earlier frame above ``threshold`` (a double difference with 3
    frames: the background a moving limb uncovers differs from one earlier frame only), not on
    the shirt, opened by a 2x2 square (the codec's block noise is single pixels)."""
    cur = frames[-1].astype(np.int16)
    m = np.ones(cur.shape[:2], bool)
    for prev in frames[:-1]:
        m &= np.abs(cur - prev.astype(np.int16)).sum(-1) > threshold
    m &= ~np.asarray(shirt, bool)
    k = np.ones((2, 2), np.uint8)  # erosion anchored top-left, dilation bottom-right: an open
    # that keeps every pixel of a 2x2 block in place (cv2's centred even kernel shifts it)
    m = cv2.erode(m.astype(np.uint8), k, anchor=(0, 0))
    return cv2.dilate(m, k, anchor=(1, 1)) > 0


def _disc_box(u, v, r, h, w):
    x0, x1 = max(int(np.floor(u - r)), 0), min(int(np.ceil(u + r)) + 1, w)
    y0, y1 = max(int(np.floor(v - r)), 0), min(int(np.ceil(v + r)) + 1, h)
    return x0, x1, y0, y1


def _window_candidates(mask, centre, r, cuts, min_area, m):
    """Centroids (<= m, 2) of the components of ``mask`` inside the disc (centre, r px) minus
    the discs ``cuts`` [(u, v, r)], nearest to the centre first (crop of the disc's box)."""
    h, w = mask.shape
    x0, x1, y0, y1 = _disc_box(centre[0], centre[1], r, h, w)
    if x1 <= x0 or y1 <= y0:
        return np.zeros((0, 2))
    yy, xx = np.mgrid[y0:y1, x0:x1]
    region = mask[y0:y1, x0:x1] & ((xx - centre[0]) ** 2 + (yy - centre[1]) ** 2 <= r * r)
    for (u, v, rc) in cuts:
        region &= (xx - u) ** 2 + (yy - v) ** 2 > rc * rc
    if not region.any():
        return np.zeros((0, 2))
    n, _, stats, cent = cv2.connectedComponentsWithStats(region.astype(np.uint8),
                                                         connectivity=8)
    keep = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= min_area]
    keep.sort(key=lambda i: float(np.sum((cent[i] + [x0, y0] - centre) ** 2)))
    return (cent[keep[:m]] + [x0, y0]).astype(np.float64).reshape(-1, 2)


def gated_hands(
    params,
    arms: ArmReach,
    masks: list[Bool[np.ndarray, "h w"]],
    predicted: Float[np.ndarray, "5 3"],
    spread: Float[np.ndarray, " 5"],
    blob_points: Float[np.ndarray, "3 3"],
    blob_valid: Bool[np.ndarray, " 3"],
    hp: HandParams | None = None,
) -> tuple[Float[np.ndarray, "2 3"], Bool[np.ndarray, " 2"], dict]:
    """The hands of one stereo frame (module docstring, steps 2-5): ``masks`` the candidate
    pixels of each view (skin, or skin | motion), ``predicted`` / ``spread`` the
    :func:`cloud_prediction` (velocity already added), ``blob_points`` / ``blob_valid`` the
    blob line's (head, left hand, right hand). Returns the hands' points (2, 3) (0 where
    missing), their valid flags and a log (``source``: per hand 0 missing, 1 blob line,
    2 window search); ``hp`` the thresholds (default :class:`HandParams`)."""
    hp = HandParams() if hp is None else hp
    cams = params.likelihood.cams
    predicted = np.asarray(predicted, np.float64)
    spread = np.asarray(spread, np.float64)
    # the head and neck of the blob line (if measured) and of the prediction: either may be off
    # (the blob line's head a skin-coloured prop, the filter's head drifted)
    heads = [predicted[0]] + ([np.asarray(blob_points[0], np.float64)] if blob_valid[0] else [])
    # the shoulders of the windows' reach test: the prediction's, moved with its head onto the
    # measured head where there is one (a drifted filter must not gate out the hands that would
    # bring it back: pf_06 of the dev split, the true hand 0.95 m from the drifted shoulder)
    shoulders = predicted[1:3] + (heads[-1] - predicted[0])
    centre = 0.5 * (shoulders[0] + shoulders[1])
    necks = [0.5 * (h + centre) for h in heads]
    out = np.zeros((2, 3))
    found = np.zeros(2, bool)
    log = {"source": np.zeros(2, np.int8)}
    if not np.all(np.isfinite(predicted)):
        return out, found, log
    f = np.asarray(cams.K, np.float64)[:, 0, 0]
    uv, depth = (np.asarray(x, np.float64) for x in _project_both(
        cams, jnp.asarray(np.vstack([predicted[3:5], *heads, *necks]), jnp.float32)))
    radii = [hp.head_exclude_m] * len(heads) + [hp.neck_exclude_m] * len(necks)
    cuts = [[], []]
    for v in range(2):
        for k, rad in enumerate(radii, start=2):
            if depth[v, k] > 0 and rad > 0:
                cuts[v].append((uv[v, k, 0], uv[v, k, 1], f[v] * rad / depth[v, k]))
    m = bloblib.MAX_BLOBS
    cand_X, cand_src, cand_hand = [], [], []
    if hp.blob_hands:
        for e in (1, 2):
            if blob_valid[e]:
                cand_X.append(np.asarray(blob_points[e], np.float64))
                cand_src.append(1)
                cand_hand.append(e - 1)
    for hand in range(2):
        if np.any(depth[:, hand] <= 0):
            continue
        radius_m = min(hp.window_m + hp.spread_k * spread[3 + hand], hp.max_window_m)
        cands = [_window_candidates(masks[v], uv[v, hand], f[v] * radius_m / depth[v, hand],
                                    cuts[v], hp.min_area, m) for v in range(2)]
        if len(cands[0]) == 0 or len(cands[1]) == 0:
            continue
        a, b = np.zeros((m, 2)), np.zeros((m, 2))
        a[:len(cands[0])], b[:len(cands[1])] = cands[0], cands[1]
        epi, X, dep, _ = (np.asarray(x) for x in bloblib._frame_geometry(
            cams, a, b, np.zeros((3, 3)), False))
        nl, nr = len(cands[0]), len(cands[1])
        ok = (epi[:nl, :nr] <= hp.max_epipolar_px) & np.all(dep[:, :nl, :nr] > 0, axis=0)
        for i, j in zip(*np.nonzero(ok), strict=True):
            cand_X.append(X[i, j])
            cand_src.append(2)
            cand_hand.append(hand)
    if not cand_X:
        return out, found, log
    Xc, src = np.asarray(cand_X), np.asarray(cand_src)
    blob_pts = Xc[src == 1]
    if len(blob_pts):  # a window's candidate on a blob line's hand is that hand, named already
        near_blob = np.linalg.norm(Xc[:, None] - blob_pts[None], axis=-1).min(1) < SAME_POINT_M
        keep = (src == 1) | ~near_blob
        Xc, src = Xc[keep], src[keep]
        cand_hand = list(np.asarray(cand_hand)[keep])
    pred = jnp.asarray(np.vstack([predicted[:1], shoulders, predicted[3:5]]), jnp.float32)
    # fixed shapes for the jitted gates (one compilation, not one per candidate count): the
    # candidates padded with NaN (not finite: never pass), the heads with the first again (the
    # nearest head is the same)
    n_c = len(Xc)
    C = jnp.asarray(np.vstack([Xc, np.full((MAX_CANDIDATES - n_c, 3), np.nan)]), jnp.float32)
    H = jnp.asarray(np.asarray(heads + heads[:1])[:2], jnp.float32)
    costs = []
    for hand in range(2):
        gate = jnp.float32(hp.gate_m + hp.gate_k * spread[3 + hand])
        _, c = _gates_jit(arms, C, hand, pred, H, gate)
        c = np.asarray(c, np.float64)[:n_c]
        if len(blob_pts):  # the blob line's hands: reach from a head (hand_gates' reach)
            _, c_neck = _gates_jit(arms, C, hand, pred, H, gate, False)
            c = np.where(src == 1, np.asarray(c_neck, np.float64)[:n_c], c)
        costs.append(c)
    cost = np.stack(costs)  # (2, c)
    # a window candidate within the gate of the prediction; the blob line's own hands only by
    # the body (a filter whose hand is off must be able to come back to a measured hand); a blob
    # line's hand passing the body's gates is preferred to a window's (+ 1: the window's
    # candidates stand in only where the blob line has none for that hand)
    window = src == 2
    cost = np.where(window[None] & (cost > 1.0), np.inf, cost + window[None])
    # identities are not taken from the prediction (a filter turned the wrong way round would
    # confirm itself): a blob line's hand stays the hand its tracker named, a window's candidate
    # is the hand whose window found it
    cost = np.where(np.arange(2)[:, None] == np.asarray(cand_hand)[None], cost, np.inf)
    # one candidate per hand, never the same point for both
    same = np.linalg.norm(Xc[:, None] - Xc[None], axis=-1) < SAME_POINT_M
    best, best_key = (None, None), None
    c0 = [None, *np.flatnonzero(np.isfinite(cost[0]))]
    c1 = [None, *np.flatnonzero(np.isfinite(cost[1]))]
    for i in c0:
        for j in c1:
            if i is not None and j is not None and same[i, j]:
                continue
            n = (i is not None) + (j is not None)
            total = (0 if i is None else cost[0, i]) + (0 if j is None else cost[1, j])
            key = (-n, total)  # as many hands as possible, then the cheapest
            if best_key is None or key < best_key:
                best, best_key = (i, j), key
    for hand, c in enumerate(best):
        if c is not None:
            out[hand], found[hand] = Xc[c], True
            log["source"][hand] = src[c]
    return out, found, log


_gates_jit = jax.jit(hand_gates, static_argnums=(2, 6))
# the most candidates of a frame: the blob line's two hands and, per hand, every pair of the two
# views' window components (at most MAX_BLOBS each)
MAX_CANDIDATES = 2 + 2 * bloblib.MAX_BLOBS**2
SAME_POINT_M = 0.05  # two candidates closer than this are one point (the blob line's, a window's)



def observe_hands(
    params,
    key: PRNGKeyArray,
    frames: UInt8[np.ndarray, "t 2 h w 3"],
    blob_params: bloblib.BlobParams | None = None,
    hp: HandParams | None = None,
) -> tuple[Observation, dict[str, np.ndarray]]:
    """:func:`~jaxmocap.trackers.stereo_pf.observe_sequence` with the gated hand search (module
    docstring; ``hp`` default ``params.hand_search``): the filter runs alongside from its start
    frame (:func:`~.filter.online_frame`, as :func:`~jaxmocap.trackers.stereo_pf.track` starts
    it); from then on each frame's hands come from :func:`gated_hands` around the prediction
    from the particle sets of the two frames before. Returns the stacked observations and a
    log: ``source`` (T, 2) per hand 0 missing / 1 blob line / 2 window / -1 not searched (the
    filter not yet started)."""
    hp = hp or params.hand_search or HandParams()
    arms = arm_reach(params.model)
    predict = jax.jit(lambda s, lw: cloud_prediction(params, arms, s, lw))
    step = compile_step(params)
    blob_state = bloblib.init(blob_params or BLOB_PARAMS)
    n = len(frames)
    log = {"source": np.full((n, 2), -1, np.int8)}
    out: list[Observation] = []
    state, history = None, []
    for t in range(n):
        frame = np.asarray(frames[t])
        seg = [_segment(params, frame[v]) for v in range(2)]
        obs, blob_state = observe(params, frame, blob_state, segmentation=seg)
        if state is not None and history:
            mean, spread = history[-1]
            vel = mean - history[-2][0] if len(history) >= 2 else np.zeros_like(mean)
            pred = mean + hp.velocity_damping * vel
            masks = [np.asarray(s.skin, bool) for s in seg]
            if hp.motion and t >= 2:
                masks = [mk | motion_map(np.asarray(frames[t - 2:t + 1, v]),
                                         np.asarray(seg[v].foreground, bool),
                                         hp.motion_threshold)
                         for v, mk in enumerate(masks)]
            pts, val = np.asarray(obs.points, np.float64), np.asarray(obs.valid, bool)
            hands, found, hl = gated_hands(params, arms, masks, pred, spread, pts, val, hp)
            pts, val = pts.copy(), val.copy()
            pts[1:], val[1:] = hands, found
            log["source"][t] = hl["source"]
            obs = dataclasses.replace(obs, points=jnp.asarray(pts, obs.points.dtype),
                                      valid=jnp.asarray(val))
        out.append(obs)
        state, est = online_frame(params, key, step, state, out, obs)
        if state is None:
            continue
        mean, spread = predict(state.particles.particles, state.particles.log_weights)
        history = (history + [(np.asarray(mean, np.float64), np.asarray(spread, np.float64))])[-2:]
    return jax.tree.map(lambda *a: jnp.stack(a), *out), log
