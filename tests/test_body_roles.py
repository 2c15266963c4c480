"""Roles, not names (issue 16): a body the project has never seen, as URDF and as MJCF.

Oracles: the foreign body's own construction constants (tests/_foreign_body.py), its FK through
pytorch-kinematics (URDF) and the same body compiled by MuJoCo (MJCF, ball joints), the mirror
geometry (the keypoints of a mirrored pose are the mirror images of the pose's), sampled
surface points of the solids (support functions), and the bundled body's hand-written keypoints.
"""

import json
import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import pytorch_kinematics as pk
import torch
from _foreign_body import (
    FOREARM,
    HAND,
    NECK_Z,
    SHOULDER_Y,
    SHOULDER_Z,
    SPINE_Z,
    UPPER_ARM,
    foreign_mjcf,
    foreign_urdf,
)
from scipy.spatial.transform import Rotation

from jaxmocap import body
from jaxmocap.body import roles as rl
from jaxmocap.body.urdf import prepare_urdf, read_urdf_text
from jaxmocap.errors import InputError
from jaxmocap.garment import (
    SHIRT_COLOURS,
    default_garment,
    garment_digest,
    garment_from_model,
    patch_at,
)
from jaxmocap.io.garment_file import load_garment, save_garment
from jaxmocap.pf import cues
from jaxmocap.posedb import mirror_pose, mirror_table

FOREIGN_LINKS = {
    "pelvis": "hips", "chest": "torso", "neck": "neck", "head": "head",
    "l_upper_arm": "left_upper_arm", "l_forearm": "left_forearm", "l_hand": "left_hand",
    "r_upper_arm": "right_upper_arm", "r_forearm": "right_forearm", "r_hand": "right_hand",
}  # fmt: skip


@pytest.fixture(scope="module")
def foreign(tmp_path_factory):
    d = tmp_path_factory.mktemp("foreign")
    urdf, mjcf = foreign_urdf(d / "foreign.urdf"), foreign_mjcf(d / "foreign.xml")
    return {"urdf": body.load_body(urdf), "mjcf": body.load_body(mjcf), "dir": d,
            "urdf_path": urdf, "mjcf_path": mjcf}  # fmt: skip


def one_line(e: pytest.ExceptionInfo) -> str:
    msg = str(e.value)
    assert "\n" not in msg
    return msg


# ------------------------------------------------------------------ roles and keypoints
def test_bundled_roles_reproduce_the_hand_written_keypoints():
    model = body.default_body()
    roles = model.roles
    assert dict(roles.links) == {r: r for r in body.LINK_ROLES if r != "neck"}
    assert roles.dofs("l_shoulder") == ("l_shoulder_x", "l_shoulder_y", "l_shoulder_z")
    assert roles.dofs("spine") == ("spine_x", "spine_y", "spine_z")
    assert roles.dofs("r_wrist") == ("r_wrist_x", "r_wrist_z")
    assert roles.torso_geoms == ("abdomen", "thorax")
    assert set(roles.skin_geoms) == {"neck", "head", "l_hand", "r_hand"}
    # the keypoint rules (joint centres, chest 3/4 up to the shoulder line, geom centres) give
    # the keypoints written by hand in body.model.DEFAULT_KEYPOINTS
    inferred = body.infer_roles(model.chain, model.geometry, "upper_body.urdf").keypoint_table()
    for name, (link, off) in body.model.DEFAULT_KEYPOINTS.items():
        assert inferred[name][0] == link
        np.testing.assert_allclose(inferred[name][1], off, atol=1e-7)
    assert model.keypoint_names == body.KEYPOINT_NAMES
    hash(model.roles)


