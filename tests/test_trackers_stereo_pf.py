"""Tests of the stereo particle-filter tracker (Azad et al. 2007) on a tiny drawn stereo scene.

The scene is drawn with OpenCV, independently of the tracker's contour model: the torso and
arm capsules of the body model are filled as polygons of their projected outlines (shirt blue),
head and hands as skin discs, over a grey background; 320x240 pairs (Azad §V), 11 cm baseline.
"""

import argparse
import dataclasses

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import camera as camlib
from jaxmocap import pf
from jaxmocap.body import default_body, dof_index, fk, keypoint_index, keypoints
from jaxmocap.errors import InputError
from jaxmocap.trackers import stereo_pf as sp
from jaxmocap.trackers.stereo_pf import filter as sp_filter
from jaxmocap.trackers.stereo_pf import observation as sp_observation
from jaxmocap.trackers.stereo_pf import swivel as sp_swivel

W, H = 320, 240
SHIRT = (26, 64, 204)
SKIN = (222, 171, 140)
BACKGROUND = (90, 90, 90)
JOINTS = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand")


def _cams():
    return [
        camlib.look_at(
            np.array([2.3, y, 1.6]), np.array([0.0, y, 1.15]), width=W, height=H, fx=308.0
        )
        for y in (0.055, -0.055)
    ]


def _draw(model, q, cam):
    """RGB image of pose q: capsules of the geometry drawn as thick projected segments."""
    img = np.full((H, W, 3), BACKGROUND, np.uint8)
    tr = np.asarray(fk(model.chain, jnp.asarray(q)))
    geo = model.geometry
    K, R, t = (np.asarray(a, np.float64) for a in (cam.K, cam.R, cam.t))
    rvec, _ = cv2.Rodrigues(R)
    scale = 8  # sub-pixel drawing (cv2 shift)

    def proj(p):
        uv, _ = cv2.projectPoints(np.asarray(p, np.float64)[None], rvec, t, K, np.zeros(5))
        return uv[0, 0]

    def depth(p):
        return (R @ p + t)[2]

    order = []
    for g, name in enumerate(geo.names):
        T = tr[int(geo.link[g])] @ np.asarray(geo.pose[g])
        c = T[:3, 3]
        order.append((depth(c), g, name, T))
    for _, g, name, T in sorted(order, reverse=True):  # far to near
        size = np.asarray(geo.size[g])
        if int(geo.kind[g]) == 0:  # sphere (r, 0, 0)
            size = np.full(3, size[0])
        skin = any(w in name for w in ("head", "neck", "hand"))
        colour = SKIN if skin else SHIRT
        if int(geo.kind[g]) in (1, 2):  # capsule / cylinder: a thick line
            a = T[:3, :3] @ [0, 0, -size[1]] + T[:3, 3]
            b = T[:3, :3] @ [0, 0, size[1]] + T[:3, 3]
            r = K[0, 0] * size[0] / depth(T[:3, 3])
            pa, pb = proj(a), proj(b)
            cv2.line(img, tuple(np.round(pa * scale).astype(int)),
                     tuple(np.round(pb * scale).astype(int)), colour, max(1, int(round(2 * r))),
                     cv2.LINE_AA, shift=3)  # fmt: skip
        else:  # sphere / ellipsoid: the projected ellipse of its y-z extent
            c = proj(T[:3, 3])
            ry = K[0, 0] * np.linalg.norm(T[:3, :3] @ np.diag(size), axis=1)[1] / depth(T[:3, 3])
            rz = K[0, 0] * np.linalg.norm(T[:3, :3] @ np.diag(size), axis=1)[2] / depth(T[:3, 3])
            cv2.ellipse(img, tuple(np.round(c * scale).astype(int)),
                        (int(ry * scale), int(rz * scale)), 0, 0, 360, colour, -1, cv2.LINE_AA,
                        shift=3)  # fmt: skip
    return img


