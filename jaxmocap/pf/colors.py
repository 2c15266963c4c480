"""Skin and shirt colour of the capture for the stereo particle filter (issue 18).

Azad et al. (§III-A, §IV) segment skin and shirt with fixed HSV intervals
(:mod:`jaxmocap.segment`). On footage from other cameras and lamps no fixed interval works: under
a warm lamp walls and floor fall inside the skin interval, under a cool one a red box does, and
a shirt of another hue is not foreground at all. This module models the colours *of the
capture* instead: one Gaussian per class (skin, shirt) in a lighting-normalised colour space,
fitted from labelled pixels of the capture's first frames (scribbles, or the automatic
calibration of :func:`calibrate_from_frames`), and a pixel belongs to a class when its squared
Mahalanobis distance is below ``threshold``.

**Colour space** (per pixel of the 3x3-blurred RGB image, as Azad's line blurs before HSV):

1. *grey-world white balance* of the frame (von Kries): each channel divided by its frame mean
   (x 100), so a change of the lamps' colour or strength moves skin, shirt and walls together;
2. *chromaticity* ``r = R / (R + G + B)``, ``g = G / (R + G + B)`` (brightness-normalised);
3. *log brightness* ``log((R + G + B) / 3)`` of the balanced image (its variance carries
   shading; it separates the lit face from a dim wall of the same chromaticity).

Measured on the dev split of the independent test world (head pixels fitted on frames 0-2,
threshold 25, every 15th frame): the head stays inside the model on 94-100% of its pixels on
two sequences, a lamp switched off included, where the unbalanced chromaticity lost it
entirely after the switch (a third loses it where the face turns into shadow); ~0.5-20k
background pixels pass per 320x240 image, which the shirt-proximity gate (``near_px``) and
the background histogram cut to tens-hundreds: the head and the hands are attached to the
shirt, the walls have the room's colours.

The skin map is the skin class **within** ``near_px`` pixels of the shirt (head above the
collar, hands at the end of the sleeves), so props and walls away from the subject are not
blobs. All of this is host-side image processing (NumPy / OpenCV) at the I/O edge.

Why one file: everything here works in the one colour space above (its features, histogram
bins and class Gaussians): the fit, the per-pixel maps, the hysteresis skin, the on-line
adaptation, the automatic calibration and the ``pf_colors.json`` file; split, each part would
import the others' private helpers.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import os
from collections.abc import Sequence
from pathlib import Path

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxmocap._config import side_device
from jaxmocap.errors import InputError

FORMAT = "jaxmocap.pf_colors"
VERSION = 1
# chi-square quantiles, 3 DOF: 25 keeps >99.9% of a Gaussian class; the head stayed inside on
# 94-100% of its pixels over the dev sequences (module docstring)
SKIN_THRESHOLD = 25.0
SHIRT_THRESHOLD = 16.0
# skin counted within this many pixels of the shirt: a head ~25 px tall sits on a neck (12 px
# lost the head on the dev split, 20 px gave 62 cm, 30 px 47 cm mean joint error)
NEAR_PX = 30
# variance floors (r, g, log-brightness): a class scribbled on one flat patch must still admit
# the frame-to-frame noise and the shading of a curved surface
MIN_VARIANCE = (0.004**2, 0.003**2, 0.08**2)
CLASSES = ("skin", "shirt")
# Background colour histogram (histogram back-projection against the skin Gaussian): the
# pixels of the calibration frames farther than BACKGROUND_FAR_PX from the shirt, binned in
# feature space over [HIST_LOW, HIST_HIGH) with HIST_BINS bins per axis, smoothed by a
# Gaussian of HIST_SMOOTH bins. A skin pixel must be more likely under the skin class than
# under the background: on the dev split this cut the background pixels passing the skin
# Gaussian from ~0.5-20k to a few hundred per image at the same head coverage.
BACKGROUND_FAR_PX = 40
HIST_BINS = (48, 48, 24)
HIST_LOW = (0.1, 0.1, 2.0)
HIST_HIGH = (0.7, 0.7, 7.0)
HIST_SMOOTH = 1.0
HIST_FLOOR = 1e-3  # counts added to every smoothed bin (colours unseen in the background)
SKIN_LOG_RATIO = 0.0  # log p(x | skin) - log p(x | background) above which a pixel is skin


def features(image: np.ndarray) -> Float[np.ndarray, "h w 3"]:
    """(r, g, log brightness) of the grey-world-balanced, 3x3-blurred RGB uint8 image."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(
            f"pf.colors.features: image: expected (h, w, 3) uint8 RGB, got {image.dtype} "
            f"{image.shape}"
        )
    x = cv2.GaussianBlur(image, (3, 3), 0).astype(np.float32) + 1.0
    x *= 100.0 / x.reshape(-1, 3).mean(0)
    s = x.sum(-1)
    return np.stack([x[..., 0] / s, x[..., 1] / s, np.log(s / 3.0)], -1)


