"""Tests of jaxmocap.ik: global 6-DOF solve, full IK with priors, limits, masks, implicit
gradients, covariance training.

Oracles: synthetic scenes whose patch centroids are made *independently* of our JAX code —
pytorch-kinematics forward kinematics (float64) of the bundled URDF, SciPy rotations for the
root, ``cv2.projectPoints`` for the cameras; joint positions of solutions are measured with the
same oracle. The closed-form minimiser of the priors-only energy; NumPy second moments for the
covariances; central finite differences for gradients through the solve.

Compile budget: every solve below shares one compiled program per function (same shapes,
dtypes and covariance structure; tolerances are traced), see the ``_cache_size`` test.
"""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx
import pytest
import pytorch_kinematics as pk
import torch
from scipy.spatial.transform import Rotation

from jaxmocap import body, ik
from jaxmocap.body.urdf import prepare_urdf, read_urdf_text
from jaxmocap.camera import look_at, stack_cameras
from jaxmocap.garment import default_garment

N_CAMS, N_PATCHES = 2, 20
# Keypoints whose position the shirt determines. No patch sees the head and hands (their DOFs
# are unobservable), nor the pelvis: chest pose = root o spine, so root rotation and spine
# trade off freely (a 3-DOF valley only the priors close).
SHIRT_KEYPOINTS = (
    "chest", "neck", "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist",
    "r_wrist",
)  # fmt: skip


# ----------------------------------------------------------------------------- oracle scene


class Oracle:
    """Independent FK (pytorch-kinematics + SciPy root) and projection (OpenCV)."""

    def __init__(self, model, anchors, cams):
        text = prepare_urdf(read_urdf_text(body.model.DEFAULT_URDF))[1]
        self.pk = pk.build_chain_from_urdf(text).to(dtype=torch.float64)
        assert list(self.pk.get_joint_parameter_names()) == list(model.chain.dof_names[6:])
        self.model, self.cams = model, cams
        self.link = np.asarray(anchors.link)
        self.offset = np.asarray(anchors.offset, np.float64)

    def transforms(self, q):
        q = np.array(q, np.float64)
        ref = self.pk.forward_kinematics(torch.tensor(q[None, 6:]))
        T_root = np.eye(4)
        T_root[:3, :3] = Rotation.from_rotvec(q[3:6]).as_matrix()
        T_root[:3, 3] = q[:3]
        return {k: T_root @ v.get_matrix().numpy()[0] for k, v in ref.items()}

    def points(self, q, links, offsets):
        T = self.transforms(q)
        names = self.model.chain.link_names
        return np.stack(
            [
                T[names[li]][:3, :3] @ o + T[names[li]][:3, 3]
                for li, o in zip(links, offsets, strict=True)
            ]
        )

    def anchors(self, q):
        return self.points(q, self.link, self.offset)

    def keypoints(self, q, names=SHIRT_KEYPOINTS):
        idx = body.keypoint_index(self.model, names)
        return self.points(q, np.asarray(self.model.keypoint_link)[idx],
                           np.asarray(self.model.keypoint_offset, np.float64)[idx])  # fmt: skip

    def centroids(self, q):
        X = self.anchors(q)
        out = []
        for i in range(self.cams.K.shape[0]):
            rvec = cv2.Rodrigues(np.asarray(self.cams.R[i], np.float64))[0]
            uv, _ = cv2.projectPoints(X, rvec, np.asarray(self.cams.t[i], np.float64),
                                      np.asarray(self.cams.K[i], np.float64),
                                      np.asarray(self.cams.dist[i], np.float64))  # fmt: skip
            out.append(uv[:, 0])
        return np.stack(out)


def make_scene():
    model = body.default_body()
    anchors = ik.anchors_from_garment(model, default_garment(model), dtype=jnp.float64)
    cams = stack_cameras([
        look_at([3.0, 1.4, 1.5], [0.0, 0.0, 1.3], width=640, height=480, fx=520.0,
                dist=jnp.array([-0.05, 0.01, 0.0005, -0.0003, 0.0])),
        look_at([2.6, -1.8, 1.1], [0.0, 0.0, 1.3], width=640, height=480, fx=480.0),
    ])  # fmt: skip
    oracle = Oracle(model, anchors, cams)
    return model, model.chain, anchors, cams, oracle


@pytest.fixture(scope="module")
def scene():
    return make_scene()


def random_pose(chain, rng, scale=0.6):
    lo, hi = np.asarray(chain.lower)[6:], np.asarray(chain.upper)[6:]
    mid, half = (lo + hi) / 2, (hi - lo) / 2
    joints = mid + scale * half * rng.uniform(-1, 1, lo.shape)
    root = np.r_[rng.normal(0, 0.2, 2), 1.0, rng.normal(0, 0.25, 3)]
    return np.r_[root, joints]


