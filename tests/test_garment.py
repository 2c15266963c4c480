"""Tests of the garment: the paper's shirt layout (Wang et al. 2011 §4: 20 patches, 10 colours
each used twice, far apart, neighbours of different colours), patch lookup against a direct
NumPy evaluation of the half-spaces, and the model-derived garments."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import render
from jaxmocap.body import default_body
from jaxmocap.camera import look_at
from jaxmocap.garment import (
    MAX_HALF_SPACES,
    SHIRT_COLOURS,
    albedo,
    colour_of,
    default_garment,
    garment_from_model,
    make_garment,
    patch_at,
    single_colour_garment,
)


@functools.cache
def shirt_views():
    """Colour and patch id maps of a few poses from front, back and both sides (80x80)."""
    model, garment = default_body(), default_garment()
    fn = jax.jit(lambda q, cam: render.render_ids(model, garment, q, cam))
    q_rest = np.zeros(model.n_dof)
    q_rest[2] = 1.0
    q_arms = q_rest.copy()
    q_arms[6:] = np.random.default_rng(3).uniform(-0.5, 0.5, model.n_dof - 6)
    maps = []
    for q in (q_rest, q_arms):
        for eye in ((3, 0.3, 1.6), (-3, -0.3, 1.6), (0.4, 3, 1.5), (-0.4, -3, 1.5)):
            cam = look_at(eye, (0, 0, 1.3), width=80, height=80, fx=110.0)
            hits = fn(jnp.asarray(q), cam)
            maps.append((np.asarray(hits.patch), np.asarray(hits.geom)))
    return maps


def test_default_shirt_layout():
    model, g = default_body(), default_garment()
    assert g.n_patches == 20 and g.n_colours == 10  # Wang et al. §4
    counts = np.bincount(np.asarray(g.patch_colour), minlength=11)[1:]
    np.testing.assert_array_equal(counts, 2)
    # covers torso (thorax + abdomen, front/back, left/right), shoulders, upper arms, forearms
    geoms = {model.geometry.names[i] for i in np.asarray(g.patch_geom)}
    assert geoms == {"thorax", "abdomen", "shoulders", "l_upper_arm", "r_upper_arm",
                     "l_forearm", "r_forearm"}  # fmt: skip
    skin = {model.geometry.names[i] for i in np.flatnonzero(np.asarray(g.skin))}
    assert skin == {"head", "neck", "l_hand", "r_hand"}
    # colours a camera can tell apart: chromaticities (Wang §4) pairwise far apart
    rgb = np.asarray(g.colours)
    chroma = rgb / rgb.sum(axis=1, keepdims=True)
    d = np.linalg.norm(chroma[:, None] - chroma[None], axis=-1) + np.eye(10)
    assert d.min() > 0.06
    assert np.all(rgb.max(axis=1) - rgb.min(axis=1) > 0.35)  # saturated


def test_same_colour_patches_far_apart_and_neighbours_differ():
    model, g = default_body(), default_garment()
    q = jnp.zeros(model.n_dof).at[2].set(1.0)
    pts, valid = render.shirt_points(model, g, q)
    pts, valid = np.asarray(pts).reshape(20, -1, 3), np.asarray(valid).reshape(20, -1)
    assert valid.sum(axis=1).min() > 10
    centroid = np.stack([p[v].mean(axis=0) for p, v in zip(pts, valid, strict=True)])
    colour = np.asarray(g.patch_colour)
    for k in range(1, 11):
        a, b = np.flatnonzero(colour == k)
        assert np.linalg.norm(centroid[a] - centroid[b]) > 0.3, g.colour_names[k - 1]
        # and no sample of one lies within 10 cm of a sample of the other
        gap = np.linalg.norm(pts[a][valid[a]][:, None] - pts[b][valid[b]][None], axis=-1)
        assert gap.min() > 0.1
    # adjacency from rendered patch maps: 4-neighbouring pixels of two different patches
    seen, adjacent = set(), set()
    for patch, _ in shirt_views():
        seen |= set(np.unique(patch[patch > 0]).tolist())
        for a, b in ((patch[:, 1:], patch[:, :-1]), (patch[1:], patch[:-1])):
            m = (a > 0) & (b > 0) & (a != b)
            adjacent |= {tuple(sorted(p)) for p in zip(a[m].tolist(), b[m].tolist(), strict=True)}
    assert seen == set(range(1, 21))  # every patch is visible in some view
    assert len(adjacent) >= 20
    for a, b in adjacent:
        assert colour[a - 1] != colour[b - 1], (g.patch_names[a - 1], g.patch_names[b - 1])


def test_patch_lookup_matches_numpy(rng):
    model, g = default_body(), default_garment()
    n = 3000
    geom = rng.integers(-1, model.geometry.n_geoms, size=n)
    p = rng.uniform(-0.2, 0.2, size=(n, 3))
    got = np.asarray(patch_at(g, jnp.asarray(geom), jnp.asarray(p)))
    planes = np.asarray(g.patch_planes)
    expect = np.zeros(n, int)
    for j in reversed(range(g.n_patches)):  # the first matching patch of the geom wins
        contains = np.all(p @ planes[j, :, :3].T + planes[j, :, 3] <= 0, axis=1)
        expect[contains & (geom == int(g.patch_geom[j]))] = j + 1
    np.testing.assert_array_equal(got, expect)
    assert set(np.unique(got)) == set(range(21))
    # jit and vmap give the same lookup
    jitted = jax.jit(jax.vmap(patch_at, (None, 0, 0)))(g, jnp.asarray(geom), jnp.asarray(p))
    np.testing.assert_array_equal(np.asarray(jitted), got)
    # colour ids and albedo
    col = np.asarray(colour_of(g, jnp.asarray(got)))
    np.testing.assert_array_equal(col, np.concatenate([[0], np.asarray(g.patch_colour)])[got])
    alb = np.asarray(albedo(g, jnp.asarray(geom), jnp.asarray(got)))
    shirt = got > 0
    np.testing.assert_allclose(alb[shirt], np.asarray(g.colours)[col[shirt] - 1])
    skin = ~shirt & (geom >= 0) & np.asarray(g.skin)[np.maximum(geom, 0)]
    np.testing.assert_allclose(alb[skin], np.broadcast_to(np.asarray(g.skin_rgb), alb[skin].shape))
    other = ~shirt & ~skin
    np.testing.assert_allclose(
        alb[other], np.broadcast_to(np.asarray(g.body_rgb), alb[other].shape)
    )


def test_rendered_patches_agree_with_geoms():
    """In the rendered maps every patch pixel belongs to its patch's geom, skin/pelvis pixels
    carry no patch."""
    g = default_garment()
    owner = np.concatenate([[-1], np.asarray(g.patch_geom)])
    for patch, geom in shirt_views():
        np.testing.assert_array_equal(owner[patch][patch > 0], geom[patch > 0])
        unpatched = np.isin(geom, [0, 4, 5, 8, 11])  # pelvis, neck, head, hands
        assert np.all(patch[unpatched] == 0)


def test_garment_from_model_and_single_colour():
    model = default_body()
    rgba = np.asarray(model.geometry.rgba).copy()
    rgba[6] = rgba[9] = (1.0, 0.0, 0.0, 1.0)  # both upper arms red
    rgba[7] = (0.0, 0.0, 1.0, 1.0)  # left forearm blue
    recoloured = eqx.tree_at(lambda m: m.geometry.rgba, model, jnp.asarray(rgba))
    g = garment_from_model(recoloured)
    skin = {"neck", "head", "l_hand", "r_hand"}
    names = [n for n in model.geometry.names if n not in skin | {"pelvis"}]
    assert g.patch_names == tuple(names)  # the shirt's role links: no pelvis (trousers)
    by_patch = dict(zip(g.patch_names, np.asarray(g.patch_colour).tolist(), strict=True))
    assert by_patch["l_upper_arm"] == by_patch["r_upper_arm"] != by_patch["l_forearm"]
    assert by_patch["thorax"] == by_patch["r_forearm"]  # the model's shared default colour
    assert g.n_colours == 3
    np.testing.assert_allclose(np.asarray(g.colours)[by_patch["l_upper_arm"] - 1], [1, 0, 0])
    # Azad et al.'s set-up: one shirt colour, skin head/neck/hands
    s = single_colour_garment(model, (0.2, 0.3, 0.8))
    assert s.n_colours == 1 and set(np.asarray(s.patch_colour).tolist()) == {1}
    skin_geoms = {model.geometry.names[i] for i in np.flatnonzero(np.asarray(s.skin))}
    assert skin_geoms == skin


def test_make_garment_validates_input():
    model = default_body()
    cols = [("red", (1.0, 0.0, 0.0))]
    with pytest.raises(ValueError, match="unknown geom 'tail'"):
        make_garment(model, [("p", "tail", [], 1)], cols)
    with pytest.raises(ValueError, match="at most 3"):
        make_garment(model, [("p", "thorax", np.zeros((MAX_HALF_SPACES + 1, 4)), 1)], cols)
    with pytest.raises(ValueError, match="colour id 2 outside 1..1"):
        make_garment(model, [("p", "thorax", [], 2)], cols)
    with pytest.raises(ValueError, match="albedo must lie in"):
        make_garment(model, [("p", "thorax", [], 1)], [("x", (1.5, 0.0, 0.0))])
    assert len(SHIRT_COLOURS) == 10
