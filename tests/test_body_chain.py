"""Tests of jaxmocap.body: FK vs pytorch-kinematics and MuJoCo, transforms, geometry, keypoints.

Oracles: pytorch-kinematics ``forward_kinematics`` (float64) on the bundled model, pybullet's
``humanoid.urdf`` and its MJCF ``humanoid.xml``; MuJoCo's ``mj_kinematics`` (body and geom
poses) for the MJCF conversion; SciPy rotations; central finite differences for gradients.
"""

import xml.etree.ElementTree as ET
from pathlib import Path

import equinox as eqx
import jax
import jax.numpy as jnp
import mujoco
import numpy as np
import pybullet_data
import pytest
import pytorch_kinematics as pk
import torch
from scipy.spatial.transform import Rotation

from jaxmocap import body, rotations
from jaxmocap.body.mjcf import compile_mjcf, flatten_to_urdf
from jaxmocap.body.urdf import prepare_urdf, read_urdf_text

DATA = Path(pybullet_data.getDataPath())
HUMANOID_URDF = DATA / "humanoid" / "humanoid.urdf"
HUMANOID_MJCF = DATA / "mjcf" / "humanoid.xml"

fk_batch = jax.jit(jax.vmap(body.fk, in_axes=(None, 0)))
fk_one = jax.jit(body.fk)
N_POSES = {"bundled": 10_000, "humanoid_urdf": 1_000, "humanoid_mjcf": 1_000}  # shared compiles


def kp_one(model, q):
    return body.keypoints_from_transforms(model, fk_one(model.chain, q))


def random_q(chain, n, rng, root=False):
    """Random poses inside the joint limits (unbounded joints in [-pi, pi])."""
    lo = np.where(np.isfinite(chain.lower), chain.lower, -np.pi)[6:]
    hi = np.where(np.isfinite(chain.upper), chain.upper, np.pi)[6:]
    th = rng.uniform(lo, hi, size=(n, lo.shape[0]))
    rt = rng.normal(size=(n, 6)) if root else np.zeros((n, 6))
    return np.concatenate([rt, th], axis=1)


@pytest.fixture(scope="module")
def models():
    return {
        "bundled": body.default_body(),
        "humanoid_urdf": body.load_urdf(HUMANOID_URDF),
        "humanoid_mjcf": body.load_mjcf(HUMANOID_MJCF),
    }


def pk_chain(name):
    if name == "bundled":
        text = prepare_urdf(read_urdf_text(body.model.DEFAULT_URDF))[1]
    elif name == "humanoid_urdf":
        text = prepare_urdf(read_urdf_text(HUMANOID_URDF))[1]
    else:
        text = flatten_to_urdf(compile_mjcf(HUMANOID_MJCF))[0]
    return pk.build_chain_from_urdf(text).to(dtype=torch.float64)


# ------------------------------------------------------------------ FK vs oracles
@pytest.mark.parametrize("name", ["bundled", "humanoid_urdf", "humanoid_mjcf"])
def test_fk_matches_pytorch_kinematics(models, name, rng):
    model = models[name]
    chain = pk_chain(name)
    assert list(chain.get_joint_parameter_names()) == list(model.chain.dof_names[6:])
    q = random_q(model.chain, N_POSES[name], rng)
    ours = np.asarray(fk_batch(model.chain, jnp.asarray(q)))
    ref = chain.forward_kinematics(torch.tensor(q[:, 6:]))
    assert set(ref) == set(model.chain.link_names)
    for i, link in enumerate(model.chain.link_names):
        m = ref[link].get_matrix().numpy()
        np.testing.assert_allclose(ours[:, i, :3, 3], m[:, :3, 3], atol=1e-5, err_msg=link)
        np.testing.assert_allclose(ours[:, i, :3, :3], m[:, :3, :3], atol=1e-5, err_msg=link)
    assert np.all(ours[:, :, 3] == np.array([0.0, 0.0, 0.0, 1.0]))


