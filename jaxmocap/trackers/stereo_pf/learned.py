"""The stereo filter's image line on the learned observation layer (issue 50; not in Azad et al.
2007): the head, each hand and the shirt from a model trained on the project's own renders
(:mod:`jaxmocap.observe`, framing ``"frame"``), instead of one global skin class and a blob
tracker that names the hands by tracking.

Per frame pair (host, around one jitted call of the model on both views):

1. **Part probabilities** (:func:`part_probabilities`): each view downscaled (OpenCV
   ``INTER_AREA``) to the model's scale -- the focal length :data:`MODEL_FOCAL_PX`, at which the
   training crops show a person ~2 m away (a 320 x 240 rig of ~58 deg at half resolution) --,
   the model's per-pixel probabilities of background, shirt, head, left hand and right hand
   (:func:`jaxmocap.observe.part_maps`), upsampled to the frame (bilinear);
2. **segmentation** (:func:`segmentation`): the skin map is the pixels whose most probable
   class is a skin part, the shirt (Azad's foreground, its edges the edge cue's) those whose
   most probable class is the shirt;
3. **named points** (:func:`part_points`): the head's candidates in each view -- the connected
   components of the pixels where the head is the most probable class, at least
   :data:`MIN_AREA_PX`, weighed by the probability they hold -- paired across the views by the
   symmetric epipolar distance (at most :data:`MAX_EPIPOLAR_PX`, in front of both cameras),
   the pair of most probability triangulated; the hands the same on the pixels where either
   hand is most probable, up to two disjoint pairs, each named by the model's left / right
   probability summed over its components in both views (the two never the same hand: on its
   own renders the model mixes left and right on a quarter of the hand pixels, and either
   hand's skin is what it finds best). A part with no pair is **missing** (``valid`` False): a
   hand the model does not see is never a wrong point. With ``reach`` (the blob line's
   plausibility), a hand farther than the arms reach from the head, or nearer than the neck,
   is missing too.

Where the model cannot tell the hands apart (a back view) the filter's hand-swap cue
(``Cues(hand_swap=True)``) pairs each particle's hands with the measured ones in the nearer
pairing, as it does for the blob line.
"""

from __future__ import annotations

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, UInt8

from jaxmocap import blobs as bloblib
from jaxmocap.camera import Camera
from jaxmocap.observe import Classes, Observer, part_maps
from jaxmocap.observe.model import log_probs
from jaxmocap.segment import Segmentation, SegmentParams, segment_cv

# The focal length (px) at which the model reads a frame: the "frame" training crops (128 px,
# 1.1-3.5 x the shirt's box, jaxmocap.observe.scenes.FRAMINGS) show the shirt 37-116 px across,
# as a person ~2 m from a 290 px-focal camera (320 x 240, 58 deg) does at half resolution.
MODEL_FOCAL_PX = 145.0
MIN_AREA_PX = 4  # a part's component at full resolution (a hand 2 m away at 320x240: ~40 px)
MAX_EPIPOLAR_PX = 3.0  # as the blob line's (Azad §IV) stereo test
CANDIDATES = 3  # components per part and view paired
PARTS = ("shirt", "head", "left_hand", "right_hand")  # planes after the background


class LearnedParts(eqx.Module):
    """The model and how the stereo line reads it: ``scale`` (model px per frame px) and the
    size of the frames the model reads (even, :class:`~jaxmocap.observe.Observer`'s need)."""

    observer: Observer
    n_colours: int = eqx.field(static=True)
    size: tuple[int, int] = eqx.field(static=True)  # (width, height) the model reads

    @property
    def classes(self) -> int:
        return self.observer.n_classes


def learned_parts(observer: Observer, classes: Classes, cams: Camera) -> LearnedParts:
    """:class:`LearnedParts` for the rig ``cams`` (stacked, both views the same size): the
    frames read at :data:`MODEL_FOCAL_PX` (the mean focal length of the two views)."""
    if observer.n_classes != classes.n:
        raise ValueError(f"stereo_pf.learned: the model gives {observer.n_classes} classes, the "
                         f"body + shirt have {classes.n}")
    f = float(np.mean(np.asarray(cams.K)[:, [0, 1], [0, 1]]))
    s = min(1.0, MODEL_FOCAL_PX / f)
    w, h = int(cams.width), int(cams.height)
    size = (max(2, 2 * round(w * s / 2)), max(2, 2 * round(h * s / 2)))
    return LearnedParts(observer, classes.n_colours, size)


@eqx.filter_jit
def _planes(observer: Observer, n_colours: int, images: Float[Array, "v h w 3"]
            ) -> Float[Array, "v h w 5"]:
    cls = Classes(("",) * observer.n_classes, n_colours, np.zeros(1, np.int32))

    def one(image):
        pm = part_maps(cls, log_probs(observer, image))
        return jnp.stack([pm.background, pm.shirt, pm.head, pm.left_hand, pm.right_hand], -1)

    return jax.vmap(one)(images)


def part_probabilities(lp: LearnedParts, frame_pair: UInt8[np.ndarray, "v h w 3"]
                       ) -> Float[np.ndarray, "v h w 5"]:
    """Per-pixel probabilities of background, shirt, head, left hand, right hand of each view
    at the frame's resolution (module docstring, step 1)."""
    h, w = frame_pair.shape[1:3]
    small = np.stack([cv2.resize(np.asarray(im), lp.size, interpolation=cv2.INTER_AREA)
                      for im in frame_pair])
    p = np.asarray(_planes(lp.observer, lp.n_colours, jnp.asarray(small, jnp.float32)))
    if lp.size == (w, h):
        return p
    return np.stack([cv2.resize(pv, (w, h), interpolation=cv2.INTER_LINEAR) for pv in p])


