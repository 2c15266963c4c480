"""``garment.json``: a shirt's patches and colours as a file (format in docs/USER_GUIDE.md,
"Your shirt"), read for a body (:class:`jaxmocap.garment.Garment`) and written from one."""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np

from jaxmocap.body import BodyModel
from jaxmocap.errors import InputError
from jaxmocap.garment import (
    MAX_HALF_SPACES,
    NO_PLANE,
    SHIRT_COLOURS,
    Garment,
    _geoms_named,
    default_skin_geoms,
    make_garment,
)

GARMENT_FORMAT = "jaxmocap.garment"
GARMENT_VERSION = 1
_GARMENT_KEYS = ("format", "version", "colours", "patches", "skin")
_PATCH_KEYS = ("name", "geom", "link", "half_spaces", "colour")


def load_garment(path: str | os.PathLike, model: BodyModel, colors=None) -> Garment:
    """A garment from a ``garment.json`` (format in docs/USER_GUIDE.md, "Your shirt").

    ``colors``: the user's colour model (a :class:`jaxmocap.color.ColorModel` with names, or a
    list of colour names): colour ids then follow its order (id k = its k-th colour), every
    colour of the file must be one of its names, and a colour without ``rgb`` in the file takes
    the model's mean. Without it, ids follow the file's ``colours`` order; a colour without
    ``rgb`` must be one of :data:`SHIRT_COLOURS`. Every error is one :class:`InputError` line
    naming the file and the field."""
    path = Path(path)

    def fail(msg: str) -> InputError:
        return InputError(f"{path}: {msg}")

    from jaxmocap.io.preflight import read_json

    data = read_json(path, "a garment.json, format in docs/USER_GUIDE.md 'Your shirt'")
    if not isinstance(data, dict):
        raise fail("expected a JSON object with 'colours' and 'patches'")
    data = _spelling(data, {"colors": "colours"}, fail, "")
    ignored = [k for k in data if k not in _GARMENT_KEYS]
    if data.get("format", GARMENT_FORMAT) != GARMENT_FORMAT:
        raise fail(f"'format' is {data['format']!r}, expected {GARMENT_FORMAT!r}")
    if data.get("version", GARMENT_VERSION) != GARMENT_VERSION:
        raise fail(f"'version' is {data['version']!r}, this jaxmocap reads {GARMENT_VERSION}")
    file_cols = data.get("colours")
    if not isinstance(file_cols, list) or not file_cols:
        raise fail("'colours' must be a non-empty list of names or {name, rgb} objects")
    rgb_of: dict[str, np.ndarray | None] = {}
    for k, c in enumerate(file_cols):
        name, rgb = _colour_entry(c, k, fail)
        if name in rgb_of:
            raise fail(f"colours[{k}]: colour {name!r} is listed twice")
        rgb_of[name] = rgb
    by_index = list(rgb_of)  # a patch may name its colour by index (0 = the first)
    order, model_rgb = list(rgb_of), {}
    if colors is not None:
        cm_names = list(colors) if isinstance(colors, (list, tuple)) else list(colors.names)
        if not cm_names:
            raise fail("the colour model has no colour names to match the garment's colours")
        missing = [n for n in rgb_of if n not in cm_names]
        if missing:
            raise fail(f"colours {missing} are not in the colour model's colours {cm_names}")
        if not isinstance(colors, (list, tuple)):
            mean = np.clip(np.asarray(colors.mean, float) / 255.0, 0.0, 1.0)
            model_rgb = dict(zip(cm_names, mean, strict=True))
        order = cm_names
    table = dict(SHIRT_COLOURS)
    colours = []
    for n in order:
        rgb = rgb_of.get(n)
        if rgb is None:
            rgb = model_rgb.get(n, table.get(n))
        if rgb is None:
            raise fail(f"colour {n!r} has no 'rgb' (and is not one of the named colours "
                       f"{[c for c, _ in SHIRT_COLOURS]})")
        colours.append((n, tuple(float(v) for v in rgb)))
    ids = {n: k + 1 for k, n in enumerate(order)}
    patches_in = data.get("patches")
    if not isinstance(patches_in, list) or not patches_in:
        raise fail("'patches' must be a non-empty list of patch objects")
    patches, seen = [], set()
    for k, p in enumerate(patches_in):
        where = f"patches[{k}]"
        if not isinstance(p, dict):
            raise fail(f"{where}: expected an object with fields {list(_PATCH_KEYS)}")
        p = _spelling(p, {"color": "colour", "halfspaces": "half_spaces"}, fail, where)
        ignored += [f"{where}.{f}" for f in p if f not in _PATCH_KEYS]
        name = p.get("name")
        if not isinstance(name, str) or not name:
            raise fail(f"{where}: 'name' must be a non-empty string")
        if name in seen:
            raise fail(f"{where}: patch name {name!r} is used twice")
        seen.add(name)
        if ("geom" in p) == ("link" in p):
            raise fail(f"{where} ({name!r}): give exactly one of 'geom' or 'link'")
        target = p.get("geom", p.get("link"))
        if "geom" in p and target not in model.geometry.names and target in model.chain.link_names:
            target = _only_geom_of_link(model, target, fail, f"{where} ({name!r})")
        if "geom" in p and target not in model.geometry.names:
            raise fail(f"{where} ({name!r}): unknown geom {target!r}; geoms: "
                       f"{model.geometry.names}")
        if "link" in p and target not in model.chain.link_names:
            raise fail(f"{where} ({name!r}): unknown link {target!r}")
        geoms = [target] if "geom" in p else _geoms_named(model, [target], where)
        if not geoms:
            raise fail(f"{where} ({name!r}): link {target!r} has no geoms")
        hs = p.get("half_spaces", [])
        if not (isinstance(hs, list) and len(hs) <= MAX_HALF_SPACES
                and all(_numbers(h, 4) for h in hs)):
            raise fail(f"{where} ({name!r}): 'half_spaces' must be at most {MAX_HALF_SPACES} "
                       "lists [a, b, c, d] of numbers (a x + b y + c z + d <= 0, geom frame)")
        colour = p.get("colour")
        if isinstance(colour, int) and not isinstance(colour, bool):
            if not 0 <= colour < len(by_index):
                raise fail(f"{where} ({name!r}): colour index {colour} outside 0.."
                           f"{len(by_index) - 1} (the indices of 'colours')")
            colour = by_index[colour]
        if not isinstance(colour, str) or colour not in rgb_of:
            raise fail(f"{where} ({name!r}): colour {colour!r} is not in 'colours' "
                       f"{list(rgb_of)}")
        for g in geoms:
            patches.append((name if len(geoms) == 1 else f"{name}:{g}", g, hs, ids[colour]))
    skin = data.get("skin")
    if skin is None:
        skin_geoms = default_skin_geoms(model)
    elif isinstance(skin, list) and all(isinstance(s, str) for s in skin):
        try:
            skin_geoms = tuple(_geoms_named(model, skin, "'skin'"))
        except InputError as e:
            raise fail(str(e)) from None
    else:
        raise fail("'skin' must be a list of geom or link names")
    if ignored:  # other tools' extra fields: not an error, but said
        print(f"{path}: note: ignoring fields jaxmocap does not use: {ignored}", file=sys.stderr)
    return make_garment(model, patches, colours, skin_geoms)


