"""The colour-shirt tracker (Wang et al. 2011 §4–5): helpers vs OpenCV, one frame step on a
rendered database pose, recompiles, ablation switches.

Small settings: two 240x180 cameras, a 1,500-pose database sampled around the cameras' view,
a 96-pixel working crop. The step is compiled once for the whole module.
"""

import dataclasses

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.extend.core import ClosedJaxpr, Jaxpr

from jaxmocap.body import default_body, keypoints
from jaxmocap.camera import look_at, stack_cameras
from jaxmocap.garment import default_garment
from jaxmocap.ik import IKCovariances, anchors_from_garment
from jaxmocap.posedb._sample import SamplingConfig, canonical_camera, sample_poses
from jaxmocap.posedb._search import make_posedb
from jaxmocap.render import render_rgb, tiny_id_maps
from jaxmocap.trackers import shirt
from jaxmocap.trackers.shirt import frame as shirt_frame

W_IMG, H_IMG = 240, 180
ROOT = np.array([0.0, 0.0, 0.85])


@pytest.fixture(scope="module")
def setup():
    model = default_body()
    garment = default_garment(model)
    rng = np.random.default_rng(3)
    lo, hi = np.asarray(model.chain.lower)[6:], np.asarray(model.chain.upper)[6:]
    pool = np.zeros((300, model.n_dof))
    pool[:, 6:] = np.clip(rng.uniform(-0.6, 0.6, (300, model.n_dof - 6)), lo, hi)
    cfg = SamplingConfig(size=1500, seed=1, yaw_range=0.5, pitch_range=0.15, roll_range=0.1)
    poses = sample_poses(cfg, model, pool).astype(np.float64)
    canon = canonical_camera()
    maps = np.asarray(tiny_id_maps(model, garment, jnp.asarray(poses), canon))
    db = make_posedb(maps, poses, garment.n_colours)
    cams_l = [
        look_at([2.75, y, 1.3], [0.0, 0.0, 1.15], width=W_IMG, height=H_IMG, fx=208.0)
        for y in (-0.6, 0.6)
    ]
    cams = stack_cameras(cams_l)
    bg = jnp.full((H_IMG, W_IMG, 3), 128, jnp.uint8)
    render = jax.jit(lambda q, cam: render_rgb(model, garment, q, cam, bg))
    # colour model from scribbles on five white-balanced renders (cheap: one camera's size)
    color = shirt.fit_color_model_from_renders(model, garment, poses[:5] + _at_root(), cams_l[0])
    q_true = jnp.asarray(poses[7] + _at_root())
    outs = [render(q_true, c) for c in cams_l]
    frames = np.stack([np.asarray(o[0]) for o in outs])
    labels = np.stack([shirt.scribbles(np.asarray(o[1].colour)) for o in outs])
    W0 = shirt.initial_white_balance(color, frames, labels)
    anchors = anchors_from_garment(model, garment)
    cov = IKCovariances.isotropic(2.0, 0.3, 0.5, model.n_dof)
    params = shirt.make_params(color, model, garment, cams, anchors, cov, db,
                               search=shirt.Search(work_size=96))
    ids = np.stack([np.asarray(o[1].colour) for o in outs])
    return dict(model=model, params=params, frames=frames, q_true=q_true, W0=W0, ids=ids)


def _at_root() -> np.ndarray:
    off = np.zeros(default_body().n_dof)
    off[:3] = ROOT
    return off


def test_step_recovers_a_database_pose_without_recompiling(setup):
    p, model = setup["params"], setup["model"]
    state = shirt.init(p, setup["W0"], jnp.zeros(model.n_dof))
    before = shirt.TRACE_COUNT["step"]
    state, out = shirt.step(p, state, setup["frames"])
    state2, out2 = shirt.step(p, state, setup["frames"])
    assert shirt.TRACE_COUNT["step"] == before + 1  # one trace for both frames
    kp = jax.jit(lambda q: keypoints(model, q))
    truth = np.asarray(kp(setup["q_true"]))
    for o in (out, out2):
        assert bool(o.valid)
        err = np.linalg.norm(np.asarray(kp(o.q)) - truth, axis=-1)
        assert err.mean() < 0.08, err  # metres (5.5 cm measured; see docs/results/shirt.md)
        assert np.asarray(o.visible).sum() >= 2 * 10
    # the refined pose is closer than the placed database blend
    err_b = np.linalg.norm(np.asarray(kp(out.q_blend)) - truth, axis=-1).mean()
    err_q = np.linalg.norm(np.asarray(kp(out.q)) - truth, axis=-1).mean()
    assert err_q <= err_b + 1e-3
    # white light: W* stays near the scribbled W0 (r* includes darker silhouette pixels that
    # the eroded scribbles leave out) and no reference is added
    np.testing.assert_allclose(np.asarray(state2.W), np.asarray(setup["W0"]), atol=0.25)
    assert not bool(jnp.any(out.added_reference))


