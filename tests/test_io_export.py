"""Exports: NPZ/CSV round trip, TRC parsed by hand against the keypoints (Y-up mapping checked
on known vectors), BVH loaded by the independent PyPI `bvh` parser, keypoints vs FK."""

import csv

import jax.numpy as jnp
import numpy as np
import pytest
from bvh import Bvh

from jaxmocap.body import default_body, fk, keypoints
from jaxmocap.io.atomic import AtomicFiles
from jaxmocap.io.export import (
    PoseFileError,
    fill_missing,
    load_track,
    pose_track,
    write_bvh,
    write_csv,
    write_exports,
    write_npz,
    write_trc,
)

FPS = 25.0


@pytest.fixture(scope="module")
def track():
    model = default_body()
    rng = np.random.default_rng(1)
    q = np.zeros((4, model.n_dof))
    q[:, :3] = rng.normal(0, 0.3, (4, 3))
    q[:, 3:6] = rng.normal(0, 0.4, (4, 3))
    q[:, 6:] = rng.uniform(-0.5, 0.5, (4, model.n_dof - 6))
    valid = np.array([True, False, True, True])
    return model, q, pose_track(model, q, valid, FPS)


def test_pose_track_keypoints_and_missing(track):
    model, q, tr = track
    assert tr.valid.tolist() == [True, False, True, True]
    assert np.isnan(tr.q[1]).all() and np.isnan(tr.keypoints[1]).all()
    for t in (0, 2, 3):
        ref = np.asarray(keypoints(model, jnp.asarray(q[t])))
        np.testing.assert_allclose(tr.keypoints[t], ref, atol=1e-12)
    # the pelvis keypoint sits on the root link's origin offset: check one against fk directly
    T = np.asarray(fk(model.chain, jnp.asarray(q[0])))
    i = model.keypoint_names.index("pelvis")
    link = int(model.keypoint_link[i])
    np.testing.assert_allclose(tr.keypoints[0, i],
                               T[link, :3, :3] @ np.asarray(model.keypoint_offset[i])
                               + T[link, :3, 3], atol=1e-12)
    filled = fill_missing(tr.q, tr.valid)
    np.testing.assert_array_equal(filled[1], q[0])
    np.testing.assert_array_equal(filled[3], q[3])


def test_npz_and_csv_round_trip(track, tmp_path):
    _, _, tr = track
    for name, writer in (("p.npz", write_npz), ("p.csv", write_csv)):
        writer(tmp_path / name, tr)
        back = load_track(tmp_path / name)
        np.testing.assert_array_equal(back.valid, tr.valid)
        np.testing.assert_allclose(back.keypoints, tr.keypoints, atol=1e-6, equal_nan=True)
        np.testing.assert_allclose(back.q, tr.q, atol=1e-6, equal_nan=True)
        assert back.keypoint_names == tr.keypoint_names and back.dof_names == tr.dof_names
        assert back.fps == pytest.approx(FPS)
    with open(tmp_path / "p.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    assert rows[1]["valid"] == "0" and rows[1]["head_z"] == ""
    assert float(rows[2]["head_z"]) == pytest.approx(tr.keypoints[2, 3, 2], abs=1e-6)
    assert float(rows[3]["q_l_elbow"]) == pytest.approx(tr.q[3, 15], abs=1e-6)


def test_trc_layout_and_y_up(track, tmp_path):
    _, _, tr = track
    write_trc(tmp_path / "p.trc", tr)
    lines = (tmp_path / "p.trc").read_text().split("\n")
    assert lines[0].split("\t") == ["PathFileType", "4", "(X/Y/Z)", "p.trc"]
    meta = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
    assert meta["NumFrames"] == "4" and meta["NumMarkers"] == "12" and meta["Units"] == "m"
    assert float(meta["DataRate"]) == FPS
    names = [c for c in lines[3].split("\t")[2:] if c]
    assert names == list(tr.keypoint_names)
    assert lines[4].split("\t")[2:5] == ["X1", "Y1", "Z1"] and lines[5] == ""
    data = [ln.split("\t") for ln in lines[6:] if ln]
    assert [r[0] for r in data] == ["1", "2", "3", "4"]
    assert data[1][2:] == [""] * 36  # missing frame = empty fields
    xyz = np.array([float(v) for v in data[0][2:]]).reshape(12, 3)
    w = tr.keypoints[0]
    # OpenSim Y up: X forward = our x, Y up = our z, Z = our -y
    np.testing.assert_allclose(xyz, np.stack([w[:, 0], w[:, 2], -w[:, 1]], -1), atol=1e-6)


def test_bvh_loads_with_independent_parser(track, tmp_path):
    model, q, tr = track
    write_bvh(tmp_path / "p.bvh", model, tr)
    ref = Bvh((tmp_path / "p.bvh").read_text())
    assert ref.nframes == 4 and ref.frame_time == pytest.approx(1 / FPS)
    assert ref.get_joints_names()[0] == "pelvis"
    elbow = ref.frame_joint_channels(2, "l_forearm", ["Zrotation"])[0]
    assert elbow == pytest.approx(np.degrees(q[2, 15]), abs=1e-4)
    # the missing frame 1 repeats frame 0
    assert ref.frame_joint_channels(1, "l_forearm", ["Zrotation"])[0] == pytest.approx(
        np.degrees(q[0, 15]), abs=1e-4)
    root = ref.frame_joint_channels(3, "pelvis", ["Xposition", "Yposition", "Zposition"])
    assert np.isfinite(root).all()


def test_write_exports_group(track, tmp_path):
    model, _, tr = track
    with AtomicFiles() as files:
        paths = write_exports(files, tmp_path / "out", model, tr, extra=np.arange(4))
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(p.name for p in paths)
    with np.load(tmp_path / "out" / "poses.npz") as z:
        np.testing.assert_array_equal(z["extra"], np.arange(4))


def test_load_errors(tmp_path):
    with pytest.raises(PoseFileError, match="no such file"):
        load_track(tmp_path / "nope.npz")
    (tmp_path / "x.txt").write_text("")
    with pytest.raises(PoseFileError, match="expected .npz or .csv"):
        load_track(tmp_path / "x.txt")
    (tmp_path / "bad.csv").write_text("a,b\n1,2\n")
    with pytest.raises(PoseFileError, match="line 1"):
        load_track(tmp_path / "bad.csv")
    (tmp_path / "short.csv").write_text("frame,time_s,valid,a_x,a_y,a_z\n0,0,1,1,2\n")
    with pytest.raises(PoseFileError, match="line 2: 5 fields"):
        load_track(tmp_path / "short.csv")
    np.savez(tmp_path / "k.npz", keypoints=np.zeros((3, 2)))
    with pytest.raises(PoseFileError, match="field 'keypoints' has shape"):
        load_track(tmp_path / "k.npz")
    (tmp_path / "c.npz").write_bytes(b"not a zip")
    with pytest.raises(PoseFileError, match="c.npz: cannot read: not an .npz archive"):
        load_track(tmp_path / "c.npz")
