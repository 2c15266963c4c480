"""Bodies designed by others, used as they come (issue 36 item 1, issue 39 decision 4).

Humanoids that ship inside packages, each loaded by ``load_body`` from its own file in the
installed package (never copied or edited) with its roles inferred -- no roles file:

* pybullet's DeepMimic humanoid (``humanoid/humanoid.urdf``: Y-up, 4x units, spherical joints,
  fixed wrist links, collision capsules/spheres/boxes);
* dm_control's CMU humanoid (``suite/humanoid_CMU.xml``: CMU names ``lhumerus``/``lradius``,
  a Y-up skeleton stood up by its root body's orientation, hinge triplets, ``<include>``);
* dm_control's suite humanoid (``suite/humanoid.xml``: head and hands fixed bodies);
* gymnasium's MuJoCo humanoid (``envs/mujoco/assets/humanoid.xml``: no head or hand bodies --
  a ``head`` sphere on the torso link and ``left_hand`` spheres on the lower arms, a torso made
  of capsules across the body);
* pybullet's MJCF humanoid (``mjcf/humanoid.xml``, the same layout as gymnasium's, no free
  joint).

Oracles: MuJoCo's own kinematics (``mj_kinematics``: joint anchors ``xanchor`` for the joint
keypoints, ``geom_xpos`` for the head and hand keypoints), pytorch-kinematics FK for the URDF,
and the body's construction (which geoms are which part, read off the files by hand: the
expected tables below).
"""

import importlib.util
import json
from pathlib import Path

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import pytorch_kinematics as pk
import torch
from scipy.spatial.transform import Rotation

from jaxmocap import body
from jaxmocap.body import roles as rl
from jaxmocap.body.mjcf import compile_mjcf
from jaxmocap.body.packages import PACKAGE_BODIES, package_body_file
from jaxmocap.body.urdf import prepare_urdf, read_urdf_text
from jaxmocap.errors import InputError
from jaxmocap.garment import garment_from_model, shirt_geoms
from jaxmocap.pf import cues


def package_file(package: str, *parts: str) -> Path:
    """A file inside an installed package, located without importing the package."""
    spec = importlib.util.find_spec(package)
    assert spec is not None and spec.submodule_search_locations, f"{package} is not installed"
    return Path(next(iter(spec.submodule_search_locations))).joinpath(*parts)


BODIES = {name: ((package, *parts), kw) for name, (package, parts, kw) in
          PACKAGE_BODIES.items()}
# The roles as read off each file by hand: link roles, and the geoms that are the head and the
# hands (the keypoints' geoms) -- the oracle for the inference.
EXPECTED = {
    "deepmimic": ({"pelvis": "base", "chest": "chest", "head": "neck",
                   "l_upper_arm": "left_shoulder", "l_forearm": "left_elbow",
                   "l_hand": "left_wrist", "r_upper_arm": "right_shoulder",
                   "r_forearm": "right_elbow", "r_hand": "right_wrist"}, None),
    "cmu": ({"pelvis": "root", "chest": "thorax", "head": "head", "l_upper_arm": "lhumerus",
             "l_forearm": "lradius", "l_hand": "lhand", "r_upper_arm": "rhumerus",
             "r_forearm": "rradius", "r_hand": "rhand"},
            {"head": "head", "l_hand": "lhand", "r_hand": "rhand"}),
    "dmc_humanoid": ({"pelvis": "torso", "chest": "torso", "head": "head",
                      "l_upper_arm": "left_upper_arm", "l_forearm": "left_lower_arm",
                      "l_hand": "left_hand", "r_upper_arm": "right_upper_arm",
                      "r_forearm": "right_lower_arm", "r_hand": "right_hand"},
                     {"head": "head", "l_hand": "left_hand", "r_hand": "right_hand"}),
    "gym_humanoid": ({"pelvis": "torso", "chest": "torso", "head": "torso",
                      "l_upper_arm": "left_upper_arm", "l_forearm": "left_lower_arm",
                      "l_hand": "left_lower_arm", "r_upper_arm": "right_upper_arm",
                      "r_forearm": "right_lower_arm", "r_hand": "right_lower_arm"},
                     {"head": "head", "l_hand": "left_hand", "r_hand": "right_hand"}),
    "pybullet_mjcf": ({"pelvis": "world", "chest": "torso", "head": "torso",
                       "l_upper_arm": "left_upper_arm", "l_forearm": "left_lower_arm",
                       "l_hand": "left_lower_arm", "r_upper_arm": "right_upper_arm",
                       "r_forearm": "right_lower_arm", "r_hand": "right_lower_arm"},
                      {"head": "head", "l_hand": "left_hand", "r_hand": "right_hand"}),
}  # fmt: skip


