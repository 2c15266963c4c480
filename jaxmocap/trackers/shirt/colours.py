"""The colour-shirt tracker's per-patch colour states
(``make_params(colours=Colours(patch_colours=True))``, issue 37): step 1 classified against
every patch's state, and step 5's update of the states (:mod:`jaxmocap.appearance`), per
camera under ``vmap``. Step 3's per-patch classification is
:func:`jaxmocap.trackers.shirt.frame.pose_assisted_centroids` with :func:`patch_model`."""

from __future__ import annotations

import jax
import jax.numpy as jnp

from jaxmocap import appearance
from jaxmocap.color import ColorModel, classified_fraction, classify
from jaxmocap.color.classify import THRESHOLD
from jaxmocap.color.illumination import ReferenceClassification
from jaxmocap.sampling import erode_ids
from jaxmocap.trackers.shirt.params import ShirtParams, ShirtState


def patch_model(params: ShirtParams, look: appearance.PartColours) -> ColorModel:
    """One camera's patch colour states as a colour model whose "colours" are the patches."""
    return ColorModel(look.mean, look.cov, shading=params.colours.shading)


def in_look_space(crop, W):
    """A crop in the colour space of the patch states (the camera's initial white balance)."""
    return crop.astype(W.dtype) @ W.T


def patch_colour_of(params: ShirtParams, patch):
    """Colour ids (0 background) of a patch id map (0 background, ``1..P``)."""
    pc = jnp.asarray(params.garment.patch_colour).astype(jnp.int32)
    return jnp.where(patch > 0, jnp.take(pc, jnp.maximum(patch - 1, 0)), 0)


def classify_by_patch(
    params: ShirtParams, state: ShirtState, crops, fgs
) -> ReferenceClassification:
    """Step 1 with ``patch_colours``: every crop pixel compared with every patch's colour state
    (threshold ``T``, the scene's colours as background), given the colour of the nearest
    patch; stacked over cameras (``W`` and ``used_reference`` as if the plain step ran)."""

    def one(look, W_look, W, crop, fg):
        img = in_look_space(crop, W_look)
        eye = jnp.eye(3, dtype=W_look.dtype)
        patch, dist = classify(patch_model(params, look), eye, img, fg, THRESHOLD,
                               params.colours.shading, params.colours.scene_colors)  # fmt: skip
        ids = patch_colour_of(params, patch)
        return ReferenceClassification(ids, dist, W, classified_fraction(ids, fg), jnp.array(False))

    fg_ax = None if fgs is None else 0
    return jax.vmap(one, in_axes=(0, 0, 0, 0, fg_ax))(state.look, state.look_W, state.W, crops, fgs)


def colour_update(params: ShirtParams, state: ShirtState, views, okq, patch, held, valid,
                  learn):
    """Step 5 with ``patch_colours`` (:mod:`jaxmocap.appearance`), per camera that found the
    shirt. On a valid frame, in the cameras where ``learn`` (the final pose explains the crop:
    :class:`~jaxmocap.trackers.shirt.params.Colours` ``learn_max_residual``,
    ``learn_min_recall``), each patch's colour state is
    relit and moved toward the pixels that the final pose's render ``patch`` (patch ids,
    stacked over cameras; eroded by one pixel) gives it, trimmed. With ``follow_light``, on the
    first invalid frame after a frame the camera learned from, only the light follows, from
    ``held``, the held pose's render (eroded by two pixels: it is a frame old;
    :func:`jaxmocap.appearance.follow_light`). Else the states stay. Returns ``(look, updated
    patches, relight applied, relight RMS)`` stacked over cameras."""
    v = views
    # follow only from a pose the camera learned from on the previous frame (a trusted one)
    follow = ~valid & (jnp.min(state.look.age, axis=-1) == 0) & params.colours.follow_light

    def one(look, W_look, patch, held_patch, crop, fg, ok_cam, follow_cam, learn_cam):
        img = in_look_space(crop, W_look)
        stats = appearance.part_statistics(look, img, erode_ids(patch),
                                           shading=params.colours.shading, mask=fg)  # fmt: skip
        new, used, fit = appearance.update_parts(look, stats, learn_cam & ok_cam)
        if not params.colours.follow_light:
            return new, jnp.sum(used).astype(jnp.int32), fit.ok, fit.rms
        held_stats = appearance.part_statistics(look, img, erode_ids(erode_ids(held_patch)),
                                                gate=jnp.inf, mask=fg)  # fmt: skip
        new, fol = appearance.follow_light(new, held_stats, follow_cam & ok_cam)
        ok = fit.ok | fol.ok
        rms = jnp.where(valid, fit.rms, fol.rms)
        return new, jnp.sum(used).astype(jnp.int32), ok, rms

    fg_ax = None if v.fgs is None else 0
    return jax.vmap(one, in_axes=(0, 0, 0, 0, 0, fg_ax, 0, 0, 0))(
        state.look, state.look_W, patch, held, v.crops, v.fgs, okq, follow, learn
    )