@pytest.mark.parametrize("fmt", ["urdf", "mjcf"])
def test_foreign_body_roles_and_keypoints(foreign, fmt):
    model = foreign[fmt]
    roles = model.roles
    assert dict(roles.links) == FOREIGN_LINKS
    assert roles.dofs("l_shoulder") == tuple(f"left_shoulder_{a}" for a in "xyz")
    assert roles.dofs("r_elbow") == ("right_elbow",)
    assert roles.dofs("spine") == tuple(f"waist_{a}" for a in "xyz")
    assert roles.dofs("neck") == tuple(f"lower_neck_{a}" for a in "xyz")
    assert roles.limb("torso") == ("torso_box",)
    assert roles.limb("l_upper_arm") == ("left_upper_arm_box",)
    assert set(roles.skin_geoms) == {"neck_cyl", "skull", "left_hand_box", "right_hand_box"}
    names = [model.chain.dof_names[i] for i in body.stereo_dofs(model)]
    assert names[6:] == [f"{w}_{j}" for w in ("left", "right")
                         for j in ("shoulder_x", "shoulder_y", "shoulder_z", "elbow")]
    # keypoints at rest, from the construction constants
    kp = np.asarray(body.keypoints(model, body.rest_pose(model, jnp.float64)))
    k = {n: kp[i] for i, n in enumerate(model.keypoint_names)}
    chest_z = SPINE_Z + SHOULDER_Z
    np.testing.assert_allclose(k["pelvis"], 0.0, atol=1e-12)
    np.testing.assert_allclose(k["chest"], [0, 0, SPINE_Z + 0.75 * SHOULDER_Z], atol=1e-6)
    np.testing.assert_allclose(k["neck"], [0, 0, SPINE_Z + NECK_Z], atol=1e-6)
    np.testing.assert_allclose(k["head"], [0, 0, SPINE_Z + NECK_Z + 0.08 + 0.09], atol=1e-6)
    for s, y in (("l", SHOULDER_Y), ("r", -SHOULDER_Y)):
        np.testing.assert_allclose(k[f"{s}_shoulder"], [0, y, chest_z], atol=1e-6)
        np.testing.assert_allclose(k[f"{s}_elbow"], [0, y, chest_z - UPPER_ARM], atol=1e-6)
        wrist = chest_z - UPPER_ARM - FOREARM
        np.testing.assert_allclose(k[f"{s}_wrist"], [0, y, wrist], atol=1e-6)
        np.testing.assert_allclose(k[f"{s}_hand"], [0, y, wrist - HAND / 2], atol=1e-6)


def test_foreign_fk_against_pytorch_kinematics_and_mujoco_compiled_twin(foreign, rng):
    """URDF: every link against pytorch-kinematics (float64); MJCF (compiled by MuJoCo): the
    keypoints equal the URDF's at the same joint angles (matched by DOF name); jit + vmap."""
    urdf, mjcf = foreign["urdf"], foreign["mjcf"]
    text = prepare_urdf(read_urdf_text(foreign["urdf_path"]))[1]
    chain = pk.build_chain_from_urdf(text).to(dtype=torch.float64)
    lo = np.where(np.isfinite(urdf.chain.lower), urdf.chain.lower, -np.pi)[6:]
    hi = np.where(np.isfinite(urdf.chain.upper), urdf.chain.upper, np.pi)[6:]
    th = rng.uniform(lo, hi, (64, lo.shape[0]))
    q = np.concatenate([np.zeros((64, 6)), th], axis=1)
    ours = np.asarray(jax.jit(jax.vmap(body.fk, in_axes=(None, 0)))(urdf.chain, jnp.asarray(q)))
    joint_names = chain.get_joint_parameter_names()
    cols = [urdf.chain.dof_names.index(n) for n in joint_names]
    ref = chain.forward_kinematics(torch.as_tensor(q[:, cols]))
    for i, name in enumerate(urdf.chain.link_names):
        # pk parses the origins in float32: agreement to its precision
        np.testing.assert_allclose(ours[:, i], ref[name].get_matrix().numpy(), atol=1e-7)
    # the MJCF twin, root included
    q[:, :3] = rng.normal(size=(64, 3))
    q[:, 3:6] = rng.uniform(-1, 1, (64, 3))
    q_m = np.zeros((64, mjcf.n_dof))
    for j, n in enumerate(mjcf.chain.dof_names):
        q_m[:, j] = q[:, urdf.chain.dof_names.index(n)]
    kp = jax.jit(jax.vmap(body.keypoints, in_axes=(None, 0)))
    np.testing.assert_allclose(kp(mjcf, jnp.asarray(q_m)), kp(urdf, jnp.asarray(q)), atol=1e-9)


def test_missing_role_is_one_line_naming_the_file_and_a_roles_file_fixes_it(foreign, tmp_path):
    text = foreign["urdf_path"].read_text()
    for old, new in (("left_upper_arm", "lua"), ("right_upper_arm", "rua")):
        text = text.replace(f'"{old}"', f'"{new}"').replace(f'"{old}__', f'"{new}__')
    path = tmp_path / "renamed.urdf"
    path.write_text(text)
    with pytest.raises(InputError) as e:
        body.load_body(path)
    msg = one_line(e)
    assert str(path) in msg and "l_upper_arm" in msg and "r_upper_arm" in msg
    assert "renamed.roles.json" in msg
    # a partial roles file beside the model names the two links; the rest is inferred
    rl.roles_path(path).write_text(json.dumps({"links": {"l_upper_arm": "lua",
                                                         "r_upper_arm": "rua"}}))
    model = body.load_body(path)
    assert model.roles.link("l_upper_arm") == "lua" and model.roles.source == str(
        rl.roles_path(path))
    np.testing.assert_array_equal(model.keypoint_offset, foreign["urdf"].keypoint_offset)
    # a complete roles file written from the roles reproduces them exactly
    rl.roles_path(path).write_text(json.dumps(body.roles_to_json(model.roles)))
    assert body.load_body(path).roles == model.roles
    for bad, field in (({"links": {"elbow": "lua"}}, "unknown roles"),
                       ({"links": {"l_upper_arm": "nope", "r_upper_arm": "rua"}},
                        "unknown links"),
                       ({"colour": 1}, "unknown fields"),
                       ({"keypoints": {"head": ["head"]}}, "keypoints")):
        rl.roles_path(path).write_text(json.dumps(bad))
        with pytest.raises(InputError, match=field) as e:
            body.load_body(path)
        assert str(path.with_suffix("")) in one_line(e)
    with pytest.raises(InputError, match="URDF"):
        body.load_body(tmp_path / "body.obj")