def drawn_scene(n_frames: int, rise: float, draw=None):
    """The drawn stereo scene: the body with its arms out, the left arm rising ``rise`` rad per
    frame and the body stepping left; ``draw(model, q, cam)`` renders a frame (default
    ``_draw``). Returns model, cameras, frames, poses, keypoints, params (200 particles) and the
    observations."""
    draw = _draw if draw is None else draw
    model = default_body()
    cams = _cams()
    q0 = np.zeros(model.n_dof)
    q0[2] = 0.75
    arms = dof_index(model, ["l_shoulder_x", "r_shoulder_x", "l_elbow", "r_elbow", "l_shoulder_y"])
    q0[arms] = [0.5, -0.4, 0.9, 1.3, -0.3]
    qs = np.repeat(q0[None], n_frames, 0)
    qs[:, arms[0]] += rise * np.arange(n_frames)  # the left arm rises slowly
    qs[:, 1] += 0.01 * np.arange(n_frames)  # the body steps left
    frames = np.stack([[draw(model, q, c) for c in cams] for q in qs])
    kp = np.asarray(jax.vmap(lambda q: keypoints(model, q))(jnp.asarray(qs)))
    params = sp.make_params(cams, dtype=jnp.float64, motion=sp.Motion(n_particles=200))
    obs = sp.observe_sequence(params, frames)
    return model, cams, frames, qs, kp, params, obs


@pytest.fixture(scope="module")
def scene():
    return drawn_scene(4, 0.05)


def _errors(model, q_est, kp_true):
    idx = keypoint_index(model, JOINTS)
    kp = np.asarray(jax.vmap(lambda q: keypoints(model, q))(jnp.asarray(q_est)))
    return np.linalg.norm(kp[:, idx] - kp_true[:, idx], axis=-1)


def test_observation_pipeline(scene):
    model, cams, _, _, kp, _, obs = scene
    assert obs.edges.shape == (4, 2, H, W) and obs.points.shape == (4, 3, 3)
    assert bool(np.all(obs.valid))  # head and both hands found and matched in every frame
    # the triangulated blobs reproject near the drawn head / hands (blob centroid vs keypoint);
    # their depth is coarse: 1 px of disparity is ~15 cm with an 11 cm baseline at f = 308 px
    idx = keypoint_index(model, ("head", "l_hand", "r_hand"))
    for cam in cams:
        px = np.linalg.norm(
            camlib.project(cam, obs.points) - camlib.project(cam, kp[:, idx]), axis=-1
        )
        assert px[:, 1:].max() < 2.5, px  # hands
        assert px[:, 0].max() < 5.0, px  # the head blob includes the neck: centroid lower
    assert float(obs.edges.max()) == 1.0 and float(obs.foreground.mean()) > 0.02


def test_tracker_initialises_and_tracks(scene):
    """Automatic initialisation + tracking, over three keys (N = 200 particles for 14 DOFs is
    a small set: one key's result is a draw; the median over keys is the tested quantity)."""
    model, _, _, qs, kp, params, obs = scene
    err0, err, degenerate = [], [], []
    for seed in range(3):
        state, est0 = sp.init(params, jax.random.key(seed), jax.tree.map(lambda a: a[0], obs))
        _, est = sp.run(params, state, obs)
        err0.append(_errors(model, est0.q[None], kp[:1]).mean())
        err.append(_errors(model, est.q, kp).mean(axis=1))
        degenerate.append(bool(np.any(est.degenerate)))
    err0, err = np.array(err0), np.array(err)
    # prior: arms uniform in their limits -> mean joint error of the prior ~ 20 cm
    prior = sp_filter._prior(params, jax.random.key(1), jax.tree.map(lambda a: a[0], obs))
    err_prior = _errors(model, params.full_q(prior.particles[:50]), np.repeat(kp[:1], 50, 0))
    assert err_prior.mean() > 0.12
    assert np.median(err0) < 0.10, err0
    # bounded over the sequence, far below the prior's error
    assert np.median(err.max(axis=1)) < 0.13, err
    assert np.median(err[:, -1]) < 0.5 * err_prior.mean()
    assert not any(degenerate)
    # the weighted mean and the best particle are valid full pose vectors
    assert est.q.shape == (4, model.n_dof) and np.all(np.isfinite(np.asarray(est.q_best)))
    # held DOFs stay at default_q
    held = np.setdiff1d(np.arange(model.n_dof), params.dofs)
    np.testing.assert_array_equal(np.asarray(est.q)[:, held], 0.0)
    del qs


