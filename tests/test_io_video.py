"""Frame sources and synchronised reading: frames equal to what was written (lossless PNG,
MJPG within compression error), refusals of inconsistent inputs, damaged input read as far
as it goes with the rest reported; the overlay writer's H.264 (codec, pixel format, frame
rate read back by PyAV and OpenCV) and its noted mp4v fallback."""

import io
import sys
from fractions import Fraction

import av
import cv2
import numpy as np
import pytest

from jaxmocap.io.sync import SyncReader
from jaxmocap.io.video import VideoError, VideoWriter, open_source, quiet_ffmpeg

H, W = 24, 32


def frames(n, seed=0):
    rng = np.random.default_rng(seed)
    out = np.zeros((n, H, W, 3), np.uint8)
    for t in range(n):
        out[t] = rng.integers(0, 60, 3, dtype=np.uint8)
        out[t, 4:12, 2 + 3 * t:10 + 3 * t] = (250, 40, 30)  # a moving red block
    return out


def png_folder(path, fr):
    path.mkdir()
    for t, f in enumerate(fr):
        cv2.imwrite(str(path / f"{t:04d}.png"), f[..., ::-1])
    return path


def avi(path, fr):
    size = (fr.shape[2], fr.shape[1])
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10.0, size)
    for f in fr:
        w.write(np.ascontiguousarray(f[..., ::-1]))
    w.release()
    return path


def test_folder_and_video_read_in_sync(tmp_path):
    quiet_ffmpeg()
    fr = frames(4)
    folder = png_folder(tmp_path / "cam0", fr)
    video = avi(tmp_path / "cam1.avi", fr)
    with SyncReader([folder, video], sizes=[(W, H), (W, H)]) as r:
        assert r.n_frames == 4 and not r.live
        got = list(r)
    assert [t for t, _ in got] == [0, 1, 2, 3]
    for t, f in got:
        np.testing.assert_array_equal(f[0], fr[t])  # PNG: lossless, RGB order kept
        assert np.abs(f[1].astype(int) - fr[t]).mean() < 6  # MJPG: lossy
        assert f[1, 8, 6 + 3 * t, 0] > 180 and f[1, 8, 6 + 3 * t, 2] < 90  # red stays red
    assert r.problems() is None
    with SyncReader([folder], max_frames=2) as r:
        assert [t for t, _ in r] == [0, 1]


def test_refusals(tmp_path):
    quiet_ffmpeg()
    a = png_folder(tmp_path / "a", frames(3))
    b = png_folder(tmp_path / "b", frames(2))
    with pytest.raises(VideoError, match="different lengths: .*a 3 frames, .*b 2 frames"):
        SyncReader([a, b])
    big = tmp_path / "big"
    big.mkdir()
    cv2.imwrite(str(big / "0.png"), np.zeros((H + 2, W, 3), np.uint8))
    with pytest.raises(VideoError, match=f"frames are {W}x{H + 2} but camera 'cam0'"):
        SyncReader([big], sizes=[(W, H)])
    with pytest.raises(VideoError, match="different resolutions"):
        SyncReader([a, big])
    with pytest.raises(VideoError, match="no such video file, frame folder or camera index"):
        open_source(tmp_path / "missing.mp4")
    (tmp_path / "empty").mkdir()
    with pytest.raises(VideoError, match="holds no image frames"):
        open_source(tmp_path / "empty")
    (tmp_path / "zero.mp4").write_bytes(b"")
    with pytest.raises(VideoError, match="empty file"):
        open_source(tmp_path / "zero.mp4")
    (tmp_path / "junk.mp4").write_bytes(b"this is not a video" * 10)
    with pytest.raises(VideoError, match="not a readable video"):
        open_source(tmp_path / "junk.mp4")
    with pytest.raises(VideoError, match="camera index 97: cannot be opened"):
        open_source("97")
    with pytest.raises(VideoError, match="2 inputs given for 1 cameras"):
        SyncReader([a, a], names=["cam0"])


def test_damaged_input_read_as_far_as_possible(tmp_path):
    quiet_ffmpeg()
    fr = frames(12, seed=3)
    folder = png_folder(tmp_path / "f", fr)
    (folder / "0002.png").write_bytes(b"")  # an empty frame
    (folder / "0005.png").write_bytes(b"\x89PNG\r\n\x1a\n garbage")  # a corrupt one
    with SyncReader([folder]) as r:
        got = dict(r)
        msg = r.problems()
    assert [t for t, f in got.items() if f is None] == [2, 5]
    np.testing.assert_array_equal(got[3][0], fr[3])
    assert msg.startswith("2 of 12 frames unreadable (frames 2, 5)") and "0002.png" in msg

    # a truncated AVI: the header declares 12 frames, the data hold fewer
    rng = np.random.default_rng(0)
    noisy = rng.integers(0, 255, (12, H, W, 3), dtype=np.uint8)  # incompressible: even sizes
    data = avi(tmp_path / "v.avi", noisy).read_bytes()
    (tmp_path / "t.avi").write_bytes(data[: int(len(data) * 0.7)])
    with SyncReader([tmp_path / "t.avi"]) as r:
        got = dict(r)
        msg = r.problems()
    n_ok = sum(f is not None for f in got.values())
    assert len(got) == 12 and 3 <= n_ok < 12
    assert all(got[t] is not None for t in range(n_ok))  # a readable prefix
    # the last frame the decoder returned may be cut by the truncation: FFmpeg says so and it
    # counts as unreadable (damaged) too
    cut = f"frame {n_ok} damaged (decoder: " in msg
    assert f"ends after {n_ok + cut} of 12 declared frames (truncated or corrupt)" in msg


