"""The camera file: ``cameras.json`` and other tools' calibration files -> cameras
(:class:`jaxmocap.camera.Camera`).

``cameras.json`` schema (version 1)::

    {"version": 1,
     "cameras": [
        {"name": "cam0",                 # unique, non-empty string
         "width": 640, "height": 480,    # image size in pixels, positive integers
         "K": [[fx, s, cx], [0, fy, cy], [0, 0, 1]],   # fx, fy > 0
         "dist": [k1, k2, p1, p2, k3],   # OpenCV order; 4 values allowed (k3 = 0)
         "R": [[...], [...], [...]],     # world -> camera rotation (orthonormal, det +1)
         # or instead of "R": "rvec": [rx, ry, rz]   (Rodrigues vector, radians)
         "t": [tx, ty, tz]}              # world -> camera translation, metres
     ]}

Files written by other tools load when their fields are OpenCV's: ``"version"`` may be left
out (if present it must be 1); the cameras may be the top-level list, the ``"cameras"`` list
or an object keyed by camera name; each camera may spell its fields as OpenCV's and common
calibration tools do (:data:`FIELD_ALIASES`: ``camera_matrix``/``matrix``/``mtx`` for ``K``,
``dist_coeffs``/``distortions``/``D`` for ``dist``, ``rvec``/``rotation`` (a 3-vector
Rodrigues or a 3x3 matrix), ``tvec``/``translation``/``T`` for ``t``, ``size``/``image_size``
``[width, height]``), with 4, 5, 8, 12 or 14 OpenCV distortion values (the terms past ``k3``
must be zero: the model here is OpenCV's 5-term one). A TOML file is read as the
calibration file of Pose2Sim / anipose / FreeMoCap (``[cam_1] name, size, matrix,
distortions, rotation, translation``; ``[metadata]`` skipped), and an OpenCV FileStorage
YAML/XML (``cv2.FileStorage``: ``camera_matrix``, ``dist_coeffs`` / ``distortion_coefficients``,
``R`` (3x3 or a Rodrigues 3x1), ``T``, ``image_width`` / ``image_height``; one camera at the
top level, named after the file, or one map per camera). The kind is told by the content
(a FileStorage header, a JSON object, a TOML table header), by the suffix where the content
allows two; a file that is none of them is one line.

Malformed files raise :class:`CameraFileError` naming the file, the camera, the field and
what was expected. ``save_cameras`` writes atomically (temporary file + ``os.replace``).
"""

import json
import os
import re
from collections.abc import Sequence
from pathlib import Path

import jax.numpy as jnp
import numpy as np

from jaxmocap.camera import Camera, unstack_cameras
from jaxmocap.errors import InputError
from jaxmocap.rotations import rodrigues

CAMERAS_JSON_VERSION = 1
ROTATION_TOLERANCE = 1e-4  # max |R R^T - I| and |det R - 1| accepted from cameras.json

__all__ = ["CAMERAS_JSON_VERSION", "CameraFileError", "load_cameras", "save_cameras"]


class CameraFileError(InputError):
    """A ``cameras.json`` file that does not follow the schema in this module's docstring."""




