"""``jaxmocap colors``: scribbled images -> the shirt's colour model ``colors.json`` (Wang §5.1),
or with ``--white-balance`` one scribbled frame per camera of the capture's light -> the
initial white balance ``W0`` per camera (``white_balance.json``).

Scribbles are a label image beside each photo: a single-channel PNG (8 or 16 bit) of the
photo's size where pixel value ``k`` marks colour ``k`` (1..K) and 0 marks "no label". Masks
written by another tool (e.g. values 0..9 with 255 = unlabelled) come with ``--labels
labels.json``, a map ``{"<value>": "<colour name>" | "unlabelled" | "room"}`` that translates
them (colour k = the k-th of ``--names`` / the garment's / the colour model's colours).

``white_balance.json``::

    {"format": "jaxmocap.white_balance", "version": 1,
     "cameras": {"cam0": [[w00, w01, w02], [w10, ...], [...]], "cam1": ...}}

``W`` maps a camera's RGB (0..255) to the colour model's: ``W rgb_observed ~ mu_k``.

With ``--room-label V`` the same scribbled frames also mark the room (label ``V``, any value
above the shirt's colours): its colours, white-balanced by each camera's ``W``, are clustered
into ``--room-colors`` Gaussians (:func:`jaxmocap.color.fit_scene_colors`) stored as
``"room": [{"name", "mean", "cov"}, ...]``; ``jaxmocap track`` then classifies a pixel nearer
one of them than every shirt colour as background. With ``--shading LO HI`` the colour model
is fitted for the shading-invariant colour distance (for footage under spot lamps; not in the
paper) and ``colors.json`` records the range.
"""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import cv2
import numpy as np

from jaxmocap.color import (
    ColorModel,
    fit_color_model,
    load_color_model,
    save_color_model,
    white_balance_from_scribbles,
)
from jaxmocap.errors import InputError
from jaxmocap.io.atomic import check_output_file
from jaxmocap.io.preflight import check_outputs, int_range, read_json
from jaxmocap.io.video import decode_image
from jaxmocap.io.white_balance import (
    WhiteBalanceFileError,
    load_room_colors,
    load_white_balance,
    save_white_balance,
    white_balance_problem,
)

__all__ = [
    "MIN_COLORS_FOR_W",
    "MIN_SCRIBBLE_PIXELS",
    "WhiteBalanceFileError",
    "add_parser",
    "load_room_colors",
    "load_white_balance",
    "read_label_mask",
    "read_rgb",
    "run",
    "save_white_balance",
    "white_balance_problem",
]

MIN_SCRIBBLE_PIXELS = 20  # labelled pixels a colour needs (cf. color.whitebalance.MIN_PIXELS)
MIN_COLORS_FOR_W = 3  # a 3x3 W is determined by >= 3 colours (fewer: only the prior decides)

EPILOG = """examples:
  # colour model from scribbled photos of the shirt (label k = colour k, 0 = none)
  jaxmocap colors --images shirt1.png shirt2.png --masks shirt1_labels.png shirt2_labels.png \\
      --names red green blue yellow --out colors.json
  # initial white balance of each camera from one scribbled frame of the capture
  jaxmocap colors --white-balance --colors colors.json --images cam0.png cam1.png \\
      --masks cam0_labels.png cam1_labels.png --out white_balance.json
  # footage under spot lamps: a shading-invariant model, and the room scribbled as label 255
  jaxmocap colors --shading 0.5 4 --images shirt1.png --masks shirt1_labels.png --out colors.json
  jaxmocap colors --white-balance --colors colors.json --images cam0.png cam1.png \\
      --masks cam0_labels.png cam1_labels.png --room-label 255 --out white_balance.json
"""


