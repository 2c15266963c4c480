"""Likelihood cues of the stereo particle filter (Azad et al. 2007, §II-A, §II-B, §III-B–D).

Every cue is a *log*-likelihood of one configuration (pure JAX; the filter vmaps it over the
particles, :mod:`jaxmocap.pf.filter`); cues are fused by product, i.e. by summing their
log-likelihoods (§II-C), and the two cameras by the same rule ("implicit stereo", §III-C).

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
With M_g = (limbs x 2 lines x M) samples g_m per camera:

* edge cue, SSD form (§II-A):  log p_g  = -1 / (2 sigma_g^2 M_g) sum_m (1 - g_m)^2
* edge cue, SAD form (§III-D): log p_g' = -1 / (2 sigma_g^2) (1 - (1 / M_g) sum_m g_m)
* distance cue (§III-D):       log p_d' = -1 / (2 sigma_d^2) sum_i valid_i |f_i(s) - c_i|^2
  for i = head, left hand, right hand (the triangulated skin blobs of :mod:`jaxmocap.blobs`;
  Azad mark a missing c_i by c_i = 0, we carry an explicit ``valid`` mask instead);
* hand-support cue (ours, not in the paper; ``use_support``): a hand is either seen as a skin
  blob or hidden behind the shirt / another skin region, or outside the image -- it never lies
  on plain background. With S the observation's ``support`` map (skin or shirt, dilated by
  about a hand's radius, :func:`jaxmocap.trackers.stereo_pf.support_map`) read at the
  projected hands h_j (nearest pixel):
  log p_s = -1 / (2 sigma_s^2) sum_cams sum_j inside_j (1 - S(h_j)), over the hands without a
  triangulated point (every hand with ``support_all``). It holds the hidden hand of a turning
  body behind the torso when the blob tracker has no point for it;
* region cue, Eq. (1):         log p_r  = -1 / (2 sigma_r^2 M_r) sum_m (1 - r_m)^2
  with r_m the foreground mask at M_r points spread over the projected limb regions
  (kept for the comparison of §III-B; the final likelihood leaves it out, §III-D).

The fused likelihood of the tracker is :class:`StereoLikelihood` (edge cue in both cameras x
distance cue, optionally x region cue). Constants: the named defaults below (the paper gives no
values; ours are chosen for 320x240 images of a person ~2.3 m from the cameras).
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from jaxmocap.body import CAPSULE, CYLINDER, BodyModel, fk, keypoint_index, require_roles
from jaxmocap.body.roles import (
    CONTOUR_LIMBS,
    geom_pose_in,
    geom_support,
    limb_axis,
    owner_link,
    rest_transforms,
)
from jaxmocap.camera import Camera, project
from jaxmocap.errors import InputError
from jaxmocap.rotations import so3_left_jacobian
from jaxmocap.sampling import sample_bilinear, sample_nearest

__all__ = [
    "DISTANCE_NAMES",
    "EDGE_OUTSIDE",
    "POINTS_PER_LINE",
    "REGION_ACROSS",
    "SIGMA_D",
    "SIGMA_G",
    "SIGMA_R",
    "SIGMA_S",
    "SUPPORT_DILATE_PX",
    "SUPPORT_NAMES",
    "LimbModel",
    "Observation",
    "StereoLikelihood",
    "distance_loglik",
    "distance_points",
    "edge_loglik",
    "edge_samples",
    "limb_endpoints",
    "fit_limb",
    "limb_model",
    "pose_transforms",
    "project_limbs",
    "region_loglik",
    "region_samples",
    "sample_bilinear",
    "sample_nearest",
    "silhouette_radius",
    "support_loglik",
]

# sigma_g: with the SAD form a particle whose contour sees a mean edge value 0.1 lower than
# another's (per camera) is exp(0.1 / (2 * 0.2^2)) = e^1.25 times less likely. Sharper values
# (0.1: e^5) collapsed the N = 1000 set onto a few particles (ESS 2-4) on our 320x240 test
# sequences and tracked worse (7.4 vs 5.8 cm mean joint error, punch clip, first frames).
SIGMA_G = 0.2
# sigma_d (m): the triangulated blob centroid lies within a few cm of the model's hand / head
# point (blob centroid vs. the model's hand centre, 1-2 px stereo disparity noise at 2.3 m);
# 4 cm gives a hand 10 cm off a weight exp(-0.1^2 / (2 * 0.04^2)) = e^-3.1.
SIGMA_D = 0.04
SIGMA_R = 0.1  # region cue, same role as sigma_g
# Hand-support cue (ours): a hand on plain background in one camera costs 1 / (2 sigma_s^2) =
# 2 nats, about a 0.16 lower mean edge value in that camera (sigma_g = 0.2).
SIGMA_S = 0.5
SUPPORT_DILATE_PX = 5  # support map dilation (px): a hand's radius (4 cm at 2.3 m, f ~ 300 px)
SUPPORT_NAMES = ("l_hand", "r_hand")  # the keypoints the support cue reads
# Edge value of a contour sample outside the image (make_params(edge_outside=...); None = Azad:
# zero padding). ~ the mean edge value of a fair fit: a limb that truly leaves the image keeps
# about the score it had inside, a wrong limb gains little by escaping.
EDGE_OUTSIDE = 0.5
POINTS_PER_LINE = 12  # M samples per contour line (5 limbs x 2 lines x 12 = 120 per camera)
REGION_ACROSS = 3  # region-cue samples across a limb (x POINTS_PER_LINE along it)
# the entities of the distance cue, in the order of jaxmocap.blobs.ENTITY_NAMES
DISTANCE_NAMES = ("head", "l_hand", "r_hand")


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


def _inside(uv: Float[Array, "*n 2"], shape: tuple[int, ...]) -> Bool[Array, "*n"]:
    """Whether pixel positions lie inside an image of ``shape`` (h, w) (pixel centres at
    integers, the image spans [-0.5, w - 0.5] x [-0.5, h - 0.5])."""
    h, w = shape[-2:]
    x, y = uv[..., 0], uv[..., 1]
    return (x >= -0.5) & (x <= w - 0.5) & (y >= -0.5) & (y <= h - 0.5)


def edge_loglik(
    g: Float[Array, "*m"], sigma_g: Float[ArrayLike, ""] = SIGMA_G, form: str = "sad"
) -> Float[Array, ""]:
    """log p_g (``form="ssd"``, §II-A) or log p_g' (``form="sad"``, §III-D) of the edge values
    g_m in [0, 1] sampled along one camera's projected contour (all limbs: M_g = g.size)."""
    g = g.reshape(-1)
    s2 = 2 * jnp.square(jnp.asarray(sigma_g, g.dtype))
    if form == "ssd":
        return -jnp.mean(jnp.square(1 - g)) / s2
    if form == "sad":
        return -(1 - jnp.mean(g)) / s2
    raise ValueError(f"edge_loglik: form must be 'sad' or 'ssd', got {form!r}")


