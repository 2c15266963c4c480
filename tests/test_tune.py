"""Tests of jaxmocap.tune: gradients of the IK and colour losses against central finite
differences (float64), jit, NaN-free gradients with missing patches, closed form as the
starting point, constraints round trip, and the loss falling under a few Adam steps; the stereo
filter's loss against the tracker's own run (its gradient's estimator is tested against the
Kalman filter in test_pf_filter.py).

The IK tests use a small arm (root + 3 revolute joints) so that the solve compiles fast; the
stereo filter's loss runs the tracker on its drawn 4-frame scene with 32 particles.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import tune
from jaxmocap.body import load_urdf
from jaxmocap.camera import stack_cameras
from jaxmocap.color import ColorModel, classify
from jaxmocap.ik import IKCovariances, anchors_from_samples, project_anchors
from jaxmocap.synth.scene import SceneConfig, make_cameras

ARM_URDF = """<robot name="arm">
  <link name="torso"><visual><geometry><box size="0.2 0.3 0.5"/></geometry></visual></link>
  <link name="upper0"/>
  <link name="upper"><visual><origin xyz="0 0 -0.15"/>
    <geometry><cylinder radius="0.05" length="0.3"/></geometry></visual></link>
  <link name="fore"><visual><origin xyz="0 0 -0.15"/>
    <geometry><cylinder radius="0.04" length="0.3"/></geometry></visual></link>
  <joint name="shoulder_x" type="revolute"><parent link="torso"/><child link="upper0"/>
    <origin xyz="0 0.2 0.2"/><axis xyz="1 0 0"/><limit lower="-2" upper="2"
    effort="1" velocity="1"/></joint>
  <joint name="shoulder_y" type="revolute"><parent link="upper0"/><child link="upper"/>
    <axis xyz="0 1 0"/><limit lower="-2" upper="2"
    effort="1" velocity="1"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/>
    <origin xyz="0 0 -0.3"/><axis xyz="0 1 0"/><limit lower="0" upper="2.5"
    effort="1" velocity="1"/></joint>
