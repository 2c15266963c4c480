"""What a test-world sequence shows: :class:`WorldSpec` and what follows from it (body,
garment, motion, rig, lamp schedule). Pure settings and NumPy; no rendering here.

The world is for **evaluation only**: its body is the bundled body scaled / renamed /
re-primitived (:mod:`jaxmocap.body.scale`), its shirt may have another layout
(:func:`bands_garment`), its motion is a **held-out** DeepMimic clip (docs/DATA.md; the
trackers' pose database is built from the training clips), optionally turned by ``yaw``
degrees and spun at ``spin`` degrees per second about the vertical through the pelvis.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np

from jaxmocap.body import BodyModel, default_body
from jaxmocap.body.scale import (
    NAMINGS,
    ScaledBody,
    rename_body,
    scale_body,
    scale_garment,
    swap_capsules,
)
from jaxmocap.camera import Camera, look_at
from jaxmocap.errors import InputError
from jaxmocap.garment import (
    SHIRT_COLOURS,
    Garment,
    default_garment,
    default_skin_geoms,
    make_garment,
    single_colour_garment,
)
from jaxmocap.synth.motion import HELDOUT_CLIPS
from jaxmocap.synth.scene import settings_kwargs, settings_to_dict

WORLD_VERSION = 1
GARMENT_LAYOUTS = ("wang", "bands", "single", "generated")
RENDERERS = ("mujoco", "cycles")
RIG_KINDS = ("webcams", "stereo")
LAMP_COLOURS = {  # linear RGB of the lamps (warm: ~2700 K tungsten, cool: ~6500 K daylight)
    "warm": (1.0, 0.72, 0.42), "cool": (0.72, 0.85, 1.0), "neutral": (1.0, 1.0, 1.0)}
LIMBS = ("capsule", "cylinder", "box")


class WorldError(InputError):
    """An invalid world setting (field named in the message)."""


@dataclasses.dataclass(frozen=True)
class WorldSpec:
    """Everything that defines a MuJoCo test-world sequence; with the seed it renders the same
    images on the same machine (MuJoCo's software rasteriser).

    Motion: ``clip`` (held out unless ``allow_train``), ``fps``, ``start``, ``n_frames``,
    ``yaw`` (deg, the whole motion turned about z; 90 = the subject's left side faces the
    cameras) and ``spin`` (deg/s, an extra turn growing with time). Body: measurements in m
    (None: proportional), ``naming`` (:data:`jaxmocap.body.scale.NAMINGS`) and ``limbs``
    (capsule, cylinder, box); or ``body`` one of :data:`jaxmocap.body.packages.PACKAGE_BODIES`
    (a humanoid that ships in another package, loaded from its own file with its roles
    inferred; measurements, naming and limbs then stay unset). Shirt: ``garment`` (``wang``:
    the paper's layout; ``bands``: the other 20-patch / 10-colour layout; ``single``: Azad's
    one colour ``shirt_rgb`` + skin; ``generated``: drawn over the body's geometry by
    :func:`jaxmocap.garment_layout.generated_garment` from ``layout_seed``, ``n_colours``
    (null: drawn) and ``shoulders``).
    Rig: ``rig`` kind (``webcams``: 2 x 640x480 converging; ``stereo``: 320x240 parallel head)
    with ``width``, ``height``, ``distance`` (m, horizontal from the pelvis' mean position),
    ``camera_height``, ``baseline``, ``fov`` (horizontal, deg), ``converge`` (look at the
    chest or parallel axes), ``look_height``. Light: lamps ``lamps`` (colour names of
    :data:`LAMP_COLOURS`, one spot lamp each with shadows), ``lamp_off`` (frame where lamp 0
    goes out), ``dim`` (first, last, level: lamp 1 ramps to ``level`` of its power),
    ``fill`` (level of the shadowless fill light). Props: ``n_clutter`` (the first two are a red
    box and an orange ball), ``moving_object``, ``occluder`` (frames the panel crosses the
    view). Camera: ``noise_sigma`` (fraction of 255), ``motion_blur`` (odd sub-frames),
    ``shutter`` (fraction of the frame interval), ``jpeg_quality`` (None: no compression).
    Renderer: ``mujoco`` (OpenGL rasteriser) or ``cycles`` (Blender's path tracer with
    ``samples`` per pixel, :mod:`jaxmocap.synth.world.cycles`).
    """

    clip: str = "humanoid3d_punch"
    fps: float = 30.0
    start: int = 0
    n_frames: int | None = 60
    yaw: float = 0.0
    spin: float = 0.0
    height: float | None = None
    shoulder_width: float | None = None
    upper_arm: float | None = None
    forearm: float | None = None
    naming: str = "jaxmocap"
    limbs: str = "capsule"
    body: str = "scaled"
    garment: str = "wang"
    shirt_rgb: tuple[float, float, float] = (0.1, 0.25, 0.8)
    layout_seed: int = 0
    n_colours: int | None = None
    shoulders: bool = False
    rig: str = "webcams"
    width: int | None = None
    height_px: int | None = None
    distance: float | None = None
    camera_height: float | None = None
    baseline: float | None = None
    fov: float | None = None
    converge: bool | None = None
    look_height: float | None = None
    lamps: tuple[str, ...] = ("warm", "cool")
    lamp_off: int | None = None
    dim: tuple[int, int, float] | None = None
    fill: float = 0.25
    n_clutter: int = 4
    moving_object: bool = False
    occluder: tuple[int, int] | None = None
    noise_sigma: float = 0.01
    motion_blur: int = 1
    shutter: float = 0.5
    jpeg_quality: int | None = None
    renderer: str = "mujoco"
    samples: int = 32
    allow_train: bool = False
    seed: int = 0

    def __post_init__(self):
        _validate(self)

    def to_dict(self) -> dict[str, Any]:
        return settings_to_dict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any], where: str = "world") -> WorldSpec:
        kw = settings_kwargs(cls, d, where, "world settings", WorldError)
        try:
            return cls(**kw)
        except WorldError as e:
            raise WorldError(f"{where}: {e}") from None
        except TypeError as e:
            raise WorldError(f"{where}: {e}") from None

    def rig_settings(self) -> dict[str, Any]:
        """The rig preset (:data:`RIG_PRESETS`) with this spec's overrides."""
        r = dict(RIG_PRESETS[self.rig])
        for name, key in (("width", "width"), ("height_px", "height"), ("distance", "distance"),
                          ("camera_height", "camera_height"), ("baseline", "baseline"),
                          ("fov", "fov"), ("converge", "converge"),
                          ("look_height", "look_height")):
            if getattr(self, name) is not None:
                r[key] = getattr(self, name)
        return r

    def to_json(self) -> str:
        return json.dumps({"version": WORLD_VERSION, "world": self.to_dict()}, indent=2)


# The rigs of issues 17 / 18: two 640x480 cameras converging on the subject (shirt tracker),
# a 320x240 stereo head with an 11 cm baseline (particle filter; Azad et al. 2007 §V).
RIG_PRESETS = {
    "webcams": dict(width=640, height=480, distance=2.6, camera_height=1.4, baseline=1.3,
                    fov=58.0, converge=True, look_height=1.15),
    "stereo": dict(width=320, height=240, distance=2.2, camera_height=1.55, baseline=0.11,
                   fov=55.0, converge=False, look_height=1.2),
}  # fmt: skip


def _check(ok: bool, field: str, expected: str, value: Any) -> None:
    if not ok:
        raise WorldError(f"field {field!r}: expected {expected}, got {value!r}")


def _num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def _int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _validate(s: WorldSpec) -> None:
    from jaxmocap.synth.deepmimic import list_clips

    _check(s.clip in list_clips(), "clip", "a DeepMimic clip name", s.clip)
    _check(isinstance(s.allow_train, bool), "allow_train", "true or false", s.allow_train)
    _check(s.allow_train or s.clip in HELDOUT_CLIPS, "clip",
           f"a held-out clip {list(HELDOUT_CLIPS)} (the test world never shows training "
           "motion; allow_train overrides)", s.clip)
    _check(_num(s.fps) and s.fps > 0, "fps", "a number > 0", s.fps)
    _check(_int(s.start) and s.start >= 0, "start", "an integer >= 0", s.start)
    _check(s.n_frames is None or (_int(s.n_frames) and s.n_frames >= 1), "n_frames",
           "an integer >= 1 or null", s.n_frames)
    for name in ("yaw", "spin"):
        _check(_num(getattr(s, name)), name, "a number (degrees)", getattr(s, name))
    for name in ("height", "shoulder_width", "upper_arm", "forearm"):
        v = getattr(s, name)
        _check(v is None or (_num(v) and v > 0), name, "a length in m or null", v)
    _check(s.naming in NAMINGS, "naming", f"one of {sorted(NAMINGS)}", s.naming)
    _check(s.limbs in LIMBS, "limbs", f"one of {list(LIMBS)}", s.limbs)
    _check(s.garment in GARMENT_LAYOUTS, "garment", f"one of {list(GARMENT_LAYOUTS)}",
           s.garment)
    from jaxmocap.body.packages import PACKAGE_BODIES

    _check(s.body == "scaled" or s.body in PACKAGE_BODIES, "body",
           f"'scaled' or a package body of {sorted(PACKAGE_BODIES)}", s.body)
    if s.body != "scaled":
        for name in ("height", "shoulder_width", "upper_arm", "forearm"):
            _check(getattr(s, name) is None, name,
                   "null with a package body (it is used as it comes)", getattr(s, name))
        _check(s.naming == "jaxmocap" and s.limbs == "capsule", "naming/limbs",
               "the defaults with a package body (its own names and primitives)",
               (s.naming, s.limbs))
        _check(s.garment in ("generated", "single"), "garment",
               "'generated' or 'single' with a package body (the designed layouts are drawn "
               "on the bundled body's geoms)", s.garment)
    _check(_int(s.layout_seed) and s.layout_seed >= 0, "layout_seed", "an integer >= 0",
           s.layout_seed)
    _check(s.n_colours is None or (_int(s.n_colours) and 2 <= s.n_colours <= 14), "n_colours",
           "null or an integer in 2..14", s.n_colours)
    _check(isinstance(s.shoulders, bool), "shoulders", "true or false", s.shoulders)
    _check(s.renderer in RENDERERS, "renderer", f"one of {list(RENDERERS)}", s.renderer)
    _check(_int(s.samples) and 1 <= s.samples <= 4096, "samples", "an integer in 1..4096",
           s.samples)
    _check(isinstance(s.shirt_rgb, tuple) and len(s.shirt_rgb) == 3
           and all(_num(v) and 0 <= v <= 1 for v in s.shirt_rgb), "shirt_rgb",
           "three numbers in [0, 1]", s.shirt_rgb)
    _check(s.rig in RIG_KINDS, "rig", f"one of {list(RIG_KINDS)}", s.rig)
    for name in ("width", "height_px"):
        v = getattr(s, name)
        _check(v is None or (_int(v) and 16 <= v <= 2048), name, "an integer in 16..2048", v)
    for name in ("distance", "camera_height", "baseline", "look_height"):
        v = getattr(s, name)
        _check(v is None or (_num(v) and v >= 0), name, "a number >= 0 (m) or null", v)
    dist = s.rig_settings()["distance"]
    _check(dist >= 1.4, "distance", "at least 1.4 m (the occluder passes at 1.0 m)", dist)
    _check(s.fov is None or (_num(s.fov) and 10 <= s.fov <= 120), "fov",
           "a number in [10, 120] (deg)", s.fov)
    _check(s.converge is None or isinstance(s.converge, bool), "converge", "true/false/null",
           s.converge)
    _check(isinstance(s.lamps, tuple) and 1 <= len(s.lamps) <= 4
           and all(c in LAMP_COLOURS for c in s.lamps), "lamps",
           f"1 to 4 lamp colours of {sorted(LAMP_COLOURS)}", s.lamps)
    _check(s.lamp_off is None or (_int(s.lamp_off) and s.lamp_off >= 0), "lamp_off",
           "a frame index >= 0 or null", s.lamp_off)
    _check(s.dim is None or (isinstance(s.dim, tuple) and len(s.dim) == 3 and _int(s.dim[0])
                             and _int(s.dim[1]) and 0 <= s.dim[0] <= s.dim[1]
                             and _num(s.dim[2]) and 0 <= s.dim[2] <= 1 and len(s.lamps) >= 2),
           "dim", "null or (first, last, level in [0, 1]) with at least two lamps", s.dim)
    _check(_num(s.fill) and 0 <= s.fill <= 1, "fill", "a number in [0, 1]", s.fill)
    _check(_int(s.n_clutter) and 0 <= s.n_clutter <= 8, "n_clutter", "an integer in 0..8",
           s.n_clutter)
    _check(isinstance(s.moving_object, bool), "moving_object", "true or false",
           s.moving_object)
    _check(s.occluder is None or (isinstance(s.occluder, tuple) and len(s.occluder) == 2
                                  and all(map(_int, s.occluder))
                                  and 0 <= s.occluder[0] < s.occluder[1]),
           "occluder", "null or frames (first, last) with first < last", s.occluder)
    _check(_num(s.noise_sigma) and 0 <= s.noise_sigma <= 0.5, "noise_sigma",
           "a number in [0, 0.5]", s.noise_sigma)
    _check(_int(s.motion_blur) and s.motion_blur >= 1 and s.motion_blur % 2 == 1,
           "motion_blur", "an odd number of sub-frames >= 1", s.motion_blur)
    _check(_num(s.shutter) and 0 <= s.shutter <= 1, "shutter", "a number in [0, 1]", s.shutter)
    _check(s.jpeg_quality is None or (_int(s.jpeg_quality) and 5 <= s.jpeg_quality <= 100),
           "jpeg_quality", "null or an integer in 5..100", s.jpeg_quality)
    _check(_int(s.seed) and s.seed >= 0, "seed", "an integer >= 0", s.seed)


# ----------------------------------------------------------------------------- body, shirt


def world_body(spec: WorldSpec) -> tuple[ScaledBody, BodyModel]:
    """(the scaled body with the library's names, the body as the world shows it: renamed and
    with its limb primitives). Both share chain order, DOF order and geom order. A package
    body is both, unscaled (factors 1)."""
    if spec.body != "scaled":
        from jaxmocap.body.packages import package_body

        model = package_body(spec.body)
        ones = np.ones((len(model.geometry.names), 3))
        return ScaledBody(model, {}, 1.0, ones), model
    sb = scale_body(height=spec.height, shoulder_width=spec.shoulder_width,
                    upper_arm=spec.upper_arm, forearm=spec.forearm)
    shown = rename_body(swap_capsules(sb.model, spec.limbs), spec.naming)
    return sb, shown


# The other shirt (issue 16 item 6): 20 patches / 10 colours of Wang's palette, each used
# twice, laid out differently from DEFAULT_SHIRT: thorax in three horizontal bands (upper and
# lower split front/back, middle split left/right), abdomen in two bands, whole shoulder caps,
# upper arms split outer/inner (along the arm), forearms front/back. Geom frames of the
# bundled body (x forward, y left, z up; shoulders capsule z = link -y).
BAND_Z = 0.06  # m, half height of the thorax's middle band (thorax c = 0.17)
_F, _B = (-1.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)  # x >= 0 / x <= 0
_L, _R = (0.0, -1.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)  # y >= 0 / y <= 0
_ABOVE, _BELOW = (0.0, 0.0, -1.0, BAND_Z), (0.0, 0.0, 1.0, BAND_Z)  # z >= +b / z <= -b
_MID_HI, _MID_LO = (0.0, 0.0, 1.0, -BAND_Z), (0.0, 0.0, -1.0, -BAND_Z)  # |z| <= b
_ZUP, _ZDOWN = (0.0, 0.0, -1.0, 0.0), (0.0, 0.0, 1.0, 0.0)  # z >= 0 / z <= 0
BANDS_SHIRT = (
    ("thorax_upper_front", "thorax", (_ABOVE, _F), "blue"),
    ("thorax_upper_back", "thorax", (_ABOVE, _B), "green"),
    ("thorax_middle_left", "thorax", (_MID_HI, _MID_LO, _L), "yellow"),
    ("thorax_middle_right", "thorax", (_MID_HI, _MID_LO, _R), "purple"),
    ("thorax_lower_front", "thorax", (_BELOW, _F), "magenta"),
    ("thorax_lower_back", "thorax", (_BELOW, _B), "cyan"),
    ("abdomen_upper_front", "abdomen", (_ZUP, _F), "lime"),
    ("abdomen_upper_back", "abdomen", (_ZUP, _B), "pink"),
    ("abdomen_lower_left", "abdomen", (_ZDOWN, _L), "orange"),
    ("abdomen_lower_right", "abdomen", (_ZDOWN, _R), "red"),
    ("shoulder_left", "shoulders", (_ZDOWN,), "red"),
    ("shoulder_right", "shoulders", (_ZUP,), "orange"),
    ("l_upper_arm_outer", "l_upper_arm", (_L,), "cyan"),
    ("l_upper_arm_inner", "l_upper_arm", (_R,), "lime"),
    ("r_upper_arm_outer", "r_upper_arm", (_R,), "magenta"),
    ("r_upper_arm_inner", "r_upper_arm", (_L,), "pink"),
    ("l_forearm_front", "l_forearm", (_F,), "purple"),
    ("l_forearm_back", "l_forearm", (_B,), "blue"),
    ("r_forearm_front", "r_forearm", (_F,), "yellow"),
    ("r_forearm_back", "r_forearm", (_B,), "green"),
)


def bands_garment(model: BodyModel | None = None) -> Garment:
    """The other 20-patch / 10-colour shirt (``BANDS_SHIRT``) on the bundled body's geoms."""
    model = default_body() if model is None else model
    ids = {name: i + 1 for i, (name, _) in enumerate(SHIRT_COLOURS)}
    patches = [(n, g, hs, ids[c]) for n, g, hs, c in BANDS_SHIRT]
    return make_garment(model, patches, SHIRT_COLOURS, default_skin_geoms(model))


def world_garment(spec: WorldSpec, sb: ScaledBody) -> Garment:
    """The spec's shirt, laid out on the bundled body and stretched with the scaled geoms
    (:func:`jaxmocap.body.scale.scale_garment`); geom indices are those of every variant of the
    body (renaming and primitive swaps keep geom order)."""
    base = default_body()
    if spec.garment == "single":
        return single_colour_garment(sb.model, spec.shirt_rgb)
    if spec.garment == "generated":
        from jaxmocap.garment_layout import generated_garment

        return generated_garment(sb.model, spec.layout_seed, shoulders=spec.shoulders,
                                 n_colours=spec.n_colours)
    g = default_garment(base) if spec.garment == "wang" else bands_garment(base)
    return scale_garment(g, sb.geom_scale)


# ----------------------------------------------------------------------------- motion


def world_motion(spec: WorldSpec, sb: ScaledBody) -> np.ndarray:
    """Poses (T, n_dof) of the scaled body: the clip retargeted (:func:`clip_poses`, its root
    path centred), root translation scaled with the body (a shorter subject's pelvis is lower
    and its steps shorter), then turned by ``yaw + spin t`` about the vertical through the
    clip's centre."""
    from scipy.spatial.transform import Rotation

    from jaxmocap.synth.scene import SceneConfig
    from jaxmocap.synth.sequence import clip_poses

    cfg = SceneConfig(clip=spec.clip, fps=float(spec.fps), start=spec.start,
                      n_frames=spec.n_frames, seed=spec.seed)
    q = clip_poses(cfg, sb.model).copy()
    q[:, 0:3] *= sb.root_scale
    t = np.arange(q.shape[0]) / spec.fps
    psi = np.radians(spec.yaw + spec.spin * t)
    rz = Rotation.from_euler("z", psi[:, None])
    q[:, 0:3] = rz.apply(q[:, 0:3])
    q[:, 3:6] = (rz * Rotation.from_rotvec(q[:, 3:6])).as_rotvec()
    return q


# ----------------------------------------------------------------------------- rig, light


def world_cameras(spec: WorldSpec) -> list[Camera]:
    """Two cameras on a horizontal line at ``x = distance``, ``baseline`` apart, at
    ``camera_height``; converging ones look at ``(0, 0, look_height)``, parallel ones along -x
    (pitched to the look height). Square pixels, centred principal point, no distortion (what
    MuJoCo's pinhole camera can render exactly), ``f = (W / 2) / tan(fov / 2)``."""
    r = spec.rig_settings()
    w, h = int(r["width"]), int(r["height"])
    f = (w / 2) / math.tan(math.radians(r["fov"]) / 2)
    target = np.array([0.0, 0.0, r["look_height"]])
    cams = []
    for i in range(2):
        y = (i - 0.5) * r["baseline"]
        eye = np.array([r["distance"], y, r["camera_height"]])
        aim = target if r["converge"] else target + np.array([0.0, y, 0.0])
        cams.append(look_at(eye, aim, width=w, height=h, fx=f))
    return cams


def lamp_levels(spec: WorldSpec, n_frames: int) -> np.ndarray:
    """Power of each lamp per frame (T, n_lamps) in [0, 1]: lamp 0 off from ``lamp_off``,
    lamp 1 ramping linearly to ``dim[2]`` over frames ``dim[0]..dim[1]``."""
    k = np.arange(n_frames)
    lv = np.ones((n_frames, len(spec.lamps)))
    if spec.lamp_off is not None:
        lv[k >= spec.lamp_off, 0] = 0.0
    if spec.dim is not None:
        a, b, level = spec.dim
        u = np.clip((k - a) / max(b - a, 1), 0, 1)
        lv[:, 1] *= 1 - (1 - level) * u
    return lv
