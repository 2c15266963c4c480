"""Limb contours of the stereo particle filter (Azad et al. 2007, §II-A, §III-B): the limb
model of a body and its projection into a camera as silhouette lines and regions.

**Limb contour model.** A limb is a cylinder of radius r (m) around the segment A B fixed in
one link of the body (the capsules / cylinders of :class:`jaxmocap.body.Geometry`; the torso
is one cylinder of elliptic cross-section fitted to the body's torso geoms; the limbs come from
the body's roles and geometry, :func:`limb_model`). In a camera
with focal length f its projected contour is the two silhouette lines

    a +- n r_a  ->  b +- n r_b,      r_a = f r / z_a,   r_b = f r / z_b,

with a, b the projected axis end points (pixels), z their depths (m) and n the unit normal of
the projected axis b - a. Each line is sampled at ``M`` points ``t_m = (m + 1/2) / M``, and the
edge map g (Azad §IV: blurred gradient of the foreground, remapped to [0, 1],
:func:`jaxmocap.segment.edge_map`) is read by bilinear interpolation (0 outside the image).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from jaxmocap.body import CAPSULE, CYLINDER, BodyModel, require_roles
from jaxmocap.body.roles import (
    CONTOUR_LIMBS,
    geom_pose_in,
    geom_support,
    limb_axis,
    owner_link,
    rest_transforms,
)
from jaxmocap.camera import Camera
from jaxmocap.errors import InputError

POINTS_PER_LINE = 12  # M samples per contour line (5 limbs x 2 lines x 12 = 120 per camera)
REGION_ACROSS = 3  # region-cue samples across a limb (x POINTS_PER_LINE along it)


class LimbModel(eqx.Module):
    """Cylinders of the contour model: axis end points ``p0``, ``p1`` (m) in the frame of link
    ``link``, radius ``radius`` (m). ``link`` is static (the FK is unrolled over it).

    A limb may have an elliptic cross-section (the torso): half-width ``radius`` along the
    link-frame unit axis ``side`` and ``depth`` along ``front = axis x side``; a round limb has
    ``depth == radius`` (then ``side`` is any unit vector normal to the axis). See
    :func:`silhouette_radius`.
    """

    p0: Float[Array, "n_limbs 3"]
    p1: Float[Array, "n_limbs 3"]
    radius: Float[Array, " n_limbs"]
    depth: Float[Array, " n_limbs"]
    side: Float[Array, "n_limbs 3"]
    link: tuple[int, ...] = eqx.field(static=True)
    names: tuple[str, ...] = eqx.field(static=True)

    @property
    def n_limbs(self) -> int:
        return len(self.link)


def limb_model(
    model: BodyModel, limbs: Sequence[str | tuple[str, ...]] | None = None
) -> LimbModel:
    """Contour model from the body geometry.

    ``limbs=None``: the body's roles -- the four arm segments (:data:`CONTOUR_LIMBS`, the geoms
    of each role link, along its bone: joint centre to the next role link's joint centre) and
    the torso (the role's torso geoms, along the chest's bone up to the neck), named by role.
    An explicit entry is a geom name or a tuple of geom names of one link (named by the geoms).

    Fit of one limb to its geoms (:func:`fit_limb`): a single capsule or cylinder along the bone
    is itself (axis +- its half length, round, radius r). Several geoms (a stacked torso) give
    the segment between the lowest and the highest geom centre along the bone, with an elliptic
    cross-section whose half-widths are the mean of the geoms' half-extents along the body's
    left-right axis (``radius``, the silhouette half-width seen from the front) and across it
    (``depth``). Any other single geom (box, ellipsoid, sphere, a capsule across the bone)
    gives its centre +- its half-extent along the bone, with its half-extents across the bone
    as ``radius`` / ``depth``. Half-extents are the solids' exact support functions.
    """
    geo = model.geometry
    glink = np.asarray(geo.link)
    if limbs is None:
        roles = require_roles(model, "limb_model")
        entries = [(role, roles.limb(role), limb_axis(model, role)) for role in
                   CONTOUR_LIMBS + ("torso",)]
    else:
        entries = [((e, (e,)) if isinstance(e, str) else ("+".join(e), tuple(e))) + (None,)
                   for e in limbs]

    p0, p1, rad, dep, side, link, names = [], [], [], [], [], [], []
    rest = rest_transforms(model.chain)
    for name, geoms, axis in entries:
        unknown = [g for g in geoms if g not in geo.names]
        if unknown or not geoms:
            where = (f"{model.roles.source}: limb_geoms[{name!r}]" if limbs is None
                     else f"limb_model: limb {name!r}")
            raise InputError(
                f"{where}: " + (f"unknown geoms {unknown}" if unknown else "no geoms (the "
                f"{name} link carries none that are not skin)") + "; name the limb's geoms "
                f"in the roles file's 'limb_geoms' (the model's geoms: {geo.names})"
            )
        idx = [geo.names.index(g) for g in geoms]
        # geoms on fixed child links belong to the link they hang from
        own = {int(glink[g]) for g in idx}
        anchor = (model.chain.link_names.index(roles.link("chest" if name == "torso" else name))
                  if limbs is None else min(own))
        if any(owner_link(model.chain, li, {anchor}) is None for li in own):
            raise InputError(
                f"limb_model: limb {name!r}: geoms {geoms} lie on several links "
                f"{[model.chain.link_names[li] for li in sorted(own)]} that no fixed joints "
                "join" + (f" (roles from {model.roles.source}, field 'limb_geoms')"
                          if limbs is None else ""))
        poses = np.stack([geom_pose_in(model.chain, geo, g, anchor, rest) for g in idx])
        a, b, r, d, sd = fit_limb(model, idx, axis, poses)
        p0.append(a)
        p1.append(b)
        rad.append(r)
        dep.append(d)
        side.append(sd)
        link.append(anchor)
        names.append(name)
    return LimbModel(
        p0=jnp.asarray(np.array(p0)),
        p1=jnp.asarray(np.array(p1)),
        radius=jnp.asarray(np.array(rad)),
        depth=jnp.asarray(np.array(dep)),
        side=jnp.asarray(np.array(side)),
        link=tuple(link),
        names=tuple(names),
    )


def fit_limb(model: BodyModel, geoms: Sequence[int], axis: np.ndarray | None,
             poses: np.ndarray | None = None
             ) -> tuple[np.ndarray, np.ndarray, float, float, np.ndarray]:
    """(p0, p1, radius, depth, side) of the contour cylinder of ``geoms`` (one link) along
    the unit link-frame ``axis`` (None: a capsule/cylinder's own axis, else the direction of
    the largest extent); see :func:`limb_model`. ``poses``: the geoms' poses in the one link's
    frame (default: their own ``geometry.pose``)."""
    geo = model.geometry
    pose = np.asarray(geo.pose, np.float64).copy()
    if poses is not None:
        pose[np.asarray(geoms)] = poses
    size = np.asarray(geo.size, np.float64)
    kind = np.asarray(geo.kind)
    g0 = geoms[0]
    rot0, c0 = pose[g0, :3, :3], pose[g0, :3, 3]
    if axis is None and len(geoms) == 1:
        if kind[g0] in (CAPSULE, CYLINDER):
            axis = rot0[:, 2]
        else:
            ext = [geom_support(int(kind[g0]), size[g0], rot0, rot0[:, k]) for k in range(3)]
            axis = rot0[:, int(np.argmax(ext))]
    elif axis is None:
        axis = pose[geoms[-1], :3, 3] - c0
        axis = axis / np.linalg.norm(axis)
    axis = np.asarray(axis, np.float64)
    if len(geoms) == 1 and kind[g0] in (CAPSULE, CYLINDER) and abs(rot0[:, 2] @ axis) > 0.9:
        r, h = size[g0, 0], size[g0, 1]
        return (rot0 @ [0, 0, -h] + c0, rot0 @ [0, 0, h] + c0, float(r), float(r),
                rot0 @ [1.0, 0.0, 0.0])
    if len(geoms) > 1:
        t = [pose[g, :3, 3] @ axis for g in geoms]
        a, b = pose[geoms[int(np.argmin(t))], :3, 3], pose[geoms[int(np.argmax(t))], :3, 3]
        line = b - a
        line = line / np.linalg.norm(line)
    else:
        ext = geom_support(int(kind[g0]), size[g0], rot0, axis)
        a, b, line = c0 - ext * axis, c0 + ext * axis, axis
    sd = np.array([0.0, 1.0, 0.0]) - line * line[1]  # the body's left-right axis, normal to it
    if np.linalg.norm(sd) < 0.3:  # a limb along y (arms out): use the body's x instead
        sd = np.array([1.0, 0.0, 0.0]) - line * line[0]
    sd = sd / np.linalg.norm(sd)
    front = np.cross(line, sd)
    r = np.mean([geom_support(int(kind[g]), size[g], pose[g, :3, :3], sd) for g in geoms])
    d = np.mean([geom_support(int(kind[g]), size[g], pose[g, :3, :3], front) for g in geoms])
    return a, b, float(r), float(d), sd


def limb_endpoints(
    limbs: LimbModel, transforms: Float[Array, "n_links 4 4"]
) -> tuple[Float[Array, "n_limbs 3"], Float[Array, "n_limbs 3"]]:
    """World end points A, B (m) of every limb axis, given the links' transforms from ``fk``."""
    t = transforms[np.asarray(limbs.link)]
    rot, trans = t[:, :3, :3], t[:, :3, 3]
    dt = transforms.dtype
    return _matvec(rot, limbs.p0.astype(dt)) + trans, _matvec(rot, limbs.p1.astype(dt)) + trans


