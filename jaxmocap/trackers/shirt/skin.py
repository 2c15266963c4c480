"""Head and hands observed as skin in the colour-shirt tracker (issue 38 item 1; not in Wang et
al. 2011, whose patches leave head and hands to the kinematic chain's extrapolation).

The skin of the body is one more colour class beside the shirt's (:class:`SkinTerms`: one
Gaussian, from scribbles on the capture's skin or from the garment's skin albedo mapped through
the colour model, :func:`skin_colour_from_garment`). Every frame each crop is classified against
the shirt's colours plus skin under the camera's current white balance (the adaptive ``W`` of
step 5, :func:`skin_maps`): a pixel is skin where skin is its nearest class within ``T``.

On a frame after a valid one (after a loss the starts are tens of cm off and the windows around
their prediction catch the wrong skin: on the DEV split skin terms on every frame measured 15.6
-> 17.1 cm, only after a valid frame 15.6 -> 14.9; docs/results/shirt_skin.md), in every round
of steps 3-4 the model is rendered at the round's start pose ``q`` (the render the patch terms
use): the rendered skin pixels of head, left hand and right hand (the skin geoms
on each role's link and the links below it: found by ``model.roles``, never by name) give each
part's expected centroid and projected size in every camera. The observed skin pixels near
each prediction (within :data:`WINDOW_RADII` blob radii plus :data:`WINDOW_MARGIN` of the crop
side, each pixel to the nearest predicted part) give the observed centroid. A part's term is
kept in a camera only where it passes three gates (else its weight is 0: the term drops out of
that frame's IK, never a wrong pull):

* *visible*: at least :data:`MIN_RENDERED` rendered skin pixels (a hand behind the torso or out
  of the crop is not predicted);
* *size*: the observed pixel count within :data:`COUNT_RATIO` of the rendered one;
* *agreement between cameras*: where the part is observed in two cameras, the closest distance
  between their rays through the observed centroids may exceed that of the rendered centroids
  by at most :data:`RAY_GAP` metres (the triangulation residual; a blob of the background or
  the other hand in one camera does not meet the other camera's).

The kept terms enter the IK as 2D reprojection terms beside the patch centroids, each
predicted like a patch's by a per-view anchor (the mean 3D point of the part's rendered skin in
its link's frame, :func:`jaxmocap.ik.view_anchors`'s construction), with the covariance
``sigma_px^2 I`` (:data:`SKIN_SIGMA_PX`) and the IK's Cauchy robustness.
"""

from __future__ import annotations

from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxmocap.body import BodyModel, fk
from jaxmocap.body.roles import geom_roles, require_roles
from jaxmocap.camera import pixel_rays, project
from jaxmocap.color import ColorModel, classify
from jaxmocap.color.classify import THRESHOLD, nearest_sq
from jaxmocap.errors import InputError
from jaxmocap.garment import Garment
from jaxmocap.ik import PatchAnchors

SKIN_PARTS = ("head", "l_hand", "r_hand")  # link roles whose skin is observed
# Standard deviation (image px, 640x480) of a kept skin centroid about the rendered one at the
# true pose, measured on the DEV split (shirt_00 and shirt_12, every frame; docs/results/
# shirt_skin.md "sigma"): the observed centroid of a part's skin pixels in its window minus the
# centroid of its render at the ground-truth pose, over the 758 coordinates of the terms that
# passed the gates: RMS 5.5 px, 1.4826 MAD 4.6 px (the patch centroids' Sigma_c: ~2 px).
SKIN_SIGMA_PX = 5.0
MIN_RENDERED = 6  # rendered skin pixels (working crop px) for a part to be predicted in a view
WINDOW_RADII = 2.0  # window radius around the predicted centroid, in radii of the rendered blob
WINDOW_MARGIN = 0.06  # ... plus this share of the crop side (frame-to-frame motion)
COUNT_RATIO = (0.3, 3.0)  # observed / rendered skin pixels of a kept term
RAY_GAP = 0.06  # metres: triangulation residual beyond the rendered centroids' own