def segmentation(segment: SegmentParams, frame_pair: UInt8[np.ndarray, "v h w 3"],
                 probs: Float[np.ndarray, "v h w 5"]) -> list[Segmentation]:
    """Skin, shirt and the shirt's spread edges of each view from the most probable class
    (module docstring, step 2)."""
    label = np.argmax(probs, -1)
    out = []
    for v in range(len(frame_pair)):
        fg = label[v] == 1
        seg = segment_cv(segment, np.asarray(frame_pair[v]), foreground=fg)
        out.append(Segmentation(label[v] >= 2, fg, seg.edges))
    return out


def _candidates(mask: np.ndarray, weight: np.ndarray, names: np.ndarray):
    """The <= :data:`CANDIDATES` components of ``mask`` of most probability mass (``weight``
    summed over the component): their weighted centroids (k, 2), masses (k,) and the sums of
    each plane of ``names`` (h, w, e) over them (k, e)."""
    n, lab, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    e = names.shape[-1]
    if n <= 1:
        return np.zeros((0, 2)), np.zeros(0), np.zeros((0, e))
    flat, w = lab.ravel(), weight.astype(np.float64).ravel()
    mass = np.bincount(flat, weights=w, minlength=n)
    ys, xs = np.indices(lab.shape)
    cu = np.bincount(flat, weights=w * xs.ravel(), minlength=n)
    cv = np.bincount(flat, weights=w * ys.ravel(), minlength=n)
    by = np.stack([np.bincount(flat, weights=names[..., i].astype(np.float64).ravel(),
                               minlength=n) for i in range(e)], -1)
    keep = [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] >= MIN_AREA_PX and mass[i] > 0]
    keep = sorted(keep, key=lambda i: -mass[i])[:CANDIDATES]
    uv = np.array([[cu[i] / mass[i], cv[i] / mass[i]] for i in keep]).reshape(-1, 2)
    return uv, mass[keep], by[keep]


def _pairs(cams: Camera, left, right, count: int):
    """Up to ``count`` disjoint (left, right) candidate pairs passing the epipolar and
    in-front tests, most mass first: a list of (point (3,), i, j)."""
    (ul, ml, _), (ur, mr, _) = left, right
    if len(ul) == 0 or len(ur) == 0:
        return []
    m = CANDIDATES
    a, b = np.zeros((m, 2)), np.zeros((m, 2))
    a[:len(ul)], b[:len(ur)] = ul, ur
    epi, X, dep, _ = bloblib._frame_geometry(cams, a, b, np.zeros((3, 3)), False)
    epi, X, dep = epi[:len(ul), :len(ur)], X[:len(ul), :len(ur)], dep[:, :len(ul), :len(ur)]
    ok = (epi <= MAX_EPIPOLAR_PX) & np.all(dep > 0, 0) & np.all(np.isfinite(X), -1)
    score = np.where(ok, np.minimum(ml[:, None], mr[None, :]), -1.0)
    out = []
    while len(out) < count and score.max() > 0:
        i, j = np.unravel_index(np.argmax(score), score.shape)
        out.append((X[i, j], int(i), int(j)))
        score[i, :], score[:, j] = -1.0, -1.0
    return out


def part_points(cams: Camera, probs: Float[np.ndarray, "2 h w 5"],
                reach: tuple[float, float] | None = None
                ) -> tuple[Float[np.ndarray, "3 3"], Bool[np.ndarray, " 3"]]:
    """The head's, the left and the right hand's triangulated points (3, 3) and which were
    found (module docstring, step 3), in the blob line's order
    (:data:`jaxmocap.blobs.HEAD`, ``LEFT_HAND``, ``RIGHT_HAND``)."""
    label = np.argmax(probs, -1)
    points, valid = np.zeros((3, 3)), np.zeros(3, bool)
    head = [_candidates(label[v] == 2, probs[v, ..., 2], probs[v, ..., 2:3]) for v in range(2)]
    found = _pairs(cams, *head, 1)
    if found:
        points[0], valid[0] = found[0][0], True
    # the hands: skin of either hand, up to two pairs; each named by the model's left / right
    # probability over both views' components, the two never the same hand
    hands = [_candidates((label[v] == 3) | (label[v] == 4), probs[v, ..., 3] + probs[v, ..., 4],
                         probs[v, ..., 3:5]) for v in range(2)]
    found = _pairs(cams, *hands, 2)
    left = [float((hands[0][2][i, 0] + hands[1][2][j, 0])
                  / max(hands[0][2][i].sum() + hands[1][2][j].sum(), 1e-12))
            for _, i, j in found]
    if len(found) == 2:
        order = (0, 1) if left[0] >= left[1] else (1, 0)
        for k, f in zip((1, 2), order, strict=True):
            points[k], valid[k] = found[f][0], True
    elif len(found) == 1:
        k = 1 if left[0] >= 0.5 else 2
        points[k], valid[k] = found[0][0], True
    if reach is not None and valid[bloblib.HEAD]:
        near, far = reach
        d = np.linalg.norm(points[1:] - points[bloblib.HEAD], axis=-1)
        drop = valid[1:] & ((d > far) | (d < near))
        valid[1:] &= ~drop
        points[1:][drop] = 0.0
    return points, valid