def mujoco_qpos(m, model, q):
    """MuJoCo qpos for our q (free root, hinges/slides by name, balls as Rx Ry Rz)."""
    qpos = np.zeros(m.nq)
    for j in range(m.njnt):
        a, name, jt = m.jnt_qposadr[j], m.joint(j).name, m.jnt_type[j]
        if jt == mujoco.mjtJoint.mjJNT_FREE:
            qpos[a : a + 3] = q[0:3]
            qpos[a + 3 : a + 7] = np.roll(Rotation.from_rotvec(q[3:6]).as_quat(), 1)
        elif jt == mujoco.mjtJoint.mjJNT_BALL:
            angles = q[body.dof_index(model, [f"{name}_{a}" for a in "xyz"])]
            qpos[a : a + 4] = np.roll(Rotation.from_euler("XYZ", angles).as_quat(), 1)
        else:
            qpos[a] = q[body.dof_index(model, name)[0]]
    return qpos


def check_against_mujoco(m, model, qs, root_is_world):
    d = mujoco.MjData(m)
    for q in qs:
        d.qpos[:] = mujoco_qpos(m, model, q)
        mujoco.mj_kinematics(m, d)
        T = np.asarray(fk_one(model.chain, jnp.asarray(q)))
        world = T[0] if root_is_world else np.eye(4)
        for b in range(1, m.nbody):
            Tb = np.linalg.solve(world, T[model.chain.link_index(m.body(b).name)])
            np.testing.assert_allclose(Tb[:3, 3], d.xpos[b], atol=1e-9)
            np.testing.assert_allclose(Tb[:3, :3], d.xmat[b].reshape(3, 3), atol=1e-9)
        G = np.linalg.solve(world, np.asarray(body.geom_world_poses(model, jnp.asarray(T))))
        gids = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, n) for n in model.geometry.names]
        np.testing.assert_allclose(G[:, :3, 3], d.geom_xpos[gids], atol=1e-9)
        np.testing.assert_allclose(G[:, :3, :3], d.geom_xmat[gids].reshape(-1, 3, 3), atol=1e-9)


def test_mjcf_humanoid_matches_mujoco(models, rng):
    """The flattening reproduces MuJoCo exactly, including joints with a non-zero pos."""
    m = compile_mjcf(HUMANOID_MJCF)
    assert np.any(m.jnt_pos != 0) and np.any(m.body_jntnum > 1)  # the pitfalls are present
    model = models["humanoid_mjcf"]
    check_against_mujoco(m, model, random_q(model.chain, 5, rng, root=True), True)
    # pytorch-kinematics' own MJCF loader cannot read it (why we flatten).
    with pytest.raises(ValueError, match="composite"):
        pk.build_chain_from_mjcf(HUMANOID_MJCF.read_text())


TOY_MJCF = """<mujoco><compiler angle="radian"/><worldbody>
  <geom name="floor" type="plane" size="5 5 .1"/>
  <body name="base" pos="0.1 0.2 1.0"><freejoint name="root"/>
    <geom name="g0" type="box" size=".1 .2 .3" rgba="1 0 0 1"/>
    <body name="a" pos="0 0 .3" quat="0.9 0.1 -0.3 0.2">
      <joint name="ball" type="ball" pos=".05 0 .02"/>
      <geom name="g1" type="capsule" fromto="0 0 0 .1 .2 .3" size=".04"/>
      <body name="b" pos=".1 .2 .3" euler=".3 -.2 .5">
        <joint name="h1" type="hinge" axis="1 1 0" pos="0 .03 0" range="-1 1"/>
        <joint name="s1" type="slide" axis="0 0 1" pos=".02 0 0" range="-.1 .1"/>
        <joint name="h2" type="hinge" axis="0 1 0" pos="0 0 .04"/>
        <geom name="g2" type="ellipsoid" size=".05 .06 .07" pos=".01 .02 .03" material="nope"/>
        <geom name="g3" type="cylinder" size=".02 .05" euler="1 0 0"/>
      </body>
    </body>
  </body></worldbody></mujoco>"""


