"""The overlay drawn over tracked frames: the body's skeleton projected by a camera (OpenCV)."""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np

from jaxmocap.camera import Camera

# Skeleton drawn on the overlay: pairs of keypoint names of the body model.
BONES = (("pelvis", "chest"), ("chest", "neck"), ("neck", "head"),
         ("neck", "l_shoulder"), ("l_shoulder", "l_elbow"), ("l_elbow", "l_wrist"),
         ("l_wrist", "l_hand"), ("neck", "r_shoulder"), ("r_shoulder", "r_elbow"),
         ("r_elbow", "r_wrist"), ("r_wrist", "r_hand"))  # fmt: skip
OVERLAY_ALPHA = 0.5  # weight of the classified colours over the frame



def _project_np(cam: Camera, X: np.ndarray) -> np.ndarray:
    R = np.asarray(cam.R, np.float64)
    uv, _ = cv2.projectPoints(np.asarray(X, np.float64), cv2.Rodrigues(R)[0],
                              np.asarray(cam.t, np.float64), np.asarray(cam.K, np.float64),
                              np.asarray(cam.dist, np.float64))
    return uv.reshape(-1, 2)


def draw_skeleton(image: np.ndarray, cam: Camera, keypoints: np.ndarray,
                  names: Sequence[str]) -> np.ndarray:
    """Draw the bones (:data:`BONES`) of world keypoints (n, 3) projected by ``cam`` on a
    copy of ``image`` (RGB uint8). Points behind the camera are skipped."""
    out = np.ascontiguousarray(image.copy())
    if not np.all(np.isfinite(keypoints)):
        return out
    depth = keypoints @ np.asarray(cam.R, np.float64)[2] + float(cam.t[2])
    uv = _project_np(cam, keypoints)
    idx = {n: i for i, n in enumerate(names)}
    for a, b in BONES:
        if a in idx and b in idx and depth[idx[a]] > 0 and depth[idx[b]] > 0:
            pa, pb = (tuple(int(round(v)) for v in uv[idx[k]]) for k in (a, b))
            cv2.line(out, pa, pb, (255, 255, 255), 2, cv2.LINE_AA)
            cv2.line(out, pa, pb, (20, 20, 20), 1, cv2.LINE_AA)
    for i in range(len(names)):
        if depth[i] > 0:
            cv2.circle(out, tuple(int(round(v)) for v in uv[i]), 2, (255, 220, 0), -1)
    return out