def region_loglik(
    r: Float[Array, "*m"], sigma_r: Float[ArrayLike, ""] = SIGMA_R
) -> Float[Array, ""]:
    """log p_r of Eq. (1): r_m the foreground values (0 / 1) at the region samples."""
    r = r.reshape(-1)
    return -jnp.mean(jnp.square(1 - r)) / (2 * jnp.square(jnp.asarray(sigma_r, r.dtype)))


def support_loglik(
    uv: Float[Array, "k 2"],
    support: Float[Array, "h w"],
    sigma_s: Float[ArrayLike, ""] = SIGMA_S,
    weight: Float[Array, " k"] | None = None,
) -> Float[Array, ""]:
    """log p_s of one camera (module docstring): -1 / (2 sigma_s^2) sum_j w_j inside_j
    (1 - S(h_j)) for the projected hands ``uv`` (pixels); a hand outside the image costs
    nothing. ``weight`` w_j (default 1) selects the hands the cue reads."""
    inside = _inside(uv, support.shape)
    s = sample_nearest(support.astype(uv.dtype), uv)
    miss = jnp.where(inside, 1.0 - s, jnp.zeros_like(s))
    if weight is not None:
        miss = miss * weight.astype(miss.dtype)
    return -jnp.sum(miss) / (2 * jnp.square(jnp.asarray(sigma_s, uv.dtype)))


