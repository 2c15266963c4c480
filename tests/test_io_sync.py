"""Camera synchronisation and damaged video (``io/video``): inputs of different frame rates
are refused before any work, in one line with the numbers, unless ``--sync timestamps``
resamples them to the first camera's clock (checked against the frames' known content); a
frame decoded after a damaged one without a keyframe in between counts as damaged too."""

import json
from fractions import Fraction

import av
import numpy as np
import pytest
from test_cli import run_cli
from test_cli_badinput import _Fixed

from jaxmocap.camera import look_at
from jaxmocap.commands import track as track_cmd
from jaxmocap.io.cameras import save_cameras
from jaxmocap.io.sync import SyncReader, resample_to_first
from jaxmocap.io.video import VideoError, quiet_ffmpeg

H, W = 48, 64


def level(t_s: float) -> int:
    """The grey level of the frame shown at time ``t_s`` (the content says when it was; it
    wraps after 1.1 s)."""
    return int(round(10 + 180 * t_s)) % 200


def video(path, fps, n, gop=5, texture=False):
    """MPEG-4 Part 2 at ``fps``, a keyframe every ``gop`` frames, no B-frames; frame k is
    grey ``level(k / fps)`` (with ``texture``: a moving random block, for P-frames that
    carry data)."""
    rng = np.random.default_rng(0)
    tex = rng.integers(0, 255, (32, 32, 3), np.uint8)
    with av.open(str(path), "w") as c:
        s = c.add_stream("mpeg4", rate=Fraction(fps))
        s.width, s.height, s.pix_fmt = W, H, "yuv420p"
        s.codec_context.gop_size = gop
        s.bit_rate = 4_000_000  # near lossless: grey levels within 1
        for k in range(n):
            img = np.full((H, W, 3), level(k / fps), np.uint8)
            if texture:
                img[8:40, 2 + k:34 + k] = tex
            f = av.VideoFrame.from_ndarray(img, format="rgb24")
            f.pts = k
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode(None):
            c.mux(p)
    return path


@pytest.fixture(autouse=True)
def _quiet():
    quiet_ffmpeg()


def test_different_frame_rates_refused_with_the_numbers(tmp_path):
    a, b = video(tmp_path / "a.mp4", 30, 30), video(tmp_path / "b.mp4", 15, 30)
    with pytest.raises(VideoError) as e:  # same length, different rates: still refused
        SyncReader([a, b])
    msg = str(e.value)
    assert "\n" not in msg
    assert f"different frame rates: {a} 30 fps, {b} 15 fps" in msg and "--sync timestamps" in msg