</robot>"""
KEYPOINTS = {"pelvis": ("torso", (0, 0, -0.25)), "neck": ("torso", (0, 0, 0.25)),
             "shoulder": ("upper", (0, 0, 0)), "elbow": ("fore", (0, 0, 0)),
             "hand": ("fore", (0, 0, -0.3))}  # fmt: skip
# Patch anchors: (link, offset in the link frame, m).
PATCHES = [("torso", (0.1, 0.1, 0.1)), ("torso", (0.1, -0.1, 0.1)), ("torso", (0.1, 0, -0.15)),
           ("torso", (0.1, 0.1, -0.15)), ("upper", (0.05, 0, -0.1)), ("upper", (0, 0.05, -0.2)),
           ("fore", (0.04, 0, -0.1)), ("fore", (0, 0.04, -0.25))]  # fmt: skip
T_WINDOW = 4
RTOL, ATOL = 1e-11, 1e-13  # tight solves: FD noise ~ solve error / h


@pytest.fixture(scope="module")
def arm(tmp_path_factory):
    path = tmp_path_factory.mktemp("arm") / "arm.urdf"
    path.write_text(ARM_URDF)
    model = load_urdf(path, keypoints=KEYPOINTS)
    link = np.array([model.chain.link_index(n) for n, _ in PATCHES])
    anchors = anchors_from_samples(link, np.array([[o] for _, o in PATCHES], np.float64))
    cams = stack_cameras(make_cameras(SceneConfig(width=160, height=120), jnp.float64))
    setup = tune.ik_setup(model, cams, anchors, rtol=RTOL, atol=ATOL)
    return model, anchors, cams, setup


def make_observations(arm, rng, n_windows=2, missing=0.25, pixel_std=1.5):
    model, anchors, cams, _ = arm
    n = model.n_dof
    T = T_WINDOW * n_windows
    t = np.arange(T)[:, None]
    q = np.zeros((T, n))
    q[:, 0:3] = [0.0, 0.0, 1.0] + 0.01 * t * np.array([1, 0, 0])
    q[:, 3:6] = 0.05 * np.sin(0.4 * t + np.arange(3))
    q[:, 6:] = [0.3, 0.2, 0.8] + 0.25 * np.sin(0.5 * t + np.arange(3))
    proj = jax.vmap(project_anchors, in_axes=(None, None, None, 0))(
        cams, model.chain, anchors, jnp.asarray(q)
    )
    c = np.asarray(proj) + rng.normal(0, pixel_std, proj.shape)
    vis = rng.random(c.shape[:3]) > missing
    c[~vis] = np.nan  # missing patches carry NaN: must not reach any gradient
    q_b = q + rng.normal(0, 0.06, q.shape) * np.r_[[0.03] * 3, [1.0] * (n - 3)]
    return tune.ik_observations([(c, vis, q_b, q)], T_WINDOW, jnp.float64)


@pytest.fixture(scope="module")
def ik_problem(arm):
    obs = make_observations(arm, np.random.default_rng(1))
    _, _, _, setup = arm
    theta = tune.ik_theta(IKCovariances.isotropic(2.0, 0.08, 0.2, setup.body.n_dof))
    vg = jax.jit(jax.value_and_grad(tune.ik_loss))  # the whole loss under one jit
    return obs, theta, vg


def directional_fd(f, theta, name, d, h):
    shift = lambda s: eqx.tree_at(lambda t: getattr(t, name), theta, getattr(theta, name) + s * d)
    return (f(shift(h)) - f(shift(-h))) / (2 * h)


# ----------------------------------------------------------------------------- constraints


def test_log_cholesky_round_trip_and_positive_definite(rng):
    A = rng.normal(size=(5, 5))
    cov = jnp.asarray(A @ A.T + 0.1 * np.eye(5))
    theta = tune.log_cholesky_from_spd(cov)
    assert theta.shape == (15,)
    np.testing.assert_allclose(tune.spd_from_log_cholesky(theta), cov, rtol=1e-12, atol=1e-12)
    for _ in range(5):  # any unconstrained vector gives a symmetric positive definite matrix
        S = tune.spd_from_log_cholesky(jnp.asarray(rng.normal(size=15) * 3))
        np.testing.assert_allclose(S, S.T)
        assert np.linalg.eigvalsh(np.asarray(S)).min() > 0
    with pytest.raises(ValueError, match="n \\(n \\+ 1\\) / 2"):
        tune.spd_from_log_cholesky(jnp.zeros(4))
    every = set(tune.IK_PARAMETERS) | set(tune.COLOR_PARAMETERS) | set(tune.PF_PARAMETERS)
    assert every == {"centroid", "blend", "prior", "cov", "threshold", "sigma_g", "sigma_d"}


def test_ik_theta_round_trip_and_refusals(arm):
    _, _, _, setup = arm
    n = setup.body.n_dof
    cov = IKCovariances.isotropic(2.0, 0.1, 0.3, n)
    back = tune.ik_covariances(tune.ik_theta(cov))
    np.testing.assert_allclose(back.centroid, cov.centroid, rtol=1e-12)
    np.testing.assert_allclose(back.blend, np.diag(cov.blend), rtol=1e-12, atol=1e-15)
    per_patch = IKCovariances(jnp.broadcast_to(jnp.eye(2), (3, 2, 2)), cov.blend, cov.prior)
    with pytest.raises(tune.TuneError, match="shared Sigma_c"):
        tune.ik_theta(per_patch)
    with pytest.raises(tune.TuneError, match="window"):
        tune.ik_observations([], 1)
    with pytest.raises(tune.TuneError, match="no sequence"):
        z = np.zeros
        tune.ik_observations([(z((3, 2, 8, 2)), z((3, 2, 8), bool), z((3, n)), z((3, n)))], 4)
    with pytest.raises(tune.TuneError, match="joints"):
        tune.ik_setup(setup.body, setup.cams, setup.anchors, joints=["nose"])


# ----------------------------------------------------------------------------- IK covariances


def test_ik_track_matches_per_frame_solves(arm, ik_problem):
    """The scan is the tracker's step 4: frame t's prior is the previous solution."""
    from jaxmocap.ik import solve_ik

    model, anchors, cams, setup = arm
    obs, theta, _ = ik_problem
    cov = tune.ik_covariances(theta)
    q_scan, ok = jax.jit(tune.ik_track)(cov, setup, obs.centroids[0], obs.visible[0], obs.q_b[0])
    q_prev = obs.q_b[0, 0]
    for t in range(T_WINDOW):
        c, v, qb = obs.centroids[0, t], obs.visible[0, t], obs.q_b[0, t]
        q_h = qb if t == 0 else q_prev
        sol = solve_ik(model.chain, cams, anchors, c, v, qb, q_h, cov, qb, rtol=RTOL, atol=ATOL)
        q_prev = sol.q if bool(ok[t]) else q_prev
        np.testing.assert_allclose(q_scan[t], q_prev, atol=1e-9)


def test_ik_track_from_given_starts(arm, ik_problem):
    """``q_start``: each solve starts there instead of at q_b (per-frame solve oracle); started
    at the solutions themselves the scan returns them (a converged LM stays put), and a
    non-finite start row falls back to q_b."""
    from jaxmocap.ik import solve_ik

    model, anchors, cams, setup = arm
    obs, theta, _ = ik_problem
    cov = tune.ik_covariances(theta)
    c, v, qb = obs.centroids[0], obs.visible[0], obs.q_b[0]
    track = jax.jit(tune.ik_track)
    q_ref, ok = track(cov, setup, c, v, qb)
    q_self, _ = track(cov, setup, c, v, qb, q_ref)
    np.testing.assert_allclose(q_self, q_ref, atol=1e-6)
    start = obs.q_gt[0] + 0.05
    q_s, _ = track(cov, setup, c, v, qb, start)
    q_prev = qb[0]
    for t in range(T_WINDOW):
        q_h = qb[t] if t == 0 else q_prev
        sol = solve_ik(model.chain, cams, anchors, c[t], v[t], qb[t], q_h, cov, start[t],
                       rtol=RTOL, atol=ATOL)  # fmt: skip
        q_prev = sol.q if bool(ok[t]) else q_prev
        np.testing.assert_allclose(q_s[t], q_prev, atol=1e-9)
    n = model.n_dof
    bad = np.asarray(start).copy()
    bad[1] = np.nan
    seq = (np.asarray(c), np.asarray(v), np.asarray(qb), np.asarray(obs.q_gt[0]),
           np.ones(T_WINDOW, bool))
    o = tune.ik_observations([(*seq, bad)], T_WINDOW)
    np.testing.assert_allclose(o.q_start[0, 1], qb[1])
    np.testing.assert_allclose(o.q_start[0, 0], start[0])
    with pytest.raises(tune.TuneError, match="q_start has shape"):
        tune.ik_observations([(*seq, np.zeros((T_WINDOW, n + 1)))], T_WINDOW)


def test_ik_loss_gradients_match_finite_differences(arm, ik_problem, rng):
    _, _, _, setup = arm
    obs, theta, vg = ik_problem
    value, grad = vg(theta, setup, obs)
    assert 0 < float(value) < 0.5  # metres
    f = lambda th: vg(th, setup, obs)[0]
    for name in ("centroid", "blend", "prior"):
        g = getattr(grad, name)
        assert np.all(np.isfinite(g)) and np.abs(g).max() > 1e-8, name
        d = rng.normal(size=g.shape)
        fd = float(directional_fd(f, theta, name, d, 1e-4))
        an = float(jnp.vdot(g, d))
        assert abs(an - fd) <= 1e-3 * abs(fd), (name, an, fd)


def test_no_nan_gradient_with_missing_patches_and_invalid_frames(arm, ik_problem):
    """Frames without patches (invalid: the pose is held) and NaN centroids give finite
    gradients."""
    _, _, _, setup = arm
    obs, theta, vg = ik_problem
    vis = obs.visible.at[0, 1].set(False).at[1, 2, 0].set(False)
    c = jnp.where(vis[..., None], obs.centroids, jnp.nan)
    obs2 = tune.IKObservations(c, vis, obs.q_b, obs.q_gt)
    value, grad = vg(theta, setup, obs2)
    assert np.isfinite(float(value))
    assert all(np.all(np.isfinite(g)) for g in jax.tree.leaves(grad))


def test_closed_form_then_adam_lowers_the_tracking_error(arm, ik_problem):
    """The paper's estimate is the start; a few Adam steps on the same data lower the loss."""
    _, _, _, setup = arm
    obs, _, vg = ik_problem
    cov0 = tune.ik_closed_form(setup, obs)
    # the closed form is the (pooled) second moment of q_gt - q_b
    e = np.asarray(obs.q_gt - obs.q_b).reshape(-1, setup.body.n_dof)
    np.testing.assert_allclose(cov0.blend, e.T @ e / e.shape[0], rtol=1e-4, atol=1e-8)  # + ridge
    theta0 = tune.ik_theta(cov0)
    theta, losses = tune.fit(lambda th: vg(th, setup, obs), theta0, steps=4,
                             learning_rate=0.1, value_and_grad=True)  # fmt: skip
    assert losses.shape == (5,) and np.all(np.isfinite(losses))
    assert losses.min() < losses[0] - 1e-5
    assert float(vg(theta, setup, obs)[0]) == pytest.approx(losses.min())