def test_mjcf_ball_slide_free_root_match_mujoco(tmp_path, rng):
    path = tmp_path / "toy.xml"
    path.write_text(TOY_MJCF)
    model = body.load_mjcf(path)
    assert model.chain.dof_names[6:] == ("ball_x", "ball_y", "ball_z", "h1", "s1", "h2")
    assert model.chain.link_names[0] == "base"
    assert model.geometry.names == ("g0", "g1", "g2", "g3")  # floor plane skipped
    np.testing.assert_allclose(model.geometry.rgba[0], [1, 0, 0, 1])
    q = random_q(model.chain, 4, rng, root=True)
    check_against_mujoco(compile_mjcf(path), model, q, False)


# ------------------------------------------------------------------ root and transforms
def test_root_composes_and_so3_exp(models, rng):
    model = models["bundled"]
    q = random_q(model.chain, 1, rng, root=True)[0]
    q0 = q.copy()
    q0[:6] = 0.0
    T, T0 = (np.asarray(fk_one(model.chain, jnp.asarray(x))) for x in (q, q0))
    root = np.eye(4)
    root[:3, :3] = Rotation.from_rotvec(q[3:6]).as_matrix()
    root[:3, 3] = q[0:3]
    np.testing.assert_allclose(T, root @ T0, atol=1e-12)
    w = np.concatenate([rng.normal(size=(20, 3)), 1e-9 * rng.normal(size=(5, 3))])
    np.testing.assert_allclose(
        body.so3_exp(jnp.asarray(w)), Rotation.from_rotvec(w).as_matrix(), atol=1e-12
    )


def test_vmap_jit_grad(models, rng):
    model = models["bundled"]
    q = random_q(model.chain, N_POSES["bundled"], rng, root=True)
    out = fk_batch(model.chain, jnp.asarray(q))
    assert out.shape == (10_000, model.chain.n_links, 4, 4)
    for k in (0, 4_321, 9_999):
        np.testing.assert_allclose(out[k], fk_one(model.chain, jnp.asarray(q[k])), atol=1e-12)

    w = rng.normal(size=(len(model.keypoint_names), 3))

    def loss(x):
        t = body.fk(model.chain, x)
        return jnp.sum(w * body.keypoints_from_transforms(model, t)) + jnp.sum(t[:, :3, :3])

    def loss_np(t):  # the same loss of a batch of fk outputs, in NumPy
        tr = np.asarray(t)[:, :, :3, :3].sum((1, 2, 3))
        t = np.asarray(t)[:, np.asarray(model.keypoint_link)]
        kp = np.einsum("bkij,kj->bki", t[..., :3, :3], model.keypoint_offset) + t[..., :3, 3]
        return np.einsum("bki,ki->b", kp, w) + tr

    def central_differences(x):  # 2 n_dof perturbed poses, padded to the compiled batch size
        eps, n = 1e-6, model.n_dof
        xs = np.zeros((N_POSES["bundled"], n))
        xs[: 2 * n] = x + eps * np.concatenate([np.eye(n), -np.eye(n)])
        v = loss_np(fk_batch(model.chain, jnp.asarray(xs))[: 2 * n])
        return (v[:n] - v[n:]) / (2 * eps)

    g = jax.jit(jax.grad(loss))
    np.testing.assert_allclose(g(jnp.asarray(q[7])), central_differences(q[7]), atol=1e-6)
    np.testing.assert_allclose(loss(jnp.asarray(q[7])), loss_np(out[7:8])[0], rtol=1e-12)
    # at q = 0 (zero rotation vector: the Taylor branch) gradients are finite and right
    g0 = g(jnp.zeros(model.n_dof))
    assert np.all(np.isfinite(g0))
    np.testing.assert_allclose(g0, central_differences(np.zeros(model.n_dof)), atol=1e-6)
    # d exp([w]) / dw_k at w = 0 is the generator [e_k]_x
    jac = jax.jacfwd(body.so3_exp)(jnp.zeros(3))
    for k in range(3):
        np.testing.assert_allclose(jac[:, :, k], rotations.skew(jnp.eye(3)[k]), atol=1e-15)


