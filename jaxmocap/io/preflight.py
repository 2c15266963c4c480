"""Checks every command makes before any work: outputs that would touch its inputs, earlier
results in a reused output folder, option ranges; and the readers of the user's JSON / NPZ
files, which turn any decoding failure into one :class:`~jaxmocap.errors.InputError` line
naming the file and what was expected.

* :func:`check_outputs` — refuse an output that *is* one of the command's inputs (compared as
  real paths: through symlinks, ``..`` and hard links) or lies inside an input folder the
  command reads (frame folders, calibration images), or an output folder holding an input;
* :func:`check_stale` — an output folder holding results of an earlier run: refused unless
  the command was given ``--overwrite`` (then the earlier set is replaced as a whole when the
  new one is complete, :meth:`jaxmocap.io.atomic.AtomicFiles.replace_set`);
* :func:`read_text` / :func:`read_json` / :func:`read_npz` — the decoders of user files (size,
  nesting depth and encoding limits), one line per failure;
* :func:`int_range` / :func:`positive_float` — argparse types that state the bound.
"""

from __future__ import annotations

import argparse
import json
import os
import zipfile
import zlib
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from jaxmocap.errors import InputError
from jaxmocap.io.atomic import OutputPathError

__all__ = [
    "check_outputs",
    "check_stale",
    "int_range",
    "positive_float",
    "parse_json",
    "read_json",
    "read_npz",
    "read_text",
]


def _real(p: str | os.PathLike) -> Path:
    return Path(os.path.realpath(os.fspath(p)))


def _same(a: Path, b: Path) -> bool:
    if _real(a) == _real(b):
        return True
    try:  # hard links
        return os.path.samefile(a, b)
    except OSError:
        return False


def check_outputs(outputs: Iterable[str | os.PathLike], inputs: Iterable[str | os.PathLike | None],
                  option: str = "--out", replaced_folders: bool = False) -> None:
    """Refuse (:class:`OutputPathError`, one line) an output that is an input or lies inside an
    input that is a folder; with ``replaced_folders`` (output folders replaced as a whole) also
    an output folder holding an input. ``outputs`` are the files and folders the command would
    write; ``inputs`` every file or folder it reads (None skipped)."""
    ins = [Path(i) for i in inputs if i is not None and str(i) != ""]
    for o in outputs:
        o = Path(o)
        ro = _real(o)
        for i in ins:
            ri = _real(i)
            if _same(o, i):
                raise OutputPathError(f"{option} {o}: is also an input of this command ({i}); "
                                      "it would be overwritten: choose another output path")
            if i.is_dir() and ri in ro.parents:
                raise OutputPathError(f"{option} {o}: lies inside the input folder {i}, which "
                                      "this command reads: choose an output outside it")
            if replaced_folders and o.is_dir() and ro in ri.parents:
                raise OutputPathError(f"{option} {o}: holds the input {i}; it would be "
                                      "replaced: choose another output folder")


def check_stale(folder: str | os.PathLike, names: Iterable[str], overwrite: bool,
                option: str = "--out") -> list[Path]:
    """The files of ``names`` (an earlier run's result set) present in ``folder``. Refused
    unless ``overwrite``: the caller then replaces them as a whole set."""
    folder = Path(folder)
    if not folder.is_dir():
        return []
    found = sorted(folder / n for n in set(names) if (folder / n).exists()
                   or (folder / n).is_symlink())
    bad = [p for p in found if p.is_dir()]
    if bad:
        raise OutputPathError(f"{option} {folder}: {bad[0].name} is a folder where an output "
                              "file goes; move it away or choose another output folder")
    if found and not overwrite:
        listing = ", ".join(p.name for p in found[:5]) + (" ..." if len(found) > 5 else "")
        raise OutputPathError(f"{option} {folder}: holds results of an earlier run ({listing}); "
                              "choose a new folder, or pass --overwrite to replace them as a "
                              "whole set")
    return found


# ----------------------------------------------------------------------------- readers


MAX_JSON_BYTES = 64 << 20  # a configuration file; the largest we write (cameras, colours) is ~10 kB
MAX_JSON_DEPTH = 64  # our formats nest 4 levels at most; deeper is not one of them


def _depth_exceeds(doc: Any, limit: int) -> bool:
    """Whether ``doc`` nests containers more than ``limit`` deep (an explicit stack: no
    recursion, so the check itself cannot overflow)."""
    stack = [(doc, 1)]
    while stack:
        node, d = stack.pop()
        if isinstance(node, (dict, list)):
            if d > limit:
                return True
            children = node.values() if isinstance(node, dict) else node
            stack.extend((c, d + 1) for c in children if isinstance(c, (dict, list)))
    return False


