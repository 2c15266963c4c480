"""Frame sources (video files, folders of frames, live cameras), image decoding and video
writing. Reading several cameras together: :mod:`jaxmocap.io.sync`.

A *source spec* (one per camera, as given on the command line) is

* a **video file** (anything OpenCV's FFmpeg backend reads: ``.mp4``, ``.avi``, ...);
* a **folder of frames**: image files (``.png``, ``.jpg``, ``.jpeg``, ``.bmp``, ``.tif``,
  ``.tiff``) read in sorted name order, one per frame;
* a **camera index** (``0``, ``1``, ...; a spec made of digits that is not an existing path):
  a live camera, read frame by frame until stopped.

Frames come out as ``uint8`` (H, W, 3) **RGB** (the library's convention; BGR only inside
OpenCV). :class:`~jaxmocap.io.sync.SyncReader` reads frame ``t`` of every camera together and
checks up front that all sources have the resolution their camera in ``cameras.json`` declares
and (for files and folders) the same number of frames; it refuses (:class:`VideoError`, an
:class:`~jaxmocap.errors.InputError`) a missing or unopenable source, a camera index that does
not open, mixed live and recorded sources, and sources with no frames.

**Damaged input is tracked as far as it is readable.** A frame that cannot be decoded (a
corrupt or empty image file, a frame of another size, a video that ends before the number of
frames its header declares — a truncated file) is yielded as ``None`` for that instant and
recorded; :meth:`~jaxmocap.io.sync.SyncReader.problems` sums them up in one line for the user.
A video frame during whose decoding FFmpeg reported an error (``illegal dc vlc``, ``Error at MB``,
``concealing errors``: the decoder returns a picture, but a damaged one) counts as unreadable
too: FFmpeg's messages (error level, ``OPENCV_FFMPEG_LOGLEVEL=16``) are read from the process's
stdout/stderr while a frame is decoded (:class:`_DecoderLog`), not shown to the user.

**Writing** (overlay videos): :class:`VideoWriter` encodes RGB frames as **H.264 in MP4**
(``yuv420p``, even width and height, ``+faststart``: what web browsers play) at the given
frame rate with PyAV's bundled FFmpeg/libx264; without it, it falls back to OpenCV's MPEG-4
Part 2 (``mp4v``) and says so in one line.
"""

from __future__ import annotations

import atexit
import contextlib
import ctypes
import os
import sys
import tempfile
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import cv2
import numpy as np

from jaxmocap.errors import InputError

__all__ = [
    "IMAGE_SUFFIXES",
    "FrameSource",
    "VideoError",
    "VideoWriter",
    "decode_image",
    "open_source",
    "quiet_ffmpeg",
]

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")


class VideoError(InputError):
    """A frame source that cannot be used (missing, unreadable, inconsistent with the others)."""


def quiet_ffmpeg() -> None:
    """Keep FFmpeg's and OpenCV's own console messages about damaged files off the console:
    OpenCV's are silenced, FFmpeg's errors are read while each frame is decoded
    (:class:`_DecoderLog`) and reported by us, in one line."""
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "16")  # AV_LOG_ERROR
    os.environ.setdefault("OPENCV_LOG_LEVEL", "SILENT")
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)


class _DecoderLog:
    """What FFmpeg prints while a call runs (OpenCV's FFmpeg log callback writes with C
    ``printf`` to stdout, FFmpeg's own to stderr): both file descriptors are pointed at a
    temporary file for the call. POSIX only (elsewhere nothing is captured)."""

    def __init__(self) -> None:
        self._ok = os.name == "posix"
        self._file = tempfile.TemporaryFile() if self._ok else None
        try:
            self._libc = ctypes.CDLL(None) if self._ok else None
        except OSError:
            self._libc = None

    def _flush(self) -> None:
        for f in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                f.flush()
        if self._libc is not None:
            self._libc.fflush(None)

    @contextlib.contextmanager
    def capture(self) -> Iterator[list[str]]:
        lines: list[str] = []
        if not self._ok:
            yield lines
            return
        self._flush()
        saved = [os.dup(1), os.dup(2)]
        try:
            os.dup2(self._file.fileno(), 1)
            os.dup2(self._file.fileno(), 2)
            yield lines
        finally:
            self._flush()
            os.dup2(saved[0], 1)
            os.dup2(saved[1], 2)
            for fd in saved:
                os.close(fd)
            self._file.seek(0)
            text = self._file.read().decode("utf-8", "replace")
            self._file.seek(0)
            self._file.truncate()
            lines.extend(ln.strip() for ln in text.splitlines() if ln.strip())

    def close(self) -> None:
        if self._file is not None:
            self._file.close()


