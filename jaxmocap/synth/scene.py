"""Scene settings of a synthetic sequence and the nuisances the papers name.

A :class:`SceneConfig` (frozen, JSON round-trip) says *what* to film: which mocap clip, which
camera rig, which garment, and which nuisances. This module turns it into plain arrays:

* the camera rig (:func:`make_cameras`): ``stereo`` reproduces Azad et al. 2007 §V (two
  cameras "at a distance of approximately eleven centimeters", 320x240, eye height);
  ``webcams`` reproduces Wang et al. 2011 §3 (two 640x480 webcams) about 1.5 m apart, 2.75 m
  from the subject and converging on it. Cameras sit at ``x = +distance`` and look back
  towards the subject, who faces ``+x`` (docs/ARCHITECTURE.md conventions);
* the static and moving props (:func:`make_props`): a textured back wall and floor, colourful
  distractor objects (some with exactly the shirt's or the skin's albedo, so that the
  histogram search of Wang §5.1 and the skin segmentation of Azad §IV meet look-alikes), a
  moving background ball, and an occluding panel that passes in front of the subject;
* the per-frame schedule (:func:`make_schedule`): the pose at every motion-blur sub-frame
  (the subject optionally walks out of the view and back), the props' positions, and the
  illuminant ``M_t`` and intensity ``I_t``.

**Illuminant** (Wang §6: "a mixture of several fluorescent ceiling lights and a tungsten floor
lamp ... even in the event when the tungsten lamp is suddenly turned off"). With the
fluorescent colour ``c_f``, the lamp colour ``c_l`` and the lamp level ``L_t``,

    M_t = diag(c_f + L_t c_l) / mean(c_f + c_l),    I_t = intensity,
    L_t = (1 + drift sin(2 pi t / period)) [t < t_off]

so the lamp's drift changes the light's colour and brightness smoothly, and switching it off
at frame ``t_off`` is a step to a dimmer, bluer light. By default the lamp gives
``mean(c_l) / mean(c_f + c_l)`` (about 48%) of the light; ``lamp_share = s`` sets its share
instead (Wang §5.2's "sudden lighting change" is stronger the larger ``s``):

    M_t = diag((1 - s) c_f / mean(c_f) + L_t s c_l / mean(c_l)),

which keeps ``mean(diag M_t) = 1`` with the lamp on at its nominal level, as above.
``intensity < 1`` is a dim scene; sensor noise is ``noise_sigma`` (fraction of 255, added
before 8-bit quantisation).
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any, NamedTuple

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from jaxmocap.body import BOX, ELLIPSOID, SPHERE
from jaxmocap.camera import Camera, look_at
from jaxmocap.errors import InputError
from jaxmocap.garment import SHIRT_COLOURS, SKIN_RGB

SCENE_JSON_VERSION = 1

# Camera rigs: (n_cameras, width, height, baseline m, distance m, height m, horizontal fov deg,
# converging). Azad et al. 2007 §V: two Dragonfly cameras ~11 cm apart in a robot head,
# 320x240. Wang et al. 2011 §3 / Fig. 1: two 640x480 USB webcams; their spacing and distance
# are not given: we take ~1.5 m apart, 2.75 m from the subject, converging on the chest.
RIGS = {
    "stereo": dict(n_cameras=2, width=320, height=240, baseline=0.11, distance=2.3,
                   camera_height=1.6, fov=55.0, converge=False),
    "webcams": dict(n_cameras=2, width=640, height=480, baseline=1.5, distance=2.75,
                    camera_height=1.3, fov=60.0, converge=True),
}  # fmt: skip
LOOK_HEIGHT = 1.15  # m, the point the rig looks at (the subject's chest; pelvis ~0.85 m)
MAX_CAMERAS = 4

# Illuminant (module docstring): fluorescent ceiling light and a tungsten floor lamp.
FLUORESCENT_RGB = (0.45, 0.50, 0.50)
TUNGSTEN_RGB = (0.65, 0.45, 0.25)
DRIFT_PERIOD = 4.0  # s, period of the lamp's smooth drift

# Props (metres, world frame: subject near the origin facing +x, cameras at +x).
WALL_X = -2.6  # the back wall is the plane x = WALL_X
MAX_DISTRACTORS = 8  # static distractor slots (fixed so that configs share one compilation)
DISTRACTOR_X = (-2.3, -0.9)  # distractors stay behind the subject
DISTRACTOR_Y = (-2.2, 2.2)
MOVER_X, MOVER_RADIUS, MOVER_SWING, MOVER_PERIOD = -1.5, 0.18, 1.2, 3.0  # moving ball
OCCLUDER_X = 1.0  # the occluding panel passes at this x, between subject and cameras
OCCLUDER_HALF = (0.03, 0.3, 0.75)  # half-extents of the panel (thin along x)
OCCLUDER_Z = 1.1
OCCLUDER_RGB = (0.55, 0.45, 0.35)  # cardboard
WALL_RGB, FLOOR_RGB = (0.62, 0.6, 0.55), (0.45, 0.42, 0.4)
TEXTURE_WAVES = 4  # sinusoids of the procedural wall texture
TILE = 0.4  # m, floor checker tile
LEAVE_MARGIN = 1.0  # m beyond the view's edge that the subject walks to

GARMENTS = ("shirt", "single")
BACKGROUNDS = ("plain", "clutter")
AZAD_SHIRT_RGB = (0.1, 0.25, 0.8)  # Azad §IV: "a solid colored shirt" (colour not given)


class SceneError(InputError):
    """An invalid scene setting (field named in the message)."""


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """Everything that defines a synthetic sequence; with the seed it regenerates it exactly.

    Motion: ``clip`` (a DeepMimic clip name, see :func:`jaxmocap.synth.list_clips`), ``fps``,
    ``start`` frame and ``n_frames`` (``None``: the whole clip; longer sequences play the
    clip back and forth). Cameras: ``rig`` preset, optionally overriding ``n_cameras`` (1–4),
    ``width``/``height`` (pixels), ``baseline`` (m between neighbouring cameras),
    ``distance`` (m from the subject) and radial distortion ``k1``. Garment: ``"shirt"``
    (Wang's 20 patches) or ``"single"`` (Azad: one ``shirt_rgb`` + skin). Nuisances:
    ``intensity`` (I, 1 = normal, < 1 dim), ``noise_sigma`` (fraction of 255), lamp
    ``drift`` (relative amplitude), ``lamp_off`` (frame of the step, or None) and
    ``lamp_share`` (the tungsten lamp's share of the light, or None for the default mix),
    ``motion_blur`` (odd number of sub-frames, 1 = none) over ``shutter`` (fraction of the
    frame interval), ``background`` (``"plain"`` or ``"clutter"``) with ``n_distractors``,
    a ``moving_object``, an ``occluder`` passing during frames ``(first, last)``, and
    ``leave_view``: the subject walks out of the view and back during ``(first, last)``.
    """

    clip: str = "humanoid3d_punch"
    fps: float = 30.0
    start: int = 0
    n_frames: int | None = None
    rig: str = "webcams"
    n_cameras: int | None = None
    width: int | None = None
    height: int | None = None
    baseline: float | None = None
    distance: float | None = None
    k1: float = 0.0
    garment: str = "shirt"
    shirt_rgb: tuple[float, float, float] = AZAD_SHIRT_RGB
    intensity: float = 1.0
    noise_sigma: float = 0.0
    drift: float = 0.0
    lamp_off: int | None = None
    lamp_share: float | None = None
    motion_blur: int = 1
    shutter: float = 0.5
    background: str = "clutter"
    n_distractors: int = 6
    moving_object: bool = False
    occluder: tuple[int, int] | None = None
    leave_view: tuple[int, int] | None = None
    colour_ids: bool = True
    seed: int = 0

    def __post_init__(self):
        _validate(dataclasses.asdict(self))

    def rig_settings(self) -> dict[str, Any]:
        """The rig preset with this config's overrides applied."""
        rig = dict(RIGS[self.rig])
        for name in ("n_cameras", "width", "height", "baseline", "distance"):
            if getattr(self, name) is not None:
                rig[name] = getattr(self, name)
        return rig

    def to_dict(self) -> dict[str, Any]:
        return settings_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "scene") -> SceneConfig:
        """Inverse of :meth:`to_dict`; unknown or ill-typed fields raise :class:`SceneError`."""
        kw = settings_kwargs(cls, d, where, "scene settings", SceneError)
        for k in _FLOAT_FIELDS & set(kw):  # JSON writes 30.0 as 30
            if _is_int(kw[k]):
                kw[k] = float(kw[k])
        if isinstance(kw.get("shirt_rgb"), tuple):
            kw["shirt_rgb"] = tuple(float(v) if _is_num(v) else v for v in kw["shirt_rgb"])
        try:
            _validate({**dataclasses.asdict(cls()), **kw})  # types too, before construction
            return cls(**kw)
        except SceneError as e:
            raise SceneError(f"{where}: {e}") from None

    def to_json(self) -> str:
        return json.dumps({"version": SCENE_JSON_VERSION, "scene": self.to_dict()}, indent=2)



def settings_to_dict(settings) -> dict[str, Any]:
    """A settings dataclass as JSON-ready fields (tuples as lists)."""
    d = dataclasses.asdict(settings)
    return {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}


def settings_kwargs(cls, d, where: str, what: str, error: type[Exception]) -> dict[str, Any]:
    """Keyword arguments of ``cls`` from a JSON object (lists as tuples); anything but an
    object, or a field ``cls`` does not have, is one ``error`` line naming ``where``."""
    if not isinstance(d, dict):
        raise error(f"{where}: expected a JSON object of {what}")
    names = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(d) - names)
    if unknown:
        raise error(f"{where}: unknown field(s) {unknown}; known: {sorted(names)}")
    return {k: tuple(v) if isinstance(v, list) else v for k, v in d.items()}