class SkinTerms(eqx.Module):
    """What the skin terms need (:func:`make_skin_terms`): the skin ``colour`` (one Gaussian,
    RGB 0..255 under the white balance, like the shirt's :class:`~jaxmocap.color.ColorModel`),
    per geom the observed part it belongs to (``part_geom``: index into :data:`SKIN_PARTS`,
    -1 none), each part's ``link``, the terms' covariance ``cov`` (3, 2, 2) pixels^2 and the
    room's colours that are not skin (``background``: the scene colours less those within
    ``T`` of the skin class, which the room's scribbles take from the uncovered head and
    hands; None: no room colours)."""

    colour: ColorModel
    part_geom: Int[Array, " n_geoms"]
    link: Int[Array, " 3"]
    cov: Float[Array, "3 2 2"]
    background: ColorModel | None = None


def skin_parts(body: BodyModel, garment: Garment) -> tuple[np.ndarray, np.ndarray]:
    """``(part_geom, link)``: per geom the index of the part of :data:`SKIN_PARTS` whose skin
    it is (a skin geom of the garment that belongs to the part's role by
    :func:`jaxmocap.body.roles.geom_roles`: on its role link, a fixed child or a link below it
    that plays no other role, or the part's geom on a link shared with other roles, e.g. a
    head sphere on the torso link; -1 else), and each part's link index. Found by the body's
    roles."""
    roles = require_roles(body, "the skin terms (head and hands observed)")
    by_role = geom_roles(body.chain, body.geometry, dict(roles.links), roles.skin_geoms)
    skin = np.asarray(garment.skin)
    part_geom = np.full(skin.shape[0], -1, np.int32)
    for k, role in enumerate(SKIN_PARTS):
        mine = [g for g in by_role.get(role, []) if skin[g]]
        part_geom[mine] = k
    links = [body.chain.link_index(roles.link(role)) for role in SKIN_PARTS]
    # skin below a moving joint that plays no role (fingers) belongs to the nearest role link
    # above it, when that is a part's link
    parents = np.asarray(body.chain.parents)
    role_links = {body.chain.link_index(li) for li in dict(roles.links).values()}
    owned = {g for gs in by_role.values() for g in gs}
    for g, li in enumerate(np.asarray(body.geometry.link).tolist()):
        if not skin[g] or g in owned:
            continue
        while li >= 0 and li not in role_links:
            li = int(parents[li])
        if li in links:
            part_geom[g] = links.index(li)
    return part_geom, np.asarray(links, np.int32)


def skin_colour_from_garment(color: ColorModel, garment: Garment) -> ColorModel:
    """The skin's Gaussian where no scribbles give it: the garment's skin albedo through the
    affine map from albedo to colour-model mean fitted on the shirt's own colours (least
    squares; their albedos and fitted means), with the shirt colours' mean covariance."""
    alb = np.asarray(garment.colours, np.float64)
    mean = np.asarray(color.mean, np.float64)
    A = np.concatenate([alb, np.ones((alb.shape[0], 1))], 1)
    M, *_ = np.linalg.lstsq(A, mean, rcond=None)
    skin = np.clip(np.append(np.asarray(garment.skin_rgb, np.float64), 1.0) @ M, 0.0, 255.0)
    cov = np.asarray(color.cov, np.float64).mean(0)
    dt = color.mean.dtype
    return ColorModel(jnp.asarray(skin[None], dt), jnp.asarray(cov[None], dt), ("skin",),
                      color.shading)


