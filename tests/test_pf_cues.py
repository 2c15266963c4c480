"""Tests of the stereo particle filter's likelihood cues (Azad et al. 2007 §II–III)."""

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import camera as camlib
from jaxmocap.body import default_body, fk, keypoint_index, stereo_dofs
from jaxmocap.errors import InputError
from jaxmocap.pf import cues

SIGMA = 0.2


def _front_camera(w=100, h=100, f=100.0):
    """Camera at the origin looking along world +z (R = I): x right, y down."""
    K = np.array([[f, 0, (w - 1) / 2], [0, f, (h - 1) / 2], [0, 0, 1.0]])
    return camlib.Camera(K=K, R=np.eye(3), t=np.zeros(3), dist=np.zeros(5), width=w, height=h)


def _one_cylinder():
    """A vertical cylinder 2 m in front of the camera: axis x = 49.5 px, v in [39.5, 59.5],
    radius 0.1 m -> 5 px: silhouette lines on columns x = 44.5 and x = 54.5."""
    a = jnp.array([[0.0, -0.2, 2.0]])
    b = jnp.array([[0.0, 0.2, 2.0]])
    return a, b, jnp.array([0.1])


def test_project_limbs_hand_computed():
    cam = _front_camera()
    starts, ends = cues.project_limbs(cam, *_one_cylinder())
    # d = (0, 1) -> n = (-1, 0): line 0 at x - 5, line 1 at x + 5
    np.testing.assert_allclose(starts[0], [[44.5, 39.5], [54.5, 39.5]], atol=1e-12)
    np.testing.assert_allclose(ends[0], [[44.5, 59.5], [54.5, 59.5]], atol=1e-12)
    # the axis end points agree with OpenCV's projection
    a, b, _ = _one_cylinder()
    ref, _ = cv2.projectPoints(
        np.concatenate([a, b]), np.zeros(3), np.zeros(3), np.asarray(cam.K), np.zeros(5)
    )
    np.testing.assert_allclose((starts[0].mean(0), ends[0].mean(0)), ref[:, 0], atol=1e-9)


def test_edge_cue_known_lines():
    """Exact p_g / p_g' on an edge map holding the cylinder's contour with known values."""
    cam = _front_camera()
    starts, ends = cues.project_limbs(cam, *_one_cylinder())
    pts = cues.edge_samples(starts, ends, 8)
    assert pts.shape == (1, 2, 8, 2)
    g = np.zeros((100, 100))
    # samples sit at x = 44.5 / 54.5: half-way between two columns -> bilinear mean of both
    g[:, 44] = g[:, 45] = 1.0  # line 0 on an edge: g_m = 1
    g[:, 54], g[:, 55] = 0.2, 0.6  # line 1: g_m = 0.4
    gm = cues.sample_bilinear(jnp.asarray(g), pts)
    np.testing.assert_allclose(gm[0, 0], 1.0, atol=1e-12)
    np.testing.assert_allclose(gm[0, 1], 0.4, atol=1e-12)
    sad = cues.edge_loglik(gm, SIGMA, "sad")
    ssd = cues.edge_loglik(gm, SIGMA, "ssd")
    # SAD: -(1 - mean g) / (2 sigma^2), mean g = 0.7; SSD: -mean (1 - g)^2 / (2 sigma^2)
    np.testing.assert_allclose(sad, -(1 - 0.7) / (2 * SIGMA**2), rtol=1e-12)
    np.testing.assert_allclose(ssd, -(0.5 * 0.36) / (2 * SIGMA**2), rtol=1e-12)
    # perfect match: p = 1
    assert cues.edge_loglik(jnp.ones(16), SIGMA, "ssd") == 0.0
    with pytest.raises(ValueError, match="form"):
        cues.edge_loglik(gm, SIGMA, "abs")