# ----------------------------------------------------------------------------- colour model


@pytest.fixture(scope="module")
def colour_problem():
    rng = np.random.default_rng(2)
    means = np.array([[200.0, 40, 40], [40, 200, 40], [40, 40, 200]])
    covs = np.stack([np.diag([90.0, 60, 50]) + 20 * (np.ones((3, 3)) - np.eye(3))] * 3)
    n_img, n_pix = 2, 300
    labels = rng.integers(0, 4, (n_img, n_pix))
    pix = rng.uniform(0, 255, (n_img, n_pix, 3))  # background: anything
    for k in range(1, 4):
        m = labels == k
        pix[m] = rng.multivariate_normal(means[k - 1], covs[k - 1] * 4, m.sum())
    pix = np.clip(pix, 0, 255)
    W = np.stack([np.eye(3), np.diag([1.05, 0.95, 1.0])])
    data = tune.ColorData(jnp.asarray(pix), jnp.asarray(labels, jnp.int32), jnp.asarray(W))
    model = ColorModel(jnp.asarray(means), jnp.asarray(covs))
    return model, data


def test_color_loss_gradients_match_finite_differences(colour_problem, rng):
    model, data = colour_problem
    theta = tune.color_theta(model, 3.0)
    vg = jax.jit(jax.value_and_grad(tune.color_loss))
    _, grad = vg(theta, model, data)
    f = lambda th: vg(th, model, data)[0]
    for name in ("cov", "threshold"):
        g = getattr(grad, name)
        assert np.all(np.isfinite(g)) and np.abs(g).max() > 1e-6
        d = rng.normal(size=g.shape)
        fd = float(directional_fd(f, theta, name, d, 1e-5))
        an = float(jnp.vdot(g, d))
        assert abs(an - fd) <= 1e-3 * abs(fd), (name, an, fd)


