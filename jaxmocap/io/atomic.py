"""Atomic file and folder writing: a target either keeps its old content or gets the new one.

Every writer puts its bytes into a temporary name on the target's own file system (so the
final ``os.replace`` is a rename within one file system, atomic on POSIX and Windows) and
renames it into place only once the content is complete; on any exception (Ctrl-C included)
the temporary is removed, so a failed command leaves no half-written file behind.

Temporaries are named ``.<stem>.jxm<pid>-<random>.tmp<suffix>``: a process killed with
``kill -9`` cannot remove its own, so every later creation of a temporary in the same folder
first **sweeps** the ones whose process is gone (:func:`sweep_temporaries`). An output
*folder* of a command (``track --out``) gets its temporaries in a hidden **staging folder
beside it** (:func:`staging_dir`, ``<parent>/.jaxmocap-staging``) so that nothing but complete
results ever appears inside ``--out``, even after a kill.

* :func:`atomic_write` — a context manager yielding an open file (text or binary);
* :func:`write_text` / :func:`write_bytes` — one-shot helpers;
* :func:`atomic_path` — a context manager yielding a temporary *path* with the target's
  suffix, for writers that want a file name (``np.savez``, ``cv2.VideoWriter``);
* :class:`AtomicFiles` — several outputs committed together at the end of a command (all or
  nothing: nothing is renamed into place unless every output was written);
* :func:`atomic_folder` — a whole folder built beside the target and renamed into place;
* :func:`check_output_file` / :func:`check_output_folder` — refuse, before any work, targets
  that cannot be written (an output folder that is a file, a file that is a folder, a folder
  where no file can be created: tried, not guessed from permission bits);
* :func:`output_folder_lock` — an output folder held by one run at a time (a lock file with
  the pid beside it; a second run is refused in one line, a killed run's lock swept).
"""

from __future__ import annotations

import contextlib
import errno
import os
import re
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
    "describe_os_error",
    "lock_path",
    "output_folder_lock",
    "staging_dir",
    "sweep_temporaries",
    "write_bytes",
    "write_text",
]


class OutputPathError(InputError):
    """An output path that cannot be written (a folder where a file goes, or the reverse)."""


# The causes of a failed write a user can act on, in words (errno's text is terse).
_CAUSES = {
    errno.ENOSPC: "no space left on the device: free some, or write elsewhere",
    errno.EDQUOT: "disk quota exceeded: free some, or write elsewhere",
    errno.EFBIG: "file too large for the file system",
    errno.ENAMETOOLONG: "a name in the path is too long for the file system: choose a shorter "
                        "one",
    errno.EACCES: "permission denied: choose a folder you can write",
    errno.EPERM: "operation not permitted: choose a folder you can write",
    errno.EROFS: "the file system is read-only: write elsewhere",
}
WRITE_ERRNOS = frozenset(_CAUSES)


def describe_os_error(err: OSError, path: str | os.PathLike | None = None) -> str:
    """One line for an OS error: the path (``path``, else the error's own) and the cause in
    words with its errno name, e.g. ``out/poses.npz: cannot write: no space left on the
    device: free some, or write elsewhere (ENOSPC)``."""
    where = path if path is not None else err.filename
    name = errno.errorcode.get(err.errno, "") if err.errno else ""
    cause = _CAUSES.get(err.errno, err.strerror or str(err) or type(err).__name__)
    verb = "cannot write: " if err.errno in WRITE_ERRNOS else ""
    return (f"{where}: " if where else "") + verb + cause + (f" ({name})" if name else "")


def _probe_writable(folder: Path, purpose: str) -> None:
    """Create and remove a file in ``folder``: the only reliable test (permission bits lie for
    root, read-only mounts and ACLs)."""
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".jaxmocap-probe.jxm{os.getpid()}-", suffix=".tmp",
                                   dir=folder)  # named like a temporary: swept if left
    except OSError as e:
        raise OutputPathError(f"{folder}: folder is not writable ({e.strerror}); {purpose}") \
            from None
    os.close(fd)
    os.unlink(tmp)


def check_output_folder(folder: str | os.PathLike) -> Path:
    """``folder`` as a Path if it is an existing writable folder or can be created (no file in
    the way on it or on any of its parents, the nearest existing one writable); raises
    :class:`OutputPathError` otherwise."""
    folder = Path(folder)
    existing = next((p for p in (folder, *folder.parents) if p.exists()), Path("."))
    if not existing.is_dir():
        what = "the output folder" if existing == folder else f"a parent of {folder}"
        raise OutputPathError(f"{existing}: {what} is a file; choose a folder path")
    check_name_lengths(folder, existing)
    _probe_writable(existing, "cannot write the outputs there" if existing == folder
                    else f"cannot create {folder}")
    return folder