def read_rgb(path: str | os.PathLike) -> np.ndarray:
    """An image file as uint8 (H, W, 3) RGB; raises InputError naming the file."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such image file")
    img, why = decode_image(path, cv2.IMREAD_COLOR)
    if img is None:
        raise InputError(f"{path}: not a readable image (empty or corrupt: {why})")
    return np.ascontiguousarray(img[..., ::-1])


def read_label_mask(path: str | os.PathLike) -> np.ndarray:
    """A label PNG as int32 (H, W): single-channel 8/16-bit, or 3 equal channels."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"{path}: no such label mask file")
    lab, why = decode_image(path, cv2.IMREAD_UNCHANGED)
    if lab is None:
        raise InputError(f"{path}: not a readable label image (empty or corrupt: {why})")
    if lab.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{path}: label mask must be 8- or 16-bit integers, got {lab.dtype}")
    if lab.ndim == 3:
        if lab.shape[2] == 4:
            lab = lab[..., :3]
        if not (np.all(lab[..., 0] == lab[..., 1]) and np.all(lab[..., 0] == lab[..., 2])):
            raise InputError(f"{path}: label mask must be single-channel (grey values 0..K), got "
                             "a colour image")
        lab = lab[..., 0]
    return lab.astype(np.int32)


UNLABELLED, ROOM = "unlabelled", "room"  # the label map's special names


def read_label_map(path: str | os.PathLike) -> dict[int, str]:
    """Another tool's label map (``--labels``): ``{"<mask value>": "<colour name>" |
    "unlabelled" | "room"}``; one InputError line naming the file and the entry."""
    path = Path(path)
    data = read_json(path, "a label map of --labels (mask value -> colour name, 'unlabelled' "
                     "or 'room')")
    if not isinstance(data, dict) or not data:
        raise InputError(f"{path}: expected an object {{\"<mask value>\": \"<colour name>\" | "
                         f"\"{UNLABELLED}\" | \"{ROOM}\"}}")
    out = {}
    for k, v in data.items():
        if not (isinstance(k, str) and k.isdigit() and int(k) <= 65535):
            raise InputError(f"{path}: key {k!r}: expected a mask value 0..65535 (as a string)")
        if not isinstance(v, str) or not v:
            raise InputError(f"{path}: {k!r}: expected a colour name, {UNLABELLED!r} or {ROOM!r}")
        out[int(k)] = v
    if all(v in (UNLABELLED, ROOM) for v in out.values()):
        raise InputError(f"{path}: names no colour (only {UNLABELLED!r}/{ROOM!r} values)")
    return out


def _label_names(mapping: dict[int, str]) -> list[str]:
    """Colour names of a label map in the order of their smallest mask value."""
    names: list[str] = []
    for _, v in sorted(mapping.items()):
        if v not in (UNLABELLED, ROOM) and v not in names:
            names.append(v)
    return names


def _translate(args, labels: list[np.ndarray], names: list[str], room: int) -> list[np.ndarray]:
    """The masks in our convention (k = the k-th of ``names``, 0 = none, ``room`` = room) from
    another tool's values through ``--labels``."""
    mapping = read_label_map(args.labels)
    missing = [n for n in _label_names(mapping) if n not in names]
    if missing:
        raise InputError(f"{args.labels}: colours {missing} are not among {names}")
    ids = {**{n: k + 1 for k, n in enumerate(names)}, UNLABELLED: 0, ROOM: room}
    out = []
    for mp, lab in zip(args.masks, labels, strict=True):
        values = np.unique(lab)
        unknown = [int(v) for v in values if int(v) not in mapping]
        if unknown:
            raise InputError(f"{mp}: mask values {unknown[:5]} are not in the label map "
                             f"{args.labels}")
        lut = np.zeros(int(values.max()) + 1, np.int32)
        for v in values:
            lut[int(v)] = ids[mapping[int(v)]]
        out.append(lut[lab])
    return out