def make_skin_terms(body: BodyModel, garment: Garment, color: ColorModel,
                    skin_colour: ColorModel | None = None, scene_colors: ColorModel | None = None,
                    gain=None, sigma_px: float = SKIN_SIGMA_PX) -> SkinTerms:
    """:class:`SkinTerms` of a capture: ``skin_colour`` one Gaussian (e.g. fitted on scribbles
    of the capture's skin, :func:`jaxmocap.color.fit_color_model` with one class), default
    :func:`skin_colour_from_garment`; ``scene_colors`` the room's (``gain`` the distance's
    shading range, as the classification's)."""
    part_geom, link = skin_parts(body, garment)
    if skin_colour is None:
        skin_colour = skin_colour_from_garment(color, garment)
    if skin_colour.n_colors != 1:
        raise InputError(f"skin colour: expected one Gaussian, got {skin_colour.n_colors}")
    dt = color.mean.dtype
    cov = jnp.broadcast_to(float(sigma_px) ** 2 * jnp.eye(2, dtype=dt), (3, 2, 2))
    colour = ColorModel(skin_colour.mean.astype(dt), skin_colour.cov.astype(dt), ("skin",),
                        color.shading)
    background = None
    if scene_colors is not None:  # the room's colours that are not the skin's own
        d = nearest_sq(colour, jnp.eye(3, dtype=dt), scene_colors.mean[None].astype(dt), gain)
        keep = np.flatnonzero(np.asarray(d[0]) > THRESHOLD**2)
        if keep.size:
            background = ColorModel(scene_colors.mean[keep], scene_colors.cov[keep],
                                    shading=scene_colors.shading)
    return SkinTerms(colour, jnp.asarray(part_geom), jnp.asarray(link), cov, background)


def skin_maps(color: ColorModel, skin: SkinTerms, W, crops, fgs,
              gain=None) -> Bool[Array, "n_cams n n"]:
    """Per camera, the crop's skin pixels: nearest to the skin class among the shirt's
    colours and skin (threshold ``T``; nearer than the room's colours that are not skin,
    ``skin.background``, as in step 1), under each camera's white balance ``W``
    (n_cams, 3, 3)."""
    both = ColorModel(jnp.concatenate([color.mean, skin.colour.mean.astype(color.mean.dtype)]),
                      jnp.concatenate([color.cov, skin.colour.cov.astype(color.cov.dtype)]),
                      shading=color.shading)
    k = color.n_colors + 1

    def one(W_i, crop, fg):
        ids, _ = classify(both, W_i, crop, fg, THRESHOLD, gain, skin.background)
        return ids == k

    fg_ax = None if fgs is None else 0
    return jax.vmap(one, in_axes=(0, 0, fg_ax))(W, crops, fgs)


class SkinObservation(NamedTuple):
    """One round's skin terms, stacked over cameras: observed centroids ``xy`` (image px),
    ``valid`` (gates passed), the per-view ``anchors`` that predict them, and the gate inputs
    (rendered and observed pixel counts, rendered centroids)."""

    xy: Float[Array, "n_cams 3 2"]
    valid: Bool[Array, "n_cams 3"]
    anchors: PatchAnchors
    rendered: Float[Array, "n_cams 3"]
    observed: Float[Array, "n_cams 3"]
    predicted: Float[Array, "n_cams 3 2"]