def test_color_tuning_lowers_cross_entropy_and_hard_errors(colour_problem):
    """Data drawn with 4x the model's covariances: tuning widens Sigma_k, and the hard
    classifier with the tuned model and T misclassifies fewer pixels."""
    model, data = colour_problem
    theta0 = tune.color_theta(model, 3.0)
    theta, losses = tune.fit(lambda th: tune.color_loss(th, model, data), theta0, steps=30,
                             learning_rate=0.1)  # fmt: skip
    assert losses.min() < 0.8 * losses[0]

    def errors(th):
        m, T = tune.color_model(th, model)
        wrong = 0
        for px, lab, W in zip(data.pixels, data.labels, data.W, strict=True):
            ids, _ = classify(m, W, px[:, None, :], threshold=T)
            wrong += int(jnp.sum(ids[:, 0] != lab))
        return wrong

    m1, _ = tune.color_model(theta, model)
    assert np.all(np.linalg.det(np.asarray(m1.cov)) > np.linalg.det(np.asarray(model.cov)))
    assert errors(theta) < errors(theta0)


def test_color_data_samples_labelled_pixels(rng):
    images = rng.integers(0, 256, (2, 20, 30, 3)).astype(np.uint8)
    ids = np.zeros((2, 20, 30), np.int32)
    ids[:, 5:10, 5:15] = 2
    data = tune.color_data(images, ids, np.stack([np.eye(3)] * 2), n_pixels=40, dtype=jnp.float64)
    assert data.pixels.shape == (2, 40, 3) and data.labels.shape == (2, 40)
    assert np.all(np.asarray(data.labels[:, :20]) == 2)  # half drawn from the foreground
    for i in range(2):  # every sampled pixel carries its own label
        for px, lab in zip(np.asarray(data.pixels[i]), np.asarray(data.labels[i]), strict=True):
            rows, cols = np.nonzero(np.all(images[i] == px, axis=-1))
            assert lab in ids[i, rows, cols]
    with pytest.raises(tune.TuneError, match="colour_ids"):
        tune.color_data(images, ids[0], np.eye(3), 10)


