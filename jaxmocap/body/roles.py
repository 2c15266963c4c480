"""Roles, not names: which links, joints and geoms of a body play which part.

Everything downstream (keypoints, the 14-DOF subset, retargeting, mirroring, the contour model,
the swivel jumps, the garment) asks the body's :class:`BodyRoles`, never a link name. Roles come
from a small JSON file beside the model, ``<model stem>.roles.json`` (format in
docs/USER_GUIDE.md, "Your body"), or are inferred from common naming conventions; whatever
cannot be found is one :class:`~jaxmocap.errors.InputError` naming the model file, the missing
roles and the roles file to write.

**Link roles** (:data:`LINK_ROLES`): ``pelvis chest neck head`` and per side (``l_``/``r_``)
``upper_arm forearm hand``. ``neck`` is optional (a body whose head link carries the neck).
Name inference splits link names into words (``_ - . :`` and camelCase: ``mixamorig:LeftArm``
-> ``left arm``), takes the side from a leading/trailing ``l``/``left``/``r``/``right`` word and
matches the rest against :data:`PART_WORDS` (first synonym wins: ``LeftArm`` is the upper arm
even when ``LeftShoulder`` exists; a side letter glued to a part word counts too: the CMU
skeleton's ``lhumerus``). ``chest`` not named -> the deepest common ancestor of the two upper
arms that carries geometry; ``pelvis`` not named, or named but not above the chest -> the root
link. A role no link is named for is played by the link carrying the geoms named for it
(gymnasium's ``head`` sphere on the torso link, its ``left_hand`` sphere on the lower arm), and
a hand nothing names by the link carrying the skin-material geoms below the forearm.

**Geometry belongs to role links**: a geom on a link joined to a role link by fixed joints
belongs to that role link (URDF visuals on fixed child links, :func:`owner_link`); on a link
that plays several roles, a geom named for one of them (or of skin material, for the skin
role there) belongs to it and the others to the most proximal role (:func:`geom_roles`).

**Joint roles** (:data:`JOINT_ROLES`) are the DOFs on the chain path between two role links:
``spine`` (pelvis -> chest), ``neck`` (chest -> head), ``l_shoulder`` (chest -> upper arm),
``l_elbow`` (upper arm -> forearm), ``l_wrist`` (forearm -> hand), and the same on the right.

**Geometry roles**: the contour shapes of the limbs (the geoms of each arm role) and of the
torso (the chest role's geoms, without capsules/cylinders lying across the body -- a shoulder
bar -- unless the torso is made of such capsules); the skin geoms (the geoms of the neck, head
and hand roles, the links below them, and every geom of a material named ``skin``).

**Mirror pairs**: every joint DOF with its left/right partner and the sign of the reflection
``y -> -y`` (``M Rot(a, t) M = Rot(M a, -t)``: sign -1 when the partner's rest axis is ``+M a``,
+1 when it is ``-M a``, 0 when the axes are not mirror images). The arm joints pair by role
(shoulder with shoulder, in chain order); other DOFs pair by geometry (the joint whose rest
centre is the mirror image and whose axis is mirrored); a DOF on the mid-plane pairs with itself.
Pairs in the roles file override both.

**Keypoints** (the 12 :data:`~jaxmocap.body.model.KEYPOINT_NAMES`, which are role names):
``pelvis`` the pelvis link's origin; ``neck``, the shoulders, elbows and wrists the joint
centres of the neck (else head), upper-arm, forearm and hand links (the origin of the last
moving joint frame of the link); ``chest`` 3/4 of the way from the chest link's joint centre
to the midpoint of the two shoulder centres; ``head`` and the hands the centre of the largest
geom of the head / hand role (offsets rounded to 1 um); where the wrist's joint centre is
the elbow's (a hand geom on the forearm link, a wrist link fixed at the elbow) the wrist is the
hand geom's end nearest the elbow, and where the head has no joint of its own the neck is the
head geom's end nearest the chest. The roles file may override any keypoint; the keypoints it
does not give are placed by these rules.

Why one file: role inference is one algorithm over names and geometry together -- the name
rules ask which geoms a link owns (roles from geom names, skin materials), the geometry rules
ask the roles found so far (ownership of fixed child links, the torso's crosswise capsules,
keypoints from the role geoms), and the derivation joins both; split, each part imports the
others. Loading a body (which joins these roles to the file readers) is :mod:`.load`.
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import re
from collections.abc import Mapping, Sequence
from pathlib import Path

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from ..errors import InputError
from .chain import FIXED, ROOT_DOFS, KinematicChain, path_to_root
from .geometry import BOX, CAPSULE, CYLINDER, ELLIPSOID, SPHERE, Geometry

SIDES = ("l", "r")
KEYPOINT_NAMES = (
    "pelvis", "chest", "neck", "head", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow",
    "l_wrist", "r_wrist", "l_hand", "r_hand",
)  # fmt: skip
LIMB_PARTS = ("upper_arm", "forearm", "hand")
LINK_ROLES = ("pelvis", "chest", "neck", "head") + tuple(
    f"{s}_{p}" for s in SIDES for p in LIMB_PARTS
)
OPTIONAL_LINK_ROLES = ("neck",)
# joint role -> (parent role link, child role link); "neck" ends at the head link.
JOINT_ROLES = {
    "spine": ("pelvis", "chest"),
    "neck": ("chest", "head"),
    **{f"{s}_shoulder": ("chest", f"{s}_upper_arm") for s in SIDES},
    **{f"{s}_elbow": (f"{s}_upper_arm", f"{s}_forearm") for s in SIDES},
    **{f"{s}_wrist": (f"{s}_forearm", f"{s}_hand") for s in SIDES},
}
CONTOUR_LIMBS = ("l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm")  # + "torso"
# Synonyms per part, in priority order (matched against the words of a link name joined by
# "_" or by nothing: "upper_arm", "upperarm").
PART_WORDS = {
    "upper_arm": ("upper_arm", "upperarm", "up_arm", "uparm", "humerus", "arm", "shldr",
                  "shoulder"),
    "forearm": ("forearm", "fore_arm", "lower_arm", "lowerarm", "low_arm", "lowarm", "radius",
                "ulna", "elbow"),
    "hand": ("hand", "palm", "wrist"),
    "head": ("head", "skull"),
    "neck": ("neck",),
    "chest": ("chest", "thorax", "upper_body", "upperbody", "torso", "upper_chest", "spine"),
    "pelvis": ("pelvis", "hips", "hip", "root", "base"),
}  # fmt: skip
CHEST_KEYPOINT_FRACTION = 0.75  # chest keypoint: 3/4 of the way up to the shoulder line
CROSSWISE_COS = math.cos(math.radians(45.0))  # a capsule this close to the body's y axis
MIRROR_LOOSE = 0.01  # second pass of the mirror pairs: centres within 1% of the body's size
MIRROR_COS = math.cos(math.radians(5.0))  # ... and axes within 5 degrees of mirror images


@dataclasses.dataclass(frozen=True)
class BodyRoles:
    """The roles of one body (hashable: a static field of :class:`~jaxmocap.body.BodyModel`).

    ``links``: (role, link name) for every role present; ``joints``: (joint role, DOF names in
    chain order); ``limb_geoms``: (limb role, geom names) for :data:`CONTOUR_LIMBS`;
    ``torso_geoms``, ``skin_geoms``: geom names; ``mirror``: (dof, partner dof, sign) for every
    joint DOF that has a partner; ``keypoints``: (name, link, (x, y, z) offset in the link
    frame) for the 12 keypoints; ``source``: the roles file, or the model file + "(inferred)".
    """

    links: tuple[tuple[str, str], ...]
    joints: tuple[tuple[str, tuple[str, ...]], ...]
    limb_geoms: tuple[tuple[str, tuple[str, ...]], ...]
    torso_geoms: tuple[str, ...]
    skin_geoms: tuple[str, ...]
    mirror: tuple[tuple[str, str, float], ...]
    keypoints: tuple[tuple[str, str, tuple[float, float, float]], ...]
    # where the roles came from (messages only: not compared, hashed or printed by repr, so
    # that caches keyed by the model do not depend on where the file lies)
    source: str = dataclasses.field(default="", compare=False, repr=False)

    def link(self, role: str) -> str:
        """The link playing ``role`` (``neck`` falls back to the head link)."""
        d = dict(self.links)
        if role == "neck" and role not in d:
            role = "head"
        if role not in d:
            raise InputError(f"{self.source}: the body has no {role!r} link role")
        return d[role]

    def dofs(self, joint: str) -> tuple[str, ...]:
        """DOF names of the joint role ``joint`` (see :data:`JOINT_ROLES`), chain order."""
        d = dict(self.joints)
        if joint not in d:
            raise InputError(f"{self.source}: unknown joint role {joint!r}; roles: {tuple(d)}")
        return d[joint]

    def limb(self, role: str) -> tuple[str, ...]:
        """Geom names of the contour limb ``role`` (``torso`` or one of CONTOUR_LIMBS)."""
        if role == "torso":
            return self.torso_geoms
        return dict(self.limb_geoms)[role]

    def keypoint_table(self) -> dict[str, tuple[str, tuple[float, float, float]]]:
        """``{keypoint: (link, offset)}`` as :func:`~jaxmocap.body.make_body_model` takes it."""
        return {k: (link, off) for k, link, off in self.keypoints}


def require_roles(model, what: str) -> BodyRoles:
    """``model.roles``, or one line saying ``what`` needs them."""
    roles = getattr(model, "roles", None)
    if roles is None:
        raise InputError(
            f"{what}: the body model has no roles (build it with jaxmocap.body.load_body, or "
            "pass roles=infer_roles(...) to make_body_model)"
        )
    return roles


# ----------------------------------------------------------------------------- names
def name_words(name: str) -> list[str]:
    """Lower-case words of a link name: ``mixamorig:LeftForeArm`` -> ``[left, fore, arm]``."""
    name = name.split(":")[-1]
    name = re.sub(r"([a-z0-9])([A-Z])", r"\1_\2", name)
    name = re.sub(r"([A-Z]+)([A-Z][a-z])", r"\1_\2", name)
    name = re.sub(r"([A-Za-z])([0-9])", r"\1_\2", name)
    return [w for w in re.split(r"[^A-Za-z0-9]+", name.lower()) if w]


def classify_link(name: str) -> tuple[str | None, str | None, int]:
    """(side ``l``/``r``/None, part, synonym rank) of a link name; part None if unmatched."""
    words = name_words(name)
    side = None
    if len(words) > 1 and words[0] in ("l", "left", "r", "right"):
        side, words = words[0][0], words[1:]
    elif len(words) > 1 and words[-1] in ("l", "left", "r", "right"):
        side, words = words[-1][0], words[:-1]
    for candidate in ("_".join(words), "".join(words)):
        for part, syn in PART_WORDS.items():
            if candidate in syn:
                return side, part, syn.index(candidate)
    if side is None and len(words) == 1 and words[0][:1] in ("l", "r"):
        # a side letter glued to a part word (the CMU skeleton's lhumerus, rradius, lhand)
        for part in LIMB_PARTS:
            if words[0][1:] in PART_WORDS[part]:
                return words[0][0], part, PART_WORDS[part].index(words[0][1:])
    sides = [i for i, w in enumerate(words) if w in ("left", "right")]
    if side is None and len(sides) == 1 and 0 < sides[0] < len(words) - 1:
        # the side word in the middle: a prefix, then side and part (skin_left_hand); only
        # the full words left/right here (a middle "l" is too often something else)
        i = sides[0]
        rest = words[i + 1:]
        for candidate in ("_".join(rest), "".join(rest)):
            for part in LIMB_PARTS:
                if candidate in PART_WORDS[part]:
                    return words[i][0], part, PART_WORDS[part].index(candidate)
    return side, None, 0


def infer_link_roles(chain: KinematicChain, geometry: Geometry | None = None
                     ) -> tuple[dict[str, str], dict[str, list[str]]]:
    """(``{role: link}`` from the link names and the tree, ``{role: [tied links]}`` for the
    roles several links claim equally); see the module docstring. Possibly partial."""
    best: dict[str, list[tuple[int, str]]] = {}
    for link in chain.link_names:
        side, part, rank = classify_link(link)
        if part is None or (part in LIMB_PARTS) != (side is not None):
            continue  # an arm part needs a side, a trunk part must not have one
        best.setdefault(f"{side}_{part}" if side else part, []).append((rank, link))
    out, ties = {}, {}
    for role, cands in best.items():
        top = min(r for r, _ in cands)
        links = [name for r, name in cands if r == top]
        if len(links) == 1:
            out[role] = links[0]
        else:
            ties[role] = links
    arms = _deepest_ancestor_of_arms(chain, out, chain.link_names, geometry)
    if arms:  # structure first: the arms hang from the chest (mixamo's "Spine" is the waist)
        out["chest"] = arms
        ties.pop("chest", None)
    if "pelvis" in ties and chain.link_names[0] in ties["pelvis"]:
        out["pelvis"] = chain.link_names[0]
        del ties["pelvis"]
    if "pelvis" not in out and "pelvis" not in ties:
        out["pelvis"] = chain.link_names[0]
    elif "pelvis" in out:  # fixed to the root link (DeepMimic's base -> root): the root moves it
        path = path_to_root(chain.topology, chain.link_names.index(out["pelvis"]))
        if all(chain.topology[i][1] == FIXED for i in path):
            out["pelvis"] = chain.link_names[0]
    if "head" not in out and "head" not in ties and "neck" in out:
        out["head"] = out.pop("neck")  # a "neck" link that carries the head (DeepMimic)
    if geometry is not None:
        _roles_from_geom_names(chain, geometry, out, ties)
    if "pelvis" in out and "chest" in out:  # the pelvis role is the trunk above the chest
        chest = chain.link_names.index(out["chest"])
        if chain.link_names.index(out["pelvis"]) not in path_to_root(chain.topology, chest):
            out["pelvis"] = chain.link_names[0]  # gym/dm_control: the root is the torso
    return out, ties


def _roles_from_geom_names(chain: KinematicChain, geometry: Geometry, out: dict,
                           ties: dict) -> None:
    """Roles no link is named for, from the names of the geoms (gymnasium's humanoid: a
    ``head`` sphere on the torso link, ``left_hand`` spheres on the lower arms): the link
    carrying the geom(s) that name the role plays it. Updates ``out``/``ties`` in place."""
    glink = np.asarray(geometry.link).tolist()
    found: dict[str, set[int]] = {}
    for g, name in enumerate(geometry.names):
        side, part, _ = classify_link(name)
        if part is None or (part in LIMB_PARTS) != (side is not None):
            continue
        role = f"{side}_{part}" if side else part
        if role in out or role in ties or role in OPTIONAL_LINK_ROLES:
            continue
        found.setdefault(role, set()).add(glink[g])
    for role, links in found.items():
        names = sorted(chain.link_names[li] for li in links)
        if len(names) == 1:
            out[role] = names[0]
        else:
            ties[role] = names
    # hands nothing names: the skin-material geoms below a forearm (a skin-coloured hand
    # capsule on the forearm link of an MJCF without hand bodies)
    for s in SIDES:
        role, fore = f"{s}_hand", out.get(f"{s}_forearm")
        if role in out or role in ties or fore is None:
            continue
        below = _subtree(chain, chain.link_names.index(fore))
        links = {glink[g] for g in range(len(geometry.names))
                 if glink[g] in below and is_skin_material(geometry, g)}
        if len(links) == 1:
            out[role] = chain.link_names[links.pop()]


def _deepest_ancestor_of_arms(chain, found: Mapping[str, str], candidates,
                              geometry: Geometry | None = None) -> str | None:
    """The deepest of ``candidates`` that is an ancestor of both upper arms (if known) and,
    with ``geometry``, carries a geom."""
    if "l_upper_arm" not in found or "r_upper_arm" not in found:
        return None
    names = chain.link_names
    common = set(path_to_root(chain.topology, names.index(found["l_upper_arm"])))
    common &= set(path_to_root(chain.topology, names.index(found["r_upper_arm"])))
    common -= {names.index(found["l_upper_arm"]), names.index(found["r_upper_arm"])}
    if geometry is not None:  # links carrying geometry, theirs or their fixed children's
        carry = set()
        for li in set(np.asarray(geometry.link).tolist()):
            carry.add(li)
            while chain.topology[li][1] == FIXED and chain.topology[li][0] >= 0:
                li = chain.topology[li][0]
                carry.add(li)
        common &= carry
    ok = [names.index(c) for c in candidates if names.index(c) in common]
    return names[max(ok)] if ok else None  # topological order: the largest index is deepest


# ----------------------------------------------------------------------------- geometry
def rest_transforms(chain: KinematicChain) -> np.ndarray:
    """World transforms (float64) of all links at q = 0 with the root at the origin."""
    origin = np.asarray(chain.joint_origin, np.float64)
    out = []
    for i, (p, _, _) in enumerate(chain.topology):
        out.append(origin[i] if p < 0 else out[p] @ origin[i])
    return np.stack(out)


def joint_centre(chain: KinematicChain, link: int, rest: np.ndarray | None = None) -> np.ndarray:
    """The centre of the joint that moves ``link``, in ``link``'s frame (m): ``link``'s origin
    when its own joint moves it; when it hangs by a fixed offset from a single-child link that
    a joint moves (an MJCF joint anchor, flattened by :mod:`jaxmocap.body.mjcf`), that link's
    origin."""
    rest = rest_transforms(chain) if rest is None else rest
    topo = chain.topology
    p = topo[link][0]
    if topo[link][1] == FIXED and p >= 0 and topo[p][1] != FIXED:
        if sum(1 for q, _, _ in topo if q == p) == 1:
            return np.linalg.solve(rest[link], rest[p])[:3, 3]
    return np.zeros(3)


def geom_support(kind: int, size: np.ndarray, rot: np.ndarray, u: np.ndarray) -> float:
    """Half-extent (m) of a geom along the unit direction ``u`` (given in the frame in which
    ``rot`` is the geom's rotation): exact support functions of the five solids."""
    v = rot.T @ u
    a, b, c = size
    if kind == SPHERE:
        return float(a)
    if kind == CAPSULE:
        return float(abs(v[2]) * b + a)
    if kind == CYLINDER:
        return float(abs(v[2]) * b + a * math.sqrt(max(0.0, 1.0 - v[2] ** 2)))
    if kind == BOX:
        return float(np.abs(v) @ size)
    if kind == ELLIPSOID:
        return float(np.linalg.norm(v * size))
    raise ValueError(f"geom kind {kind} unknown")


def geom_volume(kind: int, size: np.ndarray) -> float:
    """Volume (m^3) of a geom (to pick the largest geom of a link)."""
    a, b, c = size
    if kind == SPHERE:
        return 4 / 3 * math.pi * a**3
    if kind == CAPSULE:
        return math.pi * a * a * (2 * b) + 4 / 3 * math.pi * a**3
    if kind == CYLINDER:
        return math.pi * a * a * 2 * b
    if kind == BOX:
        return 8 * a * b * c
    return 4 / 3 * math.pi * a * b * c


def _geoms_of(geometry: Geometry, link: int) -> list[int]:
    return [g for g, li in enumerate(np.asarray(geometry.link).tolist()) if li == link]


def _subtree(chain: KinematicChain, link: int) -> set[int]:
    out = {link}
    for i, (p, _, _) in enumerate(chain.topology):
        if p in out:
            out.add(i)
    return out


# Which role keeps the unnamed geoms of a link that plays several roles (gymnasium's torso link
# is the chest and carries the head geom; its lower arm is the forearm and carries the hand).
_CONTAINER_ORDER = ("chest", "pelvis", "neck", "head") + tuple(
    f"{s}_{p}" for p in LIMB_PARTS for s in SIDES)


def owner_link(chain: KinematicChain, link: int, role_links: set[int]) -> int | None:
    """The role link that ``link``'s geometry belongs to: ``link`` itself if it plays a role,
    else its parent as long as they are joined by a fixed joint (URDF visuals on fixed child
    links belong to the parent for every role lookup); None when a moving joint comes first."""
    topo = chain.topology
    while link not in role_links:
        if topo[link][1] != FIXED or topo[link][0] < 0:
            return None
        link = topo[link][0]
    return link


def is_skin_material(geometry: Geometry, g: int) -> bool:
    """Whether geom ``g``'s material is named for skin (``skin``, ``Skin_Light``, ...)."""
    mats = getattr(geometry, "materials", ())
    return bool(mats) and "skin" in name_words(mats[g] or "")


def geom_roles(chain: KinematicChain, geometry: Geometry, links: Mapping[str, str],
               skin: Sequence[str] = ()) -> dict[str, list[int]]:
    """``{link role: [geom indices]}``: each geom belongs to the role of its owner link
    (:func:`owner_link`); on a link that plays several roles, a geom named for one of them
    (``head``, ``right_hand``, ``skin_left_hand``) belongs to it, a skin geom (of skin material,
    or in ``skin``: the roles' skin geoms) to the one skin role there (a hand on the forearm
    link), and the others to the most proximal role (:data:`_CONTAINER_ORDER`)."""
    names = chain.link_names
    by_link: dict[int, list[str]] = {}
    for role in _CONTAINER_ORDER:
        if role in links:
            by_link.setdefault(names.index(links[role]), []).append(role)
    out: dict[str, list[int]] = {r: [] for r in links}
    for g, li in enumerate(np.asarray(geometry.link).tolist()):
        owner = owner_link(chain, li, set(by_link))
        if owner is None:
            continue
        roles_here = by_link[owner]
        side, part, _ = classify_link(geometry.names[g])
        named = f"{side}_{part}" if side else part
        if named not in roles_here and (is_skin_material(geometry, g)
                                        or geometry.names[g] in skin):
            skin_roles = [r for r in roles_here if r in ("head", "neck", "l_hand", "r_hand")]
            named = skin_roles[0] if len(skin_roles) == 1 else named
        out[named if named in roles_here else roles_here[0]].append(g)
    return out


def geom_pose_in(chain: KinematicChain, geometry: Geometry, g: int, link: int,
                 rest: np.ndarray | None = None) -> np.ndarray:
    """Geom ``g``'s pose (4x4, float64) in the frame of ``link`` (its own link or an ancestor
    joined to it by fixed joints: the offset is constant)."""
    rest = rest_transforms(chain) if rest is None else rest
    own = int(np.asarray(geometry.link)[g])
    pose = np.asarray(geometry.pose, np.float64)[g]
    return pose if own == link else np.linalg.solve(rest[link], rest[own]) @ pose


def is_crosswise(geometry: Geometry, g: int) -> bool:
    """A capsule/cylinder whose axis lies within 45 degrees of its link's y axis (a bar
    across the shoulders: not part of the torso's contour)."""
    kind = int(np.asarray(geometry.kind)[g])
    if kind not in (CAPSULE, CYLINDER):
        return False
    z = np.asarray(geometry.pose, np.float64)[g, :3, 2]
    return bool(abs(z[1]) > CROSSWISE_COS)


# Where each contour limb's bone ends: keypoints, the first one not at the bone's start (a
# DeepMimic wrist sits on the elbow: the forearm then ends at the hand's centre).
_BONE_END_KEYPOINTS = {"l_upper_arm": ("l_elbow",), "l_forearm": ("l_wrist", "l_hand"),
                       "r_upper_arm": ("r_elbow",), "r_forearm": ("r_wrist", "r_hand"),
                       "torso": ("neck", "head")}


def limb_axis(model, role: str) -> np.ndarray:
    """Unit bone direction (link frame, rest) of a contour limb role (:data:`CONTOUR_LIMBS` or
    ``torso``): from the link's joint centre to the next keypoint of :data:`_BONE_END_KEYPOINTS`
    (the elbow, the wrist -- the hand if the wrist sits on the elbow --, the neck)."""
    roles = require_roles(model, f"the {role} bone")
    chain = model.chain
    rest = rest_transforms(chain)
    own = chain.link_names.index(roles.link("chest" if role == "torso" else role))
    a = joint_centre(chain, own, rest)
    table = roles.keypoint_table()
    for k in _BONE_END_KEYPOINTS[role]:
        link, off = table[k]
        li = chain.link_names.index(link)
        b = np.linalg.solve(rest[own], rest[li] @ np.append(np.asarray(off, float), 1.0))[:3]
        u = b - a
        n = np.linalg.norm(u)
        if n > 1e-3:
            return u / n
    raise InputError(f"{roles.source}: the {role} has no length (its joint centre and the "
                     f"keypoints {_BONE_END_KEYPOINTS[role]} coincide)")


# ----------------------------------------------------------------------------- derivation
def _path_dofs(chain: KinematicChain, parent: int, child: int, where: str, what: str) -> tuple:
    anc = path_to_root(chain.topology, child)
    if parent not in anc:
        raise InputError(
            f"{where}: role link {chain.link_names[child]!r} ({what}) does not hang below "
            f"{chain.link_names[parent]!r}; fix the links in the roles file"
        )
    path = anc[: anc.index(parent)][::-1]
    topo = chain.topology
    return tuple(chain.dof_names[topo[i][2]] for i in path if topo[i][1] != FIXED)


def _mirror_pairs(chain: KinematicChain, joints: Mapping[str, tuple[str, ...]],
                  explicit: Sequence[Sequence[str]] = ()) -> tuple[tuple[str, str, float], ...]:
    """(dof, partner, sign) for every joint DOF with a partner (module docstring)."""
    rest = rest_transforms(chain)
    names = chain.dof_names
    centre, axis = {}, {}
    for link, (_, t, d) in enumerate(chain.topology):
        if t != FIXED:
            centre[d] = rest[link, :3, 3]
            a = rest[link, :3, :3] @ np.asarray(chain.joint_axis[link], np.float64)
            axis[d] = a / np.linalg.norm(a)
    m = np.array([1.0, -1.0, 1.0])
    partner: dict[int, int] = {}
    for a_name, b_name in explicit:
        i, j = names.index(a_name), names.index(b_name)
        partner[i], partner[j] = j, i
    for part in ("shoulder", "elbow", "wrist"):
        left, right = joints.get(f"l_{part}", ()), joints.get(f"r_{part}", ())
        if len(left) == len(right):
            for a_name, b_name in zip(left, right, strict=True):
                i, j = names.index(a_name), names.index(b_name)
                if i not in partner and j not in partner:
                    partner[i], partner[j] = j, i
    scale = max(1e-3, float(np.abs(rest[:, :3, 3]).max()))
    # exact mirror images first; then, for what is left, a measured skeleton's (dm_control's
    # CMU humanoid: centres within 1% of the body's size, axes within 5 degrees)
    for tol, axis_tol in ((1e-6 * scale, 1e-6), (MIRROR_LOOSE * scale, 1 - MIRROR_COS)):
        for i in range(ROOT_DOFS, len(names)):
            if i in partner:
                continue
            if abs(centre[i][1]) < tol and abs(abs((m * axis[i]) @ axis[i]) - 1.0) < axis_tol:
                partner[i] = i
                continue
            cands = [j for j in range(ROOT_DOFS, len(names)) if j not in partner and j != i
                     and np.allclose(m * centre[i], centre[j], atol=tol)
                     and abs(abs((m * axis[i]) @ axis[j]) - 1.0) < axis_tol]
            if len(cands) == 1:
                partner[i], partner[cands[0]] = cands[0], i
    out = []
    for i in range(ROOT_DOFS, len(names)):
        if i not in partner:
            continue
        j = partner[i]
        c = (m * axis[i]) @ axis[j]
        sign = -1.0 if c > MIRROR_COS else 1.0 if c < -MIRROR_COS else 0.0
        out.append((names[i], names[j], sign))
    return tuple(out)


def _keypoints(chain: KinematicChain, geometry: Geometry, links: Mapping[str, str],
               where: str, skip: Sequence[str] = (), skin: Sequence[str] = ()
               ) -> dict[str, tuple[str, tuple[float, float, float]]]:
    """The keypoint rules of the module docstring for every keypoint not in ``skip`` (those
    the roles file gives: a keypoint given there is never derived, so a head link without
    geometry is no error when the file places the head)."""

    rest = rest_transforms(chain)
    idx = {r: chain.link_names.index(n) for r, n in links.items()}
    neck = links.get("neck", links["head"])
    owned = geom_roles(chain, geometry, links, skin)
    kind, size = np.asarray(geometry.kind), np.asarray(geometry.size, np.float64)

    def centre(role):
        return joint_centre(chain, idx[role], rest)

    def largest(role):
        gs = owned.get(role, [])
        if not gs:
            raise InputError(
                f"{where}: the {role} link {links[role]!r} has no geometry to place the "
                f"{role!r} keypoint; give it in the roles file (\"keypoints\")"
            )
        g = max(gs, key=lambda g: geom_volume(int(kind[g]), size[g]))
        return g, geom_pose_in(chain, geometry, g, idx[role], rest)

    def in_frame(role_from, p, role_to):
        q = rest[idx[role_from]] @ np.append(p, 1.0)
        return np.linalg.solve(rest[idx[role_to]], q)[:3]

    def chest():
        c = idx["chest"]
        start = joint_centre(chain, c, rest)
        mid = 0.5 * sum(in_frame(f"{s}_upper_arm", centre(f"{s}_upper_arm"), "chest")
                        for s in SIDES)
        return start + CHEST_KEYPOINT_FRACTION * (mid - start)

    def wrist(s):
        # the hand link's joint centre; where that is the elbow (a hand geom on the forearm
        # link, or a wrist link fixed at the elbow's anchor) the hand geom's end nearest the
        # elbow instead
        hand, fore = f"{s}_hand", f"{s}_forearm"
        p = centre(hand)
        if np.linalg.norm(in_frame(hand, p, fore) - centre(fore)) > 1e-3:
            return p
        g, pose = largest(hand)
        c = pose[:3, 3]
        u = c - in_frame(fore, centre(fore), hand)
        if np.linalg.norm(u) < 1e-6:
            return p
        u = u / np.linalg.norm(u)
        return c - geom_support(int(kind[g]), size[g], pose[:3, :3], u) * u

    def neck_point():
        # the neck (else head) link's joint centre; where the head has no joint of its own
        # (a head geom on the torso link, a head body fixed on it and centred on its origin)
        # the head geom's end nearest the chest's joint
        p = joint_centre(chain, chain.link_names.index(neck), rest)
        if neck != links["head"] or not owned.get("head"):
            return p
        g, pose = largest("head")
        c = pose[:3, 3]
        own = links["head"] == links["chest"] or np.linalg.norm(p - c) < 1e-3
        u = c - in_frame("chest", joint_centre(chain, idx["chest"], rest), "head")
        if not own or np.linalg.norm(u) < 1e-6:
            return p
        u = u / np.linalg.norm(u)
        return c - geom_support(int(kind[g]), size[g], pose[:3, :3], u) * u

    rules = {
        "pelvis": lambda: (links["pelvis"], np.zeros(3)),
        "chest": lambda: (links["chest"], chest()),
        "neck": lambda: (neck, neck_point()),
        "head": lambda: (links["head"], largest("head")[1][:3, 3]),
    }
    for s in SIDES:
        rules[f"{s}_shoulder"] = lambda s=s: (links[f"{s}_upper_arm"], centre(f"{s}_upper_arm"))
        rules[f"{s}_elbow"] = lambda s=s: (links[f"{s}_forearm"], centre(f"{s}_forearm"))
        rules[f"{s}_wrist"] = lambda s=s: (links[f"{s}_hand"], wrist(s))
        rules[f"{s}_hand"] = lambda s=s: (links[f"{s}_hand"], largest(f"{s}_hand")[1][:3, 3])
    out = {}
    for k in KEYPOINT_NAMES:
        if k in skip:
            continue
        link, off = rules[k]()
        # offsets to 1 um: the same numbers whether the chain was loaded in float32 or float64
        out[k] = (link, tuple(round(float(v), 6) + 0.0 for v in off))
    return out


def derive_roles(
    chain: KinematicChain,
    geometry: Geometry,
    links: Mapping[str, str],
    *,
    source: str,
    torso_geoms: Sequence[str] | None = None,
    limb_geoms: Mapping[str, Sequence[str]] | None = None,
    skin_geoms: Sequence[str] | None = None,
    mirror: Sequence[Sequence[str]] = (),
    keypoints: Mapping[str, Sequence] | None = None,
) -> BodyRoles:
    """Complete :class:`BodyRoles` from the link roles (module docstring): joint DOFs, geoms,
    mirror pairs and keypoints, each taken from the arguments where given."""
    where = source
    missing = [r for r in LINK_ROLES if r not in links and r not in OPTIONAL_LINK_ROLES]
    if missing:
        raise InputError(f"{where}: missing link roles {missing}")
    names = chain.link_names
    bad = {r: n for r, n in links.items() if n not in names}
    if bad:
        raise InputError(f"{where}: roles name unknown links {bad}; links are {names}")
    idx = {r: names.index(n) for r, n in links.items()}
    joints = {}
    for joint, (a, b) in JOINT_ROLES.items():
        joints[joint] = _path_dofs(chain, idx[a], idx[b], where, b)
    gnames = geometry.names

    def check(geoms, what):
        unknown = [g for g in geoms if g not in gnames]
        if unknown:
            raise InputError(f"{where}: {what} names unknown geoms {unknown}; geoms: {gnames}")
        return tuple(geoms)

    if skin_geoms is not None:
        check(skin_geoms, "skin_geoms")
    owned = geom_roles(chain, geometry, links, skin_geoms or ())
    if skin_geoms is None:  # the head, neck and hands with everything below them
        skin_roles = ("neck", "head", "l_hand", "r_hand")
        skin_set = {g for r in skin_roles for g in owned.get(r, [])}
        skin_set |= {g for g in range(geometry.n_geoms) if is_skin_material(geometry, g)}
        shared = {idx[r] for r in links if r not in skin_roles}
        below = set()
        for r in skin_roles:
            if r in idx and idx[r] not in shared:  # a head on the torso link: not its legs
                below |= _subtree(chain, idx[r]) - {idx[r]}
        glink = np.asarray(geometry.link).tolist()
        skin_set |= {g for g, li in enumerate(glink) if li in below and li not in shared
                     and owner_link(chain, li, shared) is None}
        skin = tuple(gnames[g] for g in sorted(skin_set))
    else:
        skin = check(skin_geoms, "skin_geoms")
    if torso_geoms is None:
        cover = [g for g in owned["chest"] if gnames[g] not in skin]
        # without the bars across the shoulders, unless the torso is made of such capsules
        # (gymnasium's humanoid: its torso and waist are capsules along y)
        upright = [g for g in cover if not is_crosswise(geometry, g)]
        torso = tuple(gnames[g] for g in (upright or cover))
    else:
        torso = check(torso_geoms, "torso_geoms")
    limb_geoms = dict(limb_geoms or {})
    limbs = []
    for role in CONTOUR_LIMBS:
        if role in limb_geoms:
            limbs.append((role, check(limb_geoms[role], f"limb_geoms[{role!r}]")))
        else:
            limbs.append((role, tuple(gnames[g] for g in owned[role] if gnames[g] not in skin)))
    for a_name, b_name in mirror:
        for n in (a_name, b_name):
            if n not in chain.dof_names:
                raise InputError(f"{where}: mirror names unknown joint {n!r}; joints: "
                                 f"{chain.dof_names[ROOT_DOFS:]}")

    given = dict(keypoints or {})
    kp = {} if set(KEYPOINT_NAMES) <= set(given) else _keypoints(
        chain, geometry, links, where, skip=tuple(given), skin=skin)
    for k, (link, off) in given.items():
        if link not in names:
            raise InputError(f"{where}: keypoints: {k!r} names unknown link {link!r}; links "
                             f"are {names}")
        off = tuple(float(v) for v in off)
        if len(off) != 3:
            raise InputError(f"{where}: keypoints: {k!r}: expected [link, [x, y, z]]")
        kp[k] = (link, off)
    kp = {k: kp[k] for k in (*KEYPOINT_NAMES, *kp) if k in kp}  # the 12 first, in their order
    return BodyRoles(
        links=tuple((r, links[r]) for r in LINK_ROLES if r in links),
        joints=tuple(joints.items()),
        limb_geoms=tuple(limbs),
        torso_geoms=torso,
        skin_geoms=skin,
        mirror=_mirror_pairs(chain, joints, mirror),
        keypoints=tuple((k, link, off) for k, (link, off) in kp.items()),
        source=source,
    )


def infer_roles(chain: KinematicChain, geometry: Geometry, model_file: str | os.PathLike = "",
                overrides: Mapping | None = None) -> BodyRoles:
    """Roles inferred from the names (module docstring), completed by ``overrides`` (the parsed
    roles file). Missing roles: one :class:`InputError` naming ``model_file``, the roles and
    the roles file to write."""
    overrides = dict(overrides or {})
    links, ties = infer_link_roles(chain, geometry)
    links.update(overrides.get("links", {}))
    missing = [r for r in LINK_ROLES if r not in links and r not in OPTIONAL_LINK_ROLES]
    roles_file = roles_path(model_file) if model_file else "<model>.roles.json"
    if missing:
        tied = {r: ties[r] for r in missing if r in ties}
        raise InputError(
            f"{model_file or 'body model'}: cannot tell which links play the roles {missing} "
            f"from the link names" + (f" (ambiguous: {tied})" if tied else "")
            + f"; write {roles_file} (see docs/USER_GUIDE.md, 'Your body')"
        )
    source = str(overrides.get("_source") or f"{model_file} (roles inferred)")
    return derive_roles(
        chain, geometry, links, source=source,
        torso_geoms=overrides.get("torso_geoms"), limb_geoms=overrides.get("limb_geoms"),
        skin_geoms=overrides.get("skin_geoms"), mirror=overrides.get("mirror", ()),
        keypoints=overrides.get("keypoints"),
    )  # fmt: skip


# ----------------------------------------------------------------------------- roles file
def roles_path(model_file: str | os.PathLike) -> Path:
    """``<dir>/<stem>.roles.json`` beside a model file."""
    p = Path(model_file)
    return p.with_name(p.stem + ".roles.json")


_ROLE_FILE_KEYS = ("version", "links", "torso_geoms", "limb_geoms", "skin_geoms", "mirror",
                   "keypoints")


def read_roles_file(path: str | os.PathLike) -> dict:
    """The validated contents of a roles file (format in docs/USER_GUIDE.md)."""
    from jaxmocap.io.preflight import read_json

    path = Path(path)
    data = read_json(path, "a roles file, format in docs/USER_GUIDE.md")
    if not isinstance(data, dict):
        raise InputError(f"{path}: expected a JSON object with 'links' etc.")
    unknown = [k for k in data if k not in _ROLE_FILE_KEYS]
    if unknown:
        raise InputError(f"{path}: unknown fields {unknown}; expected {list(_ROLE_FILE_KEYS)}")
    links = data.get("links", {})
    if not isinstance(links, dict) or not all(isinstance(v, str) for v in links.values()):
        raise InputError(f"{path}: 'links' must map role names to link names")
    bad = [r for r in links if r not in LINK_ROLES]
    if bad:
        raise InputError(f"{path}: 'links' has unknown roles {bad}; roles: {list(LINK_ROLES)}")
    for key in ("torso_geoms", "skin_geoms"):
        v = data.get(key)
        if v is not None and not (isinstance(v, list) and all(isinstance(s, str) for s in v)):
            raise InputError(f"{path}: {key!r} must be a list of geom names")
    limbs = data.get("limb_geoms")
    if limbs is not None and not (isinstance(limbs, dict) and set(limbs) <= set(CONTOUR_LIMBS)
                                  and all(isinstance(v, list) for v in limbs.values())):
        raise InputError(f"{path}: 'limb_geoms' must map {list(CONTOUR_LIMBS)} to geom lists")
    mirror = data.get("mirror", [])
    if not (isinstance(mirror, list) and all(
            isinstance(p, list) and len(p) == 2 and all(isinstance(s, str) for s in p)
            for p in mirror)):
        raise InputError(f"{path}: 'mirror' must be a list of [left joint, right joint] pairs")
    kps = data.get("keypoints")
    if kps is not None:

        ok = isinstance(kps, dict) and all(
            k in KEYPOINT_NAMES and isinstance(v, list) and len(v) == 2 and isinstance(v[0], str)
            and isinstance(v[1], list) and len(v[1]) == 3 for k, v in kps.items())
        if not ok:
            raise InputError(f"{path}: 'keypoints' must map keypoint names {KEYPOINT_NAMES} to "
                             "[link, [x, y, z]]")
    data = dict(data)
    data["mirror"] = [tuple(p) for p in mirror]
    data["_source"] = str(path)
    return data


def roles_to_json(roles: BodyRoles) -> dict:
    """A roles file that reproduces ``roles`` exactly (links, geoms, pairs and keypoints)."""
    pairs = {(a, b) for a, b, _ in roles.mirror}
    return {
        "version": 1,
        "links": dict(roles.links),
        "torso_geoms": list(roles.torso_geoms),
        "limb_geoms": {r: list(g) for r, g in roles.limb_geoms},
        "skin_geoms": list(roles.skin_geoms),
        "mirror": [[a, b] for a, b, _ in roles.mirror if (b, a) not in pairs or a <= b],
        "keypoints": {k: [link, list(off)] for k, link, off in roles.keypoints},
    }


def face_forward(chain: KinematicChain, roles: BodyRoles) -> KinematicChain:
    """``chain`` turned about the vertical so that at q = 0 the body faces +x with its left
    (right -> left shoulder) along +y, as every stage assumes (dm_control's CMU humanoid faces
    -y): the turn goes into the root link's fixed offset. The same chain when it already
    does (within 1e-6 rad)."""
    rest = rest_transforms(chain)
    table = roles.keypoint_table()

    def world(k):
        link, off = table[k]
        return rest[chain.link_names.index(link)] @ np.append(np.asarray(off, float), 1.0)

    left = (world("l_shoulder") - world("r_shoulder"))[:3]
    angle = math.atan2(left[1], left[0]) - math.pi / 2  # the turn that took +y to `left`
    if math.hypot(left[0], left[1]) < 1e-9 or abs(angle) < 1e-6:
        return chain
    c, s_ = math.cos(-angle), math.sin(-angle)
    turn = np.array([[c, -s_, 0, 0], [s_, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
    origin = np.asarray(chain.joint_origin, np.float64).copy()
    origin[0] = turn @ origin[0]
    return eqx.tree_at(lambda ch: ch.joint_origin, chain,
                       jnp.asarray(origin, chain.joint_origin.dtype))


def body_digest(model) -> str:
    """A short stable hash (16 hex digits) of a body: chain, geometry, keypoints and roles.

    Arrays are hashed as float32 (the same whether JAX runs in x64 or not); pose databases and
    IK covariances are keyed by it."""
    import hashlib

    h = hashlib.sha256()
    chain, geo = model.chain, model.geometry
    for a in (chain.joint_origin, chain.joint_axis, chain.lower, chain.upper, geo.pose, geo.size,
              geo.rgba, model.keypoint_offset):
        h.update(np.ascontiguousarray(np.asarray(a, np.float32)).tobytes())
    for a in (chain.parents, chain.joint_type, chain.dof_index, geo.link, geo.kind,
              model.keypoint_link):
        h.update(np.ascontiguousarray(np.asarray(a, np.int64)).tobytes())
    names = (chain.link_names, chain.dof_names, geo.names, model.keypoint_names)
    h.update(json.dumps(names).encode())
    roles = model.roles
    if roles is not None:
        h.update(json.dumps(roles_to_json(roles), sort_keys=True).encode())
    return h.hexdigest()[:16]
