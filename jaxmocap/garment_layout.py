"""Shirts generated, not designed: random patch layouts over any body's geometry (issue 36).

Wang et al.'s shirt (§4) has 20 patches in 10 colours, each colour twice; its layout was drawn
by hand for one body. A test world whose every shirt is that layout tests the layout, not the
tracker, so here a layout is *drawn* from the body's roles and geometry:

1. **Parts.** Each shirt geom (the roles' torso geoms and the four arm segments' contour geoms)
   is cut into ``k`` parts, ``k`` drawn from 2..4: arm geoms by planes normal to the bone at
   evenly spaced, jittered positions along it; torso geoms by one of the patterns
   left|right, front|back, top|bottom-left|bottom-right, or the four quadrants
   front/back x left/right, cut through the geom's centre (body axes of the rest pose: up,
   left, front). **Shoulder pieces** (optional): the crosswise bars of the chest link, split
   left|right, or, on a body without bars, the top quarter of the highest torso geom split
   left|right (listed first, so that they take precedence: a point belongs to the first patch
   of its geom whose half-spaces contain it).
2. **Count.** The part counts are adjusted (one part more or less on a random geom) until the
   number of patches ``P`` is even and ``P / 2`` colours lie in 8..14 (or equal the colour
   count asked for).
3. **Colours.** Adjacency: two patches of one geom always count as touching, patches of two
   geoms touch where surface samples of the two come within ``TOUCH`` at rest. Colours are
   assigned by a randomised backtracking search: every colour exactly twice, no touching pair
   alike (most constrained patch first, ties broken by the seeded generator).

Everything is seeded (``numpy.random.default_rng(seed)``); the paper's own layout stays
:func:`jaxmocap.garment.default_garment`.
"""

from __future__ import annotations

import colorsys

import numpy as np

from .body import BodyModel, require_roles, rest_pose
from .body.roles import CONTOUR_LIMBS, geom_support, is_crosswise, limb_axis, rest_transforms
from .errors import InputError
from .garment import Garment, default_skin_geoms, make_garment

MIN_COLOURS, MAX_COLOURS = 8, 14  # issue 36: 8-14 colours, each twice
MIN_PARTS, MAX_PARTS = 2, 4  # parts per shirt geom
TOUCH = 0.07  # m: surface samples (160 a patch) of two geoms this close at rest -> they touch
CUT_JITTER = 0.1  # arm cuts: +- this fraction of a part's length around even spacing
SHOULDER_FRACTION = 0.25  # shoulder pieces: the top quarter of the highest torso geom
TORSO_PATTERNS = {2: ("lr", "fb"), 3: ("top_lr",), 4: ("quad",)}


def _world_axes(model: BodyModel) -> dict[str, np.ndarray]:
    """The body's axes at rest (world): up from the pelvis keypoint to the neck, left from the
    right to the left shoulder (made normal to up), front = left x up."""
    kp = _rest_keypoints(model)
    names = model.keypoint_names
    up = kp[names.index("neck")] - kp[names.index("pelvis")]
    if np.linalg.norm(up) < 1e-6:
        up = kp[names.index("head")] - kp[names.index("chest")]
    up = up / np.linalg.norm(up)
    left = kp[names.index("l_shoulder")] - kp[names.index("r_shoulder")]
    left = left - (left @ up) * up
    left = left / np.linalg.norm(left)
    return {"up": up, "left": left, "front": np.cross(left, up)}


def _rest_keypoints(model: BodyModel) -> np.ndarray:
    from .body import keypoints

    return np.asarray(keypoints(model, rest_pose(model)), np.float64)


def _geom_frames(model: BodyModel) -> np.ndarray:
    """World poses (float64) of every geom at rest."""
    rest = rest_transforms(model.chain)
    link = np.asarray(model.geometry.link)
    return rest[link] @ np.asarray(model.geometry.pose, np.float64)


def _plane(frame: np.ndarray, n_world: np.ndarray, p_world: np.ndarray) -> tuple[float, ...]:
    """Half-space ``n . (x - p) <= 0`` (world) in the geom frame ``frame``: ``(a, b)``."""
    rot, c = frame[:3, :3], frame[:3, 3]
    a = rot.T @ n_world
    b = -float(a @ (rot.T @ (p_world - c)))
    return tuple(float(v) for v in np.round(a, 12) + 0.0) + (round(b, 9) + 0.0,)


def _extent(model: BodyModel, g: int, frame: np.ndarray, u: np.ndarray) -> float:
    """Half-extent (m) of geom ``g`` along the world direction ``u``."""
    kind = int(np.asarray(model.geometry.kind)[g])
    size = np.asarray(model.geometry.size, np.float64)[g]
    return geom_support(kind, size, frame[:3, :3], u)


