"""Event metrics of a cell on a sequence whose ground truth says what the cameras could see
(the independent test world's ``groundtruth.npz``: ``occluded_fraction``, ``visible``).

Issues 17 and 18 ask for numbers that a mean error hides:

* **recovery after an occlusion** (issue 17: "back within 5 frames of the shirt being visible
  again in both cameras"): an occlusion event is a run of frames in which some camera sees at
  most half of the body (``occluded_fraction >= OCCLUDED``) or none of it (``visible`` false);
  the shirt is visible again at the first later frame where every camera sees the body with
  ``occluded_fraction <= CLEAR``; the tracker is back at the first frame from there on that is
  flagged valid and within ``recover_cm`` of the truth. Reported per event as the number of
  frames from visible-again to back (0 = back at once), None if never back in the sequence;
* **frames with head and both hands in view** (issue 18: "<= 5 cm on the frames where head and
  both hands are visible in both views"): the head and hand keypoints project inside both
  images (``MARGIN_PX`` from the border) and no camera's view of the body is occluded by more
  than ``CLEAR``. Self-occlusion (a hand behind the torso) is not modelled: the ground truth
  holds no per-keypoint depth test;
* **lamp changes** (issue 17 item 2: "measured frame by frame across the switch"): a lamp
  event is a run of frames over which some lamp's level (``lamp_levels``) keeps changing (a
  switch: one frame; a dimming: tens) by at least ``LAMP_CHANGE`` in all; reported per event
  as the mean error over the ``LAMP_WINDOW`` frames before it and the ``LAMP_WINDOW`` frames
  from its last changing frame on, the share of those frames flagged valid, and the frames
  from the change's end until the tracker is back (valid and within ``recover_cm``);
* **blobs off the body** (issue 18: "never a blob on a static prop in the tracked set"): frames
  in which a triangulated skin point the tracker fed into its filter lies more than
  ``OFF_BODY_M`` from every ground-truth head and hand keypoint. Static props in the test world
  stand >= 0.5 m from the actor, a hand triangulated from an 11 cm baseline at 2 m has a depth
  error of a few cm: 0.3 m separates the two.
"""

from __future__ import annotations

import numpy as np

RECOVER_CM = 10.0  # "back": valid and within 10 cm (twice the issues' "good" 5 cm)
RECOVER_FRAMES = 5  # issue 17: back within 5 frames
OCCLUDED = 0.5  # share of the body's pixels hidden: the camera has lost the shirt
CLEAR = 0.05  # share hidden at most for the shirt to count as visible again
MARGIN_PX = 2.0
OFF_BODY_M = 0.3
SKIN_KEYPOINTS = ("head", "l_hand", "r_hand")
LAMP_CHANGE = 0.3  # total level change (0..1) of a lamp that makes a lamp event
LAMP_WINDOW = 10  # frames before / after a lamp event averaged


def _runs(flags: np.ndarray) -> list[tuple[int, int]]:
    """(first, last) index of each maximal run of True in ``flags``."""
    edges = np.diff(np.r_[0, np.asarray(flags, np.int8), 0])
    return list(zip(np.flatnonzero(edges == 1).tolist(),
                    (np.flatnonzero(edges == -1) - 1).tolist(), strict=True))


def occlusion_events(occluded: np.ndarray, visible: np.ndarray) -> list[tuple[int, int, int]]:
    """(first occluded frame, last occluded frame, visible-again frame or -1) per event, from
    ``occluded`` (T, n_cams) shares and ``visible`` (T, n_cams) flags (module docstring); a
    loss before the shirt was visible again belongs to the event before it."""
    lost = (occluded >= OCCLUDED).any(axis=1) | ~visible.all(axis=1)
    clear = (occluded <= CLEAR).all(axis=1) & visible.all(axis=1)
    events, resume = [], 0
    for start, end in _runs(lost):
        if start < resume:
            continue
        again = next((u for u in range(end + 1, len(lost)) if clear[u]), -1)
        events.append((start, end, again))
        resume = again if again >= 0 else len(lost)
    return events


def recovery(frame_err: np.ndarray, valid: np.ndarray, events, recover_cm: float) -> list[dict]:
    """Per occlusion event: frames from visible-again until the tracker is back (valid and
    within ``recover_cm``), or None if it never is (or the shirt never reappears)."""
    out = []
    for start, end, again in events:
        back = None
        if again >= 0:
            ok = valid[again:] & np.isfinite(frame_err[again:]) & (frame_err[again:] < recover_cm)
            hit = np.flatnonzero(ok)
            back = int(hit[0]) if hit.size else None
        out.append({"occluded": [int(start), int(end)],
                    "visible_again": None if again < 0 else int(again),
                    "frames_to_recover": back})
    return out


def lamp_events(levels: np.ndarray, min_change: float = LAMP_CHANGE) -> list[tuple[int, int]]:
    """(first, last) frame of each run of frames whose lamp levels differ from the previous
    frame's, kept when some lamp changed by at least ``min_change`` over the run; ``levels``
    (T, n_lamps)."""
    levels = np.asarray(levels, float)
    moving = np.r_[False, (np.abs(np.diff(levels, axis=0)) > 1e-9).any(axis=1)]
    return [(a, b) for a, b in _runs(moving)
            if np.abs(levels[b] - levels[a - 1]).max() >= min_change]