def test_dtype_follows_input(models):
    model = models["bundled"]
    q32 = jax.ShapeDtypeStruct((model.n_dof,), jnp.float32)
    assert jax.eval_shape(body.fk, model.chain, q32).dtype == jnp.float32
    assert jax.eval_shape(body.keypoints, model, q32).dtype == jnp.float32
    t32 = jax.ShapeDtypeStruct((model.chain.n_links, 4, 4), jnp.float32)
    assert jax.eval_shape(body.geom_world_poses, model, t32).dtype == jnp.float32


# ------------------------------------------------------------------ URDF conversions
def test_humanoid_urdf_spherical_scale_and_up(models, rng):
    model = models["humanoid_urdf"]
    raw = HUMANOID_URDF.read_bytes()
    assert raw.endswith(b"\x00") and b'type="spherical"' in raw
    assert {"chest_x", "chest_y", "chest_z", "left_elbow"} <= set(model.chain.dof_names)
    metric = body.load_urdf(HUMANOID_URDF, scale=0.25, up="y")
    q = jnp.asarray(random_q(model.chain, 8, rng))
    a, b = np.asarray(fk_batch(model.chain, q)), np.asarray(fk_batch(metric.chain, q))
    up = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])
    np.testing.assert_allclose(b[..., :3, 3], 0.25 * a[..., :3, 3] @ up.T, atol=1e-12)
    rest = fk_one(metric.chain, jnp.zeros(metric.n_dof))
    head, foot = (rest[metric.chain.link_index(n), 2, 3] for n in ("neck", "left_ankle"))
    assert 1.0 < head - foot < 2.0  # a human standing up in metres, +z up
    np.testing.assert_allclose(metric.geometry.size, 0.25 * model.geometry.size)


def test_urdf_geometry_matches_file(models):
    """Every <visual> of the bundled file, with capsules pytorch-kinematics drops."""
    model = models["bundled"]
    root = ET.parse(body.model.DEFAULT_URDF).getroot()
    mats = {m.get("name"): m.find("color").get("rgba") for m in root.findall("material")}
    visuals = [(link.get("name"), v) for link in root.findall("link") for v in link.iter("visual")]
    assert model.geometry.n_geoms == len(visuals) == 12
    kinds = {"sphere": 0, "capsule": 1, "cylinder": 2, "box": 3, "ellipsoid": 4}
    for i, (link, v) in enumerate(visuals):
        g = v.find("geometry")[0]
        assert model.geometry.names[i] == v.get("name")
        assert model.chain.link_names[int(model.geometry.link[i])] == link
        assert int(model.geometry.kind[i]) == kinds[g.tag]
        rgba = [float(x) for x in mats[v.find("material").get("name")].split()]
        np.testing.assert_allclose(model.geometry.rgba[i], rgba)
        xyz = [float(x) for x in v.find("origin").get("xyz").split()]
        np.testing.assert_allclose(model.geometry.pose[i, :3, 3], xyz)
        if g.tag == "capsule":
            r, h = float(g.get("radius")), float(g.get("length")) / 2
            np.testing.assert_allclose(model.geometry.size[i], [r, h, 0.0])
    sh = model.geometry.names.index("shoulders")  # capsule rotated to lie along y
    np.testing.assert_allclose(model.geometry.pose[sh, :3, 2], [0, -1, 0], atol=1e-12)
    skin = {n for n, c in zip(model.geometry.names, model.geometry.rgba, strict=True)
            if np.allclose(c, model.geometry.rgba[model.geometry.names.index("head")])}  # fmt: skip
    assert skin == {"head", "neck", "l_hand", "r_hand"}
    # pybullet humanoid: collision geometry (no visuals), capsules kept
    hum = models["humanoid_urdf"]
    assert hum.geometry.n_geoms == 15
    assert np.bincount(np.asarray(hum.geometry.kind), minlength=5).tolist() == [5, 8, 0, 2, 0]
    i = hum.geometry.names.index("right_hip_0")
    np.testing.assert_allclose(hum.geometry.size[i], [0.22, 0.6, 0.0])
    vis = pk.build_chain_from_urdf(read_urdf_text(HUMANOID_URDF).replace("spherical", "fixed"))
    assert vis.find_link("right_hip").visuals[0].geom_type is None  # what pk drops