# what our writers add to an output name: temporaries ".<stem>.jxm<pid>-<8 random>.tmp<suffix>"
# and lock files ".<name>.jaxmocap-lock"
NAME_MARGIN = 32


def check_name_lengths(path: str | os.PathLike, existing: str | os.PathLike = ".") -> None:
    """Refuse (:class:`OutputPathError`, one line) a path with a name longer than the file
    system of ``existing`` (its nearest existing folder) allows, with room for the temporary
    and lock names made from it (:data:`NAME_MARGIN`), or longer than its path limit."""
    try:
        name_max = os.pathconf(existing, "PC_NAME_MAX")
        path_max = os.pathconf(existing, "PC_PATH_MAX")
    except (OSError, ValueError, AttributeError):  # not POSIX, or not reported
        return
    for part in Path(path).parts:
        if len(os.fsencode(part)) + NAME_MARGIN > name_max:
            raise OutputPathError(f"{path}: the name {part[:24]}... is {len(os.fsencode(part))} "
                                  f"bytes; this file system allows {name_max} (and jaxmocap "
                                  f"needs {NAME_MARGIN} more for its temporaries): choose a "
                                  "shorter one")
    full = len(os.fsencode(os.path.abspath(path)))
    if full + NAME_MARGIN > path_max:
        raise OutputPathError(f"{path}: the path is {full} bytes; this file system allows "
                              f"{path_max}: choose a shorter one")


def check_output_file(path: str | os.PathLike) -> Path:
    """``path`` as a Path if a file can be written there: not a folder, and its folder exists
    or can be created; raises :class:`OutputPathError` otherwise."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"{path}: is a folder; expected an output file name")
    if path.name in ("", ".", ".."):
        raise OutputPathError(f"{path}: expected an output file name")
    check_output_folder(path.parent if str(path.parent) else Path("."))
    check_name_lengths(path, next(p for p in (*path.parents, Path(".")) if p.exists()))
    return path


def make_folders(folder: Path) -> list[Path]:
    """``mkdir -p folder``; returns the folders it created (outermost first), for
    :func:`remove_empty` to take back when the run fails."""
    missing = [d for d in (folder, *folder.parents) if not d.exists()]
    created = []
    for d in reversed(missing):
        try:
            d.mkdir()
        except FileExistsError:
            continue
        except OSError:
            remove_empty(created)
            raise
        created.append(d)
    return created


def remove_empty(folders: list[Path]) -> None:
    """Remove the folders a run created (innermost first) that are still empty."""
    for d in reversed(folders):
        with contextlib.suppress(OSError):
            d.rmdir()


_TEMP = re.compile(r"^\..*\.jxm(\d+)-[^.]+\.tmp(\.[^.]*)?$")
STAGING = ".jaxmocap-staging"


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's live process
        return True
    return True


def sweep_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporaries (files or folders named by this module) in ``folder`` whose
    process no longer runs (killed before it could clean up); returns what was removed."""
    folder = Path(folder)
    removed = []
    try:
        entries = list(folder.iterdir())
    except OSError:
        return removed
    for p in entries:
        m = _TEMP.match(p.name)
        if m and not _alive(int(m.group(1))):
            with contextlib.suppress(OSError):
                _remove(p)
                removed.append(p)
    return removed


def staging_dir(folder: str | os.PathLike) -> Path:
    """Where the temporaries of the outputs in ``folder`` are written: the hidden staging
    folder beside ``folder`` when it is writable and on the same file system (``os.replace``
    must stay a rename), else ``folder`` itself. Created if missing; swept of dead
    temporaries."""
    folder = Path(folder)
    parent = folder.parent if str(folder.parent) else Path(".")
    stage = parent / STAGING
    folder.mkdir(parents=True, exist_ok=True)
    try:
        stage.mkdir(exist_ok=True)
        if os.stat(stage).st_dev != os.stat(folder).st_dev:
            raise OSError("another file system")
        _probe_writable(stage, "")
    except (OSError, OutputPathError):
        stage = folder
    sweep_temporaries(stage)
    return stage


def _drop_staging(stage: Path) -> None:
    """Remove an emptied staging folder (another run may still use it: then it stays)."""
    if stage.name == STAGING:
        with contextlib.suppress(OSError):
            stage.rmdir()


def _temp_prefix(name: str) -> str:
    return f".{name}.jxm{os.getpid()}-"


