"""Exports of a tracked pose sequence: BVH, TRC (OpenSim markers), CSV and NPZ — and reading
our CSV / NPZ back (for ``jaxmocap eval``).

A tracked sequence is a :class:`PoseTrack`: per frame the pose ``q`` (the body model's layout,
see :mod:`jaxmocap.body`: root translation m, root rotation vector rad, 1-DOF joint angles
rad), the world positions of the model's named keypoints (m, world Z up) and whether the
tracker produced a pose for that frame (``valid``). Frames that were not tracked (an
unreadable frame, a lost subject) are **NaN** in ``q`` and ``keypoints``.

Formats (all written atomically, :mod:`jaxmocap.io.atomic`):

* **NPZ** — arrays ``q`` (T, n_dof), ``keypoints`` (T, n_kp, 3), ``valid`` (T,), ``times``
  (T,) s, ``fps`` (), ``dof_names`` (n_dof,), ``keypoint_names`` (n_kp,) — the same key
  names as a synthetic dataset's ``groundtruth.npz``, so ground truth and results compare
  directly.
* **CSV** — one header row, one row per frame: ``frame, time_s, valid``, then
  ``<keypoint>_x/_y/_z`` (m, world Z up) per keypoint, then one column per DOF (``q_<name>``);
  NaN written as an empty field.
* **TRC** — OpenSim's marker-trajectory text format (tab separated, ``PathFileType 4``),
  one marker per keypoint, in **Y-up** coordinates as OpenSim expects
  (``v_trc = M^T v_world``, ``M = Y_UP_TO_Z_UP``: x forward stays x, our z is TRC's y, our y
  is TRC's -z), units metres; untracked frames have empty fields (OpenSim's missing marker).
* **BVH** — :func:`jaxmocap.io.bvh.body_to_bvh` (Y up, degrees). BVH cannot hold missing
  frames: an untracked frame repeats the last tracked pose (the rest pose before the first).
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxmocap.body import BodyModel
from jaxmocap.body import keypoints as body_keypoints
from jaxmocap.errors import InputError
from jaxmocap.io.atomic import AtomicFiles, atomic_path, write_text
from jaxmocap.io.bvh import body_to_bvh, format_bvh
from jaxmocap.synth._rotations import Y_UP_TO_Z_UP

__all__ = [
    "FORMATS",
    "PoseFileError",
    "PoseTrack",
    "fill_missing",
    "format_csv",
    "format_trc",
    "load_track",
    "pose_track",
    "write_bvh",
    "write_csv",
    "write_exports",
    "write_npz",
    "write_trc",
]

FORMATS = ("bvh", "trc", "csv", "npz")
_M = np.asarray(Y_UP_TO_Z_UP)  # v_world = M v_yup


class PoseFileError(InputError):
    """A pose file (our CSV/NPZ, or a ground truth) that is missing, malformed or inconsistent."""


class PoseTrack(NamedTuple):
    """A tracked sequence (module docstring): NaN rows where ``valid`` is False."""

    q: np.ndarray  # (T, n_dof)
    keypoints: np.ndarray  # (T, n_kp, 3) metres, world Z up
    valid: np.ndarray  # (T,) bool
    fps: float
    dof_names: tuple[str, ...]
    keypoint_names: tuple[str, ...]

    @property
    def n_frames(self) -> int:
        return self.q.shape[0]

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.fps


_keypoints_batch = jax.jit(jax.vmap(body_keypoints, in_axes=(None, 0)))


def pose_track(model: BodyModel, q: np.ndarray, valid: np.ndarray | None, fps: float) -> PoseTrack:
    """A :class:`PoseTrack` of poses ``q`` (T, n_dof): keypoints by forward kinematics; rows
    with ``valid`` False (default: rows with a non-finite entry) become NaN."""
    q = np.array(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != model.n_dof:
        raise ValueError(f"pose_track: q must be (T, {model.n_dof}), got {q.shape}")
    finite = np.isfinite(q).all(axis=1)
    valid = finite if valid is None else np.asarray(valid, bool) & finite
    if not fps > 0:
        raise ValueError(f"pose_track: fps must be > 0, got {fps}")
    q[~valid] = np.nan
    if q.shape[0]:
        filled = np.where(valid[:, None], q, 0.0)
        kp = np.array(_keypoints_batch(model, jnp.asarray(filled)), np.float64)
    else:
        kp = np.zeros((0, len(model.keypoint_names), 3))
    kp[~valid] = np.nan
    return PoseTrack(q, kp, valid, float(fps), tuple(model.chain.dof_names),
                     tuple(model.keypoint_names))


def fill_missing(q: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``q`` with every untracked row replaced by the last tracked one (zeros = rest pose
    before the first): what BVH, which cannot express a missing frame, stores."""
    out = np.zeros_like(q)
    last = np.zeros(q.shape[1])
    for t in range(q.shape[0]):
        if valid[t]:
            last = q[t]
        out[t] = last
    return out


