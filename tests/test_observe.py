"""The learned observation layer (jaxmocap.observe): classes by roles against the body's own
keypoints, the black-body colours against Wien's law, the shadow rays against the lamp's side,
the network's jit / vmap / grad, a tiny model trained in seconds recovering a render's labels,
resumed training equal to uninterrupted training, the model file, and ``jaxmocap learn``."""

from __future__ import annotations

import subprocess
import sys

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap.body import default_body, keypoint_index, keypoints
from jaxmocap.camera import look_at, project
from jaxmocap.garment import default_garment
from jaxmocap.observe import (
    Observer,
    ObserverFileError,
    TrainConfig,
    blackbody_rgb,
    classes_of,
    features,
    labels_of,
    load,
    log_probs,
    loss_fn,
    render_geometry,
    save,
    shade,
    train,
)
from jaxmocap.observe.scenes import palette_of
from jaxmocap.render import render_ids

BODY = default_body()
GARMENT = default_garment(BODY)
CLASSES = classes_of(BODY, GARMENT)


def _rest_view():
    q = jnp.zeros(BODY.n_dof, jnp.float32)
    cam = look_at((2.5, 0.0, 0.3), (0.0, 0.0, 0.25), width=160, height=120, fx=150.0)
    return q, cam


def test_classes_by_roles_match_the_keypoints():
    """Head, left-hand and right-hand classes are where FK puts the head and the hands."""
    q, cam = _rest_view()
    hits = render_ids(BODY, GARMENT, q, cam)
    lab = np.asarray(labels_of(CLASSES, hits.geom, hits.colour))
    kp = np.asarray(project(cam, keypoints(BODY, q)))
    for cls, key in ((CLASSES.head, "head"), (CLASSES.hands[0], "l_hand"),
                     (CLASSES.hands[1], "r_hand")):
        ys, xs = np.nonzero(lab == cls)
        assert len(xs) > 3, CLASSES.names[cls]
        centre = np.array([xs.mean(), ys.mean()])
        assert np.linalg.norm(centre - kp[keypoint_index(BODY, key)]) < 8, CLASSES.names[cls]
    shirt = (lab >= 1) & (lab <= CLASSES.n_colours)
    assert np.array_equal(shirt, np.asarray(hits.colour) > 0)
    assert CLASSES.names[0] == "background" and CLASSES.n == GARMENT.n_colours + 4


def test_blackbody_against_wien():
    """R/B of blackbody_rgb equals Wien's approximation where it holds (hc / lambda k T >> 1)."""
    lam_r, lam_b = 610e-9, 465e-9
    c2 = 6.62607015e-34 * 2.99792458e8 / 1.380649e-23
    for T in (1500.0, 2000.0, 2700.0):
        rgb = np.asarray(blackbody_rgb(jnp.asarray(T)))
        wien = (lam_b / lam_r) ** 5 * np.exp(c2 / T * (1 / lam_b - 1 / lam_r))
        np.testing.assert_allclose(rgb[0] / rgb[2], wien, rtol=2e-3)
    rb = [float(x[0] / x[2]) for x in np.asarray(blackbody_rgb(jnp.array([2000.0, 4000.0,
                                                                          6500.0, 10000.0])))]
    assert rb == sorted(rb, reverse=True) and rb[0] > 3 and 0.6 < rb[2] < 1.6


@pytest.fixture(scope="module")
def geometry():
    from jaxmocap.posedb._sample import SamplingConfig, sample_poses, source_pool
    from jaxmocap.synth import TRAIN_CLIPS

    pool = source_pool(BODY, tuple(TRAIN_CLIPS))
    poses = sample_poses(SamplingConfig(size=8, seed=3), BODY, pool)
    return render_geometry(BODY, GARMENT, CLASSES, poses, jax.random.key(0), 32, batch=8)


def test_shadow_rays_only_light_the_lamps_side(geometry):
    """A lamp lights a point only if the point faces it; points facing it are sometimes in
    the shadow of another part (the ray from the lamp hits something nearer)."""
    p = np.asarray(geometry.point, np.float32)
    n = np.asarray(geometry.normal, np.float32)
    to = np.asarray(geometry.lamps)[:, :, None, None, :] - p[:, None]
    facing = np.sum(to * n[:, None], -1) > 0
    lit, body = np.asarray(geometry.lit), np.asarray(geometry.body)[:, None]
    assert lit.sum() > 100
    assert np.mean(facing[lit]) > 0.99
    assert np.sum(facing & body & ~lit) > 0  # cast shadows exist


def test_shade_is_a_camera_image_drawn_from_its_key(geometry):
    g = jax.tree.map(lambda a: jnp.asarray(a[0]), geometry)
    pal = palette_of(GARMENT)
    a, la = shade(jax.random.key(1), g, pal)
    b, lb = shade(jax.random.key(1), g, pal)
    c, _ = shade(jax.random.key(2), g, pal)
    assert np.array_equal(a, b) and np.array_equal(la, lb) and not np.array_equal(a, c)
    a = np.asarray(a)
    assert a.min() >= 0 and a.max() <= 255 and np.array_equal(a, np.round(a))
    keep = np.asarray(la) > 0  # labels are the render's, except where an occluder hides it
    assert np.array_equal(np.asarray(la)[keep], np.asarray(geometry.label[0])[keep])