def _dot(a: Float[Array, "... k"], b: Float[Array, "... k"]) -> Float[Array, " ..."]:
    """sum(a * b, -1) over a short last axis as a chain of adds (see :func:`_matvec`)."""
    out = a[..., 0] * b[..., 0]
    for i in range(1, a.shape[-1]):
        out = out + a[..., i] * b[..., i]
    return out


def _matvec(m: Float[Array, "... 3 3"], v: Float[Array, "... 3"]) -> Float[Array, "... 3"]:
    """m @ v for stacks of 3x3 matrices and 3-vectors as three broadcast multiply-adds. The
    likelihood applies such small products to 1000 particles x limbs x cameras; as batched
    dots XLA hands them to a library call each (~0.2 ms apiece in the filter step's profile,
    ``docs/results/realtime_profile.md``), as multiply-adds they fuse."""
    m = m.reshape((1,) * (v.ndim + 1 - m.ndim) + m.shape)  # explicit rank (no promotion)
    return m[..., 0] * v[..., 0:1] + m[..., 1] * v[..., 1:2] + m[..., 2] * v[..., 2:3]


def _camera_frame(cam: Camera, x: Float[Array, "*n 3"]) -> Float[Array, "*n 3"]:
    """:func:`jaxmocap.camera.to_camera` (R x + t) written with :func:`_matvec`. Kept local:
    changing ``to_camera`` itself would change the colour-shirt tracker's rounding too, which
    would then need its own held-out accuracy run."""
    rot = cam.R.astype(x.dtype)
    return _matvec(rot, x) + cam.t.astype(x.dtype).reshape((1,) * (x.ndim - 1) + (3,))


