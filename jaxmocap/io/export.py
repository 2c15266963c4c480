"""Exports of a tracked pose sequence: BVH, TRC (OpenSim markers), C3D, CSV and NPZ — and
reading our CSV / NPZ back (for ``jaxmocap eval``).

A tracked sequence is a :class:`PoseTrack`: per frame the pose ``q`` the tracker estimated
(the body model's layout, see :mod:`jaxmocap.body`: root translation m, root rotation vector
rad, 1-DOF joint angles rad), the world positions of the model's named keypoints (m, world Z
up), whether the tracker's rule calls that estimate valid (``valid``) and, optionally, the
per-frame ``diagnostics`` behind the flag (the tracker's signals, named by
``diagnostic_names``). **Every frame's estimate is kept, valid or not**: research users
decide what to trust. ``q`` and ``keypoints`` are **NaN** only where there is no estimate (an
unreadable frame, a filter not started yet, a shirt found nowhere); such a frame is never
valid. Readers that score accuracy use ``valid`` explicitly (:mod:`jaxmocap.metrics`).

Formats (all written atomically, :mod:`jaxmocap.io.atomic`); the interchange formats mark
an invalid frame the way their tools expect a missing marker, so that an invalid estimate
is never read as data there (it is in the NPZ / CSV):

* **NPZ** — arrays ``q`` (T, n_dof), ``keypoints`` (T, n_kp, 3), ``valid`` (T,), ``times``
  (T,) s, ``fps`` (), ``dof_names`` (n_dof,), ``dof_units`` (n_dof,: ``m`` or ``rad``),
  ``keypoint_names`` (n_kp,) — the same key names as a synthetic dataset's
  ``groundtruth.npz``, so ground truth and results compare directly — and, when the track
  has them, ``diagnostics`` (T, k) (NaN where a frame has no such value) and
  ``diagnostic_names`` (k,).
* **CSV** — one header row, one row per frame: ``frame, time_s, valid``, then
  ``<keypoint>_x_m/_y_m/_z_m`` (metres, world Z up) per keypoint, then one column per DOF
  named with its unit: ``q_root_tx_m .. q_root_tz_m`` (root translation),
  ``q_root_rotvec_x_rad .. _z_rad`` (root rotation vector, world frame) and
  ``q_<joint>_rad`` (``_m`` for a prismatic joint), then one ``diag_<name>`` column per
  diagnostic; NaN written as an empty field.
* **TRC** — OpenSim's marker-trajectory text format (tab separated, ``PathFileType 4``),
  one marker per keypoint, in **Y-up** coordinates as OpenSim expects
  (``v_trc = M^T v_world``, ``M = Y_UP_TO_Z_UP``: x forward stays x, our z is TRC's y, our y
  is TRC's -z), units metres. TRC has no validity flag: an invalid or untracked frame's
  markers are missing, written ``NaN`` (what OpenSim's own TRC writer writes for a missing
  marker, and what every reader that parses numbers reads; every data line keeps its
  ``2 + 3 * NumMarkers`` fields). Newer OpenSim readers also take blank fields; older ones
  parse every field as a number, so blank fields are not used.
* **C3D** — the binary format of biomechanics labs (written with ezc3d, the library OpenSim's
  C3D reader is built on): one 3D point per keypoint in **millimetres**, world frame (Z up,
  ``POINT:X_SCREEN +X``, ``Y_SCREEN +Z``), ``POINT:RATE`` = the capture's frame rate,
  residual 0 for valid points and -1 (C3D's invalid point) for invalid or untracked frames;
  ezc3d writes an invalid point's coordinates as 0 and reads them back as NaN, the `c3d`
  package returns 0 with residual -1; no analog channels.
* **BVH** — :func:`jaxmocap.io.bvh.body_to_bvh` (Y up, degrees). BVH has no validity flag
  and no missing frames: it holds every frame's estimate, valid or not (an animation of what
  the tracker computed; the flag is beside it in ``diagnostics.csv`` of ``jaxmocap track``
  and in the NPZ / CSV), and a frame without an estimate repeats the last estimate (the rest
  pose before the first).
"""

from __future__ import annotations

import csv
import io
import os
from pathlib import Path
from typing import NamedTuple

import numpy as np