# ----------------------------------------------------------------------------- writers


def _num(x: float) -> str:
    return "" if not np.isfinite(x) else f"{x:.6f}"


def format_csv(track: PoseTrack) -> str:
    """The CSV text (module docstring)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    header = ["frame", "time_s", "valid"]
    header += [f"{n}_{a}" for n in track.keypoint_names for a in "xyz"]
    header += [f"q_{n}" for n in track.dof_names]
    w.writerow(header)
    for t in range(track.n_frames):
        row = [str(t), f"{t / track.fps:.6f}", str(int(track.valid[t]))]
        row += [_num(v) for v in track.keypoints[t].reshape(-1)]
        row += [_num(v) for v in track.q[t]]
        w.writerow(row)
    return buf.getvalue()


def format_trc(track: PoseTrack, file_name: str = "poses.trc") -> str:
    """The TRC text (module docstring): OpenSim ``PathFileType 4``, Y up, metres."""
    n, k = track.n_frames, len(track.keypoint_names)
    rate = f"{track.fps:.6g}"
    lines = [
        f"PathFileType\t4\t(X/Y/Z)\t{file_name}",
        "DataRate\tCameraRate\tNumFrames\tNumMarkers\tUnits\tOrigDataRate\t"
        "OrigDataStartFrame\tOrigNumFrames",
        f"{rate}\t{rate}\t{n}\t{k}\tm\t{rate}\t1\t{n}",
        "\t".join(["Frame#", "Time"] + [f"{m}\t\t" for m in track.keypoint_names]).rstrip("\t"),
        "\t".join(["", ""] + [f"{a}{i + 1}" for i in range(k) for a in "XYZ"]),
        "",
    ]
    yup = track.keypoints @ _M  # rows: v_yup = M^T v_world
    for t in range(n):
        vals = [_num(v) for v in yup[t].reshape(-1)]
        lines.append("\t".join([str(t + 1), f"{t / track.fps:.6f}"] + vals))
    return "\n".join(lines) + "\n"


def write_csv(path: str | os.PathLike, track: PoseTrack) -> Path:
    """Write the CSV atomically."""
    return write_text(path, format_csv(track))


def write_trc(path: str | os.PathLike, track: PoseTrack) -> Path:
    """Write the TRC atomically."""
    return write_text(path, format_trc(track, Path(path).name))


def _save_npz(path: Path, track: PoseTrack, extra: dict[str, np.ndarray]) -> None:
    with open(path, "wb") as f:
        np.savez(f, q=track.q, keypoints=track.keypoints, valid=track.valid,
                 times=track.times, fps=np.float64(track.fps),
                 dof_names=np.array(track.dof_names), keypoint_names=np.array(track.keypoint_names),
                 **extra)


def write_npz(path: str | os.PathLike, track: PoseTrack, **extra: np.ndarray) -> Path:
    """Write the NPZ atomically; ``extra`` arrays are stored beside the standard keys."""
    with atomic_path(path) as tmp:
        _save_npz(tmp, track, extra)
    return Path(path)


def write_bvh(path: str | os.PathLike, model: BodyModel, track: PoseTrack) -> Path:
    """Write the BVH atomically (untracked frames hold the last tracked pose)."""
    return write_text(path, format_bvh(body_to_bvh(model, fill_missing(track.q, track.valid),
                                                   track.fps)))


def write_exports(files: AtomicFiles, folder: str | os.PathLike, model: BodyModel,
                  track: PoseTrack, formats=FORMATS, stem: str = "poses",
                  **npz_extra: np.ndarray) -> list[Path]:
    """Write ``<folder>/<stem>.<fmt>`` for each format into the all-or-nothing group
    ``files`` (committed when its ``with`` block ends); returns the target paths."""
    folder = Path(folder)
    out = []
    for fmt in formats:
        target = folder / f"{stem}.{fmt}"
        tmp = files.path(target)
        if fmt == "npz":
            _save_npz(tmp, track, npz_extra)
        elif fmt == "csv":
            tmp.write_text(format_csv(track))
        elif fmt == "trc":
            tmp.write_text(format_trc(track, target.name))
        elif fmt == "bvh":
            tmp.write_text(format_bvh(body_to_bvh(model, fill_missing(track.q, track.valid),
                                                  track.fps)))
        else:
            raise ValueError(f"write_exports: unknown format {fmt!r}; expected one of {FORMATS}")
        out.append(target)
    return out


# ----------------------------------------------------------------------------- reading


def _load_npz(path: Path) -> PoseTrack:
    from jaxmocap.io.preflight import read_npz

    data = read_npz(path, "a pose .npz (keypoints, keypoint_names)", error=PoseFileError)
    if "keypoints" not in data:
        raise PoseFileError(f"{path}: field 'keypoints' missing (expected (T, n_keypoints, 3))")
    kp = np.asarray(data["keypoints"], np.float64)
    if kp.ndim != 3 or kp.shape[2] != 3:
        raise PoseFileError(f"{path}: field 'keypoints' has shape {kp.shape}, expected "
                            "(T, n_keypoints, 3)")
    t, k = kp.shape[:2]
    if "keypoint_names" not in data or len(data["keypoint_names"]) != k:
        raise PoseFileError(f"{path}: field 'keypoint_names' missing or not {k} names")
    names = tuple(str(n) for n in data["keypoint_names"])
    q = np.asarray(data.get("q", np.full((t, 0), np.nan)), np.float64)
    if q.ndim != 2 or q.shape[0] != t:
        raise PoseFileError(f"{path}: field 'q' has shape {q.shape}, expected ({t}, n_dof)")
    dof_names = tuple(str(n) for n in data.get("dof_names", [f"q{i}" for i in range(q.shape[1])]))
    if len(dof_names) != q.shape[1]:
        raise PoseFileError(f"{path}: field 'dof_names' has {len(dof_names)} names for "
                            f"{q.shape[1]} DOFs")
    fps = float(data["fps"]) if "fps" in data else _fps_from_times(path, data.get("times"), t)
    valid = (np.asarray(data["valid"], bool) if "valid" in data
             else np.isfinite(kp).all(axis=(1, 2)))
    if valid.shape != (t,):
        raise PoseFileError(f"{path}: field 'valid' has shape {valid.shape}, expected ({t},)")
    return PoseTrack(q, kp, valid & np.isfinite(kp).all(axis=(1, 2)), fps, dof_names, names)


def _fps_from_times(path: Path, times, t: int) -> float:
    if times is not None and len(times) >= 2 and np.all(np.isfinite(times)):
        dt = float(np.median(np.diff(np.asarray(times, np.float64))))
        if dt > 0:
            return 1.0 / dt
    if t >= 2:
        raise PoseFileError(f"{path}: neither 'fps' nor increasing 'times' given")
    return 1.0


def _load_csv(path: Path) -> PoseTrack:
    try:
        with open(path, newline="") as f:
            rows = list(csv.reader(f))
    except (OSError, UnicodeDecodeError) as e:
        raise PoseFileError(f"{path}: cannot read CSV ({e})") from None
    if not rows or rows[0][:3] != ["frame", "time_s", "valid"]:
        raise PoseFileError(f"{path}: line 1: expected the header 'frame,time_s,valid,...' "
                            "of a jaxmocap pose CSV")
    header = rows[0]
    kp_cols = [c for c in header[3:] if not c.startswith("q_")]
    if len(kp_cols) % 3 or any(not c.endswith(f"_{'xyz'[i % 3]}") for i, c in enumerate(kp_cols)):
        raise PoseFileError(f"{path}: line 1: keypoint columns must come as <name>_x, _y, _z")
    names = tuple(c[:-2] for c in kp_cols[::3])
    dof_names = tuple(c[2:] for c in header[3 + len(kp_cols):])
    values = np.full((len(rows) - 1, len(header)), np.nan)
    for i, row in enumerate(rows[1:]):
        if len(row) != len(header):
            raise PoseFileError(f"{path}: line {i + 2}: {len(row)} fields, header has "
                                f"{len(header)}")
        try:
            values[i] = [float(v) if v.strip() else np.nan for v in row]
        except ValueError as e:
            raise PoseFileError(f"{path}: line {i + 2}: not a number ({e})") from None
    t, k = values.shape[0], len(names)
    kp = values[:, 3:3 + 3 * k].reshape(t, k, 3)
    q = values[:, 3 + 3 * k:]
    valid = (values[:, 2] == 1) & np.isfinite(kp).all(axis=(1, 2))
    fps = _fps_from_times(path, values[:, 1], t)
    return PoseTrack(q, kp, valid, fps, dof_names, names)


def load_track(path: str | os.PathLike) -> PoseTrack:
    """Read a pose file written by this module (``.npz`` or ``.csv``), or any ``.npz`` with
    ``keypoints`` + ``keypoint_names`` (e.g. a synthetic dataset's ``groundtruth.npz``).
    Raises :class:`PoseFileError` naming the file and field."""
    path = Path(path)
    if path.is_dir():
        raise PoseFileError(f"{path}: is a folder; expected a pose file (.npz or .csv)")
    if not path.is_file():
        raise PoseFileError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        return _load_npz(path)
    if suffix == ".csv":
        return _load_csv(path)
    raise PoseFileError(f"{path}: unknown pose file type {suffix!r}; expected .npz or .csv")