def test_settings_numbers_are_traced_and_switches_static(scene):
    """A new number of the settings (the cues' edge widths and out-of-image edge value) runs
    the compiled filter step as it is; a new switch (Azad's zero padding: no out-of-image
    value) is a new program."""
    _, cams, _, _, _, params, obs = scene
    traces = []

    @eqx.filter_jit
    def step(p, state, o):
        traces.append(1)
        return sp.filter_step(p, state, o)

    first = jax.tree.map(lambda a: a[0], obs)
    state, _ = sp.init(params, jax.random.key(0), first)
    kw = dict(dtype=jnp.float64, motion=sp.Motion(n_particles=200))
    _, a = step(params, state, first)
    other = sp.make_params(cams, cues=sp.Cues(sigma_g=0.3, edge_outside=0.1), **kw)
    _, b = step(other, state, first)
    assert len(traces) == 1  # same program, new values
    assert not np.array_equal(np.asarray(a.best_loglik), np.asarray(b.best_loglik))
    step(sp.make_params(cams, cues=sp.Cues(edge_outside=None), **kw), state, first)
    assert len(traces) == 2  # a switch is a new program


def test_determinism_and_scan_equals_loop(scene):
    _, _, frames, _, _, params, obs = scene
    first = jax.tree.map(lambda a: a[0], obs)
    s1, _ = sp.init(params, jax.random.key(3), first)
    s2, _ = sp.init(params, jax.random.key(3), first)
    np.testing.assert_array_equal(s1.particles.particles, s2.particles.particles)
    _, est_scan = sp.run(params, s1, jax.tree.map(lambda a: a[:2], obs))
    # the same scan compiled as its own program with COMPILER_OPTIONS: rounding only
    _, est_top = sp.run_top_level(params, s1, jax.tree.map(lambda a: a[:2], obs))
    np.testing.assert_allclose(est_top.q, est_scan.q, rtol=1e-9, atol=1e-12)
    # live loop: host image processing per frame + one jitted step, same key sequence
    s = s2
    for t in range(2):
        s, e = sp.step(params, s, frames[t], (np.asarray(obs.points[t]), np.asarray(obs.valid[t])))
        np.testing.assert_allclose(e.q, est_scan.q[t], rtol=1e-9, atol=1e-12)
    s3, _ = sp.init(params, jax.random.key(4), first)
    assert not np.array_equal(s3.particles.particles, s1.particles.particles)


def test_live_stream_equals_init_and_steps(scene):
    """stereo_pf.live (compiled step with the params closed over, host/device overlap, one
    frame late) hands out the same estimates as init on the anchor frame + filter_step. live's
    initialisation compiles with COMPILER_OPTIONS (XLA's classic CPU emitters), the plain init
    with XLA's defaults: the two agree to rounding (float64 here)."""
    _, _, frames, _, _, params, obs = scene
    key = jax.random.key(5)
    t0 = sp.anchor_frame(obs)
    out = list(sp.live(params, key, iter(frames)))
    assert [t for t, _ in out] == list(range(len(frames)))
    assert all(e is None for _, e in out[:t0]) and out[t0][1] is not None
    state, est = sp.init(params, key, jax.tree.map(lambda a: a[t0], obs))
    np.testing.assert_allclose(out[t0][1].q, est.q, rtol=1e-9, atol=1e-12)
    for t in range(t0 + 1, len(frames)):
        state, est = sp.filter_step(params, state, jax.tree.map(lambda a, t=t: a[t], obs))
        np.testing.assert_allclose(out[t][1].q, est.q, rtol=1e-9, atol=1e-12)


def test_live_side_device_changes_no_estimate(scene, monkeypatch):
    """The blob tracker's triangulation on the second CPU device (conftest enables it, as the
    CLI does) gives bit-identical estimates to the same calls on the default device."""
    from jaxmocap import blobs
    from jaxmocap._config import side_device

    _, _, frames, _, _, params, _ = scene
    assert side_device() is not None and side_device() != jax.devices()[0]
    key = jax.random.key(5)
    side = [(t, e) for t, e in sp.live(params, key, iter(frames)) if e is not None]
    monkeypatch.setattr(blobs, "side_device", lambda: None)
    one = [(t, e) for t, e in sp.live(params, key, iter(frames)) if e is not None]
    assert [t for t, _ in side] == [t for t, _ in one] and len(one) > 2
    for (_, a), (_, b) in zip(side, one, strict=True):
        np.testing.assert_array_equal(np.asarray(a.q), np.asarray(b.q))


