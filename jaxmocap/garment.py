"""The garment: which part of which body geom carries which colour (Wang et al. 2011 §4–5).

Wang et al.'s shirt is "composed of 20 patches colored with a set of 10 distinct colors, each
of which appears twice" (§4). Here a **patch** is a region of one geom of the body model,

    patch i = (geom g_i,  half-spaces  a_ij . p + b_ij <= 0, j = 1..3,  colour id k_i)

with ``p`` a point in the geom frame (metres). A surface point of geom g belongs to the first
patch of g whose half-spaces all contain it. **Patch id** 0 is background or an unpatched body
part; patches are ``1..P``; **colour id** 0 is "no shirt colour", shirt colours are
``1..n_colours`` with an RGB albedo table. Skin geoms (head, neck, hands) are flagged so that the
renderer shades them with a skin albedo, and the stereo tracker (Azad et al. 2007) segments
them as skin.

Constructors:

* :func:`default_garment` — the paper's shirt, placed by the body's roles
  (:func:`jaxmocap.body.default_body` by default);
* :func:`garment_from_model` — the coloured geoms of the shirt's role links (chest, upper arms,
  forearms; not trousers or shoes unless asked) become patches of their colours (how a user
  describes their own shirt, or uses a third-party model such as pybullet's humanoid);
* :func:`single_colour_garment` — Azad et al.'s set-up: one shirt colour plus skin;
* :func:`jaxmocap.io.garment_file.load_garment` / ``save_garment`` — the user's shirt as
  ``garment.json`` (docs/USER_GUIDE.md, "Your shirt").
"""

from __future__ import annotations

import json
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .body import CAPSULE, CYLINDER, BodyModel, require_roles
from .body.roles import CONTOUR_LIMBS
from .errors import InputError

RGB = ArrayLike | Sequence[float | int]  # an RGB triple in [0, 1]

MAX_HALF_SPACES = 3  # half-spaces per patch (Garment contract, docs/ARCHITECTURE.md)
NO_PLANE = (0.0, 0.0, 0.0, -1.0)  # 0 . p - 1 <= 0 holds everywhere: an unused half-space
SKIN_RGB = (0.87, 0.67, 0.55)  # a light skin albedo (linear RGB in [0, 1])
BODY_RGB = (0.35, 0.35, 0.38)  # neutral albedo of body parts the shirt does not cover

# The 10 shirt colours (Wang et al. §4: "10 distinct colors"): saturated hues spread around the
# hue circle (no white, grey or black: those are the background's and the trousers' colours,
# and the paper's classifier and histogram search work on colour). Linear RGB albedo in [0, 1].
SHIRT_COLOURS = (
    ("red", (0.85, 0.08, 0.08)),
    ("orange", (0.95, 0.45, 0.05)),
    ("yellow", (0.90, 0.85, 0.10)),
    ("lime", (0.45, 0.85, 0.10)),
    ("green", (0.05, 0.55, 0.20)),
    ("cyan", (0.10, 0.80, 0.85)),
    ("blue", (0.08, 0.20, 0.85)),
    ("purple", (0.45, 0.10, 0.70)),
    ("magenta", (0.90, 0.15, 0.65)),
    ("pink", (0.98, 0.60, 0.70)),
)


