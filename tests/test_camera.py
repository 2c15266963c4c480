"""Tests for jaxmocap.camera against OpenCV (projectPoints, undistortPoints, triangulatePoints,
findFundamentalMat, computeCorrespondEpilines, Rodrigues) and finite differences."""

import json

import cv2
import equinox as eqx
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings

from jaxmocap import camera as jc
from jaxmocap.camera import (
    Camera,
    camera_center,
    epipolar_distance,
    epipolar_distance_undistorted,
    fundamental_matrix,
    look_at,
    pixel_rays,
    project,
    stack_cameras,
    to_camera,
    triangulate,
    undistort_normalized,
)
from jaxmocap.io.cameras import CameraFileError, load_cameras, save_cameras

W, H = 640, 480
WEBCAM_DIST = np.array([-0.28, 0.09, 0.0012, -0.0008, -0.012])  # realistic webcam lens

project_j = jax.jit(project)
triangulate_j = jax.jit(triangulate, static_argnames=("refine", "n_iter"))
project_views = jax.jit(jax.vmap(project, (0, None)))
undistort_j = jax.jit(undistort_normalized)
epipolar_j = jax.jit(epipolar_distance)


def random_camera(rng, dist_scale=1.0, target=(0.0, 0.0, 1.0)) -> Camera:
    """A camera 2-4 m from ``target`` looking at it, with random intrinsics and distortion."""
    az, el = rng.uniform(-np.pi, np.pi), rng.uniform(-0.3, 0.6)
    r = rng.uniform(2.0, 4.0)
    eye = np.asarray(target) + r * np.array(
        [np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)]
    )
    fx = rng.uniform(450, 800)
    dist = WEBCAM_DIST * dist_scale * rng.uniform(0.5, 1.2, size=5)
    return look_at(
        eye,
        np.asarray(target) + rng.normal(scale=0.1, size=3),
        width=W,
        height=H,
        fx=fx,
        fy=fx * rng.uniform(0.97, 1.03),
        cx=W / 2 + rng.normal(scale=10),
        cy=H / 2 + rng.normal(scale=10),
        dist=dist,
    )


def random_points(rng, n, center=(0.0, 0.0, 1.0), scale=0.4):
    return rng.normal(scale=scale, size=(n, 3)) + np.asarray(center)


def cv_project(cam: Camera, X) -> np.ndarray:
    rvec, _ = cv2.Rodrigues(np.asarray(cam.R))
    uv, _ = cv2.projectPoints(
        np.asarray(X, float),
        rvec,
        np.asarray(cam.t, float),
        np.asarray(cam.K),
        np.asarray(cam.dist),
    )
    return uv[:, 0]


# ------------------------------------------------------------------------------- construction


def test_camera_validation():
    good = dict(K=np.eye(3), R=np.eye(3), t=np.zeros(3), dist=np.zeros(5), width=W, height=H)
    Camera(**good)
    with pytest.raises(ValueError, match="Camera.K"):
        Camera(**{**good, "K": np.diag([-1.0, 1.0, 1.0])})
    for field, bad in (("width", 0), ("height", -3)):
        with pytest.raises(ValueError, match=f"Camera.{field}"):
            Camera(**{**good, field: bad})
    with pytest.raises(Exception, match="dist|shape"):  # jaxtyping or __check_init__
        Camera(**{**good, "dist": np.zeros(4)})


def test_look_at_geometry():
    eye, target = np.array([3.0, 0.5, 1.6]), np.array([0.0, 0.0, 1.0])
    cam = look_at(eye, target, width=W, height=H, fx=500.0)
    np.testing.assert_allclose(camera_center(cam), eye, atol=1e-12)
    np.testing.assert_allclose(cam.R @ cam.R.T, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(cam.R), 1.0, atol=1e-12)
    np.testing.assert_allclose(project(cam, target), [(W - 1) / 2, (H - 1) / 2], atol=1e-9)
    # world up (+z) is image up (smaller v); the camera's right is the world's right
    assert project(cam, target + [0, 0, 0.1])[1] < (H - 1) / 2
    right = np.cross(target - eye, [0, 0, 1.0])
    assert project(cam, target + 0.1 * right / np.linalg.norm(right))[0] > (W - 1) / 2
    with pytest.raises(ValueError, match="parallel"):
        look_at([0, 0, 2.0], [0, 0, 0.0], width=W, height=H, fx=500.0)