_HARMLESS = ("libpng warning",)  # e.g. "iCCP: known incorrect sRGB profile": the image is fine
_IMAGE_LOG: _DecoderLog | None = None


def decode_image(path: str | os.PathLike, flags: int = cv2.IMREAD_COLOR
                 ) -> tuple[np.ndarray | None, str | None]:
    """(image as OpenCV decodes it, None) or (None, why) for an image file that is empty, not
    an image, or damaged. The decoders' own console messages (``libpng error: Read Error`` for
    a truncated PNG, libjpeg's ``Premature end of JPEG file``, after which it returns a
    grey-filled picture) are captured, not printed: any message but a harmless warning makes
    the image damaged, and is the ``why``."""
    global _IMAGE_LOG
    path = Path(path)
    try:
        if path.stat().st_size == 0:
            return None, "empty file"
    except OSError as e:
        return None, e.strerror
    if _IMAGE_LOG is None:  # one capture file for the process, closed at exit
        _IMAGE_LOG = _DecoderLog()
        atexit.register(_IMAGE_LOG.close)
    with _IMAGE_LOG.capture() as said:
        try:
            img = cv2.imread(str(path), flags)
        except cv2.error:
            img = None
    damage = [ln for ln in said if not ln.startswith(_HARMLESS)]
    if img is None or img.size == 0 or damage:
        why = damage[0].split(": ", 1)[-1] if damage else "not decodable"
        return None, why
    return img, None


class FrameSource:
    """One camera's frames. ``n_frames`` is None for a live camera; :meth:`read` returns the
    next frame as RGB uint8 (H, W, 3), ``None`` for an unreadable frame, and raises
    ``StopIteration`` at the end."""

    name: str
    width: int
    height: int
    n_frames: int | None
    fps: float | None = None  # frames per second, when the source knows it

    def read(self) -> np.ndarray | None:
        raise NotImplementedError

    def close(self) -> None:
        pass

    @property
    def live(self) -> bool:
        return self.n_frames is None


class _Folder(FrameSource):
    def __init__(self, path: Path):
        self.name = str(path)
        self.files = sorted(p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES
                            and p.is_file())
        if not self.files:
            raise VideoError(f"{path}: folder holds no image frames "
                             f"({', '.join(IMAGE_SUFFIXES)})")
        self.n_frames = len(self.files)
        self.errors: list[str] = []
        first = next((im for im in map(self._load, self.files[:8]) if im is not None), None)
        if first is None:
            raise VideoError(f"{path}: none of the first frames can be read as an image "
                             f"(e.g. {self.files[0].name})")
        self.height, self.width = first.shape[:2]
        self._next = 0

    @staticmethod
    def _load(p: Path) -> np.ndarray | None:
        return decode_image(p)[0]

    def read(self) -> np.ndarray | None:
        if self._next >= self.n_frames:
            raise StopIteration
        p = self.files[self._next]
        self._next += 1
        img, why = decode_image(p)
        if img is None:
            self.errors.append(f"{p.name} empty or not decodable ({why})")
            return None
        if img.shape[:2] != (self.height, self.width):
            self.errors.append(f"{p.name} is {img.shape[1]}x{img.shape[0]}")
            return None
        return np.ascontiguousarray(img[..., ::-1])