class Garment(eqx.Module):
    """Patches on the geoms of a body model, their colours, and the skin geoms.

    ``patch_planes[i, j] = (a_x, a_y, a_z, b)``: patch i contains the geom-frame points with
    ``a . p + b <= 0`` for every j (unused rows are ``NO_PLANE``). ``patch_colour[i]`` is the
    colour id in ``1..n_colours`` of patch ``i + 1``; ``colours[k - 1]`` is the RGB albedo of
    colour id k.
    """

    patch_geom: Int[Array, " n_patches"]
    patch_planes: Float[Array, "n_patches 3 4"]
    patch_colour: Int[Array, " n_patches"]
    colours: Float[Array, "n_colours 3"]
    skin: Bool[Array, " n_geoms"]
    skin_rgb: Float[Array, " 3"]
    body_rgb: Float[Array, " 3"]
    patch_names: tuple[str, ...] = eqx.field(static=True)
    colour_names: tuple[str, ...] = eqx.field(static=True)

    def __check_init__(self):
        n_p, n_c = len(self.patch_names), len(self.colour_names)
        shapes = {
            "patch_geom": (n_p,),
            "patch_planes": (n_p, MAX_HALF_SPACES, 4),
            "patch_colour": (n_p,),
            "colours": (n_c, 3),
        }
        for name, shape in shapes.items():
            if getattr(self, name).shape != shape:
                raise ValueError(
                    f"Garment.{name}: expected shape {shape}, got {getattr(self, name).shape}"
                )
        if isinstance(self.patch_colour, jax.core.Tracer) or isinstance(
            self.colours, jax.core.Tracer
        ):
            return
        col = np.asarray(self.patch_colour)
        if col.size and (col.min() < 1 or col.max() > n_c):
            raise ValueError(
                f"Garment.patch_colour: colour ids must lie in 1..{n_c}, got {sorted(set(col))}"
            )
        rgb = np.asarray(self.colours)
        if rgb.size and (rgb.min() < 0 or rgb.max() > 1):
            raise ValueError("Garment.colours: RGB albedo must lie in [0, 1]")

    @property
    def n_patches(self) -> int:
        return len(self.patch_names)

    @property
    def n_colours(self) -> int:
        return len(self.colour_names)


def make_garment(
    model: BodyModel,
    patches: Sequence[tuple[str, str, Sequence[Sequence[float | int]] | np.ndarray, int]],
    colours: Sequence[tuple[str, RGB]],
    skin_geoms: Sequence[str] = (),
    skin_rgb: RGB = SKIN_RGB,
    body_rgb: RGB = BODY_RGB,
) -> Garment:
    """Garment from readable rows: ``patches = [(name, geom name, half-spaces, colour id)]``
    with up to 3 half-spaces ``(a_x, a_y, a_z, b)`` each, ``colours = [(name, rgb)]``.

    Raises ``ValueError`` naming the patch for an unknown geom, too many half-spaces or a
    colour id outside ``1..len(colours)``."""
    names = model.geometry.names
    geom_ids, planes, colour_ids = [], [], []
    for name, geom, half_spaces, colour in patches:
        if geom not in names:
            raise ValueError(f"garment patch {name!r}: unknown geom {geom!r}; geoms: {names}")
        hs = np.asarray(half_spaces, dtype=float).reshape(-1, 4)
        if hs.shape[0] > MAX_HALF_SPACES:
            raise ValueError(
                f"garment patch {name!r}: {hs.shape[0]} half-spaces, at most {MAX_HALF_SPACES}"
            )
        if not 1 <= int(colour) <= len(colours):
            raise ValueError(
                f"garment patch {name!r}: colour id {colour} outside 1..{len(colours)}"
            )
        pad = np.tile(np.asarray(NO_PLANE), (MAX_HALF_SPACES - hs.shape[0], 1))
        geom_ids.append(names.index(geom))
        planes.append(np.concatenate([hs, pad]))
        colour_ids.append(int(colour))
    unknown = [g for g in skin_geoms if g not in names]
    if unknown:
        raise ValueError(f"garment skin_geoms: unknown geoms {unknown}; geoms: {names}")
    dtype = model.geometry.size.dtype
    return Garment(
        patch_geom=jnp.asarray(np.array(geom_ids, dtype=np.int32).reshape(-1)),
        patch_planes=jnp.asarray(np.array(planes).reshape(-1, MAX_HALF_SPACES, 4), dtype),
        patch_colour=jnp.asarray(np.array(colour_ids, dtype=np.int32).reshape(-1)),
        colours=jnp.asarray(np.array([c[1] for c in colours], dtype=float).reshape(-1, 3), dtype),
        skin=jnp.asarray(np.isin(np.array(names), np.array(list(skin_geoms), dtype=str))),
        skin_rgb=jnp.asarray(skin_rgb, dtype),
        body_rgb=jnp.asarray(body_rgb, dtype),
        patch_names=tuple(p[0] for p in patches),
        colour_names=tuple(c[0] for c in colours),
    )