def test_stack_and_unstack(rng):
    cams = [random_camera(rng) for _ in range(3)]
    s = stack_cameras(cams)
    assert s.K.shape == (3, 3, 3) and s.dist.shape == (3, 5) and (s.width, s.height) == (W, H)
    for a, b in zip(jc.unstack_cameras(s), cams, strict=True):
        np.testing.assert_array_equal(a.K, b.K)
    small = look_at([2.0, 0, 1], [0, 0, 1.0], width=320, height=240, fx=300.0)
    with pytest.raises(ValueError, match="image size"):
        stack_cameras([cams[0], small])


# ------------------------------------------------------------------------------- projection


def test_project_matches_opencv(rng):
    for _ in range(6):
        cam = random_camera(rng)
        X = random_points(rng, 200)
        np.testing.assert_allclose(project_j(cam, X), cv_project(cam, X), atol=1e-4, rtol=0)
    # batch shapes are preserved
    X = random_points(rng, 12).reshape(3, 4, 3)
    np.testing.assert_allclose(
        project(cam, X).reshape(12, 2), cv_project(cam, X.reshape(12, 3)), atol=1e-4
    )
    assert project(cam, X[0, 0]).shape == (2,)


def test_project_follows_input_dtype(rng):
    cam32 = jax.tree.map(lambda a: a.astype(jnp.float32), random_camera(rng))
    uv = project_j(cam32, jnp.asarray(random_points(rng, 5), jnp.float32))
    assert uv.dtype == jnp.float32


def test_project_jit_vmap_grad(rng):
    cams = [random_camera(rng) for _ in range(3)]
    X = random_points(rng, 50)
    stacked = stack_cameras(cams)
    per_view = project_views(stacked, X)
    for i, c in enumerate(cams):
        np.testing.assert_allclose(per_view[i], project_j(c, X), atol=1e-10)
        np.testing.assert_allclose(project_j(c, X), project(c, X), atol=1e-10)

    # gradient wrt the point and wrt every camera parameter vs central finite differences
    cam, x0 = cams[0], X[0]

    def loss(c, x):
        uv = project(c, x)
        return jnp.sum(jnp.sin(uv / 50.0))

    g_cam, g_x = jax.jit(jax.grad(loss, argnums=(0, 1)))(cam, x0)
    loss = jax.jit(loss)
    eps = 1e-6
    for k in range(3):
        e = np.zeros(3)
        e[k] = eps
        fd = (loss(cam, x0 + e) - loss(cam, x0 - e)) / (2 * eps)
        np.testing.assert_allclose(g_x[k], fd, rtol=1e-5, atol=1e-7)
    for field, idx in (
        ("dist", (0,)),
        ("dist", (3,)),
        ("K", (0, 0)),
        ("K", (1, 2)),
        ("t", (2,)),
        ("R", (1, 0)),
    ):

        def shifted(d, field=field, idx=idx):
            arr = getattr(cam, field)
            return eqx_set(cam, field, arr.at[idx].add(d))

        fd = (loss(shifted(eps), x0) - loss(shifted(-eps), x0)) / (2 * eps)
        np.testing.assert_allclose(getattr(g_cam, field)[idx], fd, rtol=1e-5, atol=1e-7)


def eqx_set(cam, field, value):
    return eqx.tree_at(lambda c: getattr(c, field), cam, value)


