"""Bad input of every kind, against every command: one line on stderr, exit code 2, nothing
written, nothing of the user's touched, and no JAX compilation before the refusal (each case
answers in seconds). Interrupts (SIGINT, SIGTERM, kill -9) in subprocesses: a marked partial
result or nothing, never a temporary file in ``--out``, never a traceback."""

import json
import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import cv2
import jax.numpy as jnp
import numpy as np
import pytest
from test_cli import run_cli

from jaxmocap.body import default_body
from jaxmocap.camera import look_at
from jaxmocap.color import ColorModel, save_color_model
from jaxmocap.commands import track as track_cmd
from jaxmocap.commands.colors import save_white_balance
from jaxmocap.errors import InputError
from jaxmocap.garment import default_garment
from jaxmocap.io.atomic import STAGING, AtomicFiles, sweep_temporaries
from jaxmocap.io.cameras import save_cameras
from jaxmocap.io.preflight import read_npz

W, H, T = 48, 36, 3
ROOT = Path(__file__).resolve().parents[1]


def _cli(capsys, *argv):
    """(exit code, stdout, stderr lines) of ``jaxmocap argv...``; argparse's exit included."""
    try:
        return run_cli(capsys, *argv)
    except SystemExit as e:
        cap = capsys.readouterr()
        return e.code, cap.out, [ln for ln in cap.err.splitlines() if ln.strip()]


def _snapshot(folder: Path) -> dict:
    return {p: p.read_bytes() for p in folder.rglob("*") if p.is_file()}


def refused(capsys, kit, match, *argv):
    """Exit 2, one stderr line holding ``match``, and no file of the kit created or changed."""
    before = _snapshot(kit)
    t0 = time.perf_counter()
    rc, out, err = _cli(capsys, *argv)
    assert rc == 2, (rc, out, err)
    assert len(err) == 1, err
    assert match in err[0], err[0]
    assert _snapshot(kit) == before
    assert time.perf_counter() - t0 < 60.0  # before any work (tracking would take minutes)
    return err[0]


