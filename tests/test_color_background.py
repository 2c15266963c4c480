"""Background subtraction: the MOG2 wrapper finds a moving object on a noisy static scene."""

import numpy as np
import pytest

from jaxmocap.color import BackgroundSubtractor


def test_mog2_finds_moving_square(rng):
    bg = rng.integers(40, 200, (60, 80, 3)).astype(np.uint8)
    sub = BackgroundSubtractor(history=50)
    for _ in range(30):  # learn the static background (sensor noise only)
        frame = np.clip(bg + rng.normal(0, 2, bg.shape), 0, 255).astype(np.uint8)
        fg = sub.apply(frame)
    assert fg.dtype == bool and fg.shape == (60, 80) and fg.mean() < 0.02
    ious = []
    for t in range(5):  # a red square moves across
        truth = np.zeros((60, 80), bool)
        truth[20:40, 10 + 8 * t : 30 + 8 * t] = True
        frame = np.clip(bg + rng.normal(0, 2, bg.shape), 0, 255).astype(np.uint8)
        frame[truth] = [230, 20, 20]
        fg = sub.apply(frame)
        ious.append((fg & truth).sum() / (fg | truth).sum())
    assert min(ious) > 0.8


def test_mog2_rejects_bad_input():
    with pytest.raises(ValueError, match="RGB uint8"):
        BackgroundSubtractor().apply(np.zeros((4, 4), np.uint8))
    with pytest.raises(ValueError, match="history must be >= 1"):
        BackgroundSubtractor(history=0)
