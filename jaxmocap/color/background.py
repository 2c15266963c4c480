"""Background subtraction: OpenCV's MOG2 adaptive Gaussian mixture (the Stauffer-Grimson model
[SG99] that Wang et al. 2011 cite in §4 and §5.2).

A stateful object at the edge (outside jit): feed frames in order, get a boolean foreground
mask ``(H, W)`` for the histogram search and the classifier. Shadows, if detected, count as
background.
"""

from __future__ import annotations

import cv2
import numpy as np

HISTORY = 500  # frames in the mixture's memory (OpenCV default)
VAR_THRESHOLD = 16.0  # squared Mahalanobis distance to call a pixel background (OpenCV default)


class BackgroundSubtractor:
    """Wraps ``cv2.createBackgroundSubtractorMOG2`` for RGB uint8 frames.

    ``learning_rate`` < 0 lets OpenCV choose (``1 / min(frames seen, history)``); 0 freezes the
    model; 1 re-learns it from the last frame.
    """

    def __init__(
        self,
        history: int = HISTORY,
        var_threshold: float = VAR_THRESHOLD,
        detect_shadows: bool = False,
        learning_rate: float = -1.0,
    ):
        if history < 1:
            raise ValueError(f"BackgroundSubtractor: history must be >= 1, got {history}")
        if var_threshold <= 0:
            raise ValueError(
                f"BackgroundSubtractor: var_threshold must be > 0, got {var_threshold}"
            )
        self.learning_rate = float(learning_rate)
        self._mog = cv2.createBackgroundSubtractorMOG2(
            history=int(history),
            varThreshold=float(var_threshold),
            detectShadows=bool(detect_shadows),
        )

    def apply(self, image: np.ndarray, learning_rate: float | None = None) -> np.ndarray:
        """Update the model with an RGB uint8 ``(H, W, 3)`` frame; return its foreground mask."""
        image = np.asarray(image)
        if image.dtype != np.uint8 or image.ndim != 3 or image.shape[-1] != 3:
            raise ValueError(
                f"BackgroundSubtractor.apply: expected an RGB uint8 (H, W, 3) frame, got "
                f"{image.dtype} {image.shape}"
            )
        rate = self.learning_rate if learning_rate is None else float(learning_rate)
        bgr = np.ascontiguousarray(image[..., ::-1])
        fg = self._mog.apply(bgr, learningRate=rate)
        return fg == 255  # 127 = shadow, treated as background
