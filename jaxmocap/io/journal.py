"""The journal of a ``track`` run: every tracked frame on disk as soon as it is tracked, and the
tracker's state now and then, so that a kill, a full disk or a read-only output folder loses
nothing tracked and ``track --resume OUT`` continues where the run stopped.

The journal is a hidden folder **beside** the output folder (``<parent>/.<name>.jaxmocap-
journal``, like the run's lock file: it exists before ``--out`` does and never appears in it):

* ``meta.json`` -- the run's settings (its parsed command line) and what its inputs were (size
  and modification time of every input file), written once, atomically;
* ``frames.jsonl`` -- one JSON line per instant, appended and flushed as the frame is tracked
  (``t``, ``read``, ``valid``, ``q`` and the diagnostics; floats written as
  Python writes them, so they read back bit for bit; NaN as ``NaN``). A line a kill cut in two
  is dropped on reading;
* ``checkpoint.pkl`` -- the tracker's state after frame ``frames - 1`` (its particles, RNG key,
  blob tracks, white balance, ...: :meth:`FrameTracker.checkpoint`), a SHA-256 digest line
  followed by the pickled state, replaced atomically at most every ``every_s`` seconds (and
  after the last frame), after the frame lines it covers were ``fsync``'ed.

Resuming keeps the first ``frames`` lines of the checkpoint, restores the state, and tracks
from there: what was tracked after the checkpoint (at most ``every_s`` seconds of tracking) is
tracked again, to the same numbers where the tracker is deterministic. The journal is removed
once the outputs are promoted complete; it stays after an interrupt, a kill or a failed write
(every message of those says where it is and how to resume).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import math
import os
import pickle
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

from jaxmocap.errors import InputError
from jaxmocap.io.atomic import describe_os_error, write_bytes, write_text

JOURNAL_FORMAT = "jaxmocap.track_journal"
JOURNAL_VERSION = 1
CHECKPOINT_EVERY_S = 1.0  # default: at most this much tracking is redone after a kill
FSYNC_EVERY_S = 1.0  # frame lines reach the disk (not only the kernel) at least this often


def journal_path(out: str | os.PathLike) -> Path:
    """The journal folder of the output folder ``out``: ``<parent>/.<name>.jaxmocap-journal``."""
    out = Path(out)
    return (out.parent if str(out.parent) else Path(".")) / f".{out.name}.jaxmocap-journal"


def input_stamps(paths) -> list[dict]:
    """Size and modification time of every input file (a frame folder: of each file in it),
    to tell on resume whether the inputs are still the ones the journal was tracked from."""
    out = []
    for p in paths:
        p = Path(p)
        files = sorted(q for q in p.iterdir() if q.is_file()) if p.is_dir() else [p]
        for f in files:
            st = f.stat()
            out.append({"path": os.path.abspath(f), "size": st.st_size,
                        "mtime_ns": st.st_mtime_ns})
    return out


def _line(t: int, read: bool, valid: bool, q: np.ndarray, diagnostics: dict) -> str:
    rec = {"t": int(t), "read": bool(read), "valid": bool(valid),
           "q": [float(v) for v in np.asarray(q, np.float64).ravel()],
           "diagnostics": {k: float(v) for k, v in diagnostics.items()}}
    return json.dumps(rec, allow_nan=True) + "\n"


class Journal:
    """An open journal (module docstring): :meth:`create` for a new run, :meth:`resume` for an
    interrupted one; :meth:`append` after every instant, :meth:`checkpoint` when
    :meth:`checkpoint_due`, :meth:`remove` once the outputs are promoted.

    A write that fails (disk full) does not stop the tracking: the journal is marked failed
    (:attr:`failure`, one line) and the frames stay in memory for the outputs. The journal
    holds no frame in memory (a long capture's memory does not grow by it): only the records
    a resumed run read back (:attr:`resumed`) until they are handed over."""

    def __init__(self, folder: Path, resumed: list[dict], every_s: float) -> None:
        self.folder = folder
        self.resumed = resumed  # a resumed run's records (read once; the rest stays on disk)
        self.count = len(resumed)  # frames journalled
        self.every_s = every_s
        self.failure: str | None = None
        self._file = None
        self._last_sync = self._last_ckpt = time.monotonic()
        self.checkpointed = 0  # frames covered by the checkpoint on disk

    # ------------------------------------------------------------------ opening
    @classmethod
    def create(cls, out: Path, meta: dict, every_s: float = CHECKPOINT_EVERY_S) -> Journal:
        folder = journal_path(out)
        try:
            if folder.exists():
                shutil.rmtree(folder)
            folder.mkdir(parents=True)
            write_text(folder / "meta.json", json.dumps(
                {"format": JOURNAL_FORMAT, "version": JOURNAL_VERSION, **meta}, indent=1) + "\n")
        except OSError as e:
            raise InputError(f"the journal of --out {out}: {describe_os_error(e)}; free some "
                             "space or choose another output folder") from None
        j = cls(folder, [], every_s)
        j._open()
        return j

    @staticmethod
    def read_meta(out: Path) -> dict:
        """The ``meta.json`` of ``out``'s journal (one line if missing or unreadable)."""
        folder = journal_path(out)
        path = folder / "meta.json"
        if not path.is_file():
            raise InputError(f"--resume {out}: no journal of an interrupted run beside it "
                             f"({folder}); nothing to resume")
        try:
            meta = json.loads(path.read_text())
        except (OSError, ValueError) as e:
            raise InputError(f"{path}: the journal's settings cannot be read ({e}); track "
                             "again without --resume (with --overwrite)") from None
        if not (isinstance(meta, dict) and meta.get("format") == JOURNAL_FORMAT
                and meta.get("version") == JOURNAL_VERSION and isinstance(meta.get("args"), dict)):
            raise InputError(f"{path}: not a journal this jaxmocap writes ({JOURNAL_FORMAT} "
                             f"version {JOURNAL_VERSION}); track again without --resume")
        return meta

    @classmethod
    def resume(cls, out: Path, every_s: float = CHECKPOINT_EVERY_S
               ) -> tuple[Journal, Any, str | None]:
        """(the journal truncated to its checkpoint, the tracker state to restore or None,
        a one-line note when the journal could not be used as far as it went)."""
        folder = journal_path(out)
        frames = _read_frames(folder / "frames.jsonl")
        state, n, note = None, 0, None
        ckpt = folder / "checkpoint.pkl"
        if ckpt.is_file():
            try:
                raw = ckpt.read_bytes()
                digest, _, body = raw.partition(b"\n")
                if hashlib.sha256(body).hexdigest().encode() != digest:
                    raise ValueError("its digest does not match its content")
                doc = pickle.loads(body)
                n, state = int(doc["frames"]), doc["tracker"]
            except (OSError, ValueError, KeyError, pickle.UnpicklingError, EOFError) as e:
                note = (f"{ckpt}: the tracker's checkpoint is damaged ({e}); tracking again "
                        f"from the first frame ({len(frames)} journalled frames dropped)")
                state, n = None, 0
        if len(frames) < n:
            note = (f"{folder / 'frames.jsonl'}: {len(frames)} frames journalled, the "
                    f"checkpoint covers {n}; tracking again from the first frame")
            state, n = None, 0
        j = cls(folder, frames[:n], every_s)
        j.checkpointed = n
        with open(folder / "frames.jsonl", "w") as f:  # the lines beyond the checkpoint go
            f.writelines(_line(r["t"], r["read"], r["valid"], np.asarray(r["q"]),
                               r["diagnostics"]) for r in j.resumed)
            f.flush()
            os.fsync(f.fileno())
        j._open()
        return j, state, note

    def _open(self) -> None:
        self._file = open(self.folder / "frames.jsonl", "a")  # noqa: SIM115 (held open)

    # ------------------------------------------------------------------ writing
    def _failed(self, err: OSError, what: str) -> None:
        if self.failure is None:
            self.failure = describe_os_error(err, self.folder / what)
            print(f"jaxmocap track: warning: the journal cannot be written ({self.failure}); "
                  "tracking goes on, the frames are kept in memory", file=sys.stderr)

    def append(self, t: int, read: bool, valid: bool, q: np.ndarray, diagnostics: dict
               ) -> None:
        """One instant's line, flushed to the kernel (a kill of the process loses nothing)
        and ``fsync``'ed at least every :data:`FSYNC_EVERY_S`."""
        rec = _line(t, read, valid, q, diagnostics)
        self.count += 1
        if self.failure is not None:
            return
        try:
            self._file.write(rec)
            self._file.flush()
            if time.monotonic() - self._last_sync >= FSYNC_EVERY_S:
                os.fsync(self._file.fileno())
                self._last_sync = time.monotonic()
        except OSError as e:
            self._failed(e, "frames.jsonl")

    def checkpoint_due(self) -> bool:
        return self.failure is None and time.monotonic() - self._last_ckpt >= self.every_s

    def checkpoint(self, state: Any) -> None:
        """The tracker's state after the frames appended so far (``fsync``'ed first, so that
        the checkpoint never covers frames that are not on disk)."""
        if self.failure is not None:
            return
        try:
            self._file.flush()
            os.fsync(self._file.fileno())
            body = pickle.dumps({"frames": self.count, "tracker": state},
                                protocol=pickle.HIGHEST_PROTOCOL)
            write_bytes(self.folder / "checkpoint.pkl",
                        hashlib.sha256(body).hexdigest().encode() + b"\n" + body)
            self.checkpointed = self.count
        except OSError as e:
            self._failed(e, "checkpoint.pkl")
        self._last_ckpt = self._last_sync = time.monotonic()

    def close(self) -> None:
        if self._file is not None:
            with contextlib.suppress(OSError):
                self._file.close()
            self._file = None

    def remove(self) -> None:
        """The outputs are promoted complete: the journal goes."""
        self.close()
        shutil.rmtree(self.folder, ignore_errors=True)

    def where(self, out: Path) -> str:
        """Where the tracked frames are and how to resume, for a message."""
        kept = (f"{self.count} tracked frames are kept in {self.folder}"
                if self.failure is None else
                f"the journal {self.folder} holds the first {self.checkpointed} frames "
                f"(writing it failed: {self.failure})")
        return f"{kept}; resume with `jaxmocap track --resume {out}`"


def _read_frames(path: Path) -> list[dict]:
    """The complete lines of ``frames.jsonl`` (a last line cut by a kill is dropped)."""
    try:
        text = path.read_text()
    except FileNotFoundError:
        return []
    out = []
    for ln in text.split("\n")[:-1]:  # a last line without its newline is incomplete
        try:
            rec = json.loads(ln)
        except ValueError:
            break
        if not (isinstance(rec, dict) and {"t", "read", "valid", "q", "diagnostics"} <= set(rec)):
            break
        out.append(rec)
    return out


def tracked_arrays(frames: list[dict], n_dof: int):
    """``(qs, valid, rows, times)`` lists as :func:`jaxmocap.trackers.driver.drive` keeps
    them, from journal records."""
    qs = [np.asarray(r["q"], np.float64).reshape(n_dof) for r in frames]
    valid = [bool(r["valid"]) for r in frames]
    rows = [(int(r["t"]), bool(r["read"]), bool(r["valid"]), dict(r["diagnostics"]))
            for r in frames]
    times = [math.nan] * len(frames)  # step times are measured by the run that steps
    return qs, valid, rows, times


__all__ = ["CHECKPOINT_EVERY_S", "Journal", "input_stamps", "journal_path", "tracked_arrays"]
