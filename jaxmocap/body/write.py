"""Writing any :class:`~jaxmocap.body.BodyModel` (chain + geometry) as URDF or MJCF.

Both writers produce files that :func:`~jaxmocap.body.load_urdf` / :func:`~jaxmocap.body.load_mjcf`
read back to the same chain (same links, DOF names and order, joint origins, axes, limits) and
geometry; other readers (pytorch-kinematics, MuJoCo) see the same kinematics.

**URDF** — one ``<link>`` per chain link (the massless links between the joints of a ball joint
included), one ``<joint>`` per non-root link, named after its DOF (fixed joints:
``<child>__fixed``): ``revolute`` with ``<limit>`` (``continuous`` when unbounded),
``prismatic``, ``fixed``; ``<origin xyz rpy>`` and ``<axis>`` as in the chain. Geoms are
``<visual>`` elements named after the geom, with an inline ``<material><color rgba>``:
``sphere``, ``box`` (full size), ``cylinder`` (full length), ``capsule radius length`` (length
between the cap centres, the ROS/gazebo/bullet extension) and ``ellipsoid radii`` (jaxmocap's
extension). The root's free motion is implicit (``q[0:6]``).

**MJCF** — nested ``<body>`` elements, one per link, each with at most one ``hinge`` / ``slide``
joint at its origin (so a ball joint is written as the chain's x-y-z hinge chain), the root body
with a ``<freejoint>`` (MuJoCo ``qpos[0:3]`` = ``q[0:3]``, ``qpos[3:7]`` = the quaternion of the
rotation vector ``q[3:6]``). Geoms are MuJoCo primitives with ``pos``/``quat``/``size``/``rgba``
(sizes follow the same conventions as ours), ``contype``/``conaffinity`` 0 (a kinematic body).
Links without geoms get a tiny ``<inertial>`` so that MuJoCo compiles them.

The root link must not have a fixed offset (``joint_origin[0] = I``): neither format can
express one together with the free root.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np

from .chain import FIXED, PRISMATIC, ROOT_DOFS
from .geometry import BOX, CAPSULE, CYLINDER, ELLIPSOID, SPHERE
from .mjcf import matrix_rpy
from .model import BodyModel

Naming = str | Callable[[str], str] | Mapping[str, str] | None
MJ_TYPES = {SPHERE: "sphere", CAPSULE: "capsule", CYLINDER: "cylinder", BOX: "box",
            ELLIPSOID: "ellipsoid"}


def _num(v: float) -> str:
    return repr(float(v))


def _nums(v) -> str:
    return " ".join(_num(x) for x in np.asarray(v, float).reshape(-1))


def matrix_quat(r: np.ndarray) -> np.ndarray:
    """Unit quaternion ``(w, x, y, z)`` of a rotation matrix (Shepperd's method)."""
    r = np.asarray(r, float)
    tr = np.trace(r)
    if tr > 0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [0.25 * s, (r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(r)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(max(1.0 + r[i, i] - r[j, j] - r[k, k], 1e-300))
        q = [0.0] * 4
        q[0] = (r[k, j] - r[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (r[j, i] + r[i, j]) / s
        q[1 + k] = (r[k, i] + r[i, k]) / s
    q = np.array(q)
    return q / np.linalg.norm(q) * (1 if q[0] >= 0 else -1)


def rotvec_quat(w: np.ndarray) -> np.ndarray:
    """Quaternion ``(w, x, y, z)`` of a rotation vector (rad)."""
    w = np.asarray(w, float)
    theta = float(np.linalg.norm(w))
    if theta < 1e-12:
        return np.array([1.0, *(0.5 * w)]) / np.linalg.norm([1.0, *(0.5 * w)])
    return np.array([math.cos(theta / 2), *(math.sin(theta / 2) * w / theta)])


def _named(model: BodyModel, link_names: Naming) -> BodyModel:
    if link_names is None:
        return model
    from .scale import rename_body

    return rename_body(model, link_names)


def _check_root(model: BodyModel) -> np.ndarray:
    origin = np.asarray(model.chain.joint_origin, np.float64)
    if not np.allclose(origin[0], np.eye(4), atol=1e-12):
        raise ValueError("write: the root link has a fixed offset (joint_origin[0] != I); "
                         "URDF/MJCF with a free root cannot express it")
    return origin


def _geoms_of(model: BodyModel, link: int) -> list[int]:
    return [k for k in range(model.geometry.n_geoms) if int(model.geometry.link[k]) == link]


# ----------------------------------------------------------------------------- URDF


def urdf_text(model: BodyModel, link_names: Naming = None, name: str = "jaxmocap_body") -> str:
    """The URDF text of ``model`` (module docstring), links/joints/geoms renamed by
    ``link_names`` (a convention of :data:`jaxmocap.body.scale.NAMINGS`, a function or a
    table)."""
    model = _named(model, link_names)
    chain, g = model.chain, model.geometry
    origin = _check_root(model)
    axis = np.asarray(chain.joint_axis, np.float64)
    lower, upper = np.asarray(chain.lower, float), np.asarray(chain.upper, float)
    size, pose, rgba = (np.asarray(a, np.float64) for a in (g.size, g.pose, g.rgba))
    robot = ET.Element("robot", name=name)
    for i, (parent, jtype, dof) in enumerate(chain.topology):
        lname = chain.link_names[i]
        if i > 0:
            pname = chain.link_names[parent]
            if jtype == FIXED:
                j = ET.SubElement(robot, "joint", name=f"{lname}__fixed", type="fixed")
            else:
                lo, hi = lower[dof], upper[dof]
                bounded = np.isfinite(lo) and np.isfinite(hi)
                kind = "prismatic" if jtype == PRISMATIC else (
                    "revolute" if bounded else "continuous")
                j = ET.SubElement(robot, "joint", name=chain.dof_names[dof], type=kind)
            ET.SubElement(j, "parent", link=pname)
            ET.SubElement(j, "child", link=lname)
            ET.SubElement(j, "origin", xyz=_nums(origin[i, :3, 3]),
                          rpy=_nums(matrix_rpy(origin[i, :3, :3])))
            if jtype != FIXED:
                ET.SubElement(j, "axis", xyz=_nums(axis[i]))
                lo, hi = lower[dof], upper[dof]
                if np.isfinite(lo) and np.isfinite(hi):
                    ET.SubElement(j, "limit", lower=_num(lo), upper=_num(hi), effort="100",
                                  velocity="10")
                elif jtype == PRISMATIC:
                    ET.SubElement(j, "limit", lower="-1e9", upper="1e9", effort="100",
                                  velocity="10")
        link = ET.SubElement(robot, "link", name=lname)
        for k in _geoms_of(model, i):
            v = ET.SubElement(link, "visual", name=g.names[k])
            ET.SubElement(v, "origin", xyz=_nums(pose[k, :3, 3]),
                          rpy=_nums(matrix_rpy(pose[k, :3, :3])))
            geo = ET.SubElement(v, "geometry")
            kind, s = int(g.kind[k]), size[k]
            if kind == SPHERE:
                ET.SubElement(geo, "sphere", radius=_num(s[0]))
            elif kind in (CAPSULE, CYLINDER):
                ET.SubElement(geo, MJ_TYPES[kind], radius=_num(s[0]), length=_num(2 * s[1]))
            elif kind == BOX:
                ET.SubElement(geo, "box", size=_nums(2 * s))
            else:
                ET.SubElement(geo, "ellipsoid", radii=_nums(s))
            mat = ET.SubElement(v, "material", name=f"{g.names[k]}_material")
            ET.SubElement(mat, "color", rgba=_nums(rgba[k]))
    ET.indent(robot)
    return '<?xml version="1.0"?>\n' + ET.tostring(robot, encoding="unicode") + "\n"


def write_urdf(model: BodyModel, path: str | os.PathLike, link_names: Naming = None,
               name: str = "jaxmocap_body") -> Path:
    """Write ``model`` as a URDF file (atomically); see :func:`urdf_text`."""
    from jaxmocap.io.atomic import write_text

    path = Path(path)
    write_text(path, urdf_text(model, link_names, name))
    return path


# ----------------------------------------------------------------------------- MJCF

GeomWriter = Callable[[ET.Element, int], None]  # (body element, link index) -> adds geoms


def primitive_geoms(model: BodyModel) -> GeomWriter:
    """The default geom writer: each geom of the link as a MuJoCo primitive."""
    g = model.geometry
    size, pose, rgba = (np.asarray(a, np.float64) for a in (g.size, g.pose, g.rgba))

    def write(body: ET.Element, link: int) -> None:
        for k in _geoms_of(model, link):
            kind = int(g.kind[k])
            s = size[k][:1] if kind == SPHERE else size[k][:2] if kind in (CAPSULE, CYLINDER) \
                else size[k]
            ET.SubElement(body, "geom", name=g.names[k], type=MJ_TYPES[kind], size=_nums(s),
                          pos=_nums(pose[k, :3, 3]), quat=_nums(matrix_quat(pose[k, :3, :3])),
                          rgba=_nums(rgba[k]), contype="0", conaffinity="0")

    return write


def mjcf_body(model: BodyModel, geoms: GeomWriter | None = None, root_joint: str = "root"
              ) -> ET.Element:
    """The ``<body>`` tree of ``model`` (module docstring) for a ``<worldbody>``. A root link
    with a fixed offset (``joint_origin[0]``, e.g. a body turned to face +x) hangs at that
    offset inside a frame body ``<root>__frame`` that carries the free joint (our FK's
    ``T(q) joint_origin[0]``)."""
    chain = model.chain
    origin = np.asarray(chain.joint_origin, np.float64)
    offset = not np.allclose(origin[0], np.eye(4), atol=1e-12)
    axis = np.asarray(chain.joint_axis, np.float64)
    lower, upper = np.asarray(chain.lower, float), np.asarray(chain.upper, float)
    geoms = primitive_geoms(model) if geoms is None else geoms
    has_geom = set(np.asarray(model.geometry.link).tolist())
    elems: list[ET.Element] = []
    for i, (parent, jtype, dof) in enumerate(chain.topology):
        attrs = {"name": chain.link_names[i]}
        if i > 0:
            attrs |= {"pos": _nums(origin[i, :3, 3]),
                      "quat": _nums(matrix_quat(origin[i, :3, :3]))}
        if i == 0 and offset:
            attrs |= {"pos": _nums(origin[0, :3, 3]),
                      "quat": _nums(matrix_quat(origin[0, :3, :3]))}
        b = ET.Element("body", **attrs)
        if i == 0 and not offset:
            ET.SubElement(b, "freejoint", name=root_joint)
        elif jtype != FIXED:
            jattrs = {"name": chain.dof_names[dof],
                      "type": "slide" if jtype == PRISMATIC else "hinge",
                      "axis": _nums(axis[i])}
            if np.isfinite(lower[dof]) and np.isfinite(upper[dof]):
                jattrs |= {"range": f"{_num(lower[dof])} {_num(upper[dof])}",
                           "limited": "true"}
            ET.SubElement(b, "joint", **jattrs)
        if i not in has_geom:
            ET.SubElement(b, "inertial", pos="0 0 0", mass="0.001",
                          diaginertia="1e-6 1e-6 1e-6")
        geoms(b, i)
        if i > 0:
            elems[parent].append(b)
        elems.append(b)
    if offset:
        frame = ET.Element("body", name=f"{chain.link_names[0]}__frame")
        ET.SubElement(frame, "freejoint", name=root_joint)
        ET.SubElement(frame, "inertial", pos="0 0 0", mass="0.001", diaginertia="1e-6 1e-6 1e-6")
        frame.append(elems[0])
        return frame
    return elems[0]


def mjcf_text(model: BodyModel, link_names: Naming = None, name: str = "jaxmocap_body") -> str:
    """The MJCF text of ``model`` (module docstring), optionally renamed (see urdf_text)."""
    model = _named(model, link_names)
    root = ET.Element("mujoco", model=name)
    ET.SubElement(root, "compiler", angle="radian", autolimits="true")
    world = ET.SubElement(root, "worldbody")
    world.append(mjcf_body(model))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode") + "\n"


def write_mjcf(model: BodyModel, path: str | os.PathLike, link_names: Naming = None,
               name: str = "jaxmocap_body") -> Path:
    """Write ``model`` as an MJCF file (atomically); see :func:`mjcf_text`."""
    from jaxmocap.io.atomic import write_text

    path = Path(path)
    write_text(path, mjcf_text(model, link_names, name))
    return path


def qpos_from_q(model: BodyModel, mj_model, q: np.ndarray, root_joint: str = "root"
                ) -> np.ndarray:
    """MuJoCo ``qpos`` of a model written by :func:`mjcf_body` for our pose vector ``q``:
    root ``qpos[0:3] = q[0:3]``, quaternion of ``q[3:6]``, hinges / slides by DOF name."""
    import mujoco

    q = np.asarray(q, np.float64)
    qpos = np.array(mj_model.qpos0, np.float64)
    adr = mj_model.jnt_qposadr[mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, root_joint)]
    qpos[adr:adr + 3] = q[0:3]
    qpos[adr + 3:adr + 7] = rotvec_quat(q[3:6])
    for d in range(ROOT_DOFS, model.n_dof):
        j = mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_JOINT, model.chain.dof_names[d])
        if j < 0:
            raise ValueError(f"qpos_from_q: MuJoCo model has no joint {model.chain.dof_names[d]!r}")
        qpos[mj_model.jnt_qposadr[j]] = q[d]
    return qpos