def test_input_errors(scene):
    _, cams, frames, _, _, params, _ = scene
    with pytest.raises(InputError, match="frame_pair"):
        sp.observe(params, frames[0, :, :60], None, (np.zeros((3, 3)), np.zeros(3, bool)))
    with pytest.raises(InputError, match="dofs"):
        sp.make_params(cams, dofs=[6, 7, 8])
    with pytest.raises(InputError, match="n_particles"):
        sp.make_params(cams, motion=sp.Motion(n_particles=1))


def _swivel(k, sh, el, ha, k_true):
    """Angle (rad) of the elbow about the shoulder-hand axis of each pose k (n, n_kp, 3),
    from the true elbow's direction about the true axis."""

    def perp(k):
        axis = k[..., ha, :] - k[..., sh, :]
        axis = axis / np.linalg.norm(axis, axis=-1, keepdims=True)
        v = k[..., el, :] - k[..., sh, :]
        return v - np.sum(v * axis, -1, keepdims=True) * axis, axis

    ref, _ = perp(k_true)
    v, axis = perp(k)
    return np.arctan2(np.sum(np.cross(ref, v) * axis, -1), np.sum(ref * v, -1))


def test_guided_proposal_lands_hands_keeps_elbow_swivel(scene):
    """The distance-cue-guided proposal on the body: particles drawn around the true pose with
    the filter's maximal noise; the guided half ends with FK head / hands on the (true) target
    points, while the elbows -- which the hand and head points do not fix (the swivel about the
    shoulder-hand line) -- keep most of their spread. A missing right hand leaves the right
    arm's DOFs exactly as predicted. jit(vmap) == a loop of single-particle eager calls."""
    model, cams, _, qs, kp, _, _ = scene
    params = sp.make_params(cams, dtype=jnp.float64, motion=sp.Motion(n_particles=200),
                            proposals=sp.Proposals(guided=True, swivel_fraction=0.0))
    prop = params.filter.proposal
    dofs = params.dofs
    rng = np.random.default_rng(5)
    x = qs[0][dofs][None] + np.asarray(params.filter.sigma_max) * rng.standard_normal((200, 14))
    ent = keypoint_index(model, ("head", "l_hand", "r_hand"))
    obs = sp.Observation(
        edges=jnp.zeros((2, H, W)), points=jnp.asarray(kp[0, ent]),
        valid=jnp.ones(3, bool), foreground=jnp.zeros((2, H, W)),
    )  # fmt: skip
    key = jax.random.key(2)
    out = np.asarray(eqx.filter_jit(prop)(jnp.asarray(x), obs, key))
    moved = np.any(out != x, axis=1)
    assert moved.sum() == 100

    def kps(s):
        return np.asarray(jax.vmap(lambda q: keypoints(model, q))(params.full_q(jnp.asarray(s))))

    kb, ka = kps(x[moved]), kps(out[moved])
    err_before = np.linalg.norm(kb[:, ent] - kp[0, ent], axis=-1)
    err_after = np.linalg.norm(ka[:, ent] - kp[0, ent], axis=-1)
    assert np.median(err_before) > 0.05
    assert np.median(err_after) < 0.005 and np.percentile(err_after, 90) < 0.02, err_after.max()
    # the swivel angle of each elbow about its own shoulder-hand line, measured from the true
    # elbow's direction: its spread is what the edge cue has to decide; it must survive
    for side in ("l", "r"):
        sh, el, ha = keypoint_index(model, (f"{side}_shoulder", f"{side}_elbow", f"{side}_hand"))
        ang_b, ang_a = _swivel(kb, sh, el, ha, kp[0]), _swivel(ka, sh, el, ha, kp[0])
        assert ang_b.std() > 0.1 and ang_a.std() > 0.8 * ang_b.std(), (ang_a.std(), ang_b.std())
    # vmap inside the jitted call == per-particle eager Gauss-Newton steps
    idx = np.flatnonzero(moved)[:3]
    for i in idx:
        one = pf.min_norm_steps(
            params.likelihood.distance_residual, jnp.asarray(x[i]), obs, prop.scale,
            prop.damping, prop.n_steps,
        )  # fmt: skip
        np.testing.assert_allclose(np.asarray(one), out[i], atol=1e-9)
    # a missing right hand constrains nothing of the right arm
    obs_l = eqx.tree_at(lambda o: o.valid, obs, jnp.array([True, True, False]))
    out_l = np.asarray(eqx.filter_jit(prop)(jnp.asarray(x), obs_l, key))
    r_arm = np.isin(
        dofs, dof_index(model, ["r_shoulder_x", "r_shoulder_y", "r_shoulder_z", "r_elbow"])
    )
    np.testing.assert_array_equal(out_l[:, r_arm], x[:, r_arm])
    assert np.any(out_l[:, ~r_arm] != x[:, ~r_arm])


