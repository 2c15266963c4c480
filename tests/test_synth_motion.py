"""DeepMimic clip decoding (oracle: pybullet posing humanoid.urdf) and retargeting to our body."""

import json
import pathlib

import jax
import jax.numpy as jnp
import numpy as np
import pybullet as pb
import pybullet_data
import pytest
from scipy.spatial.transform import Rotation, Slerp

from jaxmocap.body import default_body, fk, keypoint_index, keypoints_from_transforms
from jaxmocap.synth import (
    HELDOUT_CLIPS,
    TRAIN_CLIPS,
    clip_path,
    clip_to_body_q,
    limit_report,
    list_clips,
    load_deepmimic,
    resample,
    skeleton_fk,
)
from jaxmocap.synth.deepmimic import Clip

M = np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]])  # Y-up source -> our Z-up world
# DeepMimic frame columns of the 12 joints, in pybullet joint-index order (humanoid_stable_pd).
PB_JOINTS = [(1, 8, 4), (2, 12, 4), (3, 16, 4), (4, 20, 1), (5, 21, 4), (6, 25, 4), (7, 29, 1),
             (9, 30, 4), (10, 34, 1), (11, 35, 4), (12, 39, 4), (13, 43, 1)]


@pytest.fixture(scope="module")
def humanoid():
    """pybullet's humanoid posed the way deep_mimic does; returns a frame -> links function."""
    cid = pb.connect(pb.DIRECT)
    pb.setAdditionalSearchPath(pybullet_data.getDataPath(), physicsClientId=cid)
    h = pb.loadURDF("humanoid/humanoid.urdf", [0, 0.85, 0], globalScaling=0.25,
                    useFixedBase=True, flags=pb.URDF_MAINTAIN_LINK_ORDER, physicsClientId=cid)

    def pose(frame):
        xyzw = lambda c: [frame[c + 1], frame[c + 2], frame[c + 3], frame[c]]
        pb.resetBasePositionAndOrientation(h, frame[1:4], xyzw(4), physicsClientId=cid)
        pb.resetJointStatesMultiDof(
            h, [j for j, _, _ in PB_JOINTS],
            [xyzw(c) if n == 4 else [frame[c]] for _, c, n in PB_JOINTS], physicsClientId=cid)
        states = [pb.getLinkState(h, j, computeForwardKinematics=True, physicsClientId=cid)
                  for j in range(15)]
        pos = np.array([s[4] for s in states])
        rot = np.stack([Rotation.from_quat(s[5]).as_matrix() for s in states])
        return pos, rot

    yield pose
    pb.disconnect(cid)


def raw_frames(name):
    return np.array(json.loads(clip_path(name).read_text())["Frames"])


def test_clip_inventory_and_split():
    clips = list_clips()
    assert len(clips) == 20
    assert set(TRAIN_CLIPS).isdisjoint(HELDOUT_CLIPS)
    assert set(TRAIN_CLIPS) | set(HELDOUT_CLIPS) == set(clips)


@pytest.mark.parametrize("name", ["humanoid3d_roll", "walker/turn_left0"])
def test_load_matches_file(name):
    f = raw_frames(name)
    clip = load_deepmimic(name, dtype=np.float64)
    assert clip.n_frames == len(f) and clip.name == name
    np.testing.assert_allclose(np.diff(np.asarray(clip.times)), f[:-1, 0], atol=1e-12)
    np.testing.assert_allclose(clip.root_pos, f[:, 1:4])
    np.testing.assert_allclose(np.linalg.norm(clip.joint_quat, axis=-1), 1.0, atol=1e-12)
    raw = f[:, 4:8]  # root quaternion, normalised, same direction as stored
    np.testing.assert_allclose(clip.root_quat, raw / np.linalg.norm(raw, axis=1, keepdims=True))
    np.testing.assert_allclose(clip.hinge[:, 1], f[:, 29])  # right elbow


def test_load_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="no DeepMimic clip 'nope'"):
        load_deepmimic("nope")
    bad = tmp_path / "bad.txt"
    bad.write_text(json.dumps({"Frames": [[0.1] * 44, [0.1] * 43]}))
    with pytest.raises(ValueError, match=r"bad.txt: frame 1 has 43 values, expected 44"):
        load_deepmimic(bad)
    bad.write_text("{not json")
    with pytest.raises(ValueError, match="bad.txt: not valid JSON"):
        load_deepmimic(bad)