class ColorClass(eqx.Module):
    """One Gaussian class in :func:`features` space."""

    mean: Float[Array, " 3"]
    cov: Float[Array, "3 3"]

    def mahalanobis_sq(self, feats: np.ndarray) -> np.ndarray:
        d = np.asarray(feats, np.float64) - np.asarray(self.mean, np.float64)
        p = np.linalg.inv(np.asarray(self.cov, np.float64))
        return np.einsum("...i,ij,...j->...", d, p, d)


def _bin_index(feats: np.ndarray) -> tuple[np.ndarray, ...]:
    lo, hi, b = (np.asarray(v, np.float64) for v in (HIST_LOW, HIST_HIGH, HIST_BINS))
    i = np.floor((np.asarray(feats, np.float64) - lo) / (hi - lo) * b).astype(np.int64)
    i = np.clip(i, 0, b.astype(np.int64) - 1)
    return tuple(np.moveaxis(i, -1, 0))


def background_histogram(feats: np.ndarray) -> np.ndarray:
    """log density (per unit feature volume) of (n, 3) background feature rows: a smoothed,
    floored histogram (:data:`HIST_BINS`)."""
    from scipy.ndimage import gaussian_filter

    h = np.zeros(HIST_BINS, np.float64)
    np.add.at(h, _bin_index(np.asarray(feats).reshape(-1, 3)), 1.0)
    h = gaussian_filter(h, HIST_SMOOTH) + HIST_FLOOR
    vol = np.prod((np.asarray(HIST_HIGH) - np.asarray(HIST_LOW)) / np.asarray(HIST_BINS))
    return np.log(h / (h.sum() * vol))


class CaptureColors(eqx.Module):
    """Skin and shirt classes of one capture, the background histogram and the thresholds."""

    skin: ColorClass
    shirt: ColorClass
    background: Float[Array, "b0 b1 b2"] | None = None  # log density, background_histogram
    skin_threshold: float = eqx.field(static=True, default=SKIN_THRESHOLD)
    shirt_threshold: float = eqx.field(static=True, default=SHIRT_THRESHOLD)
    near_px: int = eqx.field(static=True, default=NEAR_PX)
    skin_log_ratio: float = eqx.field(static=True, default=SKIN_LOG_RATIO)


def fit_class(feats: np.ndarray, min_variance: Sequence[float] = MIN_VARIANCE) -> ColorClass:
    """Maximum-likelihood Gaussian of (n, 3) feature rows, variances floored."""
    f = np.asarray(feats, np.float64).reshape(-1, 3)
    if f.shape[0] < 10:
        raise InputError(f"pf.colors.fit_class: expected >= 10 labelled pixels, got {f.shape[0]}")
    cov = np.cov(f.T) + np.diag(np.asarray(min_variance, np.float64))
    return ColorClass(jnp.asarray(f.mean(0)), jnp.asarray(cov))


def fit_capture_colors(
    images: Sequence[np.ndarray],
    skin_masks: Sequence[np.ndarray],
    shirt_masks: Sequence[np.ndarray],
    **kw,
) -> CaptureColors:
    """Fit both classes from labelled pixels (scribbles) of one or more RGB uint8 images."""
    if not (len(images) == len(skin_masks) == len(shirt_masks)) or not images:
        raise InputError(
            "pf.colors.fit_capture_colors: expected as many skin and shirt masks as images (>= 1)"
        )
    sk, sh = [], []
    for img, ms, mh in zip(images, skin_masks, shirt_masks, strict=True):
        f = features(img)
        for name, m, out in (("skin", ms, sk), ("shirt", mh, sh)):
            m = np.asarray(m, bool)
            if m.shape != f.shape[:2]:
                raise InputError(
                    f"pf.colors.fit_capture_colors: {name} mask: expected shape {f.shape[:2]}, "
                    f"got {m.shape}"
                )
            out.append(f[m])
    colors = CaptureColors(fit_class(np.concatenate(sk)), fit_class(np.concatenate(sh)), **kw)
    return with_background(colors, images)