@pytest.fixture(scope="module")
def bodies():
    out = {}
    for name, (parts, kw) in BODIES.items():
        path = package_file(*parts)
        assert (path, kw) == package_body_file(name)
        assert not body.roles_path(path).exists()  # inferred, not read from a file beside it
        out[name] = (path, body.load_body(path, **kw))
    return out


@pytest.mark.parametrize("name", list(BODIES))
def test_roles_inferred_as_read_off_the_file(bodies, name):
    path, model = bodies[name]
    links, _ = EXPECTED[name]
    assert dict(model.roles.links) == links
    assert "(roles inferred)" in model.roles.source
    assert len(body.stereo_dofs(model)) >= 12  # root 6 + shoulders + elbows
    # the shirt is on the torso and arms, the skin is the head and the hands (never the legs)
    skin = set(model.roles.skin_geoms)
    shirt = set(shirt_geoms(model))
    assert shirt and not (skin & shirt)
    legs = [g for g in model.geometry.names if any(w in g for w in ("thigh", "shin", "femur",
                                                                     "tibia", "foot", "knee"))]
    assert not (skin & set(legs)) and not (shirt & set(legs))
    for role in rl.CONTOUR_LIMBS:
        assert model.roles.limb(role), role
    assert model.roles.torso_geoms


def _qpos(m, model, q):
    """MuJoCo qpos of our q: free root (its rest orientation is the root link's fixed offset),
    hinges by name."""
    qpos = m.qpos0.copy()
    base = np.asarray(model.chain.joint_origin[0], np.float64)[:3, :3]
    for j in range(m.njnt):
        a, jt = m.jnt_qposadr[j], m.jnt_type[j]
        if jt == mujoco.mjtJoint.mjJNT_FREE:
            qpos[a : a + 3] = q[0:3]
            r = Rotation.from_rotvec(q[3:6]).as_matrix() @ base
            qpos[a + 3 : a + 7] = np.roll(Rotation.from_matrix(r).as_quat(), 1)
        else:
            qpos[a] = q[body.dof_index(model, m.joint(j).name)[0]]
    return qpos


@pytest.mark.parametrize("name", ["cmu", "dmc_humanoid", "gym_humanoid", "pybullet_mjcf"])
def test_keypoints_against_mujoco(bodies, name, rng):
    """Joint keypoints at MuJoCo's joint anchors, head and hand keypoints at the centres of the
    head / hand geoms MuJoCo places, in random poses within the limits."""
    path, model = bodies[name]
    _, geoms = EXPECTED[name]
    m = compile_mjcf(path)
    d = mujoco.MjData(m)
    lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
    lo, hi = np.where(np.isfinite(lo), lo, -1.0), np.where(np.isfinite(hi), hi, 1.0)
    free = any(m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE for j in range(m.njnt))
    for _ in range(4):
        q = rng.uniform(lo, hi)
        if not free:
            q[:6] = 0.0  # the world is the root link
        d.qpos[:] = _qpos(m, model, q)
        mujoco.mj_kinematics(m, d)
        kp = np.asarray(body.keypoints(model, jnp.asarray(q)))
        world = np.asarray(body.fk(model.chain, jnp.asarray(q)))[0] if not free else np.eye(4)
        kp = (np.linalg.solve(world, np.c_[kp, np.ones(len(kp))].T).T)[:, :3]
        at = dict(zip(model.keypoint_names, kp, strict=True))
        for s in "lr":
            for joint, key in ((f"{s}_elbow", f"{s}_elbow"), (f"{s}_shoulder", f"{s}_shoulder")):
                jid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT,
                                        model.roles.dofs(joint)[-1])
                np.testing.assert_allclose(at[key], d.xanchor[jid], atol=1e-6, err_msg=key)
        for key, geom in geoms.items():
            gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, geom)
            np.testing.assert_allclose(at[key], d.geom_xpos[gid], atol=1e-5, err_msg=key)