def _arm_parts(model, g, frame, axis, k, rng) -> list[tuple[str, list]]:
    c = frame[:3, 3]
    ext = _extent(model, g, frame, axis)
    step = 2 * ext / k
    cuts = [c + axis * (-ext + step * (i + 1 + rng.uniform(-CUT_JITTER, CUT_JITTER)))
            for i in range(k - 1)]
    parts = []
    for i in range(k):
        hs = []
        if i > 0:  # distal of cut i-1
            hs.append(_plane(frame, -axis, cuts[i - 1]))
        if i < k - 1:  # proximal of cut i
            hs.append(_plane(frame, axis, cuts[i]))
        parts.append((f"part{i}", hs))
    return parts


def _torso_parts(frame, axes, pattern) -> list[tuple[str, list]]:
    c = frame[:3, 3]
    up, left, front = axes["up"], axes["left"], axes["front"]

    def hs(n):
        return _plane(frame, n, c)

    if pattern == "lr":
        return [("left", [hs(-left)]), ("right", [hs(left)])]
    if pattern == "fb":
        return [("front", [hs(-front)]), ("back", [hs(front)])]
    if pattern == "top_lr":
        return [("top", [hs(-up)]), ("bottom_left", [hs(-left)]), ("bottom_right", [hs(left)])]
    return [("front_left", [hs(-front), hs(-left)]), ("front_right", [hs(-front), hs(left)]),
            ("back_left", [hs(front), hs(-left)]), ("back_right", [hs(front), hs(left)])]


def _counts(n_geoms: int, rng, n_colours: int | None, fixed: int) -> list[int]:
    """Parts per geom (2..4) with ``fixed + sum`` even and ``/ 2`` in the colour range."""
    lo_p, hi_p = fixed + MIN_PARTS * n_geoms, fixed + MAX_PARTS * n_geoms
    if n_colours is not None:
        if not MIN_COLOURS <= n_colours <= MAX_COLOURS:
            raise InputError(f"generated_garment: n_colours must be in {MIN_COLOURS}.."
                             f"{MAX_COLOURS}, got {n_colours}")
        target = 2 * n_colours
    else:
        lo = max(2 * MIN_COLOURS, lo_p + (lo_p % 2))
        hi = min(2 * MAX_COLOURS, hi_p - (hi_p % 2))
        if lo > hi:
            target = -1
        else:
            target = int(rng.choice(np.arange(lo, hi + 1, 2)))
    if not lo_p <= target <= hi_p:
        raise InputError(
            f"generated_garment: the body's {n_geoms} shirt geoms give {lo_p}..{hi_p} patches, "
            f"not {2 * (n_colours or MIN_COLOURS)}..{2 * (n_colours or MAX_COLOURS)} (each "
            "colour twice)")
    k = list(rng.integers(MIN_PARTS, MAX_PARTS + 1, n_geoms))
    while fixed + sum(k) != target:
        grow = fixed + sum(k) < target
        cand = [i for i, v in enumerate(k) if (v < MAX_PARTS if grow else v > MIN_PARTS)]
        i = int(rng.choice(cand))
        k[i] += 1 if grow else -1
    return [int(v) for v in k]


def patch_adjacency(model: BodyModel, garment: Garment, touch: float = TOUCH) -> np.ndarray:
    """``(P, P)`` bool: patches of one geom, and patches whose surface samples come within
    ``touch`` (m) of each other at rest (see the module docstring)."""
    from .render import shirt_points

    pts, valid = shirt_points(model, garment, rest_pose(model, model.geometry.size.dtype))
    n_p = int(garment.patch_geom.shape[0])
    pts = np.asarray(pts, np.float64).reshape(n_p, -1, 3)
    valid = np.asarray(valid).reshape(n_p, -1)
    geom = np.asarray(garment.patch_geom)
    adj = geom[:, None] == geom[None, :]
    for i in range(n_p):
        for j in range(i + 1, n_p):
            if adj[i, j] or not valid[i].any() or not valid[j].any():
                continue
            d = np.linalg.norm(pts[i][valid[i]][:, None] - pts[j][valid[j]][None], axis=-1)
            adj[i, j] = adj[j, i] = bool(d.min() < touch)
    np.fill_diagonal(adj, False)
    return adj


def _backtrack(adjacency: np.ndarray, n_colours: int, order: list[int], rng,
               budget: int = 20_000) -> np.ndarray | None:
    """One randomised depth-first search (``budget`` steps) for :func:`colour_patches`."""
    n = adjacency.shape[0]
    colour = np.zeros(n, int)
    used = np.zeros(n_colours + 1, int)
    steps = 0

    def assign(m: int) -> bool:
        nonlocal steps
        if m == n:
            return True
        steps += 1
        if steps > budget:
            return False
        i = order[m]
        banned = set(colour[adjacency[i]].tolist())
        for c in rng.permutation(np.arange(1, n_colours + 1)):
            if used[c] < 2 and c not in banned:
                colour[i], used[c] = c, used[c] + 1
                if assign(m + 1):
                    return True
                colour[i], used[c] = 0, used[c] - 1
        return False

    return colour if assign(0) else None


