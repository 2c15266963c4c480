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
import importlib
import signal
import sys

from jaxmocap.errors import InputError

SUBCOMMANDS = (
    "jaxmocap.demo",
    "jaxmocap.posedb",
    "jaxmocap.synth.dataset",
    "jaxmocap.commands.calibrate",
    "jaxmocap.commands.colors",
    "jaxmocap.commands.track",
    "jaxmocap.commands.evaluate",
)


EXIT_INTERRUPTED = 130


class UsageError(InputError):
    """Bad command-line usage: reported as one line on stderr with exit code 2."""


class Terminated(KeyboardInterrupt):
    """SIGTERM, delivered as an interrupt so that it takes the Ctrl-C path."""


class _Parser(argparse.ArgumentParser):
    """argparse with its usage errors on one line (the full usage is in ``--help``)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _on_sigterm(signum, frame):
    raise Terminated


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
    try:
        parser = build_parser()
        args = parser.parse_args(argv)
    except KeyboardInterrupt:  # Ctrl-C while the libraries import
        print("jaxmocap: interrupted; nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    from jaxmocap._config import enable_compilation_cache

    enable_compilation_cache()
    previous = None
    with contextlib.suppress(ValueError):  # only the main thread may set handlers
        previous = signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        return int(args.func(args) or 0)
    except (InputError, OSError) as err:
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"jaxmocap {args.command}: error: {msg}", file=sys.stderr)
        return 2
    except KeyboardInterrupt as err:
        what = "terminated" if isinstance(err, Terminated) else "interrupted"
        print(f"jaxmocap {args.command}: {what}; nothing written", file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