def default_skin_geoms(model: BodyModel) -> tuple[str, ...]:
    """The body's skin geoms by its roles (head and neck, the hands and below them)."""
    return require_roles(model, "skin geoms").skin_geoms


# The paper's shirt, placed by roles (on the bundled body: thorax, abdomen, the shoulder capsule
# and the four arm capsules). Slots: the upper and the lower of two stacked torso geoms, the
# bar across the shoulders (a capsule/cylinder of the chest link lying along the body's y), and
# one capsule/cylinder per arm segment. Half-spaces are given in the *link* frame (x forward,
# y left, z up; a . p + b <= 0) and turned into the geom frame; arm segments split into their
# proximal (towards the shoulder) and distal halves. Upper torso: front/back x left/right, plus
# the two flanks |y| > FLANK_FRACTION x its half-width; lower torso: front/back x left/right;
# shoulders: left/right. Each colour sits on one torso patch and one limb patch on the *other*
# side of the body, chosen to maximise the smallest distance between same-coloured patches
# (>= 0.32 m between centroids at rest on the bundled body), so the two patches of a colour
# never touch and every neighbour differs.
FLANK_FRACTION = 0.11 / 0.17  # bundled: the flanks start at |y| = 0.11 m of the 0.17 m thorax
_FRONT, _BACK = (-1.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)  # x >= 0, x <= 0
_LEFT, _RIGHT = (0.0, -1.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)  # y >= 0, y <= 0
_MID_L, _MID_R = "mid_l", "mid_r"  # |y| <= flank (upper torso)
_FLANK_L, _FLANK_R = "flank_l", "flank_r"  # |y| >= flank
_PROX, _DIST = "proximal", "distal"
# (patch name, slot, half-spaces, colour name)
DEFAULT_SHIRT = (
    ("chest_front_left", "upper_torso", (_FRONT, _LEFT, _MID_L), "red"),
    ("chest_front_right", "upper_torso", (_FRONT, _RIGHT, _MID_R), "orange"),
    ("chest_back_left", "upper_torso", (_BACK, _LEFT, _MID_L), "yellow"),
    ("chest_back_right", "upper_torso", (_BACK, _RIGHT, _MID_R), "lime"),
    ("flank_left", "upper_torso", (_FLANK_L,), "magenta"),
    ("flank_right", "upper_torso", (_FLANK_R,), "pink"),
    ("belly_front_left", "lower_torso", (_FRONT, _LEFT), "green"),
    ("belly_front_right", "lower_torso", (_FRONT, _RIGHT), "cyan"),
    ("belly_back_left", "lower_torso", (_BACK, _LEFT), "blue"),
    ("belly_back_right", "lower_torso", (_BACK, _RIGHT), "purple"),
    ("shoulder_left", "shoulders", (_LEFT,), "cyan"),
    ("shoulder_right", "shoulders", (_RIGHT,), "green"),
    ("l_upper_arm_top", "l_upper_arm", (_PROX,), "purple"),
    ("l_upper_arm_bottom", "l_upper_arm", (_DIST,), "pink"),
    ("r_upper_arm_top", "r_upper_arm", (_PROX,), "blue"),
    ("r_upper_arm_bottom", "r_upper_arm", (_DIST,), "magenta"),
    ("l_forearm_top", "l_forearm", (_PROX,), "lime"),
    ("l_forearm_bottom", "l_forearm", (_DIST,), "orange"),
    ("r_forearm_top", "r_forearm", (_PROX,), "yellow"),
    ("r_forearm_bottom", "r_forearm", (_DIST,), "red"),
)


