"""Scaled / renamed / re-primitived bodies and the URDF / MJCF writers (issue 16 item 4a).

Oracles: pytorch-kinematics' FK of the written URDF, MuJoCo's ``mj_kinematics`` of the
written MJCF (qpos built with SciPy's quaternion), exact geometry of the measurements."""

import jax.numpy as jnp
import mujoco
import numpy as np
import pytest
import pytorch_kinematics as pk
import torch
from scipy.spatial.transform import Rotation

from jaxmocap.body import BOX, CAPSULE, CYLINDER, default_body, fk, keypoints, load_mjcf, load_urdf
from jaxmocap.body.scale import (
    BodyScaleError,
    measure,
    rename_body,
    scale_body,
    scale_garment,
    swap_capsules,
)
from jaxmocap.body.urdf import prepare_urdf, read_urdf_text
from jaxmocap.body.write import write_mjcf, write_urdf
from jaxmocap.cli import main
from jaxmocap.garment import default_garment, patch_at

MEAS = dict(height=1.58, shoulder_width=0.32, upper_arm=0.27, forearm=0.29)


@pytest.fixture(scope="module")
def scaled():
    return scale_body(**MEAS)


def random_q(model, n, rng):
    lo = np.nan_to_num(np.asarray(model.chain.lower), neginf=-1.0)
    hi = np.nan_to_num(np.asarray(model.chain.upper), posinf=1.0)
    return rng.uniform(lo, hi, (n, model.n_dof))


def test_measurements_are_met(scaled):
    got = measure(scaled.model, scaled.pelvis_height)
    for k, v in MEAS.items():
        assert got[k] == pytest.approx(v, abs=1e-6), k
    # missing measurements follow the height
    sb = scale_body(height=1.90)
    ref = measure(default_body())
    got = measure(sb.model, sb.pelvis_height)
    for k in ("shoulder_width", "upper_arm", "forearm"):
        assert got[k] == pytest.approx(ref[k] * 1.90 / ref["height"], rel=1e-6)
    # keypoints: the hand keypoint stays on the hand geom's end (scaled offset)
    q0 = jnp.zeros(sb.model.n_dof)
    kp = np.asarray(keypoints(sb.model, q0))
    kp_ref = np.asarray(keypoints(default_body(), q0))
    i = default_body().keypoint_names.index("l_hand")
    j = default_body().keypoint_names.index("l_wrist")
    assert np.linalg.norm(kp[i] - kp[j]) == pytest.approx(
        np.linalg.norm(kp_ref[i] - kp_ref[j]) * 1.90 / ref["height"], rel=1e-6)


def test_bad_measurement_is_one_clear_error():
    with pytest.raises(BodyScaleError, match="forearm"):
        scale_body(forearm=0.9)
    assert main(["body", "--height", "9", "--out", "/nonexistent_dir_x/b.urdf"]) == 2


@pytest.mark.parametrize("naming", ["jaxmocap", "left_right", "mixamo"])
@pytest.mark.parametrize("limbs", ["capsule", "box", "cylinder"])
def test_urdf_round_trip_and_pytorch_kinematics(scaled, tmp_path, rng, naming, limbs):
    model = swap_capsules(scaled.model, limbs)
    path = write_urdf(model, tmp_path / "b.urdf", link_names=naming)
    back = load_urdf(path)
    named = rename_body(model, naming)
    assert back.chain.dof_names == named.chain.dof_names
    assert set(back.chain.link_names) == set(named.chain.link_names)
    assert back.geometry.names == named.geometry.names
    np.testing.assert_array_equal(back.geometry.kind, model.geometry.kind)
    np.testing.assert_allclose(back.geometry.size, model.geometry.size, atol=1e-12)
    np.testing.assert_allclose(back.geometry.rgba, model.geometry.rgba, atol=1e-12)
    idx = [back.chain.link_names.index(n) for n in named.chain.link_names]
    q = random_q(model, 4, rng)
    chain = pk.build_chain_from_urdf(prepare_urdf(read_urdf_text(path))[1]).to(
        dtype=torch.float64)
    ref = chain.forward_kinematics(torch.tensor(q[:, 6:]))
    for k in range(len(q)):
        ours = np.asarray(fk(model.chain, jnp.asarray(q[k])))
        np.testing.assert_allclose(np.asarray(fk(back.chain, jnp.asarray(q[k])))[idx], ours,
                                   atol=1e-12)
        root = np.eye(4)
        root[:3, :3] = Rotation.from_rotvec(q[k, 3:6]).as_matrix()
        root[:3, 3] = q[k, :3]
        for i, name in enumerate(named.chain.link_names):
            np.testing.assert_allclose(root @ ref[name].get_matrix().numpy()[k], ours[i],
                                       atol=1e-6, err_msg=name)  # pk parses in float32
    if limbs != "capsule":
        kinds = np.asarray(model.geometry.kind)
        assert CAPSULE not in kinds and (BOX if limbs == "box" else CYLINDER) in kinds


