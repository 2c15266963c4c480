"""Loading a body model: a user's URDF or MJCF with its roles (inferred, or a roles file), and
the bundled upper body. The one place that joins the file readers (:mod:`.urdf`, :mod:`.mjcf`)
with the roles (:mod:`.roles`) and the model (:mod:`.model`)."""

from __future__ import annotations

import functools
import os
from pathlib import Path

import equinox as eqx
import numpy as np

from ..errors import InputError
from .mjcf import load_mjcf
from .model import DEFAULT_KEYPOINTS, DEFAULT_URDF, BodyModel, make_body_model
from .roles import (
    KEYPOINT_NAMES,
    BodyRoles,
    face_forward,
    infer_roles,
    read_roles_file,
    roles_path,
)
from .urdf import load_urdf

MODEL_SUFFIXES = {".urdf": "urdf", ".xml": "mjcf", ".mjcf": "mjcf"}


def load_body(path: str | os.PathLike, roles: BodyRoles | str | os.PathLike | None = None, *,
              scale: float = 1.0, up: str = "z"):
    """A user's body model: URDF or MJCF by suffix (``.urdf``; ``.xml``/``.mjcf``), with its
    roles (``roles``: a :class:`BodyRoles`, a roles file, or None = ``<stem>.roles.json``
    beside the model if it exists, else inferred from the names) and the 12 keypoints placed
    from the roles (:mod:`jaxmocap.body.roles`), followed by the MJCF's other ``<site>``
    markers (a site named like one of the 12 places that keypoint). ``scale``/``up``: a URDF's
    units and up axis (:func:`~jaxmocap.body.load_urdf`). Bad files and missing roles: one
    :class:`InputError`."""
    path = Path(path)
    kind = MODEL_SUFFIXES.get(path.suffix.lower())
    if kind is None:
        raise InputError(f"{path}: a body model must be a URDF (.urdf) or MJCF (.xml, .mjcf) file")
    if not path.is_file():
        raise InputError(f"{path}: body model file not found")
    try:
        if kind == "mjcf" and (scale != 1.0 or up != "z"):
            raise InputError(f"{path}: scale/up apply to URDF files (MJCF is metres, z up)")
        model = load_urdf(path, scale=scale, up=up) if kind == "urdf" else load_mjcf(path)
    except InputError:
        raise
    except (ValueError, RuntimeError, KeyError) as e:
        msg = " ".join(str(e).split())
        raise InputError(msg if str(path) in msg else f"{path}: {msg}") from None

    # MJCF <site> markers (load_mjcf's keypoints): a site named like one of the 12 keypoints
    # places it (under the roles file's keypoints), the others are kept as extra keypoints
    links = np.asarray(model.keypoint_link).tolist()
    offsets = np.asarray(model.keypoint_offset, np.float64)
    sites = {k: (model.chain.link_names[links[i]], tuple(float(v) for v in offsets[i]))
             for i, k in enumerate(model.keypoint_names)}
    if not isinstance(roles, BodyRoles):
        file = Path(roles) if roles is not None else roles_path(path)
        overrides = read_roles_file(file) if (roles is not None or file.is_file()) else {}
        named = {k: v for k, v in sites.items() if k in KEYPOINT_NAMES}
        if named:
            overrides["keypoints"] = {**named, **overrides.get("keypoints", {})}
        roles = infer_roles(model.chain, model.geometry, path, overrides)
        turned = face_forward(model.chain, roles)
        if turned is not model.chain:  # roles again: the mirror pairs are found at rest
            model = eqx.tree_at(lambda m: m.chain, model, turned)
            roles = infer_roles(model.chain, model.geometry, path, overrides)
    table = roles.keypoint_table()
    table.update({k: v for k, v in sites.items() if k not in table})
    return make_body_model(model.chain, model.geometry, table, roles=roles)


@functools.cache
def default_body() -> BodyModel:
    """The bundled generic adult upper body (``data/upper_body.urdf``), loaded once, with its
    roles inferred from its names and the keypoints :data:`DEFAULT_KEYPOINTS` (which are what
    the roles' keypoint rules give; tests/test_body_roles.py checks it)."""
    model = load_urdf(DEFAULT_URDF)
    kp = {k: (link, tuple(float(v) for v in off)) for k, (link, off) in DEFAULT_KEYPOINTS.items()}
    roles = infer_roles(model.chain, model.geometry, DEFAULT_URDF, {"keypoints": kp})
    return make_body_model(model.chain, model.geometry, DEFAULT_KEYPOINTS, roles=roles)


__all__ = ["MODEL_SUFFIXES", "default_body", "load_body"]
