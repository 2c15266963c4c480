"""``--body`` and ``--garment``: the user's body model and shirt, shared by the commands.

``--body FILE`` is a URDF (``.urdf``) or MJCF (``.xml``/``.mjcf``) file; its roles come from
``<stem>.roles.json`` beside it or are inferred from the names
(:func:`jaxmocap.body.load_body`). ``--garment FILE`` is a ``garment.json``
(:func:`jaxmocap.io.garment_file.load_garment`); without it the paper's 20-patch shirt is laid
out on the body by its roles (:func:`jaxmocap.garment.default_garment`), which refuses, in one line,
a body where that layout does not fit. Both default to the bundled body and shirt. Every
problem is one :class:`~jaxmocap.errors.InputError` (exit code 2) before any work.
"""

from __future__ import annotations

import argparse

from jaxmocap.body import BodyModel, default_body, load_body
from jaxmocap.errors import InputError
from jaxmocap.garment import Garment, default_garment
from jaxmocap.io.garment_file import load_garment

BODY_HELP = ("your body model: a URDF (.urdf) or MJCF (.xml) file, its roles in "
             "<stem>.roles.json beside it or inferred from its link names (default: the bundled "
             "generic upper body)")  # fmt: skip
GARMENT_HELP = ("your shirt: a garment.json (patches -> geoms, colours in your colour model's "
                "order; default: the paper's 20-patch, 10-colour shirt laid out on the body)")


def add_body_args(parser: argparse.ArgumentParser | argparse._ArgumentGroup,
                  garment: bool = True) -> None:
    """Add ``--body`` (and ``--garment``) to a command's parser."""
    parser.add_argument("--body", metavar="URDF_OR_MJCF", help=BODY_HELP)
    parser.add_argument("--body-scale", type=float, default=1.0, metavar="S",
                        help="a URDF's units in metres (pybullet's DeepMimic humanoid.urdf: "
                        "0.25, as pybullet's globalScaling; default: %(default)s)")
    parser.add_argument("--body-up", choices=("z", "y"), default="z",
                        help="a URDF's up axis (pybullet's humanoid.urdf: y; default: "
                        "%(default)s)")
    if garment:
        parser.add_argument("--garment", metavar="GARMENT_JSON", help=GARMENT_HELP)


def body_from_args(args: argparse.Namespace) -> BodyModel:
    """The body of ``--body`` (the bundled body without it)."""
    path = getattr(args, "body", None)
    scale, up = getattr(args, "body_scale", 1.0), getattr(args, "body_up", "z")
    if not path:
        if (scale, up) != (1.0, "z"):
            raise InputError("--body-scale/--body-up describe a --body URDF; give --body")
        return default_body()
    if not scale > 0:
        raise InputError(f"--body-scale: expected a positive number, got {scale}")
    return load_body(path, scale=scale, up=up)


def garment_from_args(args: argparse.Namespace, model: BodyModel, colors=None) -> Garment:
    """The shirt of ``--garment`` on ``model`` (the paper's shirt laid out by roles without
    it). ``colors``: a colour model whose colour order the garment's ids must follow."""
    path = getattr(args, "garment", None)
    if path:
        return load_garment(path, model, colors)
    return default_garment(model)


def pf_garment(args: argparse.Namespace, model: BodyModel) -> Garment:
    """The stereo filter's shirt: ``--garment`` (one colour: Azad's set-up), else Azad's blue
    shirt on ``model`` (:func:`jaxmocap.garment.single_colour_garment`)."""
    from jaxmocap.garment import single_colour_garment
    from jaxmocap.synth.scene import AZAD_SHIRT_RGB

    path = getattr(args, "garment", None)
    if not path:
        return single_colour_garment(model, AZAD_SHIRT_RGB)
    garment = load_garment(path, model)
    if garment.n_colours != 1:
        raise InputError(f"{path}: the particle filter's shirt has one colour (Azad et al. "
                         f"2007), this garment has {garment.n_colours}")
    return garment


def inputs_of(args: argparse.Namespace) -> list[str]:
    """The body/garment files a command reads (for the outputs-never-touch-inputs check)."""
    return [p for p in (getattr(args, "body", None), getattr(args, "garment", None)) if p]
