"""``white_balance.json``: the initial white balance ``W0`` per camera (Wang §5.1) and,
optionally, the room's colours, as written by ``jaxmocap colors --white-balance``::

    {"format": "jaxmocap.white_balance", "version": 1,
     "cameras": {"cam0": [[w00, w01, w02], [w10, ...], [...]], "cam1": ...},
     "room": [{"name", "mean", "cov"}, ...]}          # with --room-label only

``W`` maps a camera's RGB (0..255) to the colour model's: ``W rgb_observed ~ mu_k``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from jaxmocap.color import ColorModel
from jaxmocap.errors import InputError
from jaxmocap.io.atomic import write_text

WB_FORMAT = "jaxmocap.white_balance"
WB_VERSION = 1
MAX_GAIN = 10.0  # per-channel gain bound of a usable W (a 10x darker channel is already noise)
MAX_MIXING = 1.0  # off-diagonal Frobenius norm / diagonal norm bound of a usable W
MAX_CONDITION = 1e6  # a W this ill-conditioned is singular in float32


class WhiteBalanceFileError(InputError):
    """A ``white_balance.json`` that is missing or malformed (file and field named)."""


def white_balance_problem(W: np.ndarray) -> str | None:
    """What makes ``W`` unusable as a white balance, or None. ``W`` maps a camera's colours
    onto the model's (Wang §5.1): it must be invertible (a singular W sends every pixel to one
    line and nothing is classified) and near a diagonal scale — positive per-channel gains in
    [1/MAX_GAIN, MAX_GAIN] and off-diagonal mixing at most MAX_MIXING of the diagonal (a light
    changes each channel's gain; strong mixing means wrong labels or a wrong file)."""
    W = np.asarray(W, np.float64)
    d = np.diag(W)
    if not np.all(np.isfinite(W)) or not np.any(W) or np.linalg.cond(W) > MAX_CONDITION:
        return "expected an invertible 3x3 matrix (this one is singular: nothing would be " \
               "classified)"
    if np.any(d <= 0) or np.any(d < 1 / MAX_GAIN) or np.any(d > MAX_GAIN):
        return (f"expected positive per-channel gains in {1 / MAX_GAIN:g}..{MAX_GAIN:g} on the "
                f"diagonal, got ({', '.join(f'{v:.3g}' for v in d)})")
    mixing = float(np.linalg.norm(W - np.diag(d)) / np.linalg.norm(d))
    if mixing > MAX_MIXING:
        return (f"expected a near-diagonal scale: off-diagonal mixing is {mixing:.2f} of the "
                f"diagonal (at most {MAX_MIXING:g})")
    return None


def save_white_balance(path: str | os.PathLike, W: dict[str, np.ndarray],
                       room: ColorModel | None = None) -> Path:
    """Write ``white_balance.json`` (module docstring) atomically; ``room``: the room's
    Gaussians in the model's space (``--room-label``)."""
    doc = {"format": WB_FORMAT, "version": WB_VERSION,
           "cameras": {n: np.asarray(w, np.float64).tolist() for n, w in W.items()}}
    if room is not None:
        doc["room"] = [{"name": n, "mean": np.asarray(m, np.float64).tolist(),
                        "cov": np.asarray(c, np.float64).tolist()}
                       for n, m, c in zip(room.names, room.mean, room.cov, strict=True)]
    return write_text(path, json.dumps(doc, indent=2) + "\n")


def load_room_colors(path: str | os.PathLike) -> ColorModel | None:
    """The room's Gaussians of ``white_balance.json`` (``--room-label``), or None without."""
    from jaxmocap.io.preflight import read_json

    path = Path(path)
    doc = read_json(path, "a white_balance.json of `jaxmocap colors --white-balance`",
                    WhiteBalanceFileError)
    room = doc.get("room") if isinstance(doc, dict) else None
    if room is None:
        return None
    if not isinstance(room, list) or not room:
        raise WhiteBalanceFileError(f"{path}: field 'room': expected a non-empty list of "
                                    "colours with mean and cov")
    means, covs = [], []
    for j, c in enumerate(room):
        try:
            m = np.asarray(c["mean"], np.float64)
            v = np.asarray(c["cov"], np.float64)
        except (TypeError, KeyError, ValueError):
            m = v = np.zeros(0)
        ok = m.shape == (3,) and v.shape == (3, 3) and np.all(np.isfinite(m)) and \
            np.all(np.isfinite(v)) and np.allclose(v, v.T, rtol=1e-6, atol=1e-9) and \
            np.all(np.linalg.eigvalsh(0.5 * (v + v.T)) > 0)
        if not ok:
            raise WhiteBalanceFileError(f"{path}: field 'room[{j}]': expected a finite mean of "
                                        "3 numbers and a symmetric positive-definite 3x3 cov")
        means.append(m)
        covs.append(0.5 * (v + v.T))
    import jax.numpy as jnp

    return ColorModel(mean=jnp.asarray(np.stack(means)), cov=jnp.asarray(np.stack(covs)),
                      names=tuple(f"room{j}" for j in range(len(means))))


def load_white_balance(path: str | os.PathLike, names: list[str]) -> np.ndarray:
    """The (n_cams, 3, 3) W0 of the cameras ``names`` from ``white_balance.json``."""
    from jaxmocap.io.preflight import read_json

    path = Path(path)
    doc = read_json(path, "a white_balance.json of `jaxmocap colors --white-balance`",
                    WhiteBalanceFileError)
    if not isinstance(doc, dict) or doc.get("format") != WB_FORMAT:
        raise WhiteBalanceFileError(f"{path}: field 'format': expected {WB_FORMAT!r}")
    if doc.get("version") != WB_VERSION:
        raise WhiteBalanceFileError(f"{path}: field 'version': expected {WB_VERSION}, got "
                                    f"{doc.get('version')!r}")
    cams = doc.get("cameras")
    if not isinstance(cams, dict):
        raise WhiteBalanceFileError(f"{path}: field 'cameras': expected an object name -> 3x3")
    out = []
    for n in names:
        if n not in cams:
            raise WhiteBalanceFileError(f"{path}: field 'cameras': no entry for camera {n!r} "
                                        f"(has {sorted(cams)})")
        try:
            w = np.asarray(cams[n], np.float64)
        except (TypeError, ValueError):
            w = np.zeros(0)
        if w.shape != (3, 3) or not np.all(np.isfinite(w)):
            raise WhiteBalanceFileError(f"{path}: field 'cameras.{n}': expected a finite 3x3 "
                                        "matrix")
        problem = white_balance_problem(w)
        if problem:
            raise WhiteBalanceFileError(f"{path}: field 'cameras.{n}': {problem}")
        out.append(w)
    return np.stack(out)