def test_support_map_and_observation(scene):
    """support_map = (skin | shirt) dilated by a (2 r + 1)^2 square (scipy's binary dilation
    as the oracle); observe() adds it (both cameras) when the likelihood reads it, and the
    drawn scene's true hands lie on it in both views."""
    from scipy.ndimage import binary_dilation

    model, cams, frames, _, kp, _, _ = scene
    rng = np.random.default_rng(3)
    skin, shirt = rng.random((2, 30, 40)) > 0.97
    got = sp.support_map(skin, shirt, 2)
    want = binary_dilation(skin | shirt, np.ones((5, 5), bool))
    np.testing.assert_array_equal(got, want.astype(np.float32))
    np.testing.assert_array_equal(sp.support_map(skin, shirt, 0), (skin | shirt))
    params = sp.make_params(cams, dtype=jnp.float64, motion=sp.Motion(n_particles=200),
                            cues=sp.Cues(use_support=True))
    obs, _ = sp.observe(params, frames[0], None, (np.zeros((3, 3)), np.zeros(3, bool)))
    assert obs.support is not None and obs.support.shape == (2, H, W)
    hands = keypoint_index(model, ("l_hand", "r_hand"))
    for c, cam in enumerate(cams):
        u, v = np.round(np.asarray(camlib.project(cam, kp[0, hands]))).astype(int).T
        assert np.all(np.asarray(obs.support)[c, v, u] == 1.0)



def test_fixed_lag_smoothing_keeps_the_filter(scene):
    """``run(smooth_lag=L)``: the filter is unchanged (``q_filtered``, the other fields), ``q``
    is the genealogy smoother's mean, equal to the filter's on the last frame."""
    model, _, _, _, kp, params, obs = scene
    state, _ = sp.init(params, jax.random.key(0), jax.tree.map(lambda a: a[0], obs))
    _, ref = sp.run(params, state, obs)
    _, est = sp.run(params, state, obs, 2)
    assert ref.q_filtered is None
    np.testing.assert_array_equal(est.q_filtered, ref.q)
    np.testing.assert_array_equal(est.best_loglik, ref.best_loglik)
    np.testing.assert_allclose(est.q[-1], ref.q[-1], rtol=1e-12)
    assert not np.allclose(est.q[:-1], ref.q[:-1])
    held = np.setdiff1d(np.arange(model.n_dof), params.dofs)
    np.testing.assert_array_equal(np.asarray(est.q)[:, held], 0.0)
    # a smoothed pose is a mix of the filter's particles: as close to the truth as the filter
    assert _errors(model, est.q, kp).mean() < 1.5 * _errors(model, ref.q, kp).mean()
    with pytest.raises(InputError, match="smooth_lag"):
        sp.run(params, state, obs, -1)


