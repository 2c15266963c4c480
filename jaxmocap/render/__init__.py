"""JAX ray caster of the body model (Wang et al. 2011 §5.2: id maps of poses, the tiny 40x40
maps of the pose database; synthetic footage for both papers' experiments).

Every geom of the body is intersected analytically in its own frame (``_intersect``); the
nearest hit per pixel gives geom id, garment patch id, colour id, depth and normal
(``_raycast``); images, crops and tiny normalised maps (``_image``); Lambert shading under a
coloured illuminant with gamma, noise and background compositing (``_shade``). All functions
are pure JAX: jit and vmap over poses and (stacked) cameras.
"""

from ._image import (
    TINY_MARGIN,
    TINY_SIZE,
    patch_surface_points,
    pixel_grid,
    render_ids,
    render_rays,
    render_uv,
    resample_ids,
    shirt_points,
    shirt_window,
    square_window,
    tiny_hits,
    tiny_id_map,
    tiny_id_maps,
    window_from_mask,
    window_uv,
)
from ._intersect import (
    intersect_box,
    intersect_capsule,
    intersect_cylinder,
    intersect_ellipsoid,
    intersect_kind,
    surface_normal,
)
from ._raycast import RAY_CHUNK, Hits, Scene, cast_rays, kind_groups, posed_scene
from ._shade import CAMERA_GAMMA, Lighting, default_lighting, encode, render_rgb, shade

__all__ = [
    "TINY_MARGIN", "TINY_SIZE", "RAY_CHUNK", "CAMERA_GAMMA", "Hits", "Scene", "Lighting",
    "cast_rays", "kind_groups", "posed_scene", "render_ids", "render_rays", "render_uv",
    "render_rgb",
    "shade", "encode", "default_lighting", "pixel_grid", "tiny_id_map", "tiny_id_maps",
    "tiny_hits", "shirt_window", "shirt_points", "patch_surface_points", "square_window",
    "window_from_mask", "window_uv", "resample_ids", "intersect_box", "intersect_capsule",
    "intersect_cylinder", "intersect_ellipsoid", "intersect_kind", "surface_normal",
]  # fmt: skip