def test_distance_cue_missing_points():
    f = jnp.array([[0.0, 0.0, 1.7], [0.3, 0.2, 1.0], [0.3, -0.2, 1.0]])
    c = jnp.array([[0.0, 0.0, 1.6], [0.3, 0.2, 1.0], [0.0, 0.0, 0.0]])
    valid = jnp.array([True, True, False])
    ll = cues.distance_loglik(f, c, valid, 0.05)
    np.testing.assert_allclose(ll, -(0.1**2) / (2 * 0.05**2), rtol=1e-12)
    # a missing c_i contributes nothing, whatever its value (Azad: c_i = 0)
    ll_other = cues.distance_loglik(f, c.at[2].set(jnp.array([5.0, 5.0, 5.0])), valid, 0.05)
    assert ll_other == ll
    assert cues.distance_loglik(f, c, jnp.zeros(3, bool), 0.05) == 0.0


def test_region_cue_fraction():
    cam = _front_camera()
    starts, ends = cues.project_limbs(cam, *_one_cylinder())
    pts = cues.region_samples(starts, ends, m=10, across=4)
    assert pts.shape == (1, 4, 10, 2)
    fg = np.zeros((100, 100))
    fg[35:65, 40:60] = 1.0  # covers the whole projected cylinder (x 44.5..54.5, y 39.5..59.5)
    r = cues.sample_nearest(jnp.asarray(fg), pts)
    assert cues.region_loglik(r, SIGMA) == 0.0
    fg[:, 50:] = 0.0  # only the left half of the region (across fractions 1/8, 3/8) on it
    r = cues.sample_nearest(jnp.asarray(fg), pts)
    np.testing.assert_allclose(np.asarray(r).mean(), 0.5)
    np.testing.assert_allclose(cues.region_loglik(r, SIGMA), -0.5 / (2 * SIGMA**2), rtol=1e-12)


# --------------------------------------------------------------------- the fused likelihood


@pytest.fixture(scope="module")
def setup():
    model = default_body()
    cams = [
        camlib.look_at(
            jnp.array([2.3, y, 1.6]), jnp.array([0.0, y, 1.15]), width=80, height=60, fx=77.0
        )
        for y in (-0.055, 0.055)
    ]
    rng = np.random.default_rng(1)
    edges = cv2.GaussianBlur(rng.random((2, 60, 80)).transpose(1, 2, 0), (0, 0), 2.0)
    edges = edges.transpose(2, 0, 1)
    edges = (edges - edges.min()) / (edges.max() - edges.min())
    fg = (rng.random((2, 60, 80)) > 0.5).astype(np.float64)
    obs = cues.Observation(
        edges=jnp.asarray(edges),
        points=jnp.array([[0.0, 0.0, 1.6], [0.2, 0.25, 1.0], [0.0, 0.0, 0.0]]),
        valid=jnp.array([True, True, False]),
        foreground=jnp.asarray(fg),
    )
    dofs = stereo_dofs(model)
    lik = cues.StereoLikelihood(
        model=model,
        limbs=cues.limb_model(model),
        cams=camlib.stack_cameras(cams),
        default_q=jnp.zeros(model.n_dof),
        sigma_g=SIGMA,
        sigma_d=0.05,
        sigma_r=SIGMA,
        dofs=tuple(int(i) for i in dofs),
        use_region=True,
        edge_form="ssd",
    )
    s = np.zeros((5, len(dofs)))
    s[:, 2] = 0.85
    s += rng.normal(0, 0.3, s.shape) * (np.arange(len(dofs)) >= 3)
    return model, cams, obs, lik, jnp.asarray(s)