# ----------------------------------------------------------------------------- stereo filter

PF_JOINTS = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand")


@pytest.fixture(scope="module")
def stereo():
    """The stereo tracker's drawn scene (4 frames, tests/test_trackers_stereo_pf.py) with 32
    particles, float64: parameters at widths other than the defaults, the loss's sequence."""
    from test_trackers_stereo_pf import drawn_scene

    from jaxmocap.body import keypoint_index
    from jaxmocap.trackers import stereo_pf as sp
    from jaxmocap.trackers.stereo_pf.start import start_frame

    model, cams, _, _, kp, _, obs = drawn_scene(4, 0.05)
    make = lambda g, d: sp.make_params(cams, dtype=jnp.float64, motion=sp.Motion(n_particles=32),
                                       cues=sp.Cues(sigma_g=g, sigma_d=d))
    params = make(0.2, 0.04)
    t0, _, start = start_frame(params, obs)
    joints = np.asarray(keypoint_index(model, PF_JOINTS))
    seq = tune.PFSequence(obs=obs, first=jax.tree.map(lambda a: a[t0], obs), start=start,
                          key=jax.random.key(0), gt=jnp.asarray(kp[:, joints]),
                          joints=jnp.asarray(joints), scored=jnp.ones(4, bool))
    return model, make, params, seq, kp[:, joints]


pf_loss_jit = eqx.filter_jit(tune.pf_loss)  # shared by the tests below: one compile per shape


def test_pf_loss_is_the_real_filter_run_with_the_widths(stereo):
    """The loss at widths (0.3, 6 cm) equals the mean per-joint error of the tracker's own
    programs (``init_top_level`` + ``run_top_level``, the same key) run with parameters that
    ``make_params`` built with those widths -- the loss's width substitution and its frame loop
    are the tracker's."""
    from jaxmocap.body import keypoints
    from jaxmocap.trackers import stereo_pf as sp

    model, make, params, seq, gt = stereo
    real = make(0.3, 0.06)
    state, _ = sp.init_top_level(real, seq.key, seq.first, seq.start)
    _, est = sp.run_top_level(real, state, seq.obs)
    kp = np.asarray(jax.vmap(lambda q: keypoints(model, q))(est.q))[:, np.asarray(seq.joints)]
    want = np.linalg.norm(kp - gt, axis=-1).mean()
    got = float(pf_loss_jit(tune.pf_theta(0.3, 0.06), params, seq))
    assert got == pytest.approx(want, rel=1e-9)


def test_stereo_filter_forward_is_bit_identical_with_stop_gradient_resampling(stereo):
    """The tracker's offline run with the filter's stop-gradient resampling (the default) and
    without it: the same estimates and final state, bit for bit."""
    import dataclasses

    from jaxmocap.trackers import stereo_pf as sp

    _, _, params, seq, _ = stereo
    none = dataclasses.replace(
        params, filter=dataclasses.replace(params.filter, resampling_gradient="none"))
    runs = []
    for p in (params, none):
        state, first = sp.init_top_level(p, seq.key, seq.first, seq.start)
        runs.append(jax.tree.leaves((first, sp.run_top_level(p, state, seq.obs))))
    assert params.filter.resampling_gradient == "stop"
    raw = lambda a: np.asarray(jax.random.key_data(a) if jnp.issubdtype(
        a.dtype, jax.dtypes.prng_key) else a)
    for a, b in zip(*runs, strict=True):
        np.testing.assert_array_equal(raw(a), raw(b))