def _shirt_slots(model: BodyModel) -> dict[str, int]:
    """Geom index of every slot of :data:`DEFAULT_SHIRT` (one-line InputError if the body's
    geometry does not have the paper's layout)."""
    from .body.roles import is_crosswise, limb_axis

    roles = require_roles(model, "default_garment")
    geo = model.geometry
    names = geo.names
    kind = np.asarray(geo.kind)
    pose = np.asarray(geo.pose, np.float64)
    chest = model.chain.link_names.index(roles.link("chest"))
    torso = [names.index(g) for g in roles.torso_geoms]
    bars = [g for g, li in enumerate(np.asarray(geo.link).tolist())
            if li == chest and is_crosswise(geo, g) and names[g] not in roles.skin_geoms]
    problems = []
    if len(torso) != 2:
        problems.append(f"{len(torso)} torso geoms {roles.torso_geoms} (needs 2 stacked)")
    if len(bars) != 1:
        problems.append(f"{len(bars)} bars across the shoulders on the chest link (needs 1)")
    limbs = {}
    for role in CONTOUR_LIMBS:
        gs = roles.limb(role)
        g = names.index(gs[0]) if len(gs) == 1 else -1
        if g < 0 or kind[g] not in (CAPSULE, CYLINDER) or abs(
                pose[g, :3, 2] @ limb_axis(model, role)) < 0.9:
            problems.append(f"{role} geoms {gs} (needs one capsule/cylinder along the arm)")
        limbs[role] = g
    if problems:
        raise InputError(
            f"default_garment: the paper's 20-patch shirt does not fit {roles.source}: "
            + "; ".join(problems) + "; describe the shirt in a garment.json (docs/USER_GUIDE.md, "
            "'Your shirt')"
        )
    up = limb_axis(model, "torso")
    low, high = sorted(torso, key=lambda g: pose[g, :3, 3] @ up)
    return {"upper_torso": high, "lower_torso": low, "shoulders": bars[0], **limbs}


def _geom_plane(model: BodyModel, g: int, plane, role: str) -> tuple[float, ...]:
    """A link-frame half-space (or a named one of :data:`DEFAULT_SHIRT`) in geom ``g``'s frame,
    through the geom centre; normals snapped to 1e-12, offsets to 1 um."""
    from .body.roles import geom_support, limb_axis

    pose = np.asarray(model.geometry.pose, np.float64)[g]
    rot = pose[:3, :3]
    offset = 0.0
    if plane in (_PROX, _DIST):
        u = limb_axis(model, role)  # distal direction (link frame)
        n = u if plane == _PROX else -u  # proximal half: u . p <= 0
    elif isinstance(plane, str):  # flank planes of the upper torso
        size = np.asarray(model.geometry.size, np.float64)[g]
        flank = FLANK_FRACTION * geom_support(int(model.geometry.kind[g]), size, rot,
                                              np.array([0.0, 1.0, 0.0]))
        side = 1.0 if plane.endswith("_l") else -1.0
        n = np.array([0.0, side, 0.0]) * (1.0 if plane.startswith("mid") else -1.0)
        offset = -flank if plane.startswith("mid") else flank
    else:
        n, offset = np.asarray(plane[:3], float), float(plane[3])
    n_geom = rot.T @ n
    return tuple(float(v) for v in np.round(n_geom, 12) + 0.0) + (round(offset, 6) + 0.0,)


def default_garment(model: BodyModel | None = None) -> Garment:
    """Wang et al.'s shirt (§4): 20 patches, 10 colours each used twice, placed by the body's
    roles (:data:`DEFAULT_SHIRT`; default: :func:`jaxmocap.body.default_body`). A body without
    the paper's torso/arm layout is refused in one line (describe its shirt in a
    garment.json). Skin: the roles' skin geoms; the pelvis is unpatched (trousers)."""
    from .body import default_body

    model = default_body() if model is None else model
    slots = _shirt_slots(model)
    names = model.geometry.names
    colour_ids = {name: i + 1 for i, (name, _) in enumerate(SHIRT_COLOURS)}
    patches = [(n, names[slots[slot]], [_geom_plane(model, slots[slot], p, slot) for p in hs],
                colour_ids[c]) for n, slot, hs, c in DEFAULT_SHIRT]
    return make_garment(model, patches, SHIRT_COLOURS, default_skin_geoms(model))