def test_limits_match_file(models):
    model = models["bundled"]
    root = ET.parse(body.model.DEFAULT_URDF).getroot()
    for j in root.findall("joint"):
        lim = j.find("limit")
        i = body.dof_index(model, j.get("name"))[0]
        assert float(model.chain.lower[i]) == float(lim.get("lower"))
        assert float(model.chain.upper[i]) == float(lim.get("upper"))
    assert np.all(np.isinf(model.chain.lower[:6])) and np.all(np.isinf(model.chain.upper[:6]))
    q = jnp.full((model.n_dof,), 10.0)
    assert np.all(body.clip_to_limits(model, q)[6:] == model.chain.upper[6:])


# ------------------------------------------------------------------ body model helpers
def test_bundled_keypoints_sane(models):
    model = models["bundled"]
    assert model.keypoint_names == body.KEYPOINT_NAMES
    kp = dict(zip(model.keypoint_names, np.asarray(kp_one(model, jnp.zeros(24))),
                  strict=True))  # fmt: skip
    np.testing.assert_allclose(kp["l_shoulder"] - kp["r_shoulder"], [0, 0.36, 0], atol=1e-12)
    np.testing.assert_allclose(kp["l_shoulder"][2] - kp["pelvis"][2], 0.50)
    np.testing.assert_allclose(np.linalg.norm(kp["l_wrist"] - kp["l_shoulder"]), 0.56)
    np.testing.assert_allclose(kp["l_hand"] - kp["l_wrist"], [0, 0, -0.09], atol=1e-12)
    assert kp["pelvis"][2] < kp["chest"][2] < kp["neck"][2] < kp["head"][2]
    for s in "lr":  # arms hang straight down at rest
        np.testing.assert_allclose((kp[f"{s}_elbow"] - kp[f"{s}_shoulder"])[:2], 0, atol=1e-12)
    # flexing the left elbow by 90 deg brings the wrist forward (+x), at elbow height
    q = body.expand_q(model, jnp.array([np.pi / 2]), body.dof_index(model, "l_elbow"))
    kp2 = np.asarray(kp_one(model, q))
    iw, ie = body.keypoint_index(model, ["l_wrist", "l_elbow"])
    np.testing.assert_allclose(kp2[iw] - kp2[ie], [0.26, 0, 0], atol=1e-12)
    # abducting the left shoulder (+x) raises the arm outwards (+y); translation moves pelvis
    q = jnp.zeros(24).at[body.dof_index(model, "l_shoulder_x")].set(np.pi / 2).at[:3].set(1.0)
    kp3 = np.asarray(kp_one(model, q))
    ish, iw = body.keypoint_index(model, ["l_shoulder", "l_wrist"])
    np.testing.assert_allclose(kp3[iw] - kp3[ish], [0, 0.56, 0], atol=1e-12)
    np.testing.assert_allclose(kp3[0], [1.0, 1.0, 1.0])


def test_dofs_and_expand(models):
    model = models["bundled"]
    idx = body.stereo_dofs(model)
    assert len(idx) == 14
    assert body.STEREO_JOINTS == ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow")  # roles
    assert {model.chain.dof_names[i] for i in idx[6:]} == {
        f"{s}_shoulder_{a}" for s in "lr" for a in "xyz"} | {"l_elbow", "r_elbow"}
    default = jnp.arange(24.0)
    q = body.expand_q(model, jnp.ones(14), idx, default)
    assert np.all(q[idx] == 1) and np.all(np.delete(np.asarray(q), idx) == np.delete(default, idx))
    with pytest.raises(ValueError, match="unknown DOFs"):
        body.dof_index(model, "l_knee")
    with pytest.raises(ValueError, match="expected \\(24,\\)"):
        body.fk(model.chain, jnp.zeros(14))


def test_loader_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.urdf"):
        body.load_urdf(tmp_path / "nope.urdf")
    bad = tmp_path / "bad.urdf"
    bad.write_text('<robot name="r"><link name="a"><visual><geometry><mesh filename="x.stl"/>'
                   '</geometry></visual></link><link name="b"/><joint name="j" type="floating">'
                   '<parent link="a"/><child link="b"/></joint></robot>')  # fmt: skip
    with pytest.raises(ValueError, match="bad.urdf.*'floating'"):
        body.load_urdf(bad)
    bad.write_text(bad.read_text().replace("floating", "fixed"))
    with pytest.raises(ValueError, match="bad.urdf.*link 'a'.*<mesh> is not supported"):
        body.load_urdf(bad)