def test_skeleton_fk_matches_pybullet(humanoid):
    """Our decoding + FK of humanoid.urdf == pybullet's resetJointStatesMultiDof posing."""
    picks = [("humanoid3d_kick", [0, 17, 40]), ("humanoid3d_backflip", [5, 20]),
             ("humanoid3d_dance_b", [70])]  # kick/backflip store non-unit quaternions
    frames = np.concatenate([raw_frames(n)[k] for n, k in picks])
    # one Clip holding the picked frames (times are irrelevant to FK)
    clips = [load_deepmimic(n, dtype=np.float64) for n, _ in picks]
    sel = lambda attr: jnp.concatenate([getattr(c, attr)[np.array(k)]
                                        for c, (_, k) in zip(clips, picks, strict=True)])
    clip = Clip(jnp.arange(len(frames), dtype=jnp.float64), sel("root_pos"), sel("root_quat"),
                sel("joint_quat"), sel("hinge"), name="mix")
    rot, pos = jax.jit(skeleton_fk)(clip)
    for k, frame in enumerate(frames):
        p_ref, r_ref = humanoid(frame)
        np.testing.assert_allclose(pos[k], p_ref, atol=1e-4)
        np.testing.assert_allclose(rot[k], r_ref, atol=1e-4)


def test_resample_slerp_matches_scipy():
    clip = load_deepmimic("humanoid3d_walk", dtype=np.float64)
    fps = 2 * clip.fps  # about 60 Hz: every other frame is a midpoint
    r = resample(clip, fps)
    t = np.asarray(r.times)
    np.testing.assert_allclose(np.diff(t), 1 / fps, atol=1e-9)
    assert t[-1] <= clip.duration + 1e-9
    times = np.asarray(clip.times)
    for j in (0, 4):  # chest, right shoulder
        q = np.asarray(clip.joint_quat[:, j])
        ref = Slerp(times, Rotation.from_quat(q[:, [1, 2, 3, 0]]))(t).as_matrix()
        got = Rotation.from_quat(np.asarray(r.joint_quat[:, j])[:, [1, 2, 3, 0]]).as_matrix()
        np.testing.assert_allclose(got, ref, atol=1e-9)
    np.testing.assert_allclose(r.root_pos[:, 1], np.interp(t, times, clip.root_pos[:, 1]))
    with pytest.raises(ValueError, match="fps must be > 0"):
        resample(clip, 0.0)


# Bone: (our start role link, our end role link or keypoint), (source start link, source end)
# where a source end is a link index or "head" (the neck sphere's centre).
BONES = {
    "spine": (("pelvis", "chest"), (0, 1)),
    "chest": (("chest", "neck"), (1, 2)),
    "head": (("neck", "kp:head"), (2, "head")),
    "l_upper_arm": (("l_upper_arm", "l_forearm"), (12, 13)),
    "l_forearm": (("l_forearm", "l_hand"), (13, 14)),
    "r_upper_arm": (("r_upper_arm", "r_forearm"), (6, 7)),
    "r_forearm": (("r_forearm", "r_hand"), (7, 8)),
}
# Joint roles whose clipping can tilt each bone (its own and its ancestors' groups).
CHAINS = {
    "spine": [], "chest": ["spine"], "head": ["spine", "neck"],
    "l_upper_arm": ["spine", "l_shoulder"], "l_forearm": ["spine", "l_shoulder", "l_elbow"],
    "r_upper_arm": ["spine", "r_shoulder"], "r_forearm": ["spine", "r_shoulder", "r_elbow"],
}


@pytest.fixture(scope="module")
def bodies(tmp_path_factory):
    """The bundled body and the foreign body of tests/_foreign_body.py (URDF and MJCF)."""
    from _foreign_body import foreign_mjcf, foreign_urdf

    from jaxmocap.body import load_body

    d = tmp_path_factory.mktemp("bodies")
    return {"bundled": default_body(), "foreign_urdf": load_body(foreign_urdf(d / "f.urdf")),
            "foreign_mjcf": load_body(foreign_mjcf(d / "f.xml")),
            "deepmimic": load_body(pathlib.Path(pybullet_data.getDataPath()) / "humanoid"
                                   / "humanoid.urdf", scale=0.25, up="y")}


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


