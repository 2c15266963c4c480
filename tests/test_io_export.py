"""Exports: NPZ/CSV round trip (columns named with units, every frame's estimate with its
validity and diagnostics, the CSV read back by the standard library's csv module), TRC read
by a strict reader that follows OpenSim's column rule (NaN for invalid and untracked markers,
Y-up mapping checked on known vectors), C3D read by the independent `c3d` package and by
ezc3d (written with ezc3d; invalid points residual -1), BVH loaded by the independent PyPI
`bvh` parser and bvhio (every estimate), keypoints vs FK. Blender / OpenSim:
test_io_interop.py."""

import csv
import warnings

import bvhio
import c3d
import ezc3d
import jax.numpy as jnp
import numpy as np
import pytest
from bvh import Bvh

from jaxmocap.body import default_body, fk, keypoints
from jaxmocap.io.atomic import AtomicFiles
from jaxmocap.io.export import (
    PoseFileError,
    csv_header,
    fill_missing,
    load_track,
    pose_track,
    write_bvh,
    write_c3d,
    write_csv,
    write_exports,
    write_npz,
    write_trc,
)

FPS = 25.0
N = 5
VALID = [True, False, True, True, False]  # frame 1: an invalid estimate; frame 4: none
DIAG_NAMES = ("agreement", "patches")


@pytest.fixture(scope="module")
def track():
    model = default_body()
    rng = np.random.default_rng(1)
    q = np.zeros((N, model.n_dof))
    q[:, :3] = rng.normal(0, 0.3, (N, 3))
    q[:, 3:6] = rng.normal(0, 0.4, (N, 3))
    q[:, 6:] = rng.uniform(-0.5, 0.5, (N, model.n_dof - 6))
    q[4] = np.nan
    diag = rng.uniform(0, 30, (N, 2))
    diag[4, 0] = np.nan  # a frame without that signal
    return model, q, pose_track(model, q, np.array(VALID), FPS, diag, DIAG_NAMES)


def test_pose_track_keeps_every_estimate(track):
    model, q, tr = track
    assert tr.valid.tolist() == VALID
    assert np.isnan(tr.q[4]).all() and np.isnan(tr.keypoints[4]).all()  # no estimate
    np.testing.assert_array_equal(tr.q[1], q[1])  # an invalid frame keeps its estimate
    assert tr.diagnostic_names == DIAG_NAMES and tr.diagnostics.shape == (N, 2)
    # a NaN row is never valid, whatever the flag said; valid defaults to "has an estimate"
    assert not pose_track(model, q, np.ones(N, bool), FPS).valid[4]
    assert pose_track(model, q, None, FPS).valid.tolist() == [True] * 4 + [False]
    for t in (0, 1, 2, 3):
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
    with pytest.raises(ValueError, match="diagnostics must be"):
        pose_track(model, q, None, FPS, np.zeros((N, 3)), DIAG_NAMES)


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
        assert back.dof_units == tr.dof_units
        assert back.diagnostic_names == DIAG_NAMES
        np.testing.assert_allclose(back.diagnostics, tr.diagnostics, rtol=1e-5,
                                   equal_nan=True)
    with open(tmp_path / "p.csv", newline="") as f:
        rows = list(csv.DictReader(f))
    # the rejected frame: its estimate beside valid 0; the frame without one: empty fields
    assert rows[1]["valid"] == "0"
    assert float(rows[1]["head_z_m"]) == pytest.approx(tr.keypoints[1, 3, 2], abs=1e-6)
    assert float(rows[1]["q_l_elbow_rad"]) == pytest.approx(tr.q[1, 15], abs=1e-6)
    assert rows[4]["valid"] == "0" and rows[4]["head_z_m"] == "" and rows[4]["q_root_tx_m"] == ""
    assert float(rows[1]["diag_patches"]) == pytest.approx(tr.diagnostics[1, 1], rel=1e-5)
    assert rows[4]["diag_agreement"] == ""
    assert float(rows[2]["head_z_m"]) == pytest.approx(tr.keypoints[2, 3, 2], abs=1e-6)
    assert float(rows[3]["q_l_elbow_rad"]) == pytest.approx(tr.q[3, 15], abs=1e-6)
    # every column says its unit: metres for positions, radians for angles, the root's
    # rotation named as the rotation vector it is
    header = list(rows[0])
    assert header[:6] == ["frame", "time_s", "valid", "pelvis_x_m", "pelvis_y_m", "pelvis_z_m"]
    q_cols = [c for c in header if c.startswith("q_")]
    assert q_cols[:6] == ["q_root_tx_m", "q_root_ty_m", "q_root_tz_m", "q_root_rotvec_x_rad",
                          "q_root_rotvec_y_rad", "q_root_rotvec_z_rad"]
    assert all(c.endswith("_rad") for c in q_cols[6:]) and len(q_cols) == len(tr.dof_names)
    assert header == csv_header(tr) and header[-2:] == ["diag_agreement", "diag_patches"]
    assert float(rows[2]["q_root_rotvec_y_rad"]) == pytest.approx(tr.q[2, 4], abs=1e-6)
    with np.load(tmp_path / "p.npz") as z:
        assert list(z["dof_units"][:7]) == ["m", "m", "m", "rad", "rad", "rad", "rad"]
        assert list(z["diagnostic_names"]) == list(DIAG_NAMES)
        np.testing.assert_array_equal(z["valid"], VALID)
        np.testing.assert_array_equal(z["q"][1], tr.q[1])


