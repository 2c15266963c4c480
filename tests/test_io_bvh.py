"""BVH I/O: our poses written for any body and read back by independent readers (the PyPI `bvh`
parser, bvhio's forward kinematics: joint positions equal ours), clear errors, and driving our
body from a foreign (T-pose, centimetre, ZXY) skeleton. Blender's importer: test_io_interop.py."""

from pathlib import Path

import bvhio
import jax
import jax.numpy as jnp
import numpy as np
import pybullet_data
import pytest
from bvh import Bvh
from scipy.spatial.transform import Rotation

from jaxmocap.body import default_body, fk, keypoints, load_urdf
from jaxmocap.io.bvh import (
    BVHError,
    body_bvh_layout,
    body_to_bvh,
    bvh_fk,
    bvh_to_body_q,
    default_mapping,
    euler_zxy,
    parse_bvh,
    read_bvh,
    write_body_bvh,
)

M = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # BVH (Y up) -> our world (Z up)
N_FRAMES = 6
HUMANOID_URDF = Path(pybullet_data.getDataPath()) / "humanoid" / "humanoid.urdf"
fk_batch = jax.jit(jax.vmap(fk, in_axes=(None, 0)))


def random_q(model, rng, n=N_FRAMES):
    """Poses within the limits, ball joints' middle angle inside (-pi/2, pi/2) where Euler
    angles are unique (outside, an equivalent branch is an equally valid answer)."""
    lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
    lo = np.maximum(lo, -1.35)
    hi = np.minimum(hi, 1.35)
    q = rng.uniform(lo[6:], hi[6:], size=(n, model.n_dof - 6))
    root = np.concatenate([rng.normal(0, 1, (n, 3)), rng.normal(0, 1.0, (n, 3))], axis=1)
    return np.concatenate([root, q], axis=1)


def bvhio_positions(path, n_frames):
    """World positions of every joint per frame, by the independent reader bvhio (Y up)."""
    root = bvhio.readAsHierarchy(str(path))
    out = []
    for t in range(n_frames):
        root.loadPose(t)
        out.append({j.Name: np.array(j.PositionWorld) for j, _, _ in root.layout()})
    return out


def link_origins(model, q):
    return np.asarray(fk_batch(model.chain, jnp.asarray(q)))[..., :3, 3]


def test_round_trip_and_bvh_package(tmp_path, rng):
    model = default_body()
    q = random_q(model, rng)
    path = tmp_path / "clip.bvh"
    write_body_bvh(path, model, q, fps=30.0)

    ours = read_bvh(path)
    ref = Bvh(path.read_text())  # independent parser (PyPI `bvh`)
    assert list(ours.names) == ref.get_joints_names()
    assert ref.nframes == N_FRAMES == ours.n_frames
    assert ref.frame_time == pytest.approx(1 / 30.0, abs=1e-8)
    for j, sl in zip(ours.joints, ours.channel_slices(), strict=True):
        assert list(j.channels) == ref.joint_channels(j.name)
        assert list(j.offset) == pytest.approx(list(ref.joint_offset(j.name)), abs=1e-9)
        for k in (0, N_FRAMES - 1):
            got = ref.frame_joint_channels(k, j.name, list(j.channels))
            np.testing.assert_allclose(ours.motion[k, sl], got, atol=1e-9)
    # what Blender's importer needs: 3 rotation channels (Z X Y) per animated joint, the
    # root's position first; joints named after the keypoint roles on their pivots
    assert ref.joint_channels("pelvis") == ["Xposition", "Yposition", "Zposition",
                                            "Zrotation", "Xrotation", "Yrotation"]
    for name in ours.names[1:]:
        assert ref.joint_channels(name) == ["Zrotation", "Xrotation", "Yrotation"]
    assert ref.joint_parent("l_elbow").name == "l_shoulder"
    assert ref.joint_parent("l_wrist").name == "l_elbow"

    # joint positions read by bvhio equal our forward kinematics (metres, to the 6 decimals
    # of the file), and the keypoints sitting on the joints
    lay = body_bvh_layout(model)
    origins = link_origins(model, q)
    kps = np.asarray(jax.vmap(keypoints, in_axes=(None, 0))(model, jnp.asarray(q)))
    for t, pos in enumerate(bvhio_positions(path, N_FRAMES)):
        for name, link in zip(lay.names, lay.links, strict=True):
            np.testing.assert_allclose(M @ pos[name], origins[t, link], atol=2e-6)
            if name in model.keypoint_names:
                np.testing.assert_allclose(M @ pos[name],
                                           kps[t, model.keypoint_names.index(name)], atol=2e-6)
    # the channels are intrinsic ZXY Euler angles (scipy) of the parent-relative rotation
    T = np.asarray(fk_batch(model.chain, jnp.asarray(q)))
    rest = np.asarray(fk(model.chain, jnp.zeros(model.n_dof)))
    col = ours.channel_slices()[ours.names.index("l_elbow")]
    e, s = lay.links[ours.names.index("l_elbow")], lay.links[ours.names.index("l_shoulder")]
    d_e = T[:, e, :3, :3] @ rest[e, :3, :3].T
    d_s = T[:, s, :3, :3] @ rest[s, :3, :3].T
    want = M.T @ np.swapaxes(d_s, 1, 2) @ d_e @ M
    got = Rotation.from_euler("ZXY", ours.motion[:, col], degrees=True).as_matrix()
    np.testing.assert_allclose(got, want, atol=1e-7)

    back = bvh_to_body_q(ours, model)
    np.testing.assert_allclose(back.q, q, atol=1e-4)  # joint angles to 1e-4 rad
    np.testing.assert_allclose(back.q_raw, back.q, atol=1e-12)  # nothing was clipped