@pytest.mark.parametrize("which", ["bundled", "foreign_urdf", "foreign_mjcf", "deepmimic"])
def test_retarget_bone_directions_and_root(humanoid, bodies, which):
    """Retargeted bones point where pybullet's posed source bones point; root copied exactly.
    By roles: the same on a body with other names, proportions, primitives and a neck link, and
    on the source's own humanoid (pybullet's humanoid.urdf, whose wrists sit on the elbows).

    Bound: the angle between a bone of ours and the source's is at most the total amount
    (rad) by which the joints on its chain were clipped to their limits, + 1e-6 rad: exact
    wherever no limit is hit (walk, walker turn), bounded by the clipping elsewhere.
    """
    model = bodies[which]
    roles = model.roles
    names = model.chain.link_names
    specs = [("humanoid3d_walk", None), ("walker/turn_left0", None),
             ("humanoid3d_kick", None), ("humanoid3d_punch", 25.0)]  # all in one 64-frame bucket
    clips, results = [], []
    for name, fps in specs:
        clip = load_deepmimic(name, dtype=np.float64)
        clip = resample(clip, fps) if fps else clip
        clips.append(clip)
        results.append(clip_to_body_q(clip, model))
    q = jnp.concatenate([r.q for r in results])
    excess = np.abs(np.concatenate([np.asarray(r.q_raw - r.q) for r in results]))

    @jax.jit
    def body_fk(model, q):
        t = jax.vmap(fk, in_axes=(None, 0))(model.chain, q)
        return t, jax.vmap(keypoints_from_transforms, in_axes=(None, 0))(model, t)

    transforms, kp = body_fk(model, q)
    q = np.asarray(q)
    ours_pos = np.asarray(transforms[:, :, :3, 3])

    src_pos, src_rot = [], []
    for clip, (name, fps) in zip(clips, specs, strict=True):
        f = raw_frames(name)
        for k in range(clip.n_frames):  # pose pybullet with our (resampled) decoded frame
            row = np.concatenate([[0.0], clip.root_pos[k], clip.root_quat[k],
                                  clip.joint_quat[k, 0], clip.joint_quat[k, 1],
                                  clip.joint_quat[k, 2], clip.hinge[k, :1],
                                  clip.joint_quat[k, 3], clip.joint_quat[k, 4], clip.hinge[k, 1:2],
                                  clip.joint_quat[k, 5], clip.hinge[k, 2:3],
                                  clip.joint_quat[k, 6], clip.joint_quat[k, 7], clip.hinge[k, 3:]])
            if fps is None:  # not resampled: the decoded frame is the file's frame
                np.testing.assert_allclose(row[1:4], f[k, 1:4])
            p, r = humanoid(row)
            src_pos.append(p)
            src_rot.append(r)
    src_pos, src_rot = np.stack(src_pos), np.stack(src_rot)
    head_centre = src_pos[:, 2] + src_rot[:, 2] @ np.array([0, 0.7 * 0.25, 0])

    dof = {n: i for i, n in enumerate(model.chain.dof_names)}
    for bone, ((a, b), (sa, sb)) in BONES.items():
        ours = (kp[:, keypoint_index(model, b[3:])[0]] if b.startswith("kp:")
                else ours_pos[:, names.index(roles.link(b))]) - ours_pos[:, names.index(
                    roles.link(a))]
        src_end = head_centre if sb == "head" else src_pos[:, sb]
        src = (src_end - src_pos[:, sa]) @ M.T
        angle = np.arccos(np.clip(np.sum(unit(ours) * unit(src), -1), -1, 1))
        cols = [dof[n] for g in CHAINS[bone] for n in roles.dofs(g)]
        bound = excess[:, cols].sum(-1) + 1e-6
        assert np.all(angle <= bound), (bone, float(np.max(angle - bound)))
        free = bound < 1e-5
        assert free.mean() > 0.7 and np.all(angle[free] < 1e-6)

    # root: our pelvis origin is the source root position, its rotation the source root's
    np.testing.assert_allclose(ours_pos[:, 0], src_pos[:, 0] @ M.T, atol=1e-9)
    rest0 = np.asarray(model.chain.joint_origin[0, :3, :3])  # the root link's rest orientation
    np.testing.assert_allclose(transforms[:, 0, :3, :3] @ rest0.T, M @ src_rot[:, 0] @ M.T,
                               atol=1e-6)
    # joint limits respected, wrists untouched
    assert np.all(q[:, 6:] >= np.asarray(model.chain.lower[6:]) - 1e-12)
    assert np.all(q[:, 6:] <= np.asarray(model.chain.upper[6:]) + 1e-12)
    assert np.all(q[:, [dof[n] for w in ("l_wrist", "r_wrist") for n in roles.dofs(w)]] == 0)
    assert np.all(np.isfinite(q))
    if which != "bundled":
        return
    report = limit_report(model, results[2])  # kick leans the spine/neck past our limits
    assert set(report) <= set(model.chain.dof_names) and report
    assert limit_report(model, results[0]) == {}  # walking stays within limits
