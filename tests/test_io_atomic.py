"""Atomic writing: targets appear only complete, failures leave nothing behind, bad targets
are refused with an InputError naming the path."""

import os
import shutil

import numpy as np
import pytest
from test_io_sync import make_capture

from jaxmocap.errors import InputError
from jaxmocap.io.atomic import (
    AtomicFiles,
    OutputPathError,
    atomic_folder,
    atomic_path,
    atomic_write,
    check_output_file,
    check_output_folder,
    lock_path,
    output_folder_lock,
    write_bytes,
    write_text,
)


def test_write_and_replace(tmp_path):
    p = tmp_path / "sub" / "a.txt"
    write_text(p, "one\n")
    assert p.read_text() == "one\n"
    write_text(p, "two\n")
    assert p.read_text() == "two\n"
    write_bytes(tmp_path / "b.bin", b"\x00\x01")
    assert (tmp_path / "b.bin").read_bytes() == b"\x00\x01"
    assert sorted(os.listdir(tmp_path)) == ["b.bin", "sub"]
    assert os.listdir(tmp_path / "sub") == ["a.txt"]


def test_failure_keeps_old_content_and_no_temporaries(tmp_path):
    p = tmp_path / "a.txt"
    write_text(p, "old")
    with pytest.raises(RuntimeError), atomic_write(p) as f:
        f.write("half")
        raise RuntimeError("boom")
    assert p.read_text() == "old"
    assert os.listdir(tmp_path) == ["a.txt"]


def test_atomic_path_keeps_suffix_for_name_based_writers(tmp_path):
    target = tmp_path / "x.npz"
    with atomic_path(target) as tmp:
        assert tmp.parent == tmp_path and tmp.suffix == ".npz"
        np.savez(tmp, a=np.arange(3))  # np.savez would append .npz to another suffix
    with np.load(target) as z:
        np.testing.assert_array_equal(z["a"], np.arange(3))
    assert os.listdir(tmp_path) == ["x.npz"]


def test_group_all_or_nothing(tmp_path):
    with AtomicFiles() as out:
        out.path(tmp_path / "a.txt").write_text("a")
        out.path(tmp_path / "b.txt").write_text("b")
        assert not (tmp_path / "a.txt").exists()  # nothing visible before the end
    assert (tmp_path / "a.txt").read_text() == "a" and (tmp_path / "b.txt").read_text() == "b"
    with pytest.raises(KeyError), AtomicFiles() as out:
        out.path(tmp_path / "c.txt").write_text("c")
        raise KeyError("fail after the first output")
    assert sorted(os.listdir(tmp_path)) == ["a.txt", "b.txt"]


def test_folder(tmp_path):
    with atomic_folder(tmp_path / "ds") as d:
        (d / "f.txt").write_text("x")
        assert not (tmp_path / "ds").exists()
    assert (tmp_path / "ds" / "f.txt").read_text() == "x"
    with pytest.raises(OutputPathError, match="not empty"), atomic_folder(tmp_path / "ds"):
        pass
    with pytest.raises(ValueError), atomic_folder(tmp_path / "e") as d:
        (d / "f.txt").write_text("x")
        raise ValueError
    assert sorted(os.listdir(tmp_path)) == ["ds"]


def test_refuses_bad_targets(tmp_path):
    (tmp_path / "file").write_text("")
    with pytest.raises(InputError, match="output folder is a file"):
        check_output_folder(tmp_path / "file")
    with pytest.raises(InputError, match="file: the output folder is a file"):
        check_output_file(tmp_path / "file" / "x.csv")
    with pytest.raises(InputError, match="is a folder"):
        check_output_file(tmp_path)
    assert check_output_folder(tmp_path / "new" / "deeper") == tmp_path / "new" / "deeper"


def test_written_files_get_ordinary_permissions(tmp_path):
    """Temporaries are private (mkstemp: 0600); published files follow the umask like open()."""
    import os

    from jaxmocap.io.atomic import AtomicFiles, write_text

    mask = os.umask(0o022)
    try:
        a = write_text(tmp_path / "a.txt", "x")
        with AtomicFiles() as out:
            out.path(tmp_path / "b.csv").write_text("y")
    finally:
        os.umask(mask)
    assert (a.stat().st_mode & 0o777) == 0o644
    assert ((tmp_path / "b.csv").stat().st_mode & 0o777) == 0o644


def test_sweep_removes_only_dead_processes_temporaries(tmp_path):
    """A killed run's temporaries (named with its pid) are swept; a live run's are kept."""
    import subprocess
    import sys

    from jaxmocap.io.atomic import staging_dir, sweep_temporaries

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    pid = int(dead.stdout)
    (tmp_path / f".poses.jxm{pid}-abc.tmp.bvh").write_text("half")
    (tmp_path / f".ds.jxm{pid}-q1.tmp").mkdir()
    mine = tmp_path / f".poses.jxm{os.getpid()}-xyz.tmp.csv"
    mine.write_text("in progress")
    (tmp_path / "poses.bvh").write_text("a result")
    removed = sweep_temporaries(tmp_path)
    assert sorted(p.name for p in removed) == sorted([f".ds.jxm{pid}-q1.tmp",
                                                      f".poses.jxm{pid}-abc.tmp.bvh"])
    assert sorted(os.listdir(tmp_path)) == sorted([mine.name, "poses.bvh"])
    out = tmp_path / "out"
    assert staging_dir(out) == tmp_path / ".jaxmocap-staging" and out.is_dir()


