"""Gaussians of the scene's own colours ("background scribbles"; not in the paper).

Wang et al. suppress background pixels with background subtraction (§4, §5.2). Under spot
lamps and in a dim room, the shirt's pale colours (pink, light grey under a cool lamp) lie
within a few standard deviations of grey walls and floors, and step 1 then labels most of the
crop as shirt: on the test world's dev sequences 1.4-4x the shirt's own pixel count of wall
inside its bounding box (docs/results/shirt.md, "Footage of another renderer"). The user scribbles
the room as well as the shirt; the room's colours (white-balanced by the frame's ``W``, so that
they follow the same illumination changes as the shirt) are clustered into ``n_clusters``
Gaussians (k-means, OpenCV), and a pixel nearer one of them than every shirt colour is background
(:func:`jaxmocap.color.classify` ``background=``).
"""

from __future__ import annotations

from collections.abc import Sequence

import jax.numpy as jnp
import numpy as np

from .model import ColorModel, ColorModelError

N_CLUSTERS = 16  # Gaussians of the room's colours
MAX_PIXELS = 60_000  # pixels clustered (a regular subsample of the labelled ones)
MIN_VARIANCE = 4.0  # variance floor (0..255 units^2): flat walls are nearly one value


def fit_scene_colors(
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray],
    W: Sequence[np.ndarray],
    n_clusters: int = N_CLUSTERS,
    max_pixels: int = MAX_PIXELS,
    min_variance: float = MIN_VARIANCE,
    seed: int = 0,
) -> ColorModel:
    """``n_clusters`` Gaussians of the pixels ``masks[i]`` (True: scene, not shirt) of
    ``images[i]`` after its white balance ``W[i]`` (the model's space); k-means++ then each
    cluster's ML covariance plus ``min_variance``. Deterministic for a ``seed``."""
    import cv2

    if not (len(images) == len(masks) == len(W)) or len(images) == 0:
        raise ColorModelError(f"fit_scene_colors: need as many masks and W as images (>= 1), "
                              f"got {len(images)}, {len(masks)}, {len(W)}")
    pix = []
    for img, m, w in zip(images, masks, W, strict=True):
        img, m = np.asarray(img, np.float64), np.asarray(m, bool)
        if img.ndim != 3 or m.shape != img.shape[:2]:
            raise ColorModelError(f"fit_scene_colors: image {img.shape} and mask {m.shape} must "
                                  "be (H, W, 3) and (H, W)")
        pix.append(img[m] @ np.asarray(w, np.float64).T)
    x = np.concatenate(pix)
    if len(x) < 10 * n_clusters:
        raise ColorModelError(f"fit_scene_colors: {len(x)} scene pixels for {n_clusters} "
                              f"clusters, need >= {10 * n_clusters}")
    x = x[:: max(1, len(x) // max_pixels)].astype(np.float32)
    cv2.setRNGSeed(int(seed))
    crit = (cv2.TERM_CRITERIA_MAX_ITER + cv2.TERM_CRITERIA_EPS, 50, 0.1)
    _, lab, _ = cv2.kmeans(x, int(n_clusters), None, crit, 2, cv2.KMEANS_PP_CENTERS)
    lab = lab.ravel()
    means, covs = [], []
    for j in range(n_clusters):
        y = x[lab == j].astype(np.float64)
        if len(y) < 4:  # an empty cluster (duplicated pixels): nothing to add
            continue
        mu = y.mean(axis=0)
        means.append(mu)
        covs.append((y - mu).T @ (y - mu) / len(y) + min_variance * np.eye(3))
    return ColorModel(mean=jnp.asarray(np.stack(means)), cov=jnp.asarray(np.stack(covs)),
                      names=tuple(f"scene{j}" for j in range(len(means))))


__all__ = ["MAX_PIXELS", "MIN_VARIANCE", "N_CLUSTERS", "fit_scene_colors"]