def test_to_camera_depth(rng):
    cam = random_camera(rng)
    X = random_points(rng, 20)
    xc = to_camera(cam, X)
    np.testing.assert_allclose(xc, X @ np.asarray(cam.R).T + np.asarray(cam.t), atol=1e-12)
    assert np.all(xc[:, 2] > 0)


# ------------------------------------------------------------------------------- undistortion


def test_undistort_matches_opencv(rng):
    cam = look_at([3.0, 0, 1.0], [0, 0, 1.0], width=W, height=H, fx=520.0, dist=WEBCAM_DIST)
    # pixels over the whole image, corners included
    uv = np.stack(np.meshgrid(np.linspace(0, W - 1, 17), np.linspace(0, H - 1, 13)), -1)
    uv = uv.reshape(-1, 2)
    ref = cv2.undistortPoints(
        uv[:, None],
        np.asarray(cam.K),
        WEBCAM_DIST,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 0),
    )
    np.testing.assert_allclose(undistort_j(cam, uv), ref[:, 0], atol=1e-6, rtol=0)
    # and it inverts the distortion model exactly
    np.testing.assert_allclose(
        project_j(
            cam,
            jnp.concatenate([undistort_j(cam, uv), jnp.ones((uv.shape[0], 1))], -1) @ cam.R
            + camera_center(cam)[None],
        ),
        uv,
        atol=1e-8,
    )


def test_pixel_rays_round_trip(rng):
    for _ in range(3):
        cam = random_camera(rng)
        uv = rng.uniform([0, 0], [W - 1, H - 1], size=(7, 9, 2))
        o, d = jax.jit(pixel_rays)(cam, uv)
        assert o.shape == d.shape == (7, 9, 3)
        np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, atol=1e-12)
        np.testing.assert_allclose(o, np.broadcast_to(camera_center(cam), o.shape), atol=1e-12)
        depth = rng.uniform(0.5, 5.0, size=(7, 9, 1))
        np.testing.assert_allclose(project_j(cam, o + depth * d), uv, atol=1e-7)
        assert np.all(to_camera(cam, o + depth * d)[..., 2] > 0)
    # gradient through the fixed-iteration undistortion: d(ray)/d(u) vs finite differences
    f = lambda u: pixel_rays(cam, jnp.stack([u, jnp.asarray(300.0)]))[1]
    f = jax.jit(f)
    jac = jax.jit(jax.jacfwd(f))(jnp.asarray(100.0))
    fd = (f(jnp.asarray(100.0 + 1e-4)) - f(jnp.asarray(100.0 - 1e-4))) / 2e-4
    np.testing.assert_allclose(jac, fd, atol=1e-9)


# ------------------------------------------------------------------------------- triangulation


N_POINTS = 32  # one point count for all triangulation tests: one compilation per view count


def _scene(rng, n_views, n_points=N_POINTS, dist_scale=1.0):
    cams = [random_camera(rng, dist_scale) for _ in range(n_views)]
    X = random_points(rng, n_points)
    s = stack_cameras(cams)
    return cams, s, X, project_views(s, X)


def tri(s, uv, refine=True, w=None):
    """Triangulate with explicit weights, so that every call shares one compiled program."""
    w = np.ones(np.shape(uv)[:2]) if w is None else w
    return triangulate_j(s, uv, refine=refine, weights=w)


def test_triangulate_matches_opencv_dlt(rng):
    cams, s, X, uv = _scene(rng, 2, dist_scale=0.0)
    # exact pixels: both recover the points
    P = [np.asarray(c.K) @ np.hstack([np.asarray(c.R), np.asarray(c.t)[:, None]]) for c in cams]
    h = cv2.triangulatePoints(P[0], P[1], np.asarray(uv[0]).T, np.asarray(uv[1]).T)
    np.testing.assert_allclose((h[:3] / h[3]).T, X, atol=1e-8)
    np.testing.assert_allclose(tri(s, uv, refine=False), X, atol=1e-8)
    # noisy pixels: the same algebraic (DLT) solution when posed on normalised coordinates
    noisy = uv + rng.normal(scale=1.0, size=uv.shape)
    xy = [undistort_j(c, noisy[i]) for i, c in enumerate(cams)]
    Pn = [np.hstack([np.asarray(c.R), np.asarray(c.t)[:, None]]) for c in cams]
    h = cv2.triangulatePoints(Pn[0], Pn[1], np.asarray(xy[0]).T, np.asarray(xy[1]).T)
    np.testing.assert_allclose(tri(s, noisy, refine=False), (h[:3] / h[3]).T, atol=1e-9)