def distance_loglik(
    points: Float[Array, "k 3"],
    targets: Float[Array, "k 3"],
    valid: Bool[Array, " k"],
    sigma_d: Float[ArrayLike, ""] = SIGMA_D,
) -> Float[Array, ""]:
    """log p_d' (§III-D): -1 / (2 sigma_d^2) sum_i d_i, d_i = |f_i(s) - c_i|^2 (m^2) where
    ``valid[i]``, 0 for a missing c_i."""
    diff = points - targets.astype(points.dtype)
    d = _dot(diff, diff)
    d = jnp.where(valid, d, jnp.zeros_like(d))
    return -jnp.sum(d) / (2 * jnp.square(jnp.asarray(sigma_d, points.dtype)))


def distance_points(
    model: BodyModel, transforms: Float[Array, "n_links 4 4"], names: Sequence[str] = DISTANCE_NAMES
) -> Float[Array, "k 3"]:
    """f_i(s): world positions (m) of the named keypoints given the links' transforms."""
    idx = keypoint_index(model, names)
    link = model.keypoint_link[idx]
    off = model.keypoint_offset[idx].astype(transforms.dtype)
    t = transforms[link]
    return _matvec(t[:, :3, :3], off) + t[:, :3, 3]


def pose_transforms(model: BodyModel, q: Float[Array, " n_dof"]) -> Float[Array, "n_links 4 4"]:
    """The links' world transforms (3x3 + t forward kinematics of :mod:`jaxmocap.body`; links
    no cue reads are removed by XLA's dead-code elimination)."""
    return fk(model.chain, q)





def _ancestry(topology) -> np.ndarray:
    """(n_links, n_links) bool: ``[a, b]`` whether link a is link b or one of its ancestors
    (from the chain's static topology table)."""
    n = len(topology)
    anc = np.zeros((n, n), bool)
    for b in range(n):
        a = b
        while a >= 0:
            anc[a, b] = True
            a = topology[a][0]
    return anc


class Observation(eqx.Module):
    """What the likelihood reads of one stereo frame (leading time axis for a sequence).

    ``edges`` g (n_cams, h, w) in [0, 1]; ``points`` c_i (3, 3) m and ``valid`` (3,) of the
    triangulated head, left hand, right hand; ``foreground`` (n_cams, h, w) the foreground
    mask as 0 / 1 floats (read by the region cue only); ``support`` (n_cams, h, w) or None: the
    hand-support map S (0 / 1, skin or shirt dilated; read by the hand-support cue only).
    """

    edges: Float[Array, "*t n_cams h w"]
    points: Float[Array, "*t 3 3"]
    valid: Bool[Array, "*t 3"]
    foreground: Float[Array, "*t n_cams h w"]
    support: Float[Array, "*t n_cams h w"] | None = None


