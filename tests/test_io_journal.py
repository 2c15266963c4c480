"""The journal of a ``track`` run (:mod:`jaxmocap.io.journal`): frames read back bit for bit
(NaN and the last bits of float64 included), a line a kill cut in two dropped, the checkpoint
covering only frames on disk, a failing disk reported once without stopping the tracking."""

import errno
import os
import pickle

import numpy as np
import pytest

from jaxmocap.io.journal import Journal, journal_path, tracked_arrays


def test_frames_read_back_bit_for_bit_and_a_cut_line_is_dropped(tmp_path):
    out = tmp_path / "res"
    rng = np.random.default_rng(0)
    qs = rng.standard_normal((5, 7)) * 10.0 ** rng.integers(-300, 300, (5, 7))
    qs[2] = np.nan  # an unreadable instant
    j = Journal.create(out, {"args": {}}, every_s=0.0)
    assert j.folder == journal_path(out) == tmp_path / ".res.jaxmocap-journal"
    for t, q in enumerate(qs):
        j.append(t, t != 2, t in (0, 4), q, {} if t == 2 else {"ess": float(q[0]), "n": 3.0})
        if t == 3:
            j.checkpoint({"state": np.arange(3) + t})
    j.close()
    with open(j.folder / "frames.jsonl", "a") as f:  # a kill while the 6th line was written
        f.write('{"t": 5, "read": tr')
    again, state, note = Journal.resume(out, every_s=0.0)
    assert note is None and again.count == 4 and again.checkpointed == 4
    np.testing.assert_array_equal(state["state"], [3, 4, 5])
    q, valid, rows, times = tracked_arrays(again.resumed, 7)
    np.testing.assert_array_equal(np.array(q), qs[:4])  # bit for bit, NaN where NaN
    assert valid == [True, False, False, False] and [r[1] for r in rows] == [1, 1, 0, 1]
    assert rows[1][3] == {"ess": qs[1, 0], "n": 3.0} and np.isnan(times).all()
    # the lines after the checkpoint (and the cut one) are gone from the file
    assert len((again.folder / "frames.jsonl").read_text().splitlines()) == 4
    again.remove()
    assert not again.folder.exists()


def test_a_failing_disk_is_said_once_and_the_tracking_goes_on(tmp_path, monkeypatch, capsys):
    import jaxmocap.io.journal as journal_mod

    out = tmp_path / "res"
    j = Journal.create(out, {"args": {}}, every_s=0.0)
    j.append(0, True, True, np.zeros(3), {})
    j.checkpoint({"s": 0})

    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(journal_mod.os, "fsync", full)
    j.checkpoint({"s": 1})
    j.append(1, True, True, np.ones(3), {})
    err = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip()]
    assert len(err) == 1 and f"{j.folder / 'checkpoint.pkl'}: cannot write: no space" in err[0]
    assert j.count == 2 and j.checkpointed == 1
    assert j.where(out).startswith(f"the journal {j.folder} holds the first 1 frames (writing "
                                   "it failed:")
    monkeypatch.undo()
    j.close()
    raw = (j.folder / "checkpoint.pkl").read_bytes()
    assert pickle.loads(raw.partition(b"\n")[2]) == {"frames": 1, "tracker": {"s": 0}}


def test_create_refuses_in_one_line_when_the_journal_cannot_be_made(tmp_path):
    from jaxmocap.errors import InputError

    (tmp_path / ".res.jaxmocap-journal").write_text("a file in the way")
    with pytest.raises(InputError, match=r"the journal of --out .*res: .*jaxmocap-journal"):
        Journal.create(tmp_path / "res", {"args": {}})
