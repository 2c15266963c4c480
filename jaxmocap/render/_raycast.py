"""Ray casting the body: per-ray geom id, patch id, colour id, depth and normal.

For a pose q, forward kinematics gives every geom's world transform ``(R_g, p_g)`` (geom frame
-> world). A ray ``o + t d`` (unit d, world) is moved into each geom's frame with 3x3 maths,

    o_g = R_g^T (o - p_g),   d_g = R_g^T d,

intersected analytically there (``_intersect``), and the nearest entry ``t* = min_g t_g`` wins.
The winning geom's local hit point ``o_g + t* d_g`` selects the garment patch; its normal is
rotated back to the world. Rays are processed in fixed-size chunks (``lax.map``) so a 640x480
image with ~30 geoms needs a few MB per chunk.

Kinds are grouped statically when ``model.geometry.kind`` is concrete (close over the model,
or pass it un-jitted): each geom then runs only its own primitive's test. When the kinds are
traced (the model is a jit argument) every primitive is evaluated and selected per geom —
correct, about 3x slower.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .. import garment as _garment
from ..body import BodyModel, fk, geom_world_poses
from ..garment import Garment
from ._intersect import intersect_components, surface_normal

RAY_CHUNK = 4096  # rays per lax.map step: ~30 geoms x 4096 rays x 3 floats per temporary


class Hits(NamedTuple):
    """Per-ray result of the ray caster; background rays have ``geom = -1``, ``patch = 0``,
    ``colour = 0``, ``t = depth = inf`` and a zero normal."""

    geom: Int[Array, "*n"]  # geom index, -1 background
    patch: Int[Array, "*n"]  # patch id, 0 background / unpatched
    colour: Int[Array, "*n"]  # colour id, 0 none
    t: Float[Array, "*n"]  # distance along the unit ray (m)
    depth: Float[Array, "*n"]  # camera-frame z of the hit point (m)
    normal: Float[Array, "*n 3"]  # world unit normal
    point: Float[Array, "*n 3"]  # world hit point (m)
    background: Bool[Array, "*n"]


class Scene(NamedTuple):
    """The posed geoms, sorted by kind: rotation (geom -> world), position, size, kind, the
    original geom index of each sorted row, and the static kind groups."""

    R: Float[Array, "g 3 3"]
    p: Float[Array, "g 3"]
    size: Float[Array, "g 3"]
    kind: Int[Array, " g"]
    geom_index: Int[Array, " g"]
    groups: tuple[tuple[int | None, int, int], ...]  # (kind or None, start, stop)


def kind_groups(model: BodyModel) -> tuple[np.ndarray, tuple[tuple[int | None, int, int], ...]]:
    """Static permutation sorting geoms by kind and the ``(kind, start, stop)`` runs; one
    ``(None, 0, G)`` run (select every primitive) when the kinds are traced."""
    kind = model.geometry.kind
    n = kind.shape[0]
    try:
        k = np.asarray(kind)
    except (jax.errors.TracerArrayConversionError, jax.errors.ConcretizationTypeError):
        return np.arange(n), ((None, 0, n),)
    perm = np.argsort(k, kind="stable")
    groups, start = [], 0
    for value in np.unique(k):
        stop = start + int(np.sum(k == value))
        groups.append((int(value), start, stop))
        start = stop
    return perm, tuple(groups)


def posed_scene(model: BodyModel, q: Float[Array, " n_dof"]) -> Scene:
    """World transforms of every geom at pose ``q`` (``fk`` + ``geom_world_poses``), sorted
    into kind groups."""
    perm, groups = kind_groups(model)
    T = geom_world_poses(model, fk(model.chain, q))[perm]
    geo = model.geometry
    return Scene(
        R=T[:, :3, :3],
        p=T[:, :3, 3],
        size=geo.size.astype(q.dtype)[perm],
        kind=jnp.asarray(geo.kind)[perm],
        geom_index=jnp.asarray(perm, jnp.int32),
        groups=groups,
    )


def _cast_chunk(
    scene: Scene, garment: Garment, origin: Float[Array, " 3"], d: Float[Array, "n 3"]
) -> tuple[Array, Array, Array, Array, Array]:
    """Nearest hits of rays from one origin: (geom, patch, t, world normal, world point).

    The local rays are held as three ``(geoms, rays)`` planes, one per axis
    (``_intersect.intersect_components``): XLA vectorises each plane along the rays."""
    o_loc = jnp.einsum("gji,gj->gi", scene.R, origin[None, :] - scene.p)  # R^T (o - p)
    d_loc = jnp.einsum("gji,nj->ign", scene.R, d)  # (3, g, n)
    ts = []
    for kind, a, b in scene.groups:
        dl = tuple(d_loc[k, a:b] for k in range(3))
        ol = tuple(o_loc[a:b, k, None] for k in range(3))
        sz = tuple(scene.size[a:b, k, None] for k in range(3))
        ka = None if kind is not None else jnp.broadcast_to(scene.kind[a:b, None], dl[0].shape)
        ts.append(intersect_components(kind, sz, ol, dl, kind_array=ka))
    t_all = jnp.concatenate(ts, axis=0) if len(ts) > 1 else ts[0]  # (g, n)
    row = jnp.argmin(t_all, axis=0)
    t = jnp.min(t_all, axis=0)
    hit = jnp.isfinite(t)
    t0 = jnp.where(hit, t, 0)
    d_row = jnp.take_along_axis(d_loc, row[None, None, :], axis=1)[:, 0].T  # (n, 3)
    p_loc = o_loc[row] + t0[:, None] * d_row
    n_loc = surface_normal(scene.kind[row], scene.size[row], p_loc)
    normal = jnp.einsum("nij,nj->ni", scene.R[row], n_loc)
    geom = jnp.where(hit, scene.geom_index[row], -1)
    patch = jnp.where(hit, _garment.patch_at(garment, geom, p_loc), 0)
    point = origin[None, :] + t0[:, None] * d
    return geom, patch, t, jnp.where(hit[:, None], normal, 0), point


def _chunked(fn, x: Array, chunk: int):
    """``fn`` over the leading axis of ``x`` in chunks of ``chunk`` rows (``lax.map``); the
    last chunk is padded by repeating the last row and the padding dropped."""
    n = x.shape[0]
    if n <= chunk:
        return fn(x)
    n_chunks = -(-n // chunk)
    pad = n_chunks * chunk - n
    xp = jnp.concatenate([x, jnp.broadcast_to(x[-1:], (pad,) + x.shape[1:])]) if pad else x
    out = jax.lax.map(fn, xp.reshape((n_chunks, chunk) + x.shape[1:]))
    return jax.tree.map(lambda a: a.reshape((n_chunks * chunk,) + a.shape[2:])[:n], out)


def cast_rays(
    scene: Scene,
    garment: Garment,
    origin: Float[Array, " 3"],
    dirs: Float[Array, "n 3"],
    depth_axis: Float[Array, " 3"] | None = None,
    chunk: int = RAY_CHUNK,
) -> Hits:
    """Cast rays ``origin + t dirs`` (unit dirs, world) into a posed scene.

    ``depth_axis`` is the camera's optical axis in the world (row 2 of R) so that
    ``depth = t (d . z_cam)`` is the camera-frame z; without it ``depth = t``."""

    def one(d):
        return _cast_chunk(scene, garment, origin, d)

    geom, patch, t, normal, point = _chunked(one, dirs, chunk)
    depth = t if depth_axis is None else t * (dirs @ depth_axis)
    return Hits(
        geom=geom,
        patch=patch,
        colour=_garment.colour_of(garment, patch),
        t=t,
        depth=depth,
        normal=normal,
        point=point,
        background=geom < 0,
    )