def test_pf_loss_gradient_crosses_the_recursion(stereo):
    """The gradient is finite and non-zero for both widths; cutting the recursion at every
    frame (window 1) changes it (the weights' ancestry and the adaptive noise count), and the
    value does not depend on the window (only the gradient's truncation does)."""
    _, _, params, seq, _ = stereo
    theta = tune.pf_theta(0.2, 0.04)
    vg = eqx.filter_jit(jax.value_and_grad(tune.pf_loss))
    v4, g4 = vg(theta, params, seq, jnp.asarray(4))  # traced: one compiled program
    v1, g1 = vg(theta, params, seq, jnp.asarray(1))
    assert float(v4) == float(v1)
    for name in ("sigma_g", "sigma_d"):
        a, b = float(getattr(g4, name)), float(getattr(g1, name))
        assert np.isfinite(a) and abs(a) > 1e-8, name
        assert np.isfinite(b)
    assert float(g4.sigma_g) != float(g1.sigma_g)
    with pytest.raises(tune.TuneError, match="window"):
        tune.pf_frame_errors(theta, params, seq, 0)


def test_pf_loss_over_a_batch_of_keys_is_the_mean_of_their_runs(stereo):
    _, _, params, seq, _ = stereo
    theta = tune.pf_theta(0.25, 0.05)
    keys = jax.random.split(jax.random.key(7), 2)
    f = pf_loss_jit  # the single key's program is the one compiled above
    each = [float(f(theta, params, eqx.tree_at(lambda q: q.key, seq, k))) for k in keys]
    both = float(f(theta, params, eqx.tree_at(lambda q: q.key, seq, keys)))
    assert each[0] != each[1]
    assert both == pytest.approx(np.mean(each), rel=1e-9)


# ----------------------------------------------------------------------------- many clips


def test_per_clip_gradients_on_dask_workers_sum_to_the_in_process_loss(arm, ik_problem):
    """The IK loss over two clips: per-clip (total, count, gradient) on two Dask worker
    processes, summed, equals the in-process clip-by-clip sum and the vmapped loss over all
    windows stacked."""
    from distributed import Client

    from jaxmocap.experiment.cluster import local_cluster
    from jaxmocap.experiment.tune_dask import clip_value_and_grad, dask_value_and_grad

    _, theta, vg_all = ik_problem
    setup = arm[3]
    clips = [make_observations(arm, np.random.default_rng(s), n_windows=1, missing=0.3)
             for s in (2, 3)]  # stacked: the shapes of ik_problem's (compiled) observations
    stacked = jax.tree.map(lambda *a: jnp.concatenate(a), *clips)
    value, grad = vg_all(theta, setup, stacked)
    local_value, local_grad = clip_value_and_grad(setup, clips)(theta)
    # sums in another order, and the vmapped solves round differently from the per-clip ones,
    # so a window's LM may stop an iteration apart within its rtol 1e-11: measured 7.6e-10
    # (value) and 4.0e-9 (gradient) relative on an AMD EPYC host, below 1e-10 / 1e-9 on
    # others; a lost or doubled clip would differ by O(1)
    np.testing.assert_allclose(local_value, value, rtol=1e-8)
    for a, b in zip(jax.tree.leaves(local_grad), jax.tree.leaves(grad), strict=True):
        np.testing.assert_allclose(a, b, rtol=2e-8, atol=2e-8 * np.abs(b).max())
    import os

    with local_cluster(2, env={"XLA_FLAGS": os.environ.get("XLA_FLAGS", "")}) as cluster, \
            Client(cluster) as client:
        d_value, d_grad = dask_value_and_grad(client, setup, clips)(theta)
    np.testing.assert_allclose(d_value, local_value, rtol=1e-12)
    for a, b in zip(jax.tree.leaves(d_grad), jax.tree.leaves(local_grad), strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-12, atol=1e-15)


# ----------------------------------------------------------------------------- issue 40