def _half_width(limbs, k, T, ends3, cam):
    """Silhouette half-width (m) of limb k seen from ``cam``, by brute force: the largest
    extent of its cross-section ellipse (half-widths ``radius`` along ``side``, ``depth``
    along axis x side) along u, the direction normal to the axis and to the viewing ray
    (scipy's bounded scalar maximisation over the ellipse's angle)."""
    from scipy.optimize import minimize_scalar

    R, t = np.asarray(cam.R), np.asarray(cam.t)
    axis = (ends3[1] - ends3[0]) / np.linalg.norm(ends3[1] - ends3[0])
    side = T[:3, :3] @ np.asarray(limbs.side[k])
    front = np.cross(axis, side)
    ray = R.T @ (R @ (0.5 * (ends3[0] + ends3[1])) + t)  # camera centre -> midpoint, world
    u = np.cross(axis, ray)
    u /= np.linalg.norm(u)
    r, d = float(limbs.radius[k]), float(limbs.depth[k])

    def extent(th):
        return -((r * np.cos(th)) * (side @ u) + (d * np.sin(th)) * (front @ u))

    best = min(
        (minimize_scalar(extent, bounds=(lo, lo + np.pi), method="bounded",
                         options={"xatol": 1e-12}) for lo in (-np.pi, 0.0)),
        key=lambda res: res.fun,
    )  # fmt: skip
    return -best.fun


def _reference_loglik(model, cams, obs, lik, tr):
    """Independent NumPy/OpenCV evaluation (cv2.projectPoints, explicit bilinear weights) given
    the links' transforms ``tr`` (body.fk is checked against pytorch-kinematics elsewhere)."""
    limbs = lik.limbs
    p0s, p1s, radii = (np.asarray(x) for x in (limbs.p0, limbs.p1, limbs.radius))
    edges, fg = np.asarray(obs.edges), np.asarray(obs.foreground)
    ll = 0.0
    m = lik.points_per_line
    for c, cam in enumerate(cams):
        g_all, r_all = [], []
        for k, link in enumerate(limbs.link):
            T = tr[link]
            ends3 = [T[:3, :3] @ np.asarray(p[k]) + T[:3, 3] for p in (p0s, p1s)]
            rvec, _ = cv2.Rodrigues(np.asarray(cam.R))
            uv, _ = cv2.projectPoints(
                np.array(ends3), rvec, np.asarray(cam.t), np.asarray(cam.K), np.zeros(5)
            )
            a, b = uv[:, 0]
            depth = [(np.asarray(cam.R) @ e + np.asarray(cam.t))[2] for e in ends3]
            d = (b - a) / np.linalg.norm(b - a)
            n = np.array([-d[1], d[0]])
            f = float(cam.K[0, 0])
            ra, rb = (f * _half_width(limbs, k, T, ends3, cam) / z for z in depth)
            lines = [(a + sgn * n * ra, b + sgn * n * rb) for sgn in (1, -1)]
            for p0, p1 in lines:
                for j in range(m):
                    t = (j + 0.5) / m
                    x, y = p0 * (1 - t) + p1 * t
                    x0, y0 = int(np.floor(x)), int(np.floor(y))
                    val = 0.0
                    for xi, yi, wgt in (
                        (x0, y0, (1 - x + x0) * (1 - y + y0)),
                        (x0 + 1, y0, (x - x0) * (1 - y + y0)),
                        (x0, y0 + 1, (1 - x + x0) * (y - y0)),
                        (x0 + 1, y0 + 1, (x - x0) * (y - y0)),
                    ):
                        if 0 <= xi < 80 and 0 <= yi < 60:
                            val += wgt * edges[c, yi, xi]
                    g_all.append(val)
            for u in (np.arange(3) + 0.5) / 3:
                p0 = lines[0][0] * (1 - u) + lines[1][0] * u
                p1 = lines[0][1] * (1 - u) + lines[1][1] * u
                for j in range(m):
                    t = (j + 0.5) / m
                    x, y = np.round(p0 * (1 - t) + p1 * t).astype(int)
                    inside = 0 <= x < 80 and 0 <= y < 60
                    r_all.append(fg[c, y, x] if inside else 0.0)
        g_all, r_all = np.array(g_all), np.array(r_all)
        ll += -np.mean((1 - g_all) ** 2) / (2 * SIGMA**2)
        ll += -np.mean((1 - r_all) ** 2) / (2 * SIGMA**2)
    kp = tr
    idx = keypoint_index(model, cues.DISTANCE_NAMES)
    for kpi, ci, vi in zip(idx, np.asarray(obs.points), np.asarray(obs.valid), strict=True):
        link = int(model.keypoint_link[kpi])
        f = kp[link, :3, :3] @ np.asarray(model.keypoint_offset[kpi]) + kp[link, :3, 3]
        if vi:
            ll += -np.sum((f - ci) ** 2) / (2 * 0.05**2)
    return ll


