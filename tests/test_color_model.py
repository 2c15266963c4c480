"""Colour model (Wang §5.1): fitting from scribbles recovers the generating Gaussians;
colors.json round trip, atomic write and one clear error per bad field."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap.color import (
    ColorModel,
    ColorModelError,
    fit_color_model,
    load_color_model,
    save_color_model,
)
from jaxmocap.color.model import MIN_VARIANCE


def test_fit_recovers_generating_gaussians(rng):
    k, n = 3, 6000
    mean = np.array([[200.0, 40.0, 30.0], [40.0, 160.0, 60.0], [50.0, 60.0, 190.0]])
    a = rng.normal(size=(k, 3, 3)) * 6
    cov = a @ np.swapaxes(a, 1, 2) + 9 * np.eye(3)
    # two "images" of scribbles: float pixels drawn from the Gaussians, labels 1..k, 0 = none
    images, labels = [], []
    for _ in range(2):
        lab = rng.integers(0, k + 1, (60, n // 60))
        img = np.zeros((*lab.shape, 3))
        for c in range(k):
            sel = lab == c + 1
            img[sel] = rng.multivariate_normal(mean[c], cov[c], sel.sum())
        images.append(img)
        labels.append(lab)
    model = fit_color_model(images, labels, k, names=("red", "green", "blue"))
    assert model.names == ("red", "green", "blue") and model.n_colors == 3
    for c in range(k):
        m = sum((lab == c + 1).sum() for lab in labels)
        se = np.sqrt(np.diag(cov[c]) / m)
        assert np.all(np.abs(np.asarray(model.mean[c]) - mean[c]) < 4 * se)
        fitted = np.asarray(model.cov[c]) - MIN_VARIANCE * np.eye(3)
        # sampling error of a covariance entry ~ sqrt((S_ii S_jj + S_ij^2) / m)
        tol = 4 * np.sqrt((np.outer(np.diag(cov[c]), np.diag(cov[c])) + cov[c] ** 2) / m)
        assert np.all(np.abs(fitted - cov[c]) < tol)


def test_fit_errors():
    img = np.zeros((4, 4, 3))
    with pytest.raises(ColorModelError, match="colour 2 has 0 labelled pixels"):
        fit_color_model([img], [np.ones((4, 4), int)], 2)
    with pytest.raises(ColorModelError, match="labels of image 0 must be in"):
        fit_color_model([img], [np.full((4, 4), 3)], 2)
    with pytest.raises(ColorModelError, match="as many label masks"):
        fit_color_model([img], [], 2)


def _model():
    mean = jnp.asarray([[200.0, 30.0, 31.0], [10.0, 150.5, 70.25]])
    cov = jnp.asarray([[[40.0, 1.0, 0.0], [1.0, 35.0, 0.5], [0.0, 0.5, 38.0]], 25 * np.eye(3)])
    return ColorModel(mean=mean, cov=cov, names=("red", "green"))


def test_json_round_trip(tmp_path):
    path = save_color_model(tmp_path / "colors.json", _model())
    back = load_color_model(path)
    np.testing.assert_array_equal(back.mean, _model().mean)
    np.testing.assert_array_equal(back.cov, _model().cov)
    assert back.names == ("red", "green")
    data = json.loads(path.read_text())
    assert data["format"] == "jaxmocap.colors" and data["version"] == 1
    assert [p.name for p in tmp_path.iterdir()] == ["colors.json"]  # no temp file left


def test_save_invalid_model_writes_nothing(tmp_path):
    bad = ColorModel(mean=_model().mean, cov=_model().cov.at[1, 0, 0].set(-1.0))
    with pytest.raises(ColorModelError, match=r"colors\[1\]\.cov: expected positive definite"):
        save_color_model(tmp_path / "colors.json", bad)
    assert list(tmp_path.iterdir()) == []


def _edit(data, where, value):
    obj = data
    for key in where[:-1]:
        obj = obj[key]
    if value is KeyError:
        del obj[where[-1]]
    else:
        obj[where[-1]] = value


BAD = [
    (("format",), "other", "format: expected 'jaxmocap.colors'"),
    (("version",), 2, "version: expected 1"),
    (("space",), "hsv", "space: expected 'rgb255'"),
    (("colors",), [], "colors: expected a non-empty list"),
    (("colors", 1), 5, r"colors\[1\]: expected an object"),
    (("colors", 0, "mean"), KeyError, r"colors\[0\]\.mean: missing"),
    (("colors", 1, "cov"), KeyError, r"colors\[1\]\.cov: missing"),
    (("colors", 0, "mean"), [1.0, 2.0], r"colors\[0\]\.mean: expected shape \(3,\)"),
    (("colors", 1, "mean"), [1.0, float("nan"), 2.0], r"colors\[1\]\.mean: expected finite"),
    (("colors", 0, "mean"), ["a", 1, 2], r"colors\[0\]\.mean: expected numbers"),
    (("colors", 1, "cov"), [[1, 0], [0, 1]], r"colors\[1\]\.cov: expected shape \(3, 3\)"),
    (("colors", 0, "cov"), [[1, 0.5, 0], [0, 1, 0], [0, 0, 1]], r"\[0\]\.cov: expected a sym"),
    (("colors", 1, "cov"), [[1, 2, 0], [2, 1, 0], [0, 0, 1]], r"colors\[1\]\.cov: expected pos"),
    (("colors", 0, "cov"), [[1, 0, 0], [0, float("inf"), 0], [0, 0, 1]], r"\.cov: expected finite"),
    (("colors", 0, "name"), 7, r"colors\[0\]\.name: expected a string"),
]


@pytest.mark.parametrize(("where", "value", "message"), BAD)
def test_json_bad_fields(tmp_path, where, value, message):
    path = save_color_model(tmp_path / "colors.json", _model())
    data = json.loads(path.read_text())
    _edit(data, where, value)
    path.write_text(json.dumps(data))
    with pytest.raises(ColorModelError, match=message) as info:
        load_color_model(path)
    msg = str(info.value)
    assert msg.startswith(str(path)) and "\n" not in msg


def test_json_unreadable(tmp_path):
    (tmp_path / "colors.json").write_text("{not json")
    with pytest.raises(ColorModelError, match="not valid JSON"):
        load_color_model(tmp_path / "colors.json")
    with pytest.raises(ColorModelError, match="cannot read"):
        load_color_model(tmp_path / "missing.json")