def _colour_entry(c, k: int, fail) -> tuple[str, np.ndarray | None]:
    """(name, RGB in [0, 1] or None) of ``colours[k]``: a name, or an object with ``name`` and
    ``rgb`` (3 numbers) or MuJoCo's ``rgba`` (4 numbers, or MJCF's ``"r g b a"`` string; alpha
    is not used), all in [0, 1]. An object without ``name`` is called ``colour<k>`` (other tools
    name colours by index)."""
    if isinstance(c, str):
        return c, None
    if not isinstance(c, dict) or set(c) - {"name", "rgb", "rgba"}:
        raise fail(f"colours[{k}]: expected a name or {{\"name\": ..., \"rgb\": [r, g, b]}} "
                   "(or \"rgba\": [r, g, b, a] in [0, 1])")
    if "rgb" in c and "rgba" in c:
        raise fail(f"colours[{k}]: both 'rgb' and 'rgba' given; keep one")
    name = c.get("name", f"colour{k}")
    if not isinstance(name, str) or not name:
        raise fail(f"colours[{k}]: 'name' must be a non-empty string")
    key, n = ("rgba", 4) if "rgba" in c else ("rgb", 3)
    value = c.get(key)
    if value is None:
        return name, None
    if isinstance(value, str):  # MJCF writes rgba="0.8 0.1 0.1 1"
        try:
            value = [float(v) for v in value.split()]
        except ValueError:
            value = None
    ok = _numbers(value, n) and min(value) >= 0 and max(value) <= 1
    if not ok:
        raise fail(f"colours[{k}] ({name!r}): {key!r} must be {n} numbers in [0, 1]"
                   + (" (MuJoCo's rgba; 0..255 values: divide by 255)" if n == 4 else ""))
    return name, np.asarray(value[:3], dtype=float)