@pytest.mark.parametrize("which", ["bundled", "foreign"])
def test_swivel_jump_rotates_the_elbow_about_the_shoulder_hand_line(scene, rng, which, tmp_path):
    """``SwivelProposal._swivel``: hands, shoulders and head do not move; each elbow turns by
    exactly phi about its shoulder-hand line (measured on the keypoints); jit and vmap. The
    arms come from the body's roles: the same on the foreign body (tests/_foreign_body.py)."""
    model, cams = scene[0], scene[1]
    if which == "foreign":
        from _foreign_body import foreign_urdf

        from jaxmocap.body import load_body

        model = load_body(foreign_urdf(tmp_path / "foreign.urdf"))
    params = sp.make_params(cams, model=model, dtype=jnp.float64,
                            proposals=sp.Proposals(swivel_fraction=0.1))
    prop = params.filter.proposal
    assert isinstance(prop, sp.SwivelProposal) and len(prop.arms) == 2
    names = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand", "head")
    idx = keypoint_index(model, names)
    s = jnp.asarray(rng.uniform(-0.7, 0.7, (6, 14)))
    phi = jnp.asarray(rng.uniform(-np.pi, np.pi, (6, 2)))
    moved = jax.jit(jax.vmap(prop._swivel))(s, phi)
    for k in range(6):
        a = np.asarray(keypoints(model, params.full_q(s[k])))[idx]
        b = np.asarray(keypoints(model, params.full_q(moved[k])))[idx]
        np.testing.assert_allclose(b[[0, 1, 4, 5, 6]], a[[0, 1, 4, 5, 6]], atol=1e-9)
        for arm in range(2):
            sh, el, ha = 0 + arm, 2 + arm, 4 + arm
            u = (a[ha] - a[sh]) / np.linalg.norm(a[ha] - a[sh])
            va = a[el] - a[sh] - np.dot(a[el] - a[sh], u) * u
            vb = b[el] - a[sh] - np.dot(b[el] - a[sh], u) * u
            ang = np.arctan2(np.dot(np.cross(va, vb), u), np.dot(va, vb))
            np.testing.assert_allclose(np.linalg.norm(vb), np.linalg.norm(va), atol=1e-9)
            np.testing.assert_allclose(np.angle(np.exp(1j * (ang - float(phi[k, arm])))), 0.0,
                                       atol=1e-7)  # fmt: skip
    # elbows and root untouched in the state; the x-y-z decomposition inverts the rotation
    np.testing.assert_array_equal(moved[:, :6], s[:, :6])
    np.testing.assert_array_equal(moved[:, [9, 13]], s[:, [9, 13]])
    a3 = jnp.asarray(rng.uniform(-1.4, 1.4, (20, 3)))
    round_trip = jax.vmap(lambda v: sp_swivel._angles_xyz(sp_swivel._rot_xyz(v)))
    np.testing.assert_allclose(round_trip(a3), a3,
                               atol=1e-9)  # fmt: skip
    # the whole move on a particle set: only `fraction` of the particles change
    x = jnp.tile(s[:1], (50, 1))
    out = dataclasses.replace(prop, inner=None)(x, None, jax.random.key(0))  # the jumps alone
    changed = np.any(np.asarray(out) != np.asarray(x), axis=1)
    assert 1 <= changed.sum() <= 5
    with pytest.raises(InputError, match="swivel_fraction"):
        sp.make_params(cams, proposals=sp.Proposals(swivel_fraction=1.5))


def test_frame_validity_against_the_true_pose(scene):
    """The true pose agrees with the triangulated head and hands: valid. The same pose moved
    by 30 cm, or a frame whose head is not triangulated, cannot be trusted: invalid."""
    model, cams, frames, qs, kp, params, obs = scene
    pts, val = np.asarray(obs.points), np.asarray(obs.valid)
    assert val[:, 0].all()
    assert sp.frame_validity(params, qs, pts, val).all()
    moved = qs.copy()
    moved[:, 1] += 0.3
    assert not sp.frame_validity(params, moved, pts, val).any()
    no_head = val.copy()
    no_head[1, 0] = False
    np.testing.assert_array_equal(sp.frame_validity(params, qs, pts, no_head),
                                  [True, False, True, True])
    # swapped hand identities are paired with the nearer model hands; a hand without a point
    # leaves the arm unmeasured in depth: invalid (by default both hands are required)
    assert sp.frame_validity(params, qs, pts[:, [0, 2, 1]], val).all()
    one_hand = val.copy()
    one_hand[:, 2] = False
    assert not sp.frame_validity(params, qs, pts, one_hand).any()
    assert sp.frame_validity(params, qs, pts, one_hand, min_hands=1).all()
    res = sp.head_residual(params, moved, pts, val)
    np.testing.assert_allclose(res, 0.3, atol=0.06)  # the blob centroid is ~3 cm off the centre


