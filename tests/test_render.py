"""Tests of the ray caster against independent oracles: brute-force ray marching, the pinhole
formula, cv2.projectPoints / cv2.undistortPoints + cv2.remap, and FK-posed surface points.

Images are small and every jitted function is compiled once per image size (cameras are
traced arguments), so the whole file stays within a few compilations.
"""

import functools

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap import render
from jaxmocap.body import (
    BOX,
    CAPSULE,
    CYLINDER,
    ELLIPSOID,
    SPHERE,
    KinematicChain,
    default_body,
    dof_index,
    make_body_model,
)
from jaxmocap.body.geometry import make_geometry
from jaxmocap.camera import look_at, stack_cameras, to_camera
from jaxmocap.garment import default_garment, garment_from_model

# ----------------------------------------------------------------------------- oracles

SIZES = {
    SPHERE: (0.1, 0.0, 0.0),
    CAPSULE: (0.05, 0.12, 0.0),
    CYLINDER: (0.06, 0.1, 0.0),
    BOX: (0.05, 0.08, 0.11),
    ELLIPSOID: (0.05, 0.09, 0.13),
}


def inside(kind, s, p):
    """Independent point-in-solid tests (NumPy)."""
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    if kind == SPHERE:
        return np.linalg.norm(p, axis=-1) <= s[0]
    if kind == CAPSULE:
        return np.sqrt(x * x + y * y + (z - np.clip(z, -s[1], s[1])) ** 2) <= s[0]
    if kind == CYLINDER:
        return (x * x + y * y <= s[0] ** 2) & (np.abs(z) <= s[1])
    if kind == BOX:
        return np.all(np.abs(p) <= s, axis=-1)
    return np.sum((p / s) ** 2, axis=-1) <= 1


def surface_samples(kind, s, n=4000, rng=None):
    """Dense surface points of a primitive (NumPy, geom frame): directions pushed onto the
    surface by bisection on the inside test (independent of the renderer's parametrisation)."""
    rng = rng or np.random.default_rng(1)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    lo, hi = np.zeros(n), np.full(n, 1.0)
    for _ in range(40):
        mid = (lo + hi) / 2
        ins = inside(kind, np.asarray(s), mid[:, None] * d)
        lo, hi = np.where(ins, mid, lo), np.where(ins, hi, mid)
    return lo[:, None] * d


# ----------------------------------------------------------------------------- primitives