def test_deepmimic_fk_against_pytorch_kinematics(bodies, rng):
    path, model = bodies["deepmimic"]
    chain = pk.build_chain_from_urdf(prepare_urdf(read_urdf_text(path))[1]).to(
        dtype=torch.float64)
    q = np.zeros((5, model.n_dof))
    q[:, 6:] = rng.uniform(-1.0, 1.0, (5, model.n_dof - 6))
    ref = chain.forward_kinematics(torch.tensor(q[:, 6:]))
    for k in range(5):
        t = np.asarray(body.fk(model.chain, jnp.asarray(q[k])))
        kp = np.asarray(body.keypoints(model, jnp.asarray(q[k])))
        for i, (name, link, off) in enumerate(model.roles.keypoints):
            mref = ref[link].get_matrix().numpy()[k]
            # pk works in the file's units and frame: ours = base @ scale * pk
            p = t[0] @ np.append(0.25 * mref[:3, 3] + mref[:3, :3] @ off, 1.0)
            np.testing.assert_allclose(kp[i], p[:3], atol=1e-5, err_msg=name)


@pytest.mark.parametrize("name", list(BODIES))
def test_shirt_and_limb_model_for_every_body(bodies, name):
    """The garment is placed by roles (the body's own shirt geoms) and the stereo filter's
    contour model is made from the role geoms: four arm segments along their bones and the
    torso, each with a length and a width."""
    _, model = bodies[name]
    garment = garment_from_model(model)
    names = model.geometry.names
    covered = {names[g] for g in np.asarray(garment.patch_geom).tolist()}
    assert covered == set(shirt_geoms(model))
    for role in rl.CONTOUR_LIMBS:
        assert set(model.roles.limb(role)) <= covered
    limbs = cues.limb_model(model)
    assert limbs.names == (*rl.CONTOUR_LIMBS, "torso")
    length = np.linalg.norm(np.asarray(limbs.p1 - limbs.p0), axis=1)
    assert np.all(length > 0.05) and np.all(length < 0.6), length
    assert np.all(np.asarray(limbs.radius) > 0.01) and np.all(np.asarray(limbs.radius) < 0.3)
    # left and right arm segments are mirror images
    np.testing.assert_allclose(length[0], length[2], rtol=1e-6)
    np.testing.assert_allclose(length[1], length[3], rtol=1e-6)


def test_partial_keypoints_in_a_roles_file_are_kept_and_the_rest_inferred(bodies, tmp_path):
    """Issue 39: a roles file giving only the head keypoint (as the user guide shows) keeps
    it and infers the other eleven, identical to inference alone."""
    path, model = bodies["gym_humanoid"]
    roles = tmp_path / "humanoid.roles.json"
    roles.write_text(json.dumps({"keypoints": {"head": ["torso", [0.01, 0.0, 0.16]]}}))
    given = body.load_body(path, roles=roles)
    table, inferred = given.roles.keypoint_table(), model.roles.keypoint_table()
    assert table["head"] == ("torso", (0.01, 0.0, 0.16))
    assert {k: v for k, v in table.items() if k != "head"} == \
        {k: v for k, v in inferred.items() if k != "head"}
    assert given.keypoint_names[:12] == body.KEYPOINT_NAMES
    # a head link without geometry needs no geometry when the file places the head
    bad = tmp_path / "bad.roles.json"
    bad.write_text(json.dumps({"keypoints": {"head": ["nose", [0, 0, 0]]}}))
    with pytest.raises(InputError, match=r"bad\.roles\.json.*keypoints: 'head' names unknown"):
        body.load_body(path, roles=bad)


