"""BVH I/O: round trip of our poses, the independent `bvh` package as a parser oracle, clear
errors, and driving our body from a foreign (T-pose, centimetre, ZXY) skeleton."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from bvh import Bvh
from scipy.spatial.transform import Rotation

from jaxmocap.body import default_body, fk
from jaxmocap.io.bvh import (
    BVHError,
    body_to_bvh,
    bvh_to_body_q,
    default_mapping,
    parse_bvh,
    read_bvh,
    write_body_bvh,
)

M = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # BVH (Y up) -> our world (Z up)
N_FRAMES = 6


def random_q(model, rng, n=N_FRAMES):
    """Poses within the limits, ball joints' middle angle inside (-pi/2, pi/2) where Euler
    angles are unique (outside, an equivalent branch is an equally valid answer)."""
    lo, hi = np.asarray(model.chain.lower), np.asarray(model.chain.upper)
    lo = np.maximum(lo, -1.35)
    hi = np.minimum(hi, 1.35)
    q = rng.uniform(lo[6:], hi[6:], size=(n, model.n_dof - 6))
    root = np.concatenate([rng.normal(0, 1, (n, 3)), rng.normal(0, 1.0, (n, 3))], axis=1)
    return np.concatenate([root, q], axis=1)


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
    # the hierarchy follows the body: elbows are 1-DOF Z channels, shoulders 3-DOF
    assert ref.joint_channels("l_forearm") == ["Zrotation"]
    assert ref.joint_parent("l_forearm").name == "l_upper_arm"
    # written values are our angles in chain order (degrees), X Z Y: our y axis is BVH -z
    col = ours.channel_slices()[ours.names.index("l_upper_arm")]
    np.testing.assert_allclose(ours.motion[:, col], np.degrees(q[:, [12, 13, 14]])
                               * [1, -1, 1], atol=1e-5)

    back = bvh_to_body_q(ours, model)
    np.testing.assert_allclose(back.q, q, atol=1e-4)  # joint angles to 1e-4 rad
    np.testing.assert_allclose(back.q_raw, back.q, atol=1e-12)  # nothing was clipped


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