def test_ik_loss_gradient_matches_central_differences_on_three_frames(arm, rng):
    """One 3-frame window (x64, tight solves): every covariance's gradient against central
    differences along a random direction within 1e-4 relative. Step 1e-3: the loss is smooth
    only down to the LM stop (~1e-12 of its value), so smaller steps are noisier (measured,
    centroid / blend / prior: 3.4e-5 / 1.4e-6 / 9.2e-6 at 1e-3; 2.9e-4 / 8e-8 / 2.6e-5 at 1e-4;
    5e-4 / 8e-4 / 1.4e-4 at 1e-5)."""
    _, _, _, setup = arm
    obs = make_observations(arm, np.random.default_rng(5), n_windows=1, missing=0.2)
    obs = jax.tree.map(lambda a: a[:, :3], obs)  # (1 window, 3 frames)
    assert obs.q_b.shape[:2] == (1, 3)
    theta = tune.ik_theta(IKCovariances.isotropic(2.5, 0.1, 0.15, setup.body.n_dof))
    vg = jax.jit(jax.value_and_grad(tune.ik_loss))
    _, grad = vg(theta, setup, obs)
    f = lambda th: vg(th, setup, obs)[0]
    for name in ("centroid", "blend", "prior"):
        g = getattr(grad, name)
        d = rng.normal(size=g.shape)
        fd = float(directional_fd(f, theta, name, d, 1e-3))
        an = float(jnp.vdot(g, d))
        assert abs(fd) > 1e-5, name  # the direction moves the loss
        assert abs(an - fd) <= 1e-4 * abs(fd), (name, an, fd)


def _gaussian_problem(rng, n=3, m=400):
    """Negative log-likelihood of Gaussian samples in the scaled log-Cholesky parameters:
    its minimiser is the samples' second moment S (closed form)."""
    A = rng.normal(size=(n, n))
    x = rng.normal(size=(m, n)) @ (A + 2 * np.eye(n)).T
    S = jnp.asarray(x.T @ x / m)

    def nll(theta):
        cov = tune.spd_from_log_cholesky(theta)
        L = jnp.linalg.cholesky(cov)
        return jnp.sum(jnp.log(jnp.diagonal(L))) + 0.5 * jnp.trace(jnp.linalg.solve(cov, S))

    theta0 = tune.log_cholesky_from_spd(jnp.eye(n))
    return nll, theta0, S


@pytest.mark.parametrize("optimiser, steps, lr, tol", [("adam", 300, 0.05, 0.02),
                                                       ("lbfgs", 40, None, 1e-6)])
def test_optax_optimisers_reach_the_closed_form_minimiser(rng, optimiser, steps, lr, tol):
    nll, theta0, S = _gaussian_problem(rng)
    best, losses = tune.fit(nll, theta0, steps, lr, optimiser=optimiser)
    assert losses.shape == (steps + 1,) and losses.min() < losses[0]
    assert float(nll(best)) == pytest.approx(losses.min())
    cov = np.asarray(tune.spd_from_log_cholesky(best))
    np.testing.assert_allclose(cov, S, rtol=tol, atol=tol * np.abs(S).max())
    floor = float(nll(tune.log_cholesky_from_spd(S)))
    assert losses.min() >= floor - 1e-9  # S is the minimiser: nothing goes below it


@pytest.mark.parametrize("optimiser", ["adam", "lbfgs"])
def test_fit_resumes_from_a_checkpoint_as_if_uninterrupted(rng, tmp_path, optimiser):
    """A run killed after its step-4 checkpoint, resumed from the file, ends where an
    uninterrupted run of the same total steps ends (iterates, best and losses)."""
    nll, theta0, _ = _gaussian_problem(rng)
    steps = 9
    best_a, losses_a = tune.fit(nll, theta0, steps, 0.1, optimiser=optimiser)
    ckpt = tmp_path / "ckpt.npz"

    class Killed(Exception):
        pass

    def checkpoint(state):
        tune.save_fit_state(ckpt, state, {"run": "x"})
        if state.step == 4:
            raise Killed

    with pytest.raises(Killed):
        tune.fit(nll, theta0, steps, 0.1, optimiser=optimiser, checkpoint=checkpoint)
    opt = tune.make_optimiser(optimiser, None if optimiser == "lbfgs" else 0.1)
    start, meta = tune.load_fit_state(ckpt, theta0, opt)
    assert start.step == 4 and len(start.losses) == 4 and meta == {"run": "x"}
    best_b, losses_b = tune.fit(nll, theta0, steps, 0.1, optimiser=optimiser, start=start)
    np.testing.assert_array_equal(losses_b, losses_a)
    np.testing.assert_array_equal(best_b, best_a)
    with pytest.raises(tune.TuneError, match="needs the scalar loss"):
        tune.fit(jax.value_and_grad(nll), theta0, 1, optimiser="lbfgs", value_and_grad=True)
    with pytest.raises(tune.TuneError, match="not one of adam, lbfgs"):
        tune.make_optimiser("sgd", 0.1)