def perturb(chain, q, rng, joint=0.15, trans=0.03, rot=0.05):
    dq = np.r_[rng.normal(0, trans, 3), rng.normal(0, rot, 3), rng.normal(0, joint, q.size - 6)]
    lo, hi = np.asarray(chain.lower)[6:], np.asarray(chain.upper)[6:]
    out = q + dq
    out[6:] = np.clip(out[6:], lo + 1e-3 * (hi - lo), hi - 1e-3 * (hi - lo))
    return out


def diag_cov(centroid_var, blend_var, prior_var, n_dof=24):
    return ik.IKCovariances(
        centroid=jnp.diag(jnp.broadcast_to(jnp.asarray(centroid_var, jnp.float64), (2,))),
        blend=jnp.broadcast_to(jnp.asarray(blend_var, jnp.float64), (n_dof,)),
        prior=jnp.broadcast_to(jnp.asarray(prior_var, jnp.float64), (n_dof,)),
    )


def solve(scene, c, vis, q_b, q_h, cov, **kw):
    _, chain, anchors, cams, _ = scene
    return ik.solve_ik(chain, cams, anchors, jnp.asarray(c), jnp.asarray(vis),
                       jnp.asarray(q_b), jnp.asarray(q_h), cov, **kw)  # fmt: skip


ALL_VISIBLE = np.ones((N_CAMS, N_PATCHES), bool)


# ----------------------------------------------------------------------------- anchors


def test_anchors_from_garment_lie_on_their_patches(scene):
    model, chain, anchors, _, _ = scene
    garment = default_garment(model)
    assert anchors.n_patches == garment.n_patches == N_PATCHES
    g = np.asarray(garment.patch_geom)
    np.testing.assert_array_equal(anchors.link, np.asarray(model.geometry.link)[g])
    # Back to the geom frame: arm patches are the top / bottom halves of a capsule along z, so
    # their centroid lies on the axis (x = y = 0 up to the sampling) on the right side.
    pose = np.asarray(model.geometry.pose, np.float64)[g]
    off = np.asarray(anchors.offset)
    p_geom = np.einsum("pji,pj->pi", pose[:, :3, :3], off - pose[:, :3, 3])
    for k, name in enumerate(garment.patch_names):
        if name.endswith(("_top", "_bottom")):
            r, h = np.asarray(model.geometry.size)[g[k], :2]
            assert np.all(np.abs(p_geom[k, :2]) < 0.2 * r), name
            z = p_geom[k, 2] * (1.0 if name.endswith("_top") else -1.0)
            assert 0.2 * h < z < h + r, name
        if "left" in name:
            assert p_geom[k, 1] > 0 or name.startswith("shoulder"), name


def test_anchors_from_samples_weighted_mean(rng):
    pts = rng.normal(size=(3, 7, 3))
    w = rng.uniform(0, 1, (3, 7))
    w[1, :4] = 0.0
    link = np.array([0, 2, 5])
    a = ik.anchors_from_samples(link, pts, w)
    ref = (w[..., None] * pts).sum(1) / w.sum(1)[:, None]
    np.testing.assert_allclose(a.offset, ref, rtol=1e-12)
    np.testing.assert_array_equal(a.link, [0, 2, 5])
    w[2] = 0.0
    with pytest.raises(ValueError, match="patches \\[2\\]"):
        ik.anchors_from_samples(link, pts, w)


# ----------------------------------------------------------------------------- global solve


def test_global_solve_recovers_root(scene, rng):
    _, chain, anchors, cams, oracle = scene
    q_gt = random_pose(chain, rng)
    c = jnp.asarray(oracle.centroids(q_gt))
    q_b = jnp.asarray(q_gt).at[:6].set(0.0)  # the database knows the joints, not the root
    vis = jnp.asarray(ALL_VISIBLE)

    # Closed-form initialiser: Kabsch on triangulated anchors (exact data -> exact root).
    root0, used = ik.initial_root(cams, chain, anchors, c, vis, q_b, jnp.zeros(6))
    assert bool(used)
    np.testing.assert_allclose(root0, q_gt[:6], atol=1e-6)
    # One camera only: no triangulation, the previous root is kept.
    prev = jnp.asarray(q_gt[:6] + 0.3)
    root1, used1 = ik.initial_root(cams, chain, anchors, c, vis.at[1].set(False), q_b, prev)
    assert not bool(used1)
    np.testing.assert_array_equal(root1, prev)

    # LM from a root 8 cm / ~9 degrees away, a few patches hidden.
    init = q_gt[:6] + np.r_[0.05, -0.04, 0.05, 0.1, -0.08, 0.1]
    vis_some = vis.at[0, :3].set(False).at[1, 10:12].set(False)
    sol = ik.solve_global(chain, cams, anchors, c, vis_some, q_b, jnp.asarray(init))
    assert bool(sol.converged)
    np.testing.assert_array_equal(sol.q[6:], q_b[6:])
    assert np.linalg.norm(sol.q[:3] - q_gt[:3]) < 1e-3  # < 1 mm
    dR = Rotation.from_rotvec(np.array(sol.q[3:6])) * Rotation.from_rotvec(q_gt[3:6]).inv()
    assert np.degrees(dR.magnitude()) < 0.1
    np.testing.assert_allclose(
        oracle.keypoints(np.asarray(sol.q)), oracle.keypoints(q_gt), atol=1e-6
    )