def _reproj_rms(s, X, uv):
    return float(np.sqrt(np.mean(np.sum((project_views(s, X) - uv) ** 2, -1))))


def test_triangulate_noisy_refine_and_views(rng):
    sq = {k: 0.0 for k in ("dlt2", "ref2", "dlt4", "ref4")}
    for _ in range(10):  # 10 random rigs x 32 points
        cams, s, X, uv = _scene(rng, 4)
        noisy = uv + rng.normal(scale=1.0, size=uv.shape)
        s2 = stack_cameras(cams[:2])
        est = {
            "dlt2": tri(s2, noisy[:2], refine=False),
            "ref2": tri(s2, noisy[:2]),
            "dlt4": tri(s, noisy, refine=False),
            "ref4": tri(s, noisy),
        }
        # refinement minimises the reprojection error: always below the DLT's
        assert _reproj_rms(s2, est["ref2"], noisy[:2]) < _reproj_rms(s2, est["dlt2"], noisy[:2])
        assert _reproj_rms(s, est["ref4"], noisy) < _reproj_rms(s, est["dlt4"], noisy)
        for k, Y in est.items():
            sq[k] += float(np.sum((Y - X) ** 2))
    rms = {k: np.sqrt(v / (10 * N_POINTS)) for k, v in sq.items()}
    # the 3D error shrinks with refinement and with more views; 1 px noise at ~3 m -> mm
    assert rms["ref2"] < rms["dlt2"] and rms["ref4"] < rms["dlt4"]
    assert rms["ref4"] < 0.8 * rms["ref2"]
    assert rms["ref4"] < 0.01


def _ml_reference(cams, uv_views, x0):
    """Maximum-likelihood point from SciPy least squares on OpenCV projections."""
    from scipy.optimize import least_squares

    def res(x):
        return np.concatenate(
            [cv_project(c, x[None])[0] - u for c, u in zip(cams, uv_views, strict=True)]
        )

    return least_squares(res, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15).x


def test_triangulate_missing_views(rng):
    cams, s, X, uv = _scene(rng, 4)
    noisy = np.array(uv + rng.normal(scale=0.5, size=uv.shape))
    w = np.ones(noisy.shape[:2])
    w[1, :10] = 0.0
    noisy[1, :10] = np.nan  # missing detections
    w[2:, 20:] = 0.0
    w[1, 26:] = 0.0  # points 26.. seen by camera 0 only
    got = tri(s, noisy, w=w)
    assert np.all(np.isnan(got[26:])) and np.all(np.isfinite(got[:26]))
    for i in (0, 5, 9, 12, 20, 25):
        views = [v for v in range(4) if w[v, i] > 0]
        ref = _ml_reference([cams[v] for v in views], noisy[views, i], X[i])
        np.testing.assert_allclose(got[i], ref, atol=1e-7)
    # batch shape is preserved
    flat = tri(s, uv, refine=False)
    batched = triangulate_j(s, np.asarray(uv).reshape(4, 4, 8, 2), refine=False)
    np.testing.assert_allclose(batched.reshape(N_POINTS, 3), flat, atol=1e-12)
    # forward-mode derivative along a random pixel perturbation vs central differences
    d = rng.normal(size=uv.shape)
    jvp = jax.jit(lambda u, du: jax.jvp(lambda v: triangulate(s, v), (u,), (du,))[1])(uv, d)
    eps = 1e-5
    fd = (triangulate_j(s, uv + eps * d) - triangulate_j(s, uv - eps * d)) / (2 * eps)
    np.testing.assert_allclose(jvp, fd, rtol=1e-4, atol=1e-9)