def _field_array(path, name, entry, key, shape) -> np.ndarray:
    where = f"{path}: camera {name!r}: field {key!r}"
    if key not in entry:
        raise CameraFileError(f"{where}: missing (expected {_shape_text(shape)} numbers)")
    try:
        a = np.asarray(entry[key], dtype=float)
    except (TypeError, ValueError):
        raise CameraFileError(f"{where}: expected {_shape_text(shape)} numbers") from None
    if a.shape != shape:
        raise CameraFileError(f"{where}: expected shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        raise CameraFileError(f"{where}: contains non-finite values")
    return a


def _shape_text(shape) -> str:
    return "x".join(str(s) for s in shape)


def _parse_camera(path, i, entry, dtype) -> tuple[str, Camera]:
    name = entry.get("name")
    if not isinstance(name, str) or not name:
        raise CameraFileError(f"{path}: cameras[{i}]: field 'name': expected a non-empty string")
    size = {}
    for key in ("width", "height"):
        v = entry.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v <= 0:
            raise CameraFileError(
                f"{path}: camera {name!r}: field {key!r}: expected a positive integer, got {v!r}"
            )
        size[key] = v
    K = _field_array(path, name, entry, "K", (3, 3))
    if K[0, 0] <= 0 or K[1, 1] <= 0:
        raise CameraFileError(
            f"{path}: camera {name!r}: field 'K': focal lengths K[0][0], K[1][1] must be > 0"
        )
    if not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
        raise CameraFileError(
            f"{path}: camera {name!r}: field 'K': expected [[fx, s, cx], [0, fy, cy], [0, 0, 1]]"
        )
    if "dist" not in entry:
        raise CameraFileError(
            f"{path}: camera {name!r}: field 'dist': missing (expected 5 numbers)"
        )
    n_dist = np.shape(entry["dist"]) if isinstance(entry["dist"], list) else None
    dist = _field_array(path, name, entry, "dist", (4,) if n_dist == (4,) else (5,))
    dist = np.concatenate([dist, np.zeros(5 - dist.size)])
    if ("R" in entry) == ("rvec" in entry):
        raise CameraFileError(
            f"{path}: camera {name!r}: field 'R'/'rvec': give exactly one of 'R' (3x3) or "
            "'rvec' (3)"
        )
    if "R" in entry:
        R = _field_array(path, name, entry, "R", (3, 3))
        err = max(np.abs(R @ R.T - np.eye(3)).max(), abs(np.linalg.det(R) - 1))
        if err > ROTATION_TOLERANCE:
            raise CameraFileError(
                f"{path}: camera {name!r}: field 'R': expected a rotation (orthonormal, det +1); "
                f"off by {err:.2g}"
            )
    else:
        R = rodrigues(_field_array(path, name, entry, "rvec", (3,)))
    t = _field_array(path, name, entry, "t", (3,))
    cam = Camera(
        K=jnp.asarray(K, dtype),
        R=jnp.asarray(R, dtype),
        t=jnp.asarray(t, dtype),
        dist=jnp.asarray(dist, dtype),
        width=size["width"],
        height=size["height"],
    )
    return name, cam


# Other tools' spellings of the fields of one camera (OpenCV's FileStorage names, Pose2Sim /
# anipose calibration.toml, common JSON dumps) -> ours. "rotation" may be a 3x3 or a rvec.
FIELD_ALIASES = {
    "K": ("camera_matrix", "cameraMatrix", "matrix", "mtx", "intrinsics", "intrinsic"),
    "dist": ("dist_coeffs", "distCoeffs", "distortion", "distortions", "D", "dist_coef",
             "distortion_coefficients"),
    "R": ("rotation_matrix", "R_mat"),
    "rvec": ("rotation_vector", "rvecs"),
    "t": ("tvec", "translation", "T", "tvecs"),
}
SIZE_ALIASES = ("size", "image_size", "imageSize", "resolution")  # [width, height]


def _canonical_entry(path, i: int, entry, key_name: str | None):
    """One camera entry with the field names of our schema (other tools' names mapped)."""
    if not isinstance(entry, dict):
        raise CameraFileError(
            f"{path}: cameras[{i}]: expected an object, got {type(entry).__name__}"
        )
    e = dict(entry)
    if "name" not in e and key_name is not None:
        e["name"] = key_name
    for ours, theirs in FIELD_ALIASES.items():
        for alias in theirs:
            if alias in e and ours not in e:
                e[ours] = e.pop(alias)
    for ours, theirs in (("width", "image_width"), ("height", "image_height")):
        if theirs in e and ours not in e:
            e[ours] = e.pop(theirs)
    if "R" in e and "rvec" not in e and np.shape(e["R"]) in ((3,), (3, 1), (1, 3)):
        e["rvec"] = e.pop("R")  # OpenCV's extrinsics as a Rodrigues vector
    if "rotation" in e and "R" not in e and "rvec" not in e:
        rot = e.pop("rotation")
        e["R" if np.shape(rot) == (3, 3) else "rvec"] = rot
    if "rvec" in e and np.shape(e["rvec"]) in ((3, 1), (1, 3)):
        e["rvec"] = np.asarray(e["rvec"], float).ravel().tolist()
    if "t" in e and np.shape(e["t"]) in ((3, 1), (1, 3)):
        e["t"] = np.asarray(e["t"], float).ravel().tolist()
    for alias in SIZE_ALIASES:
        if alias in e and ("width" not in e or "height" not in e):
            size = e.pop(alias)
            if not (isinstance(size, list | tuple) and len(size) == 2):
                raise CameraFileError(
                    f"{path}: camera {e.get('name')!r}: field {alias!r}: expected [width, height]"
                )
            w, h = size
            e["width"] = int(w) if isinstance(w, float) and w.is_integer() else w
            e["height"] = int(h) if isinstance(h, float) and h.is_integer() else h
    if isinstance(e.get("dist"), list):
        flat = np.asarray(e["dist"], dtype=object).ravel().tolist()
        if len(flat) in (8, 12, 14):
            try:
                extra = np.asarray(flat[5:], float)
            except (TypeError, ValueError):
                extra = np.ones(1)
            if np.any(extra != 0):
                raise CameraFileError(
                    f"{path}: camera {e.get('name')!r}: field 'dist': {len(flat)} OpenCV terms "
                    "with non-zero rational/thin-prism/tilt terms; jaxmocap's model is the "
                    "5-term one (k1 k2 p1 p2 k3): recalibrate with those terms fixed at 0"
                )
            flat = flat[:5]
        e["dist"] = flat
    return e


def _camera_entries(path: Path, data) -> list[dict]:
    """The list of camera entries of a parsed file, whichever layout it uses."""
    if isinstance(data, list):
        entries, keys = data, [None] * len(data)
    elif isinstance(data, dict):
        if "version" in data and data["version"] != CAMERAS_JSON_VERSION:
            raise CameraFileError(
                f"{path}: field 'version': expected {CAMERAS_JSON_VERSION} (or no version), "
                f"got {data['version']!r}"
            )
        if "cameras" in data:
            entries = data["cameras"]
            if isinstance(entries, dict):
                entries, keys = list(entries.values()), list(entries)
            else:
                keys = [None] * len(entries) if isinstance(entries, list) else []
        else:  # {name: camera, ...} (Pose2Sim / anipose / OpenCV dumps); "metadata" skipped
            items = [(k, v) for k, v in data.items()
                     if isinstance(v, dict) and k not in ("metadata", "meta")]  # fmt: skip
            entries, keys = [v for _, v in items], [str(v.get("name", k)) for k, v in items]
    else:
        raise CameraFileError(f"{path}: expected a JSON object with 'cameras' (or a list)")
    if not isinstance(entries, list) or not entries:
        raise CameraFileError(f"{path}: field 'cameras': expected a non-empty list")
    return [_canonical_entry(path, i, e, k) for i, (e, k) in enumerate(zip(entries, keys,
                                                                         strict=True))]


def _filestorage_value(node):
    """A cv2.FileNode as plain Python (matrices as nested lists, maps as dicts)."""
    if node.isMap():
        if "dt" in node.keys() and "data" in node.keys():
            return np.asarray(node.mat(), float).tolist()
        return {k: _filestorage_value(node.getNode(k)) for k in node.keys()}
    if node.isSeq():
        return [_filestorage_value(node.at(i)) for i in range(node.size())]
    if node.isInt():
        return int(node.real())
    if node.isReal():
        return float(node.real())
    if node.isString():
        return node.string()
    return None


def _read_filestorage(path: Path) -> dict:
    """An OpenCV FileStorage file (YAML or XML, as ``cv2.FileStorage`` writes): one camera
    (``camera_matrix``, ``dist_coeffs``/``distortion_coefficients``, ``R``, ``T``,
    ``image_width``/``image_height`` at the top level, named after the file) or one map per
    camera."""
    import cv2

    try:
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except cv2.error as e:
        raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file ({e.err})") \
            from None
    if not fs.isOpened():
        raise CameraFileError(f"{path}: not a readable OpenCV FileStorage file")
    root = fs.root()
    data = {k: _filestorage_value(root.getNode(k)) for k in root.keys()}
    fs.release()
    k_names = ("K",) + FIELD_ALIASES["K"]
    if any(k in data for k in k_names):
        return {"cameras": [{"name": path.stem, **data}]}
    return data


def _file_kind(path: Path, head: str) -> str:
    """``json``, ``toml`` or ``filestorage``: by the file's content where it tells (an OpenCV
    FileStorage header, a JSON object, a TOML table header ``[cam_0]`` or ``key = value``),
    else by the suffix; one line if neither fits."""
    text = head.lstrip("\ufeff \t\r\n")
    first = text.split("\n", 1)[0].strip()
    suffix = path.suffix.lower()
    if text.startswith("%YAML") or (text.startswith("<?xml") and "<opencv_storage>" in head):
        return "filestorage"
    if suffix in (".json", ".toml"):
        return suffix[1:]
    if text.startswith("{"):
        return "json"
    if re.fullmatch(r"\[[A-Za-z_][\w.-]*\]", first) or re.match(r"[A-Za-z_][\w.-]*\s*=", first):
        return "toml"
    if text.startswith("[") or text[:1] in ('"', "-") or text[:1].isdigit():
        return "json"
    if suffix in (".yml", ".yaml", ".xml"):
        return "filestorage"
    raise CameraFileError(
        f"{path}: not a camera file jaxmocap reads: expected cameras.json (JSON), a "
        "calibration TOML (anipose / Pose2Sim / FreeMoCap) or an OpenCV FileStorage YAML/XML")


def _read_toml(path: Path) -> dict:
    import tomllib

    from jaxmocap.io.preflight import read_text

    text = read_text(path, "a calibration TOML (anipose / Pose2Sim / FreeMoCap)", CameraFileError)
    try:
        return tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise CameraFileError(f"{path}: not valid TOML: {e}") from None


def load_cameras(path: str | os.PathLike, dtype=None) -> tuple[list[Camera], list[str]]:
    """Read ``cameras.json`` (schema and accepted variants in the module docstring), a
    calibration TOML or an OpenCV FileStorage YAML/XML, told apart by content.

    Returns (cameras, names). Arrays get ``dtype`` (default: JAX's default float, float32
    unless x64 is on). Raises :class:`CameraFileError` naming the file, camera and field on
    any problem.
    """
    path = Path(path)
    dtype = jnp.result_type(float) if dtype is None else dtype
    try:
        with open(path, "rb") as f:
            raw = f.read(4096)
        head = raw.decode("utf-8", errors="replace")
        # binary content: the reader layer (read_json) says why in its one line
        kind = "json" if b"\x00" in raw or "\ufffd" in head[:-4] else _file_kind(path, head)
    except OSError:
        kind = "json"  # read_json says why it cannot be read
    if kind == "toml":
        data = _read_toml(path)
    elif kind == "filestorage":
        data = _read_filestorage(path)
    else:
        from jaxmocap.io.preflight import read_json

        data = read_json(path, "a cameras.json of `jaxmocap calibrate`", CameraFileError)
    cams, names = [], []
    for i, entry in enumerate(_camera_entries(path, data)):
        name, cam = _parse_camera(path, i, entry, dtype)
        if name in names:
            raise CameraFileError(f"{path}: camera {name!r}: field 'name': duplicate name")
        cams.append(cam)
        names.append(name)
    return cams, names


def save_cameras(
    path: str | os.PathLike, cams: Sequence[Camera] | Camera, names: Sequence[str] | None = None
) -> None:
    """Write cameras (a list or a stacked Camera) to ``cameras.json`` atomically.

    ``names`` default to ``cam0, cam1, ...``; they must be unique non-empty strings.
    """
    path = Path(path)
    cams = unstack_cameras(cams) if isinstance(cams, Camera) else list(cams)
    names = [f"cam{i}" for i in range(len(cams))] if names is None else list(names)
    if len(names) != len(cams):
        raise ValueError(f"save_cameras: {len(cams)} cameras but {len(names)} names")
    if len(set(names)) != len(names) or not all(isinstance(n, str) and n for n in names):
        raise ValueError(f"save_cameras: names must be unique non-empty strings, got {names}")
    entries = []
    for name, cam in zip(names, cams, strict=True):
        if cam.K.ndim != 2:
            raise ValueError(f"save_cameras: camera {name!r} is batched; pass a list")
        entries.append(
            {
                "name": name,
                "width": int(cam.width),
                "height": int(cam.height),
                "K": np.asarray(cam.K, float).tolist(),
                "dist": np.asarray(cam.dist, float).tolist(),
                "R": np.asarray(cam.R, float).tolist(),
                "t": np.asarray(cam.t, float).tolist(),
            }
        )
    text = json.dumps({"version": CAMERAS_JSON_VERSION, "cameras": entries}, indent=2) + "\n"
    from jaxmocap.io.atomic import write_text  # one atomic-write mechanism for the package

    write_text(path, text)