def test_settings_numbers_are_traced_and_switches_static(setup):
    """The settings groups' numbers are array leaves of the parameters (a new value reuses a
    compiled program: here the patch-colour learning threshold of :class:`shirt.Colours`) and
    their switches are static (a new one is a new program)."""
    import equinox as eqx

    p = setup["params"]
    traces = []

    @eqx.filter_jit
    def read(params):
        traces.append(1)
        return params.colours.learn_max_residual + params.validity.min_agreement

    read(p)
    other = shirt.make_params(p.color, p.body, p.garment, p.cams, p.anchors, p.cov, p.db,
                              search=p.search, colours=shirt.Colours(learn_max_residual=0.1))
    assert float(read(other)) == pytest.approx(0.1 + shirt.MIN_AGREEMENT)
    assert len(traces) == 1  # same program, new value
    follow = dataclasses.replace(other.colours, follow_light=True)
    read(dataclasses.replace(other, colours=follow))
    assert len(traces) == 2  # a switch is a new program


def test_validity_thresholds_are_traced(setup):
    """A new threshold value reuses the compiled step and changes the flag as the rule says:
    the same frame is valid at the default patch count and invalid when more centroids are
    asked for than the garment has."""
    p, model = setup["params"], setup["model"]
    state = shirt.init(p, setup["W0"], jnp.zeros(model.n_dof))
    dt = p.cams.K.dtype
    _, out = shirt.step(p, state, setup["frames"])
    before = shirt.TRACE_COUNT["step"]
    strict = dataclasses.replace(
        p, validity=shirt.validity_rule(dt, min_patches=10 * p.garment.n_patches))
    _, out_strict = shirt.step(strict, state, setup["frames"])
    assert shirt.TRACE_COUNT["step"] == before  # same program, new threshold
    assert bool(out.valid) and not bool(out_strict.valid)
    # a check switched on is a new program (structure is static)
    reporting = dataclasses.replace(p, validity=shirt.validity_rule(dt, min_recall=0.0))
    _, out_rep = shirt.step(reporting, state, setup["frames"])
    assert shirt.TRACE_COUNT["step"] == before + 1
    assert bool(out_rep.valid) == bool(out.valid)  # recall >= 0 holds wherever it is measured


def test_loss_and_reacquisition(setup):
    """The subject gone (a blank frame): the frame is invalid, the pose held and the tracked
    count reset; back in view, the next frame is a reacquisition (second start without the
    pose prior, extra rounds, widened temporal prior) and is within tolerance at once."""
    p, model = setup["params"], setup["model"]
    kp = jax.jit(lambda q: keypoints(model, q))
    truth = np.asarray(kp(setup["q_true"]))
    state = shirt.init(p, setup["W0"], jnp.zeros(model.n_dof))
    assert int(state.tracked) == 0
    for k in (1, 2):
        state, out = shirt.step(p, state, setup["frames"])
        assert bool(out.valid) and int(state.tracked) == k
        np.testing.assert_array_equal(np.asarray(out.q_frame), np.asarray(out.q))
    blank = np.full_like(setup["frames"], 128)
    held = np.asarray(state.q)
    state, lost = shirt.step(p, state, blank)
    assert not bool(lost.valid) and int(state.tracked) == 0
    np.testing.assert_array_equal(np.asarray(lost.q), held)
    assert np.isnan(np.asarray(lost.q_frame)).all()  # nothing measured: no own estimate
    state, back = shirt.step(p, state, setup["frames"])
    assert bool(back.valid) and int(state.tracked) == 1
    assert np.linalg.norm(np.asarray(kp(back.q)) - truth, axis=-1).mean() < 0.08


