"""``jaxmocap demo``: bad arguments are refused with one line and exit code 2, before any work.

The demo itself (render, both trackers, exports) runs in CI through the README's command
(`.ci/run`); it takes ~2 minutes, too long for the unit suite.
"""

from jaxmocap.cli import build_parser, main


def test_demo_refuses_bad_arguments(tmp_path, capsys):
    assert main(["demo", "--frames", "1", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--frames" in err[0]
    blocker = tmp_path / "file"
    blocker.write_text("x")
    assert main(["demo", "--out", str(blocker)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a file" in err[0]
    assert not (tmp_path / "o").exists() and blocker.read_text() == "x"


def test_every_subcommand_has_help():
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    assert {"demo", "synth", "calibrate", "colors", "build-db", "track", "eval"} <= set(sub.choices)
    for name, p in sub.choices.items():
        assert p.format_help().strip(), name