def test_projection_jacobian_matches_autodiff(rng):
    _, s, X, _ = _scene(rng, 2)
    uv, J = jax.jit(jc._project_views_and_jacobian)(s, X)
    auto = jax.jit(jax.vmap(jax.vmap(jax.jacfwd(project, argnums=1), (None, 0)), (0, None)))
    np.testing.assert_allclose(uv, project_views(s, X), atol=1e-10)
    np.testing.assert_allclose(J, auto(s, X), rtol=1e-9, atol=1e-9)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n_views=st.sampled_from([2, 4]))
def test_project_triangulate_identity(seed, n_views):
    rng = np.random.default_rng(seed)
    cams, s, X, uv = _scene(rng, n_views)
    np.testing.assert_allclose(tri(s, uv), X, atol=1e-7)
    np.testing.assert_allclose(project_views(s, tri(s, uv)), uv, atol=1e-6)


# ------------------------------------------------------------------------------- epipolar


def test_fundamental_matrix(rng):
    cams, s, X, uv = _scene(rng, 2, dist_scale=0.0)
    F = np.asarray(fundamental_matrix(cams[0], cams[1]))
    ha = np.hstack([uv[0], np.ones((N_POINTS, 1))])
    hb = np.hstack([uv[1], np.ones((N_POINTS, 1))])
    assert np.abs(np.einsum("ni,ij,nj->n", hb, F, ha)).max() < 1e-10
    Fcv, _ = cv2.findFundamentalMat(np.asarray(uv[0]), np.asarray(uv[1]), cv2.FM_8POINT)
    Fcv = Fcv / np.linalg.norm(Fcv)
    np.testing.assert_allclose(F * np.sign(np.sum(F * Fcv)), Fcv, atol=1e-6)
    assert np.abs(np.linalg.det(F)) < 1e-12
    np.testing.assert_allclose(epipolar_j(F, uv[0], uv[1]), 0.0, atol=1e-8)


def test_epipolar_distance_against_opencv_lines(rng):
    cams, s, X, uv = _scene(rng, 2, dist_scale=0.0)
    F = np.asarray(fundamental_matrix(cams[0], cams[1]))
    ua = np.asarray(uv[0]) + rng.normal(scale=3.0, size=(N_POINTS, 2))
    ub = np.asarray(uv[1]) + rng.normal(scale=3.0, size=(N_POINTS, 2))
    lb = cv2.computeCorrespondEpilines(ua[:, None], 1, F)[:, 0]  # lines in image b
    la = cv2.computeCorrespondEpilines(ub[:, None], 2, F)[:, 0]  # lines in image a
    db = np.abs(np.sum(lb[:, :2] * ub, 1) + lb[:, 2])
    da = np.abs(np.sum(la[:, :2] * ua, 1) + la[:, 2])
    np.testing.assert_allclose(epipolar_j(F, ua, ub), 0.5 * (da + db), rtol=1e-6)


def test_epipolar_distance_with_distortion(rng):
    cams, s, X, uv = _scene(rng, 2)
    F = fundamental_matrix(cams[0], cams[1])
    # raw distorted pixels do not satisfy the pinhole epipolar constraint; undistorted ones do
    assert float(jnp.max(epipolar_j(F, uv[0], uv[1]))) > 0.1
    np.testing.assert_allclose(
        epipolar_distance_undistorted(cams[0], cams[1], uv[0], uv[1]), 0.0, atol=1e-7
    )


# ------------------------------------------------------------------------------- cameras.json


