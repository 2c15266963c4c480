"""The classes a learned observation model gives every pixel, and their ground truth in a render.

Class ids (one table per body + garment, :class:`Classes`):

    0                background (the room, and body parts that are neither shirt nor skin)
    1 .. K           the garment's colours (its ``colour ids``: Wang et al. 2011 §4's 10 colours)
    K + 1            skin of the head (head and neck geoms)
    K + 2, K + 3     skin of the left hand, of the right hand

Skin parts are found by **roles** (:func:`jaxmocap.body.roles.geom_roles`: a geom belongs to the
role of its owner link, fixed child links included), never by a geom's name: the skin geoms
the garment flags whose role is ``head`` / ``neck`` are head, ``l_hand`` / ``r_hand`` the hands.
A skin geom of any other role (a bare forearm) is background: no tracker reads it.
"""

from __future__ import annotations

from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Int

from jaxmocap.body import BodyModel, require_roles
from jaxmocap.body.roles import geom_roles
from jaxmocap.garment import Garment

SKIN_CLASSES = ("head", "left hand", "right hand")
_SKIN_ROLES = {"head": 0, "neck": 0, "l_hand": 1, "r_hand": 2}


class Classes(NamedTuple):
    """The class table of a body + garment (module docstring).

    ``names[c]`` names class c; ``geom_class[g + 1]`` is the class of a hit on geom g that is
    not on a patch (0 for ``g = -1``, the background); patch hits take their colour id."""

    names: tuple[str, ...]
    n_colours: int
    geom_class: np.ndarray  # (n_geoms + 1,) int32

    @property
    def n(self) -> int:
        return len(self.names)

    @property
    def head(self) -> int:
        return self.n_colours + 1

    @property
    def hands(self) -> tuple[int, int]:
        return self.n_colours + 2, self.n_colours + 3


def classes_of(model: BodyModel, garment: Garment) -> Classes:
    """The class table of ``model`` wearing ``garment`` (skin parts by the body's roles)."""
    roles = require_roles(model, "observe.classes")
    by_role = geom_roles(model.chain, model.geometry, dict(roles.links), roles.skin_geoms)
    skin = np.asarray(garment.skin)
    K = garment.n_colours
    table = np.zeros(len(model.geometry.names) + 1, np.int32)
    for role, part in _SKIN_ROLES.items():
        for g in by_role.get(role, []):
            if skin[g]:
                table[g + 1] = K + 1 + part
    names = ("background", *garment.colour_names, *SKIN_CLASSES)
    return Classes(names, K, table)


def labels_of(classes: Classes, geom: Int[Array, "*s"], colour: Int[Array, "*s"]
              ) -> Int[Array, "*s"]:
    """Ground-truth class of every ray from a render's ``geom`` and ``colour`` ids (Hits)."""
    table = jnp.asarray(classes.geom_class)
    return jnp.where(colour > 0, colour, table[geom + 1]).astype(jnp.int32)


def skin_label_map(classes: Classes, labels: Int[Array, "*s"]) -> Int[Array, "*s"]:
    """Skin part per pixel from class ids: 0 none, 1 head, 2 left hand, 3 right hand."""
    part = labels - classes.n_colours
    return jnp.where((part >= 1) & (part <= 3), part, 0)


class PartMaps(NamedTuple):
    """Per-pixel probabilities of the parts a tracker reads (the interface of the learned layer
    to both trackers): the shirt (any of its colours), the head's skin, each hand's skin, and
    the background (the rest). The planes sum to 1."""

    shirt: Array
    head: Array
    left_hand: Array
    right_hand: Array
    background: Array


def part_maps(classes: Classes, logp: Array) -> PartMaps:
    """:class:`PartMaps` from a model's per-pixel log-probabilities (``(..., n_classes)``, e.g.
    :func:`jaxmocap.observe.log_probs`): the stereo filter's skin blobs (head, left and right
    hand, named by the model) and the shirt mask of its edge cue read these."""
    p = jnp.exp(logp)
    K = classes.n_colours
    return PartMaps(shirt=jnp.sum(p[..., 1:K + 1], -1), head=p[..., K + 1],
                    left_hand=p[..., K + 2], right_hand=p[..., K + 3], background=p[..., 0])
