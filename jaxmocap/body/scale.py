"""Bodies of other proportions, names and primitives, derived from the bundled upper body.

**Scaling from measurements** (beyond the papers: Wang et al. 2011 §6 name "a generic upper
body shape" as their limit). :func:`scale_body` scales :func:`~jaxmocap.body.default_body`
from up to four measurements, each optional:

* ``height`` — standing height, floor to the top of the head. The body has no legs: its
  pelvis stands at ``REFERENCE_PELVIS_HEIGHT`` (0.87 m, the DeepMimic clips' standing pelvis
  height: walk clip mean 0.862 m, legs 0.4215 + 0.4099 m + ankle) times the height factor, so
  ``height = s_h (REFERENCE_PELVIS_HEIGHT + head top above the pelvis at rest)``; the bundled
  body is 1.65 m tall. A motion driven on the scaled body has its root translation scaled by
  ``s_h`` too (:attr:`ScaledBody.root_scale`).
* ``shoulder_width`` — distance between the two shoulder joint centres (bundled: 0.36 m);
* ``upper_arm`` — shoulder joint to elbow joint (bundled: 0.30 m);
* ``forearm`` — elbow joint to wrist joint (bundled: 0.26 m).

A missing measurement follows the height factor; a missing height is the geometric mean of
the factors given (1 if none). Each link has an axis-aligned scale ``S = diag(s_x, s_y, s_z)``
in its own frame (the bundled body's link frames are all world-aligned at rest): torso links
(pelvis, chest) ``(s_h, s_w, s_h)`` — the shoulder width widens the chest, abdomen, thorax and
shoulder girdle —, the head and hands ``s_h``, upper arms ``(s_h, s_h, s_ua)`` and forearms
``(s_h, s_h, s_fa)`` (girth with the height, length along the bone). A child's joint origin,
a keypoint offset and a geom's position are multiplied by the parent link's ``S``; a geom's
size per geom axis ``k`` by ``|S R_g e_k|`` (capsule/cylinder radius: the geometric mean of
its two cross axes). Garment half-spaces move with the geoms (:func:`scale_garment`).

**Foreign names** (:func:`rename_body`, conventions ``NAMINGS``): ``left_right``
(``left_upper_arm``, ``left_forearm``, ``left_hand``, ``torso``, ``left_shoulder_x`` ...) and
``mixamo`` (``Hips``, ``Spine``, ``Head``, ``LeftArm``, ``LeftForeArm``, ``LeftHand``,
``LeftShoulder_x`` ...). Keypoint names stay the library's (they name ground-truth points,
not parts of the file). **Other primitives** (:func:`swap_capsules`): every capsule becomes a
cylinder or a box of the same total length (``h + r``) and radius (box: ``2r x 2r``).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Mapping
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxmocap.errors import InputError

from .chain import KinematicChain
from .geometry import BOX, CAPSULE, CYLINDER, ELLIPSOID, SPHERE, Geometry
from .load import default_body
from .model import BodyModel, keypoint_index

REFERENCE_PELVIS_HEIGHT = 0.87  # m, standing pelvis height of the motion source (docstring)
MEASUREMENTS = ("height", "shoulder_width", "upper_arm", "forearm")
MEASUREMENT_RANGE = (0.5, 1.6)  # allowed factor w.r.t. the bundled body, per measurement
# Scale segment of the link playing each role (links of no role listed: isotropic s_h).
_SEGMENT = {
    "pelvis": "torso", "chest": "torso", "head": "head",
    "l_upper_arm": "upper_arm", "r_upper_arm": "upper_arm",
    "l_forearm": "forearm", "r_forearm": "forearm", "l_hand": "hand", "r_hand": "hand",
}  # fmt: skip


class BodyScaleError(InputError):
    """A measurement outside the range the bundled body can be scaled to."""


class ScaledBody(NamedTuple):
    """A scaled body: the model, its factors (``height``, ``shoulder_width``, ``upper_arm``,
    ``forearm``), ``root_scale`` (multiply a motion's root translation by it) and
    ``geom_scale`` (n_geoms, 3): the scale of each geom frame's axes (for the garment)."""

    model: BodyModel
    factors: dict[str, float]
    root_scale: float
    geom_scale: np.ndarray

    @property
    def pelvis_height(self) -> float:
        """Standing pelvis height (m) of the scaled body."""
        return self.root_scale * REFERENCE_PELVIS_HEIGHT


def measure(model: BodyModel, pelvis_height: float = REFERENCE_PELVIS_HEIGHT
            ) -> dict[str, float]:
    """The four measurements of a body with the library's keypoints at rest (module doc),
    its pelvis standing at ``pelvis_height`` (a scaled body's: ``root_scale`` times the
    reference, :attr:`ScaledBody.pelvis_height`)."""
    from .chain import fk
    from .model import geom_world_poses, keypoints

    q = jnp.zeros((model.n_dof,), model.chain.joint_origin.dtype)
    kp = np.asarray(keypoints(model, q), float)
    i = dict(zip(model.keypoint_names, range(len(model.keypoint_names)), strict=True))
    keypoint_index(model, ("l_shoulder", "r_shoulder", "l_elbow", "l_wrist", "pelvis"))
    g = model.geometry
    poses = np.asarray(geom_world_poses(model, fk(model.chain, q)), float)
    size = np.asarray(g.size, float)
    top = -np.inf
    for k in range(g.n_geoms):
        top = max(top, _geom_top(int(g.kind[k]), poses[k], size[k]))
    pelvis = kp[i["pelvis"]]
    return {
        "height": float(top - pelvis[2] + pelvis_height),
        "shoulder_width": float(np.linalg.norm(kp[i["l_shoulder"]] - kp[i["r_shoulder"]])),
        "upper_arm": float(np.linalg.norm(kp[i["l_shoulder"]] - kp[i["l_elbow"]])),
        "forearm": float(np.linalg.norm(kp[i["l_elbow"]] - kp[i["l_wrist"]])),
    }


def _geom_top(kind: int, pose: np.ndarray, size: np.ndarray) -> float:
    """Highest world z of a posed geom (exact for every primitive)."""
    r, c = pose[:3, :3], pose[2, 3]
    if kind == SPHERE:
        return c + size[0]
    if kind == ELLIPSOID:
        return c + float(np.linalg.norm(r[2] * size))
    if kind == BOX:
        return c + float(np.abs(r[2] * size).sum())
    axial = abs(r[2, 2]) * size[1]
    radial = size[0] * float(np.hypot(r[2, 0], r[2, 1]))
    return c + axial + (size[0] if kind == CAPSULE else radial)


def scale_factors(measurements: Mapping[str, float | None], reference: Mapping[str, float]
                  ) -> dict[str, float]:
    """Factors per measurement (module docstring); raises :class:`BodyScaleError`."""
    unknown = sorted(set(measurements) - set(MEASUREMENTS))
    if unknown:
        raise BodyScaleError(f"unknown measurement(s) {unknown}; known: {list(MEASUREMENTS)}")
    given = {}
    for name in MEASUREMENTS:
        v = measurements.get(name)
        if v is None:
            continue
        f = float(v) / reference[name]
        lo, hi = MEASUREMENT_RANGE
        if not (np.isfinite(f) and lo <= f <= hi):
            raise BodyScaleError(
                f"{name}: {v} m is outside {lo * reference[name]:.3f}..{hi * reference[name]:.3f}"
                f" m ({lo}x..{hi}x the bundled body's {reference[name]:.3f} m)")
        given[name] = f
    if "height" in given:
        s_h = given["height"]
    elif given:
        s_h = float(np.exp(np.mean(np.log(list(given.values())))))
    else:
        s_h = 1.0
    return {name: given.get(name, s_h) for name in MEASUREMENTS} | {"height": s_h}


def scale_body(model: BodyModel | None = None, **measurements: float | None) -> ScaledBody:
    """The bundled body (or ``model``, which must have roles and world-aligned rest frames)
    scaled to the given measurements in metres (module docstring)."""
    model = default_body() if model is None else model
    chain, geom = model.chain, model.geometry
    origin = np.array(chain.joint_origin, np.float64)
    if not np.allclose(origin[:, :3, :3], np.eye(3), atol=1e-9):
        raise ValueError("scale_body: the body's joint origins must not rotate (rest link "
                         "frames world-aligned, as the bundled body's)")
    from .roles import require_roles

    roles = require_roles(model, "scale_body")
    segment_of = {roles.link(role): seg for role, seg in _SEGMENT.items()}  # link -> segment
    f = scale_factors(measurements, measure(model))
    s_h, s_w = f["height"], f["shoulder_width"]
    seg_scale = {"torso": (s_h, s_w, s_h), "head": (s_h,) * 3, "hand": (s_h,) * 3,
                 "upper_arm": (s_h, s_h, f["upper_arm"]), "forearm": (s_h, s_h, f["forearm"])}
    link_s = np.array([seg_scale[segment_of[n]] if n in segment_of else (s_h,) * 3
                       for n in chain.link_names], np.float64)
    parents = np.asarray(chain.parents)
    new_origin = origin.copy()
    for i in range(1, chain.n_links):
        new_origin[i, :3, 3] *= link_s[parents[i]]
    pose = np.array(geom.pose, np.float64)
    size = np.array(geom.size, np.float64)
    kinds = np.asarray(geom.kind)
    glink = np.asarray(geom.link)
    geom_scale = np.ones((geom.n_geoms, 3))
    for k in range(geom.n_geoms):
        s = link_s[glink[k]]
        pose[k, :3, 3] *= s
        axis_s = np.linalg.norm(s[:, None] * pose[k, :3, :3], axis=0)  # |S R e_k|
        geom_scale[k] = axis_s
        kind = int(kinds[k])
        if kind == SPHERE:
            size[k, 0] *= float(np.cbrt(np.prod(axis_s)))
        elif kind in (CAPSULE, CYLINDER):
            size[k, 0] *= float(np.sqrt(axis_s[0] * axis_s[1]))
            size[k, 1] *= axis_s[2]
        else:
            size[k] *= axis_s
    kp_off = np.array(model.keypoint_offset, np.float64) * link_s[np.asarray(model.keypoint_link)]
    dt = chain.joint_origin.dtype
    new_chain = _chain_with(chain, joint_origin=jnp.asarray(new_origin, dt))
    new_geom = Geometry(link=geom.link, kind=geom.kind, pose=jnp.asarray(pose, dt),
                        size=jnp.asarray(size, dt), rgba=geom.rgba, names=geom.names,
                        materials=geom.materials)
    scaled = BodyModel(chain=new_chain, geometry=new_geom, keypoint_link=model.keypoint_link,
                       keypoint_offset=jnp.asarray(kp_off, model.keypoint_offset.dtype),
                       keypoint_names=model.keypoint_names,
                       roles=_roles_with(model, keypoint_offset=kp_off))
    return ScaledBody(scaled, f, s_h, geom_scale)


def _roles_with(model: BodyModel, name=None, keypoint_offset=None):
    """``model.roles`` with link / DOF / geom names mapped by ``name`` and the keypoint
    offsets replaced (None if the model has no roles)."""
    import dataclasses

    roles = getattr(model, "roles", None)
    if roles is None:
        return None
    f = name or (lambda s: s)
    kp = roles.keypoints
    if keypoint_offset is not None:
        off = {k: tuple(float(v) for v in keypoint_offset[i])
               for i, k in enumerate(model.keypoint_names)}
        kp = tuple((k, link, off.get(k, o)) for k, link, o in kp)
    return dataclasses.replace(
        roles, links=tuple((r, f(n)) for r, n in roles.links),
        joints=tuple((r, tuple(f(d) for d in ds)) for r, ds in roles.joints),
        limb_geoms=tuple((r, tuple(f(g) for g in gs)) for r, gs in roles.limb_geoms),
        torso_geoms=tuple(f(g) for g in roles.torso_geoms),
        skin_geoms=tuple(f(g) for g in roles.skin_geoms),
        mirror=tuple((f(a), f(b), sg) for a, b, sg in roles.mirror),
        keypoints=tuple((k, f(link), o) for k, link, o in kp), source=roles.source)


def _chain_with(chain: KinematicChain, *, joint_origin=None, link_names=None, dof_names=None
                ) -> KinematicChain:
    return KinematicChain(
        parents=chain.parents, joint_origin=chain.joint_origin if joint_origin is None
        else joint_origin, joint_axis=chain.joint_axis, joint_type=chain.joint_type,
        dof_index=chain.dof_index, lower=chain.lower, upper=chain.upper,
        link_names=chain.link_names if link_names is None else link_names,
        dof_names=chain.dof_names if dof_names is None else dof_names)


def scale_garment(garment, geom_scale: np.ndarray):
    """The garment's half-spaces moved with geoms scaled per axis by ``geom_scale``
    (n_geoms, 3): ``a . p + b <= 0`` becomes ``(D^-1 a) . p' + b <= 0`` for ``p' = D p``,
    renormalised so that ``|a| = 1`` again (unused rows stay unused)."""
    import equinox as eqx

    planes = np.array(garment.patch_planes, np.float64)
    d = np.asarray(geom_scale, float)[np.asarray(garment.patch_geom)]  # (P, 3)
    a = planes[..., :3] / d[:, None, :]
    norm = np.linalg.norm(a, axis=-1, keepdims=True)
    used = norm[..., 0] > 0
    planes[..., :3] = np.where(used[..., None], a / np.where(used, norm[..., 0], 1)[..., None],
                               0.0)
    planes[..., 3] = np.where(used, planes[..., 3] / np.where(used, norm[..., 0], 1),
                              planes[..., 3])
    return eqx.tree_at(lambda g: g.patch_planes, garment,
                       jnp.asarray(planes, garment.patch_planes.dtype))


# ----------------------------------------------------------------------------- names

_MIXAMO = {"pelvis": "Hips", "chest": "Spine", "head": "Head", "upper_arm": "Arm",
           "forearm": "ForeArm", "hand": "Hand", "spine": "Spine", "neck": "Neck",
           "shoulder": "Shoulder", "elbow": "Elbow", "wrist": "Wrist", "abdomen": "Belly",
           "thorax": "Chest", "shoulders": "Shoulders"}
_LR = {"chest": "torso", "thorax": "torso_upper", "abdomen": "torso_lower",
       "shoulders": "shoulder_girdle"}


def _left_right(name: str) -> str:
    base, sep, rest = name.partition("__")
    m = re.fullmatch(r"([lr])_(.+)", base)
    if m:
        base = ("left_" if m.group(1) == "l" else "right_") + m.group(2)
    else:
        base = _LR.get(base, base)
    return base + sep + rest


def _mixamo(name: str) -> str:
    base, sep, rest = name.partition("__")
    side = ""
    m = re.fullmatch(r"([lr])_(.+)", base)
    if m:
        side, base = ("Left" if m.group(1) == "l" else "Right"), m.group(2)
    suffix = ""
    m = re.fullmatch(r"(.+)_([xyz])", base)
    if m and m.group(1) in _MIXAMO:
        base, suffix = m.group(1), "_" + m.group(2)
    if base not in _MIXAMO:
        return name
    return side + _MIXAMO[base] + suffix + sep + rest


NAMINGS: dict[str, Callable[[str], str]] = {
    "jaxmocap": lambda s: s, "left_right": _left_right, "mixamo": _mixamo}


def rename_body(model: BodyModel, naming: str | Callable[[str], str] | Mapping[str, str]
                ) -> BodyModel:
    """The same body with links, joints (DOFs) and geoms renamed: ``naming`` is a convention
    of ``NAMINGS``, a function of the old name, or a ``{old: new}`` table (others kept).
    Root DOFs (``root_tx`` ...) and keypoint names are kept. Raises ``ValueError`` if two
    parts of one kind would get the same name."""
    if isinstance(naming, str):
        if naming not in NAMINGS:
            raise InputError(f"naming {naming!r}: expected one of {sorted(NAMINGS)}")
        fn = NAMINGS[naming]
    elif isinstance(naming, Mapping):
        table = dict(naming)
        fn = lambda s: table.get(s, s)
    else:
        fn = naming
    chain, geom = model.chain, model.geometry
    links = tuple(fn(n) for n in chain.link_names)
    dofs = tuple(n if n.startswith("root_") else fn(n) for n in chain.dof_names)
    geoms = tuple(fn(n) for n in geom.names)
    for what, names in (("link", links), ("joint", dofs), ("geom", geoms)):
        if len(set(names)) != len(names):
            raise ValueError(f"rename_body: two {what}s would share a name: {names}")
    new_geom = Geometry(link=geom.link, kind=geom.kind, pose=geom.pose, size=geom.size,
                        rgba=geom.rgba, names=geoms, materials=geom.materials)
    dof = lambda s: s if s.startswith("root_") else fn(s)
    return BodyModel(chain=_chain_with(chain, link_names=links, dof_names=dofs),
                     geometry=new_geom, keypoint_link=model.keypoint_link,
                     keypoint_offset=model.keypoint_offset,
                     keypoint_names=model.keypoint_names, roles=_roles_with(model, dof))


def swap_capsules(model: BodyModel, kind: str) -> BodyModel:
    """Every capsule geom as a ``"cylinder"`` or ``"box"`` of the same total length and
    radius (``"capsule"``: unchanged). The geom frame (z along the limb) is kept, so garment
    half-spaces in it still apply."""
    if kind == "capsule":
        return model
    if kind not in ("cylinder", "box"):
        raise InputError(f"limb primitive {kind!r}: expected capsule, cylinder or box")
    g = model.geometry
    kinds = np.array(g.kind)
    size = np.array(g.size, np.float64)
    cap = kinds == CAPSULE
    r, h = size[cap, 0].copy(), size[cap, 1].copy()
    if kind == "cylinder":
        kinds[cap] = CYLINDER
        size[cap] = np.stack([r, h + r, np.zeros_like(r)], -1)
    else:
        kinds[cap] = BOX
        size[cap] = np.stack([r, r, h + r], -1)
    new_geom = Geometry(link=g.link, kind=jnp.asarray(kinds, g.kind.dtype), pose=g.pose,
                        size=jnp.asarray(size, g.size.dtype), rgba=g.rgba, names=g.names,
                        materials=g.materials)
    return BodyModel(chain=model.chain, geometry=new_geom, keypoint_link=model.keypoint_link,
                     keypoint_offset=model.keypoint_offset,
                     keypoint_names=model.keypoint_names, roles=model.roles)