# ----------------------------------------------------------------------------- lookups


def patch_at(garment: Garment, geom: Int[Array, "*n"], p: Float[Array, "*n 3"]) -> Int[Array, "*n"]:
    """Patch id (0 = none) of the surface point ``p`` (geom frame, metres) on geom ``geom``
    (``-1`` = background gives 0): the first patch of that geom whose half-spaces contain p."""
    planes = garment.patch_planes.astype(p.dtype)
    offset = planes[..., 3].reshape((1,) * (p.ndim - 1) + planes.shape[:2])
    vals = jnp.einsum("...k,pjk->...pj", p, planes[..., :3]) + offset
    owner = garment.patch_geom.reshape((1,) * geom.ndim + garment.patch_geom.shape)
    inside = jnp.all(vals <= 0, axis=-1) & (owner == geom[..., None])
    return jnp.where(jnp.any(inside, axis=-1), jnp.argmax(inside, axis=-1) + 1, 0).astype(jnp.int32)


def colour_of(garment: Garment, patch: Int[Array, "*n"]) -> Int[Array, "*n"]:
    """Colour id (0 = none, 1..n_colours) of patch ids (0 = none, 1..P)."""
    table = jnp.concatenate([jnp.zeros((1,), jnp.int32), garment.patch_colour.astype(jnp.int32)])
    return table[patch]


def albedo(
    garment: Garment, geom: Int[Array, "*n"], patch: Int[Array, "*n"]
) -> Float[Array, "*n 3"]:
    """RGB albedo of a surface point: its patch colour, else skin for skin geoms, else the
    neutral body colour (background, ``geom = -1``, also gets the body colour; callers
    composite the background themselves)."""
    colour = colour_of(garment, patch)
    shirt = garment.colours[jnp.maximum(colour - 1, 0)]
    skin = garment.skin[jnp.maximum(geom, 0)] & (geom >= 0)
    other = jnp.where(skin[..., None], garment.skin_rgb, garment.body_rgb)
    return jnp.where((colour > 0)[..., None], shirt, other)


# ----------------------------------------------------------------------------- constructors


def _rgb_key(rgb: np.ndarray) -> tuple[int, int, int]:
    return tuple(int(v) for v in np.round(np.clip(rgb, 0, 1) * 255))


SHIRT_ROLES = ("chest", "l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm")


def shirt_geoms(model: BodyModel) -> tuple[str, ...]:
    """The geoms a shirt covers, by the body's roles: those of the chest, upper-arm and
    forearm links (not the pelvis, legs or feet: trousers and shoes), skin excluded."""
    roles = require_roles(model, "shirt_geoms")
    links = {model.chain.link_names.index(roles.link(r)) for r in SHIRT_ROLES}
    geo = model.geometry
    return tuple(n for n, li in zip(geo.names, np.asarray(geo.link).tolist(), strict=True)
                 if li in links and n not in roles.skin_geoms)


