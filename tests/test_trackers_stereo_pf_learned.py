"""The stereo filter's image line on the learned parts (:mod:`jaxmocap.trackers.stereo_pf.learned`):
probability maps painted at the OpenCV projections (``cv2.projectPoints``, an independent oracle)
of known 3D head and hand centres give those centres back, named as painted; a part seen in one
view only, or beyond the arms' reach, is missing (never a wrong point); the observation the
filter reads on the learned path is those points, the shirt class its foreground; the model's
planes at the frame size sum to one; refusals in one line."""

from __future__ import annotations

import cv2
import jax
import numpy as np
import pytest

from jaxmocap import blobs
from jaxmocap import camera as C
from jaxmocap.body import default_body
from jaxmocap.errors import InputError
from jaxmocap.garment import default_garment, single_colour_garment
from jaxmocap.observe import Observer, classes_of
from jaxmocap.segment import SegmentParams
from jaxmocap.trackers import stereo_pf as sp
from jaxmocap.trackers.stereo_pf import learned

W, H, FX, BASELINE = 320, 240, 290.0, 0.11
EYE, TARGET = np.array([2.2, 0.0, 1.45]), np.array([0.0, 0.0, 1.3])
CENTRES = np.array([[0.0, 0.0, 1.6], [0.05, 0.3, 1.0], [0.1, -0.25, 1.2]])  # head, L, R (m)
RADII_PX = (9, 5, 5)


def _cams() -> list[C.Camera]:
    off = np.array([0.0, BASELINE / 2, 0.0])
    return [C.look_at(EYE + s * off, TARGET + s * off, width=W, height=H, fx=FX) for s in (-1, 1)]


def _probs(cams, centres, parts=(2, 3, 4), skip=()):
    """(2, H, W, 5) planes: background 1 everywhere but discs of each part at the oracle's
    projection of its centre (``skip``: (view, part) pairs left out); a shirt band below."""
    out = np.zeros((2, H, W, 5), np.float32)
    for v, cam in enumerate(cams):
        R, t, K = (np.asarray(a, np.float64) for a in (cam.R, cam.t, cam.K))
        uv = cv2.projectPoints(centres, cv2.Rodrigues(R)[0], t, K, np.zeros(5))[0][:, 0]
        lab = np.zeros((H, W), np.uint8)
        lab[200:, 100:220] = 1
        for k, part in enumerate(parts):
            if (v, part) not in skip:
                cv2.circle(lab, tuple(int(round(x * 16)) for x in uv[k]), RADII_PX[k] * 16,
                           int(part), -1, cv2.LINE_8, 4)
        out[v] = np.eye(5, dtype=np.float32)[lab]
    return out


def test_points_are_the_painted_centres_named_as_painted():
    cams = _cams()
    pts, valid = learned.part_points(C.stack_cameras(cams), _probs(cams, CENTRES))
    assert valid.all()
    # disparity quantisation of a digitised disc: <= ~0.2 px -> depth <= ~4 cm at 2.2 m
    np.testing.assert_allclose(pts, CENTRES, atol=0.05)
    # names follow the classes: the left hand's plane painted at the right hand's centre
    swapped = _probs(cams, CENTRES[[0, 2, 1]])
    pts2, _ = learned.part_points(C.stack_cameras(cams), swapped)
    np.testing.assert_allclose(pts2[1], CENTRES[2], atol=0.05)


def test_a_part_seen_in_one_view_or_beyond_reach_is_missing():
    cams = _cams()
    stacked = C.stack_cameras(cams)
    pts, valid = learned.part_points(stacked, _probs(cams, CENTRES, skip={(1, 3)}))
    assert valid.tolist() == [True, False, True] and np.all(pts[1] == 0)
    # the right hand 0.6-0.8 m from the head: within (0.3, 1.0), outside (0.3, 0.5)
    d = np.linalg.norm(CENTRES[1:] - CENTRES[0], axis=-1)
    assert np.all((d > 0.3) & (d < 1.0))
    _, valid = learned.part_points(stacked, _probs(cams, CENTRES), reach=(0.3, 1.0))
    assert valid.all()
    _, valid = learned.part_points(stacked, _probs(cams, CENTRES),
                                   reach=(0.3, float(d.min()) - 0.01))
    assert valid.tolist() == [True, False, False]


def test_segmentation_reads_the_most_probable_class():
    cams = _cams()  # Azad's default intervals: only the edges of the shirt are read
    probs = _probs(cams, CENTRES)
    frames = np.zeros((2, H, W, 3), np.uint8)
    seg = learned.segmentation(SegmentParams(), frames, probs)
    label = probs.argmax(-1)
    for v in range(2):
        np.testing.assert_array_equal(seg[v].foreground, label[v] == 1)
        np.testing.assert_array_equal(seg[v].skin, label[v] >= 2)
        assert seg[v].edges.max() == pytest.approx(1.0) and seg[v].edges[0, 0] == 0


@pytest.fixture(scope="module")
def parts():
    body = default_body()
    garment = single_colour_garment(body, (0.1, 0.25, 0.8))
    classes = classes_of(body, garment)
    obs = Observer(classes.n, jax.random.key(0), width=4, context=4)
    return body, learned.learned_parts(obs, classes, C.stack_cameras(_cams()))


def test_the_model_reads_the_frame_at_its_scale_and_its_planes_sum_to_one(parts):
    _, lp = parts
    assert lp.size == (2 * round(W * learned.MODEL_FOCAL_PX / FX / 2),
                       2 * round(H * learned.MODEL_FOCAL_PX / FX / 2))
    rng = np.random.default_rng(0)
    frames = rng.integers(0, 256, (2, H, W, 3), dtype=np.uint8)
    p = learned.part_probabilities(lp, frames)
    assert p.shape == (2, H, W, 5)
    np.testing.assert_allclose(p.sum(-1), 1.0, atol=1e-4)


def test_the_filter_observes_the_learned_points(parts, monkeypatch):
    body, lp = parts
    cams = _cams()
    params = sp.make_params(cams, model=body, images=sp.Images(observer=lp))
    probs = _probs(cams, CENTRES)
    monkeypatch.setattr(learned, "part_probabilities", lambda _lp, _f: probs)
    frames = np.zeros((2, H, W, 3), np.uint8)
    obs, _ = sp.observe(params, frames, blobs.init(sp.BLOB_PARAMS))
    np.testing.assert_allclose(np.asarray(obs.points), CENTRES, atol=0.05)
    assert np.asarray(obs.valid).all()
    np.testing.assert_array_equal(np.asarray(obs.foreground) > 0, probs.argmax(-1) == 1)


def test_refusals(parts):
    body, lp = parts
    with pytest.raises(InputError, match="observer: the learned parts replace"):
        sp.make_params(_cams(), model=body, images=sp.Images(observer=lp, hand_search=True))
    shirt10 = classes_of(body, default_garment(body))  # the colour shirt: 14 classes
    with pytest.raises(ValueError, match="classes"):
        learned.learned_parts(lp.observer, shirt10, C.stack_cameras(_cams()))