@pytest.fixture
def kit(tmp_path):
    """The guide's walk-through kit in miniature: cameras, frame folders, a colour model, a
    white balance, calibration image folders, a ground truth and a prediction."""
    cams = [look_at([2.5, y, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0) for y in (-0.3, 0.3)]
    save_cameras(tmp_path / "cameras.json", cams)
    rng = np.random.default_rng(0)
    for c in range(2):
        for sub in ("data", "calib"):
            d = tmp_path / sub / f"cam{c}"
            d.mkdir(parents=True)
            for t in range(T):
                cv2.imwrite(str(d / f"{t:02d}.png"), rng.integers(0, 255, (H, W, 3), np.uint8))
    n = default_garment(default_body()).n_colours  # one colour per shirt colour
    means = np.random.default_rng(2).uniform(20, 235, (n, 3))
    cov = jnp.asarray(np.stack([np.eye(3) * 50] * n))
    save_color_model(tmp_path / "colors.json", ColorModel(mean=jnp.asarray(means), cov=cov))
    save_color_model(tmp_path / "colors3.json", ColorModel(mean=jnp.asarray(means[:3]),
                                                           cov=cov[:3]))
    save_white_balance(tmp_path / "white_balance.json", {"cam0": np.eye(3), "cam1": np.eye(3)})
    model = default_body()
    k = len(model.keypoint_names)
    for name in ("data/groundtruth.npz", "poses.npz"):
        np.savez(tmp_path / name, keypoints=np.zeros((T, k, 3)), valid=np.ones(T, bool),
                 keypoint_names=np.array(model.keypoint_names), fps=np.float64(30))
    lab = np.zeros((H, W), np.uint8)
    lab[:10, :10], lab[10:20, :10], lab[20:30, :10] = 1, 2, 3
    cv2.imwrite(str(tmp_path / "labels.png"), lab)
    return tmp_path


# ----------------------------------------------------------------------------- 1. outputs


def test_outputs_never_touch_inputs(kit, capsys):
    k = kit
    refused(capsys, k, "lies inside the input folder", "calibrate", k / "calib/cam0",
            k / "calib/cam1", "--board", "7x5", "--square", "0.08", "--out",
            k / "calib/cam0/00.png")
    refused(capsys, k, "is also an input", "colors", "--white-balance", "--colors",
            k / "colors.json", "--images", k / "data/cam0/00.png", "--masks", k / "labels.png",
            "--out", k / "colors.json")
    refused(capsys, k, "is also an input", "colors", "--images", k / "data/cam0/00.png",
            "--masks", k / "labels.png", "--out", k / "labels.png")
    refused(capsys, k, "is also an input", "eval", k / "poses.npz", k / "data", "--out",
            k / "data/groundtruth.npz")
    refused(capsys, k, "is also an input", "eval", k / "poses.npz", k / "data", "--out",
            k / "poses.npz")
    # through a symlink and a hard link
    (k / "link.npz").symlink_to(k / "poses.npz")
    refused(capsys, k, "is also an input", "eval", k / "link.npz", k / "data", "--out",
            k / "poses.npz")
    os.link(k / "data/groundtruth.npz", k / "hard.npz")
    refused(capsys, k, "is also an input", "eval", k / "poses.npz", k / "data", "--out",
            k / "hard.npz")
    base = ["track", "--cameras", k / "cameras.json", k / "data/cam0", k / "data/cam1",
            "--quiet"]
    refused(capsys, k, "is also an input", *base, "--out", k / "data/cam0")
    refused(capsys, k, "lies inside the input folder", *base, "--out", k / "data/cam1/res")
    (k / "res").mkdir()
    (k / "res/poses.npz").write_bytes((k / "poses.npz").read_bytes())
    refused(capsys, k, "is also an input", *base, "--out", k / "res", "--db",
            k / "res/poses.npz", "--overwrite")


def test_out_folder_type_stale_and_writability(kit, capsys, monkeypatch):
    k = kit
    base = ["track", "--cameras", k / "cameras.json", k / "data/cam0", k / "data/cam1",
            "--quiet"]
    (k / "file").write_text("x")
    refused(capsys, k, "the output folder is a file", *base, "--out", k / "file")
    refused(capsys, k, "a parent of", *base, "--out", k / "file/sub")
    (k / "res/poses.bvh").mkdir(parents=True)
    refused(capsys, k, "poses.bvh is a folder where an output file goes", *base, "--out",
            k / "res", "--overwrite")
    (k / "res/poses.bvh").rmdir()
    for name in ("overlay.mp4", "eval.json", "poses.npz"):
        (k / "res" / name).write_text("earlier run")
    refused(capsys, k, "holds results of an earlier run (eval.json, overlay.mp4, poses.npz); "
            "choose a new folder, or pass --overwrite", *base, "--out", k / "res")
    if sys.platform.startswith("linux"):  # not writable even for root
        refused(capsys, k, "folder is not writable", *base, "--out", "/proc/jaxmocap-out")
        refused(capsys, k, "folder is not writable", "eval", k / "poses.npz", k / "data",
                "--out", "/proc/eval.json")
    (k / "db.npz").mkdir()
    refused(capsys, k, "db.npz: is a folder", "build-db", "--out", k / "db.npz", "--quiet")
    refused(capsys, k, "is a folder", "calibrate", k / "calib/cam0", "--board", "7x5",
            "--square", "0.08", "--out", k / "res")
    refused(capsys, k, "a file is in the way", "synth", k / "file")

    # --overwrite: the earlier set is replaced as a whole once the new one is complete
    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: _Fixed())
    rc, out, err = _cli(capsys, *base, "--out", k / "res", "--overwrite", "--formats", "csv")
    assert rc == 0, err
    assert sorted(os.listdir(k / "res")) == ["diagnostics.csv", "poses.csv", "run.json"]
    assert not (k / STAGING).exists()  # the staging folder beside --out is removed
    assert json.loads((k / "res/run.json").read_text())["complete"] is True


# ----------------------------------------------------------------------------- 2. bad files


