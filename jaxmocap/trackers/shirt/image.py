"""Image helpers of the colour-shirt tracker (:mod:`jaxmocap.trackers.shirt`): the crop window
around the histogram search's result, the working pixels' image positions, bilinear and
nearest sampling, and a one-pixel erosion of an id map."""

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int, UInt8


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


def sample_bilinear(
    image: UInt8[Array, "h w c"] | Float[Array, "h w c"], uv: Float[Array, "m n 2"]
) -> Float[Array, "m n c"]:
    """Bilinear samples of ``image`` at pixel positions ``uv`` (x, y), edge-clamped."""
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


def sample_nearest(mask: Bool[Array, "h w"], uv: Float[Array, "m n 2"]) -> Bool[Array, "m n"]:
    """Nearest-pixel samples of a mask at ``uv``; False outside the image."""
    h, w = mask.shape
    ij = jnp.round(uv).astype(jnp.int32)
    inside = (ij[..., 0] >= 0) & (ij[..., 0] < w) & (ij[..., 1] >= 0) & (ij[..., 1] < h)
    return inside & mask[jnp.clip(ij[..., 1], 0, h - 1), jnp.clip(ij[..., 0], 0, w - 1)]


def _erode(ids: Int[Array, "h w"]) -> Int[Array, "h w"]:
    """Ids kept where the 4 neighbours carry the same id (a one-pixel erosion per id)."""
    p = jnp.pad(ids, 1, constant_values=-1)
    same = (
        (p[:-2, 1:-1] == ids) & (p[2:, 1:-1] == ids) & (p[1:-1, :-2] == ids) & (p[1:-1, 2:] == ids)
    )
    return jnp.where(same, ids, 0)


def _crop_to_image(win_crop: Float[Array, " 4"], crop: Float[Array, " 4"], n: int) -> Array:
    """A window in working-pixel coordinates (pixel j covering [j - 1/2, j + 1/2]) as image
    pixels: ``x = x0 + (x_c + 1/2) s / n``."""
    k = crop[2] / n
    return jnp.stack(
        [crop[0] + (win_crop[0] + 0.5) * k, crop[1] + (win_crop[1] + 0.5) * k,
         win_crop[2] * k, win_crop[3] * k]
    )  # fmt: skip