def with_background(colors: CaptureColors, images: Sequence[np.ndarray]) -> CaptureColors:
    """``colors`` with the background histogram of ``images``: their pixels farther than
    :data:`BACKGROUND_FAR_PX` from the shirt class's mask (the subject is within reach of it)."""
    k = 2 * BACKGROUND_FAR_PX + 1
    bg = []
    for img in images:
        f = features(img)
        shirt = colors.shirt.mahalanobis_sq(f) < colors.shirt_threshold
        far = cv2.dilate(shirt.astype(np.uint8), np.ones((k, k), np.uint8)) == 0
        bg.append(f[far])
    bg = np.concatenate(bg)
    if bg.shape[0] < 100:
        raise InputError(f"pf.colors.with_background: only {bg.shape[0]} pixels farther than "
                         f"{BACKGROUND_FAR_PX} px from the shirt in the calibration frames; "
                         "expected a view with background around the subject")
    return dataclasses.replace(colors, background=jnp.asarray(background_histogram(bg)))


def _skin_log_ratio(colors: CaptureColors, f: np.ndarray, d_skin: np.ndarray) -> np.ndarray:
    """log p(x | skin) - log p(x | background) of feature rows ``f`` (``d_skin``: their
    squared Mahalanobis distances to the skin class)."""
    cov = np.asarray(colors.skin.cov, np.float64)
    log_skin = -0.5 * d_skin - 0.5 * np.log((2 * np.pi) ** 3 * np.linalg.det(cov))
    return log_skin - np.asarray(colors.background)[_bin_index(f)]