def test_bad_files_one_line(kit, capsys):
    k = kit
    binary = k / "binary.bin"
    binary.write_bytes(bytes(range(256)) * 8)
    base = ["track", k / "data/cam0", k / "data/cam1", "--out", k / "res", "--quiet"]
    refused(capsys, k, "binary.bin: not a text file", *base, "--cameras", binary)
    refused(capsys, k, "binary.bin: not a text file", *base, "--cameras", k / "cameras.json",
            "--colors", binary)
    refused(capsys, k, "binary.bin: not a text file", *base, "--cameras", k / "cameras.json",
            "--colors", k / "colors.json", "--white-balance", binary)
    refused(capsys, k, "data: cannot read: is a folder (expected a cameras.json", *base,
            "--cameras", k / "data")
    # pose databases: empty, truncated, not a zip, meta without a field, another body
    track_db = [*base, "--cameras", k / "cameras.json", "--colors", k / "colors.json", "--db"]
    (k / "empty.npz").write_bytes(b"")
    refused(capsys, k, "empty.npz: cannot read: empty file", *track_db, k / "empty.npz")
    model = default_body()
    meta = {"key": "x", "n_colours": 3, "dof_names": list(model.chain.dof_names)}
    maps = np.zeros((4, 40, 40), np.uint8)
    np.savez(k / "db.npz", maps=maps, poses=np.zeros((4, model.n_dof), np.float32),
             meta=np.array(json.dumps(meta)))
    (k / "trunc.npz").write_bytes((k / "db.npz").read_bytes()[:300])
    refused(capsys, k, "trunc.npz: cannot read: truncated or damaged .npz archive",
            *track_db, k / "trunc.npz")
    refused(capsys, k, "binary.bin: cannot read", *track_db, binary)
    np.savez(k / "nokey.npz", maps=maps, poses=np.zeros((4, model.n_dof), np.float32),
             meta=np.array(json.dumps({"key": "x", "dof_names": meta["dof_names"]})))
    refused(capsys, k, "field 'meta.n_colours' missing", *track_db, k / "nokey.npz")
    np.savez(k / "nomaps.npz", poses=np.zeros((4, model.n_dof)), meta=np.array("{}"))
    refused(capsys, k, "missing field 'maps'", *track_db, k / "nomaps.npz")
    other = dict(meta, dof_names=[f"d{i}" for i in range(model.n_dof - 3)])
    np.savez(k / "other.npz", maps=maps, poses=np.zeros((4, model.n_dof - 3), np.float32),
             meta=np.array(json.dumps(other)))
    refused(capsys, k, f"built for a body with {model.n_dof - 3} DOFs, the body has "
            f"{model.n_dof}", *track_db, k / "other.npz")
    refused(capsys, k, "cannot read", *base, "--cameras", k / "cameras.json", "--colors",
            k / "colors.json", "--db", k / "db.npz", "--ik-cov", k / "trunc.npz")
    # pose files for eval
    refused(capsys, k, "trunc.npz: cannot read", "eval", k / "trunc.npz", k / "data")
    refused(capsys, k, "empty.npz: cannot read: empty file", "eval", k / "poses.npz",
            k / "empty.npz")
    with zipfile.ZipFile(k / "junk.npz", "w") as z:
        z.writestr("keypoints.npy", b"\x93NUMPY garbage")
    refused(capsys, k, "junk.npz: cannot read", "eval", k / "junk.npz", k / "data")
    np.save(k / "single.npy", np.zeros(3))
    os.replace(k / "single.npy", k / "single.npz")
    refused(capsys, k, "single.npz: cannot read", "eval", k / "single.npz", k / "data")
    # images: a corrupt PNG as a photo or a label mask
    (k / "bad.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x00" * 40)
    refused(capsys, k, "bad.png: not a readable image", "colors", "--images", k / "bad.png",
            "--masks", k / "labels.png", "--out", k / "c.json")
    refused(capsys, k, "bad.png: not a readable label image", "colors", "--images",
            k / "data/cam0/00.png", "--masks", k / "bad.png", "--out", k / "c.json")
    # a binary scene file, a folder as a pose file, one input for two cameras, a colour model
    # of another shirt (refused before the default database would be built)
    refused(capsys, k, "binary.bin: not a text file", "synth", k / "ds", "--scene", binary)
    refused(capsys, k, "data/cam0: is a folder; expected a pose file", "eval", k / "data/cam0",
            k / "data")
    refused(capsys, k, "given for two cameras (0 and 1)", "track", k / "data/cam0",
            k / "data/cam0/../cam0", "--cameras", k / "cameras.json", "--out", k / "res")
    refused(capsys, k, "the colour model has 3 colours, the shirt has", *base, "--cameras",
            k / "cameras.json", "--colors", k / "colors3.json")
    # videos: missing, empty, not a video
    refused(capsys, k, "nope.mp4: no such video file", "track", k / "data/cam0", k / "nope.mp4",
            "--cameras", k / "cameras.json", "--out", k / "res")
    (k / "empty.mp4").write_bytes(b"")
    refused(capsys, k, "empty.mp4: empty file", "calibrate", k / "empty.mp4", "--board", "7x5",
            "--square", "0.08", "--out", k / "c.json")
    refused(capsys, k, "binary.bin: not a readable video", "calibrate", binary, "--board",
            "7x5", "--square", "0.08", "--out", k / "c.json")


