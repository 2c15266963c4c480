"""The MuJoCo scene of a test-world sequence: body with the shirt as patch meshes, room,
lamps, props and cameras, as one MJCF document.

**Shirt.** MuJoCo colours whole geoms, a garment patch is part of a geom (half-spaces in the
geom frame, :mod:`jaxmocap.garment`). Every body geom is tessellated in its own frame
(:func:`tessellate`: UV spheres / ellipsoids, capsules as a cylinder with two hemispheres,
cylinders and boxes with subdivided caps and faces, each face with its own vertices so edges
stay sharp), each triangle is given the patch of its centroid (:func:`jaxmocap.garment.patch_at`),
and the triangles of one patch become one mesh geom with the patch colour; the rest of a geom is
skin (skin geoms) or the neutral body colour. Geom names ``p<patch>_<k>`` (patch id, body geom
index) let the renderer map MuJoCo's segmentation back to patch ids.

**Colours.** Our albedos are linear RGB; MuJoCo's fixed-function lighting works on the
``rgba`` values as they are displayed, so every albedo is written gamma-encoded
(``rgb^(1/2.2)``), as our renderer's camera encodes its linear light.

**Light.** Headlight off. Spot lamps (one per ``spec.lamps`` colour) high in front of the
subject, left and right, with shadows (``castshadow``), specular highlights and a small ambient
term; a shadowless directional fill light (``spec.fill``); their power per frame is set on
the compiled model (``light_diffuse`` / ``light_specular`` / ``light_ambient``), see
:func:`jaxmocap.synth.world.spec.lamp_levels`. Materials: shirt with a mild sheen, skin, a
glossy ball, a floor with a checker texture and a little reflectance (MuJoCo's planar
reflection), textured walls.

**Cameras.** A MuJoCo camera is a pinhole looking along its -z with y up: ``xyaxes`` are
OpenCV's ``x`` and ``-y`` rows of ``R``, ``fovy = 2 atan((H / 2) / f_y)``; square pixels and a
centred principal point ``((W - 1) / 2, (H - 1) / 2)`` are required (checked), which is what
``fovy`` can express.
"""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxmocap.body import BOX, CAPSULE, CYLINDER, ELLIPSOID, SPHERE, BodyModel
from jaxmocap.body.write import matrix_quat, mjcf_body
from jaxmocap.camera import Camera
from jaxmocap.garment import SHIRT_COLOURS, SKIN_RGB, Garment, patch_at
from jaxmocap.synth.world.spec import LAMP_COLOURS, WorldError, WorldSpec

GAMMA = 2.2
PROP_GROUP = 3  # MuJoCo geom group of the room and props (hidden for the body-only pass)
ROOM = dict(wall_x=-2.6, side_y=3.2, ceiling=3.0)
OCCLUDER_X, OCCLUDER_HALF, OCCLUDER_Z = 1.0, (0.03, 0.3, 0.75), 1.1
MOVER_X, MOVER_R, MOVER_SWING, MOVER_PERIOD = -1.4, 0.16, 1.2, 3.0
FLOOR_RGB = ((0.52, 0.48, 0.44), (0.36, 0.33, 0.31))  # the floor's checker, display values
SEGMENTS = (40, 20)  # tessellation: around, along (half-sphere latitudes / rings)


def _enc(rgb) -> str:
    """Gamma-encoded ``rgba`` text of a linear RGB albedo."""
    c = np.clip(np.asarray(rgb, float), 0, 1) ** (1 / GAMMA)
    return " ".join(f"{v:.5f}" for v in c) + " 1"


def _f(v) -> str:
    return " ".join(repr(float(x)) for x in np.asarray(v, float).reshape(-1))


# ----------------------------------------------------------------------------- tessellation


def _grid(points: np.ndarray, wrap: bool) -> np.ndarray:
    """Triangles of a (rows, cols) vertex grid (indices into ``points.reshape(-1, 3)``)."""
    r, c = points.shape[:2]
    idx = np.arange(r * c).reshape(r, c)
    cols = c if wrap else c - 1
    tris = []
    for i in range(r - 1):
        for j in range(cols):
            a, b = idx[i, j], idx[i, (j + 1) % c]
            d, e = idx[i + 1, j], idx[i + 1, (j + 1) % c]
            tris += [(a, b, e), (a, e, d)]
    return np.array(tris, np.int64)


