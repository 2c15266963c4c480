"""The host's image line (Azad §III-A, §IV): segmentation, the hand-support map, the skin
blobs triangulated and tracked -> one :class:`jaxmocap.pf.cues.Observation` per frame."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, UInt8

from jaxmocap import blobs as bloblib
from jaxmocap.errors import InputError
from jaxmocap.pf import cues
from jaxmocap.pf.colors import hysteresis_masks
from jaxmocap.pf.colors import masks as color_masks
from jaxmocap.pf.cues import Observation
from jaxmocap.segment import Segmentation, segment_cv
from jaxmocap.trackers.stereo_pf.params import BLOB_PARAMS, StereoPFParams


def support_map(
    skin: Bool[np.ndarray, "h w"],
    foreground: Bool[np.ndarray, "h w"],
    dilate_px: int = cues.SUPPORT_DILATE_PX,
) -> Float[np.ndarray, "h w"]:
    """The hand-support map S of one image (host, OpenCV): 1 where a hand may be without being
    seen as a separate skin blob -- on skin (a blob, possibly merged with the head) or behind
    the shirt -- dilated by ``dilate_px`` pixels (a square of side 2 dilate_px + 1: the hand
    centre lies up to a hand's radius inside its blob's border), 0 on plain background."""
    m = (np.asarray(skin) | np.asarray(foreground)).astype(np.uint8)
    if dilate_px > 0:
        k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
        m = cv2.dilate(m, k)
    return m.astype(np.float32)


def _segment(params: StereoPFParams, image: np.ndarray) -> Segmentation:
    """Azad's image line on one image; with ``params.colors`` the skin map and the foreground
    come from the capture's colour model (:func:`jaxmocap.pf.colors.masks`)."""
    if params.colors is None:
        return segment_cv(params.segment, image)
    if params.skin_grow > 0:
        skin, shirt, _ = hysteresis_masks(params.colors, image, params.skin_grow)
    else:
        skin, shirt = color_masks(params.colors, image)
    seg = segment_cv(params.segment, image, foreground=shirt)
    return Segmentation(skin, seg.foreground, seg.edges)


def _fit_head(params: StereoPFParams, seg, points: np.ndarray) -> np.ndarray:
    """``points`` with the head replaced by the fitted head sphere's keypoint (where it fits;
    :func:`jaxmocap.trackers.stereo_pf.head.fit_head`)."""
    from jaxmocap.trackers.stereo_pf.head import fit_head

    radius, offset = params.head_sphere
    c = fit_head(params.likelihood.cams, [s.skin for s in seg], [s.foreground for s in seg],
                 np.asarray(points[bloblib.HEAD], np.float64), radius)
    if c is None:
        return points
    points = np.array(points, copy=True)
    points[bloblib.HEAD] = c + np.asarray(offset)
    return points


def observe(
    params: StereoPFParams,
    frame_pair: UInt8[np.ndarray, "2 h w 3"],
    blob_state: bloblib.BlobState | None,
    blob_obs: tuple[np.ndarray, np.ndarray] | None = None,
    segmentation: list[Segmentation] | None = None,
) -> tuple[Observation, bloblib.BlobState | None]:
    """Host side of one frame: image processing line of both images (OpenCV) and the hand /
    head tracker (unless ``blob_obs = (points3d (3, 3), valid (3,))`` is given);
    ``segmentation``: both images' :class:`~jaxmocap.segment.Segmentation` if the caller
    already has them."""
    frame_pair = np.asarray(frame_pair)
    cams = params.likelihood.cams
    if frame_pair.shape != (2, cams.height, cams.width, 3) or frame_pair.dtype != np.uint8:
        raise InputError(
            f"stereo_pf: frame_pair: expected uint8 (2, {cams.height}, {cams.width}, 3) RGB, "
            f"got {frame_pair.dtype} {frame_pair.shape}"
        )
    if params.observer is not None and segmentation is None:  # the learned parts, named
        from jaxmocap.trackers.stereo_pf import learned

        probs = learned.part_probabilities(params.observer, frame_pair)
        segmentation = learned.segmentation(params.segment, frame_pair, probs)
        if blob_obs is None:
            blob_obs = learned.part_points(cams, probs, params.reach)
    seg = segmentation or [_segment(params, frame_pair[i]) for i in range(2)]
    if blob_obs is None:
        blob_state, points, valid = bloblib.update(
            blob_state, seg[0].skin, seg[1].skin, cams, reach=params.reach
        )
    else:
        points, valid = blob_obs
    if params.head_sphere is not None and valid[bloblib.HEAD]:
        points = _fit_head(params, seg, points)
    dt = np.dtype(params.prior_lower.dtype)
    support = None
    if params.likelihood.use_support:
        support = np.stack([support_map(s.skin, s.foreground) for s in seg]).astype(dt)
    # one device_put of the whole observation: five jnp.asarray calls cost ~0.3 ms more per
    # frame (0.95 against 0.65 ms, measured), the same values
    edges, points, valid, fg, support = jax.device_put((
        np.stack([s.edges for s in seg]).astype(dt),
        np.asarray(points).astype(dt),
        np.asarray(valid, bool),
        np.stack([s.foreground for s in seg]).astype(dt),
        support,
    ))  # fmt: skip
    obs = Observation(edges=edges, points=points, valid=valid, foreground=fg, support=support)
    return obs, blob_state


def observe_sequence(
    params: StereoPFParams,
    frames: UInt8[np.ndarray, "t 2 h w 3"],
    blob_params: bloblib.BlobParams | None = None,
) -> Observation:
    """:func:`observe` over a sequence (one blob tracker through it, ``blob_params`` default
    :data:`BLOB_PARAMS`), stacked on axis 0."""
    blob_state = bloblib.init(blob_params or BLOB_PARAMS)
    out = []
    for t in range(len(frames)):
        obs, blob_state = observe(params, frames[t], blob_state)
        out.append(obs)
    return jax.tree.map(lambda *a: jnp.stack(a), *out)