def silhouette_radius(
    cam: Camera,
    limbs: LimbModel,
    transforms: Float[Array, "n_links 4 4"],
    a: Float[Array, "n_limbs 3"],
    b: Float[Array, "n_limbs 3"],
) -> Float[Array, " n_limbs"]:
    """Half-width (m) of every limb's silhouette seen from ``cam``.

    For an elliptic cross-section with half-widths r (along ``side``) and d (along ``front``),
    the silhouette lies at +- h along u, the unit vector normal to both the limb axis and the
    viewing ray to the limb's midpoint, with the support function

        h = sqrt((r u . side)^2 + (d u . front)^2)      (m; h = r for a round limb).

    Computed in the camera frame (the ray is the midpoint's camera coordinates).
    """
    return _silhouette_radius(cam, limbs, transforms, _camera_frame(cam, a), _camera_frame(cam, b))


def _silhouette_radius(cam, limbs, transforms, xa, xb):
    """:func:`silhouette_radius` from the end points' camera coordinates xa, xb."""
    dt = xa.dtype
    rot = transforms[np.asarray(limbs.link)][:, :3, :3]
    side = _matvec(cam.R.astype(dt), _matvec(rot, limbs.side.astype(dt)))
    axis = _unit(xb - xa)
    front = jnp.cross(axis, side)
    ray = 0.5 * (xa + xb)  # the midpoint's camera coordinates (the map is affine)
    u = _unit(jnp.cross(axis, ray))
    r, d = limbs.radius.astype(dt), limbs.depth.astype(dt)
    us, uf = _dot(u, side), _dot(u, front)
    h = jnp.sqrt(jnp.square(r * us) + jnp.square(d * uf))
    return jnp.where(d == r, r, h)  # round: exactly r (also when the axis points at the camera)