class _Capture(FrameSource):
    def __init__(self, spec: str | int, name: str, live: bool):
        self.name = name
        self.log = _DecoderLog()
        with self.log.capture():  # FFmpeg's complaints about a bad file: we say it in one line
            try:
                # one decoding thread: FFmpeg logs a damaged frame from the thread that
                # decodes it; with frame threading the message could land between two reads,
                # outside the capture, and the damage went unreported (a test flaked 2 in 3)
                self.cap = cv2.VideoCapture(spec, cv2.CAP_ANY) if live else cv2.VideoCapture(
                    spec, cv2.CAP_FFMPEG, [cv2.CAP_PROP_N_THREADS, 1])
            except cv2.error:
                self.cap = cv2.VideoCapture()
        if not self.cap.isOpened():
            self.log.close()
            self.cap.release()
            if live:
                raise VideoError(f"camera index {spec}: cannot be opened (no such camera, or "
                                 "it is in use); list cameras with e.g. `v4l2-ctl --list-devices`")
            raise VideoError(f"{name}: not a readable video (unknown format, or a damaged or "
                             "truncated file without its index)")
        self.width = int(self.cap.get(cv2.CAP_PROP_FRAME_WIDTH))
        self.height = int(self.cap.get(cv2.CAP_PROP_FRAME_HEIGHT))
        count = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = float(self.cap.get(cv2.CAP_PROP_FPS))
        self.fps = fps if np.isfinite(fps) and 0 < fps < 1000 else None
        self.n_frames = None if live else count
        if not live and count <= 0:
            self.cap.release()
            self.log.close()
            raise VideoError(f"{name}: the video declares no frames (empty file?)")
        self._t = 0
        self.ended_at: int | None = None
        self.errors: list[str] = []
        self._spec, self._index = spec, None  # (times, keyframes), demuxed when first needed
        self._damaged_from: int | None = None  # the damaged frame later frames decode from
        self.followers: dict[int, int] = {}  # damaged frame -> frames decoded from it

    def read(self) -> np.ndarray | None:
        if self.n_frames is not None and self._t >= self.n_frames:
            raise StopIteration
        self._t += 1
        if self.ended_at is not None:
            return None
        with self.log.capture() as damage:
            try:
                ok, img = self.cap.read()
            except cv2.error:
                ok, img = False, None
        if not ok or img is None or img.size == 0:
            if self.n_frames is None:
                raise StopIteration  # a live camera stopped delivering
            self.ended_at = self._t - 1
            return None
        if img.shape[:2] != (self.height, self.width):
            self.errors.append(f"frame {self._t - 1} is {img.shape[1]}x{img.shape[0]}")
            return None
        t = self._t - 1
        if self._damaged_from is not None:
            keys = self.keyframes
            if keys is not None and t < len(keys) and keys[t]:
                self._damaged_from = None  # a keyframe decodes on its own
        if damage:
            msg = damage[0].split("] ", 1)[-1]
            self.errors.append(f"frame {t} damaged (decoder: {msg})")
            if self.keyframes is not None:  # the frames up to the next keyframe decode from it
                self._damaged_from = t
            return None
        if self._damaged_from is not None:
            d = self._damaged_from
            self.followers[d] = self.followers.get(d, 0) + 1
            return None
        return np.ascontiguousarray(img[..., ::-1])

    def _indexed(self) -> tuple[np.ndarray | None, np.ndarray | None]:
        if self._index is None:
            if self.n_frames is None:  # a live camera: no container to demux
                self._index = (None, None)
            else:
                with self.log.capture():
                    self._index = _video_index(self._spec)
        return self._index

    @property
    def times(self) -> np.ndarray | None:
        """Each frame's presentation time (s from the first frame), from the container."""
        return self._indexed()[0]

    @property
    def keyframes(self) -> np.ndarray | None:
        """Whether each frame is a keyframe (decodes on its own), from the container."""
        return self._indexed()[1]

    def damage_note(self) -> str | None:
        """One phrase on the frames that decode from a damaged one (no keyframe between)."""
        if not self.followers:
            return None
        n = sum(self.followers.values())
        src = ", ".join(str(d) for d in sorted(self.followers)[:3])
        more = "s" if len(self.followers) > 1 else ""
        return (f"{n} frame{'s' if n > 1 else ''} decoded from damaged frame{more} {src} "
                "(no keyframe between) and damaged too")

    def close(self) -> None:
        self.cap.release()
        self.log.close()


def _video_index(path: str) -> tuple[np.ndarray | None, np.ndarray | None]:
    """(presentation time of each frame in seconds from the first, keyframe flag of each
    frame), in presentation order, from the container's packets (demuxed by PyAV, nothing
    decoded); (None, None) when the container gives no timestamps (then no frame is known
    to be a keyframe: damage is not propagated, and ``--sync timestamps`` is refused)."""
    try:
        import av

        with av.open(str(path)) as c:
            if not c.streams.video:
                return None, None
            stream = c.streams.video[0]
            pts, key = [], []
            for pkt in c.demux(stream):
                if pkt.size == 0:  # the demuxer's flush packet
                    continue
                if pkt.pts is None:
                    return None, None
                pts.append(int(pkt.pts))
                key.append(bool(pkt.is_keyframe))
            base = stream.time_base
    except Exception:  # noqa: BLE001 - PyAV missing or the container unreadable to it
        return None, None
    if not pts or base is None:
        return None, None
    order = np.argsort(np.asarray(pts), kind="stable")
    ticks = np.asarray(pts, np.int64)[order]
    return (ticks - ticks[0]) * float(base), np.asarray(key, bool)[order]