def test_features_ignore_exposure_and_white_balance_gains():
    rng = np.random.default_rng(0)
    img = rng.uniform(60, 200, (16, 16, 3))
    f0, f1 = features(jnp.asarray(img)), features(jnp.asarray(img * [0.8, 1.1, 1.25]))
    np.testing.assert_allclose(f0[:3], f1[:3], atol=0.03)


def test_model_jit_vmap_grad():
    m = Observer(CLASSES.n, jax.random.key(0), width=4, context=6)
    imgs = jax.random.uniform(jax.random.key(1), (2, 16, 16, 3), maxval=255)
    plain = log_probs(m, imgs[0])
    np.testing.assert_allclose(jax.jit(log_probs)(m, imgs[0]), plain, atol=1e-5)
    np.testing.assert_allclose(jax.vmap(log_probs, (None, 0))(m, imgs)[0], plain, atol=1e-5)
    np.testing.assert_allclose(jnp.exp(plain).sum(-1), 1, atol=1e-5)
    labels = jax.random.randint(jax.random.key(2), (2, 16, 16), 0, CLASSES.n)
    w = jnp.ones(CLASSES.n)
    g = eqx.filter_grad(loss_fn)(m, imgs, labels, w)
    # finite differences along the gradient of the head's bias
    eps = 1e-2
    d = g.head.bias / jnp.linalg.norm(g.head.bias)
    shift = lambda s: eqx.tree_at(lambda t: t.head.bias, m, m.head.bias + s * d)  # noqa: E731
    fd = (loss_fn(shift(eps), imgs, labels, w) - loss_fn(shift(-eps), imgs, labels, w)) / (2 * eps)
    np.testing.assert_allclose(fd, jnp.vdot(g.head.bias, d), rtol=0.02)


def test_tiny_model_recovers_a_renders_labels(geometry):
    """Trained for seconds on 8 renders, the model labels new light on them: shirt / skin /
    background mostly right and the colours far better than chance."""
    m = Observer(CLASSES.n, jax.random.key(0), width=8, context=12)
    pal = palette_of(GARMENT)
    m, _, losses = train(m, geometry, pal, TrainConfig(steps=150, batch=4, learning_rate=1e-2))
    assert np.mean(losses[-10:]) < 0.6 * np.mean(losses[:5])
    g = jax.tree.map(lambda a: jnp.asarray(a), geometry)
    right_c, n_c, right_g, n_g = 0, 0, 0, 0
    for i in range(8):
        img, lab = shade(jax.random.key(100 + i), jax.tree.map(lambda a, i=i: a[i], g), pal)
        pred, lab = np.asarray(jnp.argmax(log_probs(m, img), -1)), np.asarray(lab)
        group = lambda x: np.where(x == 0, 0, np.where(x <= CLASSES.n_colours, 1, 2))  # noqa
        right_g += np.sum(group(pred) == group(lab))
        n_g += lab.size
        shirt = (lab >= 1) & (lab <= CLASSES.n_colours)
        right_c += np.sum(pred[shirt] == lab[shirt])
        n_c += shirt.sum()
    assert right_g / n_g > 0.8
    assert right_c / n_c > 2 / CLASSES.n_colours


def test_resumed_training_equals_uninterrupted(geometry):
    m0 = Observer(CLASSES.n, jax.random.key(0), width=4, context=4)
    pal = palette_of(GARMENT)
    cfg = TrainConfig(steps=6, batch=2)
    full, _, l_full = train(m0, geometry, pal, cfg)
    seen = {}
    half, st, l_half = train(m0, geometry, pal, cfg,
                             on_step=lambda i, loss, m, s: seen.update(i=i),
                             stop=lambda: seen.get("i") == 2)
    rest, _, l_rest = train(half, geometry, pal, cfg, start=3, opt_state=st)
    for a, b in zip(jax.tree.leaves(eqx.filter(full, eqx.is_array)),
                    jax.tree.leaves(eqx.filter(rest, eqx.is_array)), strict=True):
        np.testing.assert_array_equal(a, b)
    assert l_half + l_rest == l_full


def test_model_file_round_trip_and_refusals(tmp_path):
    from jaxmocap.body.roles import body_digest
    from jaxmocap.garment import garment_digest, single_colour_garment

    m = Observer(CLASSES.n, jax.random.key(0), width=4, context=4)
    path = save(tmp_path / "m.eqx", m, dict(body_digest=body_digest(BODY),
                                            garment_digest=garment_digest(GARMENT)))
    back, head = load(path, BODY, GARMENT)
    for a, b in zip(jax.tree.leaves(m), jax.tree.leaves(back), strict=True):
        np.testing.assert_array_equal(a, b)
    other = single_colour_garment(BODY, (0.1, 0.2, 0.8))
    with pytest.raises(ObserverFileError, match="another garment") as e:
        load(path, BODY, other)
    assert "\n" not in str(e.value)
    raw = path.read_bytes()
    (tmp_path / "cut.eqx").write_bytes(raw[:-50])
    with pytest.raises(ObserverFileError, match="damaged"):
        load(tmp_path / "cut.eqx")
    (tmp_path / "not.eqx").write_text("hello\n")
    with pytest.raises(ObserverFileError, match="not a trained observation model"):
        load(tmp_path / "not.eqx")


