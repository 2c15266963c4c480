"""Shaded RGB images of the garment: Lambert shading under coloured light, camera gamma, sensor
noise and a background image (the nuisances Wang et al. 2011 §5 and §6 name: illuminant colour
and intensity changes, a lamp switched off, dim light with noise).

For a surface point x with albedo rho (garment patch colour, skin, or the neutral body colour)
and unit normal n, the linear camera RGB is

    c = I * M @ (rho * (a + sum_l L_l max(0, n . l_l)
                          + sum_m P_m max(0, n . (x_m - x) / |x_m - x|) / |x_m - x|^2))

with ambient a, directional lights (unit direction l_l towards the light, intensity L_l), point
lights at x_m (intensity P_m at 1 m, inverse-square fall-off), the illuminant's 3x3 colour
matrix M and overall intensity I. The camera encodes ``v = clip(c, 0, 1)^(1 / gamma)``;
background pixels take the caller's background image; Gaussian sensor noise of standard
deviation ``noise_sigma`` (in units of the full 8-bit range) is added to the whole frame, which
is then quantised to ``uint8``.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray, UInt8

from ..body import BodyModel
from ..camera import Camera
from ..garment import Garment, albedo
from ._image import render_ids
from ._raycast import RAY_CHUNK, Hits

CAMERA_GAMMA = 2.2  # sRGB-like display gamma of a webcam
AMBIENT = 0.25
KEY_LIGHT = (0.6, 0.3, 0.75)  # direction towards the key light (front, slightly left, above)
FILL_LIGHT = (0.3, -0.8, 0.2)  # a weaker fill light from the right
KEY_INTENSITY, FILL_INTENSITY = 0.7, 0.3


def _as_float(x: ArrayLike) -> Array:
    x = jnp.asarray(x)
    return x if jnp.issubdtype(x.dtype, jnp.inexact) else x.astype(jnp.result_type(float))


class Lighting(eqx.Module):
    """Ambient + directional + point lights under one illuminant (see module docstring).

    ``directions`` are unit vectors from the surface towards each directional light (world);
    ``positions`` are point-light positions (m) with ``point_intensity`` at 1 m;
    ``illuminant`` is the 3x3 colour matrix M (identity = white light) and ``intensity`` I."""

    ambient: Float[Array, ""] = eqx.field(converter=_as_float)
    directions: Float[Array, "n_dir 3"] = eqx.field(converter=_as_float)
    dir_intensity: Float[Array, " n_dir"] = eqx.field(converter=_as_float)
    positions: Float[Array, "n_point 3"] = eqx.field(converter=_as_float)
    point_intensity: Float[Array, " n_point"] = eqx.field(converter=_as_float)
    illuminant: Float[Array, "3 3"] = eqx.field(converter=_as_float)
    intensity: Float[Array, ""] = eqx.field(converter=_as_float)


def default_lighting(dtype=None) -> Lighting:
    """White light: ambient ``AMBIENT``, a key and a fill directional light, no point light."""
    dtype = dtype or jnp.result_type(float)
    dirs = jnp.asarray([KEY_LIGHT, FILL_LIGHT], dtype)
    return Lighting(
        ambient=jnp.asarray(AMBIENT, dtype),
        directions=dirs / jnp.linalg.norm(dirs, axis=-1, keepdims=True),
        dir_intensity=jnp.asarray([KEY_INTENSITY, FILL_INTENSITY], dtype),
        positions=jnp.zeros((0, 3), dtype),
        point_intensity=jnp.zeros((0,), dtype),
        illuminant=jnp.eye(3, dtype=dtype),
        intensity=jnp.asarray(1.0, dtype),
    )


def shade(hits: Hits, garment: Garment, lighting: Lighting) -> Float[Array, "*n 3"]:
    """Linear camera RGB of every hit (module docstring formula); 0 for background rays."""
    shape = hits.normal.shape
    n, x = hits.normal.reshape(-1, 3), hits.point.reshape(-1, 3)
    rho = albedo(garment, hits.geom, hits.patch).astype(n.dtype).reshape(-1, 3)
    cos_dir = n @ lighting.directions.T  # (N, n_dir)
    lit = lighting.ambient + jnp.maximum(cos_dir, 0) @ lighting.dir_intensity
    to_light = lighting.positions[None, :, :] - x[:, None, :]  # (N, n_point, 3)
    dist2 = jnp.maximum(jnp.sum(to_light * to_light, axis=-1), 1e-12)
    cos_pt = jnp.einsum("nk,nmk->nm", n, to_light) / jnp.sqrt(dist2)
    lit = lit + (jnp.maximum(cos_pt, 0) / dist2) @ lighting.point_intensity
    c = lighting.intensity * (rho * lit[:, None]) @ lighting.illuminant.T
    c = c.reshape(shape)
    return jnp.where(hits.background[..., None], 0, c)


def encode(
    linear: Float[Array, "*n 3"],
    hits: Hits,
    background: UInt8[Array, "*n 3"] | Float[Array, "*n 3"],
    gamma: float | Float[Array, ""] = CAMERA_GAMMA,
    noise_sigma: float | Float[Array, ""] = 0.0,
    key: PRNGKeyArray | None = None,
) -> UInt8[Array, "*n 3"]:
    """Camera gamma, background compositing, sensor noise, 8-bit quantisation.

    ``background`` is an image of the same size, ``uint8`` or float in [0, 1]; ``noise_sigma``
    is the noise standard deviation as a fraction of 255 (needs a ``key`` when > 0)."""
    bg = background.astype(linear.dtype)
    if jnp.issubdtype(background.dtype, jnp.integer):
        bg = bg / 255
    v = jnp.clip(linear, 0, 1) ** (1 / gamma)
    v = jnp.where(hits.background[..., None], bg, v)
    if key is not None:
        v = v + noise_sigma * jax.random.normal(key, v.shape, v.dtype)
    elif not isinstance(noise_sigma, jax.core.Tracer) and noise_sigma != 0:
        raise ValueError("encode: noise_sigma > 0 needs a PRNG key")
    return jnp.round(jnp.clip(v, 0, 1) * 255).astype(jnp.uint8)


def render_rgb(
    model: BodyModel,
    garment: Garment,
    q: Float[Array, " n_dof"],
    cam: Camera,
    background: UInt8[Array, "h w 3"] | Float[Array, "h w 3"],
    lighting: Lighting | None = None,
    gamma: float | Float[Array, ""] = CAMERA_GAMMA,
    noise_sigma: float | Float[Array, ""] = 0.0,
    key: PRNGKeyArray | None = None,
    crop: tuple[int, int, int, int] | None = None,
    chunk: int = RAY_CHUNK,
) -> tuple[UInt8[Array, "h w 3"], Hits]:
    """A shaded ``uint8`` RGB image of the body at pose ``q`` over ``background`` (same size as
    the image or the ``crop``), and the Hits (ground-truth ids, depth, normals)."""
    hits = render_ids(model, garment, q, cam, crop=crop, chunk=chunk)
    if background.shape != hits.geom.shape + (3,):
        raise ValueError(
            f"render_rgb: background has shape {background.shape}, expected "
            f"{hits.geom.shape + (3,)} (the rendered image's height, width, 3)"
        )
    lighting = default_lighting(q.dtype) if lighting is None else lighting
    linear = shade(hits, garment, lighting)
    return encode(linear, hits, background, gamma, noise_sigma, key), hits