def colour_patches(adjacency: np.ndarray, n_colours: int, rng, tries: int = 200) -> np.ndarray:
    """Colour ids ``1..n_colours`` of ``2 n_colours`` patches: each colour exactly twice, no two
    adjacent patches alike (randomised backtracking, most constrained patch first)."""
    n = adjacency.shape[0]
    if n != 2 * n_colours:
        raise ValueError(f"colour_patches: {n} patches for {n_colours} colours (need 2 each)")
    for _ in range(tries):
        order = sorted(range(n), key=lambda i: (-adjacency[i].sum(), rng.random()))
        colour = _backtrack(adjacency, n_colours, order, rng)
        if colour is not None:
            return colour
    raise InputError(f"colour_patches: no colouring of {n} patches with {n_colours} colours "
                     "(each twice, no touching pair alike) found; the layout is too crowded")


def hue_colours(n: int) -> tuple[tuple[str, tuple[float, float, float]], ...]:
    """``n`` saturated colours evenly spaced around the hue circle (names ``hue<degrees>``)."""
    out = []
    for i in range(n):
        h = i / n
        rgb = colorsys.hsv_to_rgb(h, 0.9, 0.9 if i % 2 == 0 or n <= 10 else 0.6)
        out.append((f"hue{round(360 * h):03d}", tuple(round(v, 4) for v in rgb)))
    return tuple(out)


def generated_garment(model: BodyModel, seed: int = 0, *, shoulders: bool = False,
                      n_colours: int | None = None) -> Garment:
    """A shirt drawn for ``model`` (module docstring): parts of the torso and arm geoms, with
    or without shoulder pieces, ``n_colours`` (default: drawn from 8..14 as the geometry
    allows) each used on exactly two patches that do not touch. Seeded."""
    roles = require_roles(model, "generated_garment")
    rng = np.random.default_rng(seed)
    names = model.geometry.names
    frames = _geom_frames(model)
    axes = _world_axes(model)
    rest = rest_transforms(model.chain)
    chest = model.chain.link_names.index(roles.link("chest"))
    torso = [names.index(g) for g in roles.torso_geoms]
    bars = [g for g, li in enumerate(np.asarray(model.geometry.link).tolist())
            if li == chest and is_crosswise(model.geometry, g) and names[g] not in
            roles.skin_geoms and g not in torso]
    arms = [(role, names.index(g)) for role in CONTOUR_LIMBS for g in roles.limb(role)]
    rows: list[tuple[str, int, list]] = []  # (name, geom, half-spaces)
    fixed = 0
    if shoulders:
        if bars:
            for g in bars:
                for name, hs in _torso_parts(frames[g], axes, "lr"):
                    rows.append((f"shoulder_piece_{names[g]}_{name}", g, hs))
        else:
            g = max(torso, key=lambda g: frames[g][:3, 3] @ axes["up"])
            top = frames[g][:3, 3] + axes["up"] * _extent(model, g, frames[g], axes["up"]) * (
                1 - 2 * SHOULDER_FRACTION)
            for side, n in (("left", -axes["left"]), ("right", axes["left"])):
                rows.append((f"shoulder_piece_{side}", g, [_plane(frames[g], -axes["up"], top),
                                                     _plane(frames[g], n, frames[g][:3, 3])]))
        fixed = len(rows)
    shirt = torso + [g for _, g in arms]
    k = _counts(len(shirt), rng, n_colours, fixed)
    for g, kg in zip(shirt, k, strict=True):
        if g in torso:
            pattern = str(rng.choice(TORSO_PATTERNS[kg]))
            parts = _torso_parts(frames[g], axes, pattern)
        else:
            role = next(r for r, a in arms if a == g)
            li = model.chain.link_names.index(roles.link(role))
            axis = rest[li][:3, :3] @ limb_axis(model, role)
            parts = _arm_parts(model, g, frames[g], axis, kg, rng)
        rows += [(f"{names[g]}_{name}", g, hs) for name, hs in parts]
    n_col = len(rows) // 2
    colours = hue_colours(n_col)
    # a provisional garment (one colour) to measure adjacency on its patches
    probe = make_garment(model, [(n, names[g], hs, 1) for n, g, hs in rows], colours)
    colour = colour_patches(patch_adjacency(model, probe), n_col, rng)
    patches = [(n, names[g], hs, int(c)) for (n, g, hs), c in zip(rows, colour, strict=True)]
    return make_garment(model, patches, colours, default_skin_geoms(model))


__all__ = ["generated_garment", "patch_adjacency", "colour_patches", "hue_colours"]
