"""`jaxmocap eval`: MPJPE and jitter on constructed cases with known answers; refusals."""

import json

import numpy as np
import pytest
from test_cli import assert_refused, run_cli

from jaxmocap.body import default_body
from jaxmocap.io.export import pose_track, write_csv, write_npz

T = 6


@pytest.fixture(scope="module")
def gt_track():
    model = default_body()
    rng = np.random.default_rng(4)
    q = np.zeros((T, model.n_dof))
    q[:, 2] = 0.9 + 0.05 * np.arange(T) ** 2 / T  # accelerating upwards
    q[:, 6:] = rng.uniform(-0.3, 0.3, (T, model.n_dof - 6))
    return pose_track(model, q, None, 30.0)


def save_gt(path, tr, **override):
    d = dict(q=tr.q, keypoints=tr.keypoints, times=tr.times, dof_names=np.array(tr.dof_names),
             keypoint_names=np.array(tr.keypoint_names))
    d.update(override)
    np.savez(path, **d)
    return path


def test_known_offset(gt_track, tmp_path, capsys):
    save_gt(tmp_path / "groundtruth.npz", gt_track)
    offset = np.array([0.012, -0.016, 0.0])  # |offset| = 2 cm
    valid = np.ones(T, bool)
    valid[3] = False
    kp = gt_track.keypoints + offset
    kp[3] += 1.0  # a rejected estimate, 1.7 m off: in the file, not scored
    pred = gt_track._replace(keypoints=kp, valid=valid)
    write_npz(tmp_path / "p.npz", pred)
    write_csv(tmp_path / "p.csv", pred)
    for name in ("p.npz", "p.csv"):
        out = tmp_path / f"{name}.json"
        rc, stdout, err = run_cli(capsys, "eval", tmp_path / name, tmp_path, "--out", out)
        assert rc == 0 and err == []
        res = json.loads(out.read_text())
        assert res["frames"] == T and res["frames_tracked"] == T - 1
        assert res["mpjpe_cm"] == pytest.approx(2.0, abs=1e-4)
        assert all(j["mpjpe_cm"] == pytest.approx(2.0, abs=1e-4) for j in res["joints"].values())
        # the second difference ignores a constant offset: jitter over the tracked triples
        # (0,1,2) only equals the ground truth's there; the ground truth's uses all frames
        x = gt_track.keypoints * 100
        acc = np.linalg.norm(x[2:] - 2 * x[1:-1] + x[:-2], axis=-1)
        assert res["jitter_cm_per_frame2"] == pytest.approx(acc[0].mean(), abs=1e-4)
        assert res["jitter_groundtruth_cm_per_frame2"] == pytest.approx(acc.mean(), abs=1e-9)
        assert "all" in stdout and "tracked 5 of 6 frames" in stdout


def test_refusals(gt_track, tmp_path, capsys):
    gt = save_gt(tmp_path / "gt.npz", gt_track)
    out = tmp_path / "e.json"
    write_npz(tmp_path / "short.npz", gt_track._replace(
        q=gt_track.q[:4], keypoints=gt_track.keypoints[:4], valid=gt_track.valid[:4]))
    assert_refused(capsys, "has 4 frames", "eval", tmp_path / "short.npz", gt, "--out", out,
                   leaves=[out])
    kp = gt_track.keypoints.copy()
    kp[2, 1, 0] = np.nan
    bad = save_gt(tmp_path / "gtnan.npz", gt_track, keypoints=kp)
    write_npz(tmp_path / "p.npz", gt_track)
    assert_refused(capsys, "gtnan.npz: field 'keypoints' holds NaN/inf (first at frame 2)", "eval",
                   tmp_path / "p.npz", bad, "--out", out, leaves=[out])
    kp = gt_track.keypoints.copy()
    kp[1, 0, 0] = np.inf
    write_npz(tmp_path / "pinf.npz", gt_track._replace(keypoints=kp))
    assert_refused(capsys, "holds inf at frame 1", "eval", tmp_path / "pinf.npz", gt, "--out",
                   out, leaves=[out])
    save_gt(tmp_path / "other.npz", gt_track,
            keypoint_names=np.array([f"x{i}" for i in range(12)]))
    assert_refused(capsys, "share no keypoint names", "eval", tmp_path / "p.npz",
                   tmp_path / "other.npz", leaves=[out])
    none = gt_track._replace(valid=np.zeros(T, bool),
                             keypoints=np.full_like(gt_track.keypoints, np.nan))
    write_npz(tmp_path / "none.npz", none)
    assert_refused(capsys, "no tracked frame to evaluate", "eval", tmp_path / "none.npz", gt,
                   leaves=[out])
    assert_refused(capsys, "missing.npz: no such file", "eval", tmp_path / "missing.npz", gt)
    assert_refused(capsys, "field 'keypoints' missing", "eval", tmp_path / "p.npz",
                   _no_kp(tmp_path))
    assert_refused(capsys, "is a folder", "eval", tmp_path / "p.npz", gt, "--out", tmp_path)


def _no_kp(tmp_path):
    np.savez(tmp_path / "nokp.npz", q=np.zeros((T, 3)))
    return tmp_path / "nokp.npz"
