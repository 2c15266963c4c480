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


Vec = tuple[Array, Array, Array]  # (x, y, z) components, each of the same shape


def _xyz(v: Array) -> Vec:
    return v[..., 0], v[..., 1], v[..., 2]


def _dot(a: Array, b: Array) -> Array:
    return jnp.sum(a * b, axis=-1)


def _vdot(a: Vec, b: Vec) -> Array:
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


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


# The tests below take the ray's and the size's components as separate arrays (``Vec``): the
# ray caster evaluates them on (geoms, rays) planes, where XLA's CPU back-end vectorises along
# the rays; with a trailing axis of 3 every product and sum strides over it, and the cast of a
# 128x128 crop took twice as long (docs/results/realtime_profile.md).


def _ellipsoid(radii: Vec, o: Vec, d: Vec) -> Array:
    os_ = tuple(oi / ri for oi, ri in zip(o, radii, strict=True))
    ds = tuple(di / ri for di, ri in zip(d, radii, strict=True))
    t, _ = _near_root(_vdot(ds, ds), _vdot(os_, ds), _vdot(os_, os_) - 1)
    return _entry(t)


def _radial_quadratic(r: Array, o: Vec, d: Vec) -> tuple[Array, Array, Array]:
    """Coefficients of ``|(o + t d)_xy|^2 = r^2`` as ``a t^2 + 2 b t + c = 0``."""
    a = d[0] * d[0] + d[1] * d[1]
    b = o[0] * d[0] + o[1] * d[1]
    c = o[0] * o[0] + o[1] * o[1] - r * r
    return a, b, c


def _capsule(radius: Array, half_length: Array, o: Vec, d: Vec) -> Array:
    r2 = radius * radius
    dd = _vdot(d, d)
    od_xy = o[0] * d[0] + o[1] * d[1]
    oo_xy = o[0] * o[0] + o[1] * o[1]
    t = jnp.asarray(jnp.inf, o[0].dtype)
    for sign in (-1, 1):
        oz = o[2] - sign * half_length
        t_b, _ = _near_root(dd, od_xy + oz * d[2], oo_xy + oz * oz - r2)
        t = jnp.minimum(t, _entry(t_b))
    t_s, _ = _near_root(*_radial_quadratic(radius, o, d))
    z = o[2] + jnp.where(jnp.isfinite(t_s), t_s, 0) * d[2]
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


def _cylinder(radius: Array, half_length: Array, o: Vec, d: Vec) -> Array:
    inf = jnp.asarray(jnp.inf, o[0].dtype)
    a, b, c = _radial_quadratic(radius, o, d)
    tr0, tr1 = _near_root(a, b, c)
    parallel = a <= _eps(a)
    hit_r = jnp.isfinite(tr0)
    lo_r = jnp.where(parallel, jnp.where(c <= 0, -inf, inf), tr0)
    hi_r = jnp.where(parallel, jnp.where(c <= 0, inf, -inf), jnp.where(hit_r, tr1, -inf))
    lo_z, hi_z = _slab(o[2], d[2], half_length)
    t_in = jnp.maximum(lo_r, lo_z)
    t_out = jnp.minimum(hi_r, hi_z)
    return jnp.where((t_in <= t_out) & (t_in >= 0), t_in, inf)


def _box(half: Vec, o: Vec, d: Vec) -> Array:
    (lx, hx), (ly, hy), (lz, hz) = (_slab(o[k], d[k], half[k]) for k in range(3))
    t_in = jnp.maximum(jnp.maximum(lx, ly), lz)
    t_out = jnp.minimum(jnp.minimum(hx, hy), hz)
    return jnp.where((t_in <= t_out) & (t_in >= 0), t_in, jnp.asarray(jnp.inf, o[0].dtype))


def intersect_ellipsoid(
    radii: Float[Array, "*b 3"], o: Float[Array, "*b 3"], d: Float[Array, "*b 3"]
) -> Float[Array, "*b"]:
    """Entry distance into the ellipsoid ``sum_i (p_i / r_i)^2 <= 1`` (a sphere when the radii
    are equal): in the scaled space ``p' = p / r`` it is the unit sphere, and t is unchanged."""
    return _ellipsoid(_xyz(radii), _xyz(o), _xyz(d))


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
    return _capsule(radius, half_length, _xyz(o), _xyz(d))


def intersect_cylinder(
    radius: Float[Array, "*b"],
    half_length: Float[Array, "*b"],
    o: Float[Array, "*b 3"],
    d: Float[Array, "*b 3"],
) -> Float[Array, "*b"]:
    """Entry into the solid cylinder ``x^2 + y^2 <= r^2, |z| <= h``: the intersection of the
    radial interval (infinite cylinder; all t or none for rays parallel to z) and the z slab."""
    return _cylinder(radius, half_length, _xyz(o), _xyz(d))


def intersect_box(
    half: Float[Array, "*b 3"], o: Float[Array, "*b 3"], d: Float[Array, "*b 3"]
) -> Float[Array, "*b"]:
    """Entry into the box ``|p_i| <= h_i`` by the slab method: ``max_i lo_i <= min_i hi_i``."""
    return _box(_xyz(half), _xyz(o), _xyz(d))


def _sphere_radii(size: Array) -> Array:
    r = size[..., 0]
    return jnp.stack([r, r, r], axis=-1)


def intersect_components(
    kind: int | None, size: Vec, o: Vec, d: Vec, kind_array: Array | None = None
) -> Array:
    """:func:`intersect_kind` on components: ``size``, ``o``, ``d`` are ``(x, y, z)`` tuples of
    arrays of one shape (``size`` components may broadcast), the form the ray caster uses."""
    r, h = size[0], size[1]
    if kind is not None:
        if kind == SPHERE:
            return _ellipsoid((r, r, r), o, d)
        if kind == ELLIPSOID:
            return _ellipsoid(size, o, d)
        if kind == CAPSULE:
            return _capsule(r, h, o, d)
        if kind == CYLINDER:
            return _cylinder(r, h, o, d)
        if kind == BOX:
            return _box(size, o, d)
        raise ValueError(f"geometry kind must be one of 0..4 {KIND_NAMES}, got {kind}")
    if kind_array is None:
        raise ValueError("intersect_kind: pass a static kind or a kind_array")
    sphere = kind_array == SPHERE
    radii = tuple(jnp.where(sphere, r, s) for s in size)
    t_e = _ellipsoid(radii, o, d)
    t_c = _capsule(r, h, o, d)
    t_y = _cylinder(r, h, o, d)
    t_b = _box(size, o, d)
    return jnp.where(
        kind_array == CAPSULE,
        t_c,
        jnp.where(kind_array == CYLINDER, t_y, jnp.where(kind_array == BOX, t_b, t_e)),
    )


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
    return intersect_components(kind, _xyz(size), _xyz(o), _xyz(d), kind_array)


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