def observe_skin(skin: SkinTerms, chain, cams, q, geom: Int[Array, "n_cams n n"],
                 point: Float[Array, "n_cams n n 3"], uvs: Float[Array, "n_cams n n 2"],
                 windows: Float[Array, "n_cams 4"], observed: Bool[Array, "n_cams n n"],
                 ok_cam: Bool[Array, " n_cams"]) -> SkinObservation:
    """The skin terms of a round whose model render at ``q`` is ``geom`` / ``point`` on the
    crops' pixel grids ``uvs`` (image px; crop ``windows``), against the classified skin
    pixels ``observed`` (:func:`skin_maps`); cameras not ``ok_cam`` observe nothing. See the
    module docstring for the windows and gates."""
    dt = q.dtype
    n_cams, n = geom.shape[0], geom.shape[1]
    T = fk(chain, q)[skin.link]  # (3, 4, 4)
    pg = jnp.asarray(skin.part_geom)
    part = jnp.where(geom >= 0, jnp.take(pg, jnp.maximum(geom, 0)), -1)  # (C, n, n)

    def per_cam(part_c, pts_c, uv_c, win, obs_c):
        part_c, pts_c = part_c.reshape(-1), pts_c.reshape(-1, 3).astype(dt)
        uv_c, obs_c = uv_c.reshape(-1, 2).astype(dt), obs_c.reshape(-1)
        one_hot = (part_c[:, None] == jnp.arange(3)[None]).astype(dt)  # (N, 3)
        count = one_hot.sum(0)
        safe = jnp.maximum(count, 1.0)
        c_r = (one_hot.T @ uv_c) / safe[:, None]
        pts_c = jnp.where(part_c[:, None] >= 0, pts_c, 0.0)  # background points are inf
        local = jnp.einsum("kji,nkj->nki", T[:, :3, :3], pts_c[:, None] - T[None, :, :3, 3])
        off = jnp.einsum("nk,nki->ki", one_hot, local) / safe[:, None]
        px = win[2] / n  # image px per working px
        seen = count >= MIN_RENDERED
        radius = WINDOW_RADII * jnp.sqrt(count / jnp.pi) * px + WINDOW_MARGIN * win[2]
        d = jnp.linalg.norm(uv_c[:, None] - c_r[None], axis=-1)  # (N, 3)
        d = jnp.where(seen[None], d, jnp.inf)
        near = jnp.argmin(d, axis=1)
        take = (obs_c[:, None] & (near[:, None] == jnp.arange(3)[None])
                & (d <= radius[None])).astype(dt)
        n_o = take.sum(0)
        c_o = (take.T @ uv_c) / jnp.maximum(n_o, 1.0)[:, None]
        ok = seen & (n_o >= COUNT_RATIO[0] * count) & (n_o <= COUNT_RATIO[1] * count)
        return c_o, ok, off, c_r, count, n_o

    c_o, ok, off, c_r, count, n_o = jax.vmap(per_cam)(part, point, uvs, windows, observed)
    ok = ok & ok_cam[:, None]
    # agreement between cameras: the rays through the observed centroids of a part meet as
    # closely as those through the rendered ones (+ RAY_GAP), for every pair observing it
    if n_cams > 1:
        o_o, d_o = jax.vmap(pixel_rays)(cams, c_o)  # (C, 3, 3)
        o_r, d_r = jax.vmap(pixel_rays)(cams, c_r)
        gap_o, gap_r = _ray_gaps(o_o, d_o), _ray_gaps(o_r, d_r)  # (C, C, 3)
        pair = ok[:, None] & ok[None] & ~jnp.eye(n_cams, dtype=bool)[..., None]
        bad = pair & (gap_o > gap_r + RAY_GAP)
        ok = ok & ~jnp.any(bad, axis=1)
    X = jnp.einsum("kij,ckj->cki", T[:, :3, :3], off) + T[None, :, :3, 3]
    shift = c_r - jax.vmap(project)(cams, X)
    anchors = PatchAnchors(skin.link, off, jnp.where(ok[..., None], shift, 0.0))
    return jax.lax.stop_gradient(SkinObservation(c_o, ok, anchors, count, n_o, c_r))


def _ray_gaps(o, d):
    """(C, C, K) closest distance between camera i's and camera j's ray of each part k."""
    oi, oj, di, dj = o[:, None], o[None], d[:, None], d[None]
    cr = jnp.cross(di, dj)
    nrm = jnp.linalg.norm(cr, axis=-1)
    gap = jnp.abs(jnp.sum((oj - oi) * cr, axis=-1)) / jnp.maximum(nrm, 1e-12)
    return jnp.where(nrm > 1e-9, gap, 0.0)