def test_cameras_json_round_trip(tmp_path, rng):
    cams = [random_camera(rng) for _ in range(3)]
    path = tmp_path / "sub" / "cameras.json"
    save_cameras(path, cams, ["left", "right", "top"])
    assert [p.name for p in path.parent.iterdir()] == ["cameras.json"]  # no temp files left
    loaded, names = load_cameras(path, dtype=jnp.float64)
    assert names == ["left", "right", "top"]
    for a, b in zip(loaded, cams, strict=True):
        for f in ("K", "R", "t", "dist"):
            np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
        assert (a.width, a.height) == (b.width, b.height)
    # a stacked camera saves too; default names
    save_cameras(path, stack_cameras(cams))
    assert load_cameras(path)[1] == ["cam0", "cam1", "cam2"]
    # rvec instead of R, 4 distortion values
    data = json.loads(path.read_text())
    rvec, _ = cv2.Rodrigues(np.asarray(cams[1].R))
    entry = data["cameras"][1]
    del entry["R"]
    entry["rvec"] = rvec[:, 0].tolist()
    entry["dist"] = entry["dist"][:4]
    path.write_text(json.dumps(data))
    before = path.read_bytes()
    cam1 = load_cameras(path, dtype=jnp.float64)[0][1]
    assert path.read_bytes() == before
    np.testing.assert_allclose(cam1.R, cams[1].R, atol=1e-12)
    np.testing.assert_array_equal(cam1.dist[4], 0.0)


def _good_entry():
    return {
        "name": "c",
        "width": 640,
        "height": 480,
        "K": [[500, 0, 320], [0, 500, 240], [0, 0, 1]],
        "dist": [0, 0, 0, 0, 0],
        "R": np.eye(3).tolist(),
        "t": [0, 0, 1],
    }


@pytest.mark.parametrize(
    "mutate, pattern",
    [
        (lambda e: e.pop("K"), r"camera 'c': field 'K': missing"),
        (lambda e: e.update(K=[[500, 0], [0, 500]]), r"field 'K': expected shape \(3, 3\)"),
        (lambda e: e.update(K=[[-5, 0, 320], [0, 500, 240], [0, 0, 1]]), r"'K': focal"),
        (lambda e: e.update(K=[[5, 0, 320], [0, 5, 240], [1, 0, 1]]), r"'K': expected \[\["),
        (lambda e: e.update(dist=[0, 0, 0]), r"field 'dist': expected shape \(5,\)"),
        (lambda e: e.update(dist="none"), r"field 'dist': expected 5 numbers"),
        (lambda e: e.update(R=[[1, 0, 0], [0, 1, 0], [0, 0, 2]]), r"'R': expected a rotation"),
        (lambda e: e.update(rvec=[0, 0, 0]), r"exactly one of 'R'"),
        (lambda e: e.update(t=[0, 0, float("nan")]), r"field 't': contains non-finite"),
        (lambda e: e.update(t=[0, 0]), r"field 't': expected shape \(3,\)"),
        (lambda e: e.update(width=0), r"field 'width': expected a positive integer"),
        (lambda e: e.update(height=480.5), r"field 'height': expected a positive integer"),
        (lambda e: e.update(name=""), r"cameras\[0\]: field 'name'"),
    ],
)
def test_cameras_json_bad_field(tmp_path, mutate, pattern):
    entry = _good_entry()
    mutate(entry)
    path = tmp_path / "cameras.json"
    path.write_text(json.dumps({"version": 1, "cameras": [entry]}, allow_nan=True))
    with pytest.raises(CameraFileError, match=pattern) as info:
        load_cameras(path)
    assert str(path) in str(info.value)


def test_cameras_json_bad_file(tmp_path):
    path = tmp_path / "cameras.json"
    for text, pattern in (
        ("{", "not valid JSON"),
        ('{"version": 2, "cameras": []}', "version"),
        ('{"version": 1, "cameras": []}', "non-empty list"),
        ("[1]", r"cameras\[0\]: expected an object"),
        ('"cams"', "JSON object"),
    ):
        path.write_text(text)
        with pytest.raises(CameraFileError, match=pattern):
            load_cameras(path)
    e = _good_entry()
    path.write_text(json.dumps({"version": 1, "cameras": [e, e]}))
    with pytest.raises(CameraFileError, match="duplicate"):
        load_cameras(path)
    with pytest.raises(CameraFileError, match="cannot read"):
        load_cameras(tmp_path / "missing.json")
    with pytest.raises(ValueError, match="names"):
        save_cameras(
            path, [Camera(np.eye(3), np.eye(3), np.zeros(3), np.zeros(5), 4, 4)] * 2, ["a", "a"]
        )