def test_csv_without_units_still_loads(tmp_path):
    """CSVs written before the columns carried units (``<kp>_x``, ``q_<dof>``) still load."""
    (tmp_path / "old.csv").write_text("frame,time_s,valid,head_x,head_y,head_z,q_root_tx\n"
                                      "0,0.0,1,0.1,0.2,1.7,0.5\n1,0.04,0,,,,\n")
    back = load_track(tmp_path / "old.csv")
    assert back.keypoint_names == ("head",) and back.dof_names == ("root_tx",)
    np.testing.assert_allclose(back.keypoints[0, 0], [0.1, 0.2, 1.7])
    assert back.valid.tolist() == [True, False] and back.fps == pytest.approx(25.0)


def test_track_without_diagnostics_and_earlier_files_load(track, tmp_path):
    """A track without diagnostics writes neither NPZ keys nor CSV columns for them; an NPZ
    of an earlier version (NaN rows where invalid, no diagnostics) reads as it did."""
    model, q, tr = track
    plain = pose_track(model, q, np.array(VALID), FPS)
    write_csv(tmp_path / "p.csv", plain)
    write_npz(tmp_path / "p.npz", plain)
    assert not any(c.startswith("diag_") for c in csv_header(plain))
    with np.load(tmp_path / "p.npz") as z:
        assert "diagnostics" not in z.files
    for name in ("p.csv", "p.npz"):
        back = load_track(tmp_path / name)
        assert back.diagnostics is None and back.diagnostic_names == ()
        np.testing.assert_allclose(back.q, plain.q, atol=1e-6, equal_nan=True)
    old_kp = np.where(np.array(VALID)[:, None, None], tr.keypoints, np.nan)
    np.savez(tmp_path / "old.npz", q=np.where(np.array(VALID)[:, None], tr.q, np.nan),
             keypoints=old_kp, valid=np.array(VALID), fps=FPS,
             keypoint_names=np.array(tr.keypoint_names))
    back = load_track(tmp_path / "old.npz")
    assert back.valid.tolist() == VALID and back.diagnostics is None


def read_trc_strict(path):
    """A TRC reader with OpenSim's rules (TRCFileAdapter): the header keys and values, the
    marker names on line 4, then every non-empty data line holding exactly
    ``2 + 3 * NumMarkers`` tab-separated fields, each a number (``NaN`` = missing marker)."""
    lines = path.read_text().split("\n")
    meta = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
    n_markers, n_frames = int(meta["NumMarkers"]), int(meta["NumFrames"])
    names = [c for c in lines[3].split("\t")[2:] if c]
    assert len(names) == n_markers
    rows = []
    for ln in lines[6:]:
        if not ln:
            continue
        fields = ln.split("\t")
        assert len(fields) == 2 + 3 * n_markers, f"{len(fields)} fields: {ln!r}"
        rows.append([float(v) for v in fields])
    assert len(rows) == n_frames
    data = np.array(rows)
    return meta, names, data[:, 0], data[:, 1], data[:, 2:].reshape(n_frames, n_markers, 3)


