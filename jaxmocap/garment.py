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

* :func:`default_garment` — the paper's shirt on :func:`jaxmocap.body.default_body`;
* :func:`garment_from_model` — every coloured geom of a model becomes a patch of its colour
  (how a user describes their own shirt, or uses a third-party model such as pybullet's
  humanoid);
* :func:`single_colour_garment` — Azad et al.'s set-up: one shirt colour plus skin.
"""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .body import BodyModel

RGB = ArrayLike | Sequence[float | int]  # an RGB triple in [0, 1]

MAX_HALF_SPACES = 3  # half-spaces per patch (Garment contract, docs/ARCHITECTURE.md)
NO_PLANE = (0.0, 0.0, 0.0, -1.0)  # 0 . p - 1 <= 0 holds everywhere: an unused half-space
SKIN_RGB = (0.87, 0.67, 0.55)  # a light skin albedo (linear RGB in [0, 1])
BODY_RGB = (0.35, 0.35, 0.38)  # neutral albedo of body parts the shirt does not cover
SKIN_LINK_WORDS = ("head", "neck", "hand")  # link names whose geoms count as skin by default

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
    """Geoms attached to links whose name contains ``head``, ``neck`` or ``hand``."""
    links = model.chain.link_names
    link_of = np.asarray(model.geometry.link)
    return tuple(
        g
        for g, li in zip(model.geometry.names, link_of, strict=False)
        if any(w in links[li].lower() for w in SKIN_LINK_WORDS)
    )


# The paper's shirt on the bundled body (geom frames: thorax/abdomen x forward, y left, z up;
# shoulders capsule z = link -y; arm capsules z along the arm, +z towards the shoulder).
# Thorax: front/back x left/right, plus the two flanks |y| > FLANK_Y; abdomen: front/back x
# left/right; shoulders: left/right; upper arms and forearms: proximal/distal halves. Each
# colour sits on one torso patch and one limb patch on the *other* side of the body, chosen to
# maximise the smallest distance between same-coloured patches (>= 0.32 m between centroids at
# rest), so the two patches of a colour never touch and every neighbour differs.
FLANK_Y = 0.11  # m, thorax half-width beyond which the flank patches start (thorax b = 0.17)
_FRONT, _BACK = (-1.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)  # x >= 0, x <= 0
_LEFT, _RIGHT = (0.0, -1.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)  # y >= 0, y <= 0
_UP, _DOWN = (0.0, 0.0, -1.0, 0.0), (0.0, 0.0, 1.0, 0.0)  # z >= 0, z <= 0
_MID_L, _MID_R = (0.0, 1.0, 0.0, -FLANK_Y), (0.0, -1.0, 0.0, -FLANK_Y)  # |y| <= FLANK_Y
_FLANK_L, _FLANK_R = (0.0, -1.0, 0.0, FLANK_Y), (0.0, 1.0, 0.0, FLANK_Y)  # |y| >= FLANK_Y
# (patch name, geom, half-spaces, colour name)
DEFAULT_SHIRT = (
    ("chest_front_left", "thorax", (_FRONT, _LEFT, _MID_L), "red"),
    ("chest_front_right", "thorax", (_FRONT, _RIGHT, _MID_R), "orange"),
    ("chest_back_left", "thorax", (_BACK, _LEFT, _MID_L), "yellow"),
    ("chest_back_right", "thorax", (_BACK, _RIGHT, _MID_R), "lime"),
    ("flank_left", "thorax", (_FLANK_L,), "magenta"),
    ("flank_right", "thorax", (_FLANK_R,), "pink"),
    ("belly_front_left", "abdomen", (_FRONT, _LEFT), "green"),
    ("belly_front_right", "abdomen", (_FRONT, _RIGHT), "cyan"),
    ("belly_back_left", "abdomen", (_BACK, _LEFT), "blue"),
    ("belly_back_right", "abdomen", (_BACK, _RIGHT), "purple"),
    ("shoulder_left", "shoulders", (_DOWN,), "cyan"),  # geom z = link -y: z <= 0 is left
    ("shoulder_right", "shoulders", (_UP,), "green"),
    ("l_upper_arm_top", "l_upper_arm", (_UP,), "purple"),
    ("l_upper_arm_bottom", "l_upper_arm", (_DOWN,), "pink"),
    ("r_upper_arm_top", "r_upper_arm", (_UP,), "blue"),
    ("r_upper_arm_bottom", "r_upper_arm", (_DOWN,), "magenta"),
    ("l_forearm_top", "l_forearm", (_UP,), "lime"),
    ("l_forearm_bottom", "l_forearm", (_DOWN,), "orange"),
    ("r_forearm_top", "r_forearm", (_UP,), "yellow"),
    ("r_forearm_bottom", "r_forearm", (_DOWN,), "red"),
)


def default_garment(model: BodyModel | None = None) -> Garment:
    """Wang et al.'s shirt (§4): 20 patches, 10 colours each used twice, on the bundled body
    (:func:`jaxmocap.body.default_body` unless another model with the same geom names is
    given). Head, neck and hands are skin; the pelvis is unpatched (trousers)."""
    from .body import default_body

    model = default_body() if model is None else model
    colour_ids = {name: i + 1 for i, (name, _) in enumerate(SHIRT_COLOURS)}
    patches = [(n, g, hs, colour_ids[c]) for n, g, hs, c in DEFAULT_SHIRT]
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


def garment_from_model(
    model: BodyModel,
    skin_geoms: Sequence[str] | None = None,
    skin_rgb: RGB = SKIN_RGB,
    body_rgb: RGB = BODY_RGB,
) -> Garment:
    """Each non-skin geom becomes one patch of its own ``rgba`` colour; distinct RGB values
    (compared at 8 bits) become colour ids 1..n in order of first appearance.

    This is how a user describes their own shirt (colour the geoms of a URDF/MJCF) and how a
    third-party model (e.g. pybullet's humanoid) is rendered. Skin geoms default to
    :func:`default_skin_geoms`; geoms with alpha 0 are left unpatched."""
    skin_geoms = default_skin_geoms(model) if skin_geoms is None else tuple(skin_geoms)
    rgba = np.asarray(model.geometry.rgba)
    keys: dict[tuple[int, int, int], int] = {}
    patches = []
    for g, name in enumerate(model.geometry.names):
        if name in skin_geoms or rgba[g, 3] <= 0:
            continue
        key = _rgb_key(rgba[g, :3])
        keys.setdefault(key, len(keys) + 1)
        patches.append((name, name, [], keys[key]))
    colours = [(f"rgb{k}", np.array(k) / 255.0) for k in keys]
    return make_garment(model, patches, colours, skin_geoms, skin_rgb, body_rgb)


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
