"""The stereo filter starts without a head (jaxmocap.trackers.stereo_pf.start): on the drawn
stereo scene of test_trackers_stereo_pf with the head and neck painted like the background (the
skin colour model never finds the head), the shirt silhouette places the torso, the filter
starts after the wait, says so, and reaches the drawn pose.

Oracles: the drawn pose's own forward kinematics (the torso's centre, the joints)."""

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_trackers_stereo_pf import BACKGROUND, _draw, _errors, drawn_scene

from jaxmocap import camera as camlib
from jaxmocap.body import fk, keypoint_index, keypoints
from jaxmocap.trackers import stereo_pf as sp
from jaxmocap.trackers.driver import START_ANCHOR_CODES, StereoPFFrameTracker, stereo_offline
from jaxmocap.trackers.stereo_pf import start as st

N_FRAMES = st.START_WAIT + 2


def _headless(model, q, cam):
    """The drawn image of pose q with the head and the neck painted over in the background's
    colour (discs 2 px wider than their spheres / capsules)."""
    img = _draw(model, q, cam)
    kp = np.asarray(keypoints(model, jnp.asarray(q)))
    for name, radius in (("head", 0.1), ("neck", 0.06)):
        p = kp[keypoint_index(model, [name])[0]]
        uv = np.asarray(camlib.project(cam, jnp.asarray(p)))
        z = float(np.asarray(camlib.to_camera(cam, jnp.asarray(p)))[2])
        r = float(cam.K[0, 0]) * radius / z + 2
        cv2.circle(img, (int(round(uv[0])), int(round(uv[1]))), int(np.ceil(r)), BACKGROUND, -1)
    return img


@pytest.fixture(scope="module")
def headless():
    return drawn_scene(N_FRAMES, 0.03, _headless)


def test_the_shirt_places_the_torso_where_no_head_is_found(headless):
    model, cams, frames, qs, kp, params, obs = headless
    valid = np.asarray(obs.valid)
    assert not valid[:, 0].any()  # the premise: the head is never triangulated
    lm = params.likelihood.limbs
    k = lm.names.index("torso")
    for t in range(N_FRAMES):
        tr = np.asarray(fk(model.chain, jnp.asarray(qs[t])))[lm.link[k]]
        true = tr[:3, :3] @ (0.5 * (np.asarray(lm.p0[k]) + np.asarray(lm.p1[k]))) + tr[:3, 3]
        got = st.shirt_anchor(params, np.asarray(obs.foreground[t]))
        # 1 px of disparity is ~15 cm of depth here: the sweep's plane beats a centroid pair
        assert np.linalg.norm(got - true) < 0.08, (t, got - true)
    # without a shirt region (blank frames) there is no anchor
    assert st.shirt_anchor(params, np.zeros_like(np.asarray(obs.foreground[0]))) is None
    # the offline rule: the wait for a head, then the shirt
    t0, anchor, start = st.start_frame(params, obs)
    assert (t0, anchor) == (st.START_WAIT - 1, "shirt") and start is not None
    # never from the head when asked, even where one is found; a head within the wait wins
    with_head = obs.__class__(edges=obs.edges, points=obs.points,
                              valid=obs.valid.at[2, 0].set(True), foreground=obs.foreground,
                              support=obs.support)
    assert st.start_frame(params, with_head)[:2] == (2, "head")
    assert st.start_frame(params, with_head, heads=False)[:2] == (st.START_WAIT - 1, "shirt")


def test_the_filter_starts_from_the_shirt_and_reaches_the_pose(headless, capsys):
    """On line: frames before the wait's end are not started (NaN, start_anchor 0), then the
    filter starts from the shirt (start_anchor 2, announced) and tracks; offline the same
    anchor. Without a head the blob tracker acquires no hand either (it names its entities
    from three candidates, jaxmocap.blobs), so the filter has the edge cue alone: the torso and
    shoulders are placed (median over three keys: N = 200 particles is a small set), the
    hands are not pinned. Azad's prior on the same frame (no point: the fallback root) is
    metres off."""
    model, cams, frames, qs, kp, params, obs = headless
    tr = StereoPFFrameTracker(cams, 200, 0)
    tr.start(frames[0])
    rows = [tr.step(frames[t]) for t in range(N_FRAMES)]
    w = st.START_WAIT - 1
    for r in rows[:w]:
        assert np.isnan(r.q).all() and not r.valid
        assert r.diagnostics["start_anchor"] == 0 and r.diagnostics["waiting_for_head"] == 1
    for r in rows[w:]:
        assert np.isfinite(r.q).all() and r.diagnostics["start_anchor"] == START_ANCHOR_CODES[
            "shirt"]
    assert f"started on frame {w} from the shirt silhouette" in capsys.readouterr().out
    q_live = np.stack([r.q for r in rows[w:]])
    assert np.linalg.norm(q_live[:, :3] - qs[w:, :3], axis=1).mean() < 0.15

    root, shoulders, joints, azad = [], [], [], []
    for seed in range(3):
        key = jax.random.key(seed)
        run = stereo_offline(params, key, frames, lambda: obs)
        assert (run.init_frame, run.anchor) == (w, "shirt")
        q = np.asarray(run.estimate.q)[w:]
        e = _errors(model, q, kp[w:])
        root.append(np.linalg.norm(q[:, :3] - qs[w:, :3], axis=1).mean())
        shoulders.append(e[:, :2].mean())
        joints.append(e.mean())
        state, _ = sp.init(params, key, jax.tree.map(lambda a: a[w], obs))  # no start
        _, est = sp.run(params, state, jax.tree.map(lambda a: a[w:], obs))
        azad.append(_errors(model, np.asarray(est.q), kp[w:]).mean())
    assert np.median(root) < 0.15 and np.median(shoulders) < 0.15, (root, shoulders)
    assert np.median(joints) < 0.3 and min(azad) > 1.0, (joints, azad)
