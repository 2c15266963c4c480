"""Loading an MJCF (MuJoCo) body through pytorch-kinematics.

pytorch-kinematics 0.10's own MJCF loader cannot read the humanoids that ship with pybullet
or MuJoCo: it rejects bodies with several joints ("composite joints"), it looks joint types
up in a dict keyed by ``mjtJoint`` enums that MuJoCo 4 indexes by plain ints, and it places a
joint with a non-zero ``pos`` at the wrong point (it translates the child frame by ``pos``
instead of rotating about it). So we let MuJoCo compile the file (it resolves defaults,
``fromto``, angle units and frames), *flatten* the compiled tree into an equivalent URDF and
hand that to pytorch-kinematics' URDF parser. A body with joints ``j_1..j_k`` (anchors
``p_1..p_k`` in the body frame) becomes, exactly as MuJoCo composes them,

    T_body = T_parent @ B @ Tr(p_1) R_1 Tr(p_2 - p_1) R_2 ... R_k Tr(-p_k)

with massless links ``<body>__<joint>`` between the joints. A ``ball`` joint becomes three
hinges about the body's x, y, z (``R = Rx Ry Rz``); a ``free`` joint on the single top-level
body is the root of ``q`` (``q[0:3]`` = its world position, as MuJoCo's ``qpos``). Without a
free joint the world body is the root link. Geometry comes from the compiled model (size
conventions already match ours); ground planes are skipped.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from .geometry import BOX, CAPSULE, CYLINDER, ELLIPSOID, SPHERE, ArrayLike, make_geometry
from .model import BodyModel, make_body_model
from .urdf import chain_from_pk, homogeneous

# MuJoCo mjtGeom -> our kinds; mjGEOM_PLANE (0) is skipped, the rest are rejected.
_MJ_GEOM = {2: SPHERE, 3: CAPSULE, 4: ELLIPSOID, 5: CYLINDER, 6: BOX}
_MJ_PLANE, _MJ_MESH = 0, 7
_MJ_FREE, _MJ_BALL, _MJ_SLIDE, _MJ_HINGE = 0, 1, 2, 3
_MJ_DEFAULT_RGBA = (0.5, 0.5, 0.5, 1.0)


def quat_matrix(q: ArrayLike) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``(w, x, y, z)`` (MuJoCo's order)."""
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def matrix_rpy(r: np.ndarray) -> tuple[float, float, float]:
    """URDF roll-pitch-yaw of a rotation matrix (inverse of ``urdf.rpy_matrix``)."""
    cp = math.hypot(r[0, 0], r[1, 0])
    pitch = math.atan2(-r[2, 0], cp)
    if cp > 1e-9:
        return math.atan2(r[2, 1], r[2, 2]), pitch, math.atan2(r[1, 0], r[0, 0])
    return math.atan2(-r[1, 2], r[1, 1]), pitch, 0.0


def compile_mjcf(path: str | os.PathLike):
    """The compiled ``mujoco.MjModel`` of an MJCF file.

    Read with ``MjSpec.from_file``, so that ``<include>`` files, ``meshdir`` and the other
    paths resolve against the model's own folder (dm_control's suite includes ``common/*.xml``);
    ``material=`` references to materials the file does not define (render-only) are dropped.
    """
    import mujoco

    from jaxmocap.io.preflight import read_text

    from .urdf import MAX_MODEL_BYTES

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"MJCF file not found: {path}")
    text = read_text(path, "an MJCF (MuJoCo XML) body model", max_bytes=MAX_MODEL_BYTES)
    try:
        root = ET.fromstring(text)
    except ET.ParseError as e:
        raise ValueError(f"{path}: not valid XML ({e})") from None
    if root.tag != "mujoco":
        raise ValueError(f"{path}: root element is <{root.tag}>, expected <mujoco>")
    try:
        spec = mujoco.MjSpec.from_file(str(path))
        defined = {m.name for m in spec.materials}
        for e in list(spec.geoms) + list(spec.sites):
            if e.material and e.material not in defined:
                e.material = ""
        return spec.compile()
    except ValueError as e:
        raise ValueError(f"{path}: MuJoCo could not compile it: {e}") from None