FIXED_CHILD_URDF = """<robot name="fixed_children">
  <link name="hips"><visual><geometry><box size="0.2 0.3 0.15"/></geometry></visual></link>
  <joint name="waist" type="revolute"><parent link="hips"/><child link="torso"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <link name="torso"/>
  <joint name="torso_vis" type="fixed"><parent link="torso"/><child link="torso_shape"/>
    <origin xyz="0 0 0.25"/></joint>
  <link name="torso_shape"><visual><geometry><box size="0.2 0.34 0.5"/></geometry></visual></link>
  <joint name="neck" type="revolute"><parent link="torso"/><child link="head"/>
    <origin xyz="0 0 0.52"/><axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <link name="head"/>
  <joint name="head_vis" type="fixed"><parent link="head"/><child link="head_mesh"/>
    <origin xyz="0 0 0.1"/></joint>
  <link name="head_mesh"><visual><material name="skin"/><geometry><sphere radius="0.1"/></geometry></visual></link>
  SIDES
</robot>"""  # noqa: E501
ARM = """
  <joint name="S_shoulder" type="revolute"><parent link="torso"/><child link="S_upper_arm"/>
    <origin xyz="0 Y 0.46"/><axis xyz="1 0 0"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <link name="S_upper_arm"/>
  <joint name="S_upper_arm_vis" type="fixed"><parent link="S_upper_arm"/><child link="S_upper_arm_v"/>
    <origin xyz="0 0 -0.14"/></joint>
  <link name="S_upper_arm_v"><visual><geometry><cylinder radius="0.045" length="0.26"/></geometry></visual></link>
  <joint name="S_elbow" type="revolute"><parent link="S_upper_arm"/><child link="S_forearm"/>
    <origin xyz="0 0 -0.28"/><axis xyz="0 1 0"/><limit lower="0" upper="2.5" effort="1" velocity="1"/></joint>
  <link name="S_forearm"><visual><origin xyz="0 0 -0.06"/><geometry><cylinder radius="0.04" length="0.12"/></geometry></visual></link>
  <joint name="S_forearm_vis" type="fixed"><parent link="S_forearm"/><child link="S_forearm_v"/>
    <origin xyz="0 0 -0.18"/></joint>
  <link name="S_forearm_v"><visual><geometry><cylinder radius="0.035" length="0.12"/></geometry></visual></link>
  <joint name="S_wrist" type="revolute"><parent link="S_forearm"/><child link="S_hand"/>
    <origin xyz="0 0 -0.25"/><axis xyz="1 0 0"/><limit lower="-1" upper="1" effort="1" velocity="1"/></joint>
  <link name="S_hand"/>
  <joint name="S_hand_vis" type="fixed"><parent link="S_hand"/><child link="S_hand_v"/>
    <origin xyz="0 0 -0.08"/></joint>
  <link name="S_hand_v"><visual><geometry><box size="0.04 0.08 0.16"/></geometry></visual></link>
"""  # noqa: E501