def test_name_conventions():
    cases = {
        "mixamorig:LeftArm": ("l", "upper_arm"), "mixamorig:LeftForeArm": ("l", "forearm"),
        "RightHand": ("r", "hand"), "L_UpperArm": ("l", "upper_arm"), "r_elbow": ("r", "forearm"),
        "upperarm.L": ("l", "upper_arm"), "lowerarm_r": ("r", "forearm"), "Hips": (None, "pelvis"),
        "Spine2": (None, None), "thorax": (None, "chest"), "LeftShoulder": ("l", "upper_arm"),
        "l_upper_arm__x": ("l", None),
    }  # fmt: skip
    for name, (side, part) in cases.items():
        assert rl.classify_link(name)[:2] == (side, part), name
    # mixamo: LeftArm (rank of "arm") wins over LeftShoulder (the clavicle)
    assert rl.classify_link("LeftArm")[2] < rl.classify_link("LeftShoulder")[2]


def test_mixamo_style_names(tmp_path):
    """Mixamo's skeleton: ``Spine``/``Spine1``/``Spine2`` (the arms hang from Spine2, the
    chest), ``LeftShoulder`` (clavicle) above ``LeftArm`` (upper arm)."""
    tree = [("Spine", "Hips", "0 0 0.1"), ("Spine1", "Spine", "0 0 0.1"),
            ("Spine2", "Spine1", "0 0 0.1"), ("Neck", "Spine2", "0 0 0.25"),
            ("Head", "Neck", "0 0 0.08")]
    for side, y in (("Left", 1), ("Right", -1)):
        tree += [(f"{side}Shoulder", "Spine2", f"0 {0.05 * y} 0.2"),
                 (f"{side}Arm", f"{side}Shoulder", f"0 {0.12 * y} 0"),
                 (f"{side}ForeArm", f"{side}Arm", "0 0 -0.28"),
                 (f"{side}Hand", f"{side}ForeArm", "0 0 -0.25")]
    links = ['<link name="Hips"><visual><geometry><box size="0.2 0.3 0.1"/></geometry>'
             '</visual></link>']
    joints = []
    for child, parent, xyz in tree:
        links.append(f'<link name="mixamorig:{child}"><visual><origin xyz="0 0 -0.05"/>'
                     '<geometry><sphere radius="0.04"/></geometry></visual></link>')
        joints.append(f'<joint name="{child}_j" type="continuous"><parent link="'
                      f'{"mixamorig:" + parent if parent != "Hips" else "Hips"}"/><child '
                      f'link="mixamorig:{child}"/><origin xyz="{xyz}"/><axis xyz="1 0 0"/>'
                      "</joint>")
    path = tmp_path / "mixamo.urdf"
    path.write_text('<robot name="m">' + "".join(links + joints) + "</robot>")
    roles = body.load_body(path).roles
    want = {"pelvis": "Hips", "chest": "Spine2", "neck": "Neck", "head": "Head",
            "l_upper_arm": "LeftArm", "l_forearm": "LeftForeArm", "l_hand": "LeftHand",
            "r_upper_arm": "RightArm", "r_forearm": "RightForeArm", "r_hand": "RightHand"}
    assert dict(roles.links) == {r: ("mixamorig:" + n if n != "Hips" else n)
                                 for r, n in want.items()}
    assert roles.dofs("spine") == ("Spine_j", "Spine1_j", "Spine2_j")
    assert roles.dofs("l_shoulder") == ("LeftShoulder_j", "LeftArm_j")


def test_body_digest(foreign):
    a, b = body.default_body(), body.load_body(body.model.DEFAULT_URDF)
    assert body.body_digest(a) == body.body_digest(b) and len(body.body_digest(a)) == 16
    assert body.body_digest(foreign["urdf"]) != body.body_digest(a)
    import equinox as eqx

    bigger = eqx.tree_at(lambda m: m.geometry.size, a, a.geometry.size * 1.01)
    assert body.body_digest(bigger) != body.body_digest(a)
    # the same with float32 arrays (JAX without x64)
    f32 = jax.tree.map(lambda x: x.astype(jnp.float32) if x.dtype == jnp.float64 else x, a)
    assert f32.geometry.pose.dtype == jnp.float32
    assert body.body_digest(f32) == body.body_digest(a)