from jaxmocap.body import PRISMATIC, ROOT_DOFS, BodyModel
from jaxmocap.body import keypoints as body_keypoints
from jaxmocap.body.chain import over_frames
from jaxmocap.body.model import ROOT_DOF_NAMES
from jaxmocap.errors import InputError
from jaxmocap.io.atomic import AtomicFiles, atomic_path, write_text
from jaxmocap.io.bvh import body_to_bvh, format_bvh
from jaxmocap.rotations import Y_UP_TO_Z_UP

__all__ = [
    "FORMATS",
    "PoseFileError",
    "PoseTrack",
    "bvh_poses",
    "csv_header",
    "dof_units",
    "fill_missing",
    "format_csv",
    "format_trc",
    "load_track",
    "pose_track",
    "write_bvh",
    "write_c3d",
    "write_csv",
    "write_exports",
    "write_npz",
    "write_trc",
]

FORMATS = ("bvh", "trc", "c3d", "csv", "npz")
_M = np.asarray(Y_UP_TO_Z_UP)  # v_world = M v_yup


class PoseFileError(InputError):
    """A pose file (our CSV/NPZ, or a ground truth) that is missing, malformed or inconsistent."""


class PoseTrack(NamedTuple):
    """A tracked sequence (module docstring): every frame's estimate, NaN rows where there is
    none; ``valid`` says which estimates the tracker trusts."""

    q: np.ndarray  # (T, n_dof)
    keypoints: np.ndarray  # (T, n_kp, 3) metres, world Z up
    valid: np.ndarray  # (T,) bool
    fps: float
    dof_names: tuple[str, ...]
    keypoint_names: tuple[str, ...]
    dof_units: tuple[str, ...] = ()  # per DOF "m" or "rad"; () = the chain layout's default
    diagnostics: np.ndarray | None = None  # (T, k) per-frame signals, NaN where absent
    diagnostic_names: tuple[str, ...] = ()  # (k,)

    @property
    def n_frames(self) -> int:
        return self.q.shape[0]

    @property
    def times(self) -> np.ndarray:
        return np.arange(self.n_frames) / self.fps