def test_read_npz_and_database_loader(kit):
    from jaxmocap.posedb import DatabaseError, load_database

    with pytest.raises(InputError, match="missing field 'x'"):
        read_npz(kit / "poses.npz", "a test file", ("x",))
    with pytest.raises(FileNotFoundError):
        load_database(kit / "nothing.npz")
    (kit / "meta.npz").write_bytes(b"")
    with pytest.raises(DatabaseError, match="empty file"):
        load_database(kit / "meta.npz")


@pytest.mark.parametrize("argv, match", [
    (["track", "--work-size", "0"], "argument --work-size: must be between 16 and 1,024"),
    (["track", "--particles", "10000000"], "must be between 10 and 100,000 (compile time"),
    (["track", "--particles", "5"], "argument --particles: must be between 10 and"),
    (["track", "--max-frames", "0"], "argument --max-frames: must be >= 1"),
    (["track", "--fps", "-3"], "argument --fps: must be a positive number"),
    (["track", "--pf-skin-grow", "30"], "argument --pf-skin-grow: must be between 0 and 20"),
    (["track", "--fps", "nan"], "argument --fps: must be a positive number"),
    (["calibrate", "--board", "7x5", "--square", "0.08", "--min-views", "0"],
     "argument --min-views: must be >= 3"),
    (["calibrate", "--board", "7x5", "--square", "-1"], "argument --square: must be a positive"),
    (["calibrate", "--board", "7x5", "--square", "0.1", "--every", "0"], "--every: must be >= 1"),
    (["colors", "--n-colors", "0"], "argument --n-colors: must be between 1 and 255"),
    (["build-db", "--size", "0"], "--size/--seed: "),
    (["track", "--nope"], "unrecognized arguments: --nope (see jaxmocap --help)"),
    (["demo", "--frames", "1"], "argument --frames: must be >= 2"),
])
def test_option_ranges(kit, capsys, argv, match):
    """Checked by argparse (one line, exit 2) before anything is imported or read."""
    tail = {"track": [kit / "data/cam0", "--cameras", kit / "cameras.json"],
            "calibrate": [kit / "calib/cam0"],
            "colors": ["--images", kit / "data/cam0/00.png", "--masks", kit / "labels.png"]}
    refused(capsys, kit, match, *argv, *tail.get(argv[0], []))


# ----------------------------------------------------------------------------- 3. semantics


def test_semantic_refusals(kit, capsys):
    k = kit
    base = ["track", k / "data/cam0", k / "data/cam1", "--out", k / "res", "--quiet"]
    doc = json.loads((k / "colors.json").read_text())
    doc["colors"][0]["mean"] = [-300, -50, -20]
    (k / "neg.json").write_text(json.dumps(doc))
    refused(capsys, k, "neg.json: colors[0].mean: expected RGB values in 0..255, got (-300, "
            "-50, -20)", *base, "--cameras", k / "cameras.json", "--colors", k / "neg.json")
    refused(capsys, k, "colors[0].mean: expected RGB values in 0..255", "colors",
            "--white-balance", "--colors", k / "neg.json", "--images", k / "data/cam0/00.png",
            "--masks", k / "labels.png", "--out", k / "wb.json")
    doc = json.loads((k / "colors.json").read_text())
    doc["colors"][1]["cov"] = [[1, 0, 0], [0, -1, 0], [0, 0, 1]]
    (k / "cov.json").write_text(json.dumps(doc))
    refused(capsys, k, "colors[1].cov: expected positive definite", *base, "--cameras",
            k / "cameras.json", "--colors", k / "cov.json")
    wb = k / "wb_bad.json"
    for wb_cam1, match in ((np.zeros((3, 3)), "singular"),
                     (np.diag([-0.08, 1, 1]), "expected positive per-channel gains"),
                     (np.diag([50.0, 1, 1]), "expected positive per-channel gains"),
                     (np.eye(3) + 2 * (1 - np.eye(3)), "off-diagonal mixing")):
        save_white_balance(wb, {"cam0": np.eye(3), "cam1": wb_cam1})
        err = refused(capsys, k, match, *base, "--cameras", k / "cameras.json", "--colors",
                      k / "colors.json", "--white-balance", wb)
        assert "cameras.cam1" in err
    # the stereo particle filter: one baseline, one image size
    c0 = look_at([2.5, 0, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0)
    save_cameras(k / "same.json", [c0, c0])
    refused(capsys, k, "a stereo pair needs distinct centres", *base, "--method", "pf",
            "--cameras", k / "same.json")
    c1 = look_at([2.5, 0.3, 1.2], [0, 0, 1.1], width=W + 16, height=H, fx=40.0)
    save_cameras(k / "sizes.json", [c0, c1])
    refused(capsys, k, f"needs cameras of one image size, got cam0 {W}x{H}, cam1 {W + 16}x{H}",
            *base, "--method", "pf", "--cameras", k / "sizes.json")


def test_damaged_and_mismatched_frames(kit, capsys, monkeypatch):
    """A corrupt frame in a folder is counted unreadable (exit 1, one warning line, NaN row);
    cameras with different frame counts are refused before any frame is read."""
    k = kit
    (k / "data/cam1/01.png").write_bytes(b"\x89PNG\r\n\x1a\n" + b"\x17" * 64)
    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: _Fixed())
    rc, out, err = _cli(capsys, "track", "--cameras", k / "cameras.json", k / "data/cam0",
                        k / "data/cam1", "--out", k / "res", "--quiet", "--formats", "npz")
    assert rc == 1 and len(err) == 1 and "1 of 3 frames unreadable (frames 1)" in err[0]
    with np.load(k / "res/poses.npz") as z:
        assert z["valid"].tolist() == [True, False, True] and bool(z["complete"])
    (k / "data/cam1/02.png").unlink()
    refused(capsys, k, "inputs have different lengths", "track", "--cameras",
            k / "cameras.json", k / "data/cam0", k / "data/cam1", "--out", k / "res2")