def test_stereo_likelihood_vs_reference_jit_vmap(setup):
    model, cams, obs, lik, s = setup
    q = jnp.zeros((s.shape[0], model.n_dof)).at[:, np.asarray(lik.dofs)].set(s)
    trs = np.asarray(jax.jit(jax.vmap(lambda x: fk(model.chain, x)))(q))
    ref = np.array([_reference_loglik(model, cams, obs, lik, tr) for tr in trs])
    single = float(jax.jit(lambda x: lik(x, obs))(s[0]))
    batched = jax.jit(jax.vmap(lambda x: lik(x, obs)))(s)
    np.testing.assert_allclose(single, ref[0], rtol=1e-9)
    np.testing.assert_allclose(batched, ref, rtol=1e-9)
    assert np.all(np.isfinite(ref)) and np.ptp(ref) > 1.0  # distinct particles, distinct values


def test_stereo_likelihood_grad_vs_finite_differences(setup):
    _, _, obs, lik, s = setup
    lik_e = eqx_replace(lik, use_region=False)  # the region cue reads a binary map: piecewise const
    f = jax.jit(lambda x: lik_e(x, obs))
    g = jax.jit(jax.grad(lambda x: lik_e(x, obs)))(s[0])
    eps = 1e-6
    e = np.eye(s.shape[1])
    fd = np.array(
        [(f(s[0] + eps * ei) - f(s[0] - eps * ei)) / (2 * eps) for ei in e[[0, 3, 6, 12]]]
    )
    np.testing.assert_allclose(np.asarray(g)[[0, 3, 6, 12]], fd, rtol=1e-4, atol=1e-5)


def eqx_replace(module, **kw):
    import dataclasses

    return dataclasses.replace(module, **kw)


def test_limb_model_errors():
    model = default_body()
    with pytest.raises(InputError, match="unknown geoms"):
        cues.limb_model(model, ("l_shin",))
    with pytest.raises(InputError, match="several links"):
        cues.limb_model(model, (("thorax", "head"),))
    limbs = cues.limb_model(model)
    assert limbs.names == ("l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm", "torso")
    # the explicit form gives the same torso (two stacked ellipsoids: centre to centre)
    explicit = cues.limb_model(model, ("l_upper_arm", ("abdomen", "thorax")))
    np.testing.assert_array_equal(np.asarray(explicit.p1[1]), np.asarray(limbs.p1[-1]))
    np.testing.assert_allclose(np.asarray(limbs.radius), [0.05, 0.04, 0.05, 0.04, 0.16])
    # the torso's cross-section is elliptic: half-depth (body x) 0.115 m, round limbs equal
    np.testing.assert_allclose(np.asarray(limbs.depth), [0.05, 0.04, 0.05, 0.04, 0.115])


def test_silhouette_radius_of_the_elliptic_torso():
    """Seen from the front the torso's silhouette half-width is its left-right half-width
    (radius), seen from the side its front-back one (depth); round limbs keep their radius
    from any side. Camera on the +x axis looking at the origin, body yawed by psi."""
    model = default_body()
    limbs = cues.limb_model(model)
    cam = camlib.look_at(jnp.array([3.0, 0.0, 1.2]), jnp.array([0.0, 0.0, 1.2]), width=80,
                         height=60, fx=77.0)  # fmt: skip
    for psi, want in ((0.0, limbs.radius[-1]), (np.pi / 2, limbs.depth[-1])):
        q = jnp.zeros(model.n_dof).at[2].set(0.9).at[5].set(psi)
        tr = fk(model.chain, q)
        a, b = cues.limb_endpoints(limbs, tr)
        h = cues.silhouette_radius(cam, limbs, tr, a, b)
        np.testing.assert_allclose(h[-1], want, rtol=1e-6)
        np.testing.assert_allclose(h[:4], limbs.radius[:4], rtol=1e-12)