@pytest.mark.parametrize("kind", [SPHERE, CAPSULE, CYLINDER, BOX, ELLIPSOID])
def test_primitive_entry_matches_ray_marching(kind, rng):
    s = np.asarray(SIZES[kind])
    n = 300
    o = rng.normal(size=(n, 3))
    o = o / np.linalg.norm(o, axis=1, keepdims=True) * 0.5
    d = rng.uniform(-0.15, 0.15, size=(n, 3)) - o
    # include rays parallel to the axes (the divisions the slab tests guard)
    d[:6] = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]]
    o[:6] = -0.5 * d[:6] + rng.uniform(-0.03, 0.03, size=(6, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    S = jnp.broadcast_to(jnp.asarray(s), (n, 3))
    t = np.asarray(render.intersect_kind(kind, S, jnp.asarray(o), jnp.asarray(d)))
    t_sel = render.intersect_kind(None, S, jnp.asarray(o), jnp.asarray(d), jnp.full(n, kind))
    np.testing.assert_array_equal(t, np.asarray(t_sel))

    step = 2e-4
    ts = np.arange(0.0, 1.0, step)
    ins = inside(kind, s, o[:, None] + ts[None, :, None] * d[:, None])
    brute_hit = ins.any(axis=1)
    hit = np.isfinite(t)
    assert not np.any(brute_hit & ~hit)
    assert hit[:6].all() and brute_hit.sum() > n // 4
    both = brute_hit & hit
    t_brute = ts[np.argmax(ins, axis=1)]
    np.testing.assert_array_less(np.abs(t[both] - t_brute[both]), step + 1e-9)
    # a hit the marcher missed can only be a grazing one
    p = o + np.where(hit, t, 0)[:, None] * d
    nrm = np.asarray(render.surface_normal(jnp.full(n, kind), S, jnp.asarray(p)))
    graze = hit & ~brute_hit
    assert np.all(np.abs(np.sum(nrm[graze] * d[graze], axis=1)) < 0.2)
    # the normal points out: just outside along +n, just inside along -n, facing the ray
    assert not inside(kind, s, p[hit] + 1e-5 * nrm[hit]).any()
    assert inside(kind, s, p[hit] - 1e-5 * nrm[hit]).all()
    assert np.all(np.sum(nrm[hit] * d[hit], axis=1) <= 1e-12)


# ----------------------------------------------------------------------------- analytic scene

W, H, F = 121, 91, 200.0  # odd sizes: the principal point (60, 45) is a pixel centre


def rot(axis, angle):
    return cv2.Rodrigues(np.asarray(axis, float) * angle)[0]


def pose(R, p):
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R, p
    return T


SCENE = [  # name, kind, rotation, centre, size, rgb
    ("ball", SPHERE, np.eye(3), (0.0, 0.0, 0.0), (0.15, 0, 0), (0.9, 0.1, 0.1)),
    ("capsule", CAPSULE, np.eye(3), (0.0, 0.45, 0.0), (0.05, 0.1, 0), (0.1, 0.9, 0.1)),
    ("box", BOX, rot((0, 0, 1), 0.5), (0.0, -0.5, 0.2), (0.06, 0.08, 0.1), (0.1, 0.1, 0.9)),
    ("egg", ELLIPSOID, rot((1, 1, 0), 0.7), (0.0, -0.5, -0.25), (0.05, 0.1, 0.15), (0.9, 0.9, 0)),
    ("can", CYLINDER, rot((1, 0, 0), 1.0), (0.0, 0.45, -0.35), (0.05, 0.08, 0), (0, 0.9, 0.9)),
]


@functools.cache
def scene_model():
    chain = KinematicChain(
        parents=[-1],
        joint_origin=np.eye(4)[None],
        joint_axis=np.zeros((1, 3)),
        joint_type=[0],
        dof_index=[-1],
        lower=np.full(6, -np.inf),
        upper=np.full(6, np.inf),
        link_names=("base",),
        dof_names=("tx", "ty", "tz", "rx", "ry", "rz"),
    )
    rows = [
        dict(name=n, link=0, kind=k, pose=pose(R, c), size=s, rgba=(*rgb, 1.0))
        for n, k, R, c, s, rgb in SCENE
    ]
    return make_body_model(chain, make_geometry(rows))


def scene_camera(eye=(3.0, 0.0, 0.0)):
    return look_at(eye, (0.0, 0.0, 0.0), width=W, height=H, fx=F)


@functools.cache
def scene_render():
    model = scene_model()
    garment = garment_from_model(model, skin_geoms=(), parts="all")
    return jax.jit(lambda q, cam: render.render_ids(model, garment, q, cam)), garment


def cv2_project(cam, X):
    rvec = cv2.Rodrigues(np.asarray(cam.R))[0]
    uv, _ = cv2.projectPoints(
        np.asarray(X, float).reshape(-1, 1, 3), rvec, np.asarray(cam.t, float),
        np.asarray(cam.K), np.asarray(cam.dist),
    )  # fmt: skip
    return uv.reshape(-1, 2)


def test_scene_against_pinhole_and_opencv():
    fn, garment = scene_render()
    cam = scene_camera()
    hits = jax.tree.map(np.asarray, fn(jnp.zeros(6), cam))
    assert hits.geom.shape == (H, W) and hits.geom.dtype == np.int32

    # sphere on the optical axis: silhouette radius R = f r / sqrt(D^2 - r^2) (pinhole)
    r, D = 0.15, 3.0
    R_px = F * r / np.sqrt(D * D - r * r)
    ball = hits.geom == 0
    assert abs(np.sqrt(ball.sum() / np.pi) - R_px) < 0.3
    assert ball[45].sum() == 2 * int(np.floor(R_px)) + 1
    # its depth at the principal point is D - r, and the normal faces the camera
    assert hits.depth[45, 60] == pytest.approx(D - r, abs=1e-9)
    np.testing.assert_allclose(hits.normal[45, 60], [1, 0, 0], atol=1e-9)

    # capsule: the ray through the projected axis point hits at |C - c| - r from the camera
    c = np.array([0.0, 0.45, 0.0])
    u, v = cv2_project(cam, c[None])[0]
    assert (u, v) == pytest.approx((90.0, 45.0))
    d = c - np.array([3.0, 0, 0])
    t_exp = np.linalg.norm(d) - 0.05
    assert hits.t[45, 90] == pytest.approx(t_exp, abs=1e-9)
    assert hits.depth[45, 90] == pytest.approx(t_exp * 3.0 / np.linalg.norm(d), abs=1e-9)

    # every geom: projected centre lands in its own pixels, and the silhouette's bbox matches
    # the cv2.projectPoints bbox of dense surface samples within a pixel
    for i, (_, kind, Rg, centre, size, _) in enumerate(SCENE):
        uc = np.round(cv2_project(cam, np.asarray(centre)[None])[0]).astype(int)
        assert hits.geom[uc[1], uc[0]] == i
        X = surface_samples(kind, size) @ Rg.T + np.asarray(centre)
        uv = cv2_project(cam, X)
        ys, xs = np.nonzero(hits.geom == i)
        np.testing.assert_array_less(
            np.abs([xs.min() - uv[:, 0].min(), xs.max() - uv[:, 0].max(),
                    ys.min() - uv[:, 1].min(), ys.max() - uv[:, 1].max()]), 1.0,
        )  # fmt: skip
        # patches: each geom is one patch of its own colour
        assert np.all(hits.patch[hits.geom == i] == i + 1)
    # depth is the camera z of the hit point; normals are unit, facing the camera
    fg = ~hits.background
    z = np.asarray(to_camera(cam, jnp.asarray(hits.point[fg])))[:, 2]
    np.testing.assert_allclose(hits.depth[fg], z, atol=1e-9)
    np.testing.assert_allclose(np.linalg.norm(hits.normal[fg], axis=-1), 1, atol=1e-9)
    assert np.all(hits.depth[~fg] == np.inf) and np.all(hits.patch[~fg] == 0)
    assert garment.n_colours == len(SCENE)


def test_traced_kinds_match_static_kinds():
    """A model passed as a jit argument (kinds traced: every primitive evaluated and selected)
    renders exactly as the closed-over model (kinds grouped statically)."""
    fn, garment = scene_render()
    cam = scene_camera((2.5, 1.0, 0.8))
    static = fn(jnp.zeros(6), cam)
    traced = jax.jit(render.render_ids)(scene_model(), garment, jnp.zeros(6), cam)
    np.testing.assert_array_equal(np.asarray(static.geom), np.asarray(traced.geom))
    np.testing.assert_allclose(np.asarray(static.depth), np.asarray(traced.depth), atol=1e-12)


def test_shading_lambert_illuminant_background_noise(rng):
    model = scene_model()
    garment = garment_from_model(model, skin_geoms=(), parts="all")
    cam = scene_camera()
    light = render.Lighting(
        ambient=0.1,
        directions=jnp.asarray([[1.0, 0.0, 0.0]]),
        dir_intensity=jnp.asarray([0.9]),
        positions=jnp.asarray([[3.0, 0.0, 1.0]]),
        point_intensity=jnp.asarray([2.0]),
        illuminant=jnp.diag(jnp.asarray([1.0, 0.7, 0.4])),
        intensity=0.8,
    )
    bg = rng.integers(0, 256, size=(H, W, 3), dtype=np.uint8)

    @jax.jit
    def shade(q, key, sigma):
        return render.render_rgb(
            model, garment, q, cam, jnp.asarray(bg), light, gamma=2.0, noise_sigma=sigma,
            key=key,
        )  # fmt: skip

    img, hits = jax.tree.map(np.asarray, shade(jnp.zeros(6), jax.random.key(0), 0.0))
    fg = ~hits.background
    np.testing.assert_array_equal(img[~fg], bg[~fg])
    # oracle: the ball's normals from the analytic centre, Lambert + inverse-square point light
    ball = hits.geom == 0
    x = hits.point[ball]
    n = x / np.linalg.norm(x, axis=-1, keepdims=True)
    to_l = np.array([3.0, 0.0, 1.0]) - x
    dist = np.linalg.norm(to_l, axis=-1)
    lit = 0.1 + 0.9 * np.maximum(n[:, 0], 0)
    lit += 2.0 * np.maximum(np.sum(n * to_l, -1) / dist, 0) / dist**2
    lin = 0.8 * np.array([1.0, 0.7, 0.4]) * np.array(SCENE[0][5]) * lit[:, None]
    expect = np.round(np.clip(lin, 0, 1) ** 0.5 * 255)
    np.testing.assert_allclose(img[ball], expect, atol=1)
    # Gaussian sensor noise with the requested standard deviation (fraction of 255)
    noisy, _ = shade(jnp.zeros(6), jax.random.key(1), 0.03)
    diff = (np.asarray(noisy, float) - img)[~fg] / 255
    assert np.std(diff) == pytest.approx(0.03, rel=0.1) and abs(np.mean(diff)) < 0.003


# ----------------------------------------------------------------------------- the body

BW, BH = 96, 72


@functools.cache
def body_render():
    model, garment = default_body(), default_garment()
    return jax.jit(lambda q, cam: render.render_ids(model, garment, q, cam))


def body_pose(seed=0, scale=0.5):
    model = default_body()
    q = np.zeros(model.n_dof)
    q[2] = 1.0
    q[6:] = np.random.default_rng(seed).uniform(-scale, scale, model.n_dof - 6)
    q[dof_index(model, ["l_shoulder_x"])] = 0.6
    q[dof_index(model, ["r_shoulder_x"])] = -0.5
    q[dof_index(model, ["l_elbow", "r_elbow"])] = [-0.8, -1.0]
    return jnp.asarray(q)


def body_camera(eye=(2.6, 0.8, 1.6), dist=None):
    return look_at(eye, (0.0, 0.0, 1.25), width=BW, height=BH, fx=160.0, dist=dist)


DIST = jnp.asarray([-0.8, 0.5, 0.004, -0.003, 0.0])


def test_patch_ids_match_fk_surface_points():
    """A ray cast through the cv2-projected (distorted) position of a patch's FK-posed surface
    point hits that very point when it is visible, and reports that patch; the pixel grid
    agrees too wherever the rendered depth shows the point."""
    model, garment = default_body(), default_garment()
    q = body_pose(0)
    cam = body_camera(dist=DIST)
    points = jax.jit(lambda q: render.shirt_points(model, garment, q))
    pts, valid = jax.tree.map(np.asarray, points(q))
    patch = np.repeat(np.arange(1, garment.n_patches + 1), pts.shape[0] // garment.n_patches)
    uv = cv2_project(cam, pts)
    cast = jax.jit(lambda q, cam, uv: render.render_uv(model, garment, q, cam, uv))
    hits = jax.tree.map(np.asarray, cast(q, cam, jnp.asarray(uv)))
    centre = -np.asarray(cam.R).T @ np.asarray(cam.t)
    visible = valid & (np.abs(hits.t - np.linalg.norm(pts - centre, axis=-1)) < 1e-6)
    assert visible.sum() > 400 and len(np.unique(patch[visible])) >= 14
    np.testing.assert_allclose(hits.point[visible], pts[visible], atol=1e-6)
    assert np.mean(hits.patch[visible] == patch[visible]) > 0.99
    # occluded samples are hidden behind something nearer
    assert np.all(
        hits.t[valid & ~visible] < np.linalg.norm(pts - centre, axis=-1)[valid & ~visible]
    )
    # the image: a visible point whose nearest pixel lies inside a uniform 3x3 block of
    # patch ids (away from patch borders and silhouettes) is shown with its own patch
    image = np.asarray(body_render()(q, cam).patch)
    px = np.round(uv[visible]).astype(int)
    inside = (px[:, 0] >= 1) & (px[:, 0] < BW - 1) & (px[:, 1] >= 1) & (px[:, 1] < BH - 1)
    px, expect = px[inside], patch[visible][inside]
    block = np.stack(
        [image[px[:, 1] + dy, px[:, 0] + dx] for dy in (-1, 0, 1) for dx in (-1, 0, 1)]
    )
    interior = np.all(block == block[4], axis=0)
    assert interior.sum() > 50
    assert np.mean(block[4, interior] == expect[interior]) > 0.98


def test_distortion_matches_undistorted_render_remapped():
    """Rendering through a distorted lens == rendering the ideal (distortion-free) camera at
    the positions cv2.undistortPoints gives for every pixel (exactly: the same rays), and ==
    the ideal image warped with cv2.remap (nearest neighbour, up to boundary pixels)."""
    fn = body_render()
    q = body_pose(1)
    target = (0.0, 0.35, 1.0)  # the body off-centre, where the distortion is strong
    cam = look_at((2.6, 0.8, 1.6), target, width=BW, height=BH, fx=160.0, dist=DIST)
    ideal_cam = look_at((2.6, 0.8, 1.6), target, width=BW, height=BH, fx=160.0)
    distorted = jax.tree.map(np.asarray, fn(q, cam))
    ideal = np.asarray(fn(q, ideal_cam).patch)
    uu, vv = np.meshgrid(np.arange(BW, dtype=float), np.arange(BH, dtype=float))
    pts = np.stack([uu, vv], -1).reshape(-1, 1, 2)
    K, dist = np.asarray(cam.K), np.asarray(cam.dist)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-14)
    und = cv2.undistortPoints(pts, K, dist, R=None, P=K, criteria=crit).reshape(BH, BW, 2)
    assert np.abs(und - np.stack([uu, vv], -1)).max() > 4  # a strong lens
    model, garment = default_body(), default_garment()
    same_rays = render.render_uv(model, garment, q, ideal_cam, jnp.asarray(und))
    assert np.mean(np.asarray(same_rays.patch) == distorted.patch) > 0.998
    fg = ~distorted.background
    np.testing.assert_allclose(np.asarray(same_rays.depth)[fg], distorted.depth[fg], atol=1e-6)
    maps = und.astype(np.float32)
    remapped = cv2.remap(ideal.astype(np.float32), maps[..., 0], maps[..., 1], cv2.INTER_NEAREST)
    fg = (distorted.patch > 0) | (remapped > 0)
    agree_remap = np.mean(distorted.patch[fg] == remapped.astype(int)[fg])
    assert agree_remap > 0.88 and agree_remap > np.mean(distorted.patch[fg] == ideal[fg]) + 0.03


def test_jit_vmap_over_poses_and_cameras_and_crop():
    fn = body_render()
    qs = jnp.stack([body_pose(2), body_pose(3)])
    cams = stack_cameras([body_camera(), body_camera((-2.4, -1.0, 1.5), dist=DIST)])
    batched = jax.jit(jax.vmap(jax.vmap(fn, (None, 0)), (0, None)))(qs, cams)
    assert batched.patch.shape == (2, 2, BH, BW)
    for i in range(2):
        for j, cam in enumerate([body_camera(), body_camera((-2.4, -1.0, 1.5), dist=DIST)]):
            single = fn(qs[i], cam)
            np.testing.assert_array_equal(np.asarray(batched.patch[i, j]), single.patch)
            np.testing.assert_allclose(batched.depth[i, j], single.depth, atol=1e-9)
    # a static crop is the same window of the full image
    model, garment = default_body(), default_garment()
    crop = render.render_ids(model, garment, qs[0], body_camera(), crop=(30, 10, 40, 50))
    np.testing.assert_array_equal(
        np.asarray(crop.patch), np.asarray(batched.patch[0, 0, 10:60, 30:70])
    )


# ----------------------------------------------------------------------------- tiny maps


def test_tiny_map_normalisation():
    model, garment = default_body(), default_garment()
    tiny = jax.jit(lambda q, cam: render.tiny_hits(model, garment, q, cam))
    q = body_pose(4, scale=0.3)
    (h0, w0) = tiny(q, body_camera())
    m0 = np.asarray(h0.colour)
    assert m0.shape == (render.TINY_SIZE, render.TINY_SIZE)
    shirt = m0 > 0
    # the shirt fills the square window up to the margin: touches both ends of the long axis
    rows, cols = np.nonzero(shirt)
    span = max(rows.max() - rows.min(), cols.max() - cols.min()) + 1
    assert 34 <= span <= 38 and shirt.mean() > 0.2
    # moving the body in the image (panning the camera about its centre) and changing its
    # scale (moving the camera along its line of sight) leave the tiny map nearly unchanged
    eye, target = np.array([2.6, 0.8, 1.6]), np.array([0.0, 0.0, 1.25])
    panned = look_at(eye, (0.0, -0.25, 1.1), width=BW, height=BH, fx=160.0)
    m1 = np.asarray(tiny(q, panned)[0].colour)
    m2 = np.asarray(tiny(q, body_camera(tuple(target + 1.5 * (eye - target))))[0].colour)
    for m in (m1, m2):
        fg = (m0 > 0) | (m > 0)
        assert np.mean(m0[fg] == m[fg]) > 0.88
    # a full render, cropped and resized like a classified camera image, gives the same map
    full = np.asarray(body_render()(q, body_camera()).colour)
    win = render.window_from_mask(jnp.asarray(full > 0))
    np.testing.assert_allclose(np.asarray(win), np.asarray(w0), atol=2.0)
    resampled = np.asarray(render.resample_ids(jnp.asarray(full), win))
    fg = (m0 > 0) | (resampled > 0)
    assert np.mean(m0[fg] == resampled[fg]) > 0.8
    # the batched database build equals per-pose maps (lax.map over padded chunks)
    q_moved = q.at[:3].add(jnp.asarray([0.0, 0.25, 0.1]))
    qs = jnp.stack([q, q_moved, body_pose(5, 0.3)])
    maps = render.tiny_id_maps(model, garment, qs, body_camera(), chunk=2)
    assert maps.dtype == jnp.uint8 and maps.shape == (3, 40, 40)
    np.testing.assert_array_equal(np.asarray(maps[0]), m0)
    np.testing.assert_array_equal(
        np.asarray(maps[1]), np.asarray(tiny(q_moved, body_camera())[0].colour)
    )