def test_geometry_on_fixed_child_links_belongs_to_the_parent(tmp_path, rng):
    """A URDF whose every visual hangs on a fixed child link (unnamed visuals, the usual
    export): head and hand keypoints at the child links' shapes, the contour limbs made of the
    fixed children's cylinders (the forearm of two, on two links), no roles file."""
    arms = "".join(ARM.replace("S_", f"{s}_").replace("Y", y)
                   for s, y in (("left", "0.2"), ("right", "-0.2")))
    path = tmp_path / "fixed_children.urdf"
    path.write_text(FIXED_CHILD_URDF.replace("SIDES", arms))
    model = body.load_body(path)
    roles = model.roles
    assert roles.link("l_hand") == "left_hand" and roles.link("head") == "head"
    assert roles.limb("l_forearm") == ("left_forearm_0", "left_forearm_v_0")
    assert roles.limb("l_upper_arm") == ("left_upper_arm_v_0",)
    assert roles.torso_geoms == ("torso_shape_0",)
    assert set(roles.skin_geoms) == {"head_mesh_0", "left_hand_v_0", "right_hand_v_0"}
    table = roles.keypoint_table()
    np.testing.assert_allclose(table["head"][1], [0, 0, 0.1])
    np.testing.assert_allclose(table["l_hand"][1], [0, 0, -0.08])
    limbs = cues.limb_model(model)
    i = limbs.names.index("l_forearm")
    assert limbs.link[i] == model.chain.link_index("left_forearm")
    # the two stacked cylinders: centre to centre along the bone (-0.06 .. -0.18)
    np.testing.assert_allclose(sorted([float(limbs.p0[i][2]), float(limbs.p1[i][2])]),
                               [-0.18, -0.06], atol=1e-9)
    # in any pose, the forearm's far end is the fixed child cylinder's centre (the child's
    # offset is constant, so the limb rides on the forearm link)
    q = rng.uniform(-0.5, 0.5, model.n_dof)
    t = body.fk(model.chain, jnp.asarray(q))
    a, b = (np.asarray(x[i]) for x in cues.limb_endpoints(limbs, t))
    g = np.asarray(body.geom_world_poses(model, t))[model.geometry.names.index(
        "left_forearm_v_0")]
    far = a if float(limbs.p0[i][2]) < float(limbs.p1[i][2]) else b
    np.testing.assert_allclose(far, g[:3, 3], atol=1e-6)


MESH_MJCF = """<mujoco><asset>
  <mesh name="box" vertex="-.04 -.04 -.13  .04 -.04 -.13  -.04 .04 -.13  .04 .04 -.13
                           -.04 -.04 .13  .04 -.04 .13  -.04 .04 .13  .04 .04 .13"/>
</asset><worldbody><body name="b"><freejoint/>
  <geom name="m" type="mesh" mesh="box" pos="0 0 .2"/>
  <body name="c" pos="0 0 .4"><joint name="h" axis="0 1 0"/><geom size=".05"/></body>
</body></worldbody></mujoco>"""


def test_mesh_geoms_are_their_bounding_box(tmp_path):
    path = tmp_path / "mesh.xml"
    path.write_text(MESH_MJCF)
    model = body.load_mjcf(path)
    assert int(model.geometry.kind[0]) == body.BOX
    np.testing.assert_allclose(np.asarray(model.geometry.size[0]), [0.04, 0.04, 0.13],
                               atol=1e-6)
    np.testing.assert_allclose(np.asarray(model.geometry.pose[0])[:3, 3], [0, 0, 0.2],
                               atol=1e-6)


def test_limb_model_error_names_the_roles_file_and_field(bodies, tmp_path):
    path, _ = bodies["cmu"]
    roles = tmp_path / "cmu.roles.json"
    roles.write_text(json.dumps({"limb_geoms": {"l_upper_arm": []}}))
    model = body.load_body(path, roles=roles)
    with pytest.raises(InputError, match=r"cmu\.roles\.json: limb_geoms\['l_upper_arm'\]: no "
                                         r"geoms .*'limb_geoms'"):
        cues.limb_model(model)