def test_distance_linearize_vs_autodiff_and_finite_differences(setup):
    """The closed-form Jacobian of the distance residuals (revolute axes, root translation,
    left Jacobian of the root rotation vector) equals forward-mode autodiff of the residual and
    central finite differences, at a generic pose and at a zero root rotation (Taylor branch);
    rows of a missing point are zero; under vmap too."""
    lik = setup[3]
    rng = np.random.default_rng(4)
    d = len(lik.dofs)
    z = cues.Observation(
        edges=jnp.zeros((2, 8, 8)), points=jnp.asarray(rng.standard_normal((3, 3))),
        valid=jnp.array([True, False, True]), foreground=jnp.zeros((2, 8, 8)),
    )  # fmt: skip
    s0 = jnp.asarray(0.4 * rng.standard_normal((2, d))).at[1, 3:6].set(0.0)
    r, jac = jax.vmap(lik.distance_linearize, in_axes=(0, None))(s0, z)
    np.testing.assert_allclose(r, jax.vmap(lik.distance_residual, in_axes=(0, None))(s0, z))
    auto = jax.vmap(jax.jacfwd(lik.distance_residual), in_axes=(0, None))(s0, z)
    np.testing.assert_allclose(np.asarray(jac), np.asarray(auto), atol=1e-10)
    assert np.all(np.asarray(jac)[:, 3:6] == 0)  # the missing left hand
    eps = 1e-6
    for b in range(2):
        fd = np.stack(
            [(lik.distance_residual(s0[b].at[i].add(eps), z)
              - lik.distance_residual(s0[b].at[i].add(-eps), z)) / (2 * eps) for i in range(d)],
            axis=-1,
        )  # fmt: skip
        np.testing.assert_allclose(np.asarray(jac[b]), fd, atol=1e-7)


def test_edge_outside_replaces_samples_beyond_the_image():
    """A cylinder half above the image (hand-computed): its 2 x 10 contour samples lie at
    v = -8, -3, 2, ..., 37 on the edge columns; the 4 at v < -0.5 are outside. Zero padding
    (Azad, edge_outside=None) reads 0 there, the switch reads the constant c."""
    cam = _front_camera()
    a, b = jnp.array([[0.0, -1.2, 2.0]]), jnp.array([[0.0, -0.2, 2.0]])  # v from -10.5 to 39.5
    starts, ends = cues.project_limbs(cam, a, b, jnp.array([0.1]))
    uv = cues.edge_samples(starts, ends, 10)
    np.testing.assert_allclose(uv[0, 0, :3, 1], [-8.0, -3.0, 2.0], atol=1e-12)
    g = np.zeros((100, 100))
    g[:, 44] = g[:, 45] = g[:, 54] = g[:, 55] = 1.0  # both silhouette lines on edges
    gm = cues.sample_bilinear(jnp.asarray(g), uv)
    np.testing.assert_allclose(np.asarray(gm).mean(), 16 / 20, atol=1e-12)
    inside = np.asarray(cues._inside(uv, g.shape))
    assert inside.sum() == 16 and not inside[0, :, :2].any()
    c = 0.5
    gc = jnp.where(jnp.asarray(inside), gm, c)
    np.testing.assert_allclose(
        cues.edge_loglik(gc, SIGMA), -(1 - (16 + 4 * c) / 20) / (2 * SIGMA**2), rtol=1e-12
    )