# ----------------------------------------------------------------------------- folder lock


def _dead_pid() -> int:
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_output_folder_lock_one_run_at_a_time(tmp_path):
    out = tmp_path / "new" / "deeper" / "res"
    lock = lock_path(out)
    with output_folder_lock(out) as held:
        assert held == lock and lock.read_text() == f"{os.getpid()}\n"
        with pytest.raises(OutputPathError) as e:  # a second holder (another descriptor)
            with output_folder_lock(out):
                pass
        msg = str(e.value)
        assert "\n" not in msg and msg.startswith(f"--out {out}: another jaxmocap run (pid "
                                                  f"{os.getpid()}) is writing")
        assert lock.exists()  # the refused attempt left the holder's lock alone
    assert not lock.exists() and not (tmp_path / "new").exists()  # created folders removed
    out.mkdir(parents=True)
    with output_folder_lock(out):
        pass
    assert out.is_dir() and not lock.exists()  # folders holding results stay


@pytest.mark.parametrize("flock", [True, False])
def test_output_folder_lock_sweeps_a_dead_runs_lock(tmp_path, monkeypatch, flock):
    import jaxmocap.io.atomic as atomic

    if not flock:  # the pid-only lock of systems without fcntl
        monkeypatch.setattr(atomic, "fcntl", None)
    out = tmp_path / "res"
    lock = lock_path(out)
    lock.write_text(f"{_dead_pid()}\n")  # left by a run killed with kill -9
    with output_folder_lock(out):
        assert lock.read_text() == f"{os.getpid()}\n"
    assert not lock.exists()
    if not flock:
        lock.write_text(f"{os.getppid()}\n")  # a live process's lock is respected
        with pytest.raises(OutputPathError, match=f"pid {os.getppid()}"):
            with output_folder_lock(out):
                pass
        assert lock.read_text() == f"{os.getppid()}\n"


@pytest.fixture
def capture(tmp_path):
    return make_capture(tmp_path)


def test_track_refused_while_another_run_holds_out(capture, capsys, monkeypatch):
    from test_cli import run_cli
    from test_cli_badinput import _Fixed

    from jaxmocap.commands import track as track_cmd

    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: _Fixed())
    k = capture
    argv = ["track", "--cameras", k / "cameras.json", k / "a.mp4", k / "b.mp4", "--quiet",
            "--formats", "npz", "--sync", "timestamps", "--out", k / "res"]
    with output_folder_lock(k / "res"):  # the first run, still writing
        rc, out, err = run_cli(capsys, *argv)
        assert rc == 2 and len(err) == 1, (rc, out, err)
        assert f"--out {k / 'res'}: another jaxmocap run (pid {os.getpid()})" in err[0]
        assert not (k / "res").exists()
    rc, out, err = run_cli(capsys, *argv)  # once it ended, the folder is free
    assert rc == 0, (out, err)
    assert sorted(p.name for p in (k / "res").iterdir()) == ["diagnostics.csv", "poses.npz",
                                                             "run.json"]
    assert not lock_path(k / "res").exists()


# ----------------------------------------------------------------------------- OS errors


def _leftovers(root):
    return sorted(str(p.relative_to(root)) for p in root.rglob("*"))


def test_disk_full_while_writing_names_the_folder_and_leaves_nothing(tmp_path):
    import errno

    out = tmp_path / "new" / "res"
    with pytest.raises(OutputPathError) as e:
        with AtomicFiles(out) as files:
            files.path(out / "a.txt").write_text("partial")
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))  # as file.write raises it
    assert str(e.value) == (f"{out}: cannot write: no space left on the device: free some, or "
                            "write elsewhere (ENOSPC); nothing was written")
    assert _leftovers(tmp_path) == []  # no temporary, no staging, no empty folder


def test_permission_denied_on_rename_names_the_target(tmp_path, monkeypatch):
    import errno

    import jaxmocap.io.atomic as atomic

    (tmp_path / "res").mkdir()
    (tmp_path / "res" / "old.txt").write_text("keep")

    def denied(src, dst):
        raise PermissionError(errno.EACCES, os.strerror(errno.EACCES), str(src), None, str(dst))

    monkeypatch.setattr(atomic.os, "replace", denied)
    with pytest.raises(OutputPathError) as e:
        with AtomicFiles(tmp_path / "res") as files:
            files.path(tmp_path / "res" / "b.txt").write_text("new")
    assert str(e.value).startswith(f"{tmp_path / 'res' / 'b.txt'}: cannot write: permission "
                                   "denied: choose a folder you can write (EACCES)")
    assert _leftovers(tmp_path) == ["res", "res/old.txt"]  # the user's folder stays as it was


