"""Loading a URDF body through pytorch-kinematics, with our own geometry parse.

pytorch-kinematics (0.10) is the standard parser of the chain; we prepare the XML text it
sees so that the descriptions humans-as-robots use load faithfully:

* a ``spherical``/``ball`` joint becomes three revolute joints ``<name>_x``, ``_y``, ``_z``
  (rotation ``Rx @ Ry @ Rz``) with massless links ``<child>__x``, ``<child>__y`` between;
* a moving joint without ``<axis>`` gets the URDF default x written out (pk assumes z);
* trailing NUL bytes (pybullet_data's ``humanoid.urdf``) are stripped;
* visuals / collisions are removed from its copy: its parser rejects tags it does not know
  (``<ellipsoid>``), drops ``<capsule>`` silently, keeps one visual per link and has no colour.

Geometry is read by our own parse: every ``<visual>`` of a link (its ``<collision>`` elements if
it has none), with ``<origin>``, ``<material>``/``<color rgba>`` (inline or named at robot level)
and the kinds ``sphere``, ``box``, ``cylinder``, ``capsule radius length`` (the ROS/gazebo/bullet
extension: ``length`` between the cap centres, along z) and ``ellipsoid radii="a b c"`` (ours).
Joint origins are computed here in float64 and cross-checked against pytorch-kinematics'.
"""

from __future__ import annotations

import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from .chain import FIXED, PRISMATIC, REVOLUTE, ROOT_DOFS, KinematicChain
from .geometry import (
    BOX,
    CAPSULE,
    CYLINDER,
    DEFAULT_RGBA,
    ELLIPSOID,
    SPHERE,
    ArrayLike,
    make_geometry,
)
from .model import ROOT_DOF_NAMES, BodyModel, make_body_model

_PK_TYPES = {"fixed": FIXED, "revolute": REVOLUTE, "prismatic": PRISMATIC}
UP_AXES = ("z", "y")


