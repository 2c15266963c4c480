"""Images from the ray caster: id maps (full image or a crop) and the tiny normalised id maps of
the pose database (Wang et al. 2011 §5.2, Step 2).

**Tiny map normalisation.** The database stores each pose "as a tiny id map" and is queried
with "the classified shirt region, resized as a tiny 40x40 id map" (§5.2). Both sides must crop
the same way, so the window is defined from the shirt's extent in the image:

1. the shirt's image bounding box ``[lo, hi]`` (pixels, continuous): for a rendered pose, the
   projection of a dense sample of every patch's surface (:func:`shirt_window`); for a
   classified camera image, the pixels with a colour id, each pixel covering
   ``[x - 1/2, x + 1/2]`` (:func:`window_from_mask`);
2. made square around its centre ``c = (lo + hi) / 2`` with side
   ``s = max(hi - lo) (1 + 2 margin)`` (``TINY_MARGIN`` on each side): window
   ``(x0, y0, s, s)`` with ``(x0, y0) = c - s / 2``;
3. tiny pixel ``(i, j)`` samples the image point ``(x0 + (j + 1/2) s / n, y0 + (i + 1/2) s / n)``
   — by casting a ray through it (:func:`tiny_id_map`), or by taking the nearest image pixel of
   a classified map (:func:`resample_ids`).

The bounding box of the sampled surface includes occluded shirt points, so it can exceed the
visible silhouette's by the part hidden behind skin (hands in front of the chest); both sides
otherwise agree to about a pixel of the source image.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt8

from ..body import BodyModel
from ..camera import Camera, camera_center, pixel_rays, project, to_camera
from ..garment import Garment
from ._intersect import BOX, CAPSULE, CYLINDER, SPHERE
from ._raycast import RAY_CHUNK, Hits, cast_rays, posed_scene

TINY_SIZE = 40  # Wang et al. §5.2: "a tiny 40x40 id map"
TINY_MARGIN = 0.05  # fraction of the square side added on each side of the shirt's bbox
TINY_POSE_CHUNK = 64  # poses per lax.map step in tiny_id_maps
SURFACE_SAMPLES = 160  # surface samples per patch for the shirt's projected extent


def pixel_grid(
    width: int, height: int, x0: int = 0, y0: int = 0, dtype=None
) -> Float[Array, "{height} {width} 2"]:
    """Pixel centres ``(u, v)`` of the window ``x0 <= u < x0 + width``, ``y0 <= v < y0 + h``."""
    dtype = dtype or jnp.result_type(float)
    u = jnp.arange(x0, x0 + width, dtype=dtype)
    v = jnp.arange(y0, y0 + height, dtype=dtype)
    uu, vv = jnp.meshgrid(u, v)
    return jnp.stack([uu, vv], axis=-1)


def render_uv(
    model: BodyModel,
    garment: Garment,
    q: Float[Array, " n_dof"],
    cam: Camera,
    uv: Float[Array, "*s 2"],
    chunk: int = RAY_CHUNK,
) -> Hits:
    """Cast the rays through (distorted) pixel positions ``uv`` of ``cam``; Hits of shape
    ``uv.shape[:-1]`` with ``depth`` the camera-frame z."""
    dirs = pixel_rays(cam, uv)[1]
    return render_rays(model, garment, q, camera_center(cam), dirs, cam.R[2], chunk)


def render_rays(
    model: BodyModel,
    garment: Garment,
    q: Float[Array, " n_dof"],
    origin: Float[Array, " 3"],
    dirs: Float[Array, "*s 3"],
    depth_axis: Float[Array, " 3"] | None = None,
    chunk: int = RAY_CHUNK,
) -> Hits:
    """:func:`render_uv` on rays already made (``origin`` the camera centre, ``dirs`` from
    :func:`jaxmocap.camera.pixel_rays`, ``depth_axis`` the camera's row ``R[2]``): a tracker
    that renders several poses on one pixel grid undistorts the grid once. Hits of shape
    ``dirs.shape[:-1]``."""
    shape = dirs.shape[:-1]
    scene = posed_scene(model, q)
    hits = cast_rays(scene, garment, origin, dirs.reshape(-1, 3), depth_axis=depth_axis,
                     chunk=chunk)  # fmt: skip
    return jax.tree.map(lambda a: a.reshape(shape + a.shape[1:]), hits)


def render_ids(
    model: BodyModel,
    garment: Garment,
    q: Float[Array, " n_dof"],
    cam: Camera,
    crop: tuple[int, int, int, int] | None = None,
    chunk: int = RAY_CHUNK,
) -> Hits:
    """Ray-cast the body at pose ``q`` into ``cam``: per pixel geom id, patch id, colour id,
    depth (camera z, m), world normal, background flag. Shape ``(H, W)``, or ``(h, w)`` for a
    static ``crop = (x0, y0, w, h)`` in pixels. Lens distortion is included (rays come from
    :func:`jaxmocap.camera.pixel_rays`). jit/vmap over ``q`` and stacked cameras."""
    x0, y0, w, h = (0, 0, cam.width, cam.height) if crop is None else crop
    if w <= 0 or h <= 0:
        raise ValueError(f"render_ids: crop (x0, y0, w, h) must have w, h > 0, got {crop}")
    uv = pixel_grid(int(w), int(h), int(x0), int(y0), dtype=q.dtype)
    return render_uv(model, garment, q, cam, uv, chunk)


# ----------------------------------------------------------------------------- tiny maps


def _unit_samples(n: int, rings: int = 16) -> dict[str, np.ndarray]:
    """Fixed parameters of ``n`` surface samples: Fibonacci-sphere directions; for capsule and
    cylinder sides (first half) an angle on ``rings`` meridians and a height in [-1, 1]; for
    cylinder caps (second half) a golden-angle spiral of radius fraction ``rho``, alternating
    top and bottom."""
    i = np.arange(n) + 0.5
    z = 1 - 2 * i / n
    golden = np.pi * (3 - np.sqrt(5))
    rho_s = np.sqrt(1 - z * z)
    dirs = np.stack([rho_s * np.cos(i * golden), rho_s * np.sin(i * golden), z], axis=-1)
    half = n // 2
    j = np.arange(n - half)
    theta = np.concatenate([2 * np.pi * (np.arange(half) % rings) / rings, j * golden])
    height = np.concatenate([np.linspace(-1, 1, half), np.where(j % 2 == 0, 1.0, -1.0)])
    rho = np.concatenate([np.ones(half), np.sqrt((j // 2 + 1) / ((n - half + 1) // 2))])
    return {"dirs": dirs, "theta": theta, "height": height, "rho": rho, "side": np.arange(n) < half}


_SAMPLES = _unit_samples(SURFACE_SAMPLES)


def patch_surface_points(
    model: BodyModel, garment: Garment, dtype=None
) -> tuple[Float[Array, "n_patches s 3"], Bool[Array, "n_patches s"]]:
    """Surface samples of every patch in its geom's frame (m) and whether each lies in the
    patch's half-spaces: ``SURFACE_SAMPLES`` points on the geom's surface (spheres/ellipsoids:
    Fibonacci directions scaled by the radii; capsules and cylinders: half on the side in 16
    rings, half on the caps; boxes: directions pushed out to the faces)."""
    dtype = dtype or model.geometry.size.dtype
    s = {k: jnp.asarray(v) for k, v in _SAMPLES.items()}
    kind = model.geometry.kind[garment.patch_geom][:, None]
    size = model.geometry.size.astype(dtype)[garment.patch_geom][:, None, :]
    r, h = size[..., 0], size[..., 1]
    u = s["dirs"].astype(dtype)[None]
    ring = jnp.stack(
        [jnp.cos(s["theta"]), jnp.sin(s["theta"]), jnp.zeros_like(s["theta"])], axis=-1
    ).astype(dtype)[None]
    sign_z = jnp.sign(u[..., 2])
    zero = jnp.zeros_like(r * sign_z)
    side = s["side"][None, :, None]
    cap_capsule = r[..., None] * u + jnp.stack([zero, zero, h * sign_z], axis=-1)
    along = jnp.stack([zero, zero, h * s["height"][None].astype(dtype)], axis=-1)
    side_pts = r[..., None] * ring + along
    capsule = jnp.where(side, side_pts, cap_capsule)
    cylinder = jnp.where(side, side_pts, r[..., None] * s["rho"][None, :, None] * ring + along)
    box = size * u / jnp.max(jnp.abs(u), axis=-1, keepdims=True)
    radii = jnp.where((kind == SPHERE)[..., None], jnp.stack([r, r, r], axis=-1), size)
    ellipsoid = radii * u
    k = kind[..., None]
    pts = jnp.where(
        k == CAPSULE,
        capsule,
        jnp.where(k == CYLINDER, cylinder, jnp.where(k == BOX, box, ellipsoid)),
    )
    planes = garment.patch_planes.astype(dtype)
    vals = jnp.einsum("psk,pjk->psj", pts, planes[..., :3]) + planes[:, None, :, 3]
    return pts, jnp.all(vals <= 0, axis=-1)


def shirt_points(
    model: BodyModel, garment: Garment, q: Float[Array, " n_dof"]
) -> tuple[Float[Array, "m 3"], Bool[Array, " m"]]:
    """World positions (m) of the patch surface samples at pose ``q`` and their validity."""
    from ..body import fk, geom_world_poses

    pts, valid = patch_surface_points(model, garment, q.dtype)
    T = geom_world_poses(model, fk(model.chain, q))[garment.patch_geom]
    world = jnp.einsum("pij,psj->psi", T[:, :3, :3], pts) + T[:, None, :3, 3]
    return world.reshape(-1, 3), valid.reshape(-1)


def square_window(
    lo: Float[Array, " 2"], hi: Float[Array, " 2"], margin: float = TINY_MARGIN
) -> Float[Array, " 4"]:
    """The square ``(x0, y0, s, s)`` centred on the box ``[lo, hi]`` (pixels) with side
    ``s = max(hi - lo) (1 + 2 margin)`` (at least one pixel)."""
    c = (lo + hi) / 2
    side = jnp.maximum(jnp.max(hi - lo) * (1 + 2 * margin), 1)
    return jnp.concatenate([c - side / 2, jnp.stack([side, side])])


def shirt_window(
    model: BodyModel,
    garment: Garment,
    q: Float[Array, " n_dof"],
    cam: Camera,
    margin: float = TINY_MARGIN,
) -> Float[Array, " 4"]:
    """Tiny-map window ``(x0, y0, s, s)`` (pixels) of the shirt at pose ``q``: the square around
    the bounding box of the projected patch surface samples (points behind the camera are
    ignored), see the module docstring."""
    pts, valid = shirt_points(model, garment, q)
    valid = valid & (to_camera(cam, pts)[:, 2] > 0)
    uv = project(cam, pts)
    big = jnp.asarray(jnp.inf, uv.dtype)
    lo = jnp.min(jnp.where(valid[:, None], uv, big), axis=0)
    hi = jnp.max(jnp.where(valid[:, None], uv, -big), axis=0)
    lo, hi = jnp.where(jnp.isfinite(lo), lo, 0), jnp.where(jnp.isfinite(hi), hi, 0)
    return square_window(lo, hi, margin)


def window_from_mask(mask: Bool[Array, "h w"], margin: float = TINY_MARGIN) -> Float[Array, " 4"]:
    """Tiny-map window of a classified image: the square around the bounding box of the
    ``True`` pixels, each covering ``[x - 1/2, x + 1/2]`` (see the module docstring)."""
    h, w = mask.shape
    dtype = jnp.result_type(float)
    xs = jnp.arange(w, dtype=dtype)
    ys = jnp.arange(h, dtype=dtype)
    col, row = jnp.any(mask, axis=0), jnp.any(mask, axis=1)
    lo = jnp.stack([jnp.min(jnp.where(col, xs, w)), jnp.min(jnp.where(row, ys, h))]) - 0.5
    hi = jnp.stack([jnp.max(jnp.where(col, xs, -1)), jnp.max(jnp.where(row, ys, -1))]) + 0.5
    return square_window(lo, hi, margin)


def window_uv(window: Float[Array, " 4"], size: int = TINY_SIZE) -> Float[Array, "n n 2"]:
    """Image positions sampled by a tiny map: ``x0 + (j + 1/2) s / n``, ``y0 + (i + 1/2) s / n``."""
    f = (jnp.arange(size, dtype=window.dtype) + 0.5) / size
    uu, vv = jnp.meshgrid(window[0] + f * window[2], window[1] + f * window[3])
    return jnp.stack([uu, vv], axis=-1)


def resample_ids(
    ids: Int[Array, "h w"] | UInt8[Array, "h w"],
    window: Float[Array, " 4"],
    size: int = TINY_SIZE,
) -> Int[Array, "n n"]:
    """A classified id map resized to the tiny ``size x size`` map of ``window``: nearest image
    pixel at each tiny sample position, 0 outside the image."""
    h, w = ids.shape
    uv = jnp.round(window_uv(window, size)).astype(jnp.int32)
    inside = (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    vals = ids[jnp.clip(uv[..., 1], 0, h - 1), jnp.clip(uv[..., 0], 0, w - 1)]
    return jnp.where(inside, vals.astype(jnp.int32), 0)


def tiny_hits(
    model: BodyModel,
    garment: Garment,
    q: Float[Array, " n_dof"],
    cam: Camera,
    size: int = TINY_SIZE,
    margin: float = TINY_MARGIN,
) -> tuple[Hits, Float[Array, " 4"]]:
    """Hits of the ``size x size`` tiny map of pose ``q`` and its window ``(x0, y0, s, s)``."""
    window = shirt_window(model, garment, q, cam, margin)
    return render_uv(model, garment, q, cam, window_uv(window, size)), window


def tiny_id_map(
    model: BodyModel,
    garment: Garment,
    q: Float[Array, " n_dof"],
    cam: Camera,
    size: int = TINY_SIZE,
    margin: float = TINY_MARGIN,
) -> Int[Array, "n n"]:
    """The pose database's tiny ``40 x 40`` colour-id map of pose ``q`` seen by ``cam``
    (Wang et al. §5.2): rays through the normalised shirt window (module docstring)."""
    return tiny_hits(model, garment, q, cam, size, margin)[0].colour


def tiny_id_maps(
    model: BodyModel,
    garment: Garment,
    qs: Float[Array, "b n_dof"],
    cam: Camera,
    size: int = TINY_SIZE,
    margin: float = TINY_MARGIN,
    chunk: int = TINY_POSE_CHUNK,
) -> UInt8[Array, "b n n"]:
    """Tiny colour-id maps of many poses (the pose database build), ``uint8``: ``vmap`` over
    ``chunk`` poses at a time, ``lax.map`` over the chunks."""

    def one(q):
        return tiny_id_map(model, garment, q, cam, size, margin).astype(jnp.uint8)

    b = qs.shape[0]
    if b <= chunk:
        return jax.vmap(one)(qs)
    n_chunks = -(-b // chunk)
    pad = n_chunks * chunk - b
    qp = jnp.concatenate([qs, jnp.broadcast_to(qs[-1:], (pad, qs.shape[1]))]) if pad else qs
    maps = jax.lax.map(jax.vmap(one), qp.reshape(n_chunks, chunk, -1))
    return maps.reshape(n_chunks * chunk, size, size)[:b]