def _temp_name(path: Path, folder: Path | None = None) -> Path:
    """A new empty temporary file for ``path``, in ``folder`` (default: beside ``path``)."""
    folder = path.parent if folder is None else folder
    sweep_temporaries(folder)
    fd, tmp = tempfile.mkstemp(prefix=_temp_prefix(path.stem), suffix=f".tmp{path.suffix}",
                               dir=folder)
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
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = _temp_name(path)
    except OSError as e:
        raise _naming(e, path) from None
    try:
        yield tmp
        _publish(tmp, path)
    except OSError as e:
        _remove(tmp)
        raise _naming(e, path, tmp) from None
    except BaseException:
        _remove(tmp)
        raise


def _naming(err: OSError, path: Path, tmp: Path | None = None) -> OSError:
    """``err`` naming ``path``: a write that failed (``write``/``fsync`` name no file) or
    failed on our hidden temporary is reported for the file the user asked for."""
    if err.filename is not None and (tmp is None or os.fspath(err.filename) != os.fspath(tmp)):
        return err
    out = type(err)(err.errno, err.strerror or str(err), os.fspath(path))
    out.__cause__ = err
    return out


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

    :meth:`path` checks the target and returns a temporary path (same suffix) beside it, or,
    with ``folder`` (a command's output folder), in :func:`staging_dir` of that folder. When
    the ``with`` block ends normally every temporary is renamed onto its target and the
    paths given to :meth:`replace_set` that were not written are removed (an earlier run's
    results are replaced as a whole set); when it raises, every temporary is removed and no
    target is touched.
    """

    def __init__(self, folder: str | os.PathLike | None = None) -> None:
        self._pending: list[tuple[Path, Path]] = []
        self._folder = None if folder is None else Path(folder)
        self._stage: Path | None = None
        self._stale: list[Path] = []
        self._created: list[Path] = []  # folders made for the outputs: removed on failure

    def path(self, target: str | os.PathLike) -> Path:
        target = check_output_file(target)
        if any(t == target for t, _ in self._pending):
            raise ValueError(f"AtomicFiles: {target} requested twice")
        try:
            self._created += make_folders(target.parent)
            if self._folder is not None and target.parent.resolve() == self._folder.resolve():
                if self._stage is None:
                    self._stage = staging_dir(self._folder)
                tmp = _temp_name(target, self._stage)
            else:
                tmp = _temp_name(target)
        except OSError as e:
            raise self._write_error(e, target) from None
        self._pending.append((target, tmp))
        return tmp

    def _write_error(self, err: OSError, target: Path | None = None,
                     written: list[Path] | None = None) -> OutputPathError:
        """The one line for an OS error while writing: the target whose temporary failed (or
        the output folder), the cause; what this group wrote is removed."""
        if target is None:
            named = {os.fspath(tmp): t for t, tmp in self._pending}
            target = named.get(os.fspath(err.filename)) if err.filename is not None else None
        if target is None:
            target = self._folder if self._folder is not None else (
                self._pending[0][0] if self._pending else err.filename)
        self.discard(failed=True)
        done = "nothing was written" if not written else (
            f"{len(written)} output(s) had been written ({', '.join(p.name for p in written)})")
        return OutputPathError(f"{describe_os_error(err, target)}; {done}")

    def _ours(self, err: OSError) -> bool:
        """Whether ``err`` came from writing this group (a write error on one of its
        temporaries or targets, or one that names no file, as ``write`` does)."""
        if err.errno not in WRITE_ERRNOS:
            return False
        if err.filename is None:
            return True
        paths = {os.fspath(p) for pair in self._pending for p in pair}
        return os.fspath(err.filename) in paths or (
            self._folder is not None and Path(err.filename).resolve().is_relative_to(
                self._folder.resolve().parent))

    def replace_set(self, paths) -> None:
        """On commit, also remove each of ``paths`` that this group did not write."""
        self._stale = [Path(p) for p in paths]

    @property
    def targets(self) -> list[Path]:
        return [t for t, _ in self._pending]

    def __enter__(self) -> AtomicFiles:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            if isinstance(exc, OSError) and self._ours(exc):
                raise self._write_error(exc) from None
            self.discard(failed=True)
            return
        self.commit()

    def commit(self) -> None:
        """Rename every temporary onto its target and remove the stale set (what ``with``
        does at its end; a second call does nothing)."""
        published: list[Path] = []
        try:
            for target, tmp in self._pending:
                _publish(tmp, target)
                published.append(target)
            written = {t.resolve() for t, _ in self._pending}
            for p in self._stale:
                if p.resolve() not in written and (p.is_file() or p.is_symlink()):
                    p.unlink()
        except OSError as e:
            raise self._write_error(e, written=published) from None
        finally:
            self._stale = []
            self.discard()

    def discard(self, failed: bool = False) -> None:
        """Remove every temporary not yet renamed (``failed``: and the folders this group
        created, if still empty)."""
        for _, tmp in self._pending:
            _remove(tmp)
        self._pending = []
        if self._stage is not None:
            _drop_staging(self._stage)
            self._stage = None
        if failed:
            remove_empty(self._created)
            self._created = []


# ----------------------------------------------------------------------------- folder lock
try:
    import fcntl
except ImportError:  # not POSIX: the lock file's pid alone (os.O_EXCL) decides
    fcntl = None


def lock_path(folder: str | os.PathLike) -> Path:
    """The lock file of an output folder: ``<parent>/.<name>.jaxmocap-lock`` (beside it, so
    that it exists before the folder does and never appears inside it)."""
    folder = Path(folder)
    return (folder.parent if str(folder.parent) else Path(".")) / f".{folder.name}.jaxmocap-lock"


def _lock_pid(path: Path) -> int | None:
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _try_lock(path: Path) -> int | None:
    """An open, locked descriptor of ``path`` holding our pid, or None if a live run holds
    it. With ``flock`` (POSIX) the kernel frees the lock when its process dies, so a lock file
    a killed run left behind is simply taken over; without it, a lock file whose pid is gone
    is swept and created anew."""
    for _ in range(5):
        if fcntl is None:
            try:
                fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
            except FileExistsError:
                pid = _lock_pid(path)
                if pid is not None and _alive(pid):
                    return None
                with contextlib.suppress(FileNotFoundError):
                    path.unlink()  # stale: its run is gone
                continue
        else:
            fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                os.close(fd)
                return None
            try:  # the file we locked may have been unlinked by its releasing holder
                same = os.fstat(fd).st_ino == os.stat(path).st_ino
            except FileNotFoundError:
                same = False
            if not same:
                os.close(fd)
                continue
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        os.fsync(fd)
        return fd
    raise OSError(f"{path}: could not take the lock (it kept changing)")


@contextlib.contextmanager
def output_folder_lock(folder: str | os.PathLike, option: str = "--out") -> Iterator[Path]:
    """Hold the output folder ``folder`` for the length of a run: a second run writing the
    same folder meanwhile is refused (:class:`OutputPathError`, one line naming the folder and
    the pid holding it). The lock file (:func:`lock_path`) holds the pid; one of a run that is
    gone (killed) is swept. Folders created to hold the lock file are removed at the end if
    still empty (a refused or failed run leaves nothing behind)."""
    folder = Path(folder)
    path = lock_path(folder)
    try:
        created = make_folders(path.parent)
    except OSError as e:
        raise OutputPathError(f"{option} {folder}: {describe_os_error(e)}") from None
    try:
        fd = _try_lock(path)
    except OSError as e:
        remove_empty(created)
        raise OutputPathError(f"{option} {folder}: {describe_os_error(e, path)}") from None
    if fd is None:
        pid = _lock_pid(path)
        remove_empty(created)
        who = f"pid {pid}" if pid is not None else "another process"
        raise OutputPathError(f"{option} {folder}: another jaxmocap run ({who}) is writing "
                              "its results there; wait for it to end, or choose another "
                              "output folder")
    try:
        yield path
    finally:
        with contextlib.suppress(OSError):
            path.unlink()  # while still locked: no other run can hold this file
        os.close(fd)
        remove_empty(created)


@contextlib.contextmanager
def atomic_folder(folder: str | os.PathLike) -> Iterator[Path]:
    """Yield a new temporary folder beside ``folder``; on success it replaces ``folder``
    (which must not exist or be an empty folder), on error it is removed."""
    folder = check_output_folder(folder)
    if folder.is_dir() and any(folder.iterdir()):
        raise OutputPathError(f"{folder}: folder exists and is not empty; choose a new folder")
    folder.parent.mkdir(parents=True, exist_ok=True)
    sweep_temporaries(folder.parent)
    tmp = Path(tempfile.mkdtemp(prefix=_temp_prefix(folder.name), suffix=".tmp",
                                dir=folder.parent))
    try:
        yield tmp
        if folder.is_dir():
            folder.rmdir()  # empty, checked above
        _publish(tmp, folder)
    except BaseException:
        _remove(tmp)
        raise
