"""Ray / primitive intersection in a geom's own frame (the maths of the ray caster).

Every primitive of the ``Geometry`` contract is centred at its geom frame's origin:

* ``SPHERE``    size ``(r, 0, 0)``
* ``CAPSULE``   size ``(r, h, 0)``: the segment ``z in [-h, h]`` swept by a ball of radius r
* ``CYLINDER``  size ``(r, h, 0)``: ``x^2 + y^2 <= r^2, |z| <= h`` (flat caps)
* ``BOX``       size ``(h_x, h_y, h_z)``: half-extents
* ``ELLIPSOID`` size ``(a, b, c)``: radii

A ray is ``p(t) = o + t d`` with ``d`` a unit vector (a rigid change of frame keeps it unit, so
the hit distance ``t`` is the same in the world and in the geom frame). Each function returns
the distance of the *entry* point ``t >= 0`` (``+inf`` on a miss, and for rays that start inside
the primitive); :func:`surface_normal` gives the outward unit normal at a surface point from
the point alone, so the caster only computes normals for the winning geom of each ray. All
functions are branch-free (``jnp.where``), broadcast over leading axes and follow the input
dtype.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ..body.geometry import BOX, CAPSULE, CYLINDER, ELLIPSOID, KIND_NAMES, SPHERE


def _eps(x: Array) -> Array:
    """A small positive number for guarding divisions, per dtype (sqrt of the smallest normal)."""
    return jnp.asarray(jnp.sqrt(jnp.finfo(x.dtype).tiny), x.dtype)


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _near_root(a: Array, b: Array, c: Array) -> tuple[Array, Array]:
    """Roots of ``a t^2 + 2 b t + c = 0`` (``a > 0``): ``(t_near, t_far)``, ``nan``-free.

    Where there is no real root (or ``a ~ 0``) both are ``+inf``.
    """
    disc = b * b - a * c
    ok = (disc >= 0) & (a > _eps(a))
    sq = jnp.sqrt(jnp.where(ok, disc, 0))
    a_safe = jnp.where(ok, a, 1)
    inf = jnp.asarray(jnp.inf, a.dtype)
    t0 = jnp.where(ok, (-b - sq) / a_safe, inf)
    t1 = jnp.where(ok, (-b + sq) / a_safe, inf)
    return t0, t1


def _entry(t: Array) -> Array:
    """Keep entry distances in front of the origin; ``+inf`` otherwise."""
    return jnp.where(t >= 0, t, jnp.asarray(jnp.inf, t.dtype))


def _unit(v: Array) -> Array:
    n = jnp.sqrt(_dot(v, v))[..., None]
    return v / jnp.where(n > 0, n, 1)


def intersect_ellipsoid(
    radii: Float[Array, "*b 3"], o: Float[Array, "*b 3"], d: Float[Array, "*b 3"]
) -> Float[Array, "*b"]:
    """Entry distance into the ellipsoid ``sum_i (p_i / r_i)^2 <= 1`` (a sphere when the radii
    are equal): in the scaled space ``p' = p / r`` it is the unit sphere, and t is unchanged."""
    os_, ds = o / radii, d / radii
    t, _ = _near_root(_dot(ds, ds), _dot(os_, ds), _dot(os_, os_) - 1)
    return _entry(t)


def _radial_quadratic(r: Array, o: Array, d: Array) -> tuple[Array, Array, Array]:
    """Coefficients of ``|(o + t d)_xy|^2 = r^2`` as ``a t^2 + 2 b t + c = 0``."""
    a = d[..., 0] * d[..., 0] + d[..., 1] * d[..., 1]
    b = o[..., 0] * d[..., 0] + o[..., 1] * d[..., 1]
    c = o[..., 0] * o[..., 0] + o[..., 1] * o[..., 1] - r * r
    return a, b, c