def test_cameras_from_other_tools(tmp_path, rng):
    """Files of other tools load when their fields are OpenCV's: no version, OpenCV / Pose2Sim
    field names, cameras keyed by name, 8-term distortion with zero rational terms, TOML."""
    cam = random_camera(rng)
    K, dist = np.asarray(cam.K, float), np.asarray(cam.dist, float)
    rvec = cv2.Rodrigues(np.asarray(cam.R, float))[0]
    t = np.asarray(cam.t, float)
    X = rng.normal(size=(6, 3)) * 0.3 + np.array([0.0, 0.0, 0.0])
    want = cv2.projectPoints(X, rvec, t, K, dist)[0][:, 0]  # the independent oracle
    opencv_dump = {
        "left": {
            "camera_matrix": K.tolist(),
            "dist_coeffs": [dist.tolist() + [0.0, 0.0, 0.0]],  # 1x8 as cv2 returns it
            "rvec": rvec.tolist(),  # 3x1
            "tvec": t.reshape(3, 1).tolist(),
            "image_size": [int(cam.width), int(cam.height)],
        },
        "metadata": {"tool": "someone else's calibrator"},
    }
    toml = (
        "[cam_01]\nname = \"left\"\n"
        f"size = [ {float(cam.width)}, {float(cam.height)} ]\n"
        f"matrix = {K.tolist()}\n"
        f"distortions = {dist[:4].tolist()}\n"
        f"rotation = {rvec.ravel().tolist()}\n"
        f"translation = {t.tolist()}\n"
        "fisheye = false\n\n[metadata]\nadjusted = false\n"
    )
    cases = {"dump.json": json.dumps(opencv_dump), "calibration.toml": toml,
             "plain.json": json.dumps({"cameras": [{"name": "left", "width": cam.width,
                                        "height": cam.height, "K": K.tolist(),
                                        "dist": dist.tolist(), "R": np.asarray(cam.R).tolist(),
                                        "t": t.tolist()}]})}  # fmt: skip
    for fname, text in cases.items():
        path = tmp_path / fname
        path.write_text(text)
        cams, names = load_cameras(path, dtype=jnp.float64)
        assert names == ["left"], fname
        assert (cams[0].width, cams[0].height) == (cam.width, cam.height)
        k3 = dist[4] if fname != "calibration.toml" else 0.0
        want_f = want if k3 == dist[4] else cv2.projectPoints(
            X, rvec, t, K, np.r_[dist[:4], 0.0])[0][:, 0]
        np.testing.assert_allclose(project(cams[0], jnp.asarray(X)), want_f, atol=1e-6)


def test_cameras_from_other_tools_refused(tmp_path):
    path = tmp_path / "cams.json"
    e = _good_entry()
    e["dist"] = [0, 0, 0, 0, 0, 0.1, 0, 0]  # a rational term we do not model
    path.write_text(json.dumps([e]))
    with pytest.raises(CameraFileError, match="5-term"):
        load_cameras(path)
    path.write_bytes(b"\x89PNG\r\n\x1a\n\x00\xff\xfe")
    with pytest.raises(CameraFileError, match="not a text file"):
        load_cameras(path)
    e = _good_entry()
    e.pop("width")
    e["size"] = [640]
    path.write_text(json.dumps({"c": e}))
    with pytest.raises(CameraFileError, match=r"field 'size': expected \[width, height\]"):
        load_cameras(path)