@pytest.mark.parametrize("fps", [30.0, 29.97, 10.0])
def test_writer_h264_browser_playable_at_source_rate(tmp_path, fps):
    fr = frames(6)[:, :23, :31]  # odd height and width: 4:2:0 needs even ones (padded)
    path = tmp_path / "v.mp4"
    with VideoWriter(path, fps, 31, 23) as w:
        assert w.codec == "h264"
        for f in fr:
            w.write(np.ascontiguousarray(f))
    with av.open(str(path)) as c:
        s = c.streams.video[0]
        assert s.codec_context.name == "h264" and s.codec_context.pix_fmt == "yuv420p"
        assert (s.width, s.height) == (32, 24)
        assert s.average_rate == Fraction(fps).limit_denominator(1001)
        got = [f.to_ndarray(format="rgb24") for f in c.decode(video=0)]
        assert c.format.name.split(",")[0] == "mov"  # the MP4 family of containers
    assert len(got) == 6
    for g, f in zip(got, fr, strict=True):  # the content (x264 at CRF 18, 4:2:0 chroma)
        assert np.abs(g[:23, :31].astype(int) - f).mean() < 6
    cap = cv2.VideoCapture(str(path))  # a second reader: OpenCV's FFmpeg
    assert cap.get(cv2.CAP_PROP_FPS) == pytest.approx(fps, rel=1e-4)
    assert int(cap.get(cv2.CAP_PROP_FRAME_COUNT)) == 6
    cap.release()


def test_writer_falls_back_to_mp4v_with_a_note(tmp_path, monkeypatch):
    monkeypatch.setitem(sys.modules, "av", None)  # as if PyAV were not installed
    note = io.StringIO()
    path = tmp_path / "v.mp4"
    with VideoWriter(path, 15.0, W, H, note=note) as w:
        assert w.codec == "mp4v"
        for f in frames(4):
            w.write(f)
    lines = note.getvalue().splitlines()
    assert len(lines) == 1 and "mp4v" in lines[0] and "H.264 encoder unavailable" in lines[0]
    with av.open(str(path)) as c:  # the module imported above, still usable
        s = c.streams.video[0]
        assert s.codec_context.name == "mpeg4" and s.average_rate == 15  # MPEG-4 Part 2
        assert s.frames == 4
    with pytest.raises(ValueError, match="expected \\(24, 32, 3\\) uint8"):
        VideoWriter(tmp_path / "w.mp4", 15.0, W, H, note=note).write(np.zeros((2, 2, 3)))


def test_decoder_chatter_is_captured_and_the_image_counted_damaged(tmp_path, capfd):
    """A truncated PNG makes libpng print ``libpng error: Read Error`` on the process's
    stderr, a truncated JPEG libjpeg ``Premature end of JPEG file`` (and a grey-filled
    picture): neither reaches the console, both are unreadable frames with the reason."""
    from jaxmocap.commands.colors import read_rgb
    from jaxmocap.errors import InputError
    from jaxmocap.io.video import decode_image

    fr = np.random.default_rng(0).integers(0, 255, (3, 48, 64, 3), np.uint8)  # 9 kB PNGs
    folder = png_folder(tmp_path / "cam", fr)
    png = (folder / "0001.png").read_bytes()
    (folder / "0001.png").write_bytes(png[:-300])  # the last IDAT cut short, no IEND
    cv2.imwrite(str(tmp_path / "a.jpg"), fr[0])
    jpg = (tmp_path / "a.jpg").read_bytes()
    (tmp_path / "a.jpg").write_bytes(jpg[: len(jpg) * 2 // 3])
    capfd.readouterr()
    with SyncReader([folder]) as r:
        got = [f is None for _, f in r]
        problems = r.problems()
    img, why = decode_image(tmp_path / "a.jpg")
    with pytest.raises(InputError) as e:
        read_rgb(folder / "0001.png")
    out, err = capfd.readouterr()
    assert (out, err) == ("", "")
    assert got == [False, True, False]
    assert "0001.png empty or not decodable (Read Error)" in problems
    assert img is None and why == "Premature end of JPEG file"
    assert str(e.value).endswith("not a readable image (empty or corrupt: Read Error)")
    ok, why = decode_image(folder / "0000.png")
    assert why is None and np.array_equal(ok[..., ::-1], fr[0])