@pytest.mark.parametrize("name", list(BODIES))
def test_deepmimic_clip_retargeted_by_role_follows_the_source_bones(bodies, name):
    """A DeepMimic clip retargeted onto each body by its roles (no names): on every frame
    where no arm joint hit its limits, the upper-arm keypoints (shoulder -> elbow) follow the
    source's bone directions exactly, and the forearm (elbow -> wrist) is the source forearm
    direction projected onto the plane the body's elbow hinge can reach (exact where the
    hinges are parallel: the DeepMimic body itself). Oracle: the source skeleton's FK
    (``source_bone_directions``), independent of the retargeting."""
    import jax

    from jaxmocap.synth import motion
    from jaxmocap.synth.deepmimic import load_deepmimic

    _, model = bodies[name]
    clip = load_deepmimic("humanoid3d_walk")
    src = np.asarray(motion.source_bone_directions(clip), np.float64)
    roles = list(motion.DEEPMIMIC_TO_BODY)
    res = motion.clip_to_body_q(clip, model)
    q = np.asarray(res.q, np.float64)
    hit = np.abs(np.asarray(res.q_raw) - np.asarray(res.q)) > 1e-6

    def free(*joints):  # frames where none of the joints' DOFs was clipped
        idx = body.dof_index(model, [d for j in joints for d in model.roles.dofs(j)])
        return ~np.any(hit[:, idx], axis=1)

    kp = np.asarray(jax.vmap(lambda x: body.keypoints(model, x))(jnp.asarray(q)))
    tf = np.asarray(jax.vmap(lambda x: body.fk(model.chain, x))(jnp.asarray(q)))
    at = {k: kp[:, i] for i, k in enumerate(model.keypoint_names)}

    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    def angle(a, b):
        return np.degrees(np.arccos(np.clip(np.sum(unit(a) * unit(b), -1), -1.0, 1.0)))

    for s in "lr":
        ok = free(f"{s}_shoulder")
        assert ok.mean() > 0.3, ok.mean()
        upper = angle(at[f"{s}_elbow"] - at[f"{s}_shoulder"], src[:, roles.index(f"{s}_upper_arm")])
        assert upper[ok].max() < 0.5, (s, upper[ok].max())
        (elbow,) = model.roles.dofs(f"{s}_elbow")
        link = [i for i, (_, _, d) in enumerate(model.chain.topology)
                if d == model.chain.dof_names.index(elbow)][0]
        axis = unit(tf[:, link, :3, :3] @ np.asarray(model.chain.joint_axis[link], np.float64))
        want = src[:, roles.index(f"{s}_forearm")]
        reach = want - np.sum(want * axis, -1, keepdims=True) * axis
        fore = angle(at[f"{s}_wrist"] - at[f"{s}_elbow"], reach)
        # (gymnasium's and dm_control's elbows never straighten: their range -90..50 deg
        # about a rest bent by 109 deg clips every frame of a walk; nothing to compare there)
        ok = free(f"{s}_shoulder", f"{s}_elbow")
        if ok.any():
            assert fore[ok].max() < 0.5, (s, fore[ok].max())
        if name == "deepmimic":
            assert angle(at[f"{s}_wrist"] - at[f"{s}_elbow"], want).max() < 0.5


def test_cli_body_arguments_load_every_package_body(bodies):
    """``--body FILE`` (with ``--body-scale``/``--body-up`` for the DeepMimic URDF) gives
    the same body as ``load_body``, for every package body, through the CLI's parser."""
    import argparse

    from jaxmocap.commands._body import add_body_args, body_from_args

    parser = argparse.ArgumentParser()
    add_body_args(parser)
    for name, (path, model) in bodies.items():
        extra = ["--body-scale", "0.25", "--body-up", "y"] if name == "deepmimic" else []
        args = parser.parse_args(["--body", str(path), *extra])
        assert body.body_digest(body_from_args(args)) == body.body_digest(model), name
    with pytest.raises(InputError, match="give --body"):
        body_from_args(parser.parse_args(["--body-up", "y"]))