def _check(ok: bool, field: str, expected: str, value: Any) -> None:
    if not ok:
        raise SceneError(f"field {field!r}: expected {expected}, got {value!r}")


def _is_int(v: Any) -> bool:
    return isinstance(v, (int, np.integer)) and not isinstance(v, bool)


def _is_num(v: Any) -> bool:
    return isinstance(v, (int, float, np.integer, np.floating)) and not isinstance(v, bool)


_FLOAT_FIELDS = {"fps", "baseline", "distance", "k1", "intensity", "noise_sigma", "drift",
                 "shutter", "lamp_share"}


def _validate(values: dict[str, Any]) -> None:
    """Check every field's type and range (raises :class:`SceneError` naming the field)."""
    c = _Fields(values)
    _check(isinstance(c.clip, str) and bool(c.clip), "clip", "a clip name", c.clip)
    _check(_is_num(c.fps) and c.fps > 0, "fps", "a number > 0", c.fps)
    _check(_is_int(c.start) and c.start >= 0, "start", "an integer >= 0", c.start)
    _check(c.n_frames is None or (_is_int(c.n_frames) and c.n_frames >= 1), "n_frames",
           "an integer >= 1 or null", c.n_frames)
    _check(c.rig in RIGS, "rig", f"one of {sorted(RIGS)}", c.rig)
    _check(c.n_cameras is None or (_is_int(c.n_cameras) and 1 <= c.n_cameras <= MAX_CAMERAS),
           "n_cameras", f"an integer in 1..{MAX_CAMERAS}", c.n_cameras)
    for name in ("width", "height"):
        v = getattr(c, name)
        _check(v is None or (_is_int(v) and 8 <= v <= 4096), name, "an integer in 8..4096", v)
    for name in ("baseline", "distance"):
        v = getattr(c, name)
        _check(v is None or (_is_num(v) and v >= 0), name, "a number >= 0 (metres)", v)
    dist = c.distance if c.distance is not None else RIGS.get(c.rig, {}).get("distance", 1)
    _check(dist > OCCLUDER_X + 0.3, "distance", f"more than {OCCLUDER_X + 0.3} m", dist)
    _check(_is_num(c.k1) and abs(c.k1) <= 0.5, "k1", "a number in [-0.5, 0.5]", c.k1)
    _check(c.garment in GARMENTS, "garment", f"one of {list(GARMENTS)}", c.garment)
    _check(isinstance(c.shirt_rgb, tuple) and len(c.shirt_rgb) == 3
           and all(_is_num(v) and 0 <= v <= 1 for v in c.shirt_rgb),
           "shirt_rgb", "three numbers in [0, 1]", c.shirt_rgb)
    _check(_is_num(c.intensity) and 0 < c.intensity <= 4, "intensity", "a number in (0, 4]",
           c.intensity)
    _check(_is_num(c.noise_sigma) and 0 <= c.noise_sigma <= 0.5, "noise_sigma",
           "a number in [0, 0.5]", c.noise_sigma)
    _check(_is_num(c.drift) and 0 <= c.drift <= 1, "drift", "a number in [0, 1]", c.drift)
    _check(c.lamp_off is None or (_is_int(c.lamp_off) and c.lamp_off >= 0), "lamp_off",
           "a frame index >= 0 or null", c.lamp_off)
    _check(c.lamp_share is None or (_is_num(c.lamp_share) and 0 < c.lamp_share < 1),
           "lamp_share", "a number in (0, 1) or null", c.lamp_share)
    _check(_is_int(c.motion_blur) and c.motion_blur >= 1 and c.motion_blur % 2 == 1,
           "motion_blur", "an odd number of sub-frames >= 1", c.motion_blur)
    _check(_is_num(c.shutter) and 0 <= c.shutter <= 1, "shutter", "a number in [0, 1]",
           c.shutter)
    _check(c.background in BACKGROUNDS, "background", f"one of {list(BACKGROUNDS)}",
           c.background)
    _check(_is_int(c.n_distractors) and 0 <= c.n_distractors <= MAX_DISTRACTORS,
           "n_distractors", f"an integer in 0..{MAX_DISTRACTORS}", c.n_distractors)
    _check(isinstance(c.moving_object, bool), "moving_object", "true or false",
           c.moving_object)
    for name in ("occluder", "leave_view"):
        v = getattr(c, name)
        _check(v is None or (isinstance(v, tuple) and len(v) == 2 and all(map(_is_int, v))
                             and 0 <= v[0] < v[1]),
               name, "null or two frame indices (first, last) with first < last", v)
    _check(isinstance(c.colour_ids, bool), "colour_ids", "true or false", c.colour_ids)
    _check(_is_int(c.seed) and c.seed >= 0, "seed", "an integer >= 0", c.seed)


