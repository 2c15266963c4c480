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
    Adam steps."""
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


def test_pf_loss_on_the_cached_observations_matches_central_differences(pf_run):
    """The loss tune minimises (fixed particles around the filter's own estimates), in
    float64: gradient vs central differences within 1e-4 relative on the 3-frame case."""
    import equinox as eqx

    from jaxmocap.experiment.config import dataset_sequences, load_config
    from jaxmocap.experiment.tuning import _pf_losses, _pf_setups, observations

    root, cfg, out = pf_run
    c = load_config(cfg).configs[0]
    seqs = dataset_sequences(root, None, None)
    obs = observations(c, seqs, out, progress=False)  # read back from out/observations
    terms, theta, _, _ = _pf_setups(c, seqs, obs)
    f64 = lambda a: a.astype(jnp.float64) if eqx.is_inexact_array(a) else a
    terms = [jax.tree.map(f64, t) for t in terms]
    theta = jax.tree.map(f64, theta)
    lik, data, _ = terms[0]
    # particles centred on the filter's own estimate, not on the truth
    est = np.asarray(obs[seqs[0].name]["q_tracker"])[:, np.asarray(lik.dofs)]
    centre = np.asarray(data.particles).mean(1)
    assert np.abs(centre - est).max() < np.abs(centre - np.asarray(data.s_gt)).max() + 1e-9
    scalar, vg = _pf_losses(terms)
    value, grad = vg(theta)
    assert float(value) == pytest.approx(float(scalar(theta)), rel=1e-9)
    for name in ("sigma_g", "sigma_d"):
        g = float(getattr(grad, name))
        h = 1e-4
        shift = lambda s, name=name: eqx.tree_at(lambda t: getattr(t, name), theta,
                                                 getattr(theta, name) + s)
        fd = (float(scalar(shift(h))) - float(scalar(shift(-h)))) / (2 * h)
        if name == "sigma_d" and not np.asarray(data.obs.valid).any():
            # no head / hand triangulated in the tiny images: the distance cue is absent
            assert g == 0.0 and fd == 0.0
            continue
        assert abs(g) > 1e-9, name
        assert abs(g - fd) <= 1e-4 * abs(fd), (name, g, fd)


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