def _body_name(m, b: int) -> str:
    return m.body(b).name or ("world" if b == 0 else f"body{b}")


def _xyz_rpy(t: np.ndarray) -> dict[str, str]:
    return {
        "xyz": " ".join(repr(float(v)) for v in t[:3, 3]),
        "rpy": " ".join(repr(v) for v in matrix_rpy(t[:3, :3])),
    }


def flatten_to_urdf(m) -> tuple[str, dict[str, tuple[np.ndarray, np.ndarray]], str, np.ndarray]:
    """(URDF text, {child link: (origin, axis)} in float64, root link name, the root link's
    fixed 4x4 offset) of an MjModel."""
    top = [b for b in range(1, m.nbody) if m.body_parentid[b] == 0]
    free_root = None
    if len(top) == 1 and m.body_jntnum[top[0]] >= 1:
        if m.jnt_type[m.body_jntadr[top[0]]] == _MJ_FREE:
            free_root = top[0]
    robot = ET.Element("robot", name="mjcf")
    # the free root body's own orientation (the CMU humanoid's euler="90 0 0" stands its
    # y-up skeleton up): the root link's fixed offset, so that q = 0 is MuJoCo's qpos0 pose
    base = np.eye(4)
    if free_root is not None:
        base[:3, :3] = quat_matrix(m.body_quat[free_root])
    origins: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    root_name = _body_name(m, free_root if free_root is not None else 0)
    ET.SubElement(robot, "link", name=root_name)

    def add_joint(name, jtype, parent, child, origin, axis=None, limits=None):
        j = ET.SubElement(robot, "joint", name=name, type=jtype)
        ET.SubElement(j, "parent", link=parent)
        ET.SubElement(j, "child", link=child)
        ET.SubElement(j, "origin", **_xyz_rpy(origin))
        if axis is not None:
            ET.SubElement(j, "axis", xyz=" ".join(repr(float(v)) for v in axis))
        if limits is not None:
            ET.SubElement(j, "limit", lower=repr(limits[0]), upper=repr(limits[1]), effort="0",
                          velocity="0")  # fmt: skip
        origins[child] = (origin, np.array([0.0, 0.0, 1.0]) if axis is None else axis)

    for b in range(1, m.nbody):
        if b == free_root:
            if m.body_jntnum[b] != 1:
                raise ValueError(f"body {_body_name(m, b)!r}: a free joint must be its only joint")
            continue
        name, parent = _body_name(m, b), _body_name(m, int(m.body_parentid[b]))
        joints = []  # (name, urdf type, axis, anchor, limits)
        for j in range(m.body_jntadr[b], m.body_jntadr[b] + m.body_jntnum[b]):
            jt, jname, pos = int(m.jnt_type[j]), m.joint(j).name or f"joint{j}", m.jnt_pos[j]
            lim = (float(m.jnt_range[j, 0]), float(m.jnt_range[j, 1]))
            limited = bool(m.jnt_limited[j]) if hasattr(m, "jnt_limited") else lim != (0.0, 0.0)
            if jt == _MJ_FREE:
                raise ValueError(f"joint {jname!r}: a free joint is only allowed on the single "
                                 "top-level body (the root)")  # fmt: skip
            if jt == _MJ_BALL:
                cone = (-lim[1], lim[1]) if limited else None
                for k, ax in enumerate("xyz"):
                    joints.append((f"{jname}_{ax}", "revolute" if cone else "continuous",
                                   np.eye(3)[k], pos, cone))  # fmt: skip
            else:
                jtype = "prismatic" if jt == _MJ_SLIDE else "revolute"
                if not limited:
                    jtype, lim = ("continuous", None) if jt == _MJ_HINGE else (jtype, None)
                if jtype == "prismatic" and lim is None:
                    lim = (-1e9, 1e9)  # pytorch-kinematics needs prismatic limits
                joints.append((jname, jtype, m.jnt_axis[j], pos, lim))
        body = homogeneous(quat_matrix(m.body_quat[b]), m.body_pos[b])
        if not joints:
            add_joint(f"{name}__fixed", "fixed", parent, name, body)
            ET.SubElement(robot, "link", name=name)
            continue
        prev_link, prev_anchor, start = parent, np.zeros(3), body
        for k, (jname, jtype, axis, anchor, lim) in enumerate(joints):
            last = k == len(joints) - 1
            child = name if last and not np.any(anchor) else f"{name}__{jname}"
            origin = start @ homogeneous(np.eye(3), anchor - prev_anchor)
            add_joint(jname, jtype, prev_link, child, origin, axis, lim)
            ET.SubElement(robot, "link", name=child)
            prev_link, prev_anchor, start = child, np.asarray(anchor, float), np.eye(4)
        if prev_link != name:
            add_joint(f"{name}__anchor", "fixed", prev_link, name,
                      homogeneous(np.eye(3), -prev_anchor))  # fmt: skip
            ET.SubElement(robot, "link", name=name)
    return ET.tostring(robot, encoding="unicode"), origins, root_name, base