# ----------------------------------------------------------------------------- cameras


class _Fields:
    def __init__(self, values: dict[str, Any]):
        self.__dict__.update(values)


def camera_names(config: SceneConfig) -> list[str]:
    return [f"cam{i}" for i in range(config.rig_settings()["n_cameras"])]


def make_cameras(config: SceneConfig, dtype=None) -> list[Camera]:
    """The rig: ``n`` cameras on a horizontal line at ``x = distance``, ``baseline`` apart
    (centred on ``y = 0``) at ``camera_height``; converging rigs look at the chest point
    ``(0, 0, LOOK_HEIGHT)``, parallel rigs (stereo heads) look along the same axis. Focal
    length ``f = (W / 2) / tan(fov / 2)`` pixels, principal point at the image centre."""
    r = config.rig_settings()
    dtype = dtype or jnp.result_type(float)
    n, w, h = r["n_cameras"], r["width"], r["height"]
    fx = (w / 2) / math.tan(math.radians(r["fov"]) / 2)
    target = np.array([0.0, 0.0, LOOK_HEIGHT])
    cams = []
    for i in range(n):
        y = (i - (n - 1) / 2) * r["baseline"]
        eye = np.array([r["distance"], y, r["camera_height"]])
        aim = target if r["converge"] else target + np.array([0.0, y, 0.0])
        dist = np.array([config.k1, 0.0, 0.0, 0.0, 0.0])
        cams.append(look_at(jnp.asarray(eye, dtype), jnp.asarray(aim, dtype), width=w,
                            height=h, fx=fx, dist=jnp.asarray(dist, dtype)))
    return cams


