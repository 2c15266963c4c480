"""Per-part colours for the stereo filter: head, each hand and the shirt follow the light, and
each skin part is searched near its predicted position with its own colour (issue 37 item 4;
not in Azad et al. 2007).

Azad's line (§III-A, §IV) finds the head and the hands as blobs of one global skin class
(here the capture's, :mod:`jaxmocap.pf.colors`). Under two spot lamps of different colour the
face's lit and shaded sides, and a hand under the other lamp, leave that one class. The filter
knows at every frame where each part is: this module keeps one colour state per part in the
shared appearance layer (:mod:`jaxmocap.appearance`) and

1. **updates it from the estimate** (:func:`update_colours`): the estimated pose is rendered
   into both cameras by the ray caster (:func:`render_parts`: head, left hand, right hand,
   shirt, by the body's roles), each part's mask eroded (:data:`ERODE_PX`), and a part's
   pixels are used only where its measurement agrees with the estimate (the head's
   triangulated point within ``VALID_HEAD_M``, a hand's within :data:`AGREE_HAND_M`); a frame
   whose head does not agree is invalid and leaves the state untouched
   (:func:`jaxmocap.appearance.update_parts`: trimmed, rate-limited, spread-bounded, relit by
   the two-illuminant fit, relaxing to the calibration after a loss);
2. **searches each skin part near its prediction** (:func:`seeded_search`): the filter's
   prediction (last estimate plus damped velocity) projected into each view; the pixels within
   ``window_m`` of it (metres at its depth) whose shading-invariant distance to *that part's*
   colour is below ``threshold`` and closer to it than to the shirt's; the component nearest the
   projected prediction in each view; the pair triangulated and accepted within ``gate_m`` of
   the prediction and below ``max_epipolar_px``. A part found this way replaces the blob line's
   measurement of it; where the search finds nothing, or before there is a prediction (first
   frame, after a loss), the blob line's detection stands.

Colour space: RGB of the 3x3-blurred image (the blur of Azad's line), where a lamp's change is a
per-channel gain (the relight of :func:`jaxmocap.appearance.fit_relight` needs a linear space;
the grey-world chromaticity of :mod:`jaxmocap.pf.colors` is not one). The calibrated start is the
capture's classes on the first frame with a triangulated head (:func:`calibrate_parts`): the
pixels of its skin map (all three skin parts start from it) and of its shirt map.

**Measured: not an improvement; opt-in**
(``make_params(images=Images(colors=..., part_colours=True))``, experiment option
``part_colours``; ``docs/results/world_pf_parts.md``). Dev split, seed 0, against the
same filter without it: each hand within 8 cm of the truth on 40 / 9 / 20 / 6% (left) and
51 / 0 / 22 / 2% (right) of its visible frames, against 46 / 0 / 24 / 6% and 55 / 0 / 26 / 0%;
mean joint error 14.4 / 44.7 / 37.1 / 44.9 cm against 13.9 / 42.4 / 34.5 / 41.6 (pf_00, 03, 06,
09). Both steps need the estimate: where the filter's hands are 15-40 cm off (most frames of
the dev split) the prediction's window does not hold the hand and the render does not cover
it. The frame costs ~8x as much (11 -> 89 ms, the seeded search's full-image distance maps
~60 ms of it; ``benchmarks/experiments/pf_parts_timing.py``).
"""

from __future__ import annotations

import dataclasses
import functools

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxmocap import appearance
from jaxmocap import blobs as bloblib
from jaxmocap.body import BodyModel, require_roles
from jaxmocap.body.roles import geom_roles
from jaxmocap.camera import Camera
from jaxmocap.garment import Garment, shirt_geoms, single_colour_garment
from jaxmocap.render import render_ids
from jaxmocap.trackers.stereo_pf.params import BLOB_PARAMS, SeedParams

PARTS = ("head", "l_hand", "r_hand", "shirt")  # labels 1..4 of render_parts
SKIN_PARTS = 3  # the first three are skin (the blob line's entities, same order)
ERODE_PX = 1  # a part's rendered mask loses this many pixels at its border (a hand is ~8 px)


class PartScene(eqx.Module):
    """What :func:`render_parts` casts rays against: the body, a one-colour garment (the ray
    caster's contract; only geom ids are read) and the part label of every geom (index
    ``geom + 1``; 0: background or a geom of no part)."""

    model: BodyModel
    garment: Garment
    labels: Int[Array, " g1"]


