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


DAMAGED_PROGRAM = """
import sys, jax, jax.numpy as jnp
from jaxmocap._config import enable_compilation_cache
enable_compilation_cache(sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0)
f = jax.jit(lambda x: jnp.sin(x) @ x.T + 1.5)
print(repr(float(f(jnp.ones((3, 3)))[0, 0])))
"""


def test_damaged_compiled_program_is_compiled_again_and_reported(tmp_path):
    """Issue 52 item 4: a compiled program cut short in the cache (a crash while it was
    written) is found by its codec's checksum, compiled again, replaced and reported in one line
    (JAX alone warns on every later run and keeps the damaged entry); the result equals the
    first run's (the oracle), and the next run is silent."""
    import subprocess
    import sys
    from pathlib import Path

    script = tmp_path / "prog.py"
    script.write_text(DAMAGED_PROGRAM)
    cache = tmp_path / "jax"
    env = dict(os.environ, PYTHONPATH=str(Path(__file__).resolve().parents[1]),
               JAX_PLATFORMS="cpu")

    def run():
        res = subprocess.run([sys.executable, str(script), str(cache)], env=env, text=True,
                             capture_output=True, timeout=120)
        assert res.returncode == 0, res.stderr
        return res.stdout, [ln for ln in res.stderr.splitlines() if ln.strip()]

    want, err = run()
    assert err == []
    (entry,) = cache.glob("jit__lambda-*-cache")
    intact = entry.read_bytes()
    entry.write_bytes(intact[: len(intact) // 3])
    got, err = run()
    assert got == want
    assert err == [f"jaxmocap: the compiled program {entry} in the cache was damaged; compiled "
                   "again"], err
    assert entry.stat().st_size > len(intact) // 3  # written again, whole
    assert run() == (want, [])
