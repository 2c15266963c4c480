"""The ``jaxmocap`` command.

Each sub-command lives beside the code it drives and registers itself here: a module listed in
``SUBCOMMANDS`` exposes ``add_parser(subparsers)``, which adds its parser and sets
``func=run`` (``run(args) -> int``). Bad user input raises :class:`UsageError` (or one of the
library's file-format errors, all :class:`~jaxmocap.errors.InputError` subclasses): it is
printed as one line on stderr and the exit code is 2 — argparse's own errors (an option out of
range) too, as one line.

Ctrl-C (SIGINT) and SIGTERM end any command with one line and exit code 130 (128 + SIGINT, the
shell's convention), never a traceback: every writer is atomic (:mod:`jaxmocap.io.atomic`),
so an interrupted command leaves nothing half-written; ``track`` catches the interrupt in its
frame loop and writes the frames tracked so far as a result marked partial.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import os
import signal
import sys
import threading

from jaxmocap.errors import InputError

SUBCOMMANDS = (
    "jaxmocap.demo",
    "jaxmocap.posedb",
    "jaxmocap.synth.dataset",
    "jaxmocap.commands.calibrate",
    "jaxmocap.commands.colors",
    "jaxmocap.commands.track",
    "jaxmocap.commands.evaluate",
    "jaxmocap.commands.body",
    "jaxmocap.synth.world.cli",
    "jaxmocap.experiment",
)


EXIT_INTERRUPTED = 130


class UsageError(InputError):
    """Bad command-line usage: reported as one line on stderr with exit code 2."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, delivered as an interrupt so that it takes the Ctrl-C path."""


class ArgumentError(UsageError):
    """An argument argparse rejects (unknown option, a value out of its range)."""

    def __init__(self, prog: str, message: str):
        super().__init__(f"{message} (see {prog} --help)")
        self.prog = prog


class _Parser(argparse.ArgumentParser):
    """argparse whose usage errors are :class:`ArgumentError` (one line, exit code 2, returned
    by :func:`main`; the full usage is in ``--help``)."""

    def error(self, message: str):
        raise ArgumentError(self.prog, message)


def _in_finaliser(frame) -> bool:
    """Whether ``frame`` runs a garbage-collector callback or a ``__del__``: Python prints an
    exception raised there as "Exception ignored" (a traceback) and drops it."""
    codes = {getattr(cb, "__code__", None) for cb in gc.callbacks}
    for _ in range(8):
        if frame is None:
            return False
        if frame.f_code in codes or frame.f_code.co_name == "__del__":
            return True
        frame = frame.f_back
    return False


_RAISED: list[int] = []  # the signals the handler has raised as an interrupt in this process


def _on_signal(signum, frame):
    """SIGINT/SIGTERM -> KeyboardInterrupt/Terminated, raised in ordinary code: a signal that
    lands in a finaliser is sent again a moment later instead of being lost.

    The signal is also recorded, because the interrupt may not reach :func:`main` as itself:
    raised inside a ctypes argument conversion (e.g. in PyOpenGL's function wrappers)
    it surfaces as ``ctypes.ArgumentError("argument 1: KeyboardInterrupt: ")``."""
    if _in_finaliser(frame):
        threading.Timer(0.02, os.kill, (os.getpid(), signum)).start()
        return
    _RAISED.append(signum)
    raise Terminated if signum == signal.SIGTERM else KeyboardInterrupt


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
        prog="jaxmocap",
        description="Differentiable markerless motion capture: the colour-shirt tracker of "
        "Wang et al. 2011 and the stereo particle-filter tracker of Azad et al. 2007.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND",
                                parser_class=_Parser)
    for name in SUBCOMMANDS:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    previous = {}
    del _RAISED[:]
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, _on_signal)
    command = "jaxmocap"
    from jaxmocap._config import enable_side_device

    enable_side_device()  # before anything starts JAX's backend
    try:
        args = build_parser().parse_args(argv)
        command = f"jaxmocap {args.command}"
        from jaxmocap._config import enable_compilation_cache

        enable_compilation_cache()
        return int(args.func(args) or 0)
    except BaseException as err:
        if isinstance(err, KeyboardInterrupt) or _RAISED:
            # an interrupt, possibly wrapped by the library it landed in (see _on_signal)
            terminated = isinstance(err, Terminated) or signal.SIGTERM in _RAISED
            what = "terminated" if terminated else "interrupted"
            print(f"{command}: {what}; nothing written", file=sys.stderr)
            return EXIT_INTERRUPTED
        if not isinstance(err, (InputError, OSError)):
            raise
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        prog = err.prog if isinstance(err, ArgumentError) else command
        print(f"{prog}: error: {msg}", file=sys.stderr)
        return 2
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


if __name__ == "__main__":
    sys.exit(main())