def test_sync_timestamps_pairs_the_nearest_frames(tmp_path):
    a, b = video(tmp_path / "a.mp4", 30, 30), video(tmp_path / "b.mp4", 15, 15)
    with SyncReader([a, b], ["left", "right"], sync="timestamps") as r:
        assert r.n_frames == 30
        assert "resampled to left's clock (30 fps, 30 instants" in r.sync_report
        assert "right 15 frames: nearest frame, up to 33 ms off, 15 repeated" in r.sync_report
        got = [(t, f[:, H // 2, W // 2].astype(int).mean(-1)) for t, f in r]
    assert [t for t, _ in got] == list(range(30))
    for t, (l0, l1) in got:
        assert abs(l0 - level(t / 30)) <= 3, (t, l0)
        assert abs(l1 - level((t // 2) / 15)) <= 3, (t, l1)  # ties go to the earlier frame


def test_sync_timestamps_cuts_to_the_common_span_and_skips(tmp_path):
    times = [np.arange(10) / 10, np.arange(12) / 20]  # 10 fps for 1 s; 20 fps for 0.6 s
    index, line = resample_to_first(times, ["a", "b"])
    assert index[0].tolist() == list(range(6))
    assert index[1].tolist() == [0, 2, 4, 6, 8, 10]
    assert "cut to the 6 of 10 instants all cameras cover" in line and "5 skipped" in line
    with pytest.raises(VideoError, match="share no instant"):
        resample_to_first([np.arange(5) / 10, np.arange(5) / 10 + 10.0], ["a", "b"])


def test_sync_timestamps_refuses_frame_folders(tmp_path):
    import cv2

    a = video(tmp_path / "a.mp4", 10, 5)
    folder = tmp_path / "frames"
    folder.mkdir()
    for k in range(5):
        cv2.imwrite(str(folder / f"{k}.png"), np.zeros((H, W, 3), np.uint8))
    with pytest.raises(VideoError) as e:
        SyncReader([a, folder], sync="timestamps")
    assert str(e.value).startswith(f"{folder}: --sync timestamps needs each frame's timestamp "
                                   "(a folder of frames)")


def test_frames_decoded_from_a_damaged_one_are_damaged_until_the_keyframe(tmp_path):
    clean = video(tmp_path / "clean.mp4", 10, 20, gop=5, texture=True)
    with av.open(str(clean)) as c:
        packets = [(p.pos, p.size, p.is_keyframe) for p in c.demux(c.streams.video[0])
                   if p.size]
    assert [k for _, _, k in packets] == [k % 5 == 0 for k in range(20)]
    data = bytearray(clean.read_bytes())
    pos, size, _ = packets[6]  # a P-frame: frames 7-9 are predicted from it, 10 is a keyframe
    i = pos + int(size * 0.7)
    data[i] ^= 0xFF
    data[i + 1] ^= 0x55
    bad = tmp_path / "bad.mp4"
    bad.write_bytes(bytes(data))
    with SyncReader([bad]) as r:
        unread = [t for t, f in r if f is None]
        problems = r.problems()
    assert unread == [6, 7, 8, 9]
    assert problems.startswith("4 of 20 frames unreadable (frames 6-9): ")
    assert "frame 6 damaged (decoder:" in problems
    assert "3 frames decoded from damaged frame 6 (no keyframe between) and damaged too" \
        in problems


# ----------------------------------------------------------------------------- the command


def make_capture(root):
    """``root`` with a two-camera ``cameras.json``, ``a.mp4`` (30 fps, 12 frames) and
    ``b.mp4`` (15 fps, 6 frames): the same 0.4 s at two rates."""
    cams = [look_at([2.5, y, 1.2], [0, 0, 1.1], width=W, height=H, fx=40.0) for y in (-.3, .3)]
    save_cameras(root / "cameras.json", cams)
    video(root / "a.mp4", 30, 12)
    video(root / "b.mp4", 15, 6)
    return root


@pytest.fixture
def capture(tmp_path):
    return make_capture(tmp_path)


def test_track_refuses_or_resamples(capture, capsys, monkeypatch):
    k = capture
    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: _Fixed())
    before = {p: p.read_bytes() for p in k.iterdir()}
    argv = ["track", "--cameras", k / "cameras.json", k / "a.mp4", k / "b.mp4", "--quiet",
            "--formats", "npz"]
    rc, out, err = run_cli(capsys, *argv, "--out", k / "res")
    assert rc == 2 and len(err) == 1, (rc, err)
    assert "different frame rates" in err[0] and "30 fps" in err[0] and "15 fps" in err[0]
    assert not (k / "res").exists()
    assert {p: p.read_bytes() for p in k.iterdir()} == before
    rc, out, err = run_cli(capsys, *argv, "--out", k / "res", "--sync", "timestamps")
    assert rc == 0 and err == [], (rc, out, err)
    assert "jaxmocap track: --sync timestamps: resampled to cam0's clock (30 fps, 12 instants" \
        in out
    doc = json.loads((k / "res/run.json").read_text())
    assert doc["sync"] == "timestamps" and doc["frames_written"] == 12
    assert "cam1 6 frames" in doc["sync_report"]


def _flashes(path, levels, fps=10):
    with av.open(str(path), "w") as c:
        s = c.add_stream("mpeg4", rate=Fraction(fps))
        s.width, s.height, s.pix_fmt, s.bit_rate = W, H, "yuv420p", 4_000_000
        for k, v in enumerate(levels):
            f = av.VideoFrame.from_ndarray(np.full((H, W, 3), v, np.uint8), format="rgb24")
            f.pts = k
            for p in s.encode(f):
                c.mux(p)
        for p in s.encode(None):
            c.mux(p)
    return path


def test_motion_cross_correlation_finds_a_start_offset(tmp_path):
    """Camera b started recording 3 frames (0.3 s) before camera a: every change of the
    scene shows in b 3 frames later. The estimate finds +3 frames; the aligned pair, 0."""
    scene = np.random.default_rng(1).integers(20, 230, 43).astype(np.uint8)
    a = _flashes(tmp_path / "a.mp4", scene[3:])
    b = _flashes(tmp_path / "b.mp4", scene[:40])
    for other, expect in ((b, 3), (a, 0)):
        with SyncReader([a, other], ["a", "b"]) as r:
            assert r.motion_offsets() is None  # nothing read yet
            for _ in r:
                pass
            (est,) = r.motion_offsets()
        assert est["camera"] == "b" and est["offset_frames"] == expect, est
        assert est["offset_s"] == pytest.approx(expect / 10) and est["peak"] > 0.9


def test_track_notes_a_motion_offset(capture, capsys, monkeypatch):
    k = capture
    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: _Fixed())
    scene = np.random.default_rng(1).integers(20, 230, 43).astype(np.uint8)
    _flashes(k / "early.mp4", scene[3:])
    _flashes(k / "late.mp4", scene[:40])
    rc, out, err = run_cli(capsys, "track", "--cameras", k / "cameras.json", k / "early.mp4",
                           k / "late.mp4", "--quiet", "--formats", "npz", "--out", k / "res")
    assert rc == 0 and err == [], (out, err)
    assert ("jaxmocap track: note: the cameras' image motion suggests they are not "
            "simultaneous: cam1 sees it 300 ms later than cam0 (correlation ") in out
    doc = json.loads((k / "res/run.json").read_text())
    assert [(o["camera"], o["offset_frames"]) for o in doc["motion_offsets"]] == [("cam1", 3)]