def test_capture_colours_give_the_blobs_of_the_drawn_scene(scene):
    """Skin and shirt colours fitted from scribbles on the first frame (a disc on the face, a
    stroke on the torso) find the head and both hands where the drawn scene has them."""
    from jaxmocap.pf.colors import fit_capture_colors

    model, cams, frames, qs, kp, params, obs = scene
    head = keypoint_index(model, ["head", "l_hand", "r_hand"])
    imgs, skin, shirt = [], [], []
    yy, xx = np.mgrid[:H, :W]
    for c, cam in enumerate(cams):
        uv = np.asarray(camlib.project(cam, jnp.asarray(kp[0, head[0]])))
        imgs.append(frames[0, c])
        skin.append((xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= 3**2)
        mask = np.all(frames[0, c] == SHIRT, axis=-1)
        shirt.append(cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0)
    colors = fit_capture_colors(imgs, skin, shirt)
    p2 = sp.make_params(cams, dtype=jnp.float64, motion=sp.Motion(n_particles=200),
                        images=sp.Images(colors=colors, plausible_blobs=True))
    o2 = sp.observe_sequence(p2, frames)
    assert np.asarray(o2.valid).all()
    np.testing.assert_allclose(np.asarray(o2.points), kp[:, head], atol=0.06)
    # the foreground is the shirt as the HSV interval finds it (the drawn shirt colour)
    fg = np.asarray(o2.foreground) > 0
    for c in range(2):
        drawn = np.all(frames[:, c] == SHIRT, axis=-1).astype(np.uint8)
        inner = np.stack([cv2.erode(m, np.ones((3, 3), np.uint8)) for m in drawn]) > 0
        outer = np.stack([cv2.dilate(m, np.ones((5, 5), np.uint8)) for m in drawn]) > 0
        assert fg[:, c][inner].all() and not fg[:, c][~outer].any()


def test_online_tracker_waits_for_a_triangulated_head(scene):
    """The CLI's frame tracker initialises on the first frame with a head, as the offline
    track() does: frames before it are invalid and say so."""
    from jaxmocap.trackers.driver import StereoPFFrameTracker

    model, cams, frames, qs, kp, params, obs = scene
    tr = StereoPFFrameTracker(cams, 20, 0)
    blank = np.full_like(frames[0], BACKGROUND)
    tr.start(blank)
    r0 = tr.step(blank)
    assert not r0.valid and r0.diagnostics["waiting_for_head"] == 1.0
    assert np.isnan(r0.q).all()
    r1 = tr.step(frames[0])
    assert r1.diagnostics["waiting_for_head"] == 0.0 and np.isfinite(r1.q).all()
    assert r1.diagnostics["head_residual_m"] < 0.2


def test_online_tracker_takes_the_capture_colours_and_skin_grow(scene, tmp_path):
    """`track --pf-colors FILE --pf-skin-grow 4`: the frame tracker's skin map is the
    hysteresis map of the colours (pf.colors.hysteresis_masks); without colours refused."""
    from jaxmocap.commands.track import _make_tracker
    from jaxmocap.pf.colors import hysteresis_masks, save_capture_colors
    from jaxmocap.trackers.driver import StereoPFFrameTracker

    model, cams, frames, *_ = scene
    colors = _scene_colors(scene)
    path = save_capture_colors(tmp_path / "pf_colors.json", colors)
    tr = StereoPFFrameTracker(cams, 20, 0, pf_colors=str(path), skin_grow=4)
    assert tr.params.skin_grow == 4 and tr.params.reach is not None
    seg = sp_observation._segment(tr.params, frames[0, 0])
    np.testing.assert_array_equal(seg.skin, hysteresis_masks(tr.params.colors, frames[0, 0],
                                                             4)[0])
    args = argparse.Namespace(method="pf", garment=None, pf_colors=None, skin="default",
                               pf_skin_grow=4, body=None, particles=20, seed=0,
                               tuned=None, ik_cov=None)
    with pytest.raises(InputError, match="needs --pf-colors"):
        _make_tracker(args, cams, ["0", "1"])


def _scene_colors(scene):
    """Skin and shirt colours from scribbles on frame 0 (a disc on the face, the eroded
    shirt), as in test_capture_colours_give_the_blobs_of_the_drawn_scene."""
    from jaxmocap.pf.colors import fit_capture_colors

    model, cams, frames, _, kp, _, _ = scene
    head = keypoint_index(model, ["head"])[0]
    imgs, skin, shirt = [], [], []
    yy, xx = np.mgrid[:H, :W]
    for c, cam in enumerate(cams):
        uv = np.asarray(camlib.project(cam, jnp.asarray(kp[0, head])))
        imgs.append(frames[0, c])
        skin.append((xx - uv[0]) ** 2 + (yy - uv[1]) ** 2 <= 3**2)
        mask = np.all(frames[0, c] == SHIRT, axis=-1)
        shirt.append(cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8)) > 0)
    return fit_capture_colors(imgs, skin, shirt)


