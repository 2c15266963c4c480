"""`jaxmocap track`: the I/O machinery driven through the frame protocol (outputs vs FK, BVH
read by the PyPI `bvh` parser, C3D by the `c3d` package, the H.264 overlay video's codec and
frame rate by PyAV, diagnostics), damaged inputs tracked as far as readable, every bad input
refused with one line and nothing written; and one end-to-end run of the real stereo particle
filter on rendered frames."""

import csv
import json
import os
import warnings

import av
import c3d
import cv2
import jax.numpy as jnp
import numpy as np
import pytest
from bvh import Bvh
from test_cli import assert_refused, run_cli

from jaxmocap.body import default_body, keypoints
from jaxmocap.camera import look_at
from jaxmocap.commands import track as track_cmd
from jaxmocap.io.cameras import save_cameras

W, H, T = 48, 36, 3


class LinearTracker:
    """A protocol-conforming tracker with a known answer: the rest pose at x = 0.1 t m,
    counting the frames it was stepped on; ``valid`` False on its second step."""

    diagnostic_names = ("steps", "mean_red")

    def __init__(self):
        self.body = default_body()
        self.steps = 0
        self.started = 0

    def start(self, frames):
        self.started += 1

    def step(self, frames):
        q = np.zeros(self.body.n_dof)
        q[0], q[2] = 0.1 * self.steps, 0.9
        self.steps += 1
        diag = {"steps": float(self.steps), "mean_red": float(frames[..., 0].mean())}
        return track_cmd.FrameResult(q, self.steps != 2, diag)

    def draw(self, frames, result):
        return frames


