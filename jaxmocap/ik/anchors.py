"""Patch anchors (Wang §5.2 step 4, made smooth): each patch's 3D centroid fixed in the frame of
the link that carries it, projected into every camera; per-view anchors from a render."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Int

from jaxmocap.body import BodyModel, KinematicChain, fk
from jaxmocap.camera import Camera, project
from jaxmocap.garment import Garment
from jaxmocap.render import patch_surface_points


class PatchAnchors(eqx.Module):
    """The 3D centroid of every shirt patch as a point fixed in the frame of its link.

    ``link`` (P,) link index, ``offset`` (P, 3) metres in that link's frame: one anchor per
    patch shared by all cameras (:func:`anchors_from_garment`). **Per-view anchors**
    (:func:`view_anchors`) carry a leading camera axis, ``offset`` (C, P, 3), plus a pixel
    ``shift`` (C, P, 2) added to the projection, so that each camera predicts the centroid of
    the patch's *visible* part: ``c^{*i}_k(q) = project(cam_i, T_link(q) offset_ik) + shift_ik``.
    """

    link: Int[Array, " n_patches"]
    offset: Float[Array, "*cams n_patches 3"]
    shift: Float[Array, "*cams n_patches 2"] | None = None

    def __check_init__(self):
        if self.link.shape[0] != self.offset.shape[-2]:
            raise ValueError(
                f"PatchAnchors: link has {self.link.shape[0]} rows, offset "
                f"{self.offset.shape[-2]}; expected one of each per patch"
            )
        if self.offset.ndim not in (2, 3):
            raise ValueError(f"PatchAnchors: offset must be (P, 3) or (C, P, 3), got "
                             f"{self.offset.shape}")  # fmt: skip
        if self.shift is not None and self.shift.shape != self.offset.shape[:-1] + (2,):
            raise ValueError(
                f"PatchAnchors: shift {self.shift.shape}, expected {self.offset.shape[:-1] + (2,)}"
            )

    @property
    def n_patches(self) -> int:
        return self.offset.shape[-2]

    @property
    def per_view(self) -> bool:
        """Whether the anchors differ per camera (:func:`view_anchors`)."""
        return self.offset.ndim == 3


def anchors_from_samples(
    link: Int[ArrayLike, " n_patches"],
    points: Float[ArrayLike, "n_patches n_samples 3"],
    weights: Float[ArrayLike, "n_patches n_samples"] | None = None,
) -> PatchAnchors:
    """Patch anchors as the (weighted) mean of surface samples of each patch region.

    ``points[k]`` are samples of patch k's surface expressed in the frame of ``link[k]``
    (metres); ``weights`` (default uniform) e.g. area weights, 0 for padding samples.
    """
    link = np.asarray(link)
    pts = jnp.asarray(points)
    if link.ndim != 1 or pts.ndim != 3 or pts.shape[0] != link.shape[0] or pts.shape[2] != 3:
        raise ValueError(
            f"anchors_from_samples: expected link (P,) and points (P, S, 3); got link "
            f"{link.shape} and points {pts.shape}"
        )
    w = jnp.ones(pts.shape[:2], pts.dtype) if weights is None else jnp.asarray(weights, pts.dtype)
    if w.shape != pts.shape[:2]:
        raise ValueError(f"anchors_from_samples: weights {w.shape}, expected {pts.shape[:2]}")
    total = w.sum(axis=1)
    if np.any(np.asarray(total) <= 0):
        raise ValueError(
            "anchors_from_samples: patches "
            f"{np.flatnonzero(np.asarray(total) <= 0).tolist()} have no sample of positive weight"
        )
    offset = jnp.einsum("ps,psd->pd", w, pts) / total[:, None]
    return PatchAnchors(link=jnp.asarray(link, jnp.int32), offset=offset)


def anchors_from_garment(model: BodyModel, garment: Garment, dtype=None) -> PatchAnchors:
    """Patch anchors of a garment: the mean of the surface samples of each patch region.

    Samples come from :func:`jaxmocap.render.patch_surface_points` (points on the patch's
    geom, in the geom frame, kept where the patch's half-spaces hold) and are moved into the
    frame of the geom's link. Patch k of the result is patch id k + 1 of the garment.
    """
    dtype = dtype or model.geometry.pose.dtype
    pts, valid = patch_surface_points(model, garment, dtype)  # (P, S, 3) geom frame
    pose = model.geometry.pose.astype(dtype)[garment.patch_geom]  # geom -> link coordinates
    pts_link = jnp.einsum("pij,psj->psi", pose[:, :3, :3], pts) + pose[:, None, :3, 3]
    link = np.asarray(model.geometry.link)[np.asarray(garment.patch_geom)]
    return anchors_from_samples(link, pts_link, valid.astype(dtype))


def anchor_positions(
    chain: KinematicChain, anchors: PatchAnchors, q: Float[Array, " n_dof"]
) -> Float[Array, "*cams n_patches 3"]:
    """World positions (metres) of the patch anchors at pose q: ``T_link(q) @ offset``
    ((P, 3), or (C, P, 3) for per-view anchors)."""
    T = fk(chain, q)[anchors.link]
    off = anchors.offset.astype(q.dtype)
    X = jnp.einsum("pij,...pj->...pi", T[:, :3, :3], off)
    return X + T[:, :3, 3].reshape((1,) * (X.ndim - 2) + T.shape[:1] + (3,))


def _project_all(cams: Camera, X: Float[Array, "*c n 3"]) -> Float[Array, "n_cams n 2"]:
    if X.ndim == 3:  # one point set per camera
        return jax.vmap(project)(cams, X)
    return jax.vmap(project, in_axes=(0, None))(cams, X)


def _project_anchor_points(cams: Camera, X: Array, shift: Array | None) -> Array:
    c = _project_all(cams, X)
    return c if shift is None else c + shift.astype(c.dtype)


def project_anchors(
    cams: Camera, chain: KinematicChain, anchors: PatchAnchors, q: Float[Array, " n_dof"]
) -> Float[Array, "n_cams n_patches 2"]:
    """Projected anchors ``c^{*i}_k(q)`` (pixels) in every camera of a stacked Camera."""
    return _project_anchor_points(cams, anchor_positions(chain, anchors, q), anchors.shift)


VIEW_MIN_PIXELS = 4  # rendered pixels a patch needs in a view for a per-view anchor


def view_anchors(
    chain: KinematicChain,
    anchors: PatchAnchors,
    cams: Camera,
    q_ref: Float[Array, " n_dof"],
    patch: Int[Array, "n_cams h w"],
    point: Float[Array, "n_cams h w 3"],
    uv: Float[Array, "n_cams h w 2"],
    min_pixels: int = VIEW_MIN_PIXELS,
) -> PatchAnchors:
    """Per-view anchors from a render of the model at ``q_ref`` (the paper's rendered
    centroids, made smooth in q).

    Wang et al. compare the observed centroids with the centroids of the model's *rendered*
    patches, which are piecewise constant in q. Here every rendered pixel of patch k in camera
    i (``patch`` ids, world hit ``point`` at pixel position ``uv``, e.g. the ``Hits`` of
    :func:`jaxmocap.render.render_uv` on the tracker's crop grid) is carried rigidly by the
    patch's link: the anchor is the mean of those hit points in the link frame and ``shift``
    the difference between the rendered 2D centroid and the anchor's projection at
    ``q_ref``. So at ``q_ref`` the prediction equals the rendered visible-part centroid
    exactly, and near it the prediction moves with the link (visibility frozen). Patches
    with fewer than ``min_pixels`` rendered pixels in a view keep the shared anchor of
    ``anchors`` and no shift. Not differentiated w.r.t. the render (stop_gradient).
    """
    if anchors.per_view:
        raise ValueError("view_anchors: anchors must be the shared (P, 3) anchors")
    dt = q_ref.dtype
    P = anchors.n_patches
    n_cams = cams.K.shape[0]
    T = fk(chain, q_ref)[anchors.link]  # (P, 4, 4) at the reference pose
    seg = jnp.clip(patch.reshape(n_cams, -1), 0, P + 1)  # ids > P go to a discarded bin
    pts = point.reshape(n_cams, -1, 3).astype(dt)
    pix = uv.reshape(n_cams, -1, 2).astype(dt)
    fg = (seg >= 1) & (seg <= P)
    pts = jnp.where(fg[..., None], pts, 0.0)  # background points are inf

    def per_cam(seg_c, pts_c, pix_c, fg_c):
        k = jnp.clip(seg_c - 1, 0, P - 1)
        Tk = T[k]  # link of each pixel's patch
        local = jnp.einsum("nji,nj->ni", Tk[:, :3, :3], pts_c - Tk[:, :3, 3])  # R^T (X - t)
        w = fg_c.astype(dt)
        sums = jax.ops.segment_sum(local * w[:, None], seg_c, P + 2)[1 : P + 1]
        sum_uv = jax.ops.segment_sum(pix_c * w[:, None], seg_c, P + 2)[1 : P + 1]
        count = jax.ops.segment_sum(w, seg_c, P + 2)[1 : P + 1]
        safe = jnp.maximum(count, 1.0)[:, None]
        return sums / safe, sum_uv / safe, count

    off, c2d, count = jax.vmap(per_cam)(seg, pts, pix, fg)
    use = count >= min_pixels
    off = jnp.where(use[..., None], off, anchors.offset.astype(dt)[None])
    X = jnp.einsum("pij,cpj->cpi", T[:, :3, :3], off) + T[None, :, :3, 3]
    shift = jnp.where(use[..., None], c2d - jax.vmap(project)(cams, X), 0.0)
    return jax.lax.stop_gradient(PatchAnchors(anchors.link, off, shift))


def append_anchors(anchors: PatchAnchors, more: PatchAnchors, n_cams: int) -> PatchAnchors:
    """``anchors`` followed by ``more`` (e.g. the shirt's patches and the skin terms of
    :mod:`jaxmocap.trackers.shirt.skin`): per-view (C, P + K, 3) with shifts where either is
    per-view or shifted, else shared (P + K, 3)."""
    if not (anchors.per_view or more.per_view or anchors.shift is not None
            or more.shift is not None):
        return PatchAnchors(jnp.concatenate([anchors.link, more.link]),
                            jnp.concatenate([anchors.offset, more.offset.astype(
                                anchors.offset.dtype)]))

    def views(a: PatchAnchors):
        off = a.offset if a.per_view else jnp.broadcast_to(a.offset, (n_cams,) + a.offset.shape)
        sh = jnp.zeros(off.shape[:-1] + (2,), off.dtype) if a.shift is None else a.shift
        return off, jnp.broadcast_to(sh, off.shape[:-1] + (2,))

    (o1, s1), (o2, s2) = views(anchors), views(more)
    dt = o1.dtype
    return PatchAnchors(jnp.concatenate([anchors.link, more.link]),
                        jnp.concatenate([o1, o2.astype(dt)], axis=1),
                        jnp.concatenate([s1.astype(dt), s2.astype(dt)], axis=1))