@pytest.mark.parametrize("naming", ["left_right", "mixamo"])
def test_mjcf_round_trip_and_mujoco(scaled, tmp_path, rng, naming):
    model = swap_capsules(scaled.model, "cylinder")
    path = write_mjcf(model, tmp_path / "b.xml", link_names=naming)
    named = rename_body(model, naming)
    back = load_mjcf(path)
    assert back.chain.dof_names == named.chain.dof_names
    idx = [back.chain.link_names.index(n) for n in named.chain.link_names]
    m = mujoco.MjModel.from_xml_path(str(path))
    d = mujoco.MjData(m)
    for q in random_q(model, 4, rng):
        ours = np.asarray(fk(model.chain, jnp.asarray(q)))
        np.testing.assert_allclose(np.asarray(fk(back.chain, jnp.asarray(q)))[idx], ours,
                                   atol=1e-9)
        qpos = np.zeros(m.nq)
        for j in range(m.njnt):
            a = m.jnt_qposadr[j]
            if m.jnt_type[j] == mujoco.mjtJoint.mjJNT_FREE:
                qpos[a:a + 3] = q[:3]
                qpos[a + 3:a + 7] = np.roll(Rotation.from_rotvec(q[3:6]).as_quat(), 1)
            else:
                qpos[a] = q[named.chain.dof_names.index(m.joint(j).name)]
        d.qpos[:] = qpos
        mujoco.mj_kinematics(m, d)
        for i, name in enumerate(named.chain.link_names):
            b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, name)
            np.testing.assert_allclose(d.xpos[b], ours[i, :3, 3], atol=1e-9, err_msg=name)
            np.testing.assert_allclose(d.xmat[b].reshape(3, 3), ours[i, :3, :3], atol=1e-9)


def test_scaled_garment_keeps_patch_proportions(scaled, rng):
    """A surface point keeps its patch when body and garment scale together; the stretched
    shirt is the one the roles lay out on the scaled body (default_garment of it)."""
    g0 = default_garment(default_body())
    g1 = scale_garment(g0, scaled.geom_scale)
    g2 = default_garment(scaled.model)
    u = rng.normal(size=(400, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    for k in np.unique(np.asarray(g0.patch_geom)):
        r, h, c = np.asarray(default_body().geometry.size[k])
        kind = int(default_body().geometry.kind[k])
        extent = (r, r, h + r) if kind in (CAPSULE, CYLINDER) else (r, h, c)
        p0 = u * np.asarray(extent)  # points spread over the geom's bounding box
        p1 = p0 * scaled.geom_scale[k]  # the same material points, scaled
        geom = jnp.full((400,), int(k))
        want = np.asarray(patch_at(g0, geom, jnp.asarray(p0)))
        np.testing.assert_array_equal(patch_at(g1, geom, jnp.asarray(p1)), want)
        same = np.asarray(patch_at(g2, geom, jnp.asarray(p1))) == want
        assert same.mean() > 0.99, (default_body().geometry.names[k], same.mean())


def test_cli_writes_loadable_body(tmp_path, capsys):
    out = tmp_path / "b.xml"
    assert main(["body", "--height", "1.62", "--upper-arm", "0.28", "--naming", "left_right",
                 "--limbs", "box", "--out", str(out)]) == 0
    assert "height 1.620 m" in capsys.readouterr().out
    back = load_mjcf(out)
    assert "left_upper_arm" in back.chain.link_names
    assert BOX in np.asarray(back.geometry.kind)
    # the names follow a convention the roles infer: the 12 keypoints land where the scaled
    # body's are
    from jaxmocap.body import load_body

    body = load_body(out)
    sb = scale_body(height=1.62, upper_arm=0.28)
    q = jnp.zeros(body.n_dof)
    kp = np.asarray(keypoints(body, q))
    np.testing.assert_allclose(
        kp[[body.keypoint_names.index(n) for n in sb.model.keypoint_names]],
        keypoints(sb.model, q), atol=1e-6)  # roles round offsets to 1 um
