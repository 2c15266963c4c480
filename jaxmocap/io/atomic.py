"""Atomic file and folder writing: a target either keeps its old content or gets the new one.

Every writer puts its bytes into a temporary name **in the target's own directory** (so the
final ``os.replace`` is a rename within one file system, atomic on POSIX and Windows) and
renames it into place only once the content is complete; on any exception the temporary is
removed, so a failed command leaves no half-written file behind.

* :func:`atomic_write` — a context manager yielding an open file (text or binary);
* :func:`write_text` / :func:`write_bytes` — one-shot helpers;
* :func:`atomic_path` — a context manager yielding a temporary *path* with the target's
  suffix, for writers that want a file name (``np.savez``, ``cv2.VideoWriter``);
* :class:`AtomicFiles` — several outputs committed together at the end of a command (all or
  nothing: nothing is renamed into place unless every output was written);
* :func:`atomic_folder` — a whole folder built beside the target and renamed into place;
* :func:`check_output_file` / :func:`check_output_folder` — refuse, before any work, targets
  that cannot be written (an output folder that is a file, a file that is a folder).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

from jaxmocap.errors import InputError

__all__ = [
    "AtomicFiles",
    "OutputPathError",
    "atomic_folder",
    "atomic_path",
    "atomic_write",
    "check_output_file",
    "check_output_folder",
    "write_bytes",
    "write_text",
]


class OutputPathError(InputError):
    """An output path that cannot be written (a folder where a file goes, or the reverse)."""


def check_output_folder(folder: str | os.PathLike) -> Path:
    """``folder`` as a Path if it is an existing folder or can be created (no file in the way
    on it or on any of its parents, the nearest existing one writable); raises
    :class:`OutputPathError` otherwise."""
    folder = Path(folder)
    existing = next((p for p in (folder, *folder.parents) if p.exists()), Path("."))
    if not existing.is_dir():
        what = "the output folder" if existing == folder else f"a parent of {folder}"
        raise OutputPathError(f"{existing}: {what} is a file; choose a folder path")
    if existing != folder and not os.access(existing, os.W_OK | os.X_OK):
        raise OutputPathError(f"{existing}: folder is not writable; cannot create {folder}")
    return folder


def check_output_file(path: str | os.PathLike) -> Path:
    """``path`` as a Path if a file can be written there: not a folder, and its folder exists
    or can be created; raises :class:`OutputPathError` otherwise."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"{path}: is a folder; expected an output file name")
    check_output_folder(path.parent if str(path.parent) else Path("."))
    return path


def _temp_name(path: Path) -> Path:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}",
                               dir=path.parent)
    os.close(fd)
    return Path(tmp)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def _publish(tmp: Path, target: Path) -> None:
    """Give ``tmp`` the permissions a plain ``open`` would (mkstemp/mkdtemp make them private:
    0600/0700) and rename it onto ``target``."""
    os.chmod(tmp, (0o777 if tmp.is_dir() else 0o666) & ~_umask())
    os.replace(tmp, target)


def _remove(p: Path) -> None:
    with contextlib.suppress(FileNotFoundError):
        if p.is_dir() and not p.is_symlink():
            shutil.rmtree(p)
        else:
            p.unlink()


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same suffix); rename it to ``path`` on success,
    remove it on error. The writer must create the file at exactly the yielded path."""
    path = check_output_file(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _temp_name(path)
    try:
        yield tmp
        _publish(tmp, path)
    except BaseException:
        _remove(tmp)
        raise


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "w", **open_kwargs: Any) -> Iterator[IO]:
    """``with atomic_write(p) as f: f.write(...)`` — ``mode`` "w" (text) or "wb" (binary);
    the data are flushed and fsync'ed before the rename."""
    if mode not in ("w", "wb"):
        raise ValueError(f"atomic_write: mode must be 'w' or 'wb', got {mode!r}")
    with atomic_path(path) as tmp, open(tmp, mode, **open_kwargs) as f:
        yield f
        f.flush()
        os.fsync(f.fileno())


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically; returns the path."""
    with atomic_write(path, "w", encoding="utf-8", newline="") as f:
        f.write(text)
    return Path(path)


def write_bytes(path: str | os.PathLike, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns the path."""
    with atomic_write(path, "wb") as f:
        f.write(data)
    return Path(path)


class AtomicFiles:
    """Several output files committed together (all or nothing).

    >>> with AtomicFiles() as out:
    ...     np.savez(out.path("poses.npz"), q=q)
    ...     write_csv(out.path("poses.csv"), ...)

    :meth:`path` checks the target and returns a temporary path beside it (same suffix). When
    the ``with`` block ends normally every temporary is renamed onto its target; when it
    raises, every temporary is removed and no target is touched.
    """

    def __init__(self) -> None:
        self._pending: list[tuple[Path, Path]] = []

    def path(self, target: str | os.PathLike) -> Path:
        target = check_output_file(target)
        if any(t == target for t, _ in self._pending):
            raise ValueError(f"AtomicFiles: {target} requested twice")
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = _temp_name(target)
        self._pending.append((target, tmp))
        return tmp

    @property
    def targets(self) -> list[Path]:
        return [t for t, _ in self._pending]

    def __enter__(self) -> AtomicFiles:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            self.discard()
            return
        try:
            for target, tmp in self._pending:
                _publish(tmp, target)
        finally:
            self.discard()

    def discard(self) -> None:
        """Remove every temporary not yet renamed."""
        for _, tmp in self._pending:
            _remove(tmp)
        self._pending = []


@contextlib.contextmanager
def atomic_folder(folder: str | os.PathLike) -> Iterator[Path]:
    """Yield a new temporary folder beside ``folder``; on success it replaces ``folder``
    (which must not exist or be an empty folder), on error it is removed."""
    folder = check_output_folder(folder)
    if folder.is_dir() and any(folder.iterdir()):
        raise OutputPathError(f"{folder}: folder exists and is not empty; choose a new folder")
    folder.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{folder.name}.", suffix=".tmp", dir=folder.parent))
    try:
        yield tmp
        if folder.is_dir():
            folder.rmdir()  # empty, checked above
        _publish(tmp, folder)
    except BaseException:
        _remove(tmp)
        raise