def _video(path: Path, n: int, damage: bool = False) -> None:
    rng = np.random.default_rng(0)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10.0, (W, H))
    for t in range(n):
        img = np.full((H, W, 3), 40 * (t % 5), np.uint8)
        img[8:28, 8 + t:28 + t] = rng.integers(0, 255, (20, 20, 3), np.uint8)
        w.write(img)
    w.release()
    if damage:  # flip bytes in the middle of the stream: the decoder conceals, and says so
        b = bytearray(path.read_bytes())
        for i in range(len(b) // 2, len(b) // 2 + 200, 3):
            b[i] ^= 0xFF
        path.write_bytes(bytes(b))


def test_video_frames_the_decoder_reported_damaged_are_unreadable(kit, capsys, monkeypatch):
    k = kit
    _video(k / "a.mp4", 20)
    _video(k / "b.mp4", 20, damage=True)
    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: _Fixed())
    rc, out, err = _cli(capsys, "track", "--cameras", k / "cameras.json", k / "a.mp4",
                        k / "b.mp4", "--out", k / "res", "--quiet", "--formats", "npz")
    assert rc == 1 and len(err) == 1, err
    assert "b.mp4: frame" in err[0] and "damaged (decoder: " in err[0]
    with np.load(k / "res/poses.npz") as z:
        bad = np.flatnonzero(~z["valid"])
        assert 1 <= len(bad) <= 3 and z["valid"].sum() >= 17
    assert f"frames unreadable (frames {bad[0]}" in err[0]
    _video(k / "c.mp4", 20)
    rc, out, err = _cli(capsys, "track", "--cameras", k / "cameras.json", k / "a.mp4",
                        k / "c.mp4", "--out", k / "res2", "--quiet", "--formats", "npz")
    assert rc == 0 and err == []  # an intact video: no frame flagged


class _Fixed:
    diagnostic_names = ()

    def __init__(self):
        self.body = default_body()

    def start(self, frames):
        pass

    def step(self, frames):
        q = np.zeros(self.body.n_dof)
        q[2] = 0.9
        return track_cmd.FrameResult(q, True, {})

    def draw(self, frames, result):
        return frames


# ----------------------------------------------------------------------------- 4. interrupts

# `jaxmocap track` with a tracker that takes its time (set-up ``argv[1]`` s, 0.3 s a frame) so
# that a signal lands where the test wants it: the command's own machinery is what is tested.
SLOW_TRACK = """
import sys, time
import numpy as np
from jaxmocap.body import default_body
from jaxmocap.commands import track as t

class Slow:
    diagnostic_names = ("steps",)
    def __init__(self):
        self.body = default_body()
        self.n = 0
    def start(self, frames):
        print("START", file=sys.stderr, flush=True)
        time.sleep(float(sys.argv[1]))
    def step(self, frames):
        time.sleep(0.3)
        self.n += 1
        q = np.zeros(self.body.n_dof)
        q[2] = 0.9
        print(f"STEP {self.n}", file=sys.stderr, flush=True)
        return t.FrameResult(q, True, {"steps": float(self.n)})
    def draw(self, frames, result):
        return frames

t._make_tracker = lambda args, cams, names: Slow()
from jaxmocap.cli import main
sys.exit(main(sys.argv[2:]))
"""