def test_colour_adaptation_off_is_the_fixed_model_and_follows_a_skin_change(scene):
    """adapt_colors off: track() is observe_sequence + init + run (their top-level programs),
    bit for bit; on with rates 0: the same observations. On: the skin of frames 1-3 drifts
    toward a darker, redder colour (a lamp on the subject only); the fixed model loses the head
    on the last frame, the adapted one (updated from the head the filter agrees with) still
    triangulates it."""
    from jaxmocap.trackers.stereo_pf.adapt import observe_adaptive

    model, cams, frames, qs, kp, _, _ = scene
    colors = _scene_colors(scene)
    kw = dict(motion=sp.Motion(n_particles=200), dtype=jnp.float64)
    images = sp.Images(colors=colors, plausible_blobs=True)
    p_off = sp.make_params(cams, images=images, **kw)
    assert p_off.adapt is None
    key = jax.random.key(0)
    obs = sp.observe_sequence(p_off, frames)
    state, _ = sp.init_top_level(p_off, key, jax.tree.map(lambda a: a[sp.anchor_frame(obs)], obs))
    _, ref = sp.run_top_level(p_off, state, obs)
    np.testing.assert_array_equal(sp.track(p_off, key, frames).q, ref.q)
    # the driver's offline run (experiment cells, the demo) is the same filter, bit for bit
    from jaxmocap.trackers.driver import stereo_offline

    run = stereo_offline(p_off, key, frames, repeat=True)
    np.testing.assert_array_equal(run.estimate.q, ref.q)
    assert run.init_frame == sp.anchor_frame(obs) and set(run.timings) == {
        "observe_first", "observe", "filter_first", "filter"}
    p_zero = sp.make_params(cams, images=dataclasses.replace(
        images, adapt_colors=True, adapt_rate=0.0, adapt_shirt_rate=0.0), **kw)
    o_zero, log = observe_adaptive(p_zero, key, frames)
    for a, b in zip(jax.tree.leaves(o_zero), jax.tree.leaves(obs), strict=True):
        np.testing.assert_array_equal(a, b)
    assert log["confident"].sum() >= 2  # the filter agrees with the triangulated head
    with pytest.raises(InputError, match="adapt_colors"):
        sp.make_params(cams, images=sp.Images(adapt_colors=True))

    end = np.array([205.0, 125.0, 85.0])
    drifted = frames.copy()
    for t in range(1, len(frames)):
        rgb = np.asarray(SKIN) + (end - np.asarray(SKIN)) * t / (len(frames) - 1)
        for c in range(2):
            m = np.all(frames[t, c] == SKIN, axis=-1)
            drifted[t, c][m] = np.round(rgb).astype(np.uint8)
    o_fixed = sp.observe_sequence(p_off, drifted)
    assert not np.asarray(o_fixed.valid)[-1, 0]  # the fixed model lost the head
    p_on = sp.make_params(cams, images=dataclasses.replace(
        images, adapt_colors=True, adapt_rate=0.5, adapt_shirt_rate=0.0, adapt_spread=2.0),
        **kw)  # fast: the drift spans 3 frames
    o_on, log = observe_adaptive(p_on, key, drifted)
    assert np.asarray(o_on.valid)[:, 0].all(), log
    head = keypoint_index(model, ["head"])[0]
    np.testing.assert_allclose(np.asarray(o_on.points)[:, 0], kp[:, head], atol=0.06)
    est = sp.track(p_on, key, drifted)
    assert np.isfinite(np.asarray(est.q)).all()