TOY_URDF = """<?xml version="1.0"?>
<robot name="toy">
  <link name="base"><visual><geometry><box size="0.1 0.1 0.1"/></geometry></visual></link>
  <joint name="j1" type="revolute"><parent link="base"/><child link="a"/>
    <origin xyz="0.1 0.2 0.3" rpy="0.3 -0.4 0.5"/><axis xyz="0.6 0 0.8"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <link name="a"/>
  <joint name="j2" type="revolute"><parent link="a"/><child link="b"/>
    <origin xyz="0 0.05 0" rpy="0 0.2 0"/><axis xyz="0 1 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <link name="b"><visual><geometry><cylinder radius="0.03" length="0.2"/></geometry></visual></link>
  <joint name="slide" type="prismatic"><parent link="b"/><child link="c"/>
    <origin xyz="0 0 0.2" rpy="0 0 0"/><axis xyz="0 0 1"/>
    <limit lower="-0.1" upper="0.1" effort="1" velocity="1"/></joint>
  <link name="c"/>
  <joint name="j3" type="revolute"><parent link="c"/><child link="d"/>
    <origin xyz="0 0 0" rpy="0 0 0"/><axis xyz="1 0 0"/>
    <limit lower="-2" upper="2" effort="1" velocity="1"/></joint>
  <link name="d"><visual><geometry><sphere radius="0.03"/></geometry></visual></link>
  <joint name="fix" type="fixed"><parent link="d"/><child link="e"/>
    <origin xyz="0 0.1 0" rpy="0.5 0 0"/></joint>
  <link name="e"><visual><geometry><sphere radius="0.02"/></geometry></visual></link>
</robot>
"""


def other_bodies(tmp_path):
    """pybullet's humanoid (other names, Y-up file rotated by a fixed root joint, fixed
    wrists, hips and knees) and a toy chain with tilted joint frames, an oblique axis, an
    offset between the two joints of one group, a prismatic joint and a fixed tip."""
    (tmp_path / "toy.urdf").write_text(TOY_URDF)
    return {
        "humanoid": load_urdf(HUMANOID_URDF, scale=0.25, up="y"),
        "toy": load_urdf(tmp_path / "toy.urdf",
                         keypoints={"tip": ("e", (0.0, 0.0, 0.05)), "knot": ("b", (0, 0, 0))}),
    }


def test_any_body_joint_positions_by_bvhio(tmp_path, rng):
    for kind, model in other_bodies(tmp_path).items():
        n = 4
        lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
        q = rng.uniform(np.maximum(lo, -1.5), np.minimum(hi, 1.5), size=(n, model.n_dof))
        q[:, :6] = rng.normal(0, 0.8, (n, 6))
        path = tmp_path / f"{kind}.bvh"
        write_body_bvh(path, model, q, fps=24.0)
        lay = body_bvh_layout(model)
        origins = link_origins(model, q)
        for t, pos in enumerate(bvhio_positions(path, n)):
            got = np.stack([M @ pos[name] for name in lay.names])
            np.testing.assert_allclose(got, origins[t, list(lay.links)], atol=2e-6,
                                       err_msg=kind)
        bvh = read_bvh(path)
        assert bvh.frame_time == pytest.approx(1 / 24.0)
        for j in bvh.joints[1:]:
            assert len(j.channels) in (0, 3, 6), (kind, j)
        if kind == "toy":
            assert lay.names == ("base", "a", "knot", "d", "e")  # knot: the keypoint on b
            assert [len(j.channels) for j in bvh.joints] == [6, 3, 3, 6, 0]
            tip = np.asarray(jax.vmap(keypoints, in_axes=(None, 0))(model, jnp.asarray(q)))[:, 0]
            rots, pos = bvh_fk(bvh)
            end = pos[:, -1] + np.einsum("nij,j->ni", rots[:, -1], bvh.joints[-1].end_site)
            np.testing.assert_allclose(end @ M.T, tip, atol=2e-6)  # End Site = the keypoint
        else:  # fixed joints (the Y-up root offset, the wrists) carry no channels
            assert [j.name for j in bvh.joints if not j.channels] == ["root", "right_wrist",
                                                                      "left_wrist"]