@pytest.mark.parametrize("which", ["bundled", "toy"])
def test_fk_closed_form_jacobian(models, which, rng, tmp_path):
    """``fk``'s derivatives in q come from the geometric Jacobian (a custom JVP): they match
    central finite differences, first and second order, on the bundled body and on a toy
    with ball, hinge and slide joints; derivatives in the chain's own arrays (autodiff) too."""
    if which == "toy":
        path = tmp_path / "toy.xml"
        path.write_text(TOY_MJCF)
        model = body.load_mjcf(path)
    else:
        model = models["bundled"]
    chain = model.chain
    q = jnp.asarray(random_q(chain, 1, rng, root=True)[0])
    n, eps = chain.n_dof, 1e-6
    basis = np.eye(n)

    def fd(f, x):  # central differences of f along every dof, stacked last
        return np.stack([(np.asarray(f(x + eps * e)) - np.asarray(f(x - eps * e))) / (2 * eps)
                         for e in basis], axis=-1)  # fmt: skip

    fk = jax.jit(lambda x: body.fk(chain, x))
    jac = jax.jit(jax.jacfwd(lambda x: body.fk(chain, x)))
    np.testing.assert_allclose(np.asarray(jac(q)), fd(fk, q), atol=1e-8)
    # second order (the IK's Jacobian is itself linearised by the solver)
    hess = jax.jit(jax.jacfwd(jax.jacfwd(lambda x: body.fk(chain, x))))(q)  # one program
    np.testing.assert_allclose(np.asarray(hess), fd(jac, q), atol=1e-6)
    # reverse mode and vmap agree with forward mode
    w = jnp.asarray(rng.normal(size=(chain.n_links, 4, 4)))
    g = jax.jit(jax.grad(lambda x: jnp.sum(w * body.fk(chain, x))))(q)
    np.testing.assert_allclose(np.asarray(g), np.einsum("lij,lijk->k", w, jac(q)), atol=1e-12)
    qs = jnp.stack([q, q[::-1]])
    jv = jax.jit(jax.vmap(jax.jacfwd(lambda x: body.fk(chain, x))))(qs)
    np.testing.assert_allclose(np.asarray(jv[1]), np.asarray(jac(qs[1])), atol=1e-12)
    # the chain's joint offsets (e.g. fitting proportions) are differentiated by autodiff
    @jax.jit
    def loss(origin):
        return jnp.sum(w * body.fk(eqx.tree_at(lambda c: c.joint_origin, chain, origin), q))

    o = chain.joint_origin
    k = (min(2, chain.n_links - 1), 1, 3)  # one translation entry of a joint offset
    e = jnp.zeros_like(o).at[k].set(eps)
    np.testing.assert_allclose(float(jax.jit(jax.grad(loss))(o)[k]),
                               float((loss(o + e) - loss(o - e)) / (2 * eps)), atol=1e-7)


def test_over_frames_equals_each_frame_for_any_length():
    """``over_frames`` (the exports' batched FK, in fixed-size chunks so a long capture's
    writing does not hold every frame's intermediates): every row equals that row's own
    ``fk`` call, for lengths below, at and across the chunk size (the padding never leaks)."""
    model = body.default_body()
    rng = np.random.default_rng(3)
    for T in (1, 4, 10):
        q = random_q(model.chain, T, rng, root=True)
        got = body.chain.over_frames(body.fk, model.chain, q, chunk=4)
        assert got.shape == (T, model.chain.n_links, 4, 4) and got.dtype == np.float64
        for t in range(T):
            np.testing.assert_allclose(got[t], np.asarray(body.fk(model.chain, jnp.asarray(q[t]))),
                                       atol=1e-6)
    with pytest.raises(ValueError, match="over_frames"):
        body.chain.over_frames(body.fk, model.chain, np.zeros((0, model.n_dof)))