def view_half_width(config: SceneConfig, depth: float) -> float:
    """Half the width (m, along y) that the rig sees at ``depth`` metres from the cameras,
    including the spread of the cameras themselves."""
    r = config.rig_settings()
    half_fov = math.radians(r["fov"]) / 2
    return depth * math.tan(half_fov) + r["baseline"] * (r["n_cameras"] - 1) / 2


# ----------------------------------------------------------------------------- props


class Props(eqx.Module):
    """The non-body scene: textured wall (plane ``x = WALL_X``) and floor (``z = 0``),
    distractor primitives (``kind`` SPHERE/BOX/ELLIPSOID, axis-aligned, ``centre``, ``size``
    as in the Geometry contract, albedo ``rgb``, ``active`` slots), the moving ball and the
    occluding panel (positions per frame live in the :class:`Schedule`).

    Wall texture: ``albedo(u) = wall_rgb + sum_i amp_i sin(k_i . u + phi_i) tint_i`` with
    ``u = (y, z)``; floor: a checker of ``TILE`` m between ``floor_rgb`` and ``floor_rgb2``."""

    wall_rgb: Float[Array, " 3"]
    wave_k: Float[Array, "w 2"]
    wave_phase: Float[Array, " w"]
    wave_amp: Float[Array, " w"]
    wave_tint: Float[Array, "w 3"]
    floor_rgb: Float[Array, " 3"]
    floor_rgb2: Float[Array, " 3"]
    kind: Int[Array, " d"]
    centre: Float[Array, "d 3"]
    size: Float[Array, "d 3"]
    rgb: Float[Array, "d 3"]
    active: Bool[Array, " d"]
    mover_radius: Float[Array, ""]
    mover_rgb: Float[Array, " 3"]
    mover_active: Bool[Array, ""]
    occluder_half: Float[Array, " 3"]
    occluder_rgb: Float[Array, " 3"]
    occluder_active: Bool[Array, ""]