@pytest.fixture(scope="module")
def long_capture(tmp_path_factory):
    """Two cameras x 40 tiny frames."""
    root = tmp_path_factory.mktemp("capture")
    cams = [look_at([2.5, y, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0) for y in (-0.3, 0.3)]
    save_cameras(root / "cameras.json", cams)
    rng = np.random.default_rng(1)
    for c in range(2):
        (root / f"cam{c}").mkdir()
        for t in range(40):
            cv2.imwrite(str(root / f"cam{c}" / f"{t:02d}.png"),
                        rng.integers(0, 255, (H, W, 3), np.uint8))
    (root / "slow_track.py").write_text(SLOW_TRACK)
    return root


def _start(root: Path, out: Path, setup_s: float, *extra) -> subprocess.Popen:
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    return subprocess.Popen(
        [sys.executable, str(root / "slow_track.py"), str(setup_s), "track", "--cameras",
         str(root / "cameras.json"), str(root / "cam0"), str(root / "cam1"), "--out", str(out),
         "--quiet", *extra], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)


def _wait_for(proc: subprocess.Popen, line: str, lines: list) -> None:
    deadline = time.time() + 120
    while time.time() < deadline:
        ln = proc.stderr.readline()
        if not ln:
            break
        lines.append(ln)
        if ln.strip() == line:
            return
    proc.kill()
    proc.communicate(timeout=30)
    raise AssertionError(f"never saw {line!r}: {lines}")


def _temporaries(folder: Path) -> list[str]:
    return [p.name for p in folder.rglob("*") if ".tmp" in p.name or p.name.startswith(".")] \
        if folder.exists() else []


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_interrupt_while_tracking_writes_marked_partial(long_capture, tmp_path, sig):
    out = tmp_path / "res"
    proc = _start(long_capture, out, 0.0, "--overlay")
    lines: list = []
    _wait_for(proc, "STEP 3", lines)
    proc.send_signal(sig)
    stdout, rest = proc.communicate(timeout=120)
    err = [ln for ln in lines + rest.splitlines() if ln.strip() and not ln.startswith(("STEP",
                                                                                       "START"))]
    assert proc.returncode == 130, (stdout, err)
    assert len(err) == 1 and "interrupted; wrote the" in err[0] and "marked partial" in err[0]
    assert "Traceback" not in rest
    assert stdout.startswith("PARTIAL: interrupted (" + sig.name + ") after ")
    run = json.loads((out / "run.json").read_text())
    assert run["complete"] is False and run["interrupted_by"] == sig.name
    # the 3rd step may be cut short by the signal (it printed STEP 3 before returning)
    assert 2 <= run["frames_written"] < 40 and run["frames_in_input"] == 40
    with np.load(out / "poses.npz") as z:
        assert not bool(z["complete"]) and int(z["frames_in_input"]) == 40
        assert z["q"].shape[0] == run["frames_written"] and z["valid"].all()
    rows = (out / "diagnostics.csv").read_text().splitlines()
    assert len(rows) == 1 + run["frames_written"]
    cap = cv2.VideoCapture(str(out / "overlay.mp4"))
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) >= run["frames_written"] - 1
    cap.release()
    assert _temporaries(out) == [] and not (tmp_path / STAGING).exists()


def test_interrupt_during_setup_writes_nothing(long_capture, tmp_path):
    out = tmp_path / "res"
    proc = _start(long_capture, out, 30.0, "--overlay")
    lines: list = []
    _wait_for(proc, "START", lines)
    proc.send_signal(signal.SIGINT)
    stdout, rest = proc.communicate(timeout=60)
    assert proc.returncode == 130, (stdout, rest)
    assert rest.strip() == "jaxmocap track: interrupted; nothing written"
    assert not out.exists() or os.listdir(out) == []
    assert not (tmp_path / STAGING).exists() or os.listdir(tmp_path / STAGING) == []