def pose_track(model: BodyModel, q: np.ndarray, valid: np.ndarray | None, fps: float,
               diagnostics: np.ndarray | None = None,
               diagnostic_names: tuple[str, ...] = ()) -> PoseTrack:
    """A :class:`PoseTrack` of the estimates ``q`` (T, n_dof), valid or not: keypoints by
    forward kinematics of every row that has an estimate; a row with a non-finite entry has
    none (all NaN, never valid). ``valid`` default: every row with an estimate.
    ``diagnostics`` (T, k) with their ``diagnostic_names`` are carried along."""
    q = np.array(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != model.n_dof:
        raise ValueError(f"pose_track: q must be (T, {model.n_dof}), got {q.shape}")
    finite = np.isfinite(q).all(axis=1)
    valid = finite if valid is None else np.asarray(valid, bool) & finite
    if valid.shape != finite.shape:
        raise ValueError(f"pose_track: valid must be ({q.shape[0]},), got {valid.shape}")
    if not fps > 0:
        raise ValueError(f"pose_track: fps must be > 0, got {fps}")
    names = tuple(str(n) for n in diagnostic_names)
    if diagnostics is not None:
        diagnostics = np.array(diagnostics, np.float64)
        if diagnostics.shape != (q.shape[0], len(names)):
            raise ValueError(f"pose_track: diagnostics must be ({q.shape[0]}, {len(names)}) "
                             f"for {len(names)} diagnostic_names, got {diagnostics.shape}")
    elif names:
        raise ValueError("pose_track: diagnostic_names given without diagnostics")
    q[~finite] = np.nan
    if q.shape[0]:
        filled = np.where(finite[:, None], q, 0.0)
        kp = over_frames(body_keypoints, model, filled)
    else:
        kp = np.zeros((0, len(model.keypoint_names), 3))
    kp[~finite] = np.nan
    return PoseTrack(q, kp, valid, float(fps), tuple(model.chain.dof_names),
                     tuple(model.keypoint_names), dof_units(model), diagnostics, names)


def dof_units(model: BodyModel) -> tuple[str, ...]:
    """Unit of every DOF of ``q``: ``m`` for the root translation and prismatic joints,
    ``rad`` for the root rotation vector and revolute joints."""
    units = ["m"] * 3 + ["rad"] * 3 + ["rad"] * (model.n_dof - ROOT_DOFS)
    for _, kind, dof in model.chain.topology:
        if kind == PRISMATIC:
            units[dof] = "m"
    return tuple(units)


def _units(track: PoseTrack) -> tuple[str, ...]:
    if track.dof_units:
        return track.dof_units
    n = len(track.dof_names)
    return tuple(("m", "m", "m", "rad", "rad", "rad")[:n]) + ("rad",) * max(0, n - ROOT_DOFS)


def fill_missing(q: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """``q`` with every row where ``valid`` is False replaced by the last row where it is True
    (zeros = rest pose before the first)."""
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


def _diag(x: float) -> str:
    return "" if not np.isfinite(x) else f"{x:.6g}"


DIAG_PREFIX = "diag_"  # CSV columns of the per-frame diagnostics


def _diagnostics(track: PoseTrack) -> tuple[np.ndarray, tuple[str, ...]]:
    if track.diagnostics is None:
        return np.zeros((track.n_frames, 0)), ()
    return track.diagnostics, track.diagnostic_names


def csv_header(track: PoseTrack) -> list[str]:
    """The CSV's column names, each with its unit (module docstring)."""
    header = ["frame", "time_s", "valid"]
    header += [f"{n}_{a}_m" for n in track.keypoint_names for a in "xyz"]
    for i, (name, unit) in enumerate(zip(track.dof_names, _units(track), strict=True)):
        if 3 <= i < ROOT_DOFS:
            header.append(f"q_root_rotvec_{'xyz'[i - 3]}_rad")
        else:
            header.append(f"q_{name}_{unit}")
    header += [f"{DIAG_PREFIX}{n}" for n in _diagnostics(track)[1]]
    return header


def bvh_poses(track: PoseTrack) -> np.ndarray:
    """The poses the BVH holds (module docstring): every frame's estimate, the last one
    repeated where a frame has none."""
    return fill_missing(track.q, np.isfinite(track.q).all(axis=1))


def format_csv(track: PoseTrack) -> str:
    """The CSV text (module docstring)."""
    buf = io.StringIO()
    w = csv.writer(buf, lineterminator="\n")
    w.writerow(csv_header(track))
    diag = _diagnostics(track)[0]
    for t in range(track.n_frames):
        row = [str(t), f"{t / track.fps:.6f}", str(int(track.valid[t]))]
        row += [_num(v) for v in track.keypoints[t].reshape(-1)]
        row += [_num(v) for v in track.q[t]]
        row += [_diag(v) for v in diag[t]]
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
    yup = np.where(track.valid[:, None, None], track.keypoints, np.nan) @ _M  # v_yup = M^T v
    for t in range(n):
        vals = [f"{v:.6f}" if np.isfinite(v) else "NaN" for v in yup[t].reshape(-1)]
        lines.append("\t".join([str(t + 1), f"{t / track.fps:.6f}"] + vals))
    return "\n".join(lines) + "\n"


def write_csv(path: str | os.PathLike, track: PoseTrack) -> Path:
    """Write the CSV atomically."""
    return write_text(path, format_csv(track))


def write_trc(path: str | os.PathLike, track: PoseTrack) -> Path:
    """Write the TRC atomically."""
    return write_text(path, format_trc(track, Path(path).name))


def _save_c3d(path: Path, track: PoseTrack) -> None:
    """The C3D file (module docstring) at ``path``, written by ezc3d."""
    import ezc3d

    t, k = track.n_frames, len(track.keypoint_names)
    ok = track.valid[:, None] & np.isfinite(track.keypoints).all(axis=-1)  # (T, k)
    pts = np.zeros((4, k, t))
    pts[:3] = np.where(ok[..., None], track.keypoints * 1000.0, 0.0).transpose(2, 1, 0)
    pts[3] = 1.0
    c = ezc3d.c3d()
    point = c["parameters"]["POINT"]
    point["RATE"]["value"] = [float(track.fps)]
    point["LABELS"]["value"] = tuple(track.keypoint_names)
    point["UNITS"]["value"] = ["mm"]
    c.add_parameter("POINT", "X_SCREEN", ["+X"])
    c.add_parameter("POINT", "Y_SCREEN", ["+Z"])
    c["data"]["points"] = pts
    c["data"]["meta_points"] = {
        "residuals": np.where(ok.T, 0.0, -1.0)[None],
        "camera_masks": np.zeros((7, k, t), bool),
    }
    c.write(str(path))


def write_c3d(path: str | os.PathLike, track: PoseTrack) -> Path:
    """Write the C3D atomically."""
    with atomic_path(path) as tmp:
        _save_c3d(tmp, track)
    return Path(path)


def _save_npz(path: Path, track: PoseTrack, extra: dict[str, np.ndarray]) -> None:
    if track.diagnostics is not None:
        extra = {"diagnostics": track.diagnostics,
                 "diagnostic_names": np.array(track.diagnostic_names, dtype=str), **extra}
    with open(path, "wb") as f:
        np.savez(f, q=track.q, keypoints=track.keypoints, valid=track.valid,
                 times=track.times, fps=np.float64(track.fps),
                 dof_names=np.array(track.dof_names), dof_units=np.array(_units(track)),
                 keypoint_names=np.array(track.keypoint_names), **extra)


def write_npz(path: str | os.PathLike, track: PoseTrack, **extra: np.ndarray) -> Path:
    """Write the NPZ atomically; ``extra`` arrays are stored beside the standard keys."""
    with atomic_path(path) as tmp:
        _save_npz(tmp, track, extra)
    return Path(path)


def write_bvh(path: str | os.PathLike, model: BodyModel, track: PoseTrack) -> Path:
    """Write the BVH atomically (every estimate; :func:`bvh_poses`)."""
    return write_text(path, format_bvh(body_to_bvh(model, bvh_poses(track), track.fps)))


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
        elif fmt == "c3d":
            _save_c3d(tmp, track)
        elif fmt == "bvh":
            tmp.write_text(format_bvh(body_to_bvh(model, bvh_poses(track), track.fps)))
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
    units = tuple(str(u) for u in data.get("dof_units", ()))
    if units and len(units) != q.shape[1]:
        raise PoseFileError(f"{path}: field 'dof_units' has {len(units)} units for "
                            f"{q.shape[1]} DOFs")
    diag, diag_names = None, ()
    if "diagnostics" in data:
        diag = np.asarray(data["diagnostics"], np.float64)
        diag_names = tuple(str(n) for n in data.get("diagnostic_names", ()))
        if diag.shape != (t, len(diag_names)):
            raise PoseFileError(f"{path}: field 'diagnostics' has shape {diag.shape}, expected "
                                f"({t}, {len(diag_names)}) for its 'diagnostic_names'")
    return PoseTrack(q, kp, valid & np.isfinite(kp).all(axis=(1, 2)), fps, dof_names, names,
                     units, diag, diag_names)


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
    n_diag = 0
    while n_diag < len(header) - 3 and header[-1 - n_diag].startswith(DIAG_PREFIX):
        n_diag += 1
    diag_names = tuple(c[len(DIAG_PREFIX):] for c in header[len(header) - n_diag:])
    kp_cols = [c for c in header[3:len(header) - n_diag] if not c.startswith("q_")]
    unit = "_m" if kp_cols and kp_cols[0].endswith("_m") else ""  # "" : files before units
    if len(kp_cols) % 3 or any(not c.endswith(f"_{'xyz'[i % 3]}{unit}")
                               for i, c in enumerate(kp_cols)):
        raise PoseFileError(f"{path}: line 1: keypoint columns must come as <name>_x_m, "
                            "<name>_y_m, <name>_z_m")
    names = tuple(c[:-2 - len(unit)] for c in kp_cols[::3])
    dof_names, units = _dof_columns(header[3 + len(kp_cols):len(header) - n_diag])
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
    q = values[:, 3 + 3 * k:len(header) - n_diag]
    valid = (values[:, 2] == 1) & np.isfinite(kp).all(axis=(1, 2))
    fps = _fps_from_times(path, values[:, 1], t)
    diag = values[:, len(header) - n_diag:] if n_diag else None
    return PoseTrack(q, kp, valid, fps, dof_names, names, units, diag, diag_names)


def _dof_columns(cols: list[str]) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """DOF names and units of the ``q_*`` CSV columns (inverse of :func:`csv_header`)."""
    names, units = [], []
    for c in cols:
        name = c[2:]
        unit = next((u for u in ("m", "rad") if name.endswith(f"_{u}")), "")
        name = name[:-len(unit) - 1] if unit else name
        if name.startswith("root_rotvec_") and name[-1] in "xyz":
            name = ROOT_DOF_NAMES[3 + "xyz".index(name[-1])]
        names.append(name)
        units.append(unit)
    return tuple(names), (tuple(units) if all(units) else ())


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