# ----------------------------------------------------------------------------- full solve


@pytest.fixture(scope="module")
def frame(scene):
    return make_frame(scene)


def make_frame(scene):
    """One synthetic frame: truth, noise-free centroids, a perturbed blend pose."""
    _, chain, _, _, oracle = scene
    rng = np.random.default_rng(1)
    q_gt = random_pose(chain, rng)
    q_gt[body.dof_index(scene[0], ["l_elbow", "r_elbow"])] = [1.2, 0.9]  # bent: twists observable
    return q_gt, oracle.centroids(q_gt), perturb(chain, q_gt, rng)


def kp_error(oracle, q, q_gt):
    return np.max(np.linalg.norm(oracle.keypoints(np.asarray(q)) - oracle.keypoints(q_gt), axis=1))


def test_full_solve_recovers_pose(scene, frame):
    oracle = scene[4]
    q_gt, c, q_b = frame
    assert kp_error(oracle, q_b, q_gt) > 0.05  # the start is far off
    sol = solve(scene, c, ALL_VISIBLE, q_b, q_b, diag_cov(1.0, 1.0, 1.0))
    assert bool(sol.converged) and int(sol.num_steps) < ik.DEFAULT_MAX_STEPS
    assert kp_error(oracle, sol.q, q_gt) < 0.01  # joint positions within 1 cm
    assert np.abs(oracle.centroids(np.asarray(sol.q)) - c).max() < 0.01  # pixels


def test_missing_patches_are_masked(scene, frame, rng):
    oracle = scene[4]
    q_gt, c, q_b = frame
    vis = ALL_VISIBLE.copy()
    hidden = rng.choice(N_CAMS * N_PATCHES, 8, replace=False)
    vis.reshape(-1)[hidden] = False
    vis[1, 12] = vis[0, 13] = False  # the left upper arm seen in one view only per patch
    c = c.copy()
    c[~vis] = np.nan  # what a detector reports for a missing patch
    sol = solve(scene, c, vis, q_b, q_b, diag_cov(1.0, 1.0, 1.0))
    assert np.all(np.isfinite(sol.q)) and np.isfinite(float(sol.cost))
    assert bool(sol.converged)
    assert kp_error(oracle, sol.q, q_gt) < 0.01


def test_joint_limits_hold_when_target_is_outside(scene, frame):
    model, chain, _, _, oracle = scene
    q_gt, _, q_b = frame
    target = q_gt.copy()
    e = body.dof_index(model, ["l_elbow", "r_shoulder_x"])
    target[e] = [-0.4, np.asarray(chain.lower)[e[1]] - 0.3]  # hyperextended elbow, beyond lower
    sol = solve(scene, oracle.centroids(target), ALL_VISIBLE, q_b, q_b, diag_cov(1.0, 1.0, 1.0))
    q = np.asarray(sol.q)
    lo, hi = np.asarray(chain.lower), np.asarray(chain.upper)
    assert np.all(np.isfinite(q)) and np.all(q >= lo) and np.all(q <= hi)
    np.testing.assert_allclose(q[e], lo[e], atol=0.02)  # pressed against the limits