def part_scene(model: BodyModel) -> PartScene:
    """The scene of :func:`render_parts` for ``model``: geoms of the ``head`` / ``l_hand`` /
    ``r_hand`` link roles (:func:`jaxmocap.body.roles.geom_roles`) and the shirt's geoms
    (:func:`jaxmocap.garment.shirt_geoms`), by roles."""
    roles = require_roles(model, "stereo_pf.parts")
    by_role = geom_roles(model.chain, model.geometry, dict(roles.links), roles.skin_geoms)
    labels = np.zeros(len(model.geometry.names) + 1, np.int32)
    shirt = set(shirt_geoms(model))
    for g, name in enumerate(model.geometry.names):
        if name in shirt:
            labels[g + 1] = 4
    for k, role in enumerate(PARTS[:SKIN_PARTS]):
        for g in by_role.get(role, []):
            labels[g + 1] = k + 1
    garment = single_colour_garment(model, (0.5, 0.5, 0.5))
    return PartScene(model, garment, jnp.asarray(labels))


def render_parts(scene: PartScene, cams: Camera, q: Float[Array, " n_dof"]) -> Int[Array, "v h w"]:
    """Part label (0 none, 1..4 = :data:`PARTS`) of every pixel of each stacked camera at pose
    ``q`` (the ray caster's nearest geom: a hand in front of the chest hides the shirt)."""
    def one(cam):
        hits = render_ids(scene.model, scene.garment, q, cam)
        return scene.labels[hits.geom + 1]

    return jax.vmap(one)(cams)


def erode_labels(labels: Int[Array, "*v h w"], px: int = ERODE_PX) -> Int[Array, "*v h w"]:
    """Each label kept only where its whole 3x3 neighbourhood has it, ``px`` times (no pixel
    on a part's border: the blur and the render's misfit mix colours there)."""
    for _ in range(px):
        pad = jnp.pad(labels, [(0, 0)] * (labels.ndim - 2) + [(1, 1), (1, 1)], constant_values=-1)
        h, w = labels.shape[-2:]
        same = jnp.ones(labels.shape, bool)
        for dy in range(3):
            for dx in range(3):
                same &= pad[..., dy:dy + h, dx:dx + w] == labels
        labels = jnp.where(same, labels, 0)
    return labels


# ----------------------------------------------------------------------------- colour states
SHADING = (0.25, 2.0)  # search: a pixel may be this much darker / brighter than its part
UPDATE_SHADING = (0.5, 2.0)  # update: the same, narrower (a part's own shadow, not the room)
UPDATE_GATE = 9.0  # update: a pixel farther than this squared distance is trimmed
RATES = (0.3, 0.3, 0.3, 0.1)  # weight of one frame's pixels per part (head, hands, shirt)
MIN_STD = 4.0  # RGB floor of a calibrated class's standard deviation per channel (noise ~2.5)
AGREE_HAND_M = 0.05  # a hand's pixels update its colour when its measurement is this near
RELIGHT = SeedParams.relight  # the update's two-illuminant relight (SeedParams)
SEED_MAX_AGE = 30  # a part not updated for this many frames is searched no more (a loss)


def blurred(image: np.ndarray) -> Float[np.ndarray, "h w 3"]:
    """The colour space of the part states: RGB of the 3x3-blurred uint8 image, float32."""
    return cv2.GaussianBlur(np.asarray(image), (3, 3), 0).astype(np.float32)


def calibrate_parts(
    colors, images, labels: Int[np.ndarray, "v h w"], min_pixels: int = 20
) -> appearance.PartColours | None:
    """The calibrated start of the four part states (:data:`PARTS`): the capture's classes
    (``colors``: :class:`jaxmocap.pf.colors.CaptureColors`) on ``images`` (RGB uint8, each
    view) where the estimate's render ``labels`` (:func:`render_parts`, eroded) puts the head
    (skin map; all three skin parts start from it) and the shirt (shirt map): the Gaussian of
    those pixels, each channel's spread floored at :data:`MIN_STD`. The estimate's part narrows
    the class to this subject under this frame's light (the whole skin map of a test-world
    frame has a spread of ~40 grey levels; walls and props pass it). None when the head or
    the shirt has fewer than ``min_pixels`` such pixels (the caller tries the next frame)."""
    from jaxmocap.pf.colors import masks

    sk, sh = [], []
    for img, lab in zip(images, np.asarray(labels), strict=True):
        skin, shirt = masks(colors, np.asarray(img))
        x = blurred(img)
        sk.append(x[skin & (lab == 1)])
        sh.append(x[shirt & (lab == 4)])
    out = []
    for rows in (sk, sh):
        f = np.concatenate(rows).astype(np.float64)
        if f.shape[0] < min_pixels:
            return None
        out.append((f.mean(0), np.cov(f.T) + np.eye(3) * MIN_STD**2))
    (ms, cs), (mh, ch) = out
    mean = np.stack([ms, ms, ms, mh])
    cov = np.stack([cs, cs, cs, ch])
    return appearance.init_parts(jnp.asarray(mean, jnp.float32), jnp.asarray(cov, jnp.float32))