SKIN_HANDS_MJCF = """<mujoco><asset>
  <material name="cloth" rgba=".2 .3 .8 1"/><material name="Skin_Light" rgba=".9 .7 .6 1"/>
</asset><worldbody><body name="pelvis" pos="0 0 1"><freejoint/>
  <geom type="box" size=".1 .15 .08" material="cloth"/>
  <body name="torso" pos="0 0 .1"><joint name="waist" axis="0 1 0"/>
    <geom type="box" size=".1 .17 .25" pos="0 0 .25" material="cloth"/>
    <geom type="sphere" size=".1" pos="0 0 .65" material="Skin_Light"/>
    ARMS
  </body></body></worldbody></mujoco>"""
SKIN_ARM = """<body name="S_upper_arm" pos="0 Y .45"><joint name="S_sh1" axis="1 0 0"/>
      <joint name="S_sh2" axis="0 1 0"/><joint name="S_sh3" axis="0 0 1"/>
      <geom type="capsule" fromto="0 0 0 0 0 -.26" size=".045" material="cloth"/>
      <body name="S_lower_arm" pos="0 0 -.28"><joint name="S_elbow" axis="0 1 0"/>
        <geom type="capsule" fromto="0 0 0 0 0 -.2" size=".04" material="cloth"/>
        <geom type="capsule" fromto="0 0 -.24 0 0 -.32" size=".035" material="Skin_Light"/>
      </body></body>"""


def test_skin_material_finds_the_hands_and_the_skin(tmp_path):
    """An MJCF without hand bodies and with unnamed geoms (issue 39: "no hand bodies, skin
    forearms"): the hands are the skin-material geoms on the lower arms and the skin is every
    skin-material geom; only the head link is given (its sphere is unnamed: truly ambiguous)."""
    arms = "".join(SKIN_ARM.replace("S_", f"{s}_").replace("Y", y)
                   for s, y in (("left", ".2"), ("right", "-.2")))
    path = tmp_path / "skin_hands.xml"
    path.write_text(SKIN_HANDS_MJCF.replace("ARMS", arms))
    roles = rl.infer_roles(*(lambda m: (m.chain, m.geometry))(body.load_mjcf(path)), path,
                           {"links": {"head": "torso"}})
    assert dict(roles.links)["l_hand"] == "left_lower_arm"
    g = body.load_mjcf(path).geometry
    skin = {g.names[i] for i in range(g.n_geoms) if g.materials[i] == "Skin_Light"}
    assert set(roles.skin_geoms) == skin and len(skin) == 3
    (fore,) = roles.limb("l_forearm")  # the sleeve, not the hand
    assert g.materials[g.names.index(fore)] == "cloth"
    table = roles.keypoint_table()
    np.testing.assert_allclose(table["l_hand"][1], [0, 0, -0.28], atol=1e-6)
    np.testing.assert_allclose(table["l_wrist"][1], [0, 0, -0.205], atol=1e-6)


@pytest.mark.parametrize("name", list(BODIES))
def test_every_body_faces_forward_and_mirrors(bodies, name, rng):
    """At q = 0 every body faces +x with its left along +y (dm_control's CMU humanoid, which
    faces -y as it ships, is turned by its root offset), and its joints pair left with right
    (the CMU skeleton is measured, not exactly symmetric): the mirror of a pose puts the
    keypoints at the mirror images of the pose's (up to the skeleton's asymmetry)."""
    from jaxmocap.posedb import mirror_pose, mirror_table

    _, model = bodies[name]
    kp = dict(zip(model.keypoint_names, np.asarray(body.keypoints(model, body.rest_pose(model))),
                  strict=False))
    left = kp["l_shoulder"] - kp["r_shoulder"]
    assert left[1] > 0.2 and abs(left[0]) < 0.02, left
    assert kp["head"][2] > kp["chest"][2] + 0.1  # upright
    table = mirror_table(model)
    lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
    q = np.zeros(model.n_dof)
    arm = body.dof_index(model, [d for j in ("l_shoulder", "l_elbow") for d in
                                 model.roles.dofs(j)])
    q[arm] = rng.uniform(np.maximum(lo[arm], -0.5), np.minimum(hi[arm], 0.5))
    m = np.asarray(mirror_pose(table, jnp.asarray(q)))
    a = np.asarray(body.keypoints(model, jnp.asarray(q)))
    b = np.asarray(body.keypoints(model, jnp.asarray(m)))
    i, j = model.keypoint_names.index("l_hand"), model.keypoint_names.index("r_hand")
    np.testing.assert_allclose(b[j], a[i] * [1, -1, 1], atol=0.03)