def test_over_long_names_refused_before_any_work(tmp_path):
    long = "x" * 250  # a valid name on ext4 (255), but not with our temporaries' suffixes
    with pytest.raises(OutputPathError) as e:
        check_output_folder(tmp_path / long / "res")
    msg = str(e.value)
    assert "\n" not in msg and f"the name {long[:24]}... is 250 bytes; this file system allows" \
        in msg
    with pytest.raises(OutputPathError, match="is 250 bytes"):
        check_output_file(tmp_path / (long[:246] + ".npz"))
    assert _leftovers(tmp_path) == []


def test_track_disk_full_and_long_out_one_line_nothing_left(capture, capsys, monkeypatch):
    import errno

    from test_cli import run_cli
    from test_cli_badinput import _Fixed

    from jaxmocap.commands import track as track_cmd

    monkeypatch.setattr(track_cmd, "_make_tracker", lambda args, cams, names: _Fixed())
    k = capture
    before = _leftovers(k)
    argv = ["track", "--cameras", k / "cameras.json", k / "a.mp4", k / "b.mp4", "--quiet",
            "--formats", "npz,csv", "--sync", "timestamps"]

    def full(*a, **kw):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    with monkeypatch.context() as m:
        m.setattr(track_cmd, "write_exports", full)
        rc, out, err = run_cli(capsys, *argv, "--out", k / "runs" / "a")
    assert rc == 2 and len(err) == 1, (rc, err)
    journal = k / "runs" / ".a.jaxmocap-journal"  # the tracked frames stay (issue 52)
    assert err[0] == (f"jaxmocap track: error: {k / 'runs' / 'a'}: cannot write: no space left "
                      "on the device: free some, or write elsewhere (ENOSPC); nothing was "
                      f"written; 12 tracked frames are kept in {journal}; resume with "
                      f"`jaxmocap track --resume {k / 'runs' / 'a'}`")
    assert _leftovers(k) == sorted(before + ["runs", str(journal.relative_to(k)),
                                             *(str((journal / n).relative_to(k)) for n in
                                               ("frames.jsonl", "meta.json"))])
    rc, out, err = run_cli(capsys, "track", "--resume", k / "runs" / "a", "--quiet")
    assert rc == 0, err
    assert sorted(p.name for p in (k / "runs" / "a").iterdir()) == [
        "diagnostics.csv", "poses.csv", "poses.npz", "run.json"]
    shutil.rmtree(k / "runs")
    rc, out, err = run_cli(capsys, *argv, "--out", k / ("y" * 240))
    assert rc == 2 and len(err) == 1 and "is 240 bytes; this file system allows" in err[0]
    assert _leftovers(k) == before


@pytest.mark.parametrize("fails", ["write", "fsync"])
def test_disk_full_names_the_file_it_could_not_write(tmp_path, monkeypatch, fails):
    """Issue 52 item 5: "No space left" names the file: ``write``/``fsync`` raise ENOSPC
    without a file name (as the kernel reports them); the line names the file asked for (not
    the hidden temporary), and nothing is left."""
    import errno

    import jaxmocap.io.atomic as atomic
    from jaxmocap.io.atomic import describe_os_error

    def full(*a, **kw):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    target = tmp_path / "out" / "poses.csv"
    if fails == "fsync":
        monkeypatch.setattr(atomic.os, "fsync", full)
    with pytest.raises(OSError) as e:
        if fails == "write":
            with atomic_write(target) as f:
                f.write("a,b\n")
                full()
        else:
            write_text(target, "a,b\n")
    assert e.value.filename == str(target)
    assert describe_os_error(e.value).startswith(f"{target}: cannot write: no space left")
    assert not target.exists()
    assert [p for p in tmp_path.rglob("*") if p.is_file()] == []


def test_cache_folder_refusal_names_the_variable(tmp_path, capsys, monkeypatch):
    """Issue 52 item 5: a cache folder that cannot be made or written is one line naming the
    folder, the cause and JAXMOCAP_CACHE_DIR (exit 2, before any work)."""
    from test_cli import run_cli

    from jaxmocap._config import CACHE_ENV, cache_folder

    blocker = tmp_path / "cache"
    blocker.write_text("a file where the cache folder should be")
    monkeypatch.setenv(CACHE_ENV, str(blocker))
    with pytest.raises(InputError) as e:
        cache_folder("posedb")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith(f"cache folder {blocker / 'posedb'}: ")
    assert f"{CACHE_ENV}={blocker}" in msg and f"set {CACHE_ENV} to a folder you can write" in msg
    rc, out, err = run_cli(capsys, "eval", tmp_path / "poses.npz", tmp_path)
    assert rc == 2 and len(err) == 1 and CACHE_ENV in err[0] and str(blocker) in err[0], err
    monkeypatch.delenv(CACHE_ENV)
    monkeypatch.setattr("platformdirs.user_cache_dir", lambda *a: str(blocker))
    with pytest.raises(InputError, match=f"the default cache folder {blocker}; {CACHE_ENV} is "
                                         "unset"):
        cache_folder("jax")