def _hue_rgb(hue: float, sat: float = 0.85, val: float = 0.85) -> tuple[float, float, float]:
    import colorsys

    return colorsys.hsv_to_rgb(hue % 1.0, sat, val)


def make_props(config: SceneConfig, dtype=None) -> Props:
    """Seeded props of the scene (module docstring). ``plain`` background: a uniform wall and
    floor, no distractors. Distractor colours cycle through the shirt colours, skin, and random
    saturated hues, so several look exactly like parts of the subject."""
    dtype = dtype or jnp.result_type(float)
    rng = np.random.default_rng([config.seed, 1])
    clutter = config.background == "clutter"
    w = TEXTURE_WAVES
    wave_k = rng.uniform(1.0, 6.0, (w, 2)) * rng.choice([-1, 1], (w, 2))
    wave_phase = rng.uniform(0, 2 * np.pi, w)
    wave_amp = rng.uniform(0.08, 0.18, w) * clutter
    wave_tint = rng.uniform(-1, 1, (w, 3))
    n = config.n_distractors if clutter else 0
    palette = [np.array(rgb) for _, rgb in SHIRT_COLOURS]
    shirt_like = ([np.array(config.shirt_rgb)] if config.garment == "single"
                  else [palette[i] for i in rng.permutation(len(palette))[:3]])
    colours = shirt_like + [np.array(SKIN_RGB)]
    colours += [np.array(_hue_rgb(h)) for h in rng.uniform(0, 1, MAX_DISTRACTORS)]
    kind = np.full(MAX_DISTRACTORS, SPHERE)
    centre = np.zeros((MAX_DISTRACTORS, 3))
    size = np.zeros((MAX_DISTRACTORS, 3))
    for i in range(MAX_DISTRACTORS):
        kind[i] = (BOX, SPHERE, ELLIPSOID)[rng.integers(3)]
        half = rng.uniform(0.12, 0.35, 3)
        if kind[i] == SPHERE:
            half = np.array([half[0], 0.0, 0.0])
        x = rng.uniform(*DISTRACTOR_X)
        y = rng.uniform(*DISTRACTOR_Y)
        on_floor = rng.uniform() < 0.5
        z = (half[2] if kind[i] != SPHERE else half[0]) if on_floor else rng.uniform(0.8, 2.0)
        centre[i] = (x, y, z)
        size[i] = half
    active = np.arange(MAX_DISTRACTORS) < n
    cast = lambda a: jnp.asarray(np.asarray(a, float), dtype)
    mover_rgb = colours[0]
    return Props(
        wall_rgb=cast(WALL_RGB),
        wave_k=cast(wave_k),
        wave_phase=cast(wave_phase),
        wave_amp=cast(wave_amp),
        wave_tint=cast(wave_tint),
        floor_rgb=cast(FLOOR_RGB),
        floor_rgb2=cast(np.array(FLOOR_RGB) * (0.6 if clutter else 1.0)),
        kind=jnp.asarray(kind, jnp.int32),
        centre=cast(centre),
        size=cast(size),
        rgb=cast(np.clip(np.array(colours[:MAX_DISTRACTORS]), 0, 1)),
        active=jnp.asarray(active),
        mover_radius=cast(MOVER_RADIUS),
        mover_rgb=cast(mover_rgb),
        mover_active=jnp.asarray(config.moving_object),
        occluder_half=cast(OCCLUDER_HALF),
        occluder_rgb=cast(OCCLUDER_RGB),
        occluder_active=jnp.asarray(config.occluder is not None),
    )


