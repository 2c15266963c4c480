"""`jaxmocap tune`'s refusals (one line, exit code 2, before any tracking). The command's run
on the test world's dev split is recorded in docs/results/tuning.md; its parts are tested in
test_tune.py (gradients, optimisers, resume) and test_tuned.py (the file)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from test_cli import assert_refused

from jaxmocap.cli import main


def test_refusals_before_any_work(tmp_path, capsys):
    two = tmp_path / "two.toml"
    two.write_text("[[config]]\nname='a'\nmethod='shirt'\n[[config]]\nname='b'\nmethod='pf'\n")
    out = tmp_path / "out"
    base = ["tune", str(tmp_path / "data"), "--out", str(out), "--quiet"]
    assert_refused(capsys, "--optimiser lbfgs runs in this process", *base, "--optimiser",
                   "lbfgs", "--workers", "2", leaves=[out])
    assert_refused(capsys, "2 configurations (a, b); name the one to tune (--name)", *base,
                   "--config", str(two), leaves=[out])
    assert_refused(capsys, "configuration 'b' is method 'pf', not 'shirt'", *base, "--config",
                   str(two), "--name", "b", leaves=[out])
    assert_refused(capsys, "no configuration 'c'", *base, "--config", str(two), "--name", "c",
                   leaves=[out])
    assert_refused(capsys, "--optimiser lbfgs takes its step from the linesearch", *base,
                   "--optimiser", "lbfgs", "--learning-rate", "0.1", leaves=[out])
    assert_refused(capsys, "not a dataset folder", *base, leaves=[out])
    assert_refused(capsys, "not both", *base, "--workers", "1", "--scheduler", "tcp://x:1",
                   leaves=[out])
    assert_refused(capsys, "--optimiser cma is the stereo filter's black-box baseline", *base,
                   "--optimiser", "cma", "--tracker", "shirt", leaves=[out])
    assert_refused(capsys, "--pf-seeds is the stereo filter's", *base, "--pf-seeds", "2",
                   leaves=[out])


# ----------------------------------------------------------------------------- stereo filter

PF_CONFIG = """
[[config]]
name = "pf"
method = "pf"
[config.options]
particles = 32
validity = false
"""


@pytest.fixture(scope="module")
def pf_run(tmp_path_factory):
    """A tiny stereo sequence (64x48, 3 frames, `jaxmocap synth`) tuned by the command for 2
    Adam steps through the filter's recursion."""
    base = tmp_path_factory.mktemp("pf")
    root = base / "data"
    assert main(["synth", str(root / "clip"), "--clip", "humanoid3d_punch", "--preset",
                 "stereo", "--garment", "single", "--background", "plain", "--frames", "3",
                 "--width", "64", "--height", "48", "--png", "--no-video", "--no-colour-ids",
                 "--quiet", "--seed", "0"]) == 0
    cfg = base / "pf.toml"
    cfg.write_text(PF_CONFIG)
    out = base / "out"
    assert main(["tune", str(root), "--tracker", "pf", "--config", str(cfg), "--steps", "2",
                 "--every", "1", "--learning-rate", "0.1", "--out", str(out), "--quiet"]) == 0
    return root, cfg, out


def test_pf_tune_writes_a_file_track_accepts_and_resumes(pf_run):
    from jaxmocap.body import default_body
    from jaxmocap.trackers.stereo_pf.params import Cues
    from jaxmocap.tuned import TunedParameters

    root, cfg, out = pf_run
    t = TunedParameters.load(out / "tuned.json")
    t.check_for("pf", default_body())  # the bundled body the sequence was rendered with
    assert t.tracker == "pf" and t.tuned_on["frames"] == 3
    loss = t.loss
    assert len(loss["curve"]) == 3 and loss["before"] == loss["curve"][0]
    assert loss["after"] == min(loss["curve"])
    w = t.cue_widths()
    i = loss["best_step"]
    if i == 0:  # the start is the configuration's (the filter's default) widths
        assert w == pytest.approx({"sigma_g": Cues().sigma_g, "sigma_d": Cues().sigma_d})
    else:  # Adam moved both log-widths
        assert w["sigma_g"] != pytest.approx(Cues().sigma_g, rel=1e-3)
    # a rerun with more steps continues from the checkpoint: the same first three losses
    assert main(["tune", str(root), "--tracker", "pf", "--config", str(cfg), "--steps", "3",
                 "--every", "1", "--learning-rate", "0.1", "--out", str(out), "--quiet"]) == 0
    again = TunedParameters.load(out / "tuned.json").loss["curve"]
    assert len(again) == 4
    np.testing.assert_allclose(again[:3], loss["curve"], rtol=1e-6)


