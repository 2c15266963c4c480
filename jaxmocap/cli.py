"""The ``jaxmocap`` command.

Each sub-command lives beside the code it drives and registers itself here: a module listed in
``SUBCOMMANDS`` exposes ``add_parser(subparsers)``, which adds its parser and sets
``func=run`` (``run(args) -> int``). Bad user input raises :class:`UsageError` (or one of the
library's file-format errors, all :class:`~jaxmocap.errors.InputError` subclasses): it is
printed as one line on stderr and the exit code is 2.
"""

from __future__ import annotations

import argparse
import importlib
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
    "jaxmocap.experiment",
)


class UsageError(InputError):
    """Bad command-line usage: reported as one line on stderr with exit code 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxmocap",
        description="Differentiable markerless motion capture: the colour-shirt tracker of "
        "Wang et al. 2011 and the stereo particle-filter tracker of Azad et al. 2007.",
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from jaxmocap._config import enable_compilation_cache

    enable_compilation_cache()
    try:
        return int(args.func(args) or 0)
    except (InputError, OSError) as err:
        msg = str(err).splitlines()[0] if str(err) else type(err).__name__
        print(f"jaxmocap {args.command}: error: {msg}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
