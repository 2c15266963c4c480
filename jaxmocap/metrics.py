"""Metrics of a track against a ground truth: per-joint position error and jitter (``jaxmocap
eval``: :mod:`jaxmocap.commands.evaluate`; ``jaxmocap experiment``'s cells).

Both files hold keypoint trajectories (:func:`jaxmocap.io.export.load_track`): our
``poses.npz`` / ``poses.csv`` and a synthetic dataset's ``groundtruth.npz`` (or the dataset
folder). Keypoints are matched by name. Metrics (all in **centimetres**):

* **MPJPE** — mean over the frames the tracker reported valid of ``||x_pred - x_gt||`` per
  joint, and over all joints (the file's ``valid`` flag decides: an invalid frame's estimate,
  which the file holds too, and a frame without one are counted separately, not averaged in);
* **jitter** — mean ``||x_{t+1} - 2 x_t + x_{t-1}||`` over consecutive valid triples (cm per
  frame^2, the second difference), for the prediction and for the ground truth — tracking
  noise shows as prediction jitter well above the ground truth's;
* **depth and lateral error** (:func:`depth_lateral`) — each joint's error split into its
  component along the line of sight from the camera rig (the cameras' mean centre) to the true
  joint and the remainder across it: a short stereo baseline measures depth far more coarsely
  than position across the view, and the split shows which one an error is.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from jaxmocap.errors import InputError
from jaxmocap.io.export import PoseFileError, load_track

__all__ = ["depth_lateral", "evaluate", "facing_angle", "format_table"]


def _jitter(x: np.ndarray, ok: np.ndarray) -> np.ndarray:
    """Per-joint mean second-difference norm over triples with all three frames ``ok``."""
    if len(x) < 3:
        return np.full(x.shape[1], np.nan)
    acc = np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=-1)  # (T-2, k)
    m = ok[2:] & ok[1:-1] & ok[:-2]
    return acc[m].mean(axis=0) if m.any() else np.full(x.shape[1], np.nan)


def depth_lateral(pred: np.ndarray, gt: np.ndarray, origin: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """The error ``pred - gt`` (..., 3) split along the line of sight ``u = (gt - origin) /
    ||gt - origin||`` from ``origin`` (3,) (the rig's centre): ``(|e . u|, ||e - (e . u) u||)``,
    depth and lateral, each (...,), in the units of the input. Their squares sum to
    ``||e||^2``."""
    e = np.asarray(pred, np.float64) - np.asarray(gt, np.float64)
    u = np.asarray(gt, np.float64) - np.asarray(origin, np.float64)
    u = u / np.linalg.norm(u, axis=-1, keepdims=True)
    along = np.sum(e * u, axis=-1)
    lateral = np.linalg.norm(e - along[..., None] * u, axis=-1)
    return np.asarray(np.abs(along)), np.asarray(lateral)  # arrays also for one point


def facing_angle(l_shoulder: np.ndarray, r_shoulder: np.ndarray, neck: np.ndarray,
                 centres: np.ndarray) -> np.ndarray:
    """The angle (degrees) between a body's facing direction and the direction to each camera,
    in the ground plane (world Z up): 0 facing the camera, 90 side-on, 180 the back to it.
    The facing direction is the shoulder axis (left minus right) crossed with up; the camera
    direction runs from the neck to each centre. ``l_shoulder``, ``r_shoulder``, ``neck``
    (T, 3), ``centres`` (n_cams, 3) -> (T, n_cams). Used to bin errors by view (issue 38
    decision 2)."""
    lat = np.asarray(l_shoulder, np.float64) - np.asarray(r_shoulder, np.float64)
    fwd = np.cross(lat, [0.0, 0.0, 1.0])[:, None, :2]
    to_cam = (np.asarray(centres, np.float64)[None, :, :2]
              - np.asarray(neck, np.float64)[:, None, :2])
    cos = np.sum(fwd * to_cam, -1) / (np.linalg.norm(fwd, axis=-1)
                                      * np.linalg.norm(to_cam, axis=-1))
    return np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))


def evaluate(pred_path: str | Path, gt_path: str | Path) -> dict:
    """The metrics of the module docstring as a JSON-ready dict."""
    gt_path = Path(gt_path)
    if gt_path.is_dir():
        gt_path = gt_path / "groundtruth.npz"
    pred, gt = load_track(pred_path), load_track(gt_path)
    if not np.all(np.isfinite(gt.keypoints)):
        t = int(np.argwhere(~np.isfinite(gt.keypoints))[0, 0])
        raise PoseFileError(f"{gt_path}: field 'keypoints' holds NaN/inf (first at frame {t}); "
                            "a ground truth must be complete")
    if np.isinf(pred.keypoints).any():
        t = int(np.argwhere(np.isinf(pred.keypoints))[0, 0])
        raise PoseFileError(f"{pred_path}: field 'keypoints' holds inf at frame {t} (missing "
                            "frames must be NaN)")
    if pred.n_frames != gt.n_frames:
        raise InputError(f"{pred_path} has {pred.n_frames} frames, {gt_path} has {gt.n_frames}; "
                         "evaluate a tracking of the whole ground-truth sequence")
    names = [n for n in gt.keypoint_names if n in pred.keypoint_names]
    if not names:
        raise InputError(f"{pred_path} and {gt_path} share no keypoint names "
                         f"({list(pred.keypoint_names)[:4]}... vs "
                         f"{list(gt.keypoint_names)[:4]}...)")
    ip = [pred.keypoint_names.index(n) for n in names]
    ig = [gt.keypoint_names.index(n) for n in names]
    xp, xg = pred.keypoints[:, ip] * 100.0, gt.keypoints[:, ig] * 100.0  # cm
    ok = pred.valid & np.isfinite(xp).all(axis=(1, 2))  # flagged valid and finite
    if not ok.any():
        raise InputError(f"{pred_path}: no tracked frame to evaluate (all {pred.n_frames} "
                         "frames are missing)")
    err = np.linalg.norm(xp[ok] - xg[ok], axis=-1)  # (n_ok, k)
    per_joint = err.mean(axis=0)
    jp, jg = _jitter(xp, ok), _jitter(xg, np.ones_like(ok))
    return {
        "prediction": str(pred_path),
        "groundtruth": str(gt_path),
        "frames": int(pred.n_frames),
        "frames_tracked": int(ok.sum()),
        "mpjpe_cm": float(err.mean()),
        "median_error_cm": float(np.median(err)),
        "jitter_cm_per_frame2": float(np.nanmean(jp)) if np.isfinite(jp).any() else None,
        "jitter_groundtruth_cm_per_frame2": float(np.nanmean(jg)) if np.isfinite(jg).any()
        else None,
        "joints": {n: {"mpjpe_cm": float(per_joint[i]),
                       "jitter_cm_per_frame2": None if np.isnan(jp[i]) else float(jp[i])}
                   for i, n in enumerate(names)},
    }


def _fmt(v) -> str:
    return "-" if v is None else f"{v:8.2f}"


def format_table(res: dict) -> str:
    lines = [f"{'joint':<12} {'MPJPE cm':>8} {'jitter':>8}"]
    for n, r in res["joints"].items():
        lines.append(f"{n:<12} {_fmt(r['mpjpe_cm'])} {_fmt(r['jitter_cm_per_frame2'])}")
    lines.append(f"{'all':<12} {_fmt(res['mpjpe_cm'])} {_fmt(res['jitter_cm_per_frame2'])}")
    lines.append(f"tracked {res['frames_tracked']} of {res['frames']} frames; ground-truth "
                 f"jitter {_fmt(res['jitter_groundtruth_cm_per_frame2']).strip()} cm/frame^2")
    return "\n".join(lines)