def open_source(spec: str | os.PathLike) -> FrameSource:
    """Open one source spec (module docstring); raises :class:`VideoError`."""
    text = str(spec)
    path = Path(text)
    if path.is_dir():
        return _Folder(path)
    if path.is_file():
        if path.stat().st_size == 0:
            raise VideoError(f"{path}: empty file (0 bytes)")
        return _Capture(text, text, live=False)
    if text.isdigit():
        return _Capture(int(text), f"camera {text}", live=True)
    raise VideoError(f"{text}: no such video file, frame folder or camera index")


# ----------------------------------------------------------------------------- writing

H264_CRF = 18  # x264 constant-rate factor: visually lossless for thin skeleton lines


def _h264_unavailable() -> str | None:
    """Why PyAV cannot encode H.264 here (one line), or None when it can."""
    try:
        import av

        av.codec.Codec("libx264", "w")
    except (ImportError, ValueError) as e:  # no PyAV, or an FFmpeg build without libx264
        return f"{type(e).__name__}: {e}".splitlines()[0]
    return None


class VideoWriter:
    """Write RGB uint8 (H, W, 3) frames to an MP4 file at ``fps`` (module docstring).

    ``codec`` is ``"h264"`` (PyAV + libx264, ``yuv420p``; an odd width or height is padded by
    one edge pixel since 4:2:0 needs even sizes) or ``"mp4v"`` (the OpenCV fallback, noted
    once on ``note``, default stderr). ``path`` must end in ``.mp4``; the caller makes it
    atomic (write to a temporary from :mod:`jaxmocap.io.atomic`).
    """

    def __init__(self, path: str | os.PathLike, fps: float, width: int, height: int,
                 note=None):
        if not (np.isfinite(fps) and fps > 0):
            raise ValueError(f"VideoWriter: fps must be > 0, got {fps}")
        self.path, self.fps, self.size = str(path), float(fps), (int(width), int(height))
        self._n = 0
        self._cv = self._av = None
        why = _h264_unavailable()
        if why is not None:
            print(f"note: H.264 encoder unavailable ({why}); writing {Path(path).name} as "
                  "MPEG-4 Part 2 (mp4v), which web browsers do not play",
                  file=sys.stderr if note is None else note)
            self.codec = "mp4v"
            self._cv = cv2.VideoWriter(self.path, cv2.VideoWriter_fourcc(*"mp4v"), self.fps,
                                       self.size)
            if not self._cv.isOpened():
                raise OSError(f"{path}: OpenCV cannot open an mp4v video writer")
            return
        import av

        self.codec = "h264"
        self.rate = Fraction(self.fps).limit_denominator(1001)
        self._av = av.open(self.path, mode="w", format="mp4",
                           options={"movflags": "+faststart"})
        stream = self._av.add_stream("libx264", rate=self.rate)
        stream.width, stream.height = (v + v % 2 for v in self.size)
        stream.pix_fmt = "yuv420p"
        stream.options = {"crf": str(H264_CRF), "preset": "medium"}
        self._stream = stream
        self._frame_cls = av.VideoFrame

    def write(self, rgb: np.ndarray) -> None:
        """Append one RGB uint8 (H, W, 3) frame of the writer's size."""
        w, h = self.size
        if rgb.shape != (h, w, 3) or rgb.dtype != np.uint8:
            raise ValueError(f"VideoWriter: frame is {rgb.shape} {rgb.dtype}, expected "
                             f"({h}, {w}, 3) uint8")
        if self._cv is not None:
            self._cv.write(np.ascontiguousarray(rgb[..., ::-1]))
            return
        img = np.pad(rgb, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge")
        frame = self._frame_cls.from_ndarray(np.ascontiguousarray(img), format="rgb24")
        frame.pts = self._n
        frame.time_base = 1 / self.rate
        for packet in self._stream.encode(frame):
            self._av.mux(packet)
        self._n += 1

    def close(self) -> None:
        """Flush the encoder and close the file (idempotent)."""
        if self._cv is not None:
            self._cv.release()
            self._cv = None
        if self._av is not None:
            for packet in self._stream.encode(None):
                self._av.mux(packet)
            self._av.close()
            self._av = None

    def __enter__(self) -> VideoWriter:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