@pytest.fixture
def rig(tmp_path, monkeypatch):
    cams = [look_at([2.5, y, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0) for y in (-0.3, 0.3)]
    save_cameras(tmp_path / "cameras.json", cams)
    rng = np.random.default_rng(0)
    inputs = []
    for c in range(2):
        d = tmp_path / f"cam{c}"
        d.mkdir()
        for t in range(T):
            cv2.imwrite(str(d / f"{t:03d}.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
        inputs.append(d)
    tracker = LinearTracker()
    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: tracker)
    return tmp_path, inputs, tracker


def test_outputs(rig, capsys):
    root, inputs, tracker = rig
    out = root / "out"
    rc, stdout, err = run_cli(capsys, "track", "--cameras", root / "cameras.json", *inputs,
                              "--out", out, "--overlay", "--quiet", "--fps", "10",
                              "--no-smooth")  # the estimates as tracked (test_smooth smooths)
    assert rc == 0 and err == [], err
    assert tracker.started == 1 and tracker.steps == T
    assert sorted(os.listdir(out)) == ["diagnostics.csv", "overlay.mp4", "poses.bvh",
                                       "poses.c3d", "poses.csv", "poses.npz", "poses.trc",
                                       "run.json"]
    model = tracker.body
    q1, q2 = np.zeros(model.n_dof), np.zeros(model.n_dof)
    q1[0], q1[2] = 0.1, 0.9  # the rejected frame's estimate
    q2[0], q2[2] = 0.2, 0.9
    kp1 = np.asarray(keypoints(model, jnp.asarray(q1)))
    with np.load(out / "poses.npz") as z:
        np.testing.assert_array_equal(z["valid"], [True, False, True])
        assert float(z["fps"]) == 10.0
        # the rejected frame's pose is there, beside valid 0 and the tracker's signals
        np.testing.assert_allclose(z["q"][1], q1, atol=1e-12)
        np.testing.assert_allclose(z["keypoints"][1], kp1, atol=1e-6)
        np.testing.assert_allclose(z["keypoints"][2], np.asarray(keypoints(model, jnp.asarray(q2))),
                                   atol=1e-6)
        assert list(z["diagnostic_names"]) == ["steps", "mean_red"]
        np.testing.assert_array_equal(z["diagnostics"][:, 0], [1, 2, 3])
    with open(out / "poses.csv", newline="") as f:  # the standard library's reader
        rows_csv = list(csv.DictReader(f))
    assert [r["valid"] for r in rows_csv] == ["1", "0", "1"]
    assert float(rows_csv[1]["q_root_tx_m"]) == pytest.approx(0.1)
    assert float(rows_csv[1]["head_z_m"]) == pytest.approx(kp1[3, 2], abs=1e-6)
    assert float(rows_csv[1]["diag_steps"]) == 2.0
    assert json.loads((out / "run.json").read_text())["frames_estimated"] == 3
    ref = Bvh((out / "poses.bvh").read_text())
    assert ref.nframes == T and ref.frame_time == pytest.approx(0.1)
    xs = [ref.frame_joint_channels(t, "pelvis", ["Xposition"])[0] for t in range(T)]
    assert xs[2] - xs[0] == pytest.approx(0.2, abs=1e-6)  # BVH x = our x (metres)
    assert xs[1] - xs[0] == pytest.approx(0.1, abs=1e-6)  # every estimate, the rejected one too
    rows = (out / "diagnostics.csv").read_text().splitlines()
    assert rows[0] == "frame,read,valid,steps,mean_red" and rows[2].startswith("1,1,0,2,")
    red = cv2.imread(str(inputs[0] / "000.png"))[..., 2].mean()
    red1 = cv2.imread(str(inputs[1] / "000.png"))[..., 2].mean()
    assert float(rows[1].split(",")[4]) == pytest.approx((red + red1) / 2, rel=1e-5)
    with av.open(str(out / "overlay.mp4")) as c:  # browser-playable H.264 at the --fps rate
        v = c.streams.video[0]
        assert v.codec_context.name == "h264" and v.codec_context.pix_fmt == "yuv420p"
        assert v.average_rate == 10 and v.frames == T and (v.width, v.height) == (2 * W, H)
    with open(out / "poses.c3d", "rb") as f, warnings.catch_warnings():
        warnings.filterwarnings("ignore", "No analog data found", UserWarning)
        reader = c3d.Reader(f)
        assert reader.point_rate == 10.0
        pts = np.stack([p for _, p, _ in reader.read_frames()])
    assert (pts[1, :, 3] == -1).all() and (pts[[0, 2], :, 3] == 0).all()
    np.testing.assert_allclose(pts[2, :, :3], 1000 * np.asarray(keypoints(model, jnp.asarray(q2))),
                               atol=1e-3)
    assert "tracked 2 of 3 frames (3 readable)" in stdout


def test_smooth(rig, monkeypatch, capsys):
    """--smooth: the rejected frame (an outlier 5 m off) is a missing observation, bridged by
    the constant-velocity model between its neighbours (x = 0 and 0.2: 0.1); the per-frame
    estimates stay in poses.npz (q_raw) and the valid flags are unchanged. Where the tracker
    reports its own gate (the shirt's diagnostics column ``gate``) that is the weight, not the
    reported flag; smoothing is the default of the shirt's learned path (no --colors), off with
    --no-smooth. Bad settings are refused in one line before any frame is read."""
    root, inputs, tracker = rig

    class Outlier(LinearTracker):
        def step(self, frames):
            res = super().step(frames)
            if not res.valid:
                res.q[0] = 5.0
            return res

    class Gated(Outlier):  # the outlier reported valid; only its gate says it was not kept
        diagnostic_names = ("steps", "mean_red", "gate")

        def step(self, frames):
            res = super().step(frames)
            res.diagnostics["gate"] = float(res.valid)
            return res._replace(valid=True)

    cams = root / "cameras.json"
    for name, make, extra, valid in (("flag", Outlier, ["--smooth"], [True, False, True]),
                                     ("gate", Gated, [], [True, True, True])):
        monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names, m=make: m())
        out = root / f"out_{name}"
        rc, _, err = run_cli(capsys, "track", "--cameras", cams, *inputs, "--out", out,
                             "--quiet", "--fps", "10", "--formats", "npz,trc", *extra)
        assert rc == 0 and err == [], err
        with np.load(out / "poses.npz") as z:
            np.testing.assert_array_equal(z["valid"], valid)
            np.testing.assert_allclose(z["q"][:, 0], [0.0, 0.1, 0.2], atol=1e-3)
            np.testing.assert_allclose(z["q"][:, 2], 0.9, atol=1e-6)
            assert z["q_raw"][1, 0] == 5.0 and z["q_raw"][2, 0] == pytest.approx(0.2)
        assert json.loads((out / "run.json").read_text())["smooth_hz"] == 4.0
    out = root / "out_raw"
    assert run_cli(capsys, "track", "--cameras", cams, *inputs, "--out", out, "--quiet",
                   "--fps", "10", "--formats", "npz", "--no-smooth")[0] == 0
    with np.load(out / "poses.npz") as z:
        assert z["q"][1, 0] == 5.0 and "q_raw" not in z.files
    common = ["track", "--cameras", cams, *inputs, "--quiet", "--fps", "10"]
    assert_refused(capsys, "--smooth-hz 2 sets the smoother of --smooth", *common,
                   "--no-smooth", "--smooth-hz", "2", "--out", root / "o1", leaves=[root / "o1"])
    assert_refused(capsys, "--smooth-hz 6: must be below half the frame rate (10 fps", *common,
                   "--smooth", "--smooth-hz", "6", "--out", root / "o2", leaves=[root / "o2"])
    assert_refused(capsys, "--smooth-hz", *common, "--smooth", "--smooth-hz", "-1",
                   "--out", root / "o3", leaves=[root / "o3"])


def test_damaged_frame_is_reported_and_skipped(rig, capsys):
    root, inputs, tracker = rig
    (inputs[1] / "001.png").write_bytes(b"")  # an empty frame in camera 1
    out = root / "out"
    rc, stdout, err = run_cli(capsys, "track", "--cameras", root / "cameras.json", *inputs,
                              "--out", out, "--quiet", "--formats", "npz,csv")
    assert rc == 1 and len(err) == 1
    assert err[0].startswith("jaxmocap track: warning: 1 of 3 frames unreadable (frames 1)")
    assert "001.png empty or not decodable" in err[0]
    assert tracker.steps == 2  # the unreadable instant is not stepped (its 2nd step: invalid)
    assert sorted(os.listdir(out)) == ["diagnostics.csv", "poses.csv", "poses.npz", "run.json"]
    with np.load(out / "poses.npz") as z:
        np.testing.assert_array_equal(z["valid"], [True, False, False])
        # the unreadable frame has no estimate; frame 2 (the tracker's rejected 2nd step) has
        assert np.isnan(z["q"][1]).all() and np.isfinite(z["q"][[0, 2]]).all()
    assert (out / "diagnostics.csv").read_text().splitlines()[2] == "1,0,0,,"


def test_refusals(rig, tmp_path, capsys):
    root, inputs, _ = rig
    cams = root / "cameras.json"
    out = root / "out"
    common = ["--out", out, "--quiet"]

    def refused(match, *argv):
        assert_refused(capsys, match, "track", *argv, *common, leaves=[out])

    refused("1 inputs given for the 2 cameras", "--cameras", cams, inputs[0])
    refused("no such video file, frame folder or camera index", "--cameras", cams, inputs[0],
            root / "nope.mp4")
    refused("camera index 97: cannot be opened", "--cameras", cams, inputs[0], "97")
    short = root / "short"
    short.mkdir()
    for t in range(2):
        (short / f"{t}.png").write_bytes((inputs[1] / f"00{t}.png").read_bytes())
    refused("inputs have different lengths", "--cameras", cams, inputs[0], short)
    big = root / "big"
    big.mkdir()
    for t in range(T):
        cv2.imwrite(str(big / f"{t}.png"), np.zeros((H, W + 4, 3), np.uint8))
    refused(f"frames are {W + 4}x{H} but camera 'cam1' in cameras.json is {W}x{H}", "--cameras",
            cams, inputs[0], big)
    empty = root / "empty"
    empty.mkdir()
    refused("holds no image frames", "--cameras", cams, inputs[0], empty)
    doc = json.loads(cams.read_text())
    doc["cameras"][1]["K"][0][0] = float("nan")
    (root / "nan.json").write_text(json.dumps(doc))
    refused("nan.json", "--cameras", root / "nan.json", *inputs)
    refused("cameras.json", "--cameras", root / "missing" / "cameras.json", *inputs)
    refused("--formats 'bvh,fbx'", "--cameras", cams, *inputs, "--formats", "bvh,fbx")
    refused("--show needs a display", "--cameras", cams, *inputs, "--show")
    (root / "file").write_text("")
    assert_refused(capsys, "the output folder is a file", "track", "--cameras", cams, *inputs,
                   "--out", root / "file", "--quiet")
    (root / "trunc.avi").write_bytes(b"RIFF\x00\x00")
    refused("trunc.avi: not a readable video", "--cameras", cams, inputs[0], root / "trunc.avi")


def test_tracker_input_refusals(tmp_path, capsys):
    """The real trackers' set-up refusals (before any frame is tracked)."""
    cams = [look_at([2.5, 0, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0)]
    save_cameras(tmp_path / "one.json", cams)
    d = tmp_path / "cam0"
    d.mkdir()
    cv2.imwrite(str(d / "0.png"), np.zeros((H, W, 3), np.uint8))
    out = tmp_path / "out"
    base = ["track", "--cameras", tmp_path / "one.json", d, "--out", out, "--quiet"]
    assert_refused(capsys, "--method pf needs exactly 2 cameras", *base, "--method", "pf",
                   leaves=[out])
    (tmp_path / "wb.json").write_text("{}")
    assert_refused(capsys, "--white-balance goes with --colors", *base, "--white-balance",
                   tmp_path / "wb.json", leaves=[out])
    two = [look_at([2.5, y, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0) for y in (-.1, .1)]
    save_cameras(tmp_path / "two.json", two)
    from jaxmocap.body.packages import package_body_file

    cmu, _ = package_body_file("dmc_humanoid")  # two shoulder hinges: no swivel jumps
    d1 = tmp_path / "cam1"
    d1.mkdir()
    cv2.imwrite(str(d1 / "0.png"), np.zeros((H, W, 3), np.uint8))
    pf = ["track", "--method", "pf", "--cameras", tmp_path / "two.json", d, d1, "--out", out,
          "--quiet", "--body", cmu]
    assert_refused(capsys, "--pf-swivel 0", *pf, leaves=[out])
    assert_refused(capsys, "--pf-swivel: must be a fraction in [0, 1]", *pf, "--pf-swivel",
                   "1.5", leaves=[out])
    (tmp_path / "colors.json").write_text('{"format": "jaxmocap.colors", "version": 2}')
    assert_refused(capsys, "colors.json: version: expected 1, got 2", *base, "--colors",
                   tmp_path / "colors.json", leaves=[out])


def test_stereo_pf_end_to_end(tmp_path, capsys):
    """The real particle filter through the command on two rendered frames of the body
    (tiny images, 20 particles: this checks the wiring, not the accuracy). The 64x48 views hold
    no triangulable head and two frames are within the wait for one, so the online filter waits
    (as the offline one does): the frames are
    written invalid (NaN) and say why; tests/test_trackers_stereo_pf.py steps the frame tracker
    through its initialisation on a drawn scene."""
    from jaxmocap.garment import default_garment
    from jaxmocap.render import render_rgb

    model = default_body()
    garment = default_garment(model)
    cams = [look_at([2.5, y, 1.2], [0, 0, 1.1], width=64, height=48, fx=60.0)
            for y in (-0.2, 0.2)]
    save_cameras(tmp_path / "cameras.json", cams)
    q = np.zeros((2, model.n_dof))
    q[:, 2] = 0.85
    q[1, 12] = 0.4
    bg = jnp.full((48, 64, 3), 90, jnp.uint8)
    for c, cam in enumerate(cams):
        (tmp_path / f"cam{c}").mkdir()
        for t in range(2):
            rgb, _ = render_rgb(model, garment, jnp.asarray(q[t]), cam, bg)
            cv2.imwrite(str(tmp_path / f"cam{c}" / f"{t}.png"), np.asarray(rgb)[..., ::-1])
    out = tmp_path / "out"
    rc, stdout, err = run_cli(capsys, "track", "--method", "pf", "--particles", "20",
                              "--cameras", tmp_path / "cameras.json", tmp_path / "cam0",
                              tmp_path / "cam1", "--out", out, "--quiet", "--formats",
                              "npz,bvh,c3d")
    assert rc == 0 and err == [], err
    with np.load(out / "poses.npz") as z:
        assert z["keypoints"].shape == (2, 12, 3) and not z["valid"].any()
        assert np.isnan(z["q"]).all()
    assert Bvh((out / "poses.bvh").read_text()).nframes == 2
    assert (out / "poses.c3d").stat().st_size > 0
    rows = (out / "diagnostics.csv").read_text().splitlines()
    assert rows[0] == ("frame,read,valid,ess,best_loglik,degenerate,spread_root_m,blobs,"
                       "waiting_for_head,head_residual_m,calibrating,start_anchor")
    assert [r.split(",")[8] for r in rows[1:]] == ["1", "1"]  # waiting for a head
    assert [r.split(",")[-1] for r in rows[1:]] == ["0", "0"]  # not started


def test_shirt_options_from_files(tmp_path, capsys, monkeypatch):
    """The shirt tracker of `jaxmocap track` takes the shading-invariant distance from a
    colors.json fitted with --shading, the room colours from white_balance.json, and the
    validity rule from --validity; said in one line each; the paper's set-up otherwise; the
    learned observation's calibrated rule without --colors."""
    from jaxmocap.cli import build_parser
    from jaxmocap.color import ColorModel, save_color_model
    from jaxmocap.commands.colors import save_white_balance
    from jaxmocap.garment import default_garment
    from jaxmocap.posedb import SamplingConfig, build_database

    body = default_body()
    garment = default_garment(body)
    db = build_database(SamplingConfig(size=20), body, garment, progress=False)
    monkeypatch.setattr("jaxmocap.posedb.load_or_build", lambda **kw: db)
    cams = [look_at([2.5, y, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0) for y in (-0.3, 0.3)]
    mean = jnp.asarray(garment.colours) * 200 + 20
    cov = jnp.stack([jnp.eye(3) * 50.0] * garment.n_colours)
    save_color_model(tmp_path / "plain.json", ColorModel(mean, cov, garment.colour_names))
    save_color_model(tmp_path / "shaded.json", ColorModel(mean, cov, garment.colour_names,
                                                          shading=(0.5, 4.0)))
    room = ColorModel(jnp.asarray([[120.0, 110, 100], [60, 60, 70]]),
                      jnp.stack([jnp.eye(3) * 30.0] * 2), ("room0", "room1"))
    save_white_balance(tmp_path / "wb.json", {"cam0": np.eye(3), "cam1": np.eye(3)}, room)
    save_white_balance(tmp_path / "wb0.json", {"cam0": np.eye(3), "cam1": np.eye(3)})

    def tracker(*extra):
        args = build_parser().parse_args(["track", "--cameras", "c.json", "0", "1",
                                          *map(str, extra)])
        t = track_cmd._make_tracker(args, cams, ["cam0", "cam1"])
        return t.params, capsys.readouterr().err

    p, err = tracker("--colors", tmp_path / "plain.json", "--white-balance", tmp_path / "wb0.json")
    assert p.colours.shading is None and p.colours.scene_colors is None and err == ""
    from jaxmocap.trackers import shirt

    rule = p.validity  # the thresholds are traced arrays of the parameters' dtype
    assert (float(rule.min_agreement), int(rule.min_patches),
            float(rule.gate_min_fraction)) == pytest.approx(
        (shirt.MIN_AGREEMENT, shirt.MIN_VALID_PATCHES, shirt.GATE_MIN_FRACTION))
    p, err = tracker("--colors", tmp_path / "shaded.json", "--white-balance",
                     tmp_path / "wb.json", "--validity", "footage")
    assert p.colours.shading == (0.5, 4.0)
    np.testing.assert_allclose(np.asarray(p.colours.scene_colors.mean), np.asarray(room.mean))
    np.testing.assert_allclose(np.asarray(p.colours.scene_colors.cov), np.asarray(room.cov))
    import tomllib
    from pathlib import Path

    toml = Path(__file__).parents[1] / "benchmarks" / "experiments" / "world_shirt.toml"
    validated = next(c for c in tomllib.loads(toml.read_text())["config"]
                     if c["name"] == "validated")["options"]
    for k, v in track_cmd.VALIDITY["footage"].items():  # the rule the experiment measured
        got = getattr(p.validity, k)
        got = got if isinstance(got, bool) else float(got)
        assert got == pytest.approx(v) and v == validated[k], k
    assert "brightness 0.5..4" in err and "2 room colours of" in err
    # the learned observation (no --colors) runs the rule its experiment measured
    # (world_shirt_learned.toml's "learned": the footage gate, the flag calibrated on dev)
    toml = Path(__file__).parents[1] / "benchmarks" / "experiments" / "world_shirt_learned.toml"
    measured = next(c for c in tomllib.loads(toml.read_text())["config"]
                    if c["name"] == "learned")["options"]
    p, _ = tracker("--quiet")
    for k, v in track_cmd.VALIDITY["learned"].items():
        got = getattr(p.validity, k)
        assert (got if isinstance(got, bool) else float(got)) == pytest.approx(v), k
        assert v == measured[k], k
    assert p.validity.report and p.validity.check_residual and p.validity.check_recall
    save_cameras(tmp_path / "cameras.json", cams)
    assert_refused(capsys, "--validity footage is the shirt tracker's rule", "track",
                   "--method", "pf", "--cameras", tmp_path / "cameras.json", "0", "1",
                   "--validity", "footage", "--out", tmp_path / "o")


def test_observer_refusals(tmp_path, capsys):
    """``--observer`` (issue 49): with Wang's colour model, with the particle filter, a file
    trained for another shirt, and a file that is not a model: one line each, before any work."""
    from jaxmocap.garment import default_garment
    from jaxmocap.io.garment_file import save_garment
    from jaxmocap.observe import BUNDLED

    two = [look_at([2.5, y, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0) for y in (-.1, .1)]
    save_cameras(tmp_path / "two.json", two)
    ins = []
    for c in range(2):
        d = tmp_path / f"cam{c}"
        d.mkdir()
        cv2.imwrite(str(d / "0.png"), np.zeros((H, W, 3), np.uint8))
        ins.append(d)
    out = tmp_path / "out"
    base = ["track", "--cameras", tmp_path / "two.json", *ins, "--out", out, "--quiet",
            "--observer", BUNDLED]
    (tmp_path / "colors.json").write_text("{}")
    assert_refused(capsys, "leave out --colors", *base, "--colors", tmp_path / "colors.json",
                   leaves=[out])
    assert_refused(capsys, "--observer is read by the shirt tracker", *base, "--method", "pf",
                   leaves=[out])
    body = default_body()
    g = default_garment(body)
    other = eqx_swap_colours(g)
    save_garment(tmp_path / "garment.json", other, body)
    assert_refused(capsys, "trained for another garment", *base, "--garment",
                   tmp_path / "garment.json", leaves=[out])
    (tmp_path / "bad.eqx").write_text("not a model\n")
    assert_refused(capsys, "not a trained observation model", *base[:-1], tmp_path / "bad.eqx",
                   leaves=[out])


def eqx_swap_colours(g):
    """The garment with its first two patches' colours swapped (another shirt, same colours)."""
    import equinox as eqx

    pc = np.asarray(g.patch_colour).copy()
    pc[[0, 1]] = pc[[1, 0]]
    return eqx.tree_at(lambda x: x.patch_colour, g, jnp.asarray(pc))


# ----------------------------------------------------------------------------- journal, resume


@pytest.fixture(scope="module")
def pf_footage(tmp_path_factory):
    """The smallest footage on which the real stereo filter starts and runs: `jaxmocap synth`
    (stereo rig, 96x72, plain background, 12 frames of the punch clip), played forwards and
    backwards to 48 frames per camera (frame folders)."""
    import shutil
    import subprocess
    import sys
    from pathlib import Path

    root = tmp_path_factory.mktemp("pf_footage")
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]))
    subprocess.run([sys.executable, "-m", "jaxmocap.cli", "synth", str(root / "ds"),
                    "--preset", "stereo", "--width", "96", "--height", "72", "--frames", "12",
                    "--background", "plain", "--png", "--no-video", "--quiet"],
                   check=True, env=env, capture_output=True, timeout=120)
    shutil.copy(root / "ds" / "cameras.json", root / "cameras.json")
    for c in range(2):
        src = sorted((root / "ds" / f"cam{c}").iterdir())
        (root / f"cam{c}").mkdir()
        for i, f in enumerate((src + src[::-1]) * 2):
            shutil.copy(f, root / f"cam{c}" / f"{i:03d}.png")
    return root, env


def _journal_lines(out) -> list[dict]:
    path = out.parent / f".{out.name}.jaxmocap-journal" / "frames.jsonl"
    try:
        text = path.read_text()
    except FileNotFoundError:
        return []
    return [json.loads(ln) for ln in text.split("\n")[:-1]]


def test_kill_9_mid_run_then_resume_equals_an_uninterrupted_run(pf_footage, tmp_path):
    """Issue 52 items 2-3: a real `jaxmocap track --method pf` process killed with SIGKILL
    part-way (after the filter started: its particles and RNG key are in the checkpoint) leaves
    its tracked frames in the journal beside --out and nothing in --out; `track --resume OUT`
    continues from the checkpoint and writes outputs bit-identical to an uninterrupted run's
    (the oracle), then removes the journal and the lock."""
    import pickle
    import signal
    import subprocess
    import sys
    import time

    root, env = pf_footage
    argv = [sys.executable, "-m", "jaxmocap.cli", "track", "--method", "pf", "--skin", "synth",
            "--particles", "50", "--cameras", str(root / "cameras.json"), str(root / "cam0"),
            str(root / "cam1"), "--formats", "npz,csv,bvh", "--checkpoint", "0", "--quiet"]
    whole, cut = tmp_path / "whole", tmp_path / "cut"
    n_all = 48
    # the cut run first, the oracle after it: the oracle then reads the programs the cut run
    # compiled from the compilation cache (run side by side, both compiled them from cold)
    proc = subprocess.Popen([*argv, "--out", str(cut)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.time() + 180
    while len(_journal_lines(cut)) < 30 and proc.poll() is None and time.time() < deadline:
        time.sleep(0.005)
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=30)
    lines = _journal_lines(cut)
    assert proc.returncode == -signal.SIGKILL and 30 <= len(lines) < n_all, len(lines)
    assert not cut.exists() or not any(cut.iterdir())  # nothing half-written in --out
    journal = tmp_path / ".cut.jaxmocap-journal"
    raw = (journal / "checkpoint.pkl").read_bytes()
    done = pickle.loads(raw.partition(b"\n")[2])["frames"]
    assert 0 < done <= len(lines)
    assert any(r["diagnostics"].get("waiting_for_head") == 0 for r in lines[:done])  # started
    oracle = subprocess.run([*argv, "--out", str(whole)], env=env, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True, timeout=180)  # uncut
    assert oracle.returncode == 0, oracle.stderr
    assert json.loads((whole / "run.json").read_text())["frames_written"] == n_all
    res = subprocess.run([sys.executable, "-m", "jaxmocap.cli", "track", "--resume", str(cut),
                          "--quiet"], env=env, capture_output=True, text=True, timeout=180)
    assert res.returncode == 0, res.stderr
    for name in ("poses.npz", "poses.csv", "poses.bvh", "diagnostics.csv", "run.json"):
        assert (cut / name).read_bytes() == (whole / name).read_bytes(), name
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cut", "whole"]  # journal, lock gone


class CheckpointTracker(LinearTracker):
    """LinearTracker with the checkpoint protocol (its state: the step count); ``crash_at``:
    the step on which it dies (a stand-in for a kill between two frames)."""

    def __init__(self, crash_at=None):
        super().__init__()
        self.crash_at, self.stepped = crash_at, 0

    def step(self, frames):
        if self.crash_at is not None and self.steps + 1 == self.crash_at:
            raise RuntimeError("killed")
        self.stepped += 1
        return super().step(frames)

    def checkpoint(self):
        return {"steps": self.steps}

    def restore(self, checkpoint):
        self.steps = checkpoint["steps"]


def _outputs(folder):
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir())}


def test_resume_after_a_crash_and_after_a_read_only_out(rig, capsys, monkeypatch):
    """Issue 52 items 2-3 through the command: (a) a run that dies on frame 3 leaves frames 1-2
    and the tracker's checkpoint in the journal; --resume steps only the third frame from the
    restored state; (b) an --out that refuses the outputs (read-only: EROFS when they are
    renamed into place) is one line saying where the tracked frames are and how to resume;
    --resume then only writes them (nothing is tracked again). Both equal an uninterrupted
    run's outputs (the oracle), and the journal is gone afterwards."""
    import errno
    from pathlib import Path

    import jaxmocap.io.atomic as atomic

    root, inputs, _ = rig
    argv = ["track", "--cameras", root / "cameras.json", *inputs, "--quiet", "--checkpoint", "0"]
    trackers = []

    def make(crash_at=None):
        def factory(args, cams, names):
            trackers.append(CheckpointTracker(crash_at))
            return trackers[-1]
        return factory

    monkeypatch.setattr(track_cmd, "_make_tracker", make())
    assert run_cli(capsys, *argv, "--out", root / "whole")[0] == 0
    want = _outputs(root / "whole")
    # (a) dies on the third frame
    monkeypatch.setattr(track_cmd, "_make_tracker", make(crash_at=3))
    with pytest.raises(RuntimeError, match="killed"):
        run_cli(capsys, *argv, "--out", root / "a")
    journal = root / ".a.jaxmocap-journal"
    assert len((journal / "frames.jsonl").read_text().splitlines()) == 2
    assert not (root / "a").exists()
    rc, out, err = run_cli(capsys, *argv, "--out", root / "a")  # not over a journal
    assert rc == 2 and len(err) == 1 and f"({journal}); resume it with `jaxmocap track " \
        f"--resume {root / 'a'}`" in err[0], err
    monkeypatch.setattr(track_cmd, "_make_tracker", make())
    rc, out, err = run_cli(capsys, "track", "--resume", root / "a", "--quiet")
    assert rc == 0, err
    assert trackers[-1].stepped == 1 and trackers[-1].steps == 3  # restored after frame 2
    assert _outputs(root / "a") == want and not journal.exists()
    # (b) the outputs cannot be renamed into --out
    real_replace = atomic.os.replace

    def read_only(src, dst):  # --out (only) became read-only
        if Path(dst).parent == root / "b":
            raise OSError(errno.EROFS, os.strerror(errno.EROFS), str(src), None, str(dst))
        real_replace(src, dst)

    monkeypatch.setattr(atomic.os, "replace", read_only)
    rc, out, err = run_cli(capsys, *argv, "--out", root / "b")
    journal = root / ".b.jaxmocap-journal"
    assert rc == 2 and len(err) == 1, err
    assert "the file system is read-only" in err[0] and err[0].endswith(
        f"3 tracked frames are kept in {journal}; resume with `jaxmocap track --resume "
        f"{root / 'b'}`"), err[0]
    monkeypatch.setattr(atomic.os, "replace", real_replace)
    rc, out, err = run_cli(capsys, "track", "--resume", root / "b", "--quiet")
    assert rc == 0, err
    assert trackers[-1].stepped == 0  # the journal held every frame and the last state
    assert _outputs(root / "b") == want and not journal.exists()


def test_resume_refusals(rig, capsys, monkeypatch):
    """--resume is refused in one line: with other options, without a journal, when an input
    changed since the interrupted run; a journal without its checkpoint's lines, or a damaged
    checkpoint, tracks again from the first frame and says so."""
    root, inputs, _ = rig
    monkeypatch.setattr(track_cmd, "_make_tracker",
                        lambda args, cams, names: CheckpointTracker(crash_at=3))
    argv = ["track", "--cameras", root / "cameras.json", *inputs, "--quiet", "--checkpoint", "0"]
    with pytest.raises(RuntimeError):
        run_cli(capsys, *argv, "--out", root / "a")
    assert_refused(capsys, "--resume", "track", "--resume", root / "a", "--formats", "npz")
    assert_refused(capsys, f"--resume {root / 'nowhere'}: no journal of an interrupted run",
                   "track", "--resume", root / "nowhere")
    assert_refused(capsys, "give the inputs", "track", "--out", root / "x")
    ckpt = root / ".a.jaxmocap-journal" / "checkpoint.pkl"
    ckpt.write_bytes(ckpt.read_bytes()[:-3])  # a damaged checkpoint (a disk that lied)
    monkeypatch.setattr(track_cmd, "_make_tracker",
                        lambda args, cams, names: CheckpointTracker())
    png = inputs[1] / "001.png"
    stat = png.stat()
    os.utime(png, ns=(stat.st_atime_ns, stat.st_mtime_ns + 10**9))
    assert_refused(capsys, f"--resume {root / 'a'}: {png} changed since the interrupted run",
                   "track", "--resume", root / "a")
    os.utime(png, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    rc, out, err = run_cli(capsys, "track", "--resume", root / "a", "--quiet")
    assert rc == 0 and len(err) == 1 and "checkpoint is damaged" in err[0] and \
        "tracking again from the first frame" in err[0], err
    with np.load(root / "a" / "poses.npz") as z:
        np.testing.assert_array_equal(z["diagnostics"][:, 0], [1, 2, 3])