def test_orientation_hypotheses_start_only_after_a_loss(setup):
    """With ``orientation_hypotheses`` (opt-in) the first (lost) frame tries every camera's
    placed orientation hypotheses beside the usual starts and is within tolerance of the
    truth; a tracked frame runs exactly the default program's arithmetic (the hypotheses are
    not started there), so its outputs are bitwise the default's."""
    p, model = setup["params"], setup["model"]
    ph = dataclasses.replace(p, rounds=dataclasses.replace(p.rounds, orientation_hypotheses=2))
    kp = jax.jit(lambda q: keypoints(model, q))
    truth = np.asarray(kp(setup["q_true"]))
    state0 = shirt.init(p, setup["W0"], jnp.zeros(model.n_dof))
    st_h, first = shirt.step(ph, state0, setup["frames"])
    assert bool(first.valid)
    assert np.linalg.norm(np.asarray(kp(first.q)) - truth, axis=-1).mean() < 0.08
    dt = p.cams.K.dtype

    @eqx.filter_jit  # one program (op by op, these calls compiled ~1,100 small ones)
    def n_hypotheses(ph, state, frames):
        views = shirt_frame.locate_and_classify(ph, state, frames, None)
        return shirt_frame.orientation_starts(ph, views, shirt_frame.database_pose(ph, views, dt),
                                              dt)[1]

    n = int(n_hypotheses(ph, state0, jnp.asarray(setup["frames"])))
    assert 1 <= n <= 2 * p.n_cams  # real hypotheses, from both cameras
    tracked, _ = shirt.step(p, state0, setup["frames"])
    _, a = shirt.step(p, tracked, setup["frames"])
    _, b = shirt.step(ph, tracked, setup["frames"])
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b), strict=True):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_own_start_carries_an_invalid_frames_estimate(setup):
    """``own_start``: a frame flagged invalid (here by a rule that asks for more centroids than
    the garment has) still leaves its own estimate in the state (``q_own``) while ``q``
    holds the last valid pose; the next frame, a reacquisition, starts from it among the
    others and lands within tolerance of the truth; without the switch the state has no
    ``q_own`` (the state of before)."""
    p, model = setup["params"], setup["model"]
    dt = p.cams.K.dtype
    assert p.rounds.own_start  # the default
    strict = dataclasses.replace(
        p, validity=shirt.validity_rule(dt, min_patches=10 * p.garment.n_patches))
    kp = jax.jit(lambda q: keypoints(model, q))
    truth = np.asarray(kp(setup["q_true"]))
    state = shirt.init(strict, setup["W0"], jnp.zeros(model.n_dof))
    off = dataclasses.replace(p, rounds=dataclasses.replace(p.rounds, own_start=False))
    assert shirt.init(off, setup["W0"], jnp.zeros(model.n_dof)).q_own is None
    for _ in range(2):
        held = np.asarray(state.q)
        state, out = shirt.step(strict, state, setup["frames"])
        assert not bool(out.valid)
        np.testing.assert_array_equal(np.asarray(state.q), held)  # nothing valid yet
        np.testing.assert_array_equal(np.asarray(state.q_own), np.asarray(out.q_frame))
        assert np.linalg.norm(np.asarray(kp(out.q_frame)) - truth, axis=-1).mean() < 0.08


def test_widened_temporal_covariance_matches_numpy(rng):
    """Sigma_p + Sigma_b for the frames after a loss, for vectors of variances and matrices."""
    a = rng.uniform(0.1, 1.0, 5)
    B = rng.normal(size=(5, 5))
    B = B @ B.T
    for prior, blend, ref in (
        (a, 2 * a, 3 * a),
        (a, B, np.diag(a) + B),
        (B, a, B + np.diag(a)),
    ):
        got = shirt_frame._widened(jnp.asarray(prior), jnp.asarray(blend), jnp.asarray(True))
        np.testing.assert_allclose(np.asarray(got), ref, rtol=1e-12)
        kept = shirt_frame._widened(jnp.asarray(prior), jnp.asarray(blend), jnp.asarray(False))
        np.testing.assert_allclose(np.asarray(kept), np.diag(prior) if ref.ndim > prior.ndim
                                   else prior, rtol=1e-12)  # fmt: skip


def test_step_with_foreground_masks(setup):
    """The background-subtraction path (masks through the search and every vmapped camera
    stage): all-foreground masks give the step without masks; the shirt's silhouettes,
    dilated by 3 px, keep the frame valid and as accurate."""

    p, model = setup["params"], setup["model"]
    state = shirt.init(p, setup["W0"], jnp.zeros(model.n_dof))
    frames = setup["frames"]
    _, plain = shirt.step(p, state, frames)
    _, full = shirt.step(p, state, frames, np.ones(frames.shape[:3], bool))
    np.testing.assert_allclose(np.asarray(full.q), np.asarray(plain.q), atol=1e-4)
    assert bool(full.valid) == bool(plain.valid)
    np.testing.assert_array_equal(np.asarray(full.visible), np.asarray(plain.visible))
    body = np.stack([cv2.dilate((m > 0).astype(np.uint8), np.ones((7, 7), np.uint8)) > 0
                     for m in setup["ids"]])  # fmt: skip
    _, out = shirt.step(p, state, frames, body)
    kp = jax.jit(lambda x: keypoints(model, x))
    err = np.linalg.norm(np.asarray(kp(out.q)) - np.asarray(kp(setup["q_true"])), axis=-1)
    assert bool(out.valid) and err.mean() < 0.08, err


def test_ablation_switches_change_the_program(setup):
    p = setup["params"]
    state = shirt.init(p, setup["W0"], jnp.zeros(p.body.n_dof))
    frames = jnp.asarray(setup["frames"])

    def count(jaxpr) -> int:  # equations, those of nested jaxprs (scan, cond, jit) included
        n = 0
        for eqn in jaxpr.eqns:
            n += 1
            for v in eqn.params.values():
                for sub in v if isinstance(v, (tuple, list)) else (v,):
                    if isinstance(sub, ClosedJaxpr):
                        n += count(sub.jaxpr)
                    elif isinstance(sub, Jaxpr):
                        n += count(sub)
        return n

    def n_eqns(params):
        jaxpr = jax.make_jaxpr(lambda s, f: shirt_frame._step(params, s, f, None))(state, frames)
        return count(jaxpr.jaxpr)

    full = n_eqns(p)
    no_wb = n_eqns(dataclasses.replace(p, ablations=shirt.Ablations(adaptive_white_balance=False)))
    no_prior = n_eqns(dataclasses.replace(p, ablations=shirt.Ablations(pose_prior=False)))
    assert no_wb < full  # no W* refit, no rendering of r*
    assert no_prior != full
    paper_loss = dataclasses.replace(p, rounds=dataclasses.replace(
        p.rounds, reacquire_start=False, reacquire_passes=0, reacquire_frames=0))
    assert n_eqns(paper_loss) < full  # no lax.cond of extra rounds, no widened prior