def test_kill_9_leaves_no_temporary_in_out(long_capture, tmp_path):
    out = tmp_path / "res"
    proc = _start(long_capture, out, 0.0, "--overlay")
    lines: list = []
    _wait_for(proc, "STEP 3", lines)  # the overlay video is being written
    staged = [p.name for p in (tmp_path / STAGING).iterdir()]
    assert any(n.startswith(".overlay.") for n in staged), staged
    proc.kill()
    proc.communicate(timeout=30)
    assert not out.exists() or os.listdir(out) == []  # nothing but complete results in --out
    # the next run's staging sweeps the dead process's temporary
    assert sweep_temporaries(tmp_path / STAGING)
    with AtomicFiles(out) as files:
        files.path(out / "x.txt").write_text("x")
    assert os.listdir(out) == ["x.txt"] and not (tmp_path / STAGING).exists()


@pytest.mark.parametrize("argv", [["build-db", "--size", "40000", "--quiet"],
                                  ["synth", "{tmp}/ds", "--frames", "200", "--quiet"]])
def test_interrupt_elsewhere_is_one_line(tmp_path, argv):
    """Ctrl-C in build-db / synth (while importing, compiling or rendering): one line, exit
    130, nothing written."""
    argv = [a.replace("{tmp}", str(tmp_path)) for a in argv]
    if argv[0] == "build-db":
        argv += ["--out", str(tmp_path / "db.npz")]
    env = dict(os.environ, PYTHONPATH=str(ROOT), JAX_PLATFORMS="cpu")
    proc = subprocess.Popen([sys.executable, "-m", "jaxmocap.cli", *argv], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(4.0)
    proc.send_signal(signal.SIGINT)
    stdout, err = proc.communicate(timeout=120)
    assert proc.returncode == 130, (stdout, err)
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "interrupted; nothing written" in err
    assert sorted(os.listdir(tmp_path)) == []


@pytest.mark.parametrize("sig, word", [(signal.SIGINT, "interrupted"),
                                       (signal.SIGTERM, "terminated")])
def test_interrupt_wrapped_by_ctypes_is_one_line(tmp_path, monkeypatch, capsys, sig, word):
    """A signal whose handler runs inside a ctypes argument conversion (e.g. in PyOpenGL's
    function wrappers) reaches main as ``ctypes.ArgumentError``, not as the interrupt: still
    one line, exit 130, nothing written. The conversion here is real ctypes."""
    import ctypes

    from jaxmocap import cli
    from jaxmocap.commands import body as body_cmd

    class SignalsOnConversion:
        @classmethod
        def from_param(cls, obj):
            os.kill(os.getpid(), sig)
            for _ in range(1000):  # the handler runs at a bytecode boundary in here
                pass
            return obj

    labs = ctypes.CDLL(None).labs
    labs.argtypes, labs.restype = [SignalsOnConversion], ctypes.c_long

    def run(args):
        labs(ctypes.c_long(-3))
        Path(args.out).write_text("written after the signal")
        return 0

    monkeypatch.setattr(body_cmd, "run", run)
    code = cli.main(["body", "--out", str(tmp_path / "b.urdf")])
    err = capsys.readouterr().err
    assert code == cli.EXIT_INTERRUPTED, err
    assert err.strip() == f"jaxmocap body: {word}; nothing written"
    assert os.listdir(tmp_path) == []


def test_interrupt_wrapped_by_ctypes_while_tracking_writes_marked_partial(
        long_capture, tmp_path, monkeypatch, capsys):
    """The same wrapped interrupt during tracking: the frames tracked before it are written,
    marked partial, as for a plain Ctrl-C."""
    import ctypes

    from jaxmocap import cli

    class SignalsOnConversion:
        @classmethod
        def from_param(cls, obj):
            os.kill(os.getpid(), signal.SIGINT)
            for _ in range(1000):
                pass
            return obj

    labs = ctypes.CDLL(None).labs
    labs.argtypes, labs.restype = [SignalsOnConversion], ctypes.c_long

    class Wrapped:
        diagnostic_names = ("steps",)

        def __init__(self):
            self.body, self.n = default_body(), 0

        def start(self, frames):
            pass

        def step(self, frames):
            self.n += 1
            if self.n == 4:
                labs(ctypes.c_long(-3))
            q = np.zeros(self.body.n_dof)
            q[2] = 0.9
            return track_cmd.FrameResult(q, True, {"steps": float(self.n)})

        def draw(self, frames, result):
            return frames

    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: Wrapped())
    out = tmp_path / "res"
    code = cli.main(["track", "--cameras", str(long_capture / "cameras.json"),
                     str(long_capture / "cam0"), str(long_capture / "cam1"), "--out", str(out),
                     "--quiet"])
    captured = capsys.readouterr()
    assert code == cli.EXIT_INTERRUPTED, captured.err
    assert captured.out.startswith("PARTIAL: interrupted (SIGINT) after ")
    run = json.loads((out / "run.json").read_text())
    assert run["complete"] is False and run["interrupted_by"] == "SIGINT"
    assert run["frames_written"] == 3 and run["frames_in_input"] == 40