def test_priors_only_closed_form_and_limits_of_covariances(scene, frame, rng):
    chain = scene[1]
    q_gt, c, q_b = frame
    q_h = perturb(chain, q_gt, rng)
    # No patch visible: E = |q - q_b|^2_Sb + |q - q_h|^2_Sp, minimised in closed form by the
    # precision-weighted mean (inside the limits, since both poses are).
    vb = rng.uniform(0.01, 0.1, q_b.size)
    vp = rng.uniform(0.01, 0.1, q_b.size)
    sol = solve(scene, c, ~ALL_VISIBLE, q_b, q_h, diag_cov(1.0, vb, vp), rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(sol.q, (q_b / vb + q_h / vp) / (1 / vb + 1 / vp), atol=1e-8)

    # With the centroids: shrinking Sigma_b pulls q* to q_b, shrinking Sigma_p pulls it to q_h.
    for target, make in (
        (q_b, lambda s: diag_cov(1.0, s, 1.0)),
        (q_h, lambda s: diag_cov(1.0, 1.0, s)),
    ):
        dist = [np.abs(np.asarray(solve(scene, c, ALL_VISIBLE, q_b, q_h, make(s)).q) - target).max()
                for s in (1e-2, 1e-5, 1e-10)]  # fmt: skip
        assert dist[0] > dist[1] > dist[2] and dist[2] < 1e-4, dist


def test_nonconvergence_is_reported_not_raised(scene, frame):
    q_gt, c, q_b = frame
    sol = solve(scene, c, ALL_VISIBLE, q_b, q_b, diag_cov(1.0, 1.0, 1.0), rtol=0.0, atol=0.0,
                ftol=0.0)
    assert sol.result == optx.RESULTS.nonlinear_max_steps_reached and not bool(sol.converged)
    assert int(sol.num_steps) == ik.DEFAULT_MAX_STEPS and np.all(np.isfinite(sol.q))


def test_ftol_stops_float32_solve_at_the_floor_of_plain_lm(scene, frame, rng):
    """In float32 with noisy centroids (a non-zero residual at the optimum, as in tracking) and
    the robust loss, optimistix's own test is not met at the optimum; MINPACK's ftol stops
    there: far fewer steps than the plain LM (ftol = 0), same cost to float rounding, same pose
    to well under a milliradian."""
    _, chain, _, cams, _ = scene
    model = scene[0]
    anchors = ik.anchors_from_garment(model, default_garment(model), dtype=jnp.float32)
    q_gt, c, q_b = frame
    f32 = lambda x: jnp.asarray(x, jnp.float32)  # noqa: E731
    cov = jax.tree.map(f32, diag_cov(4.0, 0.1, 0.1))
    to32 = lambda t: jax.tree.map(  # noqa: E731
        lambda a: f32(a) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a, t)
    cams32, chain = to32(cams), to32(chain)
    noisy = f32(c + rng.normal(0, 2.0, c.shape))
    q0 = f32(perturb(chain, q_gt, rng))
    run = lambda **kw: ik.solve_ik(chain, cams32, anchors, noisy, jnp.asarray(ALL_VISIBLE),  # noqa: E731
                                   f32(q_b), f32(q_b), cov, q0, robust=3.0, **kw)
    with jax.enable_x64(False):  # the tracker's float32 world (the suite enables x64)
        plain, ftol = run(ftol=0.0), run()
    assert bool(ftol.converged) and int(ftol.num_steps) < 0.6 * int(plain.num_steps), (
        int(ftol.num_steps), int(plain.num_steps))
    assert abs(float(ftol.cost) - float(plain.cost)) <= 1e-5 * float(plain.cost)
    assert float(jnp.max(jnp.abs(ftol.q - plain.q))) < 1e-3


def test_jit_tolerances_traced_no_recompile(scene, frame, rng):
    q_gt, c, q_b = frame
    cov = diag_cov(1.0, 1.0, 1.0)
    solve(scene, c, ALL_VISIBLE, q_b, q_b, cov)  # default tolerances
    traces = []

    def count(event, duration, **kw):
        if event == "/jax/core/compile/jaxpr_trace_duration":
            traces.append(event)

    jax.monitoring.register_event_duration_secs_listener(count)
    try:
        for rtol, atol in ((1e-5, 1e-7), (1e-9, 1e-12), (0.5, jnp.float64(1e-3))):
            noisy = c + rng.normal(0, 0.5, c.shape)
            q = perturb(scene[1], q_gt, rng)
            solve(scene, noisy, ALL_VISIBLE, q, q_b, cov, rtol=rtol, atol=atol)
    finally:
        jax.monitoring.unregister_event_duration_listener(count)
    assert traces == []


def test_vmap_over_frames_matches_single_calls(scene, frame, rng):
    _, chain, anchors, cams, _ = scene
    q_gt, c, q_b = frame
    cov = diag_cov(1.0, 1.0, 1.0)
    cs = np.stack([c, c + rng.normal(0, 1.0, c.shape), c])
    vis = np.stack([ALL_VISIBLE, ALL_VISIBLE, ALL_VISIBLE])
    vis[2, 0, :5] = False
    qbs = np.stack([q_b, perturb(chain, q_gt, rng), q_gt])
    batched = jax.vmap(ik.solve_ik, in_axes=(None, None, None, 0, 0, 0, 0, None))(
        chain, cams, anchors, jnp.asarray(cs), jnp.asarray(vis), jnp.asarray(qbs),
        jnp.asarray(qbs), cov,
    )  # fmt: skip
    for i in range(3):
        one = solve(scene, cs[i], vis[i], qbs[i], qbs[i], cov)
        np.testing.assert_allclose(batched.q[i], one.q, atol=1e-8)
        assert bool(batched.converged[i])


# ----------------------------------------------------------------------------- implicit gradients


def test_grad_wrt_log_covariances_matches_finite_differences(scene, frame, rng):
    _, chain, anchors, cams, oracle = scene
    q_gt, c, q_b = frame
    c_noisy = jnp.asarray(c + rng.normal(0, 1.5, c.shape))
    q_h = jnp.asarray(perturb(chain, q_gt, rng))
    q_b = jnp.asarray(q_b)
    vis = jnp.asarray(ALL_VISIBLE)
    n = q_b.size

    def loss(theta):
        cov = ik.IKCovariances(
            centroid=jnp.diag(jnp.exp(theta[:2])),
            blend=jnp.exp(theta[2 : 2 + n]),
            prior=jnp.exp(theta[2 + n :]),
        )
        # converged to the Cauchy test alone (ftol=0): ftol's stop at 8 eps of the loss leaves q
        # ~sqrt(eps) off, which the loss differences below would resolve
        sol = ik.solve_ik(chain, cams, anchors, c_noisy, vis, q_b, q_h, cov, rtol=1e-13, atol=1e-15,
                          ftol=0.0)
        return jnp.sum((sol.q - q_gt) ** 2)

    theta = jnp.log(jnp.concatenate([jnp.array([1.5, 2.5]), rng.uniform(0.01, 0.05, 2 * n)]))
    g = jax.jit(jax.grad(loss))(theta)
    assert np.all(np.isfinite(g)) and np.abs(g).max() > 1e-6
    # central differences: with h = 1e-2 the O(h^2) error stays < 1e-4 relative (the loss is
    # smooth in the log-variances) while the loss differences (down to ~1e-6) stand far above
    # the solver's convergence noise (~1e-10 of the loss); h = 1e-3 met that noise on the
    # small-derivative directions (0.4% off with optimistix 0.1)
    h = 1e-2
    dirs = [np.eye(theta.size)[k] for k in (0, 1, 2 + 15, 2 + n + 15)] + list(
        rng.normal(size=(2, theta.size))
    )
    loss_jit = jax.jit(loss)  # one compiled solve on both sides (eager calls differ ~1e-7)
    for d in dirs:
        fd = (loss_jit(theta + h * d) - loss_jit(theta - h * d)) / (2 * h)
        an = float(g @ d)
        assert abs(an - fd) <= 1e-3 * abs(fd) + 1e-10, (an, fd)


# ----------------------------------------------------------------------------- covariances


def test_estimate_covariances_and_file_round_trip(scene, rng, tmp_path):
    _, chain, anchors, cams, oracle = scene
    T = 6
    q_gt = np.stack([random_pose(chain, rng) for _ in range(T)])
    q_b = q_gt + rng.normal(0, [0.02] * 6 + [0.1] * 18, q_gt.shape)
    exact = np.stack([oracle.centroids(q) for q in q_gt])
    noise = rng.normal(0, [2.0, 1.0], exact.shape)
    vis = rng.uniform(size=exact.shape[:3]) > 0.2
    obs = np.where(vis[..., None], exact - noise, np.nan)
    cov = ik.estimate_covariances(cams, chain, anchors, jnp.asarray(q_gt), jnp.asarray(obs),
                                  jnp.asarray(vis), jnp.asarray(q_b))  # fmt: skip

    e = noise[vis]  # c*(q_gt) - c = noise
    ref_c = e.T @ e / len(e)
    ridge = lambda S, floor: S + (ik.COV_REL_RIDGE * np.trace(S) / len(S) + floor) * np.eye(len(S))
    # (oracle and JAX projections agree to ~1e-7 px, hence rtol 1e-5 on the pixel moments)
    np.testing.assert_allclose(cov.centroid, ridge(ref_c, ik.COV_FLOOR_PX2), rtol=1e-5)
    db, dp = q_gt - q_b, np.diff(q_gt, axis=0)
    np.testing.assert_allclose(cov.blend, ridge(db.T @ db / T, ik.COV_FLOOR_Q), rtol=1e-8)
    np.testing.assert_allclose(cov.prior, ridge(dp.T @ dp / (T - 1), ik.COV_FLOOR_Q), rtol=1e-8)
    assert np.all(np.linalg.eigvalsh(np.asarray(cov.blend)) > 0)  # 6 frames, 24 DOFs: ridge
    assert abs(cov.centroid[0, 0] / 4.0 - 1) < 0.3 and abs(cov.centroid[1, 1] - 1) < 0.3
    # the model's centroids at the truth given directly (e.g. rendered): same moments
    cov2 = ik.estimate_covariances(cams, chain, anchors, jnp.asarray(q_gt), jnp.asarray(obs),
                                   jnp.asarray(vis), jnp.asarray(q_b),
                                   predicted=jnp.asarray(exact))  # fmt: skip
    np.testing.assert_allclose(cov2.centroid, ridge(ref_c, ik.COV_FLOOR_PX2), rtol=1e-9)
    cov3 = ik.estimate_covariances(cams, chain, anchors, jnp.asarray(q_gt), jnp.asarray(obs),
                                   jnp.asarray(vis), jnp.asarray(q_b), diagonal=True)  # fmt: skip
    np.testing.assert_allclose(cov3.blend, np.diag(np.asarray(cov.blend)), rtol=1e-12)
    np.testing.assert_allclose(cov3.prior, np.diag(np.asarray(cov.prior)), rtol=1e-12)
    # the temporal term against the tracker's previous output; a floor on Sigma_c
    q_prev = q_gt + rng.normal(0, 0.05, q_gt.shape)
    cov4 = ik.estimate_covariances(cams, chain, anchors, jnp.asarray(q_gt), jnp.asarray(obs),
                                   jnp.asarray(vis), jnp.asarray(q_b), q_h=jnp.asarray(q_prev),
                                   min_centroid_std=3.0)  # fmt: skip
    dh = q_gt[1:] - q_prev[1:]
    np.testing.assert_allclose(cov4.prior, ridge(dh.T @ dh / (T - 1), ik.COV_FLOOR_Q), rtol=1e-8)
    np.testing.assert_allclose(np.diag(cov4.centroid), [9.0, 9.0], rtol=1e-12)
    # no floor asked: the covariance is untouched, a negative correlation included
    corr = obs.copy()
    corr[..., 1] = np.where(vis, exact[..., 1] + noise[..., 0], np.nan)  # y error = -x error
    cov5 = ik.estimate_covariances(cams, chain, anchors, jnp.asarray(q_gt), jnp.asarray(corr),
                                   jnp.asarray(vis), jnp.asarray(q_b))  # fmt: skip
    assert float(cov5.centroid[0, 1]) < -1.0
    np.testing.assert_array_equal(cov5.centroid[0, 1], cov5.centroid[1, 0])

    # pooled training: two sequences stacked, the second's first frame has no temporal pair
    # (NumPy oracle: the moments of the within-sequence pairs only)
    start = np.zeros(T, bool)
    start[3] = True
    cov6 = ik.estimate_covariances(cams, chain, anchors, jnp.asarray(q_gt), jnp.asarray(obs),
                                   jnp.asarray(vis), jnp.asarray(q_b), q_h=jnp.asarray(q_prev),
                                   sequence_start=jnp.asarray(start))  # fmt: skip
    pairs = np.delete(dh, 2, axis=0)  # the pair (frame 3 vs previous output) dropped
    np.testing.assert_allclose(
        cov6.prior, ridge(pairs.T @ pairs / (T - 2), ik.COV_FLOOR_Q), rtol=1e-8
    )
    np.testing.assert_allclose(cov6.blend, cov.blend, rtol=1e-12)  # every frame has a blend
    with pytest.raises((ValueError, TypeError), match="sequence_start"):  # beartype first
        ik.estimate_covariances(cams, chain, anchors, jnp.asarray(q_gt), jnp.asarray(obs),
                                jnp.asarray(vis), jnp.asarray(q_b),
                                sequence_start=jnp.zeros(T - 1, bool))  # fmt: skip

    path = tmp_path / "ik_cov.npz"
    cov.save(path)
    back = ik.IKCovariances.load(path)
    for f in ("centroid", "blend", "prior"):
        np.testing.assert_array_equal(getattr(back, f), getattr(cov, f))
    np.savez(tmp_path / "bad.npz", centroid=np.eye(2), blend=-np.ones(24), prior=np.ones(24),
             version=ik.COV_FILE_VERSION)  # fmt: skip
    with pytest.raises(ValueError, match="bad.npz: field 'blend' is not a positive definite"):
        ik.IKCovariances.load(tmp_path / "bad.npz")
    np.savez(tmp_path / "missing.npz", centroid=np.eye(2))
    with pytest.raises(ValueError, match="missing.npz: missing field 'blend'"):
        ik.IKCovariances.load(tmp_path / "missing.npz")


def test_so3_log_matches_scipy_near_zero_and_pi(rng):
    vecs = [rng.normal(size=3), [0.0, 0.0, np.pi - 1e-9], [1e-10, 0.0, 0.0], [0.0, 0.0, 0.0]]
    vecs += [u / np.linalg.norm(u) * 3.1 for u in rng.normal(size=(3, 3))]
    for v in vecs:
        R = Rotation.from_rotvec(v).as_matrix()
        ours = np.asarray(jax.jit(ik.so3_log)(jnp.asarray(R)))
        np.testing.assert_allclose(ours, Rotation.from_matrix(R).as_rotvec(), atol=1e-9)


# ----------------------------------------------------------------------------- per-view anchors


def _render_views(model, cams, q):
    """Patch ids, world hit points and pixel positions of every camera's full image."""
    from jaxmocap.render import pixel_grid, render_uv

    garment = default_garment(model)
    uv = pixel_grid(int(cams.width), int(cams.height), dtype=jnp.float64)
    hits = [render_uv(model, garment, jnp.asarray(q), jax.tree.map(lambda a, i=i: a[i], cams), uv)
            for i in range(cams.K.shape[0])]  # fmt: skip
    return (jnp.stack([h.patch for h in hits]), jnp.stack([h.point for h in hits]),
            jnp.stack([uv] * len(hits)))  # fmt: skip


def test_view_anchors_predict_the_rendered_visible_centroids(scene):
    """Per-view anchors reproduce the centroids of the render they come from (checked with
    the oracle's FK and OpenCV's projection), the whole-patch anchors do not (visible-part
    bias), and IK on rendered centroids converges to the truth with them."""
    from jaxmocap.color.pose_assisted import patch_centroids

    model, chain, anchors, _, oracle = scene
    cams = stack_cameras([
        look_at([3.0, 1.4, 1.5], [0.0, 0.0, 1.3], width=160, height=120, fx=130.0,
                dist=jnp.array([-0.05, 0.01, 0.0005, -0.0003, 0.0])),
        look_at([2.6, -1.8, 1.1], [0.0, 0.0, 1.3], width=160, height=120, fx=120.0),
    ])  # fmt: skip
    rng = np.random.default_rng(4)
    q_gt = random_pose(chain, rng, 0.4)
    q_gt[body.dof_index(model, ["l_elbow", "r_elbow"])] = [1.2, 0.9]
    patch, point, uv = _render_views(model, cams, q_gt)
    obs = [patch_centroids(patch[i], N_PATCHES, None, 4) for i in range(N_CAMS)]
    c_obs = np.stack([np.asarray(o.xy) for o in obs])
    vis = np.stack([np.asarray(o.valid) for o in obs])
    assert vis.sum() >= 20

    A = ik.view_anchors(chain, anchors, cams, jnp.asarray(q_gt), patch, point, uv)
    assert A.per_view and A.offset.shape == (N_CAMS, N_PATCHES, 3)
    pred = np.asarray(ik.project_anchors(cams, chain, A, jnp.asarray(q_gt)))
    np.testing.assert_allclose(pred[vis], c_obs[vis], atol=1e-6)
    # independent: oracle FK (pytorch-kinematics) + cv2.projectPoints of the offsets, + shift
    for i in range(N_CAMS):
        X = oracle.points(q_gt, np.asarray(A.link), np.asarray(A.offset[i], np.float64))
        rvec = cv2.Rodrigues(np.asarray(cams.R[i], np.float64))[0]
        uv_cv, _ = cv2.projectPoints(X, rvec, np.asarray(cams.t[i], np.float64),
                                     np.asarray(cams.K[i], np.float64),
                                     np.asarray(cams.dist[i], np.float64))  # fmt: skip
        np.testing.assert_allclose((uv_cv[:, 0] + np.asarray(A.shift[i]))[vis[i]],
                                   c_obs[i][vis[i]], atol=1e-4)  # fmt: skip
    shared = np.asarray(ik.project_anchors(cams, chain, anchors, jnp.asarray(q_gt)))
    assert np.abs(shared - c_obs)[vis].max() > 0.5  # whole-patch centroid != visible part

    cov = diag_cov(0.25, 1.0, 1.0)
    c, v = jnp.asarray(c_obs), jnp.asarray(vis)
    sol_truth = ik.solve_ik(chain, cams, A, c, v, jnp.asarray(q_gt), jnp.asarray(q_gt), cov)
    assert kp_error(oracle, sol_truth.q, q_gt) < 1e-3  # the truth is a fixed point
    sol_shared = ik.solve_ik(chain, cams, anchors, c, v, jnp.asarray(q_gt), jnp.asarray(q_gt), cov)
    assert kp_error(oracle, sol_shared.q, q_gt) > 5e-3  # ... not with whole-patch anchors
    # From a perturbed pose: anchors from its render, a second pass from the first solution's.
    q_p = jnp.asarray(perturb(chain, q_gt, rng, joint=0.1, trans=0.02, rot=0.03))
    q1 = ik.solve_ik(chain, cams, ik.view_anchors(chain, anchors, cams, q_p,
                                                  *_render_views(model, cams, q_p)),
                     c, v, q_p, q_p, cov).q  # fmt: skip
    q2 = ik.solve_ik(chain, cams, ik.view_anchors(chain, anchors, cams, q1,
                                                  *_render_views(model, cams, q1)),
                     c, v, q_p, q_p, cov, q1).q  # fmt: skip
    assert kp_error(oracle, q2, q_gt) < min(0.02, kp_error(oracle, q_p, q_gt) / 3)


def test_robust_centroid_term(scene, frame, rng):
    """Cauchy rho: |r~|^2 = c^2 log(1 + |r|^2/c^2), identity for c = inf, smooth at 0
    (finite differences); an IK with one grossly wrong centroid keeps the pose with it and
    loses it without."""
    r = jnp.asarray(rng.normal(size=(5, 2)) * 4.0)
    c = jnp.asarray(3.0)
    out = ik.robust_centroid_residual(r, c)
    n2 = np.sum(np.asarray(r) ** 2, -1)
    np.testing.assert_allclose(np.sum(np.asarray(out) ** 2, -1), 9.0 * np.log1p(n2 / 9.0),
                               rtol=1e-12)  # fmt: skip
    np.testing.assert_array_equal(ik.robust_centroid_residual(r, jnp.asarray(jnp.inf)), r)
    f = lambda x: jnp.sum(ik.robust_centroid_residual(x, c) ** 2)
    for x in (np.asarray(r[0]), np.zeros(2)):
        g = np.asarray(jax.grad(f)(jnp.asarray(x)))
        fd = [(f(jnp.asarray(x + e)) - f(jnp.asarray(x - e))) / 2e-6 for e in np.eye(2) * 1e-6]
        np.testing.assert_allclose(g, fd, atol=1e-6)
        assert np.all(np.isfinite(g))

    oracle = scene[4]
    q_gt, cen, q_b = frame
    bad = cen.copy()
    bad[0, 0] += [150.0, -120.0]  # a patch centroid dragged by misclassified clutter
    cov = diag_cov(1.0, 1.0, 1.0)
    plain = solve(scene, bad, ALL_VISIBLE, q_b, q_b, cov)
    robust = solve(scene, bad, ALL_VISIBLE, q_b, q_b, cov, robust=3.0)
    assert kp_error(oracle, robust.q, q_gt) < 0.01
    assert kp_error(oracle, plain.q, q_gt) > 3 * kp_error(oracle, robust.q, q_gt)


def test_robust_covariance_ignores_outliers(scene, rng):
    """Sigma_c with robust=True: Gaussian centroid noise (std 2 / 1 px) plus 10% gross
    errors (50-150 px) -> the inlier covariance (NumPy), the plain one is inflated."""
    _, chain, anchors, cams, oracle = scene
    T = 40
    q_gt = np.stack([random_pose(chain, rng) for _ in range(T)])
    exact = np.stack([oracle.centroids(q) for q in q_gt])
    noise = rng.normal(0, [2.0, 1.0], exact.shape)
    gross = rng.uniform(size=exact.shape[:3]) < 0.1
    noise[gross] = rng.uniform(50, 150, (gross.sum(), 2)) * rng.choice([-1, 1], (gross.sum(), 2))
    vis = np.ones(exact.shape[:3], bool)
    args = (cams, chain, anchors, jnp.asarray(q_gt), jnp.asarray(exact - noise),
            jnp.asarray(vis), jnp.asarray(q_gt))  # fmt: skip
    plain = np.asarray(ik.estimate_covariances(*args).centroid)
    rob = np.asarray(ik.estimate_covariances(*args, robust=True).centroid)
    inl = noise[~gross]
    ref = inl.T @ inl / len(inl)
    assert plain[0, 0] > 100 * ref[0, 0]
    np.testing.assert_allclose(np.diag(rob), np.diag(ref), rtol=0.1)
    assert abs(rob[0, 1]) < 0.2
