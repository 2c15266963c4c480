"""Tests of the subject-proportions fit (``jaxmocap.body.proportions``).

Oracle: a body of other proportions written as its own URDF (bones and keypoint offsets edited
in the file's text, loaded by the URDF loader), whose rest-pose segment lengths are measured
from its own keypoints; finite differences for the gradient.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxmocap.body import default_body, keypoints, load_urdf
from jaxmocap.body.model import DEFAULT_KEYPOINTS, DEFAULT_URDF
from jaxmocap.body.proportions import (
    SEGMENTS,
    ProportionsError,
    fit_proportions,
    scaled_body,
    scaled_kinematics,
    segment_lengths,
    segment_table,
)
from jaxmocap.camera import look_at, project, stack_cameras

# Edits of the bundled URDF (joint -> new origin xyz): longer upper arms (0.30 -> 0.335),
# shorter forearms (0.26 -> 0.235), shoulders 8% further from the chest point, a 6% longer
# trunk (spine and neck joints, and the chest point with them). Keypoints: bigger hands,
# a smaller head. Each segment changes as a whole (the fit's family: one factor per segment).
EDITS = {"l_elbow": "0 0 -0.335", "r_elbow": "0 0 -0.335", "l_wrist_x": "0 0 -0.235",
         "r_wrist_x": "0 0 -0.235", "l_shoulder_x": "0 0.1944 0.4432",
         "r_shoulder_x": "0 -0.1944 0.4432", "spine_x": "0 0 0.106", "neck_x": "0 0 0.4558"}
# fmt: skip


def _edited_body(tmp_path):
    text = DEFAULT_URDF.read_text()
    for joint, xyz in EDITS.items():
        text, n = re.subn(rf'(<joint name="{joint}"[^>]*>\s*<parent[^>]*/>\s*<child[^>]*/>\s*'
                          r'<origin xyz=")[^"]*', rf"\g<1>{xyz}", text)  # fmt: skip
        assert n == 1, joint
    path = tmp_path / "subject.urdf"
    path.write_text(text)
    kp = dict(DEFAULT_KEYPOINTS)
    kp["l_hand"], kp["r_hand"] = ("l_hand", (0, 0, -0.105)), ("r_hand", (0, 0, -0.105))
    kp["head"] = ("head", (0, 0, 0.135))
    kp["chest"] = ("chest", (0, 0, 0.318))
    return load_urdf(path, keypoints=kp)


def _rig():
    cams = [look_at((2.6, 1.2 * s, 1.3), (0.0, 0.0, 1.2), width=640, height=480, fx=520.0)
            for s in (-1, 1)]  # fmt: skip
    return stack_cameras(cams)


def _observations(body, cams, n_frames, rng, noise_px):
    q = np.zeros((n_frames, body.n_dof))
    q[:, 2] = 0.9
    q[:, 5] = rng.uniform(-0.6, 0.6, n_frames)
    lo, hi = np.asarray(body.chain.lower), np.asarray(body.chain.upper)
    q[:, 6:] = rng.uniform(np.maximum(lo[6:], -1.2), np.minimum(hi[6:], 1.2)) * 0.8
    kp = jax.vmap(lambda qt: keypoints(body, qt))(jnp.asarray(q))
    uv = jax.vmap(lambda c: jax.vmap(lambda x: project(c, x))(kp), out_axes=1)(cams)
    uv = np.asarray(uv) + rng.normal(0, noise_px, np.shape(uv))
    return q, jnp.asarray(uv)


def test_segment_table_by_roles():
    model = default_body()
    t = segment_table(model)
    names = model.chain.link_names
    owned = {names[i]: t.names[s] for i, s in enumerate(t.link_segment) if s >= 0}
    assert owned["l_forearm"] == owned["r_forearm"] == "upper_arm"  # the elbow bone
    assert owned["l_hand__x"] == "forearm" and owned["l_upper_arm__x"] == "shoulders"
    assert owned["head__x"] == "torso" and "pelvis" not in owned
    # the identity scales change nothing; a factor scales exactly its segment's lengths
    same = scaled_kinematics(model, t, jnp.ones(len(SEGMENTS)))
    np.testing.assert_allclose(keypoints(same, jnp.zeros(model.n_dof)),
                               keypoints(model, jnp.zeros(model.n_dof)), atol=1e-12)
    s = np.ones(len(SEGMENTS))
    s[list(SEGMENTS).index("forearm")] = 1.2
    before, after = segment_lengths(model), segment_lengths(scaled_body(model, s))
    for name in SEGMENTS:
        assert after[name] == pytest.approx(before[name] * (1.2 if name == "forearm" else 1))


def test_fit_recovers_segment_lengths(tmp_path):
    """Lengths of a body of other proportions recovered within 1 cm from 8 frames of two
    cameras (0.5 px noise), starting from the generic body and perturbed poses."""
    rng = np.random.default_rng(3)
    truth = _edited_body(tmp_path)
    generic = default_body()
    cams = _rig()
    q, uv = _observations(truth, cams, 8, rng, noise_px=0.5)
    visible = jnp.ones(uv.shape[:3], bool)
    q0 = q + rng.normal(0, 0.1, q.shape) * (np.arange(q.shape[1]) >= 3)
    fit = jax.jit(lambda uv, q0: fit_proportions(generic, cams, uv, visible, q0))(uv, q0)
    assert fit.rms_px < 1.0
    want = segment_lengths(truth)
    got = segment_lengths(scaled_body(generic, fit.scales))
    for name in SEGMENTS:
        assert abs(got[name] - want[name]) < 0.01, (name, got[name], want[name])
    # the generic body itself is off by more than that on the edited segments
    base = segment_lengths(generic)
    assert max(abs(base[n] - want[n]) for n in ("upper_arm", "forearm", "hand")) > 0.015


def test_fit_gradient_matches_finite_differences(tmp_path):
    rng = np.random.default_rng(4)
    generic = default_body()
    cams = _rig()
    q, uv = _observations(_edited_body(tmp_path), cams, 1, rng, noise_px=0.0)
    visible = jnp.ones(uv.shape[:3], bool)
    k = list(SEGMENTS).index("forearm")

    def forearm(shift):  # move every observed left-wrist pixel by `shift` along x
        i = generic.keypoint_names.index("l_wrist")
        return fit_proportions(generic, cams, uv.at[:, :, i, 0].add(shift), visible,
                               jnp.asarray(q)).scales[k]  # fmt: skip

    g = jax.jit(jax.grad(forearm))(0.0)
    f = jax.jit(forearm)
    eps = 1e-3
    fd = (f(eps) - f(-eps)) / (2 * eps)
    assert abs(g) > 1e-5
    np.testing.assert_allclose(g, fd, rtol=2e-3, atol=1e-7)


def test_missing_keypoint_role_is_one_line():
    from jaxmocap.body import BodyModel

    model = default_body()
    names = tuple("x" if n == "l_elbow" else n for n in model.keypoint_names)
    bad = BodyModel(chain=model.chain, geometry=model.geometry, keypoint_link=model.keypoint_link,
                    keypoint_offset=model.keypoint_offset, keypoint_names=names)
    with pytest.raises(ProportionsError, match=r"no keypoints \['l_elbow'\]"):
        segment_table(bad)