def test_edge_outside_and_support_cue_in_the_likelihood_vs_reference(setup):
    """The fused likelihood with the two switches, against NumPy / OpenCV: (i) edge_outside
    changes exactly the outside samples' contribution (cameras framing the body tightly so
    that limbs leave the image); (ii) the support cue is -1 / (2 sigma_s^2) times the number of
    (hand, camera) pairs whose hand -- projected with cv2.projectPoints, nearest pixel -- lies
    inside the image on a 0 of the support map, over the hands without a point (the right
    hand here; both with support_all). jit(vmap) over particles."""
    model, cams, obs, lik, s = setup
    rng = np.random.default_rng(7)
    support = (rng.random((2, 60, 80)) > 0.5).astype(np.float64)
    z = cues.Observation(obs.edges, obs.points, obs.valid, obs.foreground, jnp.asarray(support))
    base = eqx_replace(lik, use_region=False, use_distance=False)
    f = jax.jit(jax.vmap(lambda L, x: L(x, z), in_axes=(None, 0)))
    ll0 = np.asarray(f(base, s))
    # (ii) support cue
    q = jnp.zeros((s.shape[0], model.n_dof)).at[:, np.asarray(lik.dofs)].set(s)
    trs = np.asarray(jax.vmap(lambda x: fk(model.chain, x))(q))
    idx = keypoint_index(model, cues.SUPPORT_NAMES)
    for support_all, hands in ((False, [1]), (True, [0, 1])):
        want = []
        for tr in trs:
            n_miss = 0
            for c, cam in enumerate(cams):
                rvec, _ = cv2.Rodrigues(np.asarray(cam.R))
                for j in hands:
                    kpi = idx[j]
                    link = int(model.keypoint_link[kpi])
                    p = tr[link, :3, :3] @ np.asarray(model.keypoint_offset[kpi]) + tr[link, :3, 3]
                    uv, _ = cv2.projectPoints(p[None], rvec, np.asarray(cam.t),
                                              np.asarray(cam.K), np.asarray(cam.dist))  # fmt: skip
                    x, y = np.round(uv[0, 0]).astype(int)
                    if 0 <= x < 80 and 0 <= y < 60 and support[c, y, x] == 0:
                        n_miss += 1
            want.append(-n_miss / (2 * cues.SIGMA_S**2))
        lik_s = eqx_replace(base, use_support=True, support_all=support_all)
        got = np.asarray(f(lik_s, s)) - ll0
        np.testing.assert_allclose(got, want, atol=1e-9)
    assert np.any(np.array(want) < 0)  # some hands do land on 0s
    # (i) edge_outside: tight cameras (fx 200): parts of the limbs leave the 80 x 60 image
    tight = camlib.stack_cameras(
        [camlib.look_at(jnp.array([2.3, y, 1.6]), jnp.array([0.0, y, 1.15]), width=80,
                        height=60, fx=200.0) for y in (-0.055, 0.055)]
    )  # fmt: skip
    b0 = eqx_replace(base, cams=tight)
    b5 = eqx_replace(b0, edge_outside=0.5)
    d = np.asarray(f(b5, s)) - np.asarray(f(b0, s))

    def samples(x):  # contour samples of both cameras (projection tested against OpenCV above)
        tr = fk(model.chain, x)
        a, b = cues.limb_endpoints(lik.limbs, tr)

        def one(cam):
            st, en = cues.project_limbs(cam, a, b, cues.silhouette_radius(cam, lik.limbs, tr, a, b))
            return cues.edge_samples(st, en, lik.points_per_line).reshape(-1, 2)

        uv = jax.vmap(one)(tight)
        return uv, jax.vmap(cues.sample_bilinear)(z.edges, uv)

    uvs, gs = (np.asarray(v) for v in jax.jit(jax.vmap(samples))(q))
    out = ~((uvs[..., 0] >= -0.5) & (uvs[..., 0] <= 79.5) & (uvs[..., 1] >= -0.5)
            & (uvs[..., 1] <= 59.5))  # fmt: skip
    # the fixture's SSD form -mean (1 - g)^2 / (2 sigma^2): outside, (1 - g)^2 -> (1 - 0.5)^2
    ref = np.sum(np.where(out, (1 - gs) ** 2 - 0.25, 0.0), axis=(1, 2))
    ref = ref / uvs.shape[2] / (2 * SIGMA**2)
    np.testing.assert_allclose(d, ref, atol=1e-9)
    assert np.sum(ref > 0.05) >= 2  # the tight framing does cut limbs of some particles