def _read_pairs(args, names: list[str] | None = None, room: int = 0
                ) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Images and label masks; with ``--labels`` the masks are translated (colour names in the
    order ``names``; default: the map's own order, which then names the model)."""
    if not args.images:
        raise InputError("--images: give at least one image")
    if len(args.masks or []) != len(args.images):
        raise InputError(f"--masks: need one label mask per image, got {len(args.images)} images "
                         f"and {len(args.masks or [])} masks")
    images, labels = [], []
    for ip, mp in zip(args.images, args.masks, strict=True):
        img, lab = read_rgb(ip), read_label_mask(mp)
        if lab.shape != img.shape[:2]:
            raise InputError(f"{mp}: label mask is {lab.shape[1]}x{lab.shape[0]} but image {ip} "
                             f"is {img.shape[1]}x{img.shape[0]}; they must be the same size")
        images.append(img)
        labels.append(lab)
    if getattr(args, "labels", None):
        labels = _translate(args, labels, names or _label_names(read_label_map(args.labels)),
                            room)
    return images, labels


def _check_labels(masks: list[str], labels: list[np.ndarray], n_colors: int,
                  need_all: bool) -> np.ndarray:
    """Per-colour pixel counts; refuse labels > n_colors and (``need_all``) colours with too
    few pixels."""
    for mp, lab in zip(masks, labels, strict=True):
        bad = np.unique(lab[(lab < 0) | (lab > n_colors)])
        if bad.size:
            raise InputError(f"{mp}: labels {bad[:5].tolist()} out of range: expected 0 (none) "
                             f"or a colour 1..{n_colors}")
    counts = np.zeros(n_colors + 1, np.int64)
    for lab in labels:
        counts += np.bincount(lab.reshape(-1), minlength=n_colors + 1)
    if need_all:
        few = [k for k in range(1, n_colors + 1) if counts[k] < MIN_SCRIBBLE_PIXELS]
        if few:
            k = few[0]
            raise InputError(f"colour {k} has {counts[k]} labelled pixels in the masks (need >= "
                             f"{MIN_SCRIBBLE_PIXELS}): scribble more of colour {k}, or lower "
                             "--n-colors if the shirt has fewer colours")
    return counts[1:]


def _garment_colours(args) -> tuple[str, ...] | None:
    """The colour names of ``--garment`` (on ``--body``), in the file's order: label k of the
    masks is then the garment's k-th colour, and the model is named after them."""
    if not getattr(args, "garment", None):
        return None
    from jaxmocap.commands._body import body_from_args, garment_from_args

    if args.names or args.n_colors:
        raise InputError("--garment names the colours and their count; leave out --names and "
                         "--n-colors")
    return garment_from_args(args, body_from_args(args)).colour_names


def _run_model(args, out: Path) -> int:
    garment_names = _garment_colours(args)
    if getattr(args, "labels", None) and garment_names is None:
        map_names = _label_names(read_label_map(args.labels))
        if args.names and sorted(args.names) != sorted(map_names):
            raise InputError(f"--names {args.names}: the label map {args.labels} names "
                             f"{map_names}")
        args.names = list(args.names or map_names)
        args.n_colors = args.n_colors or len(args.names)
    images, labels = _read_pairs(args, list(garment_names or args.names or []) or None)
    if garment_names is not None:
        args.names, args.n_colors = list(garment_names), len(garment_names)
    n = args.n_colors or int(max(lab.max() for lab in labels))
    if n < 1:
        raise InputError("the label masks hold no labels (all 0): scribble each shirt colour "
                         "with its label value 1..K")
    if args.names and len(args.names) != n:
        raise InputError(f"--names: {len(args.names)} names for {n} colours")
    counts = _check_labels(args.masks, labels, n, need_all=True)
    model = fit_color_model(images, labels, n, tuple(args.names or ()),
                            gain=None if args.shading is None else tuple(args.shading))
    out.parent.mkdir(parents=True, exist_ok=True)
    save_color_model(out, model)
    names = model.names or tuple(f"color{k + 1}" for k in range(n))
    mean = np.asarray(model.mean)
    for k in range(n):
        sd = np.sqrt(np.diag(np.asarray(model.cov[k])))
        print(f"colour {k + 1} {names[k]}: {counts[k]} px, mean RGB "
              f"({mean[k, 0]:.0f}, {mean[k, 1]:.0f}, {mean[k, 2]:.0f}), sd "
              f"({sd[0]:.1f}, {sd[1]:.1f}, {sd[2]:.1f})")
    if model.shading is not None:
        print(f"fitted for the shading-invariant distance, brightness {model.shading[0]:g}.."
              f"{model.shading[1]:g} (recorded in {out.name}; `jaxmocap track` uses it)")
    print(f"wrote {out}")
    return 0


def _run_pf(args, out: Path) -> int:
    """The stereo particle filter's capture colours (:mod:`jaxmocap.pf.colors`): label 1
    marks skin (the face), label 2 the shirt."""
    from jaxmocap.pf.colors import fit_capture_colors, save_capture_colors

    images, labels = _read_pairs(args, ["skin", "shirt"])
    counts = _check_labels(args.masks, labels, 2, need_all=True)
    colors = fit_capture_colors(images, [lab == 1 for lab in labels],
                                [lab == 2 for lab in labels])
    out.parent.mkdir(parents=True, exist_ok=True)
    save_capture_colors(out, colors)
    print(f"skin: {counts[0]} px, shirt: {counts[1]} px (label 1 skin, 2 shirt)")
    print(f"wrote {out}")
    return 0


def _run_white_balance(args, out: Path) -> int:
    if not args.colors:
        raise InputError("--white-balance needs --colors colors.json (the colour model)")
    model: ColorModel = load_color_model(args.colors)
    if getattr(args, "labels", None):
        if args.room_label is not None:
            raise InputError(f"--room-label: the label map {args.labels} says which value is "
                             f"the room ({ROOM!r}); leave --room-label out")
        if ROOM in read_label_map(args.labels).values():
            args.room_label = model.n_colors + 1
    images, labels = _read_pairs(args, list(model.names), args.room_label or 0)
    names = args.names or [f"cam{i}" for i in range(len(images))]
    if len(names) != len(images) or len(set(names)) != len(names):
        raise InputError(f"--names: need {len(images)} distinct camera names, got {names}")
    room_masks = _room_masks(args, labels, model.n_colors)
    W = {}
    for name, mp, img, lab in zip(names, args.masks, images, labels, strict=True):
        if room_masks is not None:
            lab = np.where(lab == args.room_label, 0, lab)
        counts = _check_labels([mp], [lab], model.n_colors, need_all=False)
        usable = int((counts >= MIN_SCRIBBLE_PIXELS).sum())
        if usable < MIN_COLORS_FOR_W:
            raise InputError(f"{mp}: {usable} colours have >= {MIN_SCRIBBLE_PIXELS} labelled "
                             f"pixels, need >= {MIN_COLORS_FOR_W} to determine W: scribble "
                             "more colours of the shirt in this frame")
        W[name] = np.asarray(white_balance_from_scribbles(model, [img], [lab]), np.float64)
        problem = white_balance_problem(W[name])
        if problem:
            raise InputError(f"{mp}: the white balance fitted from these labels is unusable: "
                             f"{problem}; check that label k marks colour k of {args.colors}")
        print(f"{name}: W from {usable} colours, diag ({W[name][0, 0]:.3f}, "
              f"{W[name][1, 1]:.3f}, {W[name][2, 2]:.3f})")
    room = None
    if room_masks is not None:
        from jaxmocap.color import fit_scene_colors

        room = fit_scene_colors(images, room_masks, [W[n] for n in names], args.room_colors)
        print(f"room: {room.n_colors} colours from {sum(int(m.sum()) for m in room_masks)} px "
              f"(label {args.room_label})")
    save_white_balance(out, W, room)
    print(f"wrote {out}")
    return 0


def _room_masks(args, labels: list[np.ndarray], n_colors: int) -> list[np.ndarray] | None:
    """The room pixels (label ``--room-label``) of each mask, checked before any fitting."""
    if args.room_label is None:
        return None
    if args.room_label <= n_colors:
        raise InputError(f"--room-label {args.room_label}: labels 1..{n_colors} are the shirt's "
                         f"colours of {args.colors}; mark the room with a larger value (e.g. "
                         "255)")
    masks = [lab == args.room_label for lab in labels]
    need = 10 * args.room_colors
    have = sum(int(m.sum()) for m in masks)
    if have < need:
        raise InputError(f"--masks: {have} pixels carry the room label {args.room_label}, need "
                         f">= {need} for {args.room_colors} room colours: scribble more of the "
                         "room (walls, floor, props) or lower --room-colors")
    return masks


def add_parser(sub) -> None:
    p = sub.add_parser(
        "colors", help="fit the shirt's colour model (colors.json) or an initial white balance "
        "from scribbled images",
        description="Fit one Gaussian per shirt colour from labelled pixels (Wang et al. 2011 "
        "§5.1): each image comes with a single-channel label PNG of the same size where value k "
        "marks colour k and 0 marks nothing. With --white-balance, fit instead each camera's "
        "initial white balance W from one scribbled frame of the capture environment.",
        epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--images", nargs="+", metavar="IMAGE", required=True,
                   help="photos (PNG/JPEG); with --white-balance one frame per camera")
    p.add_argument("--masks", nargs="+", metavar="MASK", required=True,
                   help="label PNGs, one per image, same size (0 = none, k = colour k)")
    p.add_argument("--out", help="output file (default: colors.json, or white_balance.json "
                   "with --white-balance)")
    p.add_argument("--names", nargs="+", help="colour names (model) or camera names "
                   "(--white-balance; default cam0 cam1 ... as in cameras.json)")
    p.add_argument("--n-colors", type=int_range(1, 255, "label values are 8-bit"), metavar="K",
                   help="number of colours (default: the largest label)")
    p.add_argument("--white-balance", action="store_true",
                   help="fit the initial white balance W0 per camera instead of the model")
    p.add_argument("--colors", metavar="COLORS_JSON",
                   help="the colour model (required with --white-balance)")
    p.add_argument("--pf", action="store_true",
                   help="fit the stereo particle filter's skin and shirt colours of the capture "
                   "(pf_colors.json for `jaxmocap track --method pf --pf-colors`): label 1 = "
                   "skin (scribble the face), 2 = shirt")
    p.add_argument("--shading", nargs=2, type=float, metavar=("LO", "HI"),
                   help="fit the colour model for the shading-invariant colour distance: a "
                   "pixel is compared with each colour at its best brightness in LO..HI (0 < "
                   "LO <= 1 <= HI; e.g. 0.5 4 under spot lamps; not in the paper)")
    p.add_argument("--room-label", type=int_range(1, 65535, "16-bit label values"),
                   metavar="V", help="with --white-balance: label V in the masks marks the room "
                   "(walls, floor, props); its colours become background for `jaxmocap track`")
    p.add_argument("--labels", metavar="LABELS_JSON",
                   help="masks written by another tool: a JSON map from mask value to colour "
                   f"name, {UNLABELLED!r} or {ROOM!r} (e.g. {{\"0\": \"red\", ..., \"255\": "
                   f"\"{UNLABELLED}\"}}); colour names follow --names / --garment / the colour "
                   "model (--white-balance), else the map's order (by value)")
    p.add_argument("--room-colors", type=int_range(1, 64), default=16, metavar="N",
                   help="Gaussians of the room's colours with --room-label (default: "
                   "%(default)s)")
    from jaxmocap.commands._body import add_body_args

    add_body_args(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from jaxmocap.io.video import quiet_ffmpeg

    quiet_ffmpeg()  # OpenCV's own lines about a corrupt image: we report it in one line
    if args.pf and args.white_balance:
        raise InputError("--pf and --white-balance: give one of them")
    if args.shading is not None and (args.pf or args.white_balance):
        raise InputError("--shading applies to the shirt's colour model; leave it out with "
                         f"{'--pf' if args.pf else '--white-balance'}")
    if args.shading is not None:
        from jaxmocap.color.model import shading_problem

        problem = shading_problem(args.shading)
        if problem:
            raise InputError(f"--shading: {problem}")
    if args.room_label is not None and not args.white_balance:
        raise InputError("--room-label marks the room in the capture's scribbled frames: give "
                         "it with --white-balance")
    default = "white_balance.json" if args.white_balance else \
        "pf_colors.json" if args.pf else "colors.json"
    out = check_output_file(args.out or default)
    check_outputs([out], [*args.images, *args.masks, args.colors, getattr(args, "body", None),
                          getattr(args, "garment", None), args.labels])
    if args.pf:
        return _run_pf(args, out)
    return _run_white_balance(args, out) if args.white_balance else _run_model(args, out)
