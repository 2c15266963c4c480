"""Event metrics of the independent test world (jaxmocap.experiment.world_metrics): occlusion
events and recovery, head and hands in view (oracle: cv2.projectPoints), blobs off the body,
and the metrics of a real test-world sequence through the experiment's cell_metrics."""

import cv2
import numpy as np

from jaxmocap.camera import look_at
from jaxmocap.experiment import world_metrics as wm

NAMES = ["pelvis", "head", "l_hand", "r_hand"]


def test_occlusion_events_and_recovery_count_frames_from_visible_again():
    T = 40
    occ = np.zeros((T, 2))
    occ[10:15, 0] = [0.2, 0.6, 0.9, 0.7, 0.3]  # lost 11..13, clear again at 15
    occ[15, 0] = 0.0
    vis = np.ones((T, 2), bool)
    vis[25:28, 1] = False  # left the second view 25..27; visible again at 28
    occ[28, 1] = 0.1  # ... but 10% hidden at 28: clear at 29
    events = wm.occlusion_events(occ, vis)
    assert events == [(11, 13, 15), (25, 27, 29)]
    err = np.full(T, 30.0)
    err[:11] = 3.0
    err[18:] = 4.0  # back 3 frames after 15
    valid = np.ones(T, bool)
    valid[29:31] = False  # flagged invalid at 29, 30: back at 31, 2 frames after 29
    rec = wm.recovery(err, valid, events, recover_cm=10.0)
    assert [r["frames_to_recover"] for r in rec] == [3, 2]
    err[18:] = 12.0  # never within 10 cm
    rec = wm.recovery(err, valid, events, recover_cm=10.0)
    assert [r["frames_to_recover"] for r in rec] == [None, None]
    # an occlusion that lasts to the end: no visible-again frame, never recovered
    occ2 = np.zeros((10, 2))
    occ2[6:, :] = 1.0
    ev = wm.occlusion_events(occ2, np.ones((10, 2), bool))
    assert ev == [(6, 9, -1)]
    assert wm.recovery(np.zeros(10), np.ones(10, bool), ev, 10.0)[0]["frames_to_recover"] is None


def test_skin_in_view_agrees_with_opencv_projection():
    cams = [look_at((x, -3.0, 1.5), (0.0, 0.0, 1.2), width=160, height=120, fx=150.0)
            for x in (-0.1, 0.1)]
    rng = np.random.default_rng(0)
    T = 200
    kp = np.zeros((T, 4, 3))
    kp[:, 1:] = rng.uniform([-1.6, -0.5, 0.2], [1.6, 0.5, 2.2], size=(T, 3, 3))
    occ = np.zeros((T, 2))
    occ[::17, 1] = 0.2  # partly occluded frames never count
    got = wm.skin_in_view(kp, NAMES, cams, occ)
    want = occ.max(axis=1) <= wm.CLEAR
    for cam in cams:
        R, t = np.asarray(cam.R, float), np.asarray(cam.t, float)
        uv = cv2.projectPoints(kp[:, 1:].reshape(-1, 3), cv2.Rodrigues(R)[0], t,
                               np.asarray(cam.K, float), np.asarray(cam.dist, float))[0]
        uv = uv.reshape(T, 3, 2)
        m = wm.MARGIN_PX
        want &= ((uv[..., 0] >= m) & (uv[..., 0] <= 159 - m) & (uv[..., 1] >= m)
                 & (uv[..., 1] <= 119 - m)).all(axis=1)
    assert 20 < want.sum() < T - 20  # both outcomes occur
    np.testing.assert_array_equal(got, want)


def test_blobs_off_body_counts_points_far_from_head_and_hands():
    T = 3
    kp = np.zeros((T, 4, 3))
    kp[:, 1] = [0.0, 0.0, 1.7]
    kp[:, 2] = [0.4, 0.0, 1.0]
    kp[:, 3] = [-0.4, 0.0, 1.0]
    pts = np.repeat(kp[:, None, 1:], 1, axis=1)[:, 0].copy()  # (T, 3, 3): on the body
    valid = np.ones((T, 3), bool)
    pts[1, 2] = [-0.4, 0.35, 1.0]  # 35 cm from the right hand: off the body
    pts[2, 1] = [2.0, 1.0, 0.5]  # a prop ... not fed into the filter
    valid[2, 1] = False
    np.testing.assert_array_equal(wm.blobs_off_body(pts, valid, kp, NAMES),
                                  [False, True, False])


def test_world_metrics_none_without_visibility_ground_truth():
    assert wm.world_metrics({"keypoints": np.zeros((2, 4, 3))}, np.zeros(2), np.ones(2, bool),
                            recover_cm=10.0, good_cm=5.0) is None


def test_lamp_events_switch_and_dimming():
    """A switch is a one-frame event, a dimming the run of its changing frames; a flicker
    smaller than LAMP_CHANGE is none. Errors are averaged over the windows around each."""
    T = 60
    lv = np.ones((T, 2))
    lv[20:, 0] = 0.0  # lamp 0 switched off at frame 20
    lv[35:46, 1] = np.linspace(0.95, 0.45, 11)  # lamp 1 dimmed over frames 35..45
    lv[46:, 1] = 0.45
    lv[52, 1] = 0.5  # a 0.05 flicker at 52 and back at 53: no event
    ev = wm.lamp_events(lv)
    assert ev == [(20, 20), (35, 45)]
    err = np.full(T, 2.0)
    err[20:24] = 40.0  # lost for 4 frames after the switch
    valid = np.ones(T, bool)
    valid[20:23] = False
    out = wm.lamp_change_errors(err, valid, ev, recover_cm=10.0, window=10)
    assert out[0]["cm_before"] == 2.0
    assert out[0]["cm_after"] == (4 * 40.0 + 6 * 2.0) / 10
    assert out[0]["valid_after"] == 0.7
    assert out[0]["frames_to_recover"] == 4  # frame 24
    assert out[1]["frames"] == [35, 45] and out[1]["frames_to_recover"] == 0
    gt = {"occluded_fraction": np.zeros((T, 1)), "visible": np.ones((T, 1), bool),
          "keypoints": np.zeros((T, 4, 3)), "keypoint_names": np.array(NAMES),
          "lamp_levels": lv}
    m = wm.world_metrics(gt, err, valid, recover_cm=10.0, good_cm=5.0)
    assert m["lamp_cm_before"] == 2.0
    assert m["lamp_cm_after"] == ((4 * 40.0 + 6 * 2.0) / 10 + 2.0) / 2