def test_step_with_shading_and_scene_colours(setup):
    """Issue 17's options for footage under spot lamps (shading-invariant colour distance, the
    room's colour Gaussians from the non-shirt pixels, white-balanced by W0) keep the frame
    valid and as accurate on the own renderer; make_params refuses a bad brightness range."""
    from jaxmocap.color import fit_scene_colors

    p, model = setup["params"], setup["model"]
    room = [shirt.scribbles((m == 0).astype(np.int32), 3) > 0 for m in setup["ids"]]
    scene = fit_scene_colors(list(setup["frames"]), room, list(np.asarray(setup["W0"])), 8)
    q = dataclasses.replace(p, colours=shirt.Colours(shading=(0.5, 4.0), scene_colors=scene))
    state = shirt.init(q, setup["W0"], jnp.zeros(model.n_dof))
    state, out = shirt.step(q, state, setup["frames"])
    kp = jax.jit(lambda x: keypoints(model, x))
    err = np.linalg.norm(np.asarray(kp(out.q)) - np.asarray(kp(setup["q_true"])), axis=-1)
    assert bool(out.valid) and err.mean() < 0.08, err
    assert float(jnp.min(out.fraction)) > 0.1  # the shirt is still classified
    # every frame invalid (an agreement gate no render can pass): hold_invalid=False still
    # reports the frame's own estimate; the state keeps the last valid pose (here the initial)
    r = dataclasses.replace(q, validity=shirt.validity_rule(
        p.cams.K.dtype, min_agreement=1.5, gate_min_fraction=0.0, hold_invalid=False))
    state = shirt.init(r, setup["W0"], jnp.zeros(model.n_dof))
    state, out = shirt.step(r, state, setup["frames"])
    assert not bool(out.valid) and not np.any(np.asarray(state.q))
    err = np.linalg.norm(np.asarray(kp(out.q)) - np.asarray(kp(setup["q_true"])), axis=-1)
    assert err.mean() < 0.08, err
    with pytest.raises(ValueError, match="shading"):
        shirt.make_params(p.color, model, p.garment, p.cams, p.anchors, p.cov, p.db,
                          colours=shirt.Colours(shading=(2.0, 4.0)))


