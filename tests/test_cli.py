"""The ``jaxmocap`` command as a whole: help texts of every sub-command; and the helpers the
other CLI tests import (run ``jaxmocap.cli.main`` in-process, check a refusal)."""

import os

import pytest

from jaxmocap.cli import SUBCOMMANDS, build_parser, main


def run_cli(capsys, *argv):
    """(exit code, stdout, stderr lines) of ``jaxmocap argv...``."""
    rc = main([str(a) for a in argv])
    cap = capsys.readouterr()
    return rc, cap.out, [ln for ln in cap.err.splitlines() if ln.strip()]


def assert_refused(capsys, match, *argv, leaves=()):
    """The command exits 2 with exactly one stderr line containing ``match`` and leaves none
    of the paths ``leaves`` (nor a temporary beside them)."""
    rc, out, err = run_cli(capsys, *argv)
    assert rc == 2, (rc, out, err)
    assert len(err) == 1, err
    assert match in err[0], err[0]
    for p in leaves:
        assert not os.path.exists(p), p
        folder = os.path.dirname(p) or "."
        if os.path.isdir(folder):
            assert not [f for f in os.listdir(folder) if f.endswith(".tmp") or ".tmp." in f]
    return err[0]


def test_help_texts_complete(capsys):
    with pytest.raises(SystemExit) as e:
        main(["--help"])
    assert e.value.code == 0
    top = capsys.readouterr().out
    parser = build_parser()
    sub = next(a for a in parser._actions if a.dest == "command")
    mine = {"calibrate", "colors", "track", "eval"} & set(sub.choices)
    assert {"calibrate", "colors"} <= mine
    for name in mine:
        assert name in top
        with pytest.raises(SystemExit) as e:
            main([name, "--help"])
        assert e.value.code == 0
        text = capsys.readouterr().out
        assert "examples:" in text and f"jaxmocap {name}" in text.split("examples:")[1]
        p = sub.choices[name]
        assert p.description and len(p.description) > 80
        for a in p._actions:
            if a.dest != "help":
                assert a.help, (name, a.dest)  # every option documented
    assert len(SUBCOMMANDS) == len(set(SUBCOMMANDS))