# ----------------------------------------------------------------------------- schedule


class Schedule(NamedTuple):
    """Per-frame inputs of the renderer (NumPy, float64). ``q[t, s]`` is the pose at
    sub-frame ``s`` of frame ``t`` (the middle sub-frame is the frame's own pose
    ``q_frame[t]``); positions of the moving ball and the occluder per sub-frame; the
    illuminant ``M_t`` and intensity ``I_t``; frame times (s)."""

    q: np.ndarray  # (T, S, n_dof)
    q_frame: np.ndarray  # (T, n_dof)
    mover: np.ndarray  # (T, S, 3)
    occluder: np.ndarray  # (T, S, 3)
    illuminant: np.ndarray  # (T, 3, 3)
    intensity: np.ndarray  # (T,)
    times: np.ndarray  # (T,)


def illuminant_schedule(config: SceneConfig, n_frames: int) -> tuple[np.ndarray, np.ndarray]:
    """``M_t`` (T, 3, 3) and ``I_t`` (T,) of the module docstring."""
    t = np.arange(n_frames) / config.fps
    level = 1 + config.drift * np.sin(2 * np.pi * t / DRIFT_PERIOD)
    if config.lamp_off is not None:
        level = np.where(np.arange(n_frames) >= config.lamp_off, 0.0, level)
    cf, cl = np.array(FLUORESCENT_RGB), np.array(TUNGSTEN_RGB)
    if config.lamp_share is None:
        gains = (cf[None] + level[:, None] * cl[None]) / np.mean(cf + cl)
    else:
        s = float(config.lamp_share)
        gains = (1 - s) * cf[None] / np.mean(cf) + level[:, None] * (s * cl[None] / np.mean(cl))
    M = gains[:, :, None] * np.eye(3)[None]
    return M, np.full(n_frames, float(config.intensity))


def subframe_offsets(config: SceneConfig) -> np.ndarray:
    """Sub-frame times relative to the frame (in frames): ``shutter ((s + 1/2) / S - 1/2)``;
    S is odd so the middle one is 0."""
    s = config.motion_blur
    return config.shutter * ((np.arange(s) + 0.5) / s - 0.5)


def _smoothstep(x: np.ndarray) -> np.ndarray:
    x = np.clip(x, 0, 1)
    return x * x * (3 - 2 * x)


def leave_offset(config: SceneConfig, t: np.ndarray) -> np.ndarray:
    """Lateral root offset (m, +y) at (fractional) frames ``t``: out during the first third
    of ``leave_view``, out of every camera's view during the middle third, back in the last."""
    if config.leave_view is None:
        return np.zeros_like(t)
    a, b = config.leave_view
    u = (t - a) / (b - a)
    prof = np.where(u < 0.5, _smoothstep(3 * u), _smoothstep(3 * (1 - u)))
    return leave_distance(config) * prof