class StereoLikelihood(eqx.Module):
    """The fused likelihood p(z | s) of a configuration s (the filter's DOF subset ``dofs``;
    the other DOFs held at ``default_q``), as a log-likelihood (Azad §III-D):

        log p = sum_cams log p_g'(cam) [+ log p_d'] [+ sum_cams log p_r(cam)]
                [+ sum_cams log p_s(cam)].

    ``edge_form`` "sad" (p_g', the paper's final choice) or "ssd" (p_g); ``use_distance``,
    ``use_edges``, ``use_region``, ``use_support`` switch the cues (static; the support cue
    needs ``Observation.support``; it reads the hands without a triangulated point only, or
    every hand with ``support_all``). sigmas are traced (no recompile).
    ``edge_outside``: the edge value g_m given to a contour sample outside the image (static).
    None (Azad) reads the zero-padded image, i.e. a limb leaving the image looks like a limb on
    plain background and is pulled back in; a constant (e.g. :data:`EDGE_OUTSIDE`) neither
    rewards nor punishes the part of a contour outside the image as much.
    """

    model: BodyModel
    limbs: LimbModel
    cams: Camera  # stacked (n_cams,)
    default_q: Float[Array, " n_dof"]
    sigma_g: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    sigma_d: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    sigma_r: Float[Array, ""] = eqx.field(converter=jnp.asarray)
    dofs: tuple[int, ...] = eqx.field(static=True)
    sigma_s: Float[Array, ""] = eqx.field(converter=jnp.asarray, default=SIGMA_S)
    points_per_line: int = eqx.field(static=True, default=POINTS_PER_LINE)
    edge_form: str = eqx.field(static=True, default="sad")
    use_edges: bool = eqx.field(static=True, default=True)
    use_distance: bool = eqx.field(static=True, default=True)
    use_region: bool = eqx.field(static=True, default=False)
    use_support: bool = eqx.field(static=True, default=False)
    support_all: bool = eqx.field(static=True, default=False)
    edge_outside: float | None = eqx.field(static=True, default=None)
    # hands by nearest assignment (not in the paper): each particle's hands take the two
    # triangulated hands in the pairing of least squared distance, so a blob tracker that
    # swapped the hands' identities (40-47% of the measured hands on two dev sequences of the
    # independent test world) does not pull the arms across the body
    hand_swap: bool = eqx.field(static=True, default=False)

    def _targets(
        self, f: Float[Array, "3 3"], z: Observation
    ) -> tuple[Float[Array, "3 3"], Bool[Array, " 3"]]:
        """The distance cue's targets c_i and their validity for the model points ``f`` (head,
        left hand, right hand): as observed, or with the hands swapped when ``hand_swap`` and
        that pairing is nearer."""
        c, v = z.points.astype(f.dtype), z.valid
        if not self.hand_swap:
            return c, v
        perm = np.array([0, 2, 1])
        cs, vs = c[perm], v[perm]

        def cost(cc, vv):
            diff = f[1:] - cc[1:]
            return jnp.sum(jnp.where(vv[1:], _dot(diff, diff), 0.0))

        swap = cost(cs, vs) < cost(c, v)
        return jnp.where(swap, cs, c), jnp.where(swap, vs, v)

    def __check_init__(self):
        if self.edge_form not in ("sad", "ssd"):
            raise ValueError(f"StereoLikelihood.edge_form: 'sad' or 'ssd', got {self.edge_form!r}")
        if self.default_q.shape != (self.model.n_dof,):
            raise ValueError(
                f"StereoLikelihood.default_q: expected shape ({self.model.n_dof},), "
                f"got {self.default_q.shape}"
            )

    def full_q(self, s: Float[Array, " d"]) -> Float[Array, " n_dof"]:
        return self.default_q.astype(s.dtype).at[np.asarray(self.dofs)].set(s)

    def distance_residual(self, s: Float[Array, " d"], z: Observation) -> Float[Array, " k3"]:
        """The distance cue's residuals valid_i (f_i(s) - c_i), flattened (3 k,) in m (zero
        for a missing c_i): log p_d' = -|r|^2 / (2 sigma_d^2). The residual of the guided
        proposal (:class:`jaxmocap.pf.guided.GuidedProposal`)."""
        f = distance_points(self.model, pose_transforms(self.model, self.full_q(s)))
        c, v = self._targets(f, z)
        r = f - c
        return jnp.where(v[:, None], r, jnp.zeros_like(r)).reshape(-1)

    def distance_linearize(
        self, s: Float[Array, " d"], z: Observation
    ) -> tuple[Float[Array, " k3"], Float[Array, "k3 d"]]:
        """:meth:`distance_residual` and its Jacobian d r / d s (3 k, d) in closed form from
        one forward kinematics (the guided proposal's Gauss-Newton steps): for a point p of a
        link below a revolute joint with world axis a through the joint origin o,
        dp/dtheta = a x (p - o); for the root translation dp/dt = I; for the root rotation
        vector w (world frame, about the root position t), dp/dw = -[p - t]_x J_l(w) with J_l
        the left Jacobian of SO(3). Rows of missing points are zero. Equals
        ``jax.jacfwd(distance_residual)`` (tested) at ~1/15 of its cost."""
        model = self.model
        q = self.full_q(s)
        tr = pose_transforms(model, q)
        f = distance_points(model, tr)
        idx = keypoint_index(model, DISTANCE_NAMES)
        plink = model.keypoint_link[idx]  # traced when the model is a jit argument
        topo = model.chain.topology
        anc = jnp.asarray(_ancestry(topo))
        link_of_dof = {d: i for i, (_, jt, d) in enumerate(topo) if d >= 0}
        axis = model.chain.joint_axis.astype(s.dtype)
        rel_root = f - q[None, :3]
        jl = so3_left_jacobian(q[3:6])
        # column c of -[p - t]_x J_l is J_l[:, c] x (p - t)
        d_rot = jnp.stack([jnp.cross(jl[:, c][None, :], rel_root) for c in range(3)], -1)
        cols = []
        for dof in self.dofs:
            if dof < 3:
                cols.append(jnp.zeros_like(f).at[:, dof].set(1.0))
            elif dof < 6:
                cols.append(d_rot[:, :, dof - 3])
            else:
                link = link_of_dof[dof]
                below = anc[link, plink]
                a = _matvec(tr[link, :3, :3], axis[link])
                col = jnp.cross(a[None, :], f - tr[link, :3, 3][None, :])
                cols.append(jnp.where(below[:, None], col, 0.0))
        jac = jnp.stack(cols, axis=-1)  # (k, 3, d)
        c, v = self._targets(f, z)
        r = f - c
        r = jnp.where(v[:, None], r, jnp.zeros_like(r)).reshape(-1)
        jac = jnp.where(v[:, None, None], jac, jnp.zeros_like(jac))
        return r, jac.reshape(-1, len(self.dofs))

    def __call__(self, s: Float[Array, " d"], z: Observation) -> Float[Array, ""]:
        tr = pose_transforms(self.model, self.full_q(s))
        ll = jnp.zeros((), s.dtype)
        if self.use_edges or self.use_region:
            a, b = limb_endpoints(self.limbs, tr)

            def per_cam(cam, edges, fg):
                xa, xb = _camera_frame(cam, a), _camera_frame(cam, b)
                radius = _silhouette_radius(cam, self.limbs, tr, xa, xb)
                starts, ends = _project_limbs(cam, xa, xb, radius)
                out = jnp.zeros((), s.dtype)
                if self.use_edges:
                    uv = edge_samples(starts, ends, self.points_per_line)
                    g = sample_bilinear(edges.astype(s.dtype), uv)
                    if self.edge_outside is not None:
                        g = jnp.where(
                            _inside(uv, edges.shape), g, jnp.asarray(self.edge_outside, g.dtype)
                        )
                    out = out + edge_loglik(g, self.sigma_g.astype(s.dtype), self.edge_form)
                if self.use_region:
                    r = sample_nearest(
                        fg.astype(s.dtype), region_samples(starts, ends, self.points_per_line)
                    )
                    out = out + region_loglik(r, self.sigma_r.astype(s.dtype))
                return out

            ll = ll + jnp.sum(jax.vmap(per_cam)(self.cams, z.edges, z.foreground))
        if self.use_distance:
            f = distance_points(self.model, tr)
            c, v = self._targets(f, z)
            ll = ll + distance_loglik(f, c, v, self.sigma_d.astype(s.dtype))
        if self.use_support:
            if z.support is None:
                raise ValueError(
                    "StereoLikelihood: use_support needs Observation.support (the hand-support "
                    "map), got None"
                )
            hands = distance_points(self.model, tr, SUPPORT_NAMES)
            uv = jax.vmap(lambda cam: project(cam, hands))(self.cams)
            idx = [DISTANCE_NAMES.index(n) for n in SUPPORT_NAMES]
            weight = jnp.ones(len(idx), s.dtype) if self.support_all else ~z.valid[..., idx]
            ll = ll + jnp.sum(
                jax.vmap(support_loglik, in_axes=(0, 0, None, None))(
                    uv, z.support, self.sigma_s.astype(s.dtype), weight.astype(s.dtype)
                )
            )
        return ll