def _merge(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    verts, faces, n = [], [], 0
    for v, f in parts:
        verts.append(v.reshape(-1, 3))
        faces.append(f + n)
        n += verts[-1].shape[0]
    return np.concatenate(verts), np.concatenate(faces)


def _orient(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Faces wound counter-clockwise seen from outside (normal away from the geom centre;
    every tessellated primitive is convex and centred at its frame origin)."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    n = np.cross(b - a, c - a)
    flip = np.sum(n * (a + b + c), axis=1) < 0
    f = f.copy()
    f[flip] = f[flip][:, ::-1]
    return f


def tessellate(kind: int, size: np.ndarray, segments: tuple[int, int] = SEGMENTS
               ) -> tuple[np.ndarray, np.ndarray]:
    """Vertices (n, 3) and outward triangles (m, 3) of a primitive in its geom frame
    (sizes as :mod:`jaxmocap.body.geometry`)."""
    n_u, n_v = segments
    u = np.linspace(0, 2 * np.pi, n_u, endpoint=False)
    if kind in (SPHERE, ELLIPSOID):
        radii = np.full(3, size[0]) if kind == SPHERE else np.asarray(size, float)
        lat = np.linspace(-np.pi / 2, np.pi / 2, n_v + 1)
        p = np.stack([np.cos(lat)[:, None] * np.cos(u), np.cos(lat)[:, None] * np.sin(u),
                      np.sin(lat)[:, None] * np.ones_like(u)], -1) * radii
        v, f = p.reshape(-1, 3), _grid(p, wrap=True)
    elif kind == CAPSULE:
        r, h = size[0], size[1]
        lat_lo = np.linspace(-np.pi / 2, 0, n_v // 2 + 1)
        lat_hi = np.linspace(0, np.pi / 2, n_v // 2 + 1)
        side = np.linspace(-h, h, max(n_v // 2, 2) + 1)[1:-1]
        z = np.concatenate([r * np.sin(lat_lo) - h, side, r * np.sin(lat_hi) + h])
        rad = np.concatenate([r * np.cos(lat_lo), np.full(side.size, r), r * np.cos(lat_hi)])
        p = np.stack([rad[:, None] * np.cos(u), rad[:, None] * np.sin(u),
                      z[:, None] * np.ones_like(u)], -1)
        v, f = p.reshape(-1, 3), _grid(p, wrap=True)
    elif kind == CYLINDER:
        r, h = size[0], size[1]
        z = np.linspace(-h, h, n_v + 1)
        side = np.stack([r * np.cos(u) * np.ones_like(z)[:, None],
                         r * np.sin(u) * np.ones_like(z)[:, None],
                         z[:, None] * np.ones_like(u)], -1)
        parts = [(side, _grid(side, wrap=True))]
        rad = np.linspace(0, r, n_v // 4 + 2)[1:]
        for zc in (-h, h):
            disc = np.stack([rad[:, None] * np.cos(u), rad[:, None] * np.sin(u),
                             np.full((rad.size, n_u), zc)], -1)
            centre = np.array([[0.0, 0.0, zc]])
            fan = np.array([(0, 1 + j, 1 + (j + 1) % n_u) for j in range(n_u)])
            parts.append((np.concatenate([centre, disc.reshape(-1, 3)]),
                          np.concatenate([fan, _grid(disc, wrap=True) + 1])))
        v, f = _merge(parts)
    elif kind == BOX:
        s = np.asarray(size, float)
        n = max(n_v // 2, 4)
        t = np.linspace(-1, 1, n + 1)
        parts = []
        for ax in range(3):
            for sign in (-1.0, 1.0):
                a, b = [k for k in range(3) if k != ax]
                p = np.zeros((n + 1, n + 1, 3))
                p[..., ax] = sign
                p[..., a], p[..., b] = np.meshgrid(t, t, indexing="ij")
                parts.append((p * s, _grid(p, wrap=False)))
        v, f = _merge(parts)
    else:
        raise ValueError(f"tessellate: unknown geom kind {kind}")
    return v, _orient(v, f)


class PatchMesh(NamedTuple):
    """One mesh geom of the body: body geom index, patch id (0: skin / body colour),
    vertices (geom frame) and faces."""

    geom: int
    patch: int
    vertices: np.ndarray
    faces: np.ndarray


def patch_meshes(model: BodyModel, garment: Garment, segments=SEGMENTS) -> list[PatchMesh]:
    """Every body geom tessellated and split by the patch of each triangle's centroid."""
    out = []
    g = model.geometry
    size = np.asarray(g.size, np.float64)
    for k in range(g.n_geoms):
        v, f = tessellate(int(g.kind[k]), size[k], segments)
        centroid = v[f].mean(axis=1)
        pid = np.asarray(patch_at(garment, jnp.full((f.shape[0],), k, jnp.int32),
                                  jnp.asarray(centroid, garment.patch_planes.dtype)))
        for p in np.unique(pid):
            sel = f[pid == p]
            used = np.unique(sel)
            remap = np.full(v.shape[0], -1)
            remap[used] = np.arange(used.size)
            out.append(PatchMesh(k, int(p), v[used], remap[sel]))
    return out


# ----------------------------------------------------------------------------- MJCF


def camera_mjcf(cam: Camera, name: str) -> ET.Element:
    """A MuJoCo ``<camera>`` with exactly ``cam``'s projection (module docstring)."""
    K = np.asarray(cam.K, float)
    R = np.asarray(cam.R, float)
    w, h = int(cam.width), int(cam.height)
    if not (abs(K[0, 0] - K[1, 1]) <= 1e-9 * K[0, 0] and abs(K[0, 1]) < 1e-12
            and abs(K[0, 2] - (w - 1) / 2) < 1e-9 and abs(K[1, 2] - (h - 1) / 2) < 1e-9):
        raise WorldError(f"camera {name!r}: MuJoCo renders square pixels with a centred "
                         f"principal point; K = {K.tolist()}")
    if np.any(np.asarray(cam.dist, float) != 0):
        raise WorldError(f"camera {name!r}: MuJoCo renders no lens distortion; dist must be 0")
    centre = -R.T @ np.asarray(cam.t, float)
    fovy = math.degrees(2 * math.atan((h / 2) / K[1, 1]))
    return ET.Element("camera", name=name, pos=_f(centre),
                      xyaxes=_f(np.concatenate([R[0], -R[1]])), fovy=repr(fovy))


class WorldScene(NamedTuple):
    """The MJCF text and what the renderer needs to drive it: names of the lamps (in spec
    order) and the fill light, mocap body names, the patch id of each mesh geom name, the
    body geom names (all MuJoCo geoms of the subject) and the camera names."""

    xml: str
    lamps: tuple[str, ...]
    lamp_rgb: np.ndarray  # (n_lamps, 3) linear colour at full power
    mocap: tuple[str, ...]
    geom_patch: dict[str, int]
    camera_names: tuple[str, ...]


def _prop_colours(spec: WorldSpec, garment: Garment, rng: np.random.Generator) -> list:
    """Clutter colours: a red box and an orange ball first (issue 18's look-alikes), then skin,
    a shirt colour, and random saturated hues."""
    import colorsys

    shirt = (spec.shirt_rgb if spec.garment == "single"
             else SHIRT_COLOURS[int(rng.integers(len(SHIRT_COLOURS)))][1])
    fixed = [("box", (0.8, 0.08, 0.05)), ("sphere", (0.95, 0.42, 0.05)), ("box", SKIN_RGB),
             ("sphere", shirt)]
    for _ in range(8):
        fixed.append((("box", "sphere", "cylinder")[int(rng.integers(3))],
                      colorsys.hsv_to_rgb(rng.uniform(), rng.uniform(0.5, 0.9),
                                          rng.uniform(0.5, 0.9))))
    return fixed


def build_scene(spec: WorldSpec, model: BodyModel, garment: Garment, cams: list[Camera],
                camera_names: list[str], segments=SEGMENTS,
                markers: np.ndarray | None = None, marker_radius: float = 0.02) -> WorldScene:
    """The MJCF document of ``spec`` with ``model`` (its names as shown) in ``garment``;
    ``markers`` (n, 3): white spheres ``marker<i>`` at these world points (calibration
    checks)."""
    rng = np.random.default_rng([spec.seed, 7])
    w = max(int(c.width) for c in cams)
    h = max(int(c.height) for c in cams)
    root = ET.Element("mujoco", model="jaxmocap_test_world")
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    ET.SubElement(root, "statistic", extent="4", center="0 0 1")
    vis = ET.SubElement(root, "visual")
    ET.SubElement(vis, "headlight", active="0", ambient="0 0 0", diffuse="0 0 0",
                  specular="0 0 0")
    ET.SubElement(vis, "global", offwidth=str(w), offheight=str(h))
    ET.SubElement(vis, "quality", shadowsize="2048", offsamples="2")
    ET.SubElement(vis, "map", znear="0.005", zfar="20", shadowclip="4", shadowscale="0.8")
    asset = ET.SubElement(root, "asset")
    ET.SubElement(asset, "texture", name="floor_tex", type="2d", builtin="checker",
                  width="512", height="512", rgb1=" ".join(map(str, FLOOR_RGB[0])),
                  rgb2=" ".join(map(str, FLOOR_RGB[1])),
                  mark="random", random="0.02", markrgb="0.2 0.2 0.2")
    ET.SubElement(asset, "material", name="floor", texture="floor_tex", texrepeat="6 6",
                  reflectance="0.08", specular="0.3", shininess="0.3")
    wall_rgb = 0.55 + 0.1 * rng.uniform(-1, 1, 3)
    ET.SubElement(asset, "texture", name="wall_tex", type="2d", builtin="gradient",
                  width="256", height="256", rgb1=_f(np.clip(wall_rgb + 0.08, 0, 1)),
                  rgb2=_f(wall_rgb - 0.08), mark="random", random="0.05",
                  markrgb=_f(wall_rgb * 0.6))
    ET.SubElement(asset, "material", name="wall", texture="wall_tex", texrepeat="3 2",
                  specular="0.1")
    ET.SubElement(asset, "material", name="cloth", specular="0.25", shininess="0.25")
    ET.SubElement(asset, "material", name="skin", specular="0.35", shininess="0.5")
    ET.SubElement(asset, "material", name="gloss", specular="0.9", shininess="0.9")
    ET.SubElement(asset, "material", name="matte", specular="0.05", shininess="0.1")
    meshes = patch_meshes(model, garment, segments)
    geom_patch = {}
    colour = np.concatenate([np.zeros((1, 3)), np.asarray(garment.colours, float)])
    pcol = np.concatenate([[0], np.asarray(garment.patch_colour)])
    skin = np.asarray(garment.skin)
    by_link: dict[int, list] = {}
    for i, pm in enumerate(meshes):
        name = f"p{pm.patch}_{pm.geom}_{i}"
        ET.SubElement(asset, "mesh", name=name, vertex=_f(pm.vertices),
                      face=" ".join(str(int(x)) for x in pm.faces.reshape(-1)), inertia="shell")
        geom_patch[name] = pm.patch
        by_link.setdefault(int(model.geometry.link[pm.geom]), []).append((name, pm))
    pose = np.asarray(model.geometry.pose, np.float64)
    skin_rgb = np.asarray(garment.skin_rgb, float)
    body_rgb = np.asarray(garment.body_rgb, float)

    def geoms(body: ET.Element, link: int) -> None:
        for name, pm in by_link.get(link, []):
            if pm.patch > 0:
                rgb, mat = colour[pcol[pm.patch]], "cloth"
            elif skin[pm.geom]:
                rgb, mat = skin_rgb, "skin"
            else:
                rgb, mat = body_rgb, "cloth"
            ET.SubElement(body, "geom", name=name, type="mesh", mesh=name,
                          pos=_f(pose[pm.geom, :3, 3]),
                          quat=_f(matrix_quat(pose[pm.geom, :3, :3])), rgba=_enc(rgb),
                          material=mat, contype="0", conaffinity="0", group="0",
                          mass="0.01")

    world = ET.SubElement(root, "worldbody")
    pg = str(PROP_GROUP)
    ET.SubElement(world, "geom", name="floor", type="plane", size="8 8 0.1",
                  material="floor", group=pg)
    ET.SubElement(world, "geom", name="wall_back", type="box", size=f"0.05 {ROOM['side_y']} 1.6",
                  pos=f"{ROOM['wall_x']} 0 1.6", material="wall", group=pg)
    for s in (-1, 1):
        ET.SubElement(world, "geom", name=f"wall_side{s:+d}", type="box",
                      size="3.5 0.05 1.6", pos=f"0.9 {s * ROOM['side_y']} 1.6",
                      material="wall", group=pg)
    # lamps: spot lamps high in front, alternating left/right, aimed at the subject's chest
    lamp_names, lamp_rgb = [], []
    for i, c in enumerate(spec.lamps):
        side = 1 if i % 2 == 0 else -1
        pos = np.array([1.6 + 0.4 * rng.uniform(), side * (1.3 + 0.6 * rng.uniform()),
                        2.4 + 0.4 * rng.uniform()])
        d = np.array([0.0, 0.0, 1.1]) - pos
        rgb = np.asarray(LAMP_COLOURS[c]) * 0.75
        ET.SubElement(world, "light", name=f"lamp{i}", type="spot", pos=_f(pos),
                      dir=_f(d / np.linalg.norm(d)), diffuse=_f(rgb), specular=_f(0.5 * rgb),
                      ambient=_f(0.06 * rgb), castshadow="true", cutoff="55", exponent="6",
                      attenuation="1 0 0.02")
        lamp_names.append(f"lamp{i}")
        lamp_rgb.append(rgb)
    ET.SubElement(world, "light", name="fill", type="directional", pos="0 0 3",
                  dir=_f(np.array([-0.4, 0.2, -1.0]) / np.linalg.norm([-0.4, 0.2, -1.0])),
                  diffuse=_f([spec.fill] * 3), specular="0 0 0",
                  ambient=_f([0.35 * spec.fill] * 3), castshadow="false")
    # clutter: static props behind and beside the subject, in the cameras' view
    for i, (kind, rgb) in enumerate(_prop_colours(spec, garment, rng)[:spec.n_clutter]):
        x = rng.uniform(-2.2, -0.8)
        y = rng.choice([-1, 1]) * rng.uniform(0.7, 1.9)
        half = rng.uniform(0.1, 0.22, 3)
        on_floor = rng.uniform() < 0.5 or i < 2
        zc = (half[2] if kind != "sphere" else half[0]) if on_floor else rng.uniform(0.9, 1.6)
        size = half[:1] if kind == "sphere" else half[[0, 2]] if kind == "cylinder" else half
        mat = "gloss" if kind == "sphere" else "matte"
        ET.SubElement(world, "geom", name=f"clutter{i}", type=kind, size=_f(size),
                      pos=_f([x, y, zc]), rgba=_enc(rgb), material=mat, group=pg)
        if not on_floor:  # a pedestal under a raised prop
            bottom = zc - (half[0] if kind == "sphere" else half[2])
            ET.SubElement(world, "geom", name=f"pedestal{i}", type="cylinder",
                          size=_f([0.04, bottom / 2]), pos=_f([x, y, bottom / 2]),
                          rgba=_enc((0.3, 0.3, 0.32)), material="matte", group=pg)
    mocap = []
    if spec.moving_object:
        b = ET.SubElement(world, "body", name="mover", mocap="true", pos=f"{MOVER_X} 0 1.3")
        ET.SubElement(b, "geom", name="mover", type="sphere", size=repr(MOVER_R),
                      rgba=_enc(_prop_colours(spec, garment, np.random.default_rng(
                          [spec.seed, 8]))[3][1]), material="gloss", group=pg,
                      contype="0", conaffinity="0")
        mocap.append("mover")
    if spec.occluder is not None:
        b = ET.SubElement(world, "body", name="occluder", mocap="true",
                          pos=f"{OCCLUDER_X} -5 {OCCLUDER_Z}")
        ET.SubElement(b, "geom", name="occluder", type="box", size=_f(OCCLUDER_HALF),
                      rgba=_enc((0.55, 0.45, 0.35)), material="matte", group=pg,
                      contype="0", conaffinity="0")
        mocap.append("occluder")
    for i, p in enumerate(np.zeros((0, 3)) if markers is None else np.asarray(markers)):
        ET.SubElement(world, "geom", name=f"marker{i}", type="sphere", size=repr(marker_radius),
                      pos=_f(p), rgba="1 1 1 1", group=pg, contype="0", conaffinity="0")
    for cam, name in zip(cams, camera_names, strict=True):
        world.append(camera_mjcf(cam, name))
    world.append(mjcf_body(model, geoms))
    ET.indent(root)
    return WorldScene(xml=ET.tostring(root, encoding="unicode"), lamps=tuple(lamp_names),
                      lamp_rgb=np.array(lamp_rgb), mocap=tuple(mocap), geom_patch=geom_patch,
                      camera_names=tuple(camera_names))