def lamp_change_errors(frame_err: np.ndarray, valid: np.ndarray, events, recover_cm: float,
                       window: int = LAMP_WINDOW) -> list[dict]:
    """Per lamp event: mean error (cm) over the ``window`` frames before and from its last
    changing frame on, the share of the latter flagged valid, and the frames from there until
    the tracker is back (valid and within ``recover_cm``; None if never)."""
    def mean(x):
        x = x[np.isfinite(x)]
        return float(x.mean()) if x.size else None

    out = []
    for start, end in events:
        before = frame_err[max(0, start - window):start]
        after = slice(end, min(len(frame_err), end + window))
        ok = valid[end:] & np.isfinite(frame_err[end:]) & (frame_err[end:] < recover_cm)
        hit = np.flatnonzero(ok)
        out.append({"frames": [int(start), int(end)], "cm_before": mean(before),
                    "cm_after": mean(frame_err[after]),
                    "valid_after": float(valid[after].mean()),
                    "frames_to_recover": int(hit[0]) if hit.size else None})
    return out


def skin_in_view(keypoints: np.ndarray, names, cameras, occluded: np.ndarray) -> np.ndarray:
    """(T,) bool: head and both hands project inside every image and no camera's view of the
    body is occluded by more than ``CLEAR`` (module docstring)."""
    import jax.numpy as jnp

    from jaxmocap.camera import project

    idx = [list(names).index(k) for k in SKIN_KEYPOINTS]
    pts = jnp.asarray(keypoints[:, idx])  # (T, 3, 3)
    ok = (occluded <= CLEAR).all(axis=1)
    for cam in cameras:
        w, h = cam.width, cam.height
        uv = np.asarray(project(cam, pts))
        inside = ((uv[..., 0] >= MARGIN_PX) & (uv[..., 0] <= w - 1 - MARGIN_PX)
                  & (uv[..., 1] >= MARGIN_PX) & (uv[..., 1] <= h - 1 - MARGIN_PX))
        ok &= inside.all(axis=1)
    return ok


def blobs_off_body(points: np.ndarray, valid: np.ndarray, keypoints: np.ndarray,
                   names) -> np.ndarray:
    """(T,) bool: some valid triangulated point of ``points`` (T, k, 3) lies farther than
    ``OFF_BODY_M`` from every ground-truth head / hand keypoint."""
    idx = [list(names).index(k) for k in SKIN_KEYPOINTS]
    skin = keypoints[:, idx]  # (T, 3, 3)
    d = np.linalg.norm(points[:, :, None, :] - skin[:, None, :, :], axis=-1).min(axis=2)
    return (valid & (d > OFF_BODY_M)).any(axis=1)


def world_metrics(gt: dict, frame_err: np.ndarray, valid: np.ndarray, *, recover_cm: float,
                  good_cm: float, cameras=None,
                  blobs: tuple[np.ndarray, np.ndarray] | None = None) -> dict | None:
    """The event metrics of one cell, or None when ``gt`` (the arrays of ``groundtruth.npz``)
    has no ``occluded_fraction`` / ``visible`` (footage without visibility ground truth).

    ``frame_err`` (T,) cm, ``valid`` (T,) the tracker's flags; ``cameras`` for the
    head-and-hands-in-view frames; ``blobs`` = (points (T, k, 3) m, valid (T, k)) for the
    off-body count (stereo filter only)."""
    if "occluded_fraction" not in gt or "visible" not in gt:
        return None
    occ = np.asarray(gt["occluded_fraction"], float)
    vis = np.asarray(gt["visible"], bool)
    rec = recovery(frame_err, valid, occlusion_events(occ, vis), recover_cm)
    frames = [r["frames_to_recover"] for r in rec]
    m = {"recover_cm": recover_cm, "occlusions": rec,
         # share of events back within RECOVER_FRAMES (None: no occlusion in the sequence)
         "recovered_in_time": (None if not rec else float(np.mean(
             [f is not None and f <= RECOVER_FRAMES for f in frames])))}
    if "lamp_levels" in gt:
        lamps = lamp_change_errors(frame_err, valid, lamp_events(gt["lamp_levels"]), recover_cm)
        m["lamp_changes"] = lamps
        for key in ("cm_before", "cm_after"):
            m[f"lamp_{key}"] = (None if not lamps or any(e[key] is None for e in lamps)
                                else float(np.mean([e[key] for e in lamps])))
    names = [str(n) for n in gt["keypoint_names"]]
    if cameras is not None and all(k in names for k in SKIN_KEYPOINTS):
        inview = skin_in_view(np.asarray(gt["keypoints"]), names, cameras, occ)
        sel = inview & np.isfinite(frame_err)
        m["frames_skin_in_view"] = int(inview.sum())
        m["mean_cm_skin_in_view"] = float(frame_err[sel].mean()) if sel.any() else None
        m["below_good_skin_in_view"] = (float((frame_err[sel] < good_cm).mean())
                                        if sel.any() else None)
    if blobs is not None and all(k in names for k in SKIN_KEYPOINTS):
        off = blobs_off_body(np.asarray(blobs[0]), np.asarray(blobs[1], bool),
                             np.asarray(gt["keypoints"]), names)
        m["frames_blob_off_body"] = int(off.sum())
    return m
