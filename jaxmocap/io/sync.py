"""Reading several cameras together (:class:`SyncReader`): frame ``t`` of every camera as one
instant, the checks a capture needs before tracking starts (resolutions, frame counts, frame
rates), ``--sync timestamps`` (every video resampled to the first camera's clock) and the
motion cross-correlation estimate of the cameras' offsets. The sources: :mod:`jaxmocap.io.video`.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence

import cv2
import numpy as np

from jaxmocap.io.video import FrameSource, VideoError, _Capture, _Folder, open_source

MOTION_SIZE = (32, 24)  # image motion for the offset estimate: grey images shrunk to this
MAX_LAG_S = 2.0  # the offsets the motion cross-correlation looks for, either way
MIN_MOTION_FRAMES = 10  # instants both cameras must share for an offset estimate
FPS_TOLERANCE = 1e-4  # relative; 29.97 vs 30 fps (1e-3) drift apart a frame every 33 s

__all__ = ["SYNC_MODES", "SyncReader", "check_frame_rates", "resample_to_first"]


def check_frame_rates(sources: Sequence[FrameSource], remedy: str) -> None:
    """Refuse (:class:`VideoError`, one line with the numbers) recorded sources whose frame
    rates differ (by more than :data:`FPS_TOLERANCE`): frame t of each is then not one
    instant. Sources that do not know their rate (folders of frames) are not compared."""
    rates = [(s.name, s.fps) for s in sources if s.fps]
    known = [r for _, r in rates]
    if known and max(known) - min(known) > FPS_TOLERANCE * max(known):
        listing = ", ".join(f"{n} {r:.4g} fps" for n, r in rates)
        raise VideoError(f"inputs have different frame rates: {listing}; their frames are "
                         f"not simultaneous: {remedy}")


class _Resampled(FrameSource):
    """Frames ``index[k]`` of ``source`` for k = 0, 1, ... (non-decreasing: a frame is
    repeated or frames are skipped, each frame read once from the source)."""

    def __init__(self, source: FrameSource, index: np.ndarray):
        self.source, self.index = source, [int(i) for i in index]
        self.name, self.width, self.height = source.name, source.width, source.height
        self.fps, self.n_frames = source.fps, len(self.index)
        self._k, self._at, self._frame = 0, -1, None

    def read(self) -> np.ndarray | None:
        if self._k >= len(self.index):
            raise StopIteration
        want = self.index[self._k]
        self._k += 1
        while self._at < want:
            self._frame = self.source.read()
            self._at += 1
        return self._frame

    def close(self) -> None:
        self.source.close()


SYNC_MODES = ("frames", "timestamps")


def resample_to_first(times: Sequence[np.ndarray], names: Sequence[str]
                      ) -> tuple[list[np.ndarray], str]:
    """The nearest frame of each camera at each frame time of the first camera (its clock),
    over the instants every camera covers (within half of its frame interval), and a line
    saying what was done. ``times``: each camera's frame times (s from its first frame; the
    recordings are assumed to start together). Raises :class:`VideoError` if no instant is
    covered by all."""
    t0 = np.asarray(times[0], float)
    indices, covered = [], np.ones(len(t0), bool)
    for ts in times:
        ts = np.asarray(ts, float)
        half = 0.5 * (float(np.median(np.diff(ts))) if len(ts) > 1 else 0.0)
        after = np.searchsorted(ts, t0)  # the first frame at or after each instant
        lo, hi = np.clip(after - 1, 0, len(ts) - 1), np.clip(after, 0, len(ts) - 1)
        j = np.where(np.abs(ts[lo] - t0) <= np.abs(ts[hi] - t0) + 1e-9, lo, hi)  # ties: earlier
        covered &= np.abs(ts[j] - t0) <= half * (1 + 1e-6) + 1e-9  # ties: rounded times
        indices.append(j)
    n = int(np.argmin(covered)) if not covered.all() else len(t0)  # the leading covered span
    if n == 0:
        raise VideoError(f"--sync timestamps: the cameras share no instant ({names[0]} starts "
                         "where another has no frame)")
    rate = (len(t0) - 1) / t0[-1] if len(t0) > 1 and t0[-1] > 0 else float("nan")
    parts = []
    for name, ts, j in zip(names[1:], times[1:], indices[1:], strict=True):
        j = j[:n]
        off = float(np.max(np.abs(np.asarray(ts)[j] - t0[:n]))) * 1e3
        rep = n - len(np.unique(j))
        skip = int(j[-1] - j[0] + 1) - len(np.unique(j))
        parts.append(f"{name} {len(ts)} frames: nearest frame, up to {off:.0f} ms off"
                     + (f", {rep} repeated" if rep else "") + (f", {skip} skipped" if skip else ""))
    cut = f", cut to the {n} of {len(t0)} instants all cameras cover" if n < len(t0) else ""
    line = (f"--sync timestamps: resampled to {names[0]}'s clock ({rate:.3g} fps, {n} instants "
            f"over {t0[n - 1]:.2f} s{cut}): " + "; ".join(parts))
    return [j[:n] for j in indices], line


class SyncReader:
    """Frame ``t`` of every source at once: ``for t, frames in reader`` gives ``frames`` uint8
    (n_cams, H, W, 3) RGB, or ``None`` when some camera's frame ``t`` is unreadable.

    ``sizes`` — the (width, height) each source must have (from ``cameras.json``).
    ``max_frames`` — stop after this many instants (needed to end a live capture, or to
    track a prefix of a recording).
    """

    def __init__(self, specs: Sequence[str | os.PathLike], names: Sequence[str] | None = None,
                 sizes: Sequence[tuple[int, int]] | None = None, max_frames: int | None = None,
                 sync: str = "frames"):
        if not specs:
            raise VideoError("no input given: pass one video, frame folder or camera index "
                             "per camera")
        names = [f"cam{i}" for i in range(len(specs))] if names is None else list(names)
        if len(names) != len(specs):
            raise VideoError(f"{len(specs)} inputs given for {len(names)} cameras "
                             f"({', '.join(names)}); give one input per camera, in that order")
        if max_frames is not None and max_frames < 1:
            raise VideoError(f"--max-frames must be >= 1, got {max_frames}")
        if sync not in SYNC_MODES:
            raise VideoError(f"--sync {sync!r}: expected one of {', '.join(SYNC_MODES)}")
        self.names = names
        self.sources: list[FrameSource] = []
        self.sync_report: str | None = None
        try:
            for s in specs:
                self.sources.append(open_source(s))
            self._check(sizes, sync)
            if sync == "timestamps":
                self._resample()
        except BaseException:
            self.close()
            raise
        counts = [s.n_frames for s in self.sources]
        self.n_frames = None if counts[0] is None else counts[0]
        if max_frames is not None:
            self.n_frames = max_frames if self.n_frames is None else min(self.n_frames, max_frames)
        self.missing: list[int] = []
        self.n_read = 0
        self.fps = next((s.fps for s in self.sources if s.fps), None)
        self._motion: list[list[float]] = [[] for _ in self.sources]  # image motion per instant
        self._last: list[np.ndarray | None] = [None] * len(self.sources)

    def _resample(self) -> None:
        """``--sync timestamps``: every camera read at the first camera's frame times."""
        if self.sources[0].live:
            raise VideoError("--sync timestamps: live cameras are read as they come; it "
                             "resamples recorded videos")
        for s in self.sources:
            if getattr(s, "times", None) is None:
                why = "a folder of frames" if isinstance(s, _Folder) else "its container " \
                    "gives none"
                raise VideoError(f"{s.name}: --sync timestamps needs each frame's timestamp "
                                 f"({why}); give videos, or cut the inputs to the same "
                                 "synchronised frames and drop --sync")
        times = []
        for s in self.sources:  # frames the container lists but OpenCV does not read: dropped
            times.append(s.times[:s.n_frames])
        index, self.sync_report = resample_to_first(times, self.names)
        self.sources = [_Resampled(s, j) for s, j in zip(self.sources, index, strict=True)]

    def _check(self, sizes, sync: str = "frames") -> None:
        src = self.sources
        live = [s.live for s in src]
        if any(live) and not all(live):
            raise VideoError("mixed live cameras and recorded files: use either camera indices "
                             "or videos/frame folders for all cameras")
        if sizes is not None:
            for s, name, (w, h) in zip(src, self.names, sizes, strict=True):
                if (s.width, s.height) != (int(w), int(h)):
                    raise VideoError(f"{s.name}: frames are {s.width}x{s.height} but camera "
                                     f"{name!r} in cameras.json is {w}x{h}; give the inputs in "
                                     "the cameras' order, at the calibrated resolution")
        else:
            res = {(s.width, s.height) for s in src}
            if len(res) > 1:
                listing = ", ".join(f"{s.name} {s.width}x{s.height}" for s in src)
                raise VideoError(f"inputs have different resolutions: {listing}")
        if sync == "timestamps":
            return
        if not any(live):
            check_frame_rates(src, "record at one rate, or pass --sync timestamps to resample "
                              "them to the first camera's clock")
        counts = [s.n_frames for s in src]
        if not any(live) and len(set(counts)) > 1:
            listing = ", ".join(f"{s.name} {n} frames" for s, n in zip(src, counts, strict=True))
            raise VideoError(f"inputs have different lengths: {listing}; cut them to the same "
                             "synchronised frames (or, for videos, pass --sync timestamps)")

    @property
    def live(self) -> bool:
        return self.sources[0].live

    def __iter__(self) -> Iterator[tuple[int, np.ndarray | None]]:
        t = 0
        while self.n_frames is None or t < self.n_frames:
            frames = []
            try:
                for s in self.sources:
                    frames.append(s.read())
            except StopIteration:
                return
            self._record_motion(frames)
            if any(f is None for f in frames):
                self.missing.append(t)
                yield t, None
            else:
                self.n_read += 1
                yield t, np.stack(frames)
            t += 1

    def _record_motion(self, frames: list[np.ndarray | None]) -> None:
        """Each camera's image motion at this instant: the mean absolute change of its
        grey image (shrunk to :data:`MOTION_SIZE`) since the previous instant; NaN where a
        frame is missing."""
        for c, f in enumerate(frames):
            small = None if f is None else cv2.resize(
                cv2.cvtColor(f, cv2.COLOR_RGB2GRAY), MOTION_SIZE,
                interpolation=cv2.INTER_AREA).astype(np.float32)
            prev = self._last[c]
            self._motion[c].append(np.nan if small is None or prev is None
                                   else float(np.abs(small - prev).mean()))
            self._last[c] = small

    def motion_offsets(self, max_lag_s: float = MAX_LAG_S) -> list[dict] | None:
        """For each camera after the first, the time shift that best aligns its image motion
        with the first camera's over the instants read so far (normalised cross-correlation
        of the two motion signals, whole instants within ``max_lag_s``): ``{"camera",
        "offset_s", "offset_frames", "peak"}``, a positive offset meaning that camera sees
        the same motion later (its recording started earlier). None with one camera, no
        known frame rate, or too few frames (:data:`MIN_MOTION_FRAMES`)."""
        if len(self.sources) < 2 or not self.fps:
            return None
        ref = np.asarray(self._motion[0], float)
        if np.isfinite(ref).sum() < MIN_MOTION_FRAMES:
            return None
        k = max(1, int(round(max_lag_s * self.fps)))
        out = []
        for name, sig in zip(self.names[1:], self._motion[1:], strict=True):
            lag, peak = _best_lag(ref, np.asarray(sig, float), k)
            if lag is None:
                return None
            out.append({"camera": name, "offset_frames": lag,
                        "offset_s": round(lag / self.fps, 6), "peak": round(peak, 3)})
        return out

    def problems(self) -> str | None:
        """One line describing the unreadable frames so far, or None if all were read."""
        if not self.missing:
            return None
        parts = []
        for s in self.sources:
            s = getattr(s, "source", s)  # under --sync timestamps: the resampled source
            if isinstance(s, _Capture) and s.ended_at is not None:
                parts.append(f"{s.name} ends after {s.ended_at} of {s.n_frames} declared frames "
                             "(truncated or corrupt)")
            errors = getattr(s, "errors", [])
            note = s.damage_note() if isinstance(s, _Capture) else None
            if errors or note:
                more = f" (+{len(errors) - 3} more)" if len(errors) > 3 else ""
                text = "; ".join(errors[:3]) + more
                parts.append(f"{s.name}: " + "; ".join(t for t in (text, note) if t))
        return (f"{len(self.missing)} of {self.n_read + len(self.missing)} frames unreadable "
                f"({_ranges(self.missing)}): " + "; ".join(parts))

    def close(self) -> None:
        for s in self.sources:
            s.close()

    def __enter__(self) -> SyncReader:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _best_lag(a: np.ndarray, b: np.ndarray, max_lag: int) -> tuple[int | None, float]:
    """The lag L in ``-max_lag..max_lag`` maximising the normalised correlation of ``a[t]``
    with ``b[t + L]`` over the instants where both are finite (at least half the shorter
    signal's), and that correlation; (None, nan) when no lag has enough overlap or a signal
    is flat."""
    best, best_r = None, -np.inf
    need = max(MIN_MOTION_FRAMES, min(len(a), len(b)) // 2)
    for lag in range(-max_lag, max_lag + 1):
        t0, t1 = max(0, -lag), min(len(a), len(b) - lag)  # a[t] pairs with b[t + lag]
        if t1 <= t0:
            continue
        x, y = a[t0:t1], b[t0 + lag:t1 + lag]
        ok = np.isfinite(x) & np.isfinite(y)
        if ok.sum() < need:
            continue
        x, y = x[ok] - x[ok].mean(), y[ok] - y[ok].mean()
        den = float(np.sqrt((x * x).sum() * (y * y).sum()))
        if den <= 0:
            continue
        r = float((x * y).sum()) / den
        if r > best_r:
            best, best_r = lag, r
    return best, (best_r if best is not None else float("nan"))


def _ranges(ts: Sequence[int]) -> str:
    """'3, 7-9' for [3, 7, 8, 9]."""
    out, start = [], None
    for i, t in enumerate(ts):
        if start is None:
            start = t
        if i + 1 == len(ts) or ts[i + 1] != t + 1:
            out.append(str(start) if start == t else f"{start}-{t}")
            start = None
    return "frames " + ", ".join(out)