def _only_geom_of_link(model: BodyModel, link: str, fail, where: str) -> str:
    """The one geom of ``link`` (with its fixed children), for a patch whose ``geom`` names a
    link: a URDF link's unnamed visual is the geom ``<link>_0``, and other tools name it by its
    link. A link with no geom or several is an error naming them."""
    geoms = _geoms_named(model, [link], where)
    if len(geoms) != 1:
        raise fail(f"{where}: 'geom' {link!r} is a link with {len(geoms)} geoms "
                   f"{geoms}, not one: name one of them as 'geom', or give 'link' for all")
    return geoms[0]


def _spelling(obj: dict, aliases: dict[str, str], fail, where: str) -> dict:
    """``obj`` with other tools' spellings of our fields (``colors``, ``color``) renamed; both
    spellings at once is ambiguous (one error naming the field)."""
    out = dict(obj)
    for other, ours in aliases.items():
        if other in out:
            if ours in out:
                raise fail(f"{where + ': ' if where else ''}both {other!r} and {ours!r} given; "
                           "keep one")
            out[ours] = out.pop(other)
    return out


def _numbers(v, n: int) -> bool:
    return (isinstance(v, list) and len(v) == n
            and all(isinstance(x, (int, float)) and not isinstance(x, bool) and np.isfinite(x)
                    for x in v))


def garment_to_json(garment: Garment, model: BodyModel) -> dict:
    """The ``garment.json`` contents of a garment on ``model`` (round trip with
    :func:`load_garment`)."""
    names = model.geometry.names
    planes = np.asarray(garment.patch_planes, np.float64)
    unused = np.asarray(NO_PLANE)
    patches = []
    for i, pname in enumerate(garment.patch_names):
        hs = [[float(v) for v in row] for row in planes[i] if not np.allclose(row, unused)]
        patches.append({"name": pname, "geom": names[int(garment.patch_geom[i])],
                        "half_spaces": hs,
                        "colour": garment.colour_names[int(garment.patch_colour[i]) - 1]})
    return {
        "format": GARMENT_FORMAT,
        "version": GARMENT_VERSION,
        "colours": [{"name": n, "rgb": [float(v) for v in rgb]}
                    for n, rgb in zip(garment.colour_names, np.asarray(garment.colours),
                                      strict=True)],
        "patches": patches,
        "skin": [n for n, s in zip(names, np.asarray(garment.skin).tolist(), strict=True) if s],
    }


def save_garment(path: str | os.PathLike, garment: Garment, model: BodyModel) -> Path:
    """Write ``garment`` as a ``garment.json`` (atomically)."""
    from jaxmocap.io.atomic import write_text

    return write_text(path, json.dumps(garment_to_json(garment, model), indent=1) + "\n")
