"""Image sampling and crops, one home for the package (floor 1: imports nothing of jaxmocap).

Pixel centres at integer coordinates, ``uv = (x, y)`` (OpenCV's convention, as everywhere).
Two bilinear samplers because two boundary conventions are wanted: :func:`sample_bilinear`
reads 0 outside the image (an edge map: no edge there; the stereo filter's cues), and
:func:`sample_bilinear_clamped` reads the border pixel (a colour crop that leaves the frame:
the colour-shirt tracker). :func:`sample_nearest` reads 0 / False outside. The crop window of
the colour-shirt tracker (Wang §4: a square of ``factor s'`` around the histogram search's
result) and the one-pixel erosion of an id map live here too.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float, Int, UInt8


def sample_bilinear(image: Float[Array, "h w"], uv: Float[Array, "*n 2"]) -> Float[Array, "*n"]:
    """Bilinear interpolation of ``image`` at pixel positions ``uv = (x, y)`` (pixel centres at
    integers); a neighbour outside the image counts 0 (no edge / background).

    Implementation: the image is zero-padded by 2 px and its 2x2 neighbourhoods are stacked
    into a (h+3, w+3, 4) table once (it does not depend on ``uv``, so under ``vmap`` over
    particles it is built once per image); each sample is then ONE gather of 4 contiguous
    values instead of four scattered ones (the gathers dominate the likelihood's cost).
    """
    h, w = image.shape
    x, y = uv[..., 0], uv[..., 1]
    x0f, y0f = jnp.floor(x), jnp.floor(y)
    fx, fy = (x - x0f).astype(image.dtype), (y - y0f).astype(image.dtype)
    # p[y + 2, x + 2] = image[y, x]; quad[j, i] = (p[j, i], p[j, i+1], p[j+1, i], p[j+1, i+1])
    p = jnp.pad(image, 2)
    quad = jnp.stack([p[:-1, :-1], p[:-1, 1:], p[1:, :-1], p[1:, 1:]], axis=-1)
    # a corner index clipped into the padding reads zeros only (all four neighbours outside)
    i = jnp.clip(x0f + 2, 0, w + 2).astype(jnp.int32)
    j = jnp.clip(y0f + 2, 0, h + 2).astype(jnp.int32)
    v = quad.reshape(-1, 4)[j * (w + 3) + i]
    top = v[..., 0] * (1 - fx) + v[..., 1] * fx
    bottom = v[..., 2] * (1 - fx) + v[..., 3] * fx
    return top * (1 - fy) + bottom * fy


def sample_nearest(image: Array, uv: Float[Array, "*n 2"]) -> Array:
    """``image`` at the nearest pixel of ``uv`` (0 / False outside the image)."""
    h, w = image.shape
    xi = jnp.round(jnp.clip(uv[..., 0], -1, w)).astype(jnp.int32)
    yi = jnp.round(jnp.clip(uv[..., 1], -1, h)).astype(jnp.int32)
    inside = (xi >= 0) & (xi < w) & (yi >= 0) & (yi < h)
    v = image.reshape(-1)[jnp.clip(yi, 0, h - 1) * w + jnp.clip(xi, 0, w - 1)]
    return jnp.where(inside, v, jnp.zeros((), image.dtype))


def crop_window(x: Array, y: Array, s: Array, factor: float) -> Float[Array, " 4"]:
    """Square crop ``(x0, y0, side, side)`` of side ``factor s`` centred on ``(x, y)``."""
    side = factor * s
    return jnp.stack([x - side / 2, y - side / 2, side, side])


def crop_uv(window: Float[Array, " 4"], n: int) -> Float[Array, "n n 2"]:
    """Image positions of the ``n x n`` working pixels: ``x0 + (j + 1/2) s / n`` (as
    :func:`jaxmocap.render.window_uv`)."""
    f = (jnp.arange(n, dtype=window.dtype) + 0.5) / n
    uu, vv = jnp.meshgrid(window[0] + f * window[2], window[1] + f * window[3])
    return jnp.stack([uu, vv], axis=-1)


def sample_bilinear_clamped(
    image: UInt8[Array, "h w c"] | Float[Array, "h w c"], uv: Float[Array, "m n 2"]
) -> Float[Array, "m n c"]:
    """Bilinear samples of a (multi-channel) ``image`` at pixel positions ``uv`` (x, y),
    edge-clamped: a position outside reads the nearest border pixel (the shirt's crops)."""
    h, w = image.shape[:2]
    dt = uv.dtype
    x = jnp.clip(uv[..., 0], 0, w - 1)
    y = jnp.clip(uv[..., 1], 0, h - 1)
    x0 = jnp.clip(jnp.floor(x), 0, w - 2).astype(jnp.int32)
    y0 = jnp.clip(jnp.floor(y), 0, h - 2).astype(jnp.int32)
    fx = (x - x0)[..., None]
    fy = (y - y0)[..., None]
    im = image.astype(dt)
    a, b = im[y0, x0], im[y0, x0 + 1]
    c, d = im[y0 + 1, x0], im[y0 + 1, x0 + 1]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def erode_ids(ids: Int[Array, "h w"]) -> Int[Array, "h w"]:
    """Ids kept where the 4 neighbours carry the same id (a one-pixel erosion per id)."""
    p = jnp.pad(ids, 1, constant_values=-1)
    same = (
        (p[:-2, 1:-1] == ids) & (p[2:, 1:-1] == ids) & (p[1:-1, :-2] == ids) & (p[1:-1, 2:] == ids)
    )
    return jnp.where(same, ids, 0)


def crop_to_image(win_crop: Float[Array, " 4"], crop: Float[Array, " 4"], n: int) -> Array:
    """A window in working-pixel coordinates (pixel j covering [j - 1/2, j + 1/2]) as image
    pixels: ``x = x0 + (x_c + 1/2) s / n``."""
    k = crop[2] / n
    return jnp.stack(
        [crop[0] + (win_crop[0] + 0.5) * k, crop[1] + (win_crop[1] + 0.5) * k,
         win_crop[2] * k, win_crop[3] * k]
    )  # fmt: skip