@functools.partial(jax.jit, static_argnames=("relight",))
def update_colours(
    state: appearance.PartColours,
    images: Float[Array, "v h w 3"],
    labels: Int[Array, "v h w"],
    agree: Bool[Array, " 4"],
    valid: Bool[Array, ""],
    relight: bool = RELIGHT,
) -> tuple[appearance.PartColours, Bool[Array, " 4"], appearance.Relight]:
    """One frame's update of the part states (module docstring, 1): ``labels`` the estimate's
    eroded part render in every view, ``agree`` which parts' measurements agree with the
    estimate (the others' pixels are not used), ``valid`` whether the frame is (else the state
    is left as it is). Returns :func:`jaxmocap.appearance.update_parts`'s triple."""
    use = jnp.concatenate([jnp.zeros((1,), bool), agree])[labels]
    v, h, w = labels.shape
    stats = appearance.part_statistics(state, images.reshape(v * h, w, 3),
                                       labels.reshape(v * h, w), gate=UPDATE_GATE,
                                       shading=UPDATE_SHADING, mask=use.reshape(v * h, w))
    rate = jnp.asarray(RATES, state.mean.dtype)
    return appearance.update_parts(state, stats, valid, rate=rate, relight=relight)


@jax.jit
def _distances(state: appearance.PartColours, images: Float[Array, "v h w 3"]):
    return appearance.part_distances(state, images, SHADING)


# ----------------------------------------------------------------------------- seeded search
def seeded_search(
    params,
    colours: appearance.PartColours,
    images: Float[np.ndarray, "2 h w 3"],
    predicted: Float[np.ndarray, "3 3"],
    points: Float[np.ndarray, "3 3"],
    valid: Bool[np.ndarray, " 3"],
    seed: SeedParams | None = None,
    searched: Bool[np.ndarray, " 3"] | None = None,
) -> tuple[Float[np.ndarray, "3 3"], Bool[np.ndarray, " 3"], Bool[np.ndarray, " 3"]]:
    """Each skin part (head, left hand, right hand) searched near its ``predicted`` position
    (3, 3) m in both views ``images`` (:func:`blurred`) with its own colour state (module
    docstring, 2); ``searched``: the parts to search (default all). Returns the points and
    valid flags with the found parts filled in (the others as the blob line gave them) and
    which parts the search found."""
    from jaxmocap.trackers.stereo_pf.search import _components, _paired, _project_both

    seed = SeedParams() if seed is None else seed

    cams = params.likelihood.cams
    points = np.array(points, np.float64)
    valid = np.array(valid, bool)
    found = np.zeros(3, bool)
    predicted = np.asarray(predicted, np.float64)
    searched = np.ones(3, bool) if searched is None else np.asarray(searched, bool)
    if not np.all(np.isfinite(predicted)):
        return points, valid, found
    d2 = np.asarray(_distances(colours, jnp.asarray(images)))  # (2, h, w, 4)
    h, w = d2.shape[1:3]
    f = np.asarray(cams.K, np.float64)[:, 0, 0]
    yy, xx = np.mgrid[:h, :w]
    head = points[0] if valid[0] else predicted[0]
    uv, depth = (np.asarray(x, np.float64) for x in _project_both(
        cams, jnp.asarray(np.vstack([predicted, head[None]]), jnp.float32)))  # (2, 4, 2), (2, 4)
    m = BLOB_PARAMS.max_blobs  # the blob line's pair kernel, compiled once for both
    for e in range(SKIN_PARTS):
        if not searched[e] or (valid[e] and not seed.replace[e]) or np.any(depth[:, e] <= 0):
            continue
        cands = []
        for v in range(2):
            r = f[v] * seed.window_m / max(depth[v, e], 1e-3)
            disc = (xx - uv[v, e, 0]) ** 2 + (yy - uv[v, e, 1]) ** 2 <= r * r
            region = disc & (d2[v, ..., e] < seed.threshold) & (d2[v, ..., e] <= d2[v, ..., 3])
            if e > 0 and depth[v, 3] > 0:  # a hand: not in the face
                rh = f[v] * seed.head_exclude_m / depth[v, 3]
                region &= (xx - uv[v, 3, 0]) ** 2 + (yy - uv[v, 3, 1]) ** 2 > rh * rh
            cands.append(_components(region, region, uv[v, e], seed.min_area, 0, m))
        pairs = _paired(cams, cands, m, predicted[e], seed.max_epipolar_px, seed.gate_m)
        if pairs is None:
            continue
        X, dist, ok = pairs
        if not ok.any():
            continue
        i, j = np.unravel_index(np.argmin(np.where(ok, dist, np.inf)), ok.shape)
        points[e], valid[e], found[e] = X[i, j], True, True
    return points, valid, found