def intersect_capsule(
    radius: Float[Array, "*b"],
    half_length: Float[Array, "*b"],
    o: Float[Array, "*b 3"],
    d: Float[Array, "*b 3"],
) -> Float[Array, "*b"]:
    """Entry into a capsule along z: the union of the two end balls (centres ``(0, 0, +-h)``)
    and the side of the cylinder between them. For a union of convex sets the entry is the
    minimum of the entries, so ``t = min(t_ball(-h), t_ball(+h), t_side)``, the side hit kept
    only where ``|z| <= h`` (an entry through the flat end of the inner cylinder lies inside a
    ball, whose own entry is earlier)."""
    r2 = radius * radius
    dd = _dot(d, d)
    od_xy = o[..., 0] * d[..., 0] + o[..., 1] * d[..., 1]
    oo_xy = o[..., 0] * o[..., 0] + o[..., 1] * o[..., 1]
    t = jnp.asarray(jnp.inf, o.dtype)
    for sign in (-1, 1):
        oz = o[..., 2] - sign * half_length
        t_b, _ = _near_root(dd, od_xy + oz * d[..., 2], oo_xy + oz * oz - r2)
        t = jnp.minimum(t, _entry(t_b))
    a, b, c = _radial_quadratic(radius, o, d)
    t_s, _ = _near_root(a, b, c)
    z = o[..., 2] + jnp.where(jnp.isfinite(t_s), t_s, 0) * d[..., 2]
    t_s = jnp.where(jnp.abs(z) <= half_length, _entry(t_s), jnp.inf)
    return jnp.minimum(t, t_s)


def _slab(o: Array, d: Array, half: Array) -> tuple[Array, Array]:
    """Interval of t where ``|o + t d| <= half`` (one axis); ``d ~ 0`` handled by a tiny
    stand-in divisor, which yields ``(-huge, +huge)`` inside the slab and an empty or
    out-of-range interval outside."""
    eps = _eps(d)
    d_safe = jnp.where(jnp.abs(d) < eps, eps, d)
    t1 = (-half - o) / d_safe
    t2 = (half - o) / d_safe
    return jnp.minimum(t1, t2), jnp.maximum(t1, t2)


def intersect_cylinder(
    radius: Float[Array, "*b"],
    half_length: Float[Array, "*b"],
    o: Float[Array, "*b 3"],
    d: Float[Array, "*b 3"],
) -> Float[Array, "*b"]:
    """Entry into the solid cylinder ``x^2 + y^2 <= r^2, |z| <= h``: the intersection of the
    radial interval (infinite cylinder; all t or none for rays parallel to z) and the z slab."""
    inf = jnp.asarray(jnp.inf, o.dtype)
    a, b, c = _radial_quadratic(radius, o, d)
    tr0, tr1 = _near_root(a, b, c)
    parallel = a <= _eps(a)
    hit_r = jnp.isfinite(tr0)
    lo_r = jnp.where(parallel, jnp.where(c <= 0, -inf, inf), tr0)
    hi_r = jnp.where(parallel, jnp.where(c <= 0, inf, -inf), jnp.where(hit_r, tr1, -inf))
    lo_z, hi_z = _slab(o[..., 2], d[..., 2], half_length)
    t_in = jnp.maximum(lo_r, lo_z)
    t_out = jnp.minimum(hi_r, hi_z)
    return jnp.where((t_in <= t_out) & (t_in >= 0), t_in, inf)


def intersect_box(
    half: Float[Array, "*b 3"], o: Float[Array, "*b 3"], d: Float[Array, "*b 3"]
) -> Float[Array, "*b"]:
    """Entry into the box ``|p_i| <= h_i`` by the slab method: ``max_i lo_i <= min_i hi_i``."""
    lo, hi = _slab(o, d, half)
    t_in = jnp.max(lo, axis=-1)
    t_out = jnp.min(hi, axis=-1)
    return jnp.where((t_in <= t_out) & (t_in >= 0), t_in, jnp.asarray(jnp.inf, o.dtype))


