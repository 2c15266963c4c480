"""The shirt's colour model: one Gaussian N(mu_k, Sigma_k) in RGB per colour (Wang et al. §5.1).

Colours are in **RGB units of 0..255** (the scale of uint8 images). The model is fitted from
labelled pixels ("scribbles"): a list of images with label masks, label 0 = unlabelled and
``1..k`` = colour ids, and saved as ``colors.json``:

.. code-block:: json

    {
      "format": "jaxmocap.colors",
      "version": 1,
      "space": "rgb255",
      "colors": [
        {"name": "red", "mean": [200.0, 30.0, 31.0],
         "cov": [[40.0, 1.0, 0.0], [1.0, 35.0, 0.5], [0.0, 0.5, 38.0]]},
        ...
      ]
    }

``colors[i]`` is colour id ``i + 1``; ``mean`` has 3 finite numbers, ``cov`` is a finite,
symmetric (to 1e-6 relative) positive-definite 3 x 3 matrix. An optional top-level
``"shading": [lo, hi]`` says the model was fitted for the shading-invariant colour distance
(``fit_color_model(gain=(lo, hi))``; :mod:`jaxmocap.color.classify`), the range its user
(``jaxmocap track``) classifies with. Loading validates every field and
raises :class:`ColorModelError` with a one-line message naming the file, colour and field.
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxmocap.errors import InputError

FORMAT = "jaxmocap.colors"
VERSION = 1
# Not in the paper: a variance floor (0..255 units^2) keeping fitted covariances positive
# definite when a colour is saturated or quantised to a single value in a channel.
MIN_VARIANCE = 1.0
GAIN_FIT_ROUNDS = 3  # brightness normalisation <-> Gaussian fit alternations (``gain=``)


class ColorModelError(InputError):
    """A colour model (``colors.json`` or a fit) that is malformed or not usable."""


class ColorModel(eqx.Module):
    """k Gaussian colours in RGB (0..255 units): ``mean[k - 1]``, ``cov[k - 1]`` = colour id k."""

    mean: Float[Array, "k 3"]
    cov: Float[Array, "k 3 3"]
    names: tuple[str, ...] = eqx.field(static=True, default=())
    # (lo, hi) when fitted for the shading-invariant distance (``fit_color_model(gain=)``)
    shading: tuple[float, float] | None = eqx.field(static=True, default=None)

    def __check_init__(self):
        k = self.mean.shape[0]
        if self.mean.shape != (k, 3) or self.cov.shape != (k, 3, 3):
            raise ValueError(
                f"ColorModel: expected mean (k, 3) and cov (k, 3, 3), got {self.mean.shape} "
                f"and {self.cov.shape}"
            )
        if self.names and len(self.names) != k:
            raise ValueError(f"ColorModel: {len(self.names)} names for {k} colours")
        if self.shading is not None and shading_problem(self.shading) is not None:
            raise ValueError(f"ColorModel: shading {shading_problem(self.shading)}")

    @property
    def n_colors(self) -> int:
        return self.mean.shape[0]


def fit_color_model(
    images: Sequence[np.ndarray],
    labels: Sequence[np.ndarray],
    n_colors: int,
    names: Sequence[str] = (),
    min_variance: float = MIN_VARIANCE,
    gain: tuple[float, float] | None = None,
) -> ColorModel:
    """Maximum-likelihood Gaussians of the labelled pixels (Wang §5.1; NumPy, at the edge).

    With ``gain = (lo, hi)`` (the shading-invariant classification of
    :mod:`jaxmocap.color.classify`; not in the paper) every pixel is first brought to its
    colour's brightness, ``x -> a x`` with ``a = argmin ||a x - mu||_Sigma`` clipped to
    ``[lo, hi]``, alternating with the fit (:data:`GAIN_FIT_ROUNDS` rounds), so that the
    covariance holds the chromatic spread only and not the shading's.

    ``images[i]`` is (H, W, 3) RGB (uint8 or float in 0..255), ``labels[i]`` (H, W) ints with
    0 = unlabelled and ``1..n_colors`` the colour ids. Each colour needs at least 4 pixels. The
    covariance is the ML estimate plus ``min_variance * I``. Returns float64 NumPy-backed arrays
    converted to JAX (float32 unless x64 is enabled).
    """
    if len(images) != len(labels) or len(images) == 0:
        raise ColorModelError(
            f"fit_color_model: need as many label masks as images (>= 1), got {len(images)} "
            f"images and {len(labels)} label masks"
        )
    pix = [[] for _ in range(n_colors)]
    for i, (img, lab) in enumerate(zip(images, labels, strict=True)):
        img, lab = np.asarray(img), np.asarray(lab)
        if img.ndim != 3 or img.shape[-1] != 3 or lab.shape != img.shape[:2]:
            raise ColorModelError(
                f"fit_color_model: image {i} must be (H, W, 3) with labels (H, W), got "
                f"{img.shape} and {lab.shape}"
            )
        if lab.min() < 0 or lab.max() > n_colors:
            raise ColorModelError(
                f"fit_color_model: labels of image {i} must be in [0, {n_colors}], got "
                f"[{lab.min()}, {lab.max()}]"
            )
        for k in range(n_colors):
            pix[k].append(img[lab == k + 1].astype(np.float64))
    means, covs = [], []
    for k in range(n_colors):
        x = np.concatenate(pix[k])
        if len(x) < 4:
            raise ColorModelError(
                f"fit_color_model: colour {k + 1} has {len(x)} labelled pixels, need >= 4"
            )
        mu = x.mean(axis=0)
        cov = (x - mu).T @ (x - mu) / len(x) + min_variance * np.eye(3)
        for _ in range(GAIN_FIT_ROUNDS if gain is not None else 0):
            P = np.linalg.inv(cov)
            a = np.clip((x @ P @ mu) / np.maximum(np.einsum("ni,ij,nj->n", x, P, x), 1e-12),
                        gain[0], gain[1])
            y = a[:, None] * x
            mu = y.mean(axis=0)
            cov = (y - mu).T @ (y - mu) / len(y) + min_variance * np.eye(3)
        means.append(mu)
        covs.append(cov)
    return ColorModel(
        mean=jnp.asarray(np.stack(means)), cov=jnp.asarray(np.stack(covs)), names=tuple(names),
        shading=None if gain is None else (float(gain[0]), float(gain[1])),
    )


def shading_problem(shading) -> str | None:
    """What makes ``shading`` unusable as a brightness range (lo, hi), or None."""
    try:
        lo, hi = (float(g) for g in shading)
    except (TypeError, ValueError):
        return f"expected two numbers (lo, hi), got {shading!r}"
    if not (np.isfinite(lo) and np.isfinite(hi) and 0 < lo <= 1 <= hi):
        return f"expected (lo, hi) with 0 < lo <= 1 <= hi, got ({lo:g}, {hi:g})"
    return None


def _fail(path, where: str, msg: str) -> ColorModelError:
    return ColorModelError(f"{path}: {where}: {msg}")


def _matrix(path, where: str, value, shape: tuple[int, ...]) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise _fail(path, where, f"expected numbers of shape {shape}, got {value!r}") from None
    if arr.shape != shape:
        raise _fail(path, where, f"expected shape {shape}, got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise _fail(path, where, "expected finite numbers, got NaN/inf")
    return arr


def _check_mean(path, where: str, mean: np.ndarray) -> np.ndarray:
    """A colour mean lies in the image range: outside it the white balance fit (which maps
    observed colours onto the means) gets negative or huge gains."""
    if np.any(mean < 0) or np.any(mean > 255):
        raise _fail(path, where, f"expected RGB values in 0..255, got "
                    f"({', '.join(f'{v:g}' for v in mean)})")
    return mean


def _check_cov(path, where: str, cov: np.ndarray) -> None:
    scale = max(float(np.abs(cov).max()), 1e-300)
    if np.abs(cov - cov.T).max() > 1e-6 * scale:
        raise _fail(path, where, "expected a symmetric 3x3 matrix")
    lo = float(np.linalg.eigvalsh(cov).min())
    if lo <= 0:
        raise _fail(path, where, f"expected positive definite, min eigenvalue is {lo:.3g}")


def validate_color_model(model: ColorModel, source: str = "ColorModel") -> None:
    """Raise :class:`ColorModelError` unless means are finite RGB (0..255) and covariances
    SPD."""
    mean, cov = np.asarray(model.mean), np.asarray(model.cov)
    for k in range(mean.shape[0]):
        _check_mean(source, f"colors[{k}].mean", _matrix(source, f"colors[{k}].mean", mean[k],
                                                        (3,)))
        _check_cov(source, f"colors[{k}].cov", _matrix(source, f"colors[{k}].cov", cov[k], (3, 3)))


def load_color_model(path: str | os.PathLike) -> ColorModel:
    """Read and validate ``colors.json`` (schema in the module docstring)."""
    path = Path(path)
    from jaxmocap.io.preflight import read_json

    data = read_json(path, "a colors.json of `jaxmocap colors`", ColorModelError)
    if not isinstance(data, dict):
        raise _fail(path, "top level", "expected a JSON object")
    if data.get("format") != FORMAT:
        raise _fail(path, "format", f"expected {FORMAT!r}, got {data.get('format')!r}")
    if data.get("version") != VERSION:
        raise _fail(path, "version", f"expected {VERSION}, got {data.get('version')!r}")
    if data.get("space", "rgb255") != "rgb255":
        raise _fail(path, "space", f"expected 'rgb255', got {data.get('space')!r}")
    colors = data.get("colors")
    if not isinstance(colors, list) or len(colors) == 0:
        raise _fail(path, "colors", "expected a non-empty list of colours")
    means, covs, names = [], [], []
    for k, c in enumerate(colors):
        if not isinstance(c, dict):
            raise _fail(path, f"colors[{k}]", "expected an object with mean and cov")
        for key in ("mean", "cov"):
            if key not in c:
                raise _fail(path, f"colors[{k}].{key}", "missing")
        means.append(_check_mean(path, f"colors[{k}].mean",
                                 _matrix(path, f"colors[{k}].mean", c["mean"], (3,))))
        cov = _matrix(path, f"colors[{k}].cov", c["cov"], (3, 3))
        _check_cov(path, f"colors[{k}].cov", cov)
        covs.append(0.5 * (cov + cov.T))
        name = c.get("name", f"color{k + 1}")
        if not isinstance(name, str):
            raise _fail(path, f"colors[{k}].name", f"expected a string, got {name!r}")
        names.append(name)
    shading = data.get("shading")
    if shading is not None:
        problem = shading_problem(shading)
        if problem:
            raise _fail(path, "shading", problem)
        shading = (float(shading[0]), float(shading[1]))
    return ColorModel(
        mean=jnp.asarray(np.stack(means)), cov=jnp.asarray(np.stack(covs)), names=tuple(names),
        shading=shading,
    )


def save_color_model(path: str | os.PathLike, model: ColorModel) -> Path:
    """Validate and write ``colors.json`` atomically (temporary file + ``os.replace``)."""
    path = Path(path)
    validate_color_model(model, str(path))
    mean, cov = np.asarray(model.mean, np.float64), np.asarray(model.cov, np.float64)
    names = model.names or tuple(f"color{k + 1}" for k in range(mean.shape[0]))
    data = {
        "format": FORMAT,
        "version": VERSION,
        "space": "rgb255",
        "colors": [
            {"name": n, "mean": mean[k].tolist(), "cov": cov[k].tolist()}
            for k, n in enumerate(names)
        ],
    }
    if model.shading is not None:
        data["shading"] = list(model.shading)
    from jaxmocap.io.atomic import write_text  # one atomic-write mechanism for the package

    write_text(path, json.dumps(data, indent=2) + "\n")
    return path


def log_cholesky(cov: Float[Array, "*batch 3 3"]) -> Float[Array, "*batch 6"]:
    """Unconstrained parameters of an SPD matrix: ``log diag(L)`` (3) and ``L``'s lower part (3).

    ``cov = L L^T``; the inverse is :func:`cov_from_log_cholesky`. Optimising these six numbers
    keeps ``Sigma`` symmetric positive definite (as dynamax declares constrained parameters).
    """
    chol = jnp.linalg.cholesky(cov)
    diag = jnp.log(jnp.diagonal(chol, axis1=-2, axis2=-1))
    lower = jnp.stack([chol[..., 1, 0], chol[..., 2, 0], chol[..., 2, 1]], axis=-1)
    return jnp.concatenate([diag, lower], axis=-1)


def cov_from_log_cholesky(params: Float[Array, "*batch 6"]) -> Float[Array, "*batch 3 3"]:
    """``Sigma = L L^T`` with ``L = [[e^a, 0, 0], [l10, e^b, 0], [l20, l21, e^c]]``."""
    d = jnp.exp(params[..., :3])
    z = jnp.zeros_like(d[..., 0])
    chol = jnp.stack(
        [
            jnp.stack([d[..., 0], z, z], axis=-1),
            jnp.stack([params[..., 3], d[..., 1], z], axis=-1),
            jnp.stack([params[..., 4], params[..., 5], d[..., 2]], axis=-1),
        ],
        axis=-2,
    )
    return chol @ jnp.swapaxes(chol, -1, -2)


__all__ = [
    "ColorModel",
    "ColorModelError",
    "fit_color_model",
    "load_color_model",
    "save_color_model",
    "shading_problem",
    "validate_color_model",
    "log_cholesky",
    "cov_from_log_cholesky",
]