def garment_from_model(
    model: BodyModel,
    skin_geoms: Sequence[str] | None = None,
    skin_rgb: RGB = SKIN_RGB,
    body_rgb: RGB = BODY_RGB,
    *,
    parts: str | Sequence[str] = "shirt",
    colours: Sequence[tuple[str, RGB]] | None = None,
) -> Garment:
    """The shirt is "these colours of the model": each chosen geom becomes one patch of its
    own ``rgba`` colour.

    ``parts``: ``"shirt"`` (default: :func:`shirt_geoms`, by roles -- trousers and shoes are
    not patches), ``"all"`` (every non-skin geom, e.g. a scene of props) or geom/link names.
    ``colours``: the user's named colours ``[(name, rgb)]`` in the order of their colour model
    (``colors.json``): colour id k is ``colours[k - 1]`` and a chosen geom is a patch only if
    its RGB matches one of them at 8 bits; None: the distinct RGB values of the chosen geoms in
    order of first appearance. Skin geoms default to the roles' (:func:`default_skin_geoms`);
    geoms with alpha 0 are left unpatched."""
    skin_geoms = default_skin_geoms(model) if skin_geoms is None else tuple(skin_geoms)
    names = model.geometry.names
    if isinstance(parts, str) and parts == "shirt":
        chosen = set(shirt_geoms(model))
    elif isinstance(parts, str) and parts == "all":
        chosen = set(names)
    else:
        chosen = set(_geoms_named(model, [parts] if isinstance(parts, str) else parts,
                                  "garment_from_model parts"))
    rgba = np.asarray(model.geometry.rgba)
    keys: dict[tuple[int, int, int], int] = {}
    if colours is not None:
        for k, (_, rgb) in enumerate(colours):
            keys.setdefault(_rgb_key(np.asarray(rgb, float)), k + 1)
    patches = []
    for g, name in enumerate(names):
        if name not in chosen or name in skin_geoms or rgba[g, 3] <= 0:
            continue
        key = _rgb_key(rgba[g, :3])
        if colours is None:
            keys.setdefault(key, len(keys) + 1)
        elif key not in keys:
            continue
        patches.append((name, name, [], keys[key]))
    if colours is None:
        colours = [(f"rgb{k}", np.array(k) / 255.0) for k in keys]
    return make_garment(model, patches, colours, skin_geoms, skin_rgb, body_rgb)


def _geoms_named(model: BodyModel, names: Sequence[str], where: str) -> list[str]:
    """Geom names for geom-or-link names (a link stands for all its geoms and those of the
    links fixed to it: URDF visuals on fixed child links belong to their parent)."""
    from .body.roles import owner_link

    geo, links = model.geometry, model.chain.link_names
    glink = np.asarray(geo.link).tolist()
    roles = {links.index(n) for _, n in model.roles.links} if model.roles is not None else set()
    out = []
    for n in names:
        if n in geo.names:
            out.append(n)
        elif n in links:
            li = links.index(n)  # (a fixed child playing a role of its own stays its own)
            out.extend(g for g, gl in zip(geo.names, glink, strict=True)
                       if owner_link(model.chain, gl, roles | {li}) == li)
        else:
            raise InputError(f"{where}: {n!r} is neither a geom nor a link of the body; geoms: "
                             f"{geo.names}")
    return out


def single_colour_garment(
    model: BodyModel,
    shirt_rgb: RGB,
    skin_rgb: RGB = SKIN_RGB,
    skin_geoms: Sequence[str] | None = None,
) -> Garment:
    """Azad et al. 2007's set-up: every non-skin geom is shirt (one colour id 1), head, neck
    and hands are skin."""
    skin_geoms = default_skin_geoms(model) if skin_geoms is None else tuple(skin_geoms)
    patches = [(n, n, [], 1) for n in model.geometry.names if n not in skin_geoms]
    return make_garment(model, patches, [("shirt", shirt_rgb)], skin_geoms, skin_rgb)


def garment_digest(garment: Garment) -> str:
    """A short stable hash (16 hex digits) of a garment: patches, half-spaces (as float32),
    colours, skin and names (with :func:`jaxmocap.body.body_digest`, what a pose database is
    built for)."""
    import hashlib

    h = hashlib.sha256()
    for a in (garment.patch_planes, garment.colours, garment.skin_rgb, garment.body_rgb):
        h.update(np.ascontiguousarray(np.asarray(a, np.float32)).tobytes())
    for a in (garment.patch_geom, garment.patch_colour, garment.skin):
        h.update(np.ascontiguousarray(np.asarray(a, np.int64)).tobytes())
    h.update(json.dumps([garment.patch_names, garment.colour_names]).encode())
    return h.hexdigest()[:16]