def _class_maps_numpy(colors: CaptureColors, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(skin, shirt) per pixel before the shirt-proximity gate: the direct evaluation (NumPy:
    float32 features, float64 Mahalanobis distances)."""
    f = features(image)
    d_skin = colors.skin.mahalanobis_sq(f)
    d_shirt = colors.shirt.mahalanobis_sq(f)
    shirt = d_shirt < colors.shirt_threshold
    skin = (d_skin < colors.skin_threshold) & (d_skin < d_shirt)
    if colors.background is not None:
        skin &= _skin_log_ratio(colors, f, d_skin) > colors.skin_log_ratio
    return skin, shirt


def _quadratic_form(f, mean, prec):
    """(f - mean)^T prec (f - mean) over the last axis of 3, written out (one fused pass)."""
    d = [f[..., i] - mean[i] for i in range(3)]
    out = prec[0, 0] * d[0] * d[0] + prec[1, 1] * d[1] * d[1] + prec[2, 2] * d[2] * d[2]
    return out + 2.0 * (prec[0, 1] * d[0] * d[1] + prec[0, 2] * d[0] * d[2]
                        + prec[1, 2] * d[1] * d[2])  # fmt: skip


@functools.partial(jax.jit, static_argnames=("skin_threshold", "shirt_threshold", "log_ratio"))
def _class_maps_compiled(blurred, mean_skin, prec_skin, mean_shirt, prec_shirt, log_norm,
                         background, *, skin_threshold, shirt_threshold, log_ratio):  # fmt: skip
    """:func:`_class_maps_numpy` as one fused XLA program (float32) from the 3x3-blurred
    image: the same features, distances, histogram bins and decisions."""
    x = blurred.astype(jnp.float32) + 1.0
    x = x * (100.0 / jnp.mean(x.reshape(-1, 3), axis=0))[None, None, :]
    s = x.sum(-1)
    f = jnp.stack([x[..., 0] / s, x[..., 1] / s, jnp.log(s / 3.0)], -1)
    d_skin = _quadratic_form(f, mean_skin, prec_skin)
    d_shirt = _quadratic_form(f, mean_shirt, prec_shirt)
    skin = (d_skin < skin_threshold) & (d_skin < d_shirt)
    if background is not None:
        i = [
            jnp.clip(jnp.floor((f[..., k] - lo) / (hi - lo) * n).astype(jnp.int32), 0, n - 1)
            for k, (lo, hi, n) in enumerate(zip(HIST_LOW, HIST_HIGH, HIST_BINS, strict=True))
        ]
        log_bg = background[i[0], i[1], i[2]]
        skin &= (-0.5 * d_skin - log_norm - log_bg) > log_ratio
    return skin, d_shirt < shirt_threshold


def _class_maps(colors: CaptureColors, image: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`_class_maps_numpy` through :func:`_class_maps_compiled` (~10x faster on a
    320x240 image; decisions differ only for pixels within float32 rounding of a threshold or
    a histogram bin edge: 1 of 12.3 M on 40 frame pairs of a test-world sequence, 0 of 12.3 M
    on the synthetic clip, ``benchmarks/bench_pf_colors.py``). The precisions and the skin
    class's normaliser are computed in float64 on the host."""
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
        raise InputError(
            f"pf.colors.masks: image: expected (h, w, 3) uint8 RGB, got {image.dtype} "
            f"{image.shape}"
        )
    cov_skin = np.asarray(colors.skin.cov, np.float64)
    prec = [np.linalg.inv(np.asarray(c.cov, np.float64)) for c in (colors.skin, colors.shirt)]
    log_norm = 0.5 * np.log((2 * np.pi) ** 3 * np.linalg.det(cov_skin))
    f32 = functools.partial(np.asarray, dtype=np.float32)
    args = (
        cv2.GaussianBlur(image, (3, 3), 0), f32(colors.skin.mean), f32(prec[0]),
        f32(colors.shirt.mean), f32(prec[1]), np.float32(log_norm),
        None if colors.background is None else f32(colors.background),
    )  # fmt: skip
    side = side_device()  # off the device of a filter step that may be computing (live loops)
    if side is not None:
        args = jax.device_put(args, side)
    skin, shirt = _class_maps_compiled(
        *args,
        skin_threshold=float(colors.skin_threshold), shirt_threshold=float(colors.shirt_threshold),
        log_ratio=float(colors.skin_log_ratio),
    )  # fmt: skip
    return np.asarray(skin), np.asarray(shirt)


def masks(
    colors: CaptureColors, image: np.ndarray, compiled: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """(skin, shirt) boolean maps of an RGB uint8 image: each class below its threshold; skin
    only within ``near_px`` of the shirt, and never where the shirt class is closer.

    ``compiled``: the per-pixel evaluation as one fused XLA program (:func:`_class_maps`);
    False: the direct NumPy evaluation (the reference it is tested against)."""
    skin, shirt = (_class_maps if compiled else _class_maps_numpy)(colors, image)
    if colors.near_px > 0:
        k = 2 * colors.near_px + 1
        near = cv2.dilate(shirt.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
        skin = skin & near
    return skin, shirt



def skin_evidence(
    colors: CaptureColors, image: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel of an RGB uint8 image: (squared Mahalanobis distance to the skin class, the
    same to the shirt class, log p(skin) - log p(background), +inf without a background
    histogram) -- the quantities :func:`masks` thresholds, for searches that relax them in a
    window (:mod:`jaxmocap.trackers.stereo_pf.search`)."""
    f = features(image)
    d_skin = colors.skin.mahalanobis_sq(f)
    d_shirt = colors.shirt.mahalanobis_sq(f)
    ratio = (np.full(d_skin.shape, np.inf) if colors.background is None
             else _skin_log_ratio(colors, f, d_skin))
    return d_skin, d_shirt, ratio


# Hysteresis skin (not in Azad et al.; issue 18): at 320x240 a hand is a few tens of pixels of
# which the capture's skin class (threshold SKIN_THRESHOLD) keeps fragments -- its shaded side
# falls outside -- so the blob line's stereo tests (area / aspect ratio of whole blobs) fail. As
# Canny's hysteresis: the skin map is grown from its own pixels into a relaxed map (the skin
# threshold x GROW_SKIN_SCALE, a log ratio to the background above GROW_MIN_LOG_RATIO, still
# nearer the skin class than the shirt and within near_px of the shirt) by at most `grow` px
# (geodesic dilation, 8-connected): a fragment gains its shaded rim, a wall of the relaxed
# colour is not reached beyond a few pixels. Dev split of the independent test world (3 seeds),
# grow 4 px: mean error 35.5 -> 28.0 cm; on the test split 33.4 -> 34.9 cm (better on 4 of 8
# sequences, worse on 3): an option, not a default (docs/results/stereo_pf.md).
GROW_SKIN_SCALE = 2.0
GROW_MIN_LOG_RATIO = SKIN_LOG_RATIO - 5.0


def hysteresis_masks(
    colors: CaptureColors,
    image: np.ndarray,
    grow: int,
    scale: float = GROW_SKIN_SCALE,
    min_log_ratio: float = GROW_MIN_LOG_RATIO,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(skin, shirt, relaxed skin) boolean maps of an RGB uint8 image: :func:`masks`' skin
    map grown by up to ``grow`` px into the relaxed map (the comment above); ``grow = 0`` is
    :func:`masks`' skin map."""
    if not isinstance(grow, (int, np.integer)) or grow < 0:
        raise InputError(f"pf.colors.hysteresis_masks: grow: expected an int >= 0, got {grow!r}")
    d_skin, d_shirt, ratio = skin_evidence(colors, image)
    shirt = d_shirt < colors.shirt_threshold
    closer = d_skin < d_shirt
    skin = (d_skin < colors.skin_threshold) & closer & (ratio > colors.skin_log_ratio)
    relaxed = (d_skin < scale * colors.skin_threshold) & closer & (ratio > min_log_ratio)
    relaxed |= skin
    if colors.near_px > 0:
        k = 2 * colors.near_px + 1
        near = cv2.dilate(shirt.astype(np.uint8), np.ones((k, k), np.uint8)) > 0
        skin &= near
        relaxed &= near
    return grow_into(skin, relaxed, grow), shirt, relaxed


def grow_into(seed: np.ndarray, region: np.ndarray, steps: int) -> np.ndarray:
    """Geodesic dilation: ``seed`` grown by ``steps`` 8-connected 1-px steps, each step only
    into pixels of ``region`` (``seed`` pixels are kept)."""
    out = np.asarray(seed, bool).astype(np.uint8)
    allowed = (np.asarray(region, bool) | out.astype(bool)).astype(np.uint8)
    k = np.ones((3, 3), np.uint8)
    for _ in range(steps):
        nxt = cv2.dilate(out, k) & allowed
        if np.array_equal(nxt, out):
            break
        out = nxt
    return out.astype(bool)

# ----------------------------------------------------------------------------- on-line adaptation
# Not in Azad et al.: the classes follow the capture's lighting over time (issue 18). On the dev
# split of the independent test world the face's features jump by d^2 ~30-50 from the fitted
# skin class in one frame where the head turns under a lamp (pf_03, frame 23: r 0.33 -> 0.40,
# log brightness -0.6), while an occluder passing in front of the head sits at d^2 ~100 and a
# log ratio vs the background of ~-50: the gates below accept the first and refuse the second.
ADAPT_RATE = 0.1  # weight of one frame's pixels in the running mean / covariance (the cap;
# dev split: 0.3 was worse, 48.4 vs 35.7 cm, with the spread cap at 1)
ADAPT_SKIN_GATE = 2 * SKIN_THRESHOLD  # candidates' d^2 to the current skin class
ADAPT_SHIRT_GATE = SHIRT_THRESHOLD  # ... to the current shirt class: its own pixels (a wider
# gate took the walls inside the body's box on the dev split: the shirt class covered the image)
ADAPT_MIN_LOG_RATIO = SKIN_LOG_RATIO - 5.0  # candidates' log p(skin) - log p(background)
ADAPT_MAX_SPREAD = 1.0  # the adapted class's spread along any axis <= this x the fitted one's
# (dev split: without a cap the face's shading and the neck widened the brightness spread 3x
# and the skin class took the room; 1: the classes move, they do not widen)
ADAPT_MIN_PX = 20  # fewer candidate pixels than this: the class is left as it is


def adapt_class(
    cls: ColorClass, feats: np.ndarray, rate: float, min_variance: Sequence[float] = MIN_VARIANCE
) -> ColorClass:
    """``cls`` moved toward the Gaussian of (n, 3) feature rows with weight ``rate`` in [0, 1]
    (exponential forgetting): the moment-matched mixture (1 - rate) cls + rate new, whose
    covariance keeps both spreads and the shift between their means."""
    f = np.asarray(feats, np.float64).reshape(-1, 3)
    m0, c0 = np.asarray(cls.mean, np.float64), np.asarray(cls.cov, np.float64)
    m1 = f.mean(0)
    c1 = np.cov(f.T) + np.diag(np.asarray(min_variance, np.float64))
    m = (1 - rate) * m0 + rate * m1
    d0, d1 = m0 - m, m1 - m
    cov = (1 - rate) * (c0 + np.outer(d0, d0)) + rate * (c1 + np.outer(d1, d1))
    return ColorClass(jnp.asarray(m), jnp.asarray(cov))


def _cap_spread(cls: ColorClass, ref: ColorClass, factor: float) -> ColorClass:
    """``cls`` with its covariance shrunk, in ``ref``'s whitened space, to eigenvalues of at
    most ``factor``^2 (its spread along any direction <= factor x ``ref``'s)."""
    lr = np.linalg.cholesky(np.asarray(ref.cov, np.float64))
    li = np.linalg.inv(lr)
    a = li @ np.asarray(cls.cov, np.float64) @ li.T
    w, v = np.linalg.eigh(0.5 * (a + a.T))
    a = (v * np.minimum(w, factor**2)) @ v.T
    return ColorClass(cls.mean, jnp.asarray(lr @ a @ lr.T))


def adapt_capture_colors(
    colors: CaptureColors,
    images: Sequence[np.ndarray],
    head_masks: Sequence[np.ndarray],
    body_masks: Sequence[np.ndarray] | None = None,
    rate: float = ADAPT_RATE,
    shirt_rate: float = ADAPT_RATE,
    reference: CaptureColors | None = None,
    max_spread: float = ADAPT_MAX_SPREAD,
) -> tuple[CaptureColors, int, int]:
    """One on-line update of the classes from the tracked subject's pixels: the skin class
    from the pixels inside ``head_masks`` (per image: where the tracker puts the head), the
    shirt class from those inside ``body_masks`` (where it puts the body; None: not adapted).

    Guards against drifting onto the room: a skin candidate is within d^2
    :data:`ADAPT_SKIN_GATE` of the current skin class, closer to it than to the shirt, and
    not much likelier under the background histogram (log ratio >= :data:`ADAPT_MIN_LOG_RATIO`);
    a shirt candidate is within :data:`ADAPT_SHIRT_GATE` of the shirt class and not a skin
    candidate; a class with fewer than :data:`ADAPT_MIN_PX` candidates is left unchanged; one
    frame weighs at most ``rate`` (``shirt_rate``); with ``reference`` (the fitted colours) a
    class's spread stays within ``max_spread`` x the reference class's (1: its covariance
    never wider than the fitted one, the class only moves). The
    background histogram is not adapted (the subject moves through it). Returns (colors,
    skin pixels used, shirt pixels used)."""
    sk, sh = [], []
    for i, img in enumerate(images):
        f = features(img)
        d_skin = colors.skin.mahalanobis_sq(f)
        d_shirt = colors.shirt.mahalanobis_sq(f)
        cand = (d_skin < ADAPT_SKIN_GATE) & (d_skin < d_shirt)
        if colors.background is not None:
            cand &= _skin_log_ratio(colors, f, d_skin) >= ADAPT_MIN_LOG_RATIO
        head = cand & np.asarray(head_masks[i], bool)
        sk.append(f[head])
        if body_masks is not None:
            sh.append(f[np.asarray(body_masks[i], bool) & (d_shirt < ADAPT_SHIRT_GATE) & ~cand])
    n_sk = sum(len(x) for x in sk)
    n_sh = sum(len(x) for x in sh)
    new = {}
    for name, rows, r in (("skin", sk, rate), ("shirt", sh, shirt_rate)):
        if sum(len(x) for x in rows) < ADAPT_MIN_PX or r <= 0:
            continue
        cls = adapt_class(getattr(colors, name), np.concatenate(rows), r)
        if reference is not None:
            cls = _cap_spread(cls, getattr(reference, name), max_spread)
        new[name] = cls
    return (dataclasses.replace(colors, **new), n_sk if "skin" in new else 0,
            n_sh if "shirt" in new else 0)


def save_capture_colors(path: str | os.PathLike, colors: CaptureColors) -> Path:
    """Write ``colors`` as JSON (format ``jaxmocap.pf_colors``)."""
    doc = {"format": FORMAT, "version": VERSION, "space": "greyworld_rg_logi",
           "skin_threshold": colors.skin_threshold, "shirt_threshold": colors.shirt_threshold,
           "near_px": colors.near_px}  # fmt: skip
    for name in CLASSES:
        c = getattr(colors, name)
        doc[name] = {"mean": np.asarray(c.mean).tolist(), "cov": np.asarray(c.cov).tolist()}
    if colors.background is not None:
        doc["background_log_density"] = np.round(np.asarray(colors.background), 4).tolist()
    from jaxmocap.io.atomic import write_text

    path = Path(path)
    write_text(path, json.dumps(doc, indent=2) + "\n")
    return path


def load_capture_colors(path: str | os.PathLike) -> CaptureColors:
    """Read a ``jaxmocap.pf_colors`` file; one-line :class:`InputError` on a bad field."""
    from jaxmocap.io.preflight import read_json

    path = Path(path)
    doc = read_json(path, "a jaxmocap.pf_colors JSON from `jaxmocap colors --pf`")
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(f"{path}: field 'format': expected {FORMAT!r} (from `jaxmocap colors "
                         "--pf`)")
    classes = {}
    for name in CLASSES:
        c = doc.get(name)
        try:
            mean = np.asarray(c["mean"], np.float64)
            cov = np.asarray(c["cov"], np.float64)
        except (TypeError, KeyError, ValueError):
            raise InputError(f"{path}: field {name!r}: expected {{'mean': [3], 'cov': [3x3]}}") \
                from None
        ok = mean.shape == (3,) and cov.shape == (3, 3) and np.all(np.isfinite(cov)) \
            and np.all(np.isfinite(mean)) and np.allclose(cov, cov.T, rtol=1e-6, atol=1e-12)
        if not ok or np.any(np.linalg.eigvalsh(cov) <= 0):
            raise InputError(f"{path}: field {name!r}: expected a finite mean of 3 and a "
                             "symmetric positive-definite 3x3 cov")
        classes[name] = ColorClass(jnp.asarray(mean), jnp.asarray(cov))
    kw = {}
    for k, default in (("skin_threshold", SKIN_THRESHOLD), ("shirt_threshold", SHIRT_THRESHOLD),
                       ("near_px", NEAR_PX)):
        v = doc.get(k, default)
        if isinstance(v, bool) or not isinstance(v, int | float) or not v >= 0:
            raise InputError(f"{path}: field {k!r}: expected a number >= 0, got {v!r}")
        kw[k] = int(v) if k == "near_px" else float(v)
    bg = doc.get("background_log_density")
    if bg is not None:
        try:
            bg = np.asarray(bg, np.float64)
        except ValueError:
            bg = None
        if bg is None or bg.shape != HIST_BINS or not np.all(np.isfinite(bg)):
            raise InputError(f"{path}: field 'background_log_density': expected a finite "
                             f"{'x'.join(map(str, HIST_BINS))} array")
        bg = jnp.asarray(bg)
    return CaptureColors(classes["skin"], classes["shirt"], bg, **kw)


# ----------------------------------------------------------------------------- automatic
# calibrate_from_frames: the shirt is the dominant clearly coloured surface that moves over the
# first frames; the head sits on top of it. Not in Azad et al.; constants for 320x240.
AUTO_FRAMES = 30  # frames of the capture looked at (1 s at 30 Hz)
MOTION_STEP = 5  # frames between the compared images
MOTION_THRESHOLD = 25  # grey-level difference (0..255, 3x3-blurred) of a "moving" pixel
COLOURED = 0.08  # chromaticity distance from neutral grey of a "coloured" pixel (the balanced
# walls of the dev split lie within 0.06 of it, the shirts 0.11-0.19 away)
MODE_RADIUS = 0.03  # chromaticity radius around the histogram mode taken as the shirt
FACE_PERCENTILE = 40  # the window's pixels least like the background taken as face candidates
FACE_RADIUS = 0.02  # chromaticity radius around the window's mode taken as the face
HEAD_WINDOW = (0.35, 0.25)  # head search window above the shirt: height, half width (x the
# shirt's height)


def _shirt_from_motion(frames: Sequence[np.ndarray], feats: np.ndarray) -> np.ndarray:
    """(n, 3) feature rows of the shirt: among the pixels that change over the frames and are
    clearly coloured, those near the chromaticity mode (the moving subject is mostly shirt)."""
    grey = [cv2.GaussianBlur(cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), (3, 3), 0) for f in frames]
    rows = []
    for t in range(0, len(frames) - MOTION_STEP, MOTION_STEP):
        for a in (t, t + MOTION_STEP):
            moving = cv2.absdiff(grey[t], grey[t + MOTION_STEP]) > MOTION_THRESHOLD
            rows.append(feats[a][moving])
    f = np.concatenate(rows) if rows else np.zeros((0, 3))
    coloured = np.hypot(f[:, 0] - 1 / 3, f[:, 1] - 1 / 3) > COLOURED
    f = f[coloured]
    if f.shape[0] < 100:
        raise InputError("pf.colors.calibrate_from_frames: fewer than 100 coloured pixels move "
                         "over the calibration frames; give the colours from scribbles "
                         "(`jaxmocap colors --pf`)")
    return _near_mode(f, MODE_RADIUS)


def _near_mode(f: np.ndarray, radius: float) -> np.ndarray:
    """The rows of ``f`` within ``radius`` (chromaticity) of the 2D chromaticity histogram's
    mode (50 bins per axis)."""
    h, ex, ey = np.histogram2d(f[:, 0], f[:, 1], bins=50, range=((0, 1), (0, 1)))
    i, j = np.unravel_index(np.argmax(h), h.shape)
    mode = np.array([(ex[i] + ex[i + 1]) / 2, (ey[j] + ey[j + 1]) / 2])
    return f[np.hypot(*(f[:, :2] - mode).T) < radius]


def calibrate_from_frames(
    frames: Sequence[np.ndarray], n_frames: int = AUTO_FRAMES, **kw
) -> CaptureColors:
    """The capture's colours without labels, from the first ``n_frames`` RGB uint8 frames of
    one camera:

    1. **shirt**: the Gaussian of the clearly coloured pixels that move over the frames, near
       their chromaticity mode (walls and props do not move; the subject is mostly shirt);
    2. **background**: the histogram of the pixels far from the shirt (:func:`with_background`);
    3. **skin**: the face -- in a window above the shirt's largest component, centred on its
       centroid's column (the torso dominates it), the pixels that are neither shirt nor
       background-like (log background density below the window's 40th percentile), near the
       chromaticity mode of those.
    """
    frames = [np.asarray(f) for f in list(frames)[:n_frames]]
    if len(frames) < 2:
        raise InputError("pf.colors.calibrate_from_frames: expected >= 2 frames")
    feats = np.stack([features(f) for f in frames])
    shirt = fit_class(_shirt_from_motion(frames, feats))
    dummy = ColorClass(shirt.mean, shirt.cov)
    colors = with_background(CaptureColors(dummy, shirt, **kw), frames[:: max(1, len(frames) // 5)])
    bg = np.asarray(colors.background)
    skin_px = []
    for f in feats[:: max(1, len(feats) // 5)]:
        m = shirt.mahalanobis_sq(f) < colors.shirt_threshold
        n, lab, stats, cents = cv2.connectedComponentsWithStats(m.astype(np.uint8), 8)
        if n < 2:
            continue
        k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
        x0, y0, w, h = stats[k, :4]
        cx = int(round(cents[k][0]))
        col = np.flatnonzero(lab[:, max(cx - 2, 0):cx + 3].max(1) == k)
        top = int(col[0]) if col.size else y0
        hh, hw = int(HEAD_WINDOW[0] * h), int(HEAD_WINDOW[1] * h)
        win = (slice(max(top - hh, 0), top), slice(max(cx - hw, 0), cx + hw + 1))
        lb = bg[_bin_index(f[win])]
        cand = ~m[win] & (lb < np.percentile(lb, FACE_PERCENTILE))
        skin_px.append(f[win][cand])
    skin_px = np.concatenate(skin_px) if skin_px else np.zeros((0, 3))
    if skin_px.shape[0] >= 10:
        skin_px = _near_mode(skin_px, FACE_RADIUS)
    if skin_px.shape[0] < 10:
        raise InputError("pf.colors.calibrate_from_frames: no face found above the shirt in the "
                         "calibration frames; give the colours from scribbles (`jaxmocap colors "
                         "--pf`)")
    return dataclasses.replace(colors, skin=fit_class(skin_px))
