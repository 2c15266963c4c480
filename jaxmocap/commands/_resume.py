"""``track --resume`` and the journal of a ``track`` run (:mod:`jaxmocap.io.journal`) on the
command line: the settings a journal keeps and a resume takes back, the refusals (a resume with
other options or changed inputs, a new run over a journal), and what becomes of the journal
when a run fails (kept, and the failure's line says where it is and how to resume; removed when
nothing was tracked)."""

from __future__ import annotations

import argparse
import math
import os
import sys
from pathlib import Path

from jaxmocap.errors import InputError
from jaxmocap.io.atomic import OutputPathError, describe_os_error
from jaxmocap.io.journal import Journal, input_stamps, journal_path


def non_negative_seconds(text: str) -> float:
    """``--checkpoint``'s type: seconds >= 0."""
    try:
        v = float(text)
    except ValueError:
        v = math.nan
    if not v >= 0 or not math.isfinite(v):
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, got {text!r}")
    return v


# the settings a journal keeps (the parsed command line but what only this invocation says)
_NOT_RESUMED = ("resume", "quiet", "func", "command", "show", "inputs_given")


def resumed_args(args: argparse.Namespace) -> argparse.Namespace:
    """The interrupted run's settings from the journal beside ``--resume OUT``, refused in
    one line when other options are given or the inputs changed since."""
    from jaxmocap.cli import build_parser

    defaults = vars(build_parser().parse_args(["track"]))
    given = [k for k, v in vars(args).items()
             if k not in _NOT_RESUMED and defaults.get(k) != v]
    if given:
        names = ", ".join("INPUT" if k == "inputs" else "--" + k.replace("_", "-")
                          for k in given)
        raise InputError(f"--resume {args.resume}: takes the interrupted run's settings from "
                         f"its journal; leave out {names}")
    out = Path(args.resume)
    meta = Journal.read_meta(out)
    now = input_stamps(p for p in _input_files(argparse.Namespace(**meta["args"])))
    if now != meta.get("input_stamps"):
        then = {d["path"]: d for d in meta.get("input_stamps", [])}
        changed = next((d["path"] for d in now if then.get(d["path"]) != d), None) or next(
            iter(set(then) - {d["path"] for d in now}), "an input")
        raise InputError(f"--resume {out}: {changed} changed since the interrupted run (size "
                         "or time); the journal is of other inputs: track again with "
                         "--overwrite")
    resumed = argparse.Namespace(**meta["args"])
    resumed.resume, resumed.quiet, resumed.show, resumed.func = out, args.quiet, False, args.func
    return resumed


def _input_files(args) -> list:
    """The input files and folders whose content a journal depends on."""
    return [p for p in input_paths(args) if p is not None and os.path.exists(p)]


_PATH_ARGS = ("out", "cameras", "colors", "white_balance", "db", "ik_cov", "tuned", "body",
              "garment", "pf_colors", "observer")


def journal_meta(args) -> dict:
    """The settings and inputs a journal keeps: paths made absolute (a resume may run from
    another folder)."""
    keep = {k: v for k, v in vars(args).items()
            if k not in _NOT_RESUMED and isinstance(v, (str, int, float, bool, list, type(None)))}
    for k in _PATH_ARGS:
        if isinstance(keep.get(k), str) and (k == "out" or os.path.exists(keep[k])):
            keep[k] = os.path.abspath(keep[k])
    keep["inputs"] = [os.path.abspath(i) if os.path.exists(i) else i for i in args.inputs]
    keep["inputs_given"] = list(getattr(args, "inputs_given", None) or args.inputs)  # run.json
    return {"args": keep, "input_stamps": input_stamps(_input_files(args))}


def input_paths(args) -> list:
    """Every file or folder the command reads (camera indices are not paths)."""
    srcs = [i for i in args.inputs if os.path.exists(i) or not str(i).isdigit()]
    return [*srcs, args.cameras, args.colors, args.white_balance, args.db, args.ik_cov,
            getattr(args, "tuned", None), getattr(args, "observer", None),
            getattr(args, "body", None), getattr(args, "garment", None),
            None if getattr(args, "pf_colors", None) == "auto" else getattr(args, "pf_colors",
                                                                            None)]


def refuse_over_journal(out: Path, overwrite: bool, resume: bool) -> None:
    """A new run into an ``--out`` with a journal beside it is refused (resume it, or
    ``--overwrite``: the journal is then replaced)."""
    jdir = journal_path(out)
    if not resume and jdir.exists() and not overwrite:
        raise InputError(f"--out {out}: the journal of an interrupted run is beside it "
                         f"({jdir}); resume it with `jaxmocap track --resume {out}`, or pass "
                         "--overwrite to track again from the start")


def open_journal(args: argparse.Namespace, out: Path) -> tuple[Journal, object]:
    """(the run's journal, the tracker state to restore or None): a new journal, or, with
    ``--resume``, the interrupted run's truncated to its checkpoint (notes on stderr)."""
    if not args.resume:
        return Journal.create(out, journal_meta(args), args.checkpoint), None
    journal, restore, note = Journal.resume(out, args.checkpoint)
    if note:
        print(f"jaxmocap track: note: {note}", file=sys.stderr)
    if args.overlay:
        args.overlay = False
        print("jaxmocap track: note: the overlay video is not journalled; the resumed run "
              "writes none (track again with --overlay for one)", file=sys.stderr)
    if not args.quiet:
        print(f"jaxmocap track: resuming {out} after frame {journal.count} (the "
              "journal's last checkpoint)", file=sys.stderr)
    return journal, restore


def keep_or_drop(journal: Journal, err: BaseException, out: Path, n_read: int
                 ) -> BaseException:
    """The exception a failed run raises, and the journal's fate: removed when it holds no
    frame (set-up, compiling) or no frame was readable; otherwise kept, and an OS error
    writing the outputs (disk full, a read-only folder) says where the frames are and how to
    resume."""
    if journal.count == 0 or (isinstance(err, InputError) and n_read == 0):
        journal.remove()
        return err
    if isinstance(err, OSError) or (isinstance(err, OutputPathError)):
        msg = str(err) if isinstance(err, InputError) else describe_os_error(err)
        return OutputPathError(f"{msg}; {journal.where(out)}")
    return err
