"""A window update that fails is counted, its traceback kept and warned about once, shown in
the diagnostics and the replay's summary, and loses nothing: its track's measurements stay and
the next update adjusts them. With ``strict`` a bug (not a GaError) raises."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import SolverError
from ga_ros.pipeline.session import AlignmentSession
from ga_ros.pipeline.session.diagnostics import diagnostic_values
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.pipeline import replay
from ga_ros.replay.samples import aerial_sample, write_measurement_bag
from ga_ros.replay.text import result_text

CFG = AlignerConfig(window_tracks=2)


@pytest.fixture(scope='module')
def sample():
    return aerial_sample(n_tracks=4, positions_per_swath=6, noise_pct=5.0, seed=3)


class FailingStage:
    """The window adjustment of the aligner, failing at its ``at``-th calls with ``exc``."""

    def __init__(self, al: TrackWindowAligner, at: int | set[int], exc: Exception) -> None:
        self.real, self.exc, self.calls = al._adjust, exc, 0
        self.at = {at} if isinstance(at, int) else at
        self.windows: list[list[int]] = []    # the window's tracks of each call
        al._adjust = self

    def __call__(self, window_tracks, *args, **kwargs):
        self.calls += 1
        self.windows.append(list(window_tracks))
        if self.calls in self.at:
            raise self.exc
        return self.real(window_tracks, *args, **kwargs)


def failing_aligner(strict: bool, at: int | set[int], exc: Exception,
                    T_world_first=None) -> tuple[TrackWindowAligner, FailingStage]:
    """An aligner of :data:`CFG` (``strict`` as given) whose window adjustment fails at its
    ``at``-th calls with ``exc``, and that failing stage."""
    al = TrackWindowAligner(CFG, T_world_first=T_world_first)
    al.strict = strict
    return al, FailingStage(al, at, exc)


def _track_rows(al: TrackWindowAligner, track: int) -> np.ndarray:
    path = al.corrected_path()
    return np.array(sorted(al.state.index[int(i)] for i in path.node_ids[path.track_ids == track]))


def test_a_failed_update_is_counted_and_its_track_is_adjusted_by_the_next(sample):
    al, stage = failing_aligner(False, 2, RuntimeError('broken gate'))   # the update of track 1
    ups = al.add_measurements(sample.measurements).updates
    failed = [u for u in ups if u.reason.startswith('failed')]
    assert [u.track_id for u in failed] == [1]
    assert al.stats.n_failed_updates == 1 and al.n_failed_updates == 1
    assert 'Traceback' in al.stats.last_failure and 'RuntimeError: broken gate' in \
        al.stats.last_failure
    # nothing lost: every measurement kept, track 1 in the window of the next update
    ref = TrackWindowAligner(CFG)
    ref.strict = False
    ref_ups = ref.add_measurements(sample.measurements).updates
    assert al.stats.n_connections == ref.stats.n_connections == len(sample.measurements)
    nxt = ups[ups.index(failed[0]) + 1]
    assert nxt.track_id == 2 and nxt.converged and stage.windows[2] == [1, 2]
    assert ref.stats.n_failed_updates == 0 and len(ref_ups) == len(ups)
    al.finish_track()
    ref.finish_track()
    # the failed track's nodes were adjusted after all: as in the run without a failure
    rows = _track_rows(al, 1)
    np.testing.assert_allclose(al.state.T[rows], ref.state.T[rows], atol=0.05)


def test_strict_raises_a_bug_after_putting_the_state_back(sample):
    al, _ = failing_aligner(True, 2, AttributeError("'NoneType' object has no attribute 'w'"))
    ms = sample.measurements
    k2 = next(k for k, m in enumerate(ms) if m.dst_track == 2)
    al.add_measurements(ms[:k2])
    n = len(al.state.ids)
    T_before = al.state.T[:n].copy()
    with pytest.raises(AttributeError):
        al.add_measurement(ms[k2])          # ends track 1: its update fails
    np.testing.assert_array_equal(al.state.T[:n], T_before)
    assert al.stats.n_failed_updates == 1


def test_strict_reports_a_numerical_failure_without_raising(sample):
    al, _ = failing_aligner(True, 2, SolverError('not positive definite'))
    ups = al.add_measurements(sample.measurements).updates
    assert sum(u.reason.startswith('failed') for u in ups) == 1
    assert al.stats.n_failed_updates == 1


def test_the_session_counts_diagnoses_and_warns_once_with_the_traceback(sample):
    warnings: list[str] = []
    al, _ = failing_aligner(False, {2, 3}, RuntimeError('broken gate'))   # twice the same error
    session = AlignmentSession(CFG, warn=warnings.append, aligner=al)
    notes = []
    for m in sample.measurements:
        out = session.step(m)
        assert out.accepted
        notes += out.notes
    assert al.stats.n_failed_updates == 2
    values = diagnostic_values(session)
    assert values['failed_updates'] == 2 and values['solver_failures'] == 2
    tracebacks = [w for w in warnings if 'Traceback' in w]
    assert len(tracebacks) == 1 and 'RuntimeError: broken gate' in tracebacks[0]
    assert sum('failed, previous estimate kept' in n for n in notes) == 2


def test_the_replay_summary_counts_failed_updates(tmp_path: Path, sample, monkeypatch):
    made = []

    def factory(T0):
        al, _ = failing_aligner(False, 2, RuntimeError('broken gate'), T_world_first=T0)
        made.append(al)
        return al

    bag = write_measurement_bag(tmp_path / 'in', sample.measurements, sample.ground_truth)
    r = replay(bag, tmp_path / 'out', ReplayConfig(plot=False), aligner_factory=factory)
    assert made and r.failed_updates == 1
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert summary['failed_updates'] == 1
    assert 'broken gate' in summary['failed_update_examples'][0]
    assert any(line.startswith('failed window updates: 1')
               for line in result_text(r).splitlines())


def test_the_snapshot_keeps_the_count_and_the_last_failure(tmp_path: Path, sample):
    """A restart from the snapshot continues the survey's count of failed updates (and keeps
    the last one's traceback); a failure after the restart adds to it."""
    from ga_ros.core.window.persistence import load_state, save_state

    al, _ = failing_aligner(False, 2, RuntimeError('broken gate'))
    ms = sample.measurements
    k3 = next(k for k, m in enumerate(ms) if m.dst_track == 3)
    al.add_measurements(ms[:k3])
    assert al.n_failed_updates == 1
    save_state(al, tmp_path / 'state')
    back = load_state(tmp_path / 'state').aligner
    back.strict = False
    assert back.stats.n_failed_updates == 1
    assert back.stats.last_failure == al.stats.last_failure
    assert 'RuntimeError: broken gate' in back.last_failure
    FailingStage(back, 1, SolverError('not positive definite'))   # the update of track 2
    back.add_measurements(ms[k3:])
    assert back.stats.n_failed_updates == 2
    assert back.last_failure == 'not positive definite'
    al.close()
    back.close()