def leave_distance(config: SceneConfig) -> float:
    """The smallest lateral offset (m, +y, in steps of 0.25 m) that puts a box of
    ``LEAVE_MARGIN`` m around the subject's region (``|x| <= 0.8``, ``0 <= z <= 2.2``) outside
    every camera's field of view (pinhole projection)."""
    cams = make_cameras(config)
    xs, zs = np.meshgrid(np.linspace(-0.8, 0.8, 5), np.linspace(0.0, 2.2, 5))
    for step in range(1, 200):
        d = 0.25 * step
        pts = np.stack([xs.ravel(), np.full(xs.size, d - LEAVE_MARGIN), zs.ravel()], axis=1)
        seen = False
        for cam in cams:
            pc = pts @ np.asarray(cam.R, float).T + np.asarray(cam.t, float)
            u = np.asarray(cam.K, float)[0, 0] * pc[:, 0] / np.maximum(pc[:, 2], 1e-9)
            u = u + np.asarray(cam.K, float)[0, 2]
            seen |= bool(np.any((pc[:, 2] > 0) & (u < cam.width + 0.5)))
        if not seen:
            return d
    raise SceneError("leave_view: the rig sees too wide to walk out of its view")


def interpolate_poses(q: np.ndarray, t: np.ndarray) -> np.ndarray:
    """Poses at fractional frames ``t`` from per-frame poses ``q`` (T, n_dof): translation and
    joint angles linearly, the root rotation (rotation vector) along the geodesic."""
    from scipy.spatial.transform import Rotation, Slerp

    n = q.shape[0]
    tc = np.clip(t, 0, n - 1)
    k = np.clip(np.floor(tc).astype(int), 0, max(n - 2, 0))
    u = (tc - k)[..., None]
    k1 = np.minimum(k + 1, n - 1)
    out = q[k] + u * (q[k1] - q[k])
    if n > 1:
        slerp = Slerp(np.arange(n), Rotation.from_rotvec(q[:, 3:6]))
        out[..., 3:6] = slerp(tc.reshape(-1)).as_rotvec().reshape(tc.shape + (3,))
    return out


def make_schedule(config: SceneConfig, q_frames: np.ndarray) -> Schedule:
    """The per-frame schedule from the subject's poses ``q_frames`` (T, n_dof) (module
    docstring): leave-view offsets, motion-blur sub-frames, props and light."""
    q_frames = np.asarray(q_frames, np.float64)
    n = q_frames.shape[0]
    frames = np.arange(n, dtype=np.float64)
    t_sub = frames[:, None] + subframe_offsets(config)[None, :]  # (T, S)
    q = interpolate_poses(q_frames, t_sub)
    q[..., 1] += leave_offset(config, t_sub)
    q_frame = q_frames.copy()
    q_frame[:, 1] += leave_offset(config, frames)
    time = t_sub / config.fps
    phase = 2 * np.pi * time / MOVER_PERIOD
    mover = np.stack([np.full_like(time, MOVER_X), MOVER_SWING * np.sin(phase),
                      1.3 + 0.25 * np.cos(2 * phase)], axis=-1)
    if config.occluder is not None:
        a, b = config.occluder
        span = view_half_width(config, config.rig_settings()["distance"] - OCCLUDER_X)
        span += OCCLUDER_HALF[1] + 0.1
        y = -span + 2 * span * np.clip((t_sub - a) / (b - a), 0, 1)
    else:
        y = np.zeros_like(time)
    occluder = np.stack([np.full_like(time, OCCLUDER_X), y, np.full_like(time, OCCLUDER_Z)],
                        axis=-1)
    M, intensity = illuminant_schedule(config, n)
    return Schedule(q=q, q_frame=q_frame, mover=mover, occluder=occluder, illuminant=M,
                    intensity=intensity, times=frames / config.fps)