def _gym_with_hands_named(tmp_path, left: str, right: str) -> Path:
    """gymnasium's humanoid as another tool writes it: the same file with its hand spheres
    (on the lower-arm bodies) renamed."""
    path, _ = package_body_file("gym_humanoid")
    text = path.read_text()
    assert text.count('name="left_hand"') == 1 and text.count('name="right_hand"') == 1
    out = tmp_path / "humanoid.xml"
    out.write_text(text.replace('name="left_hand"', f'name="{left}"')
                   .replace('name="right_hand"', f'name="{right}"'))
    return out


def _hand_keypoints_at_mujoco_geoms(path, model, geoms, rng):
    m = compile_mjcf(path)
    d = mujoco.MjData(m)
    lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
    lo, hi = np.where(np.isfinite(lo), lo, -1.0), np.where(np.isfinite(hi), hi, 1.0)
    for _ in range(3):
        q = rng.uniform(lo, hi)
        d.qpos[:] = _qpos(m, model, q)
        mujoco.mj_kinematics(m, d)
        at = dict(zip(model.keypoint_names, np.asarray(body.keypoints(model, jnp.asarray(q))),
                      strict=True))
        for key, geom in geoms.items():
            gid = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, geom)
            np.testing.assert_allclose(at[key], d.geom_xpos[gid], atol=1e-5, err_msg=key)


def test_hand_geoms_named_with_the_side_in_the_middle(bodies, tmp_path, rng):
    """Issue 52 item 6: gymnasium's humanoid with its hand spheres named ``skin_left_hand`` /
    ``skin_right_hand`` (the side word in the middle): the roles are inferred as for the
    original file, and the hand keypoints sit at those spheres as MuJoCo places them."""
    path = _gym_with_hands_named(tmp_path, "skin_left_hand", "skin_right_hand")
    model = body.load_body(path)
    assert dict(model.roles.links) == EXPECTED["gym_humanoid"][0]
    assert {"skin_left_hand", "skin_right_hand"} <= set(model.roles.skin_geoms)
    _, original = bodies["gym_humanoid"]
    assert model.roles.keypoint_table() == original.roles.keypoint_table()
    _hand_keypoints_at_mujoco_geoms(path, model, {"l_hand": "skin_left_hand",
                                                  "r_hand": "skin_right_hand"}, rng)


def test_roles_file_hand_on_the_forearm_link_placed_at_its_skin_geom(tmp_path, rng):
    """Issue 52 item 6: hand spheres with names that say nothing (``lh_ball``), the roles file
    naming the lower arms as the hands and the spheres as skin: the hand keypoints are placed
    at the spheres (not refused for "no geometry"); without the skin geoms it stays one line
    asking for them (which geom on the lower arm is the hand is then ambiguous)."""
    path = _gym_with_hands_named(tmp_path, "lh_ball", "rh_ball")
    links = {"l_hand": "left_lower_arm", "r_hand": "right_lower_arm"}
    rf = body.roles_path(path)
    rf.write_text(json.dumps({"links": links}))
    with pytest.raises(InputError, match=r"the l_hand link 'left_lower_arm' has no geometry"):
        body.load_body(path)
    rf.write_text(json.dumps({"links": links, "skin_geoms": ["head", "lh_ball", "rh_ball"]}))
    model = body.load_body(path)
    assert model.roles.limb("l_forearm") == ("left_larm",)  # the sleeve, not the hand
    _hand_keypoints_at_mujoco_geoms(path, model, {"l_hand": "lh_ball", "r_hand": "rh_ball"},
                                    rng)