def mjcf_geometry(m, link_names: Sequence[str], where: str) -> list[dict]:
    """Geom rows of a compiled MjModel, attached to the links named after their bodies."""
    rows = []
    for g in range(m.ngeom):
        gt = int(m.geom_type[g])
        name = m.geom(g).name or f"geom{g}"
        if gt == _MJ_PLANE:
            continue
        if gt not in _MJ_GEOM and gt != _MJ_MESH:
            raise ValueError(f"{where}: geom {name!r} has MuJoCo type {gt}; supported: sphere, "
                             "capsule, ellipsoid, cylinder, box (planes are skipped)")  # fmt: skip
        link = _body_name(m, int(m.geom_bodyid[g]))
        if link not in link_names:  # world geoms when the free body is the root
            continue
        pose = homogeneous(quat_matrix(m.geom_quat[g]), m.geom_pos[g])
        if gt == _MJ_MESH:  # its bounding box in the geom frame (MuJoCo's geom_aabb)
            kind, size = BOX, np.array(m.geom_aabb[g, 3:], float)
            pose = pose @ homogeneous(np.eye(3), m.geom_aabb[g, :3])
        else:
            kind = _MJ_GEOM[gt]
            size = np.array(m.geom_size[g], float)
        if kind == SPHERE:
            size[1:] = 0.0
        elif kind in (CAPSULE, CYLINDER):
            size[2] = 0.0
        rgba = np.array(m.geom_rgba[g], float)
        if m.geom_matid[g] >= 0 and np.allclose(rgba, _MJ_DEFAULT_RGBA):
            rgba = np.array(m.mat_rgba[m.geom_matid[g]], float)
        material = m.material(int(m.geom_matid[g])).name if m.geom_matid[g] >= 0 else ""
        rows.append(dict(name=name, link=list(link_names).index(link), kind=kind,
                         pose=pose, size=size, rgba=rgba, material=material))  # fmt: skip
    return rows


def mjcf_sites(m, link_names: Sequence[str]) -> dict[str, tuple[str, tuple[float, ...]]]:
    """``{site name: (link, offset in the link frame)}`` of the sites on the body's links (a
    link named after a MuJoCo body has that body's frame); world sites are not body markers."""
    out = {}
    for i in range(m.nsite):
        link = _body_name(m, int(m.site_bodyid[i]))
        if link in link_names:
            out[m.site(i).name or f"site{i}"] = (link, tuple(float(v) for v in m.site_pos[i]))
    return out


def load_mjcf(
    path: str | os.PathLike,
    *,
    keypoints: dict[str, tuple[str, ArrayLike]] | None = None,
) -> BodyModel:
    """Load an MJCF body (see module docstring); links are named after MuJoCo bodies. Its
    ``<site>`` markers become keypoints named after them (``keypoints`` given here win)."""
    import pytorch_kinematics as pk

    m = compile_mjcf(path)
    text, origins, _, base = flatten_to_urdf(m)
    chain = chain_from_pk(pk.build_chain_from_urdf(text), origins=origins, base=base)
    rows = mjcf_geometry(m, chain.link_names, str(path))
    return make_body_model(chain, make_geometry(rows),
                           {**mjcf_sites(m, chain.link_names), **(keypoints or {})})
