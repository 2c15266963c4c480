"""Generated shirts (issue 36 item 2): constraints checked independently of the generator.

The generator decides adjacency from surface samples at rest; the oracle here is the
ray-cast id map (``render_ids``): two 4-neighbouring pixels of different patches whose depths
agree to 1.5 cm lie on touching surface, so their patches must differ in colour -- from four
views around the body, at rest and in a second pose. Colour counts are counted on the
garment's arrays; coverage is checked on the patches' own surface samples.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_package_bodies import BODIES, package_file

from jaxmocap import body, render
from jaxmocap.camera import look_at
from jaxmocap.errors import InputError
from jaxmocap.garment import default_garment, garment_from_model
from jaxmocap.garment_layout import (
    MAX_COLOURS,
    MIN_COLOURS,
    colour_patches,
    generated_garment,
)

SIZE = 96
DEPTH_STEP = 0.015  # m: neighbouring pixels closer than this in depth lie on one surface


@pytest.fixture(scope="module")
def models():
    out = {"bundled": body.default_body()}
    for name in ("deepmimic", "cmu", "gym_humanoid"):
        parts, kw = BODIES[name]
        out[name] = body.load_body(package_file(*parts), **kw)
    return out


def touching_pairs(model, garment, q) -> set[tuple[int, int]]:
    """Patch pairs (1-based ids) seen side by side on one surface in four views."""
    kp = np.asarray(body.keypoints(model, q))
    centre = kp[model.keypoint_names.index("chest")]
    pairs = set()
    ids = jax.jit(lambda cam: render.render_ids(model, garment, q, cam))
    for az in np.radians([0.0, 90.0, 180.0, 270.0, 45.0]):
        eye = centre + 2.2 * np.array([np.cos(az), np.sin(az), 0.15])
        hits = ids(look_at(eye, centre, width=SIZE, height=SIZE, fx=110.0))
        patch, depth = np.asarray(hits.patch), np.asarray(hits.depth)
        for a, b, da, db in ((patch[:, :-1], patch[:, 1:], depth[:, :-1], depth[:, 1:]),
                             (patch[:-1], patch[1:], depth[:-1], depth[1:])):
            with np.errstate(invalid="ignore"):
                close = np.abs(da - db) < DEPTH_STEP
            m = (a > 0) & (b > 0) & (a != b) & close
            pairs |= {tuple(sorted(p)) for p in zip(a[m].tolist(), b[m].tolist(), strict=True)}
    return pairs


@pytest.mark.parametrize("name", ["bundled", "deepmimic", "cmu", "gym_humanoid"])
@pytest.mark.parametrize("shoulders", [False, True])
def test_generated_shirt_constraints(models, name, shoulders):
    model = models[name]
    garment = generated_garment(model, seed=3, shoulders=shoulders)
    colour = np.asarray(garment.patch_colour)
    n = len(garment.colour_names)
    assert MIN_COLOURS <= n <= MAX_COLOURS
    assert np.bincount(colour, minlength=n + 1)[1:].tolist() == [2] * n  # each colour twice
    assert any("shoulder_piece" in p for p in garment.patch_names) == shoulders
    # every shirt geom is split into 2..4 parts (shoulder pieces aside)
    geoms = np.asarray(garment.patch_geom)
    body_parts = [g for g, p in zip(geoms, garment.patch_names, strict=True)
                  if "shoulder_piece" not in p]
    assert set(np.bincount(body_parts)[np.unique(body_parts)].tolist()) <= {2, 3, 4}
    # the parts cover their geoms: every surface sample lies in some patch of its geom
    pts, _ = render.patch_surface_points(model, garment)
    for p in range(len(colour)):
        same = np.flatnonzero(geoms == geoms[p])
        planes = np.asarray(garment.patch_planes)[same]
        vals = np.einsum("sk,pjk->psj", np.asarray(pts[p]), planes[..., :3]) + planes[:, None, :, 3]
        assert np.all(np.any(np.all(vals <= 1e-9, axis=-1), axis=0)), garment.patch_names[p]
    # no touching pair alike, seen in rendered id maps at rest and in a second pose
    q2 = np.zeros(model.n_dof)
    for joint in ("l_shoulder", "r_shoulder"):
        q2[body.dof_index(model, model.roles.dofs(joint)[-1])] = 0.4
    q2 = body.clip_to_limits(model, jnp.asarray(q2))
    for q in (body.rest_pose(model), q2):
        pairs = touching_pairs(model, garment, jnp.asarray(q, model.geometry.size.dtype))
        assert pairs, "no patch boundaries seen"
        alike = [(garment.patch_names[a - 1], garment.patch_names[b - 1]) for a, b in pairs
                 if colour[a - 1] == colour[b - 1]]
        assert not alike


def test_generation_is_seeded_and_varied(models):
    model = models["cmu"]
    a, b = generated_garment(model, seed=5), generated_garment(model, seed=5)
    assert np.array_equal(np.asarray(a.patch_planes), np.asarray(b.patch_planes))
    assert np.array_equal(np.asarray(a.patch_colour), np.asarray(b.patch_colour))
    layouts = {(len(g.patch_names), tuple(np.asarray(g.patch_colour).tolist()))
               for g in (generated_garment(model, seed=s) for s in range(6))}
    assert len(layouts) >= 4
    for n in (MIN_COLOURS, 10):
        assert len(generated_garment(model, seed=1, n_colours=n).colour_names) == n
    assert len(generated_garment(model, seed=1, n_colours=11, shoulders=True).colour_names) == 11
    # the CMU body has 5 shirt geoms (thorax, 4 arm segments): at most 4 parts each -> 20
    # patches, 10 colours (22 / 11 with shoulder pieces); the bundled body reaches 13
    with pytest.raises(InputError, match="5 shirt geoms give 10..20 patches"):
        generated_garment(model, n_colours=MAX_COLOURS)
    assert len(generated_garment(models["bundled"], seed=2, n_colours=13,
                                 shoulders=True).colour_names) == 13
    with pytest.raises(InputError, match="n_colours must be in 8..14"):
        generated_garment(model, n_colours=15)


def test_colouring_refuses_the_impossible():
    rng = np.random.default_rng(0)
    # 16 patches that all touch one another: no colour can be used twice
    full = ~np.eye(16, dtype=bool)
    with pytest.raises(InputError, match="no colouring"):
        colour_patches(full, 8, rng, tries=2)
    # a ring of 16: easy
    ring = np.zeros((16, 16), bool)
    for i in range(16):
        ring[i, (i + 1) % 16] = ring[(i + 1) % 16, i] = True
    c = colour_patches(ring, 8, rng)
    assert np.bincount(c)[1:].tolist() == [2] * 8
    assert not np.any(ring & (c[:, None] == c[None, :]))


def test_the_papers_layout_and_the_bodys_own_colours_stay(models):
    assert len(default_garment(models["bundled"]).patch_names) == 20
    for name in ("deepmimic", "cmu", "gym_humanoid"):
        assert len(garment_from_model(models[name]).patch_names) >= 5


def test_garment_json_from_another_tool(models, tmp_path, capsys):
    """Patches by link (taking the link's fixed child visuals) and by geom, American
    spellings, and extra fields ignored with one note on stderr naming them."""
    from jaxmocap.io.garment_file import load_garment

    model = models["deepmimic"]
    spec = {
        "generator": "some-tool 2.1", "units": "m",
        "colors": [{"name": "red", "rgb": [0.9, 0.1, 0.1]}, "blue"],
        "patches": [
            {"name": "chest", "link": "chest", "color": "red", "uv_seam": 3},
            {"name": "l_sleeve", "geom": "left_shoulder_0", "halfspaces": [[0, 0, 1, 0]],
             "color": "blue"},
        ],
    }  # fmt: skip
    path = tmp_path / "garment.json"
    path.write_text(__import__("json").dumps(spec))
    g = load_garment(path, model)
    assert g.colour_names == ("red", "blue") and g.patch_names == ("chest", "l_sleeve")
    err = capsys.readouterr().err
    assert str(path) in err and "generator" in err and "patches[0].uv_seam" in err
    assert err.count("\n") == 1
    # a link's fixed child links carry its patch, but not a fixed child playing a role (the
    # DeepMimic wrists hang fixed on the elbows)
    spec2 = {"colours": ["red"], "patches": [{"name": "fore", "link": "left_elbow",
                                              "colour": "red"}]}
    path.write_text(__import__("json").dumps(spec2))
    g2 = load_garment(path, model)
    assert g2.patch_names == ("fore",)
    spec3 = {**spec2, "colors": ["red"]}
    path.write_text(__import__("json").dumps(spec3))
    with pytest.raises(InputError, match="both 'colors' and 'colours' given"):
        load_garment(path, model)
