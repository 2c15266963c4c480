"""Body geometry: simple solids attached to links (Wang et al. 2011 §3 shirt surface;
Azad et al. 2007 §III.A limb cylinders / ellipsoids).

One row per geom. ``pose`` maps the link frame to the geom frame; capsules and cylinders lie
along the geom's z axis. ``size`` per kind (metres):

    SPHERE    (r, 0, 0)
    CAPSULE   (r, h, 0)   h = half length of the segment between the two cap centres
    CYLINDER  (r, h, 0)   h = half height
    BOX       (a, b, c)   half extents
    ELLIPSOID (a, b, c)   semi-axes
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

ArrayLike = Sequence | np.ndarray  # numbers (plain, so that beartype checks it cheaply)
SPHERE, CAPSULE, CYLINDER, BOX, ELLIPSOID = 0, 1, 2, 3, 4
KIND_NAMES = ("sphere", "capsule", "cylinder", "box", "ellipsoid")
DEFAULT_RGBA = (0.7, 0.7, 0.7, 1.0)


class Geometry(eqx.Module):
    """Solids attached to the links of a chain; one row per geom (see module docstring)."""

    link: Int[Array, " n_geoms"]
    kind: Int[Array, " n_geoms"]
    pose: Float[Array, "n_geoms 4 4"]
    size: Float[Array, "n_geoms 3"]
    rgba: Float[Array, "n_geoms 4"]
    names: tuple[str, ...] = eqx.field(static=True)
    # material name per geom as the file gives it ("" none; read by role inference: "skin")
    materials: tuple[str, ...] = eqx.field(static=True, default=())

    def __check_init__(self):
        n = len(self.names)
        for field in ("link", "kind", "pose", "size", "rgba"):
            if getattr(self, field).shape[0] != n:
                raise ValueError(f"Geometry.{field}: expected {n} rows (one per geom name)")

    @property
    def n_geoms(self) -> int:
        return len(self.names)


def make_geometry(rows: list[dict]) -> Geometry:
    """Geometry from rows ``{name, link, kind, pose (4x4), size (3,), rgba (4,)}``."""
    if not rows:
        return Geometry(
            link=jnp.zeros((0,), jnp.int32),
            kind=jnp.zeros((0,), jnp.int32),
            pose=jnp.zeros((0, 4, 4)),
            size=jnp.zeros((0, 3)),
            rgba=jnp.zeros((0, 4)),
            names=(),
        )
    return Geometry(
        link=jnp.asarray(np.array([r["link"] for r in rows]), dtype=jnp.int32),
        kind=jnp.asarray(np.array([r["kind"] for r in rows]), dtype=jnp.int32),
        pose=jnp.asarray(np.stack([np.asarray(r["pose"], float) for r in rows])),
        size=jnp.asarray(np.stack([np.asarray(r["size"], float) for r in rows])),
        rgba=jnp.asarray(np.stack([np.asarray(r["rgba"], float) for r in rows])),
        names=tuple(r["name"] for r in rows),
        materials=tuple(str(r.get("material") or "") for r in rows),
    )