def test_pf_loss_on_the_cached_observations_is_the_trackers_all_frames_error(pf_run):
    """The loss tune minimises, at the configuration's widths, equals the all-frames error of
    the tracker's own run (its estimates cached by the experiment cell, seed 0) against the
    sequence's ground-truth keypoints: the loss is the filter re-run, not a surrogate. In the
    filter's float32 (as tune runs it), so to 1e-5 relative; value-and-gradient agrees with
    the scalar loss and its gradient is finite."""
    from jaxmocap.body import keypoints
    from jaxmocap.experiment.cell import eval_joints
    from jaxmocap.experiment.config import dataset_sequences, load_config
    from jaxmocap.experiment.tuning import _pf_losses, _pf_setups, observations
    from jaxmocap.io.export import load_track

    root, cfg, out = pf_run
    c = load_config(cfg).configs[0]
    seqs = dataset_sequences(root, None, None)
    obs = observations(c, seqs, out, progress=False)  # read back from out/observations
    jax.config.update("jax_enable_x64", False)
    try:
        terms, theta, _, _ = _pf_setups(c, seqs, obs)
        scalar, vg = _pf_losses(terms)
        value, grad = vg(theta)
        loss = float(scalar(theta))
        params, seq = terms[0]
        q = jnp.asarray(obs[seqs[0].name]["q_tracker"], jnp.float32)
        kp = np.asarray(jax.vmap(lambda x: keypoints(params.model, x))(q), np.float64)
    finally:
        jax.config.update("jax_enable_x64", True)
    gt = load_track(root / "clip" / "groundtruth.npz")
    joints = eval_joints(c.to_dict())
    names = list(params.model.keypoint_names)
    err = np.linalg.norm(kp[:, [names.index(j) for j in joints]]
                         - gt.keypoints[:, [list(gt.keypoint_names).index(j) for j in joints]],
                         axis=-1).mean()
    assert loss == pytest.approx(err, rel=1e-5)
    assert float(value) == pytest.approx(loss, rel=1e-6)
    assert all(np.isfinite(float(g)) for g in jax.tree.leaves(grad))


def test_cma_search_minimises_within_its_budget_and_resumes(tmp_path):
    """CMA-ES on a quadratic in two parameters (a PFTheta): the start is evaluated first,
    then whole generations (6 candidates in 2-D) within the budget; it gets near the minimum;
    a search stopped at 31 evaluations and resumed from its checkpoint to 61 ends exactly
    where an uninterrupted search of 61 ends."""
    from jaxmocap import tune
    from jaxmocap.experiment.tuning import cma_search

    target = np.array([0.3, -0.5])
    value = lambda th: float((th.sigma_g - target[0]) ** 2 + (th.sigma_d - target[1]) ** 2)
    theta0 = tune.PFTheta(jnp.asarray(0.0), jnp.asarray(0.0))
    best, losses = cma_search(value, theta0, 61, tmp_path / "a.pkl", "k")
    assert len(losses) == 61 and losses[0] == pytest.approx(float(target @ target))
    assert value(best) == losses.min() < 1e-3
    _, part = cma_search(value, theta0, 31, tmp_path / "b.pkl", "k")
    assert len(part) == 31
    best_b, resumed = cma_search(value, theta0, 61, tmp_path / "b.pkl", "k")
    np.testing.assert_array_equal(resumed, losses)
    assert float(best_b.sigma_g) == float(best.sigma_g)
    from jaxmocap.experiment.config import ExperimentError

    with pytest.raises(ExperimentError, match="not a checkpoint of this CMA-ES run"):
        cma_search(value, theta0, 61, tmp_path / "b.pkl", "another run")


def test_pf_tune_with_cma_spends_the_gradient_descents_budget(pf_run, tmp_path, capsys):
    """`--optimiser cma --steps 6` evaluates the loss 7 times (the start + one generation of
    6), as 6 Adam steps would; the file records every evaluation and the best; a learning
    rate is refused in one line."""
    import shutil

    from jaxmocap.tuned import TunedParameters

    root, cfg, out = pf_run
    cma_out = tmp_path / "cma"
    shutil.copytree(out / "observations", cma_out / "observations")  # the tracking, cached
    assert main(["tune", str(root), "--tracker", "pf", "--config", str(cfg), "--optimiser",
                 "cma", "--steps", "6", "--out", str(cma_out), "--quiet"]) == 0
    t = TunedParameters.load(cma_out / "tuned.json")
    curve = t.loss["curve"]
    assert len(curve) == 7 and t.loss["optimiser"] == "cma"
    assert t.loss["after"] == min(curve) and t.loss["learning_rate"] is None
    adam = TunedParameters.load(out / "tuned.json").loss["curve"]
    assert curve[0] == pytest.approx(adam[0], rel=1e-6)  # the same loss at the same start
    assert (cma_out / "checkpoint_cma.pkl").is_file()
    assert_refused(capsys, "--optimiser cma adapts its own step", "tune", str(root),
                   "--tracker", "pf", "--optimiser", "cma", "--learning-rate", "0.1",
                   "--out", str(tmp_path / "x"), leaves=[tmp_path / "x"])


def test_tune_refuses_to_write_over_its_tuned_input(pf_run, capsys):
    """A configuration whose `tuned` option names the file this run would write (the earlier
    run's out/tuned.json) is refused in one line before any work; the file is untouched."""
    root, _, out = pf_run
    cfg = out.parent / "pf_tuned.toml"
    cfg.write_text(PF_CONFIG + f'tuned = "{out / "tuned.json"}"\n')
    before = (out / "tuned.json").read_bytes()
    assert_refused(capsys, "is also an input of this command", "tune", str(root), "--tracker",
                   "pf", "--config", str(cfg), "--steps", "3", "--out", str(out), "--quiet")
    assert (out / "tuned.json").read_bytes() == before
