"""Rendering a synthetic sequence with ground truth, in memory.

:func:`render_sequence` films the retargeted mocap clip of a :class:`SceneConfig` with its
camera rig and nuisances (:mod:`jaxmocap.synth.scene`) and returns a :class:`Sequence`:
``uint8`` RGB frames ``(T, n_cams, H, W, 3)``, the cameras, and the ground truth (joint angles,
3D keypoints, per-camera patch / colour id maps, the illuminant, visibility flags).

One frame (:func:`render_frame`, jitted once per image size and sub-frame count, ``vmap``
over the cameras) ray-casts, per pixel ray ``o + t d``:

* the body (:func:`jaxmocap.render.cast_rays`) at each motion-blur sub-frame pose;
* the props: wall plane, floor plane, distractors, the moving ball and the occluding panel
  (analytic primitives of :mod:`jaxmocap.render`);

the nearest surface wins. Its linear colour under the frame's lighting is (Lambert, as
:func:`jaxmocap.render.shade`) ``c = I M (rho (a + sum_l L_l max(0, n . l_l)))``. The blurred
linear image is the mean over sub-frames; the camera then encodes
``v = clip(mean c, 0, 1)^(1 / gamma) + sigma N(0, 1)``, quantised to 8 bits.

Ground-truth id maps are those of the frame's own pose (the middle sub-frame) **after
occlusion**: a body pixel hidden by the panel (or any prop) gets id 0. ``visible[t, c]`` says
whether any body pixel falls in camera c's image (ignoring the props), and
``occluded_fraction`` is the fraction of those pixels that props hide.
"""

from __future__ import annotations

from functools import cache
from typing import Any, NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, PRNGKeyArray, UInt8

from jaxmocap import render
from jaxmocap.body import BOX, SPHERE, BodyModel, default_body, keypoints
from jaxmocap.camera import Camera, pixel_rays, stack_cameras
from jaxmocap.garment import Garment, albedo, default_garment, single_colour_garment
from jaxmocap.synth.scene import (
    TILE,
    WALL_X,
    Props,
    SceneConfig,
    SceneError,
    Schedule,
    camera_names,
    make_cameras,
    make_props,
    make_schedule,
)

GAMMA = render.CAMERA_GAMMA


class Sequence(NamedTuple):
    """A rendered sequence: ``frames`` ``uint8`` (T, n_cams, H, W, 3) RGB, the cameras and
    their names, the ground truth (see :func:`render_sequence`) and the config."""

    frames: np.ndarray
    cameras: list[Camera]
    camera_names: list[str]
    groundtruth: dict[str, np.ndarray]
    config: SceneConfig


class FrameOut(NamedTuple):
    rgb: UInt8[Array, "c h w 3"]
    patch_ids: UInt8[Array, "c h w"]
    colour_ids: UInt8[Array, "c h w"]
    body_pixels: Array  # (c,) int: body pixels ignoring props
    visible_pixels: Array  # (c,) int: body pixels after occlusion by props


# ----------------------------------------------------------------------------- motion