# ------------------------------------------------------------------ mirror table
@pytest.mark.parametrize("which", ["bundled", "urdf", "mjcf"])
def test_mirror_table_pairs_left_with_right(foreign, which, rng):
    """The keypoints of the mirrored pose are the mirror images (y -> -y) of the pose's, left
    and right swapped; left_* joints pair with right_* ones (never with themselves)."""
    model = body.default_body() if which == "bundled" else foreign[which]
    mir = mirror_table(model)
    names = model.chain.dof_names
    for i, n in enumerate(names):
        partner = names[mir.perm[i]]
        if n.startswith(("left", "l_")):
            assert partner == re.sub(r"^(left|l)_", lambda m: "right_" if m[1] == "left"
                                     else "r_", n)
    lo = np.where(np.isfinite(model.chain.lower), model.chain.lower, -np.pi)
    hi = np.where(np.isfinite(model.chain.upper), model.chain.upper, np.pi)
    q = rng.uniform(np.maximum(lo, -1.0), np.minimum(hi, 1.0), (16, model.n_dof))
    q[:, :3] = rng.normal(size=(16, 3))
    kp = jax.vmap(body.keypoints, in_axes=(None, 0))
    a = np.asarray(kp(model, jnp.asarray(q)))
    b = np.asarray(kp(model, mirror_pose(mir, jnp.asarray(q))))
    swap = [model.keypoint_names.index(re.sub(r"^(l|r)_", lambda m: "r_" if m[1] == "l"
                                              else "l_", k)) for k in model.keypoint_names]
    np.testing.assert_allclose(b[:, swap], a * np.array([1.0, -1.0, 1.0]), atol=1e-9)


def test_mirror_table_refuses_unpaired_sides(foreign, tmp_path):
    text = foreign["urdf_path"].read_text()
    text = text.replace('<joint name="right_hip" type="spherical">',
                        '<joint name="right_hip" type="revolute">')
    text = text.replace('<child link="right_thigh"/><origin xyz="0 -0.095 -0.05"/>',
                        '<child link="right_thigh"/><origin xyz="0 -0.095 -0.05"/>'
                        '<axis xyz="0 1 0"/><limit lower="-1" upper="1" effort="1" '
                        'velocity="1"/>')
    path = tmp_path / "lopsided.urdf"
    path.write_text(text)
    model = body.load_body(path)
    with pytest.raises(InputError) as e:
        mirror_table(model)
    msg = one_line(e)
    assert "left_hip_x" in msg and "mirror" in msg and str(path) in msg


# ------------------------------------------------------------------ contour limbs, swivel
@pytest.mark.parametrize("kind", [body.SPHERE, body.CAPSULE, body.CYLINDER, body.BOX,
                                  body.ELLIPSOID])