def test_hand_swap_pairs_hands_by_the_nearer_assignment(setup):
    """With ``hand_swap`` the distance cue of a pose is the same whichever identities the
    triangulated hands carry, and equals the unswapped cue (reference: the NumPy sum of
    squared distances) for identities that match the model; its closed-form Jacobian still
    equals forward-mode autodiff."""
    model, cams, obs, lik, s = setup
    lik2 = dataclasses.replace(lik, hand_swap=True)
    q = jnp.zeros(model.n_dof).at[np.asarray(lik.dofs)].set(s[0])
    tr = np.asarray(fk(model.chain, q))
    idx = keypoint_index(model, cues.DISTANCE_NAMES)
    f = np.stack([tr[int(model.keypoint_link[i]), :3, :3] @ np.asarray(model.keypoint_offset[i])
                  + tr[int(model.keypoint_link[i]), :3, 3] for i in idx])
    c = f + np.array([[0.01, 0, 0], [0.0, 0.02, 0], [0, 0, -0.03]])
    for valid in ([True, True, True], [True, True, False]):
        z = dataclasses.replace(obs, points=jnp.asarray(c), valid=jnp.array(valid))
        zs = dataclasses.replace(obs, points=jnp.asarray(c[[0, 2, 1]]),
                                 valid=jnp.array(valid)[np.array([0, 2, 1])])
        ref = -np.sum(np.where(valid, np.sum((f - c) ** 2, -1), 0)) / (2 * 0.05**2)
        for zz in (z, zs):
            ll = float(lik2(s[0], zz)) - float(dataclasses.replace(lik2, use_distance=False)(
                s[0], zz))
            np.testing.assert_allclose(ll, ref, rtol=1e-9)
        # without hand_swap the swapped identities cost more
        assert float(lik(s[0], zs)) < float(lik(s[0], z))
        r, jac = lik2.distance_linearize(s[0], zs)
        np.testing.assert_allclose(r, lik2.distance_residual(s[0], zs))
        np.testing.assert_allclose(np.asarray(jac),
                                   np.asarray(jax.jacfwd(lik2.distance_residual)(s[0], zs)),
                                   atol=1e-10)


