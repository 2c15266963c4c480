"""Elbow-swivel jumps on shoulders that are not the bundled body's x-y-z links
(:mod:`jaxmocap.trackers.stereo_pf.swivel`): dm_control's CMU humanoid (a clavicle of two
hinges, then a humerus z-y-x in a rotated frame) and URDFs whose shoulder hinges hang in rotated
frames. The oracle is forward kinematics: after the jump the shoulders, hands and head are
where they were, and each elbow has turned by exactly the drawn angle about its shoulder-hand
line at the same distance from it."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _foreign_body import SHOULDER_Y, SHOULDER_Z, foreign_urdf

from jaxmocap import camera as camlib
from jaxmocap.body import keypoint_index, keypoints, load_body
from jaxmocap.errors import InputError
from jaxmocap.trackers import stereo_pf as sp

NAMES = ("l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_hand", "r_hand", "head")


def _cams():
    return [camlib.look_at(jnp.array([2.5, y, 1.2]), jnp.array([0.0, 0.0, 1.0]), width=64,
                           height=48, fx=60.0) for y in (0.1, -0.1)]  # fmt: skip


def _params(model, fraction=0.1):
    return sp.make_params(_cams(), model=model, dtype=jnp.float64,
                          motion=sp.Motion(n_particles=8),
                          proposals=sp.Proposals(swivel_fraction=fraction))


def _check_swivel(model, params, rng, n=6, tol=1e-9):
    """FK oracle of one batch of jumps (jit + vmap); returns (state before, after)."""
    prop = params.filter.proposal
    lo, hi = np.asarray(params.prior_lower), np.asarray(params.prior_upper)
    s = rng.uniform(np.maximum(lo, -1.2), np.minimum(hi, 1.2), (n, lo.size))
    s[:, :6] = rng.normal(0.0, 0.3, (n, 6))
    s = jnp.asarray(s)
    phi = jnp.asarray(rng.uniform(-np.pi, np.pi, (n, 2)))
    moved = jax.jit(jax.vmap(prop._swivel))(s, phi)
    idx = keypoint_index(model, NAMES)
    for k in range(n):
        a = np.asarray(keypoints(model, params.full_q(s[k])))[idx]
        b = np.asarray(keypoints(model, params.full_q(moved[k])))[idx]
        np.testing.assert_allclose(b[[0, 1, 4, 5, 6]], a[[0, 1, 4, 5, 6]], atol=tol)
        for arm in range(2):
            sh, el, ha = arm, 2 + arm, 4 + arm
            u = (a[ha] - a[sh]) / np.linalg.norm(a[ha] - a[sh])
            va = a[el] - a[sh] - np.dot(a[el] - a[sh], u) * u
            vb = b[el] - a[sh] - np.dot(b[el] - a[sh], u) * u
            ang = np.arctan2(np.dot(np.cross(va, vb), u), np.dot(va, vb))
            np.testing.assert_allclose(np.linalg.norm(vb), np.linalg.norm(va), atol=tol)
            np.testing.assert_allclose(np.angle(np.exp(1j * (ang - float(phi[k, arm])))), 0.0,
                                       atol=tol / 1e-2)  # fmt: skip
    np.testing.assert_array_equal(moved[:, :6], s[:, :6])  # the root never moves
    return s, moved


def test_swivel_on_the_cmu_humanoid(rng):
    """dm_control's CMU humanoid: the humerus's three hinges turn about the shoulder's centre in
    a rotated frame (closed form); the clavicles and elbows keep their values."""
    from jaxmocap.body.packages import package_body

    model = package_body("cmu")
    params = _params(model)
    prop = params.filter.proposal
    assert [f.kind for f in prop.fits] == ["tait_bryan", "tait_bryan"]
    dof_names = [model.chain.dof_names[i] for i in params.dofs]
    solved = [dof_names[c] for arm in prop.arms for c in arm[0]]
    assert solved == ["lhumerusrz", "lhumerusry", "lhumerusrx",
                      "rhumerusrz", "rhumerusry", "rhumerusrx"]
    s, moved = _check_swivel(model, params, rng)
    kept = [i for i, n in enumerate(dof_names) if "clavicle" in n or "radius" in n]
    assert len(kept) == 6
    np.testing.assert_array_equal(moved[:, kept], s[:, kept])


def _gimbal_urdf(path, rpys):
    """The foreign body with each shoulder a chain of three revolute hinges (z, y, x) whose
    origins turn by ``rpys`` (the first also carries the shoulder's offset)."""
    text = foreign_urdf(path).read_text()
    for w, y in (("left", 1), ("right", -1)):
        old = (f'<joint name="{w}_shoulder" type="spherical"><parent link="torso"/>'
               f'<child link="{w}_upper_arm"/><origin xyz="0 {y * SHOULDER_Y} {SHOULDER_Z}"/>'
               "</joint>")
        assert old in text
        lim = '<limit lower="-3.1" upper="3.1" effort="1" velocity="1"/>'
        chain = [("torso", f"{w}_gimbal_a", f"0 {y * SHOULDER_Y} {SHOULDER_Z}", "0 0 1"),
                 (f"{w}_gimbal_a", f"{w}_gimbal_b", "0 0 0", "0 1 0"),
                 (f"{w}_gimbal_b", f"{w}_upper_arm", "0 0 0", "1 0 0")]
        new = "".join(
            f'<joint name="{w}_shoulder_{i}" type="revolute"><parent link="{p}"/>'
            f'<child link="{c}"/><origin xyz="{xyz}" rpy="{rpy}"/><axis xyz="{ax}"/>{lim}</joint>'
            + (f'<link name="{c}"/>' if i < 2 else "")
            for i, ((p, c, xyz, ax), rpy) in enumerate(zip(chain, rpys, strict=True)))
        text = text.replace(old, new)
    path.write_text(text)
    return path


@pytest.mark.parametrize("rpys, kind", [
    # the first frame turned only: the hinges' axes stay perpendicular -> closed form
    (("0.4 -0.6 0.9", "0 0 0", "0 0 0"), "tait_bryan"),
    # every frame turned: the axes are oblique -> Gauss-Newton
    (("0.4 -0.6 0.9", "0.3 0.2 -0.5", "-0.2 0.5 0.1"), "gauss_newton"),
])
def test_swivel_on_a_urdf_with_rotated_shoulder_frames(tmp_path, rng, rpys, kind):
    model = load_body(_gimbal_urdf(tmp_path / "gimbal.urdf", rpys))
    assert len(model.roles.dofs("l_shoulder")) == 3
    params = _params(model)
    assert [f.kind for f in params.filter.proposal.fits] == [kind, kind]
    _check_swivel(model, params, rng, tol=1e-9 if kind == "tait_bryan" else 1e-6)


def test_bundled_body_keeps_the_xyz_closed_form(rng):
    """The bundled body's shoulders take the round-1 x-y-z decomposition (bit-identical: the
    same code path, no per-arm fit)."""
    from jaxmocap.body import default_body

    params = _params(default_body())
    assert params.filter.proposal.fits is None


def test_a_shoulder_that_cannot_swivel_is_refused():
    """dm_control's plain humanoid: two shoulder hinges cannot turn the upper arm about three
    axes: one line naming the joints, the body file and the setting."""
    from jaxmocap.body.packages import package_body, package_body_file

    with pytest.raises(InputError) as e:
        _params(package_body("dmc_humanoid"))
    msg = str(e.value)
    assert "\n" not in msg and "swivel_fraction" in msg and "left_shoulder1" in msg
    assert str(package_body_file("dmc_humanoid")[0]) in msg
    _params(package_body("dmc_humanoid"), fraction=0.0)