def test_learned_step3_recovers_the_true_patch_map():
    """With the true colours as the model's probabilities and the true patch map as the
    prior, step 3 on the model gives back the rendered patch map."""
    from jaxmocap.color.pose_assisted import patch_distance_maps
    from jaxmocap.trackers.shirt.frame import learned_costs, learned_pose_assisted

    q, cam = _rest_view()
    hits = render_ids(BODY, GARMENT, q, cam)
    lab = labels_of(CLASSES, hits.geom, hits.colour)
    logp = jnp.log(jax.nn.one_hot(lab, CLASSES.n) * 0.98 + 0.02 / CLASSES.n)
    dist = patch_distance_maps(hits.patch, GARMENT.n_patches, jnp.float32)
    patch = learned_pose_assisted(learned_costs(GARMENT, logp), dist, 0.05, None)
    np.testing.assert_array_equal(patch, hits.patch)


def test_learn_command(tmp_path, capsys, monkeypatch):
    env_cache = {"JAXMOCAP_CACHE_DIR": str(tmp_path / "cache")}
    import os

    env = {**os.environ, **env_cache}
    out = tmp_path / "m.eqx"
    r = subprocess.run([sys.executable, "-m", "jaxmocap.cli", "learn", "--poses", "8",
                        "--steps", "2", "--out", str(out), "--quiet"], capture_output=True,
                       text=True, env=env)
    assert r.returncode == 0, r.stderr
    assert "observation model: 14 classes" in r.stdout
    _, head = load(out, BODY, GARMENT)
    assert head["record"]["steps"] == 2 and head["settings"]["poses"] == 8
    r = subprocess.run([sys.executable, "-m", "jaxmocap.cli", "learn", "--out", "m.npz"],
                       capture_output=True, text=True, env=env)
    assert r.returncode == 2 and r.stderr.strip().count("\n") == 0 and ".eqx" in r.stderr
    # --tracker pf: the rig's framing on Azad's one-colour shirt (5 classes) reaches learn()
    # (the training itself is the same code as above's; here only what the option selects)
    import jaxmocap.observe as observe_pkg
    from jaxmocap.cli import main

    seen = {}

    def fake_learn(model, garment, settings=None, **kw):
        seen.update(classes=classes_of(model, garment).names, framing=kw.get("framing"))
        rec = dict(loss_every_10=[1.0], steps=0)
        return None, dict(classes=list(seen["classes"]), key="k", record=rec), tmp_path / "x"

    monkeypatch.setattr(observe_pkg, "learn", fake_learn)
    assert main(["learn", "--tracker", "pf", "--quiet"]) == 0
    assert seen == dict(classes=("background", "shirt", "head", "left hand", "right hand"),
                        framing="frame")
    capsys.readouterr()
    ten = tmp_path / "ten.json"  # the colour shirt's garment: refused for the filter, one line
    from jaxmocap.io.garment_file import save_garment

    save_garment(ten, GARMENT, BODY)
    assert main(["learn", "--tracker", "pf", "--garment", str(ten), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "has one colour" in err[0] and "has 10" in err[0], err


def test_part_maps_partition_the_probabilities():
    """The interface the trackers read: shirt, head, hands and background sum to one and the
    hands' planes are the model's hand classes."""
    from jaxmocap.observe import part_maps

    m = Observer(CLASSES.n, jax.random.key(0), width=4, context=4)
    img = jax.random.uniform(jax.random.key(1), (16, 16, 3), maxval=255)
    lp = log_probs(m, img)
    pm = jax.jit(lambda x: part_maps(CLASSES, x))(lp)
    np.testing.assert_allclose(sum(pm), 1, atol=1e-5)
    np.testing.assert_allclose(pm.left_hand, jnp.exp(lp[..., CLASSES.hands[0]]), atol=1e-6)


def test_learn_gives_the_bundled_model_and_refuses_a_start_of_other_classes(tmp_path):
    """The bundled body and shirt get the shipped model without training; a model of another
    class count is refused as a start in one line."""
    from jaxmocap.garment import single_colour_garment
    from jaxmocap.observe import BUNDLED, learn
    from jaxmocap.observe.fit import start_model

    obs, head, path = learn(BODY, GARMENT, cache=tmp_path, progress=False)
    assert path == BUNDLED and obs.n_classes == CLASSES.n
    assert head["settings"]["steps"] >= 1000 and len(head["record"]["loss_every_10"]) > 50
    one = classes_of(BODY, single_colour_garment(BODY, (0.1, 0.2, 0.8)))
    with pytest.raises(ObserverFileError, match="gives 14 classes, this shirt needs 5") as e:
        start_model(BUNDLED, one)
    assert "\n" not in str(e.value)
