"""Synthetic datasets on disk (written by ``jaxmocap synth``: :mod:`jaxmocap.commands.synth`).

A dataset folder holds

* ``scene.json`` — ``{"version": 1, "scene": {SceneConfig fields}, "render": {...}}``: every
  setting (with the seed it regenerates the sequence bit-identically on the same machine
  and dtype, recorded in ``render.dtype``);
* ``cameras.json`` — the rig (:func:`jaxmocap.io.cameras.save_cameras`);
* ``groundtruth.npz`` — the ground truth of :func:`~jaxmocap.synth.sequence.render_sequence`;
* ``<camera>.mp4`` — one video per camera (``mp4v``, lossy), and/or with ``--png``
  ``<camera>/000000.png, ...`` lossless frames.

The folder is written into a temporary folder beside the target and renamed into place, so
a target either does not exist or is complete. :func:`load_dataset` reads it back as a
:class:`~jaxmocap.synth.sequence.Sequence` (PNG frames when present, else the videos).
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import cv2
import numpy as np

from jaxmocap.errors import InputError
from jaxmocap.io.cameras import load_cameras, save_cameras
from jaxmocap.synth.scene import SCENE_JSON_VERSION, SceneConfig, SceneError
from jaxmocap.synth.sequence import Sequence

VIDEO_CODEC = "mp4v"
GT_FRAME_KEYS = ("q", "keypoints", "patch_ids", "illuminant", "intensity", "visible",
                 "occluded_fraction", "body_pixels", "times")
GT_KEYS = GT_FRAME_KEYS + ("dof_names", "keypoint_names")


class DatasetError(InputError):
    """A dataset folder that is missing files or holds inconsistent ones."""


# ----------------------------------------------------------------------------- writing


def _check_target(folder: Path) -> None:
    if folder.exists() and not folder.is_dir():
        raise DatasetError(f"{folder}: a file is in the way; expected a new or empty folder")
    if folder.is_dir() and any(folder.iterdir()):
        raise DatasetError(f"{folder}: folder exists and is not empty; choose a new folder")


def _write_video(path: Path, frames: np.ndarray, fps: float) -> None:
    h, w = frames.shape[1:3]
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*VIDEO_CODEC), float(fps),
                             (w, h))
    if not writer.isOpened():
        raise OSError(f"{path}: OpenCV cannot open a {VIDEO_CODEC} video writer")
    try:
        for f in frames:
            writer.write(np.ascontiguousarray(f[..., ::-1]))
    finally:
        writer.release()


def write_dataset(seq: Sequence, folder: str | os.PathLike, video: bool = True,
                  png: bool = False, dtype_name: str | None = None, sheet: bool = False
                  ) -> Path:
    """Write ``seq`` as a dataset folder (module docstring), atomically, optionally with a
    ``contact_sheet.png`` preview (:func:`contact_sheet`). Raises
    :class:`DatasetError` if ``folder`` is a file or a non-empty folder."""
    folder = Path(folder)
    if not (video or png):
        raise DatasetError("write_dataset: nothing to write; ask for video and/or png frames")
    _check_target(folder)
    from jaxmocap.io.atomic import atomic_folder

    with atomic_folder(folder) as tmp:
        t, n_cams, h, w, _ = seq.frames.shape
        render_info = {"dtype": dtype_name or str(seq.groundtruth["q"].dtype), "n_frames": t,
                       "cameras": list(seq.camera_names), "width": w, "height": h,
                       "fps": seq.config.fps, "video": video, "png": png}
        doc = {"version": SCENE_JSON_VERSION, "scene": seq.config.to_dict(),
               "render": render_info}
        (tmp / "scene.json").write_text(json.dumps(doc, indent=2) + "\n")
        save_cameras(tmp / "cameras.json", seq.cameras, seq.camera_names)
        np.savez_compressed(tmp / "groundtruth.npz", **seq.groundtruth)
        if sheet:
            cv2.imwrite(str(tmp / "contact_sheet.png"), contact_sheet(seq)[..., ::-1])
        for c, name in enumerate(seq.camera_names):
            if video:
                _write_video(tmp / f"{name}.mp4", seq.frames[:, c], seq.config.fps)
            if png:
                (tmp / name).mkdir()
                for k in range(t):
                    cv2.imwrite(str(tmp / name / f"{k:06d}.png"), seq.frames[k, c, ..., ::-1])
    return folder


def contact_sheet(seq: Sequence, n: int = 8, width: int = 200) -> np.ndarray:
    """A preview image (``uint8`` RGB): ``n`` evenly spaced frames (columns) x cameras (rows),
    each thumbnail ``width`` pixels wide and labelled with its frame number and camera."""
    t, n_cams, h, w, _ = seq.frames.shape
    idx = np.unique(np.linspace(0, t - 1, min(n, t)).round().astype(int))
    th = max(1, round(h * width / w))
    rows = []
    for c in range(n_cams):
        tiles = []
        for k in idx:
            tile = cv2.resize(seq.frames[k, c], (width, th), interpolation=cv2.INTER_AREA)
            label = f"{seq.camera_names[c]} frame {k}"
            for colour, thick in (((0, 0, 0), 3), ((255, 255, 255), 1)):
                cv2.putText(tile, label, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, thick,
                            cv2.LINE_AA)
            tiles.append(cv2.copyMakeBorder(tile, 1, 1, 1, 1, cv2.BORDER_CONSTANT, value=0))
        rows.append(np.concatenate(tiles, axis=1))
    return np.concatenate(rows, axis=0)


# ----------------------------------------------------------------------------- reading


def _read_frames_png(folder: Path, name: str, t: int, h: int, w: int) -> np.ndarray:
    from jaxmocap.io.video import decode_image

    out = np.empty((t, h, w, 3), np.uint8)
    for k in range(t):
        path = folder / name / f"{k:06d}.png"
        img, why = decode_image(path) if path.is_file() else (None, "no such file")
        if img is None:
            raise DatasetError(f"{path}: missing or not a readable PNG ({why}; frame {k} of "
                               f"{t})")
        if img.shape != (h, w, 3):
            raise DatasetError(f"{path}: image is {img.shape[1]}x{img.shape[0]}, "
                               f"expected {w}x{h}")
        out[k] = img[..., ::-1]
    return out


def _read_frames_video(path: Path, t: int, h: int, w: int) -> np.ndarray:
    if not path.is_file():
        raise DatasetError(f"{path}: missing video (and no PNG frames folder)")
    cap = cv2.VideoCapture(str(path))
    frames = []
    try:
        while True:
            ok, img = cap.read()
            if not ok:
                break
            frames.append(img[..., ::-1])
    finally:
        cap.release()
    if len(frames) != t:
        raise DatasetError(f"{path}: {len(frames)} readable frames, expected {t}")
    if frames[0].shape != (h, w, 3):
        raise DatasetError(f"{path}: frames are {frames[0].shape[1]}x{frames[0].shape[0]}, "
                           f"expected {w}x{h}")
    return np.stack(frames)


def _read_groundtruth(path: Path, t: int, n_cams: int, h: int, w: int) -> dict[str, np.ndarray]:
    try:
        with np.load(path, allow_pickle=False) as npz:
            gt = {k: npz[k] for k in npz.files}
    except FileNotFoundError:
        raise DatasetError(f"{path}: missing ground-truth file") from None
    except (OSError, ValueError) as e:
        raise DatasetError(f"{path}: not a readable .npz file ({e})") from None
    missing = [k for k in GT_KEYS if k not in gt]
    if missing:
        raise DatasetError(f"{path}: missing field(s) {missing}")
    expect = {"patch_ids": (t, n_cams, h, w), "colour_ids": (t, n_cams, h, w),
              "illuminant": (t, 3, 3), "intensity": (t,), "visible": (t, n_cams),
              "occluded_fraction": (t, n_cams), "body_pixels": (t, n_cams), "times": (t,)}
    for k, shape in expect.items():
        if k in gt and gt[k].shape != shape:
            raise DatasetError(f"{path}: field {k!r} has shape {gt[k].shape}, expected {shape}")
    n_dof, n_kp = len(gt["dof_names"]), len(gt["keypoint_names"])
    for k, shape in (("q", (t, n_dof)), ("keypoints", (t, n_kp, 3))):
        if gt[k].shape != shape:
            raise DatasetError(f"{path}: field {k!r} has shape {gt[k].shape}, expected {shape}")
    return gt


def load_dataset(folder: str | os.PathLike) -> Sequence:
    """Read a dataset folder written by :func:`write_dataset` (or ``jaxmocap synth``).

    Raises :class:`DatasetError` naming the file and field for a missing or corrupt part.
    Frames come from the PNG folders when present (lossless), else from the videos."""
    folder = Path(folder)
    if not folder.is_dir():
        raise DatasetError(f"{folder}: not a dataset folder (does not exist or is a file)")
    scene_path = folder / "scene.json"
    from jaxmocap.io.preflight import read_json

    doc = read_json(scene_path, "the scene.json of a `jaxmocap synth` dataset", DatasetError)
    if not isinstance(doc, dict) or doc.get("version") != SCENE_JSON_VERSION:
        got = doc.get("version") if isinstance(doc, dict) else doc
        raise DatasetError(f"{scene_path}: field 'version': expected {SCENE_JSON_VERSION}, "
                           f"got {got!r}")
    try:
        config = SceneConfig.from_dict(doc.get("scene"), str(scene_path))
    except SceneError as e:
        raise DatasetError(str(e)) from None
    info = doc.get("render")
    keys = ("n_frames", "cameras", "width", "height")
    if not isinstance(info, dict) or any(k not in info for k in keys):
        raise DatasetError(f"{scene_path}: field 'render': expected an object with {keys}")
    t, names, w, h = (info[k] for k in keys)
    try:
        cams, cam_names = load_cameras(folder / "cameras.json")
    except ValueError as e:  # CameraFileError names the file and field
        raise DatasetError(str(e)) from None
    if cam_names != list(names):
        raise DatasetError(f"{folder / 'cameras.json'}: cameras {cam_names}, scene.json "
                           f"says {list(names)}")
    gt = _read_groundtruth(folder / "groundtruth.npz", t, len(names), h, w)
    frames = np.stack([
        _read_frames_png(folder, n, t, h, w) if (folder / n).is_dir()
        else _read_frames_video(folder / f"{n}.mp4", t, h, w)
        for n in names], axis=1)
    return Sequence(frames=frames, cameras=cams, camera_names=cam_names, groundtruth=gt,
                    config=config)