def read_text(path: str | os.PathLike, what: str, error: type[InputError] = InputError,
              max_bytes: int = MAX_JSON_BYTES) -> str:
    """The UTF-8 text of ``path`` (a configuration or model file of at most ``max_bytes``);
    any failure (missing, a folder, unreadable, too large, binary, not UTF-8) is one ``error``
    line naming the file and ``what`` it should be."""
    path = Path(path)
    try:
        size = path.stat().st_size
        if path.is_dir():
            raise IsADirectoryError
        if size > max_bytes:
            raise error(f"{path}: {size:,} bytes is too large (at most {max_bytes:,}; expected "
                        f"{what})")
        return path.read_bytes().decode("utf-8")
    except FileNotFoundError:
        raise error(f"{path}: cannot read: no such file (expected {what})") from None
    except IsADirectoryError:
        raise error(f"{path}: cannot read: is a folder (expected {what})") from None
    except OSError as e:
        raise error(f"{path}: cannot read: {e.strerror} (expected {what})") from None
    except UnicodeDecodeError:
        raise error(f"{path}: not a text file (binary data; expected {what})") from None


def parse_json(text: str, path: str | os.PathLike, what: str,
               error: type[InputError] = InputError) -> Any:
    """The JSON document of ``text`` (read from ``path``): not JSON or nested more than
    :data:`MAX_JSON_DEPTH` deep is one ``error`` line naming the file and ``what``."""
    too_deep = False
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as e:
        raise error(f"{path}: not valid JSON: {e.msg} (line {e.lineno}; expected {what})") \
            from None
    except RecursionError:
        doc, too_deep = None, True
    if too_deep or _depth_exceeds(doc, MAX_JSON_DEPTH):
        raise error(f"{path}: JSON nested too deeply (more than {MAX_JSON_DEPTH} levels; "
                    f"expected {what})")
    return doc


def read_json(path: str | os.PathLike, what: str,
              error: type[InputError] = InputError) -> Any:
    """The JSON document of ``path``; any failure (missing, a folder, unreadable, too large,
    not UTF-8, not JSON, nested too deeply) is one ``error`` line naming the file and ``what``
    it should be (e.g. "cameras.json of `jaxmocap calibrate`"). Every JSON file a user gives
    jaxmocap is read here."""
    return parse_json(read_text(path, what, error), path, what, error)


_NPZ_ERRORS = (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error,
               UnicodeDecodeError, TypeError, NotImplementedError)


def read_npz(path: str | os.PathLike, what: str, keys: Sequence[str] | None = None,
             error: type[InputError] = InputError) -> dict[str, np.ndarray]:
    """Every array of the ``.npz`` at ``path`` (or only ``keys``, which must all be present),
    read fully (``np.load`` is lazy: a truncated member fails only when read) without pickles;
    any failure is one ``error`` line naming the file and ``what`` it should be."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{path}: cannot read: is a folder (expected {what})")
    if not path.exists():
        raise error(f"{path}: cannot read: no such file (expected {what})")
    try:  # our own handle: np.load leaks it when the archive is bad
        with open(path, "rb") as fh:
            magic = fh.read(4)
            fh.seek(0)
            if not magic:
                raise error(f"{path}: cannot read: empty file (0 bytes; expected {what})")
            if magic != b"PK\x03\x04":
                raise error(f"{path}: cannot read: not an .npz archive (a zip of .npy arrays; "
                            f"expected {what})")
            z = np.load(fh, allow_pickle=False)
            with z:
                return _read_members(path, z, keys, what, error)
    except InputError:
        raise
    except _NPZ_ERRORS as e:
        why = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise error(f"{path}: cannot read: truncated or damaged .npz archive ({why}; expected "
                    f"{what})") from None


def _read_members(path: Path, z, keys, what: str, error) -> dict[str, np.ndarray]:
    names = list(z.files) if keys is None else list(keys)
    missing = [k for k in names if k not in z.files]
    if missing:
        raise error(f"{path}: missing field {missing[0]!r} (has {sorted(z.files)}; "
                    f"expected {what})")
    return {k: np.asarray(z[k]) for k in names}


# ----------------------------------------------------------------------------- options


def int_range(lo: int, hi: int | None = None, why: str = "") -> Callable[[str], int]:
    """An argparse ``type``: an integer in ``lo..hi`` (``hi`` None: no upper bound), the bound
    and its reason stated in the error."""

    def parse(text: str) -> int:
        try:
            v = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if v < lo or (hi is not None and v > hi):
            rng = f">= {lo}" if hi is None else f"between {lo} and {hi:,}"
            raise argparse.ArgumentTypeError(f"must be {rng}{f' ({why})' if why else ''}, "
                                             f"got {v}")
        return v

    parse.__name__ = "integer"
    return parse


def unit_fraction(text: str) -> float:
    """An argparse ``type``: a finite number in [0, 1]."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number in [0, 1], got {text!r}") from None
    if not 0.0 <= v <= 1.0:  # NaN fails too
        raise argparse.ArgumentTypeError(f"must be a fraction in [0, 1], got {text}")
    return v


def positive_float(text: str) -> float:
    """An argparse ``type``: a finite number > 0."""
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
    if not (np.isfinite(v) and v > 0):
        raise argparse.ArgumentTypeError(f"must be a positive number, got {text}")
    return v


positive_float.__name__ = "number"