def test_a_strict_session_raises_the_bug_after_losing_nothing(sample):
    """A strict aligner's bug reaches the session's caller as an UpdateBug (chained to it),
    raised once the step is complete: the measurement that ended the track taken, the failure
    counted and warned about; the returned state is the non-strict run's."""
    from ga_ros.pipeline.session.outputs import UpdateBug

    def run(strict: bool) -> tuple[AlignmentSession, list]:
        al, _ = failing_aligner(strict, 2,
                                AttributeError("'NoneType' object has no attribute 'w'"))
        s = AlignmentSession(CFG, aligner=al)
        bugs = []
        for m in sample.measurements:
            try:
                out = s.step(m)
            except UpdateBug as bug:
                bugs.append(bug)
                out = bug.result
            assert out.accepted
        return s, bugs

    strict, bugs = run(True)
    lax, none = run(False)
    assert len(bugs) == 1 and not none
    assert isinstance(bugs[0].__cause__, AttributeError)
    assert [u.track_id for u in bugs[0].result.updates] == [1]
    assert bugs[0].result.updates[0].reason.startswith('failed')
    for s in (strict, lax):
        assert s.counts.accepted == len(sample.measurements)
        assert diagnostic_values(s)['failed_updates'] == 1
    np.testing.assert_array_equal(strict.aligner.corrected_path().T_world_node,
                                  lax.aligner.corrected_path().T_world_node)