def test_cameras_from_opencv_filestorage_and_by_content(tmp_path, rng):
    """Issue 36: OpenCV FileStorage files written by cv2.FileStorage itself (YAML and XML; one
    camera at the top level as OpenCV's calibration samples write it, and one map per
    camera), and an anipose / FreeMoCap calibration TOML or a cameras.json under a suffix
    that says nothing -- told apart by content. Oracle: cv2.projectPoints."""
    cams = [random_camera(rng) for _ in range(2)]
    X = rng.normal(size=(6, 3)) * 0.3
    want = []
    for c in cams:
        rvec = cv2.Rodrigues(np.asarray(c.R, float))[0]
        want.append(cv2.projectPoints(X, rvec, np.asarray(c.t, float), np.asarray(c.K, float),
                                      np.asarray(c.dist, float))[0][:, 0])

    def write_fs(path, per_camera):
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
        if per_camera:
            for i, c in enumerate(cams):
                fs.startWriteStruct(f"cam{i}", cv2.FileNode_MAP)
                fs.write("image_width", int(c.width))
                fs.write("image_height", int(c.height))
                fs.write("camera_matrix", np.asarray(c.K, float))
                fs.write("distortion_coefficients", np.asarray(c.dist, float).reshape(1, 5))
                fs.write("R", cv2.Rodrigues(np.asarray(c.R, float))[0])  # a 3x1 rvec
                fs.write("T", np.asarray(c.t, float).reshape(3, 1))
                fs.endWriteStruct()
        else:
            c = cams[0]
            fs.write("calibration_time", "today")
            fs.write("image_width", int(c.width))
            fs.write("image_height", int(c.height))
            fs.write("camera_matrix", np.asarray(c.K, float))
            fs.write("dist_coeffs", np.asarray(c.dist, float).reshape(5, 1))
            fs.write("R", np.asarray(c.R, float))
            fs.write("T", np.asarray(c.t, float).reshape(3, 1))
        fs.release()
        return path

    for suffix in (".yml", ".xml"):
        one = write_fs(tmp_path / f"left{suffix}", per_camera=False)
        got, names = load_cameras(one, dtype=jnp.float64)
        assert names == ["left"]
        np.testing.assert_allclose(project(got[0], jnp.asarray(X)), want[0], atol=1e-6)
        both = write_fs(tmp_path / f"rig{suffix}", per_camera=True)
        got, names = load_cameras(both, dtype=jnp.float64)
        assert names == ["cam0", "cam1"]
        for g, w in zip(got, want, strict=True):
            np.testing.assert_allclose(project(g, jnp.asarray(X)), w, atol=1e-6)
    # a FreeMoCap / anipose TOML and a cameras.json, both under a suffix that says nothing
    c = cams[1]
    rvec = cv2.Rodrigues(np.asarray(c.R, float))[0].ravel()
    toml = (f"[cam_0]\nname = \"0\"\nsize = [ {c.width}, {c.height} ]\n"
            f"matrix = {np.asarray(c.K).tolist()}\ndistortions = {np.asarray(c.dist).tolist()}\n"
            f"rotation = {rvec.tolist()}\ntranslation = {np.asarray(c.t).tolist()}\n\n"
            "[metadata]\nadjusted = false\nerror = 0.3\n")
    (tmp_path / "calib.cal").write_text(toml)
    got, names = load_cameras(tmp_path / "calib.cal", dtype=jnp.float64)
    assert names == ["0"]
    np.testing.assert_allclose(project(got[0], jnp.asarray(X)), want[1], atol=1e-6)
    save_cameras(tmp_path / "rig.json", cams)
    (tmp_path / "rig.cal").write_text((tmp_path / "rig.json").read_text())
    assert load_cameras(tmp_path / "rig.cal")[1] == ["cam0", "cam1"]
    (tmp_path / "notes.cal").write_text("a rig I calibrated on Tuesday\n")
    with pytest.raises(CameraFileError, match="not a camera file jaxmocap reads"):
        load_cameras(tmp_path / "notes.cal")