def _sphere_radii(size: Array) -> Array:
    r = size[..., 0]
    return jnp.stack([r, r, r], axis=-1)


def intersect_kind(
    kind: int | None,
    size: Float[Array, "*b 3"],
    o: Float[Array, "*b 3"],
    d: Float[Array, "*b 3"],
    kind_array: Int[Array, "*b"] | None = None,
) -> Float[Array, "*b"]:
    """Entry distance for primitives of one static ``kind`` (a Python int: the fast path), or,
    with ``kind=None``, for a traced per-geom ``kind_array``: every primitive is evaluated and
    the right one selected (sphere and ellipsoid share one test). ``size``, ``o``, ``d`` must
    have the same shape (broadcast them first)."""
    r, h = size[..., 0], size[..., 1]
    if kind is not None:
        if kind == SPHERE:
            return intersect_ellipsoid(_sphere_radii(size), o, d)
        if kind == ELLIPSOID:
            return intersect_ellipsoid(size, o, d)
        if kind == CAPSULE:
            return intersect_capsule(r, h, o, d)
        if kind == CYLINDER:
            return intersect_cylinder(r, h, o, d)
        if kind == BOX:
            return intersect_box(size, o, d)
        raise ValueError(f"geometry kind must be one of 0..4 {KIND_NAMES}, got {kind}")
    if kind_array is None:
        raise ValueError("intersect_kind: pass a static kind or a kind_array")
    radii = jnp.where((kind_array == SPHERE)[..., None], _sphere_radii(size), size)
    t_e = intersect_ellipsoid(radii, o, d)
    t_c = intersect_capsule(r, h, o, d)
    t_y = intersect_cylinder(r, h, o, d)
    t_b = intersect_box(size, o, d)
    return jnp.where(
        kind_array == CAPSULE,
        t_c,
        jnp.where(kind_array == CYLINDER, t_y, jnp.where(kind_array == BOX, t_b, t_e)),
    )


def surface_normal(
    kind: Int[Array, "*b"], size: Float[Array, "*b 3"], p: Float[Array, "*b 3"]
) -> Float[Array, "*b 3"]:
    """Outward unit normal, in the geom frame, at a point ``p`` on the primitive's surface.

    Sphere/ellipsoid: ``p / r^2``; capsule: ``p - (0, 0, clip(p_z, -h, h))``; cylinder: the cap
    normal ``(0, 0, sign p_z)`` where ``|p_z| / h >= |p_xy| / r`` else ``(p_x, p_y, 0)``; box:
    ``sign(p_i) e_i`` on the axis with the largest ``|p_i| / h_i``. On edges (box, cylinder rim)
    one adjacent face is picked."""
    eps = _eps(p)
    r, h = size[..., 0], size[..., 1]
    zero = jnp.zeros_like(r)
    radii = jnp.where((kind == SPHERE)[..., None], _sphere_radii(size), size)
    n_ell = p / (radii * radii)
    n_cap = p - jnp.stack([zero, zero, jnp.clip(p[..., 2], -h, h)], axis=-1)
    rho = jnp.sqrt(p[..., 0] ** 2 + p[..., 1] ** 2)
    on_cap = jnp.abs(p[..., 2]) * r >= rho * h
    n_cyl = jnp.where(
        on_cap[..., None],
        jnp.stack([zero, zero, jnp.sign(p[..., 2])], axis=-1),
        jnp.stack([p[..., 0], p[..., 1], zero], axis=-1),
    )
    box_axis = jnp.argmax(jnp.abs(p) / jnp.maximum(size, eps), axis=-1)
    n_box = jnp.sign(p) * jax.nn.one_hot(box_axis, 3, dtype=p.dtype)
    n = jnp.where(
        (kind == CAPSULE)[..., None],
        n_cap,
        jnp.where(
            (kind == CYLINDER)[..., None], n_cyl, jnp.where((kind == BOX)[..., None], n_box, n_ell)
        ),
    )
    return _unit(n)