def test_trc_layout_and_y_up(track, tmp_path):
    _, _, tr = track
    write_trc(tmp_path / "p.trc", tr)
    meta, names, frame, time, xyz = read_trc_strict(tmp_path / "p.trc")
    assert names == list(tr.keypoint_names) and frame.tolist() == [1, 2, 3, 4, 5]
    np.testing.assert_allclose(time, np.arange(N) / FPS, atol=1e-6)
    # TRC has no validity flag: an invalid frame's markers are missing, like an untracked one
    assert np.isnan(xyz[[1, 4]]).all() and np.isfinite(xyz[[0, 2, 3]]).all()
    w = np.where(np.array(VALID)[:, None, None], tr.keypoints, np.nan)
    # OpenSim Y up: X forward = our x, Y up = our z, Z = our -y
    np.testing.assert_allclose(xyz, np.stack([w[..., 0], w[..., 2], -w[..., 1]], -1), atol=1e-6,
                               equal_nan=True)
    lines = (tmp_path / "p.trc").read_text().split("\n")
    assert lines[0].split("\t") == ["PathFileType", "4", "(X/Y/Z)", "p.trc"]
    meta = dict(zip(lines[1].split("\t"), lines[2].split("\t"), strict=True))
    assert meta["NumFrames"] == str(N) and meta["NumMarkers"] == "12" and meta["Units"] == "m"
    assert float(meta["DataRate"]) == FPS
    names = [c for c in lines[3].split("\t")[2:] if c]
    assert names == list(tr.keypoint_names)
    assert lines[4].split("\t")[2:5] == ["X1", "Y1", "Z1"] and lines[5] == ""
    data = [ln.split("\t") for ln in lines[6:] if ln]
    assert data[1][2:] == ["NaN"] * 36  # missing frame: NaN in every field, none left empty
    for key in ("DataRate", "CameraRate", "OrigDataRate"):
        assert float(meta[key]) == FPS
    assert meta["OrigDataStartFrame"] == "1" and meta["OrigNumFrames"] == str(N)


def test_c3d_read_by_c3d_package(track, tmp_path):
    _, _, tr = track
    write_c3d(tmp_path / "p.c3d", tr)
    with open(tmp_path / "p.c3d", "rb") as f, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data found", UserWarning)
        reader = c3d.Reader(f)  # the pure-Python reader; the file was written with ezc3d
        assert reader.point_rate == pytest.approx(FPS)
        assert [str(n).strip() for n in reader.point_labels] == list(tr.keypoint_names)
        assert reader.get("POINT:UNITS").string_value.strip() == "mm"
        assert reader.analog_used == 0
        frames = list(reader.read_frames())
    assert len(frames) == N
    pts = np.stack([p for _, p, _ in frames])  # (T, n, 5): x, y, z, residual, cameras
    ok = tr.valid
    np.testing.assert_allclose(pts[ok, :, :3], tr.keypoints[ok] * 1000.0, atol=1e-3)  # < 1 um
    # invalid (frame 1, with an estimate) and untracked (frame 4): C3D's invalid point
    assert (pts[~ok, :, 3] == -1).all() and (pts[ok, :, 3] >= 0).all()
    # ezc3d (OpenSim's C3D reader is built on it) reads an invalid point as NaN
    e = ezc3d.c3d(str(tmp_path / "p.c3d"))
    xyz = e["data"]["points"][:3].transpose(2, 1, 0)  # (T, n, 3) mm
    assert np.isnan(xyz[~ok]).all()
    np.testing.assert_allclose(xyz[ok], tr.keypoints[ok] * 1000.0, atol=1e-3)
    res = e["data"]["meta_points"]["residuals"][0].T  # (T, n)
    assert (res[~ok] == -1).all() and (res[ok] >= 0).all()


def test_bvh_loads_with_independent_parsers(track, tmp_path):
    model, q, tr = track
    write_bvh(tmp_path / "p.bvh", model, tr)
    ref = Bvh((tmp_path / "p.bvh").read_text())
    assert ref.nframes == N and ref.frame_time == pytest.approx(1 / FPS)
    assert ref.get_joints_names()[0] == "pelvis"
    zxy = ["Zrotation", "Xrotation", "Yrotation"]
    assert ref.joint_channels("l_elbow") == zxy
    # the frame without an estimate (4) repeats the last estimate (3); the invalid frame 1
    # holds its own estimate (BVH has no validity: the flag is in the CSV / NPZ)
    np.testing.assert_allclose(ref.frame_joint_channels(4, "l_elbow", zxy),
                               ref.frame_joint_channels(3, "l_elbow", zxy), atol=1e-9)
    assert not np.allclose(ref.frame_joint_channels(1, "l_elbow", zxy),
                           ref.frame_joint_channels(0, "l_elbow", zxy))
    # bvhio's joint positions are the keypoints on the joints (Y up -> our Z up)
    root = bvhio.readAsHierarchy(str(tmp_path / "p.bvh"))
    M = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    for t, src in enumerate([0, 1, 2, 3, 3]):
        root.loadPose(t)
        for j, _, _ in root.layout():
            if j.Name in tr.keypoint_names:
                k = tr.keypoint_names.index(j.Name)
                np.testing.assert_allclose(M @ np.array(j.PositionWorld),
                                           tr.keypoints[src, k], atol=2e-6)


def test_write_exports_group(track, tmp_path):
    model, _, tr = track
    with AtomicFiles() as files:
        paths = write_exports(files, tmp_path / "out", model, tr, extra=np.arange(4))
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == sorted(p.name for p in paths)
    assert sorted(p.suffix for p in paths) == [".bvh", ".c3d", ".csv", ".npz", ".trc"]
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