# ----------------------------------------------------------------------------- transforms
def rpy_matrix(rpy: ArrayLike) -> np.ndarray:
    """URDF roll-pitch-yaw (fixed axes x, y, z): ``R = Rz(yaw) Ry(pitch) Rx(roll)``."""
    r, p, y = rpy
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), math.cos(y), \
        math.sin(y)  # fmt: skip
    return np.array(
        [
            [cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
            [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
            [-sp, cp * sr, cp * cr],
        ]
    )


def homogeneous(rot: ArrayLike, pos: ArrayLike) -> np.ndarray:
    m = np.eye(4)
    m[:3, :3] = rot
    m[:3, 3] = pos
    return m


def up_axis_rotation(up: str) -> np.ndarray:
    """Rotation taking a model whose up axis is ``up`` to our Z-up world (x kept)."""
    if up == "z":
        return np.eye(3)
    if up == "y":  # Rx(+90 deg): y -> z, z -> -y
        return np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
    raise ValueError(f"up axis must be one of {UP_AXES}, got {up!r}")


def _floats(text: str | None, n: int, default: ArrayLike, where: str) -> np.ndarray:
    if text is None:
        return np.asarray(default, float)
    vals = text.split()
    try:
        out = np.array([float(v) for v in vals])
    except ValueError:
        out = None
    if len(vals) != n or out is None or not np.all(np.isfinite(out)):
        raise ValueError(f"{where}: expected {n} finite numbers, got {text!r}")
    return out


def _origin(elem: ET.Element | None, where: str) -> np.ndarray:
    o = None if elem is None else elem.find("origin")
    if o is None:
        return np.eye(4)
    xyz = _floats(o.get("xyz"), 3, (0, 0, 0), f"{where} <origin xyz>")
    rpy = _floats(o.get("rpy"), 3, (0, 0, 0), f"{where} <origin rpy>")
    return homogeneous(rpy_matrix(rpy), xyz)


# ----------------------------------------------------------------------------- XML prep
MAX_MODEL_BYTES = 64 << 20  # a body description; pybullet's humanoid.urdf is 16 kB
URDF_JOINT_TYPES = ("fixed", "revolute", "continuous", "prismatic", "spherical", "ball")


def read_urdf_text(path: str | os.PathLike) -> str:
    """The URDF text with NUL bytes and surrounding whitespace removed (``FileNotFoundError``
    if there is no file); a binary or oversized file is one :class:`~jaxmocap.errors.InputError`
    line."""
    from jaxmocap.io.preflight import read_text

    if not Path(path).is_file():
        raise FileNotFoundError(f"URDF file not found: {path}")
    return read_text(path, "a URDF body model (XML)", max_bytes=MAX_MODEL_BYTES) \
        .replace("\x00", "").strip()


def check_urdf_structure(robot: ET.Element, where: str = "<urdf>") -> None:
    """The URDF's links and joints form one tree, checked before pytorch-kinematics sees them
    (its parser fails on these with tracebacks that name the wrong link): every link named
    once; every joint named, of a known type, with one ``<parent link>`` and one
    ``<child link>`` naming links of the file (the *missing* one is named); no link the child
    of two joints; no loop; one root link. Raises :class:`~jaxmocap.errors.InputError`
    naming the file, the element and what is expected."""
    from jaxmocap.errors import InputError

    def fail(msg: str) -> InputError:
        return InputError(f"{where}: {msg}")

    links: list[str] = []
    for k, link in enumerate(robot.findall("link")):
        name = link.get("name")
        if not name:
            raise fail(f"<link> #{k} has no name attribute; expected <link name=\"...\">")
        if name in links:
            raise fail(f"<link name={name!r}> is defined twice; expected unique link names")
        links.append(name)
    if not links:
        raise fail("no <link> elements; expected a <robot> with links and joints")
    known = set(links)
    listing = ", ".join(links[:8]) + (" ..." if len(links) > 8 else "")
    parent_of: dict[str, tuple[str, str]] = {}  # child link -> (parent link, joint)
    joints: set[str] = set()
    for k, joint in enumerate(robot.findall("joint")):
        jname = joint.get("name")
        if not jname:
            raise fail(f"<joint> #{k} has no name attribute; expected <joint name=\"...\">")
        w = f"<joint name={jname!r}>"
        if jname in joints:
            raise fail(f"{w} is defined twice; expected unique joint names")
        joints.add(jname)
        jtype = joint.get("type")
        if jtype not in URDF_JOINT_TYPES and jtype not in ("floating", "planar"):
            raise fail(f"{w} has type {jtype!r}; expected one of {', '.join(URDF_JOINT_TYPES)}")
        ends = {}
        for tag in ("parent", "child"):
            found = joint.findall(tag)
            if len(found) != 1:
                what = "no" if not found else f"{len(found)}"
                raise fail(f"{w} has {what} <{tag}> elements; expected exactly one "
                           f"<{tag} link=\"...\">")
            link = found[0].get("link")
            if not link:
                raise fail(f"{w} <{tag}> has no link attribute; expected <{tag} link=\"...\">")
            if link not in known:
                raise fail(f"{w} <{tag} link={link!r}>: no link named {link!r} in the file "
                           f"(links: {listing})")
            ends[tag] = link
        parent, child = ends["parent"], ends["child"]
        if parent == child:
            raise fail(f"{w} joins link {child!r} to itself; expected two different links")
        if child in parent_of:
            other = parent_of[child][1]
            raise fail(f"{w}: link {child!r} is already the child of joint {other!r}; a link "
                       "has one parent joint (the links must form a tree)")
        parent_of[child] = (parent, jname)
    for start in links:  # walk up from every link: a loop revisits a link
        seen, link = [start], start
        while link in parent_of:
            link = parent_of[link][0]
            if link in seen:
                cycle = seen[seen.index(link):] + [link]
                raise fail(f"the joints form a loop ({' <- '.join(cycle)}, through joint "
                           f"{parent_of[cycle[0]][1]!r}); expected a tree of links")
            seen.append(link)
    roots = [n for n in links if n not in parent_of]
    if len(roots) > 1:
        raise fail(f"links {', '.join(map(repr, roots[:4]))} all have no parent joint; expected "
                   "one root link (every other link the <child> of a joint)")


def _expand_spherical(robot: ET.Element, where: str) -> None:
    """Replace every spherical/ball joint by three revolute joints about x, y, z."""
    for joint in list(robot.findall("joint")):
        jtype = joint.get("type")
        if jtype in ("floating", "planar"):
            raise ValueError(
                f"{where}: joint {joint.get('name')!r} has type {jtype!r}; expected fixed, "
                "revolute, continuous, prismatic or spherical (a free root is implicit in q)"
            )
        if jtype not in ("spherical", "ball"):
            continue
        name = joint.get("name")
        parent = joint.find("parent").get("link")
        child = joint.find("child").get("link")
        origin = joint.find("origin")
        index = list(robot).index(joint)
        robot.remove(joint)
        links = [parent, f"{child}__x", f"{child}__y", child]
        new = []
        for k, ax in enumerate("xyz"):
            if k < 2:
                new.append(ET.Element("link", name=links[k + 1]))
            j = ET.Element("joint", name=f"{name}_{ax}", type="continuous")
            ET.SubElement(j, "parent", link=links[k])
            ET.SubElement(j, "child", link=links[k + 1])
            if k == 0 and origin is not None:
                j.append(origin)
            ET.SubElement(j, "axis", xyz=" ".join("1" if a == ax else "0" for a in "xyz"))
            new.append(j)
        for k, e in enumerate(new):
            robot.insert(index + k, e)


def prepare_urdf(text: str, where: str = "<urdf>") -> tuple[ET.Element, str]:
    """Parse the URDF; return (our tree with spherical joints expanded, pytorch-kinematics text)."""
    try:
        robot = ET.fromstring(text)
    except ET.ParseError as e:
        raise ValueError(f"{where}: not valid XML ({e})") from None
    if robot.tag != "robot":
        raise ValueError(f"{where}: root element is <{robot.tag}>, expected <robot>")
    check_urdf_structure(robot, where)
    _expand_spherical(robot, where)
    for joint in robot.findall("joint"):  # URDF's default axis is x; pytorch-kinematics uses z
        if joint.find("axis") is None and joint.get("type") != "fixed":
            ET.SubElement(joint, "axis", xyz="1 0 0")
    pk_robot = ET.fromstring(ET.tostring(robot))
    for link in pk_robot.findall("link"):
        for tag in ("visual", "collision", "inertial"):
            for e in link.findall(tag):
                link.remove(e)
    return robot, ET.tostring(pk_robot, encoding="unicode")


# ----------------------------------------------------------------------------- geometry
def _rgba(visual: ET.Element, materials: dict[str, np.ndarray], where: str) -> np.ndarray:
    mat = visual.find("material")
    if mat is None:
        return np.asarray(DEFAULT_RGBA, float)
    color = mat.find("color")
    if color is not None:
        return _floats(color.get("rgba"), 4, DEFAULT_RGBA, f"{where} <color rgba>")
    return materials.get(mat.get("name", ""), np.asarray(DEFAULT_RGBA, float))


def parse_geometry(robot: ET.Element, where: str = "<urdf>") -> list[dict]:
    """Geom rows (link *name*, kind, pose, size, rgba, name) of every link of the URDF tree."""
    materials = {}
    for mat in robot.findall("material"):
        color = mat.find("color")
        if color is not None:
            materials[mat.get("name")] = _floats(
                color.get("rgba"), 4, DEFAULT_RGBA, f"{where} material {mat.get('name')!r}"
            )
    rows = []
    for link in robot.findall("link"):
        lname = link.get("name")
        elems = link.findall("visual") or link.findall("collision")
        for k, vis in enumerate(elems):
            w = f"{where} link {lname!r} <{vis.tag}> #{k}"
            geom = vis.find("geometry")
            if geom is None or len(geom) == 0:
                raise ValueError(f"{w}: missing <geometry> child")
            g = geom[0]
            kind, size = _geom_kind_size(g, w)
            rows.append(
                dict(
                    name=vis.get("name") or f"{lname}_{k}",
                    link=lname,
                    kind=kind,
                    pose=_origin(vis, w),
                    size=size,
                    rgba=_rgba(vis, materials, w),
                    material=(vis.find("material").get("name", "")
                              if vis.find("material") is not None else ""),
                )
            )
    return rows


def _attr(g: ET.Element, name: str, where: str) -> float:
    v = g.get(name)
    if v is None:
        raise ValueError(f"{where}: <{g.tag}> needs attribute {name!r}")
    return float(_floats(v, 1, (0,), f"{where} <{g.tag} {name}>")[0])


def _geom_kind_size(g: ET.Element, where: str) -> tuple[int, np.ndarray]:
    if g.tag == "sphere":
        return SPHERE, np.array([_attr(g, "radius", where), 0.0, 0.0])
    if g.tag in ("capsule", "cylinder"):
        r, length = _attr(g, "radius", where), _attr(g, "length", where)
        return (CAPSULE if g.tag == "capsule" else CYLINDER), np.array([r, length / 2, 0.0])
    if g.tag == "box":
        return BOX, _floats(g.get("size"), 3, (0, 0, 0), f"{where} <box size>") / 2
    if g.tag == "ellipsoid":
        return ELLIPSOID, _floats(g.get("radii"), 3, (0, 0, 0), f"{where} <ellipsoid radii>")
    raise ValueError(
        f"{where}: geometry <{g.tag}> is not supported; expected sphere, capsule, cylinder, "
        "box or ellipsoid"
    )


# ----------------------------------------------------------------------------- chain
def chain_from_pk(
    pk_chain,
    origins: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
    base: np.ndarray | None = None,
    scale: float = 1.0,
) -> KinematicChain:
    """Our KinematicChain from a pytorch-kinematics Chain (depth-first, pk's joint order).

    ``origins`` maps child link names to float64 (joint origin, unit axis) to use instead of
    pk's float32 ones (checked to agree within 1e-5); ``base`` is the root link's fixed 4x4 offset;
    ``scale`` multiplies all translations (unit conversion).
    """
    joint_names = list(pk_chain.get_joint_parameter_names())
    parents, origin_list, axes, types, dofs, names = [], [], [], [], [], []
    lower = [-np.inf] * ROOT_DOFS + [0.0] * len(joint_names)
    upper = [np.inf] * ROOT_DOFS + [0.0] * len(joint_names)
    stack = [(pk_chain._root, -1)]
    while stack:
        frame, parent = stack.pop()
        idx = len(names)
        names.append(frame.link.name)
        parents.append(parent)
        j = frame.joint
        m = np.eye(4)
        for off in (frame.link.offset, j.offset):
            if off is not None and parent >= 0:
                m = m @ off.get_matrix().detach().cpu().double().numpy()[0]
        axis = j.axis.detach().cpu().double().numpy()
        if origins is not None and parent >= 0:
            mine, my_axis = origins[frame.link.name]
            my_axis = np.asarray(my_axis, float) / np.linalg.norm(my_axis)
            if not (
                np.allclose(mine, m, atol=1e-5)
                and (j.joint_type == "fixed" or np.allclose(my_axis, axis, atol=1e-5))
            ):
                raise RuntimeError(f"joint of {frame.link.name!r}: our parse disagrees with pk's")
            m, axis = mine.copy(), my_axis
        if parent < 0:
            m = np.eye(4) if base is None else np.asarray(base, float)
        m[:3, 3] *= scale
        origin_list.append(m)
        axes.append(axis)
        types.append(_PK_TYPES[j.joint_type] if parent >= 0 else FIXED)
        if types[-1] == FIXED:
            dofs.append(-1)
        else:
            d = ROOT_DOFS + joint_names.index(j.name)
            dofs.append(d)
            if j.limits is not None:
                lower[d], upper[d] = float(j.limits[0]), float(j.limits[1])
            else:
                lower[d], upper[d] = -np.inf, np.inf
        for child in reversed(frame.children):
            stack.append((child, idx))
    return KinematicChain(
        parents=parents,
        joint_origin=np.stack(origin_list),
        joint_axis=np.stack(axes),
        joint_type=types,
        dof_index=dofs,
        lower=np.array(lower),
        upper=np.array(upper),
        link_names=names,
        dof_names=list(ROOT_DOF_NAMES) + joint_names,
    )


def load_urdf(
    path: str | os.PathLike,
    *,
    keypoints: dict[str, tuple[str, ArrayLike]] | None = None,
    scale: float = 1.0,
    up: str = "z",
) -> BodyModel:
    """Load a URDF body: chain through pytorch-kinematics, geometry by our parse.

    ``scale`` converts the file's units to metres (pybullet's ``humanoid.urdf``: 0.25);
    ``up`` names the file's up axis (``"y"`` for pybullet's humanoid), rotated to our +z by
    the root link's fixed offset. ``keypoints`` maps names to ``(link, offset in m)``.
    """
    import pytorch_kinematics as pk

    where = str(path)
    robot, pk_text = prepare_urdf(read_urdf_text(path), where)
    origins = {}
    for joint in robot.findall("joint"):
        w = f"{where} joint {joint.get('name')!r}"
        axis = joint.find("axis")
        axis = _floats(None if axis is None else axis.get("xyz"), 3, (1, 0, 0), f"{w} <axis>")
        origins[joint.find("child").get("link")] = (_origin(joint, w), axis)
    pk_chain = pk.build_chain_from_urdf(pk_text)
    base = homogeneous(up_axis_rotation(up), (0.0, 0.0, 0.0))
    chain = chain_from_pk(pk_chain, origins=origins, base=base, scale=scale)
    rows = parse_geometry(robot, where)
    for r in rows:
        r["link"] = chain.link_index(r["link"])
        r["pose"] = r["pose"].copy()
        r["pose"][:3, 3] *= scale
        r["size"] = r["size"] * scale
    return make_body_model(chain, make_geometry(rows), keypoints)