def test_geom_support_against_sampled_surfaces(kind, rng):
    size = np.array([0.05, 0.12, 0.08]) if kind in (body.BOX, body.ELLIPSOID) else \
        np.array([0.05, 0.12, 0.0])
    rot = Rotation.random(random_state=1).as_matrix()
    # dense points of the solid (geom frame) -> the largest projection on random directions
    p = rng.normal(size=(200_000, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    a, b, c = size
    if kind == body.SPHERE:
        pts = a * p
    elif kind == body.ELLIPSOID:
        pts = p * size
    elif kind == body.BOX:
        pts = np.sign(p) * size
        pts[: len(p) // 2] = rng.uniform(-1, 1, (len(p) // 2, 3)) * size
    elif kind == body.CAPSULE:
        pts = a * p + np.c_[0 * p[:, :2], np.sign(p[:, 2]) * b]
    else:
        ang = rng.uniform(0, 2 * np.pi, len(p))
        pts = np.c_[a * np.cos(ang), a * np.sin(ang), rng.choice([-b, b], len(p))]
    for u in Rotation.random(5, random_state=2).as_matrix()[:, 0]:
        want = np.max(pts @ (rot.T @ u))
        got = rl.geom_support(kind, size, rot, u)
        assert want <= got + 1e-12 and got - want < 2e-3


def test_contour_limbs_from_the_foreign_geometry(foreign):
    for fmt in ("urdf", "mjcf"):
        limbs = cues.limb_model(foreign[fmt])
        assert limbs.names == ("l_upper_arm", "l_forearm", "r_upper_arm", "r_forearm", "torso")
        # upper arm: a 0.09 x 0.10 x 0.24 box along the bone -> its length, half-widths
        np.testing.assert_allclose(limbs.p0[0], [0, 0, -UPPER_ARM / 2 + 0.12], atol=1e-6)
        np.testing.assert_allclose(limbs.p1[0], [0, 0, -UPPER_ARM / 2 - 0.12], atol=1e-6)
        np.testing.assert_allclose([limbs.radius[0], limbs.depth[0]], [0.05, 0.045], atol=1e-6)
        # forearm: a cylinder along the bone is itself
        np.testing.assert_allclose([limbs.radius[1], limbs.depth[1]], [0.038, 0.038], atol=1e-6)
        np.testing.assert_allclose(np.sort([limbs.p0[1][2], limbs.p1[1][2]]),
                                   [-FOREARM + 0.02, -0.02], atol=1e-6)
        # torso: the one box, left-right half-width 0.18, front-back 0.11, 0.52 tall
        np.testing.assert_allclose(limbs.p0[4], [0, 0, -0.02], atol=1e-6)
        np.testing.assert_allclose(limbs.p1[4], [0, 0, 0.50], atol=1e-6)
        np.testing.assert_allclose([limbs.radius[4], limbs.depth[4]], [0.18, 0.11], atol=1e-6)
        tr = body.fk(foreign[fmt].chain, jnp.zeros(foreign[fmt].n_dof))
        assert [foreign[fmt].chain.link_names[i] for i in limbs.link] == [
            FOREIGN_LINKS[r] for r in ("l_upper_arm", "l_forearm", "r_upper_arm",
                                       "r_forearm", "chest")]
        a, b = cues.limb_endpoints(limbs, tr)
        assert np.all(np.isfinite(np.asarray(a))) and np.all(np.isfinite(np.asarray(b)))


def test_swivel_arms_by_roles_and_refusal(foreign, tmp_path):
    from jaxmocap import camera as camlib
    from jaxmocap.trackers import stereo_pf as sp

    cams = [camlib.look_at(jnp.array([2.5, y, 1.2]), jnp.array([0.0, 0.0, 1.0]), width=64,
                           height=48, fx=60.0) for y in (0.1, -0.1)]  # fmt: skip
    model = foreign["urdf"]
    params = sp.make_params(cams, model=model, motion=sp.Motion(n_particles=8),
                            proposals=sp.Proposals(swivel_fraction=0.1))
    arms = params.filter.proposal.arms
    names = model.chain.link_names
    assert [(names[p], names[c], h) for _, p, c, h in arms] == [
        ("torso", "left_upper_arm", "l_hand"),
        ("torso", "right_upper_arm", "r_hand"),
    ]
    # a body whose shoulders are one hinge each: one line instead of silently no jumps
    text = foreign["urdf_path"].read_text()
    for w, y in (("left", 1), ("right", -1)):
        text = text.replace(
            f'<joint name="{w}_shoulder" type="spherical">',
            f'<joint name="{w}_shoulder" type="revolute">',
        )
        text = text.replace(
            f'<child link="{w}_upper_arm"/><origin xyz="0 {y * SHOULDER_Y} {SHOULDER_Z}"/>',
            f'<child link="{w}_upper_arm"/><origin xyz="0 '
            f'{y * SHOULDER_Y} {SHOULDER_Z}"/><axis xyz="1 0 0"/><limit '
            'lower="-3" upper="3" effort="1" velocity="1"/>',
        )
    path = tmp_path / "hinged.urdf"
    path.write_text(text)
    hinged = body.load_body(path)
    assert hinged.roles.dofs("l_shoulder") == ("left_shoulder",)
    with pytest.raises(InputError) as e:
        sp.make_params(
            cams,
            model=hinged,
            motion=sp.Motion(n_particles=8),
            proposals=sp.Proposals(swivel_fraction=0.1),
        )
    assert "swivel_fraction" in one_line(e) and str(path) in str(e.value)
    sp.make_params(
        cams,
        model=hinged,
        motion=sp.Motion(n_particles=8),
        proposals=sp.Proposals(swivel_fraction=0.0),
    )


# ------------------------------------------------------------------ garments
def test_garment_from_model_takes_the_shirt_not_the_trousers(foreign):
    model = foreign["urdf"]
    g = garment_from_model(model)
    assert set(g.patch_names) == {
        "torso_box",
        "left_upper_arm_box",
        "right_upper_arm_box",
        "left_forearm_cyl",
        "right_forearm_cyl",
    }
    assert g.n_colours == 3
    # "shirt = these colours of the model", ids in the user's colour order
    user = [("cuff", (0.10, 0.20, 0.80)), ("shirt", (0.80, 0.10, 0.10))]
    g2 = garment_from_model(model, colours=user)
    ids = dict(zip(g2.patch_names, np.asarray(g2.patch_colour).tolist(), strict=True))
    assert ids == {"torso_box": 2, "left_forearm_cyl": 1, "right_forearm_cyl": 1}
    assert g2.colour_names == ("cuff", "shirt")
    # trousers only when asked
    assert "hips_box" in garment_from_model(model, parts="all").patch_names
    assert garment_from_model(model, parts=["hips"]).patch_names == ("hips_box",)


def test_default_garment_refused_on_the_foreign_body(foreign):
    with pytest.raises(InputError) as e:
        default_garment(foreign["urdf"])
    msg = one_line(e)
    assert "garment.json" in msg and "torso" in msg


def test_garment_json_round_trip_and_colour_order(foreign, tmp_path):
    from jaxmocap.color import ColorModel

    model = body.default_body()
    g = default_garment(model)
    path = save_garment(tmp_path / "garment.json", g, model)
    back = load_garment(path, model)
    assert back.patch_names == g.patch_names and back.colour_names == g.colour_names
    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(back), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    # colour ids follow the user's colour model (ColorModel names), not the file's order
    names = [n for n, _ in SHIRT_COLOURS][::-1]
    cm = ColorModel(
        mean=jnp.asarray(np.linspace(20, 230, 30).reshape(10, 3)),
        cov=jnp.tile(jnp.eye(3) * 20.0, (10, 1, 1)),
        names=tuple(names),
    )
    ordered = load_garment(path, model, colors=cm)
    assert ordered.colour_names == tuple(names)
    for i, p in enumerate(g.patch_names):
        was = g.colour_names[int(g.patch_colour[i]) - 1]
        assert ordered.colour_names[int(ordered.patch_colour[i]) - 1] == was, p
    np.testing.assert_allclose(ordered.colours, g.colours[::-1], atol=1e-12)  # file rgb kept
    assert garment_digest(back) == garment_digest(g) != garment_digest(ordered)
    with pytest.raises(InputError, match="not in the colour model") as e:
        load_garment(path, model, colors=names[:5])
    assert str(path) in one_line(e)


def test_garment_json_on_the_foreign_body(foreign, tmp_path):
    """A 4-patch shirt by link and geom with half-spaces; colours by name (the bundled palette)
    and by rgb; skin by link; patch lookup against the half-spaces evaluated by hand."""
    model = foreign["mjcf"]
    spec = {
        "colours": ["red", {"name": "teal", "rgb": [0.1, 0.6, 0.6]}],
        "patches": [
            {"name": "front", "geom": "torso_box", "half_spaces": [[-1, 0, 0, 0]],
             "colour": "red"},
            {"name": "back", "geom": "torso_box", "half_spaces": [[1, 0, 0, 0]],
             "colour": "teal"},
            {"name": "sleeves_l", "link": "left_upper_arm", "colour": "teal"},
            {"name": "sleeves_r", "link": "right_upper_arm", "colour": "red"},
        ],
        "skin": ["head", "neck", "left_hand", "right_hand_box"],
    }  # fmt: skip
    path = tmp_path / "shirt.json"
    path.write_text(json.dumps(spec))
    g = load_garment(path, model)
    assert g.colour_names == ("red", "teal")
    np.testing.assert_allclose(np.asarray(g.colours)[0], dict(SHIRT_COLOURS)["red"])
    assert g.patch_names == ("front", "back", "sleeves_l", "sleeves_r")
    skin = {model.geometry.names[i] for i in np.flatnonzero(np.asarray(g.skin))}
    assert skin == {"skull", "neck_cyl", "left_hand_box", "right_hand_box"}
    torso = model.geometry.names.index("torso_box")
    pts = jnp.asarray([[0.05, 0.0, 0.1], [-0.05, 0.1, 0.0]])
    np.testing.assert_array_equal(patch_at(g, jnp.array([torso, torso]), pts), [1, 2])
    for bad, field in (
        (
            {**spec, "patches": [{"name": "x", "geom": "tail", "colour": "red"}]},
            "unknown geom 'tail'",
        ),
        ({**spec, "colours": ["chartreuse"]}, "has no 'rgb'"),
        (
            {**spec, "patches": [{"name": "x", "link": "torso", "colour": "blue"}]},
            "not in 'colours'",
        ),
        ({**spec, "skin": ["tail"]}, "neither a geom nor a link"),
    ):
        path.write_text(json.dumps(bad))
        with pytest.raises(InputError, match=field) as e:
            load_garment(path, model)
        assert str(path) in one_line(e)


def test_mjcf_sites_are_kept_as_keypoints(foreign, tmp_path, rng):
    """<site> markers become keypoints (a site named ``head`` places the head keypoint); their
    world positions equal MuJoCo's ``site_xpos`` at random ball-joint poses."""
    import mujoco

    text = foreign["mjcf_path"].read_text()
    text = text.replace(
        '<body name="left_forearm" pos="0 0 -0.26">',
        '<body name="left_forearm" pos="0 0 -0.26"><site name="LELB" pos="0.03 0.01 -0.02"/>',
    )
    text = text.replace(
        '<body name="head" pos="0 0 0.08">',
        '<body name="head" pos="0 0 0.08"><site name="head" pos="0 0 0.1"/>',
    )
    path = tmp_path / "markers.xml"
    path.write_text(text)
    model = body.load_body(path)
    assert model.keypoint_names == body.KEYPOINT_NAMES + ("LELB",)
    assert model.roles.keypoint_table()["head"] == ("head", (0.0, 0.0, 0.1))
    m = mujoco.MjModel.from_xml_path(str(path))
    d = mujoco.MjData(m)
    idx = body.keypoint_index(model, ["LELB", "head"])
    for _ in range(3):
        q = np.zeros(model.n_dof)
        q[:3] = rng.normal(size=3)
        rot = Rotation.random(random_state=rng.integers(1 << 30))
        q[3:6] = rot.as_rotvec()
        d.qpos[:3], d.qpos[3:7] = q[:3], rot.as_quat()[[3, 0, 1, 2]]
        for j in range(1, m.njnt):  # ball joints: R = Rx Ry Rz of our x, y, z DOFs
            name, adr = m.joint(j).name, m.jnt_qposadr[j]
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL:
                a = rng.uniform(-1, 1, 3)
                for ax, v in zip("xyz", a, strict=True):
                    q[model.chain.dof_names.index(f"{name}_{ax}")] = v
                d.qpos[adr : adr + 4] = Rotation.from_euler("XYZ", a).as_quat()[[3, 0, 1, 2]]
            else:
                v = rng.uniform(*m.jnt_range[j]) if m.jnt_limited[j] else rng.uniform(-1, 1)
                q[model.chain.dof_names.index(name)] = v
                d.qpos[adr] = v
        mujoco.mj_kinematics(m, d)
        kp = np.asarray(body.keypoints(model, jnp.asarray(q)))[idx]
        np.testing.assert_allclose(
            kp, d.site_xpos[[m.site("LELB").id, m.site("head").id]], atol=1e-9
        )


def test_pose_database_for_the_foreign_body(foreign):
    """``posedb.build_database`` on a body with other names (issue 16: it failed in
    retargeting): clip frames retargeted by roles, mirrored by the role pairs, rendered with
    the body's own shirt; poses within the limits, every shirt colour seen."""
    from jaxmocap import posedb
    from jaxmocap.posedb._build import build_arrays

    model = foreign["urdf"]
    garment = garment_from_model(model)
    cfg = posedb.SamplingConfig(size=64, seed=1, clips=("humanoid3d_walk",))
    maps, poses = (np.asarray(a) for a in build_arrays(cfg, model, garment, False))
    assert poses.shape == (64, model.n_dof) and np.all(np.isfinite(poses))
    lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
    assert np.all((poses[:, 6:] >= lo[6:] - 1e-6) & (poses[:, 6:] <= hi[6:] + 1e-6))
    assert set(np.unique(maps).tolist()) >= {1, 2, 3}


def test_third_party_deepmimic_humanoid():
    """pybullet's DeepMimic humanoid (links root/chest/neck/left_shoulder/left_elbow/
    left_wrist, fixed wrists on the elbows, a base link fixed to the root) by inference alone."""
    from pathlib import Path

    import pybullet_data

    model = body.load_body(
        Path(pybullet_data.getDataPath()) / "humanoid" / "humanoid.urdf", scale=0.25, up="y"
    )
    roles = model.roles
    assert dict(roles.links) == {
        "pelvis": "base", "chest": "chest", "head": "neck", "l_upper_arm": "left_shoulder",
        "l_forearm": "left_elbow", "l_hand": "left_wrist", "r_upper_arm": "right_shoulder",
        "r_forearm": "right_elbow", "r_hand": "right_wrist"}  # fmt: skip
    assert roles.dofs("l_wrist") == () and len(body.stereo_dofs(model)) == 14
    limbs = cues.limb_model(model)  # the forearm ends at the hand (its wrist sits on the elbow)
    assert np.all(np.linalg.norm(np.asarray(limbs.p1 - limbs.p0), axis=1) > 0.1)
    mir = mirror_table(model)
    names = model.chain.dof_names
    assert names[mir.perm[names.index("left_knee")]] == "right_knee"
    with pytest.raises(InputError, match="scale/up apply to URDF"):
        body.load_body(Path(pybullet_data.getDataPath()) / "mjcf" / "humanoid.xml", scale=0.5)


def test_garment_json_as_other_tools_write_it(foreign, tmp_path):
    """Issue 52 item 6: MuJoCo-style ``rgba`` in 0..1 (a list, or MJCF's "r g b a" string),
    patches naming their colour by index (0 = the first), and a patch ``geom`` given by the
    name of a URDF link whose one visual has no name (jaxmocap calls it ``<link>_0``) read as
    the same garment as the file written the jaxmocap way (the oracle)."""
    text = foreign["urdf_path"].read_text()
    unnamed = tmp_path / "unnamed.urdf"
    unnamed.write_text(re.sub(r'<visual name="[^"]*">', "<visual>", text))
    model = body.load_body(unnamed)
    assert "torso_0" in model.geometry.names and "torso" not in model.geometry.names
    ours = {
        "colours": [{"name": "red", "rgb": [0.8, 0.1, 0.1]},
                    {"name": "colour1", "rgb": [0.1, 0.6, 0.6]}],
        "patches": [
            {"name": "front", "geom": "torso_0", "half_spaces": [[-1, 0, 0, 0]], "colour": "red"},
            {"name": "back", "geom": "torso_0", "half_spaces": [[1, 0, 0, 0]],
             "colour": "colour1"},
        ],
    }  # fmt: skip
    theirs = {
        "colours": [{"name": "red", "rgba": [0.8, 0.1, 0.1, 1.0]}, {"rgba": "0.1 0.6 0.6 0.5"}],
        "patches": [
            {"name": "front", "geom": "torso", "half_spaces": [[-1, 0, 0, 0]], "colour": 0},
            {"name": "back", "geom": "torso", "half_spaces": [[1, 0, 0, 0]], "colour": 1},
        ],
    }  # fmt: skip
    a, b = tmp_path / "ours.json", tmp_path / "theirs.json"
    a.write_text(json.dumps(ours))
    b.write_text(json.dumps(theirs))
    want, got = load_garment(a, model), load_garment(b, model)
    assert got.colour_names == want.colour_names and got.patch_names == want.patch_names
    for x, y in zip(jax.tree.leaves(want), jax.tree.leaves(got), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))
    assert garment_digest(got) == garment_digest(want)
    # what stays refused, each in one line naming the file and the field
    for bad, field in (
        ({**theirs, "colours": [{"rgba": [204, 25, 25, 255]}, "red"]},
         r"colours\[0\].*'rgba' must be 4 numbers in \[0, 1\]"),
        ({**theirs, "colours": [{"rgb": [1, 0, 0], "rgba": [1, 0, 0, 1]}]},
         r"colours\[0\]: both 'rgb' and 'rgba'"),
        ({**theirs, "patches": [{"name": "x", "geom": "torso", "colour": 2}]},
         r"patches\[0\].*colour index 2 outside 0..1"),
        ({**theirs, "patches": [{"name": "x", "geom": "torso", "colour": True}]},
         r"patches\[0\].*colour True is not in 'colours'"),
        ({**theirs, "patches": [{"name": "x", "geom": "hips", "colour": 0}]}, None),
    ):  # fmt: skip
        b.write_text(json.dumps(bad))
        if field is None:  # hips has one visual too: accepted
            assert load_garment(b, model).patch_geom.tolist() == [
                model.geometry.names.index("hips_0")]
            continue
        with pytest.raises(InputError, match=field) as e:
            load_garment(b, model)
        assert str(b) in one_line(e)


def test_garment_geom_naming_a_link_of_several_geoms_is_refused(foreign, tmp_path):
    """A patch ``geom`` naming a link with several geoms is ambiguous: one line naming them."""
    text = foreign["urdf_path"].read_text()
    two = tmp_path / "two.urdf"
    extra = '<visual><geometry><sphere radius="0.05"/></geometry></visual>'
    two.write_text(re.sub(r'<visual name="[^"]*">', "<visual>", text)
                   .replace('<link name="hips">', '<link name="hips">' + extra))
    model = body.load_body(two)
    assert {"hips_0", "hips_1"} <= set(model.geometry.names)
    path = tmp_path / "g.json"
    path.write_text(json.dumps({"colours": ["red"],
                                "patches": [{"name": "x", "geom": "hips", "colour": 0}]}))
    with pytest.raises(InputError, match=r"'geom' 'hips' is a link with 2 geoms") as e:
        load_garment(path, model)
    assert str(path) in one_line(e)


def test_side_word_in_the_middle_of_a_name():
    """Issue 52: ``skin_left_hand`` (a prefix, then side and part) is the left hand; a middle
    ``l`` or a part word before the side word is not read."""
    assert rl.classify_link("skin_left_hand")[:2] == ("l", "hand")
    assert rl.classify_link("geom_right_upper_arm")[:2] == ("r", "upper_arm")
    assert rl.classify_link("skin_l_hand")[:2] == (None, None)
    assert rl.classify_link("hand_left_skin")[:2] == (None, None)
    assert rl.classify_link("left_hand")[:2] == ("l", "hand")