def test_frame_signals_and_the_calibrated_validity_checks(setup):
    """Issue 17's validity signals of a tracked frame of the own renderer: the centroid
    residual equals the one recomputed from the model's centroids at the output pose
    (``model_centroids``, an independent render on the output windows) and is small, most
    rendered shirt pixels carry their colour in step 1; with ``max_residual=0`` (no real pose
    reaches it) the same frame is reported invalid while everything measured, and the state
    (which follows the tracker's own rule), stays bitwise equal."""
    p, model = setup["params"], setup["model"]
    state0 = shirt.init(p, setup["W0"], jnp.zeros(model.n_dof))
    st, out = shirt.step(p, state0, setup["frames"])
    sig = jax.device_get(out.signals)
    mc = jax.device_get(shirt.model_centroids(p, out.q, out.window))
    use = np.asarray(out.visible) & np.asarray(mc.valid)
    d = np.linalg.norm(np.asarray(out.centroids) - np.asarray(mc.xy), axis=-1)
    ref = np.array([d[i][use[i]].mean() for i in range(2)]) / np.asarray(out.window)[:, 2]
    np.testing.assert_allclose(sig.residual, ref, rtol=1e-4, atol=1e-6)
    assert bool(out.valid) and np.all(sig.residual < 0.03), sig.residual
    assert np.all(sig.recall > 0.5) and np.all(sig.coverage > 0.5), sig
    assert float(sig.root_jump) == 0.0  # first frame: after a loss
    dt = p.cams.K.dtype
    strict = dataclasses.replace(p, validity=shirt.validity_rule(dt, max_residual=0.0,
                                                                 min_recall=0.0))
    st2, out2 = shirt.step(strict, shirt.init(strict, setup["W0"], jnp.zeros(model.n_dof)),
                           setup["frames"])
    assert not bool(out2.valid) and bool(st2.valid)
    for a, b in zip(jax.tree.leaves(st), jax.tree.leaves(st2), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    for a, b in zip(jax.tree.leaves(out.signals), jax.tree.leaves(out2.signals), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(out.centroids), np.asarray(out2.centroids))
    # a rule that passes everything: the flag follows whether the output pose is this
    # frame's solution. The tracker's own gate made impossible (agreement > 1): with
    # hold_invalid the output is the held pose and never reported valid; without, the
    # frame's own estimate is output and the rule reports it
    lenient = dict(min_agreement=1.1, gate_min_fraction=0.0, report_patches=0,
                   max_residual=1.0, min_recall=0.0)
    for hold in (True, False):
        pl = dataclasses.replace(p, validity=shirt.validity_rule(dt, hold_invalid=hold,
                                                                 **lenient))
        st3, out3 = shirt.step(pl, shirt.init(pl, setup["W0"], jnp.zeros(model.n_dof)),
                               setup["frames"])
        assert not bool(st3.valid)
        assert bool(out3.valid) == (not hold)
        same = np.array_equal(np.asarray(out3.q), np.asarray(st3.q))  # the held (initial) q
        assert same == hold
        # the frame's own solution is output beside it either way (jaxmocap track writes
        # it): the same IK result as the valid frame's, whatever the rule said
        np.testing.assert_allclose(np.asarray(out3.q_frame), np.asarray(out.q), atol=1e-5)
    with pytest.raises(ValueError, match="max_residual"):
        shirt.make_params(p.color, model, p.garment, p.cams, p.anchors, p.cov, p.db,
                          validity=shirt.validity_rule(max_residual=2.0))


def test_invalid_inputs(setup):
    p = setup["params"]
    state = shirt.init(p, setup["W0"], jnp.zeros(p.body.n_dof))
    with pytest.raises(ValueError, match="frames must be"):
        shirt.step(p, state, setup["frames"][:1])
    with pytest.raises((ValueError, TypeError)):  # TypeError from the runtime type check
        shirt.step(p, state, jnp.asarray(setup["frames"], jnp.float32))
    with pytest.raises((ValueError, TypeError)):
        shirt.init(p, jnp.eye(3), jnp.zeros(p.body.n_dof))


def test_bundled_trained_covariances():
    """The covariances saved with the model load, are positive definite, match the default
    body's DOFs, and a body of another size is refused with a message naming the file."""
    from jaxmocap.body import default_body

    n = default_body().n_dof
    cov = shirt.trained_covariances(n)
    assert np.all(np.linalg.eigvalsh(np.asarray(cov.centroid)) > 0)
    for term in (cov.blend, cov.prior):
        assert np.asarray(term).shape[-1] == n and np.all(np.isfinite(np.asarray(term)))
    with pytest.raises(ValueError, match="shirt_ik_cov.npz.*DOF"):
        shirt.trained_covariances(n + 1)


def test_step_renders_with_static_geom_kinds(setup):
    """Inside the jitted step the body's arrays are traced; with ``static_kinds``,
    ``params.render_body`` keeps the geom kinds static so that the ray caster runs each geom's
    own primitive test (per-kind groups, not one group of every kind), and renders what the
    body as given renders."""
    import equinox as eqx

    from jaxmocap.render import render_uv
    from jaxmocap.render._raycast import kind_groups

    p, model = setup["params"], setup["model"]
    assert p.rounds.static_kinds  # the default
    traced_kinds = dataclasses.replace(p.rounds, static_kinds=False)
    assert dataclasses.replace(p, rounds=traced_kinds).render_body is p.body
    assert p.geom_kinds == tuple(int(k) for k in np.asarray(model.geometry.kind))
    seen = {}

    @eqx.filter_jit
    def patches(p, q, uv):
        seen["traced"] = kind_groups(p.body)[1]
        seen["static"] = kind_groups(p.render_body)[1]
        cam = jax.tree.map(lambda a: a[0], p.cams)
        return render_uv(p.render_body, p.garment, q, cam, uv).patch

    uv = shirt.crop_uv(jnp.asarray([60.0, 20.0, 120.0, 120.0]), 48)
    got = np.asarray(patches(p, setup["q_true"], uv))
    kinds = np.unique(np.asarray(model.geometry.kind))
    assert seen["traced"][0][0] is None  # the traced body: one group of every kind
    assert [g[0] for g in seen["static"]] == kinds.tolist()
    cam0 = jax.tree.map(lambda a: a[0], p.cams)
    ref = np.asarray(render_uv(model, p.garment, setup["q_true"], cam0, uv).patch)  # eager
    assert np.mean(got == ref) > 0.995 and (ref > 0).sum() > 100


def test_patch_colours_follow_a_lamp_change(setup):
    """Issue 37's per-patch colour states in the tracker: tracked under white light, then
    under a warm lamp on one half of each image and a dimmer cool one on the other (per-pixel
    channel gains), every frame within tolerance and, from the frame after the switch on,
    valid again; the patches' states follow the lamp that lights them (their means'
    chromaticity moves to that lamp's, both lamps among them); a blank frame is invalid and
    leaves every state untouched. Without the light followed from the held pose
    (``follow_light``) every frame after the switch stayed invalid (measured: 1-3% of the
    crops classified)."""
    p, model = setup["params"], setup["model"]
    q = dataclasses.replace(p, colours=shirt.Colours(shading=(0.5, 4.0), patch_colours=True,
                                                     follow_light=True))
    kp = jax.jit(lambda x: keypoints(model, x))
    truth = np.asarray(kp(setup["q_true"]))
    state = shirt.init(q, setup["W0"], jnp.zeros(model.n_dof))
    warm, cool = np.array([1.0, 0.8, 0.55]), np.array([0.6, 0.7, 0.85])
    half = (np.arange(W_IMG) < W_IMG // 2)[None, :, None]
    gains = np.where(half, warm, cool)  # (1, W, 3): left half warm, right half cool
    lit = np.clip(setup["frames"].astype(np.float64) * gains[None], 0, 255).astype(np.uint8)
    start = np.asarray(state.look.mean)
    valid = []
    for frames in [setup["frames"]] * 2 + [lit] * 6:
        state, out = shirt.step(q, state, frames)
        err = np.linalg.norm(np.asarray(kp(out.q)) - truth, axis=-1).mean()
        valid.append(bool(out.valid))
        assert err < 0.08, err
    # the switch frame itself classifies almost nothing (invalid, the light followed from the
    # held pose, appearance.follow_light); from the next frame on it is tracked again
    assert valid[:2] == [True, True] and all(valid[3:]), valid
    assert int(np.asarray(out.colour_updated).min()) >= 8
    moved = np.asarray(state.look.mean) / start  # (n_cams, P, 3)
    chroma = moved / moved.sum(-1, keepdims=True)
    near = lambda g: np.linalg.norm(chroma - g / g.sum(), axis=-1)  # noqa: E731
    warm_like = near(warm) < near(cool)
    assert warm_like.any() and (~warm_like).any()  # both lamps are followed
    before = jax.tree.map(np.asarray, state.look)
    state, out = shirt.step(q, state, np.full_like(setup["frames"], 128))
    assert not bool(out.valid)
    for a, b in zip(jax.tree.leaves(before)[:5], jax.tree.leaves(state.look)[:5], strict=True):
        np.testing.assert_array_equal(a, np.asarray(b))


@pytest.fixture(scope="module")
def skin_setup(setup):
    """The tracker with ``skin_terms`` (skin colour from the garment's albedo) and one frame's
    round inputs at the true pose."""
    p, model = setup["params"], setup["model"]
    ps = shirt.make_params(p.color, model, p.garment, p.cams, p.anchors, p.cov, p.db,
                           search=p.search, rounds=shirt.Rounds(skin_terms=True))
    state = shirt.init(ps, setup["W0"], jnp.zeros(model.n_dof))
    state = dataclasses.replace(state, valid=jnp.array(True))  # a tracked frame
    q = setup["q_true"]

    @eqx.filter_jit  # one program instead of hundreds of ops dispatched one by one
    def round_inputs(ps, state, frames, q):
        views = shirt_frame.locate_and_classify(ps, state, frames, None)
        ctx = shirt_frame.round_context(ps, state, views, views.found, q)
        return ctx, shirt_frame.render_views(ps, ctx, q)

    ctx, hits = round_inputs(ps, state, jnp.asarray(setup["frames"]), q)
    return dict(ps=ps, state=state, ctx=ctx, hits=hits, q=q)


@eqx.filter_jit
def _observe(ps, ctx, hits, q, observed=None):
    from jaxmocap.trackers.shirt.skin import observe_skin

    return observe_skin(ps.skin, ps.body.chain, ps.cams, q, hits.geom, hits.point, ctx.uvs,
                        ctx.views.windows, ctx.skin if observed is None else observed, ctx.okq)


def test_skin_centroids_observed_at_the_rendered_skin(setup, skin_setup):
    """At the true pose every camera sees head and both hands: each observed skin centroid
    (the pixels classified as skin near the prediction) lies within 1.5 px of the centroid of
    the part's skin in an independent full-frame render (NumPy over the ray caster's geom ids,
    here the skin geoms on the part's role link and below), and the per-view anchors predict
    the rendered centroid exactly at that pose."""
    from jaxmocap.ik import project_anchors
    from jaxmocap.render import render_ids
    from jaxmocap.trackers.shirt.skin import SKIN_PARTS

    ps, ctx, hits, q = (skin_setup[k] for k in ("ps", "ctx", "hits", "q"))
    ob = _observe(ps, ctx, hits, q)
    assert np.asarray(ob.valid).all()
    model = setup["model"]
    geom_ids = jax.jit(lambda q, cam: render_ids(model, ps.garment, q, cam).geom)
    roles, chain = model.roles, model.chain
    parents = np.asarray(chain.parents)
    for k, role in enumerate(SKIN_PARTS):
        below = {chain.link_index(roles.link(role))}
        for j in range(len(parents)):
            if parents[j] in below:
                below.add(j)
        geoms = np.flatnonzero(np.asarray(ps.garment.skin)
                               & np.isin(np.asarray(model.geometry.link), sorted(below)))
        for c in range(ps.n_cams):
            g = geom_ids(q, jax.tree.map(lambda a, c=c: a[c], ps.cams))
            yy, xx = np.nonzero(np.isin(g, geoms))
            truth = np.array([xx.mean(), yy.mean()])
            np.testing.assert_allclose(np.asarray(ob.xy[c, k]), truth, atol=1.5)
    pred = project_anchors(ps.cams, ps.body.chain, ob.anchors, q)
    np.testing.assert_allclose(np.asarray(pred), np.asarray(ob.predicted), atol=1e-6)


def test_skin_gate_drops_a_hidden_hand_and_no_skin_leaves_the_ik_unchanged(skin_setup):
    """A hand whose skin is not seen (its pixels removed from the skin map) fails the size
    gate (weight 0) while the others stay; with no skin seen at all the round's IK result is
    the one without skin terms; after a loss no skin is observed."""
    import dataclasses as dc

    ps, ctx, hits, q = (skin_setup[k] for k in ("ps", "ctx", "hits", "q"))
    ob = _observe(ps, ctx, hits, q)
    # erase the left hand's observed skin: every skin pixel within 12 px of its centroid
    d = jnp.linalg.norm(ctx.uvs - ob.xy[:, 1][:, None, None], axis=-1)
    hidden = _observe(ps, ctx, hits, q, ctx.skin & (d > 12.0))
    np.testing.assert_array_equal(np.asarray(hidden.valid),
                                  np.array([[True, False, True]] * ps.n_cams))
    q0 = q + 0.05 * jnp.ones_like(q).at[:6].set(0.0)  # a round started off the truth
    hits0 = eqx.filter_jit(shirt_frame.render_views)(ps, ctx, q0)
    none = ctx._replace(skin=jnp.zeros_like(ctx.skin))
    off = dc.replace(ps, skin=None, rounds=dc.replace(ps.rounds, skin_terms=False))
    ik_round = eqx.filter_jit(lambda p, c, q, h: shirt_frame.ik_round(p, c, q, h)[0])
    with_terms = ik_round(ps, none, q0, hits0)
    without = ik_round(off, ctx._replace(skin=None), q0, hits0)
    np.testing.assert_allclose(np.asarray(with_terms), np.asarray(without), atol=1e-9)
    # and with the skin seen, the terms move the result (they are in the IK)
    seen = ik_round(ps, ctx, q0, hits0)
    assert float(jnp.max(jnp.abs(seen - without))) > 1e-4
    # after a loss (the previous frame invalid) no skin is observed: no terms
    lost = dc.replace(skin_setup["state"], valid=jnp.array(False))
    ctx_lost = shirt_frame.round_context(ps, lost, ctx.views, ctx.okq, q)
    assert not bool(jnp.any(ctx_lost.skin)) and bool(jnp.any(ctx.skin))


def test_skin_terms_residual_jit_vmap_grad(skin_setup):
    """The IK energy with the skin terms appended (ik.append_anchors,
    append_centroid_covariances): its gradient in q matches central finite differences, and
    jit / vmap over poses give the unbatched values."""
    from jaxmocap.ik import append_anchors, append_centroid_covariances, ik_residuals

    ps, ctx, hits, q = (skin_setup[k] for k in ("ps", "ctx", "hits", "q"))
    ob = _observe(ps, ctx, hits, q)
    P = ps.garment.n_patches
    anchors = append_anchors(ps.anchors, ob.anchors, ps.n_cams)
    assert anchors.offset.shape == (ps.n_cams, P + 3, 3)
    cov = append_centroid_covariances(ps.cov, P, ps.skin.cov)
    c = jnp.concatenate([jnp.zeros((ps.n_cams, P, 2)), ob.xy], axis=1)
    v = jnp.concatenate([jnp.zeros((ps.n_cams, P), bool), ob.valid], axis=1)
    chain = ps.body.chain

    def energy(x):
        r = ik_residuals(x, chain, ps.cams, anchors, c, v, q, q, cov)
        return jnp.sum(r**2)

    x = q + 0.02 * jnp.arange(q.shape[0]) / q.shape[0]
    g = jax.jit(jax.grad(energy))(x)
    eps = 1e-6
    e = jax.jit(energy)  # the finite differences' 2 n_dof evaluations: one program
    fd = np.array([(e(x.at[i].add(eps)) - e(x.at[i].add(-eps))) / (2 * eps)
                   for i in range(x.shape[0])])
    np.testing.assert_allclose(np.asarray(g), fd, rtol=1e-5, atol=1e-5)
    assert float(jnp.linalg.norm(g[6:])) > 0
    xs = jnp.stack([x, q, 2 * x - q])
    np.testing.assert_allclose(np.asarray(jax.vmap(energy)(xs)),
                               [float(energy(y)) for y in xs], rtol=1e-10)


def test_skin_parts_found_by_role_under_other_names():
    """The observed parts are found by the body's roles: a body with other link and geom
    names (mixamo's) gets the same parts and links as the bundled one."""
    from jaxmocap.body.scale import rename_body
    from jaxmocap.trackers.shirt.skin import skin_parts

    model = default_body()
    other = rename_body(model, "mixamo")
    assert other.chain.link_names != model.chain.link_names
    a, b = skin_parts(model, default_garment(model)), skin_parts(other, default_garment(other))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert set(a[0].tolist()) == {-1, 0, 1, 2}  # head and both hands have skin


@pytest.mark.parametrize("name", ["gym_humanoid", "cmu"])
def test_skin_parts_of_package_bodies_lie_at_their_keypoints(name):
    """Bodies designed elsewhere: gymnasium's humanoid hangs its head sphere on the torso link
    and its hand spheres on the forearm links, the CMU body has finger links below moving
    joints. Every skin geom given to a part has its centre (forward kinematics at rest) nearer
    that part's keypoint than the other parts' (geometry as the oracle), and each part has
    one."""
    from jaxmocap.body import fk
    from jaxmocap.body.packages import package_body
    from jaxmocap.garment import default_skin_geoms, make_garment
    from jaxmocap.trackers.shirt.skin import SKIN_PARTS, skin_parts

    model = package_body(name)
    garment = make_garment(model, [], [], default_skin_geoms(model))  # skin only
    part_geom, _ = skin_parts(model, garment)
    T = np.asarray(fk(model.chain, jnp.zeros(model.n_dof)))
    g = model.geometry
    centre = np.einsum("gij,gj->gi", T[np.asarray(g.link)], np.asarray(g.pose)[:, :, 3])[:, :3]
    kp = np.asarray(keypoints(model, jnp.zeros(model.n_dof)))
    names = list(model.keypoint_names)
    parts = kp[[names.index(k) for k in SKIN_PARTS]]
    for k in range(len(SKIN_PARTS)):
        mine = np.flatnonzero(part_geom == k)
        assert mine.size, SKIN_PARTS[k]
        d = np.linalg.norm(centre[mine, None] - parts[None], axis=-1)
        assert (d.argmin(1) == k).all(), (SKIN_PARTS[k], [g.names[i] for i in mine])


def test_step_on_the_learned_observation(setup, monkeypatch):
    """``colours.observer`` (issue 49): steps 1 and 3 read the model's probabilities. With an
    oracle in the model's place (each crop pixel's nearest rendered albedo, camera gamma:
    the scene's white light and grey background make that nearly the truth), the step recovers
    the pose as the paper's path does, traced once for two frames; the white balance is left
    alone; make_params refuses the model beside shading / room colours and a model of another
    class count."""
    from jaxmocap import observe
    from jaxmocap.observe import Observer, classes_of

    p, model = setup["params"], setup["model"]
    garment = p.garment
    classes = classes_of(model, garment)
    albedo = np.concatenate([[[0.5, 0.5, 0.5]], np.asarray(garment.colours),
                             np.tile(np.asarray(garment.skin_rgb), (3, 1))])
    from jaxmocap.render._shade import AMBIENT, FILL_INTENSITY, KEY_INTENSITY

    lit = AMBIENT + 0.6 * (KEY_INTENSITY + FILL_INTENSITY)
    ref = np.clip(albedo * lit, 0, 1) ** (1 / 2.2) * 255
    ref[0] = 128.0  # the background image

    def oracle(_model, crop):
        ref_j = jnp.asarray(ref, jnp.float32)[None, None]
        d2 = jnp.sum((crop.astype(jnp.float32)[..., None, :] - ref_j) ** 2, -1)
        return jax.nn.log_softmax(-d2 / 200.0, -1)

    monkeypatch.setattr(observe, "log_probs", oracle)
    obs = Observer(classes.n, jax.random.key(0), width=4, context=4)
    q = dataclasses.replace(p, colours=shirt.Colours(observer=obs))
    state = shirt.init(q, setup["W0"], jnp.zeros(model.n_dof))
    before = shirt.TRACE_COUNT["step"]
    state, out = shirt.step(q, state, setup["frames"])
    state2, out2 = shirt.step(q, state, setup["frames"])
    assert shirt.TRACE_COUNT["step"] == before + 1
    kp = jax.jit(lambda x: keypoints(model, x))
    truth = np.asarray(kp(setup["q_true"]))
    for o in (out, out2):
        err = np.linalg.norm(np.asarray(kp(o.q)) - truth, axis=-1)
        assert bool(o.valid) and err.mean() < 0.08, err
        assert np.asarray(o.visible).sum() >= 2 * 10
    np.testing.assert_array_equal(np.asarray(state2.W), np.asarray(setup["W0"]))
    for bad in (shirt.Colours(observer=obs, shading=(0.5, 4.0)),
                shirt.Colours(observer=Observer(classes.n + 1, jax.random.key(0), width=4,
                                                context=4))):
        with pytest.raises(ValueError, match="observer"):
            shirt.make_params(p.color, model, garment, p.cams, p.anchors, p.cov, p.db,
                              colours=bad)