def test_sigma_depth_splits_the_distance_cue_along_the_line_of_sight(setup):
    """With ``sigma_depth`` the distance cue weighs each residual's component along the line
    of sight from the cameras' midpoint (``camera_center`` of both, an independent formula:
    C = -R^T t) to the target by 1 / sigma_depth^2 and the rest by 1 / sigma_d^2
    (hand-computed against the isotropic cue's value); sigma_depth = sigma_d is the isotropic
    cue; a model point moved along the target's line of sight costs (d / sigma_depth)^2 / 2,
    moved across it (d / sigma_d)^2 / 2; the closed-form Jacobian equals autodiff and finite
    differences of the whitened residual; jit and vmap give the same values, grad is finite."""
    lik = dataclasses.replace(setup[3], use_edges=False, use_region=False)
    rng = np.random.default_rng(7)
    d = len(lik.dofs)
    s0 = jnp.asarray(0.3 * rng.standard_normal((3, d)))
    f = jax.vmap(lambda s: cues.distance_points(
        lik.model, cues.pose_transforms(lik.model, lik.full_q(s))))(s0)
    targets = f[0] + jnp.asarray(0.1 * rng.standard_normal((3, 3)))
    z = cues.Observation(edges=jnp.zeros((2, 8, 8)), points=targets,
                         valid=jnp.array([True, True, False]), foreground=jnp.zeros((2, 8, 8)))
    iso = jax.vmap(lik, in_axes=(0, None))(s0, z)
    same = dataclasses.replace(lik, sigma_depth=jnp.asarray(lik.sigma_d))
    np.testing.assert_allclose(np.asarray(jax.vmap(same, in_axes=(0, None))(s0, z)),
                               np.asarray(iso), rtol=1e-12)
    sd, sz = float(lik.sigma_d), 0.2
    aniso = dataclasses.replace(lik, sigma_depth=jnp.asarray(sz))
    origin = np.mean([np.asarray(camlib.camera_center(c))
                      for c in camlib.unstack_cameras(lik.cams)], axis=0)
    want = []
    for b in range(3):
        tot = 0.0
        for i in range(2):  # the third target is missing
            r = np.asarray(f[b, i] - targets[i])
            u = np.asarray(targets[i]) - origin
            u /= np.linalg.norm(u)
            along = r @ u
            tot -= np.sum((r - along * u) ** 2) / (2 * sd**2) + along**2 / (2 * sz**2)
        want.append(tot)
    got = jax.jit(jax.vmap(aniso, in_axes=(0, None)))(s0, z)
    np.testing.assert_allclose(np.asarray(got), want, rtol=1e-10)
    # the model's head 0.1 m behind its target on the target's line of sight (the hand on its
    # own): (0.1 / sigma_depth)^2 / 2 against the isotropic cue's (0.1 / sigma_d)^2 / 2
    head = np.asarray(f[0, 0])
    u = head - origin
    u /= np.linalg.norm(u)
    tz = z.points.at[0].set(jnp.asarray(head - 0.1 * u)).at[1].set(f[0, 1])
    zz = dataclasses.replace(z, points=tz)
    np.testing.assert_allclose(float(aniso(s0[0], zz)), -(0.1 / sz) ** 2 / 2, rtol=1e-9)
    np.testing.assert_allclose(float(lik(s0[0], zz)), -(0.1 / sd) ** 2 / 2, rtol=1e-9)
    r, jac = jax.vmap(aniso.distance_linearize, in_axes=(0, None))(s0, z)
    np.testing.assert_allclose(np.asarray(r), np.asarray(
        jax.vmap(aniso.distance_residual, in_axes=(0, None))(s0, z)), atol=1e-12)
    auto = jax.vmap(jax.jacfwd(aniso.distance_residual), in_axes=(0, None))(s0, z)
    np.testing.assert_allclose(np.asarray(jac), np.asarray(auto), atol=1e-10)
    eps = 1e-6
    fd = np.stack([(aniso.distance_residual(s0[0].at[i].add(eps), z)
                    - aniso.distance_residual(s0[0].at[i].add(-eps), z)) / (2 * eps)
                   for i in range(d)], axis=-1)
    np.testing.assert_allclose(np.asarray(jac[0]), fd, atol=1e-7)
    # |r_w|^2 / (2 sigma_d^2) of the whitened residual is the cue
    np.testing.assert_allclose(-np.sum(np.asarray(r) ** 2, axis=1) / (2 * sd**2), want,
                               rtol=1e-10)
    g = jax.grad(lambda sig: dataclasses.replace(aniso, sigma_depth=sig)(s0[0], z))(
        jnp.asarray(sz))
    assert np.isfinite(float(g)) and float(g) > 0  # a wider depth width explains more


def test_make_params_refuses_a_sigma_depth_not_positive():
    from jaxmocap.trackers import stereo_pf as sp

    cams = [camlib.look_at(jnp.array([2.3, y, 1.6]), jnp.array([0.0, y, 1.15]), width=80,
                           height=60, fx=77.0) for y in (-0.055, 0.055)]
    with pytest.raises(InputError, match="sigma_depth: expected > 0"):
        sp.make_params(cams, cues=sp.Cues(sigma_depth=0.0))
    p = sp.make_params(cams, cues=sp.Cues(sigma_depth=0.08))
    assert float(p.likelihood.sigma_depth) == pytest.approx(0.08)