@cache
def garment_for(kind: str, shirt_rgb: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Garment:
    """The preset garment on the bundled body (cached: one object per preset)."""
    model = default_body()
    if kind == "shirt":
        return default_garment(model)
    return single_colour_garment(model, shirt_rgb)


def config_garment(config: SceneConfig) -> Garment:
    return garment_for("shirt") if config.garment == "shirt" else garment_for(
        "single", tuple(float(v) for v in config.shirt_rgb))


def clip_poses(config: SceneConfig, model: BodyModel | None = None) -> np.ndarray:
    """The subject's pose per frame (T, n_dof): the clip retargeted to the body at
    ``config.fps``, played back and forth for long sequences, from frame ``start``, with the
    root's horizontal path over the whole clip centred on the origin (the rig looks there)."""
    from jaxmocap.synth.deepmimic import load_deepmimic
    from jaxmocap.synth.motion import clip_to_body_q

    model = default_body() if model is None else model
    try:
        clip = load_deepmimic(config.clip, dtype=np.float64)
    except FileNotFoundError as e:
        raise SceneError(f"field 'clip': {e}") from None
    q = np.array(clip_to_body_q(clip, model, fps=config.fps).q, np.float64)
    n_clip = q.shape[0]
    n = config.n_frames if config.n_frames is not None else max(n_clip - config.start, 0)
    if n < 1:
        raise SceneError(f"field 'start': {config.start} is past the clip's {n_clip} frames")
    k = config.start + np.arange(n)
    period = max(2 * (n_clip - 1), 1)
    k = k % period
    k = np.where(k < n_clip, k, period - k)  # ping-pong
    xy = q[:, :2]
    q[:, :2] = xy - (xy.min(axis=0) + xy.max(axis=0)) / 2  # whole clip: same for any window
    return q[k]


# ----------------------------------------------------------------------------- one frame


def _lambert(
    rho: Float[Array, "n 3"], normal: Float[Array, "n 3"], lighting: render.Lighting
) -> Float[Array, "n 3"]:
    """``I M (rho (a + sum_l L_l max(0, n . l_l)))`` (point lights ignored for the props)."""
    lit = lighting.ambient + jnp.maximum(normal @ lighting.directions.T, 0) @ lighting.dir_intensity
    return lighting.intensity * (rho * lit[:, None]) @ lighting.illuminant.T


def _plane_t(o: Array, d: Array, axis: int, value: float) -> Array:
    """Distance along unit rays to the plane ``x_axis = value`` (+inf if behind / parallel)."""
    dn = d[:, axis]
    safe = jnp.where(jnp.abs(dn) > 1e-12, dn, 1.0)
    t = (value - o[axis]) / safe
    return jnp.where((jnp.abs(dn) > 1e-12) & (t > 0), t, jnp.inf)


def _prop_hits(props: Props, o: Array, d: Array, mover: Array, occluder: Array):
    """Nearest prop per ray: distance ``t`` (n,), linear albedo (n, 3), world normal (n, 3),
    and whether the occluder/mover/distractor won (for the body ids)."""
    n = d.shape[0]
    dt = d.dtype
    # wall and floor
    t_wall = _plane_t(o, d, 0, WALL_X)
    t_floor = _plane_t(o, d, 2, 0.0)
    o1 = o[None, :]
    p_wall = o1 + jnp.where(jnp.isfinite(t_wall), t_wall, 0)[:, None] * d
    p_floor = o1 + jnp.where(jnp.isfinite(t_floor), t_floor, 0)[:, None] * d
    uv = p_wall[:, 1:3]
    waves = jnp.sin(uv @ props.wave_k.T + props.wave_phase[None])  # (n, w)
    wall_rgb = props.wall_rgb[None] + (waves * props.wave_amp[None]) @ props.wave_tint
    checker = (jnp.floor(p_floor[:, 0] / TILE) + jnp.floor(p_floor[:, 1] / TILE)) % 2
    floor_rgb = jnp.where(checker[:, None] > 0, props.floor_rgb2[None], props.floor_rgb[None])
    # primitives: distractors + mover (sphere) + occluder (box), axis-aligned
    kinds = jnp.concatenate([props.kind, jnp.asarray([SPHERE, BOX], jnp.int32)])
    centres = jnp.concatenate([props.centre, mover[None], occluder[None]])
    r = props.mover_radius
    zero = jnp.zeros((), dt)
    sizes = jnp.concatenate([props.size, jnp.stack([r, zero, zero])[None],
                             props.occluder_half[None]])
    rgbs = jnp.concatenate([props.rgb, props.mover_rgb[None], props.occluder_rgb[None]])
    active = jnp.concatenate([props.active, props.mover_active[None],
                              props.occluder_active[None]])
    m = kinds.shape[0]
    o_loc = o[None, None, :] - centres[None]  # (1, m, 3)
    t_prim = render.intersect_kind(
        None, jnp.broadcast_to(sizes[None], (n, m, 3)), jnp.broadcast_to(o_loc, (n, m, 3)),
        jnp.broadcast_to(d[:, None, :], (n, m, 3)), kind_array=jnp.broadcast_to(kinds, (n, m)))
    t_prim = jnp.where(active[None], t_prim, jnp.inf)
    row = jnp.argmin(t_prim, axis=1)
    t_obj = jnp.min(t_prim, axis=1)
    p_loc = o1 - centres[row] + jnp.where(jnp.isfinite(t_obj), t_obj, 0)[:, None] * d
    n_obj = render.surface_normal(kinds[row], sizes[row], p_loc)
    # nearest of the three
    t_all = jnp.stack([t_wall, t_floor, t_obj], axis=1)
    which = jnp.argmin(t_all, axis=1)
    t = jnp.min(t_all, axis=1)
    e0 = jnp.asarray([[1.0, 0.0, 0.0]], dt)
    e2 = jnp.asarray([[0.0, 0.0, 1.0]], dt)
    normal = jnp.where((which == 0)[:, None], e0, jnp.where((which == 1)[:, None], e2, n_obj))
    rho = jnp.where((which == 0)[:, None], wall_rgb,
                    jnp.where((which == 1)[:, None], floor_rgb, rgbs[row]))
    return t, jnp.clip(rho, 0, 1), normal


def render_frame(
    model: BodyModel,
    garment: Garment,
    props: Props,
    cams: Camera,
    q: Float[Array, "s n_dof"],
    mover: Float[Array, "s 3"],
    occluder: Float[Array, "s 3"],
    lighting: render.Lighting,
    noise_sigma: Float[Array, ""],
    key: PRNGKeyArray,
) -> FrameOut:
    """One frame in every (stacked) camera: ``s`` motion-blur sub-frames (the middle one is
    the frame's pose and gives the ground truth), see the module docstring."""
    n_sub = q.shape[0]
    h, w = cams.height, cams.width
    keys = jax.random.split(key, cams.K.shape[0])

    def one_camera(cam: Camera, k: PRNGKeyArray):
        uv = render.pixel_grid(w, h, dtype=q.dtype).reshape(-1, 2)
        origins, dirs = pixel_rays(cam, uv)
        o = origins[0]

        def sub(args):
            q_s, mover_s, occ_s = args
            scene = render.posed_scene(model, q_s)
            hits = render.cast_rays(scene, garment, o, dirs)
            t_p, rho_p, n_p = _prop_hits(props, o, dirs, mover_s, occ_s)
            body_front = hits.t < t_p
            rho_b = albedo(garment, hits.geom, hits.patch).astype(q.dtype)
            front = body_front[:, None]
            linear = _lambert(jnp.where(front, rho_b, rho_p),
                              jnp.where(front, hits.normal, n_p), lighting)
            return linear, hits.patch, hits.colour, body_front, ~hits.background

        linear, patch, colour, front, body = jax.lax.map(sub, (q, mover, occluder))
        mid = n_sub // 2
        v = jnp.clip(jnp.mean(linear, axis=0), 0, 1) ** (1 / GAMMA)
        v = v + noise_sigma * jax.random.normal(k, v.shape, v.dtype)
        rgb = jnp.round(jnp.clip(v, 0, 1) * 255).astype(jnp.uint8).reshape(h, w, 3)
        shown = front[mid]
        pid = jnp.where(shown, patch[mid], 0).astype(jnp.uint8).reshape(h, w)
        cid = jnp.where(shown, colour[mid], 0).astype(jnp.uint8).reshape(h, w)
        return rgb, pid, cid, jnp.sum(body[mid]), jnp.sum(shown)

    rgb, pid, cid, n_body, n_shown = jax.vmap(one_camera)(cams, keys)
    return FrameOut(rgb, pid, cid, n_body, n_shown)


_RENDERERS: dict[tuple[int, int], tuple[Any, Any, Any]] = {}


def frame_renderer(model: BodyModel, garment: Garment):
    """``jit(render_frame)`` closed over ``model`` and ``garment`` (so geom kinds are static
    and each ray runs only its primitive's test); cached per (model, garment) object, so one
    compilation serves every config with the same image size, cameras and sub-frames."""
    key = (id(model), id(garment))
    if key not in _RENDERERS:
        fn = eqx.filter_jit(lambda *a: render_frame(model, garment, *a))
        _RENDERERS[key] = (model, garment, fn)  # keep both alive so ids stay unique
    return _RENDERERS[key][2]


def frame_lighting(schedule: Schedule, t: int, dtype) -> render.Lighting:
    base = render.default_lighting(dtype)
    return eqx.tree_at(lambda lt: (lt.illuminant, lt.intensity), base,
                       (jnp.asarray(schedule.illuminant[t], dtype),
                        jnp.asarray(schedule.intensity[t], dtype)))


# ----------------------------------------------------------------------------- sequence


def render_sequence(
    config: SceneConfig,
    dtype=None,
    progress: bool = False,
    q_frames: np.ndarray | None = None,
) -> Sequence:
    """Render ``config`` in memory (deterministic given ``config.seed``).

    ``q_frames`` (T, n_dof) replaces the clip's motion (e.g. poses from an experiment);
    ``progress`` shows a tqdm bar. Ground truth (NumPy):

    * ``q`` (T, n_dof) joint angles of the frame (after the leave-view offset), ``dof_names``;
    * ``keypoints`` (T, n_kp, 3) world positions (m), ``keypoint_names``;
    * ``patch_ids`` (T, n_cams, H, W) ``uint8`` (0 background or hidden), ``colour_ids``
      (same, only when ``config.colour_ids``);
    * ``illuminant`` (T, 3, 3) colour matrix M_t and ``intensity`` (T,) I_t;
    * ``visible`` (T, n_cams) bool, ``occluded_fraction`` (T, n_cams), ``body_pixels``
      (T, n_cams); ``times`` (T,) seconds.
    """
    dtype = dtype or jnp.result_type(float)
    model = default_body()
    garment = config_garment(config)
    q_src = clip_poses(config, model) if q_frames is None else np.asarray(q_frames, np.float64)
    if q_src.ndim != 2 or q_src.shape[1] != model.n_dof:
        raise SceneError(f"q_frames: expected shape (T, {model.n_dof}), got {q_src.shape}")
    schedule = make_schedule(config, q_src)
    cams_list = make_cameras(config, dtype)
    cams = stack_cameras(cams_list)
    props = make_props(config, dtype)
    fn = frame_renderer(model, garment)
    base_key = jax.random.key(config.seed)
    sigma = jnp.asarray(config.noise_sigma, dtype)
    n = schedule.q.shape[0]
    outs = []
    frames_iter = range(n)
    if progress:
        from tqdm import tqdm

        frames_iter = tqdm(frames_iter, desc="synth", unit="frame")
    for t in frames_iter:
        out = fn(props, cams, jnp.asarray(schedule.q[t], dtype),
                 jnp.asarray(schedule.mover[t], dtype), jnp.asarray(schedule.occluder[t], dtype),
                 frame_lighting(schedule, t, dtype), sigma, jax.random.fold_in(base_key, t))
        outs.append(jax.device_get(out))
    body = np.stack([o.body_pixels for o in outs]).astype(np.int64)
    shown = np.stack([o.visible_pixels for o in outs]).astype(np.int64)
    kp = jax.jit(jax.vmap(lambda q: keypoints(model, q)))(jnp.asarray(schedule.q_frame, dtype))
    gt = {
        "q": schedule.q_frame.astype(np.dtype(dtype)),
        "dof_names": np.array(model.chain.dof_names),
        "keypoints": np.asarray(kp),
        "keypoint_names": np.array(model.keypoint_names),
        "patch_ids": np.stack([o.patch_ids for o in outs]),
        "illuminant": schedule.illuminant.astype(np.dtype(dtype)),
        "intensity": schedule.intensity.astype(np.dtype(dtype)),
        "visible": body > 0,
        "occluded_fraction": np.where(body > 0, 1 - shown / np.maximum(body, 1), 0.0),
        "body_pixels": body,
        "times": schedule.times,
    }
    if config.colour_ids:
        gt["colour_ids"] = np.stack([o.colour_ids for o in outs])
    frames = np.stack([o.rgb for o in outs])
    return Sequence(frames=frames, cameras=cams_list, camera_names=camera_names(config),
                    groundtruth=gt, config=config)
