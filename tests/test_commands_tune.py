"""`jaxmocap tune`'s refusals (one line, exit code 2, before any tracking). The command's run
on the test world's dev split is recorded in docs/results/tuning.md; its parts are tested in
test_tune.py (gradients, optimisers, resume) and test_tuned.py (the file)."""

from test_cli import assert_refused


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
    assert_refused(capsys, "not a dataset folder", *base, leaves=[out])
    assert_refused(capsys, "not both", *base, "--workers", "1", "--scheduler", "tcp://x:1",
                   leaves=[out])