def test_euler_zxy_against_scipy(rng):
    r = Rotation.random(200, random_state=1).as_matrix()
    r[0] = Rotation.from_euler("ZXY", [30, 90, 0], degrees=True).as_matrix()  # gimbal lock
    r[1] = Rotation.from_euler("ZXY", [-10, -90, 0], degrees=True).as_matrix()
    ang = euler_zxy(r)
    np.testing.assert_allclose(Rotation.from_euler("ZXY", ang).as_matrix(), r, atol=1e-9)
    ref = Rotation.from_matrix(r[2:]).as_euler("ZXY")
    np.testing.assert_allclose(ang[2:], ref, atol=1e-9)


BAD = {
    "missing_offset": ("HIERARCHY\nROOT Hips\n{\n  CHANNELS 3 Xrotation Yrotation Zrotation\n",
                       4, "expected 'OFFSET', got 'CHANNELS'"),
    "bad_channel": ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 1 Wrotation\n}\n",
                    5, "unknown channel 'Wrotation' of joint 'Hips'"),
    "short_row": ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 2 Xrotation Yrotation\n"
                  "}\nMOTION\nFrames: 2\nFrame Time: 0.1\n1 2\n3\n", 11,
                  "frame 1 has 1 values, expected 2"),
    "frame_count": ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 1 Xrotation\n}\n"
                    "MOTION\nFrames: 3\nFrame Time: 0.1\n1\n2\n", 11,
                    "Frames: 3 declared, 2 rows found"),
    "not_number": ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 zero 0\n", 4,
                   "expected a number (OFFSET value), got 'zero'"),
    "truncated": ("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 1 Xrotation\n", 5,
                  "unexpected end of file"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_files_give_one_line_errors(tmp_path, case):
    text, line, msg = BAD[case]
    path = tmp_path / f"{case}.bvh"
    path.write_text(text)
    with pytest.raises(BVHError) as info:
        read_bvh(path)
    err = str(info.value)
    assert err.startswith(f"{path}:{line}: ") and msg in err and "\n" not in err
    assert info.value.line == line


# A foreign skeleton: CMU-like names, centimetres, ZXY channels, T-pose rest (arms along the
# BVH z axis, i.e. sideways), body facing +x.
FOREIGN = """HIERARCHY
ROOT Hips
{
  OFFSET 0 0 0
  CHANNELS 6 Xposition Yposition Zposition Zrotation Xrotation Yrotation
  JOINT Spine
  {
    OFFSET 0 20 0
    CHANNELS 3 Zrotation Xrotation Yrotation
    JOINT Neck
    {
      OFFSET 0 30 0
      CHANNELS 3 Zrotation Xrotation Yrotation
      JOINT Head
      {
        OFFSET 0 10 0
        CHANNELS 3 Zrotation Xrotation Yrotation
        End Site
        {
          OFFSET 0 15 0
        }
      }
    }
    JOINT LeftArm
    {
      OFFSET 0 25 -18
      CHANNELS 3 Zrotation Xrotation Yrotation
      JOINT LeftForeArm
      {
        OFFSET 0 0 -28
        CHANNELS 3 Zrotation Xrotation Yrotation
        JOINT LeftHand
        {
          OFFSET 0 0 -25
          CHANNELS 3 Zrotation Xrotation Yrotation
          End Site
          {
            OFFSET 0 0 -8
          }
        }
      }
    }
    JOINT RightArm
    {
      OFFSET 0 25 18
      CHANNELS 3 Zrotation Xrotation Yrotation
      JOINT RightForeArm
      {
        OFFSET 0 0 28
        CHANNELS 3 Zrotation Xrotation Yrotation
        JOINT RightHand
        {
          OFFSET 0 0 25
          CHANNELS 3 Zrotation Xrotation Yrotation
          End Site
          {
            OFFSET 0 0 8
          }
        }
      }
    }
  }
}
"""
JOINTS = ["Hips", "Spine", "Neck", "Head", "LeftArm", "LeftForeArm", "LeftHand", "RightArm",
          "RightForeArm", "RightHand"]
PARENT = [-1, 0, 1, 2, 1, 4, 5, 1, 7, 8]
OFFSET = np.array([[0, 0, 0], [0, 20, 0], [0, 30, 0], [0, 10, 0], [0, 25, -18], [0, 0, -28],
                   [0, 0, -25], [0, 25, 18], [0, 0, 28], [0, 0, 25]], dtype=float)


def test_foreign_tpose_skeleton_drives_body(rng):
    n = N_FRAMES
    # arms lowered from the T-pose by ~75-90 deg (about BVH x), moderate other rotations,
    # elbows bent about the forearm's own hinge-like axis (BVH y after lowering).
    deg = rng.uniform(-15, 15, size=(n, 10, 3))
    deg[:, 4, 1] -= 80  # LeftArm: X rotation lowers the arm (-z -> -y)
    deg[:, 7, 1] += 80
    deg[:, 5] = [0, 0, 0]
    deg[:, 8] = [0, 0, 0]
    deg[:, 5, 2] = -rng.uniform(20, 90, n)  # LeftForeArm: Y rotation bends it forward
    deg[:, 8, 2] = rng.uniform(20, 90, n)
    root_pos = rng.normal(0, 50, (n, 3))
    motion = np.concatenate([root_pos, deg.reshape(n, -1)], axis=1)
    text = FOREIGN + f"MOTION\nFrames: {n}\nFrame Time: 0.04\n"
    text += "\n".join(" ".join(f"{v:.9f}" for v in row) for row in motion) + "\n"
    bvh = parse_bvh(text, "foreign.bvh")
    model = default_body()
    assert default_mapping(bvh, model) == {
        "pelvis": "Hips", "chest": "Spine", "head": "Head", "l_upper_arm": "LeftArm",
        "l_forearm": "LeftForeArm", "l_hand": "LeftHand", "r_upper_arm": "RightArm",
        "r_forearm": "RightForeArm", "r_hand": "RightHand"}

    # independent FK of the BVH with scipy's intrinsic ZXY Euler angles
    rots, pos = [], []
    for j in range(10):
        r = Rotation.from_euler("ZXY", deg[:, j], degrees=True).as_matrix()
        if PARENT[j] < 0:
            rots.append(r)
            pos.append(root_pos + OFFSET[0])
        else:
            rp = rots[PARENT[j]]
            pos.append(pos[PARENT[j]] + np.einsum("nij,j->ni", rp, OFFSET[j]))
            rots.append(rp @ r)
    pos = np.stack(pos, 1) * 0.01 @ M.T  # metres, our world

    res = bvh_to_body_q(bvh, model, scale=0.01)
    t = jax.jit(jax.vmap(fk, in_axes=(None, 0)))(model.chain, jnp.asarray(res.q))
    p = np.asarray(t[:, :, :3, 3])
    link = model.chain.link_names.index
    np.testing.assert_allclose(p[:, 0], pos[:, 0], atol=1e-9)  # root trajectory, metres

    def unit(v):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)

    pairs = [(("pelvis", "chest"), (0, 1)), (("l_upper_arm", "l_forearm"), (4, 5)),
             (("l_forearm", "l_hand"), (5, 6)), (("r_upper_arm", "r_forearm"), (7, 8)),
             (("r_forearm", "r_hand"), (8, 9)), (("chest", "head"), (1, 2))]
    excess = np.abs(np.asarray(res.q_raw - res.q)).sum(-1)
    assert res.q.shape == (n, model.n_dof)
    for (a, b), (sa, sb) in pairs:
        ours = unit(p[:, link(b)] - p[:, link(a)])
        theirs = unit(pos[:, sb] - pos[:, sa])
        ang = np.arccos(np.clip(np.sum(ours * theirs, -1), -1, 1))
        assert np.all(excess < 1e-9)  # these poses are within our joint limits
        assert np.all(ang < 1e-6), (a, b, ang)


def test_mapping_errors():
    bvh = parse_bvh(FOREIGN + "MOTION\nFrames: 1\nFrame Time: 0.1\n" + "0 " * 33 + "\n")
    with pytest.raises(ValueError, match="BVH joint 'Pelvis' .* not in the file"):
        bvh_to_body_q(bvh, default_body(), mapping={"pelvis": "Pelvis"})
    with pytest.raises(ValueError, match="no BVH joint for our root 'pelvis'"):
        bvh_to_body_q(bvh, default_body(), mapping={"chest": "Spine"})
    with pytest.raises(ValueError, match=r"q has shape \(3,\)"):
        body_to_bvh(default_body(), np.zeros(3), 30.0)
