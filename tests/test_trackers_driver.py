"""The one tracker driver (jaxmocap.trackers.driver): the frame loop's bookkeeping (unreadable
instants, stopping, outputs, timing), interrupts as the caller reads them, and the shirt
tracker's diagnostics (one builder, one column list). The trackers through it:
tests/test_trackers_stereo_pf.py (stereo_offline == stereo_pf.track), tests/test_commands_track.py
(track_frames), tests/test_experiment_runner.py (cells), the demo (CI)."""

from types import SimpleNamespace

import numpy as np
import pytest

from jaxmocap.trackers import driver

N_DOF = 5


class Counting:
    """A frame tracker with a known answer: q = t (the step count), valid on even steps;
    raises ``raise_at`` (an exception instance) on that step."""

    diagnostic_names = ("step",)

    def __init__(self, raise_at=None, err=None):
        self.body = SimpleNamespace(n_dof=N_DOF)
        self.n = 0
        self.started = 0
        self.raise_at, self.err = raise_at, err

    def start(self, frames):
        self.started += 1

    def step(self, frames):
        if self.n == self.raise_at:
            raise self.err
        q = np.full(N_DOF, float(self.n))
        self.n += 1
        return driver.FrameResult(q, self.n % 2 == 1, {"step": float(self.n)}, output=self.n)

    def draw(self, frames, result):
        return frames


def frames_with_gap(n=6, gap=2):
    return [(t, None if t == gap else np.zeros((1, 2, 2, 3), np.uint8)) for t in range(n)]


def test_frames_unreadable_instants_outputs_and_timing():
    tr = Counting()
    seen = []
    run = driver.drive(tr, frames_with_gap(), progress=False, keep_outputs=True,
                       on_frame=lambda t, f, r: seen.append((t, r is None)))
    assert tr.started == 1 and tr.n == 5  # the unreadable instant is not stepped
    assert run.q.shape == (6, N_DOF) and run.valid.tolist() == [1, 0, 0, 1, 0, 1]
    assert np.isnan(run.q[2]).all()  # unreadable: no estimate
    np.testing.assert_array_equal(run.q[1], 1.0)  # invalid: its estimate is kept
    np.testing.assert_array_equal(run.q[3], 2.0)  # the third step answered q = 2
    assert [r[:3] for r in run.rows][:3] == [(0, True, True), (1, True, False), (2, False, False)]
    assert run.rows[2][3] == {} and run.rows[4][3] == {"step": 4.0}
    assert run.outputs == [1, 2, 3, 4, 5] and run.interrupted is None
    assert np.isnan(run.times[2]) and np.all(run.times[[0, 1, 3, 4, 5]] >= 0)
    assert seen == [(0, False), (1, False), (2, True), (3, False), (4, False), (5, False)]


def test_on_frame_stops_the_loop():
    run = driver.drive(Counting(), frames_with_gap(), progress=False,
                       on_frame=lambda t, f, r: t == 3)
    assert len(run.valid) == 4 and run.interrupted is None


def test_interrupt_keeps_what_was_tracked():
    run = driver.drive(Counting(raise_at=3, err=KeyboardInterrupt()), frames_with_gap(8, 9),
                       progress=False)
    assert run.interrupted == "SIGINT" and len(run.valid) == 3 and run.q.shape == (3, N_DOF)


def test_interrupt_before_any_frame_and_other_errors_propagate():
    with pytest.raises(KeyboardInterrupt):  # set-up or the first step's compile: nothing kept
        driver.drive(Counting(raise_at=0, err=KeyboardInterrupt()), frames_with_gap(),
                     progress=False)
    with pytest.raises(ValueError):  # a bug is not an interrupt
        driver.drive(Counting(raise_at=2, err=ValueError("bug")), frames_with_gap(),
                     progress=False)


def test_the_caller_reads_interrupts():
    """The command line reads an exception a library made of a signal as the interrupt."""
    def reader(err):
        return "SIGTERM" if isinstance(err, OSError) else None

    run = driver.drive(Counting(raise_at=2, err=OSError("wrapped signal")), frames_with_gap(),
                       progress=False, interrupt=reader)
    assert run.interrupted == "SIGTERM" and len(run.valid) == 3  # steps 0, 1 and the gap


def test_shirt_diagnostics_match_their_column_list():
    names = ["left", "right"]
    out = SimpleNamespace(fraction=np.array([0.5, 0.25]), used_reference=np.array([1, 0]),
                          added_reference=np.array([0, 1]), agreement=np.float32(0.75),
                          visible=np.ones(7, bool),
                          signals=SimpleNamespace(residual=np.array([0.01, 0.02]),
                                                  recall=np.array([0.9, 0.8]),
                                                  coverage=np.array([0.7, 0.6]),
                                                  blend_distance=np.float32(0.125),
                                                  db_spread=np.float32(0.25),
                                                  root_jump=np.float32(0.5)))
    W = np.stack([np.diag([1.0, 2.0, 3.0]), np.diag([4.0, 5.0, 6.0])])
    d = driver.shirt_diagnostics(out, W, names, np.bool_(False))
    assert tuple(d) == driver.shirt_diagnostic_names(names)
    assert d["W_right_gg"] == 5.0 and d["fraction_right"] == 0.25 and d["patches"] == 7.0
    assert d["recall_left"] == pytest.approx(0.9) and d["agreement"] == 0.75
    assert d["coverage_right"] == pytest.approx(0.6) and d["root_jump"] == 0.5
    assert (d["blend_distance"], d["db_spread"]) == (0.125, 0.25) and d["gate"] == 0.0


def test_diagnostics_table():
    run = driver.drive(Counting(), frames_with_gap(4, 1), progress=False)
    table = driver.diagnostics_table(run.rows, ("step", "absent"))
    assert table.shape == (4, 2) and np.isnan(table[:, 1]).all()
    np.testing.assert_array_equal(table[:, 0], [1.0, np.nan, 2.0, 3.0])