# ----------------------------------------------------------------------------- the sequence
def observe_parts(params, key, frames, blob_params: bloblib.BlobParams | None = None):
    """:func:`~jaxmocap.trackers.stereo_pf.observe_sequence` with per-part colours and the
    seeded search (module docstring; ``params.part_colours`` the :class:`SeedParams`). The
    filter runs alongside from the first frame with a triangulated head (initialised there as
    :func:`~jaxmocap.trackers.stereo_pf.track` does, then stepped from frame 0); the part
    states start there (:func:`calibrate_parts`). Frame t is searched with the states updated
    up to frame t - 1 around the prediction from the estimates of frames t - 1 and t - 2.

    Returns the stacked observations and a log: ``found`` (T, 3) the parts the seeded search
    found, ``updated`` (T, 4) the parts whose state a frame updated, ``mean`` (T, 4, 3) the
    states' means after the frame, ``relit`` (T,) whether the relight was applied."""
    from jaxmocap.body import keypoint_index, keypoints
    from jaxmocap.errors import InputError
    from jaxmocap.trackers.stereo_pf.checks import VALID_HEAD_M
    from jaxmocap.trackers.stereo_pf.filter import compile_step, online_frame
    from jaxmocap.trackers.stereo_pf.observation import observe

    seed = params.part_colours
    if seed is None or params.colors is None:
        raise InputError("stereo_pf.parts.observe_parts: params without part colours "
                         "(make_params(images=Images(colors=..., part_colours=True)))")
    model = params.model
    idx = np.asarray([keypoint_index(model, k)[0] for k in bloblib.ENTITY_NAMES])
    kp_fn = jax.jit(lambda q: keypoints(model, q)[idx])
    cams = params.likelihood.cams
    scene = part_scene(model)
    render = jax.jit(lambda q: erode_labels(render_parts(scene, cams, q)))
    step = compile_step(params)
    blob_state = bloblib.init(blob_params or BLOB_PARAMS)
    n = len(frames)
    log = {"found": np.zeros((n, 3), bool), "updated": np.zeros((n, 4), bool),
           "mean": np.full((n, 4, 3), np.nan), "relit": np.zeros(n, bool)}  # fmt: skip
    out = []
    state, colours, history = None, None, []
    limit = np.array([VALID_HEAD_M, AGREE_HAND_M, AGREE_HAND_M])
    for t in range(n):
        obs, blob_state = observe(params, frames[t], blob_state)
        blob_head = np.asarray(obs.points[0], np.float64) if bool(obs.valid[0]) else None
        images = np.stack([blurred(frames[t][v]) for v in range(2)])
        if colours is not None and history:
            last = history[-1]
            vel = last - history[-2] if len(history) >= 2 else np.zeros_like(last)
            pred = last + seed.velocity_damping * vel
            searched = np.asarray(colours.age)[:SKIN_PARTS] <= SEED_MAX_AGE
            pts, val, found = seeded_search(params, colours, images, pred,
                                            np.asarray(obs.points), np.asarray(obs.valid),
                                            seed, searched)  # fmt: skip
            log["found"][t] = found
            obs = dataclasses.replace(obs, points=jnp.asarray(pts, obs.points.dtype),
                                      valid=jnp.asarray(val))  # fmt: skip
        out.append(obs)
        state, est = online_frame(params, key, step, state, out, obs)
        if est is None:
            continue
        q = np.asarray(est.q)
        if not np.all(np.isfinite(q)):
            continue
        kp = np.asarray(kp_fn(jnp.asarray(q)), np.float64)
        history = (history + [kp])[-2:]
        pts, val = np.asarray(obs.points, np.float64), np.asarray(obs.valid, bool)
        agree3 = val & (np.linalg.norm(pts - kp, axis=-1) <= limit)
        # the frame (and the head's colour) only on the blob line's own head: the seeded
        # search's head is where the filter predicted it, no check of the estimate
        frame_ok = blob_head is not None and np.linalg.norm(blob_head - kp[0]) <= limit[0]
        agree3[0] = frame_ok
        labels = render(jnp.asarray(q))
        if colours is None:  # the start: the first frame whose head agrees (calibrate_parts)
            if frame_ok:
                colours = calibrate_parts(params.colors, frames[t], labels)
            if colours is None:
                continue
        agree = np.append(agree3, frame_ok)
        colours, used, fit = update_colours(colours, jnp.asarray(images), labels,
                                            jnp.asarray(agree), jnp.asarray(frame_ok),
                                            seed.relight)
        log["updated"][t] = np.asarray(used)
        log["mean"][t] = np.asarray(colours.mean)
        log["relit"][t] = bool(fit.ok)
    return jax.tree.map(lambda *a: jnp.stack(a), *out), log