def _unit(v: Array) -> Array:
    n2 = _dot(v, v)[..., None]
    ok = n2 > jnp.finfo(v.dtype).tiny
    return jnp.where(ok, v / jnp.sqrt(jnp.where(ok, n2, 1.0)), jnp.zeros_like(v))


def project_limbs(
    cam: Camera,
    a: Float[Array, "n_limbs 3"],
    b: Float[Array, "n_limbs 3"],
    radius: Float[Array, " n_limbs"],
) -> tuple[Float[Array, "n_limbs 2 2"], Float[Array, "n_limbs 2 2"]]:
    """The two projected silhouette lines of every limb in ``cam`` (pixels).

    Returns ``(starts, ends)``, each (n_limbs, 2 lines, 2): line k runs from
    ``a + s_k n r_a`` to ``b + s_k n r_b`` with s = (+1, -1). A pinhole projection (lens
    distortion is left out: over a limb's width it is a sub-pixel effect); radii in pixels
    use the mean focal length and each end point's depth.
    """
    return _project_limbs(cam, _camera_frame(cam, a), _camera_frame(cam, b), radius)


def _project_limbs(cam, xa, xb, radius):
    """:func:`project_limbs` from the end points' camera coordinates xa, xb."""
    dt = xa.dtype
    K = cam.K.astype(dt)
    za, zb = xa[:, 2], xb[:, 2]
    f = 0.5 * (K[0, 0] + K[1, 1])
    c = K[:2, 2]
    pa = f * xa[:, :2] / za[:, None] + c[None, :]
    pb = f * xb[:, :2] / zb[:, None] + c[None, :]
    d = _unit(pb - pa)
    n = jnp.stack([-d[:, 1], d[:, 0]], axis=-1)
    ra = (f * radius.astype(dt) / za)[:, None, None]
    rb = (f * radius.astype(dt) / zb)[:, None, None]
    s = jnp.asarray([1.0, -1.0], dt)[None, :, None]
    starts = pa[:, None, :] + s * n[:, None, :] * ra
    ends = pb[:, None, :] + s * n[:, None, :] * rb
    return starts, ends


def _line_points(starts: Array, ends: Array, m: int) -> Array:
    t = (jnp.arange(m, dtype=starts.dtype) + 0.5) / m
    t = t.reshape((1,) * (starts.ndim - 1) + (m, 1))
    return starts[..., None, :] * (1 - t) + ends[..., None, :] * t


def edge_samples(
    starts: Float[Array, "*l 2"], ends: Float[Array, "*l 2"], m: int = POINTS_PER_LINE
) -> Float[Array, "*l m 2"]:
    """``m`` points ``(1 - t) start + t end`` at ``t = (k + 1/2) / m`` on every line."""
    return _line_points(starts, ends, m)


def region_samples(
    starts: Float[Array, "n_limbs 2 2"],
    ends: Float[Array, "n_limbs 2 2"],
    m: int = POINTS_PER_LINE,
    across: int = REGION_ACROSS,
) -> Float[Array, "n_limbs q m 2"]:
    """A grid of ``across x m`` points inside each projected limb quadrilateral (the region
    between its two silhouette lines), at fractions ``(j + 1/2) / across`` across."""
    u = (jnp.arange(across, dtype=starts.dtype) + 0.5) / across
    u = u[None, :, None]
    s = starts[:, 0:1, :] * (1 - u) + starts[:, 1:2, :] * u
    e = ends[:, 0:1, :] * (1 - u) + ends[:, 1:2, :] * u
    return _line_points(s, e, m)
