"""The ``jaxmocap`` command."""

from __future__ import annotations

import argparse
import sys


class UsageError(Exception):
    """Bad user input: reported as one line on stderr with exit code 2."""


def _cmd_demo(args: argparse.Namespace) -> int:
    from jaxmocap.demo import run_demo

    return run_demo(args)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="jaxmocap",
        description="Differentiable markerless motion capture (Wang et al. 2011 colour shirt, "
        "Azad et al. 2007 stereo particle filter).",
    )
    sub = parser.add_subparsers(dest="command", required=True)
    demo = sub.add_parser("demo", help="run the main job on bundled data")
    demo.add_argument("--out", default="jaxmocap-demo", help="output folder")
    demo.set_defaults(func=_cmd_demo)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from jaxmocap._config import enable_compilation_cache

    enable_compilation_cache()
    try:
        return int(args.func(args) or 0)
    except UsageError as err:
        print(f"jaxmocap: error: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