# `jaxmocap body` whose work is replaced by ``argv[1]``'s case, run through the entry point of
# ``python -m jaxmocap.cli``: the interrupt machinery of jaxmocap.cli is what is tested.
SIGNAL_CASES = """
import os, signal, sys, time
from jaxmocap import cli
from jaxmocap.commands import body

def in_string_exec(args):
    # a KeyboardInterrupt leaving a string exec: CPython's own exit would re-raise SIGINT
    exec("import os, signal\\nos.kill(os.getpid(), signal.SIGINT)\\nfor _ in range(10**7): pass")
    raise AssertionError("not interrupted")

def in_import(args):
    sys.path.insert(0, FOLDER)
    import sends_sigint_while_imported  # its body signals, then waits for a re-send
    print("after the import statement", flush=True)  # never: the interrupt lands before
    raise AssertionError("not interrupted")

def in_native_import(args):
    # the same import started by native code (PyImport_Import, as nanobind's module_::import_
    # does in jaxlib): the interrupt must not be raised into the native caller (a C++ caller
    # aborts the process) but in the Python code after it
    import ctypes
    sys.path.insert(0, FOLDER)
    native_import = ctypes.pythonapi.PyImport_ImportModule
    native_import.argtypes, native_import.restype = [ctypes.c_char_p], ctypes.py_object
    native_import(b"sends_sigint_while_imported")
    print("native import returned", flush=True)
    for _ in range(3000):  # the re-sent signal lands in here
        time.sleep(0.01)
    raise AssertionError("not interrupted")

def swallowed(args):
    try:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)
    except KeyboardInterrupt:
        pass  # a library that eats the interrupt
    time.sleep(60)

cli.LOST_INTERRUPT_S = 1.0
body.run, FOLDER = globals()[sys.argv[1]], sys.argv[2]
sys.argv[1:] = ["body", "--out", os.path.join(FOLDER, "b.urdf")]
cli.entry()
"""

SENDS_SIGINT = """
import os, signal, time
from jaxmocap import cli
os.kill(os.getpid(), signal.SIGINT)  # the handler runs before os.kill returns: deferred
assert cli._DEFERRED == [signal.SIGINT] and len(cli._TIMERS) == 1
while len(cli._TIMERS) < 2:  # until the timer sent it again and it was deferred again
    time.sleep(0.001)
done = True
print("import finished", done, flush=True)
"""


@pytest.mark.parametrize("case", ["in_string_exec", "in_import", "in_native_import",
                                  "swallowed"])
def test_interrupt_machinery_exits_130_with_one_line(tmp_path, case):
    """A KeyboardInterrupt that left a string ``exec`` (CPython's exit would make it -2); one
    that lands while a module is imported (deferred, sent again and deferred again while the
    import runs, raised where the import statement ends: never inside the import, never
    later); one that lands while native code imports a module (never raised into the native
    caller: raised by a re-send once the native call has returned); one a library swallows
    (the watchdog ends the process): each exits 130 with the one line, and writes nothing.
    Every step waits for an event, none for a time."""
    (tmp_path / "cases.py").write_text(SIGNAL_CASES)
    mods = tmp_path / "mods"
    mods.mkdir()
    (mods / "sends_sigint_while_imported.py").write_text(SENDS_SIGINT)
    out = tmp_path / "out"
    out.mkdir()
    # run as a module, like ``python -m jaxmocap.cli``: only there does CPython's exit turn an
    # interrupt that once left a string exec into SIGINT (a script's sys.exit ends earlier)
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT), str(tmp_path)]),
               JAX_PLATFORMS="cpu")
    args = [sys.executable, "-m", "cases", case, str(mods if "import" in case else out)]
    t0 = time.time()
    proc = subprocess.run(args, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 130, (proc.stdout, proc.stderr)
    assert proc.stderr.strip() == "jaxmocap body: interrupted; nothing written", proc.stderr
    if case == "in_import":  # the import ran to its end, the interrupt landed right after it
        assert proc.stdout.strip() == "import finished True"
    if case == "in_native_import":  # the native call returned the module, then it landed
        assert proc.stdout.split("\n")[:2] == ["import finished True", "native import returned"]
    if case == "swallowed":
        assert time.time() - t0 < 40
    assert os.listdir(out) == []
