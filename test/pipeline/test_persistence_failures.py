"""Persistence that says when it fails and always starts (ROS-free, pipeline/session/ and
pipeline/journal/): a damaged or missing snapshot never discards an intact journal, a failing
write (a file-size limit standing in for a full disk) is counted and the estimate stays
complete, an unusable state path gives one warning and a session without persistence, and error
texts are bounded. Each recovered state is checked against an aligner fed the measurements
directly."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import InputError, PersistenceError
from ga_ros.pipeline.journal import RECORD, journal_path
from ga_ros.pipeline.session import MAX_ERROR_CHARS, AlignmentSession, SessionConfig
from ga_ros.replay.samples import aerial_sample

CFG = AlignerConfig(window_tracks=2)


@pytest.fixture(scope='module')
def measurements() -> list:
    return aerial_sample(n_tracks=3, positions_per_swath=6, noise_pct=5.0, seed=9).measurements


def _direct(ms: list) -> TrackWindowAligner:
    al = TrackWindowAligner(CFG)
    for m in ms:
        al.add_measurement(m)
    return al


def _same(a: TrackWindowAligner, b: TrackWindowAligner) -> None:
    pa, pb = a.corrected_path(), b.corrected_path()
    np.testing.assert_array_equal(pa.node_ids, pb.node_ids)
    np.testing.assert_allclose(pa.T_world_node, pb.T_world_node, atol=1e-9)


def _run_and_kill(state: Path, ms: list) -> None:
    """A session journals and snapshots ``ms``; then it is gone without closing (a kill)."""
    live = AlignmentSession(CFG, SessionConfig(str(state)))
    live.resume()
    for m in ms:
        assert live.step(m).accepted
    assert live.counts.persistence_errors == 0


@pytest.mark.parametrize('damage', ['empty', 'random', 'truncated', 'missing'])
def test_a_damaged_snapshot_never_discards_the_journal(tmp_path: Path, measurements: list,
                                                       damage: str) -> None:
    state = tmp_path / 'state'
    _run_and_kill(state, measurements)
    data = state.read_bytes()
    if damage == 'empty':
        state.write_bytes(b'')
    elif damage == 'random':
        state.write_bytes(np.random.default_rng(3).bytes(len(data)))
    elif damage == 'truncated':
        state.write_bytes(data[:len(data) // 3])
    else:
        state.unlink()
    warnings: list[str] = []
    again = AlignmentSession(CFG, SessionConfig(str(state)), warn=warnings.append)
    how = again.resume()
    assert how is not None and how.startswith('journal:'), how
    assert f'{len(measurements)} replayed' in how
    _same(again.aligner, _direct(measurements))
    assert again.journal is not None       # persistence stays on: the journal goes on
    if damage == 'random':                 # not recognisable as ours: left as it was
        assert state.read_bytes() == np.random.default_rng(3).bytes(len(data))
        assert again.diagnostic_values()['persistence'].startswith('journal only')
        assert any('left untouched' in w for w in warnings)
    elif damage != 'missing':
        assert warnings and any('.corrupt-' in p.name for p in tmp_path.iterdir())
    again.close()


_FULL_DISK = r"""
import json, resource, signal, sys
from ga_ros.core.window import AlignerConfig
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.replay.samples import aerial_sample
ms = aerial_sample(n_tracks=3, positions_per_swath=6, noise_pct=5.0, seed=9).measurements
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)      # an over-limit write fails with EFBIG
warnings = []
s = AlignmentSession(AlignerConfig(window_tracks=2), SessionConfig(sys.argv[1]),
                     warn=warnings.append)
s.resume()
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[2]), resource.RLIM_INFINITY))
outs = [s.step(m) for m in ms]
s.finish_track()
v = s.diagnostic_values()
print(json.dumps({'accepted': sum(o.accepted for o in outs), 'values': v,
                  'health': [s.health().ok, s.health().error], 'warnings': warnings,
                  'T': s.aligner.corrected_path().T_world_node.tolist()}, default=str))
"""


def test_a_full_disk_is_counted_and_the_estimate_stays_complete(tmp_path: Path,
                                                                measurements: list) -> None:
    """Writes beyond 20 records fail (EFBIG under RLIMIT_FSIZE, as ENOSPC on a full disk)."""
    state = tmp_path / 'state'
    limit = 11 + 20 * RECORD.itemsize
    run = subprocess.run([sys.executable, '-c', _FULL_DISK, str(state), str(limit)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    v = out['values']
    n = len(measurements)
    assert out['accepted'] == n and int(v['measurements_accepted']) == n
    assert int(v['rejected']) == 0                       # not both accepted and rejected
    assert int(v['persistence_errors']) >= n - 20        # every failed append (+ snapshots)
    assert out['health'] == [False, True]                # ERROR level
    assert 'File too large' in v['last_persistence_error']
    assert any('NOT journaled' in w for w in out['warnings'])
    assert len(v['last_error']) <= MAX_ERROR_CHARS
    ref = _direct(measurements)
    ref.finish_track()
    np.testing.assert_allclose(np.array(out['T']), ref.corrected_path().T_world_node, atol=1e-9)
    # the journal holds the 20 records that fit, none cut in half; they are recovered
    assert os.path.getsize(journal_path(state)) == limit
    again = AlignmentSession(CFG, SessionConfig(str(state)))
    assert again.resume().startswith('journal: base of 0 journal records + 20 replayed')
    _same(again.aligner, _direct(measurements[:20]))
    again.close()


@pytest.mark.parametrize('where', ['under a regular file', 'a directory'])
def test_an_unusable_state_path_starts_without_persistence(tmp_path: Path, measurements: list,
                                                          where: str) -> None:
    (tmp_path / 'file').write_text('x')
    state = (tmp_path / 'file' / 'state') if where == 'under a regular file' else tmp_path
    warnings: list[str] = []
    s = AlignmentSession(CFG, SessionConfig(str(state)), warn=warnings.append)
    assert s.resume().startswith('failed')
    assert len(warnings) == 1 and 'WITHOUT persistence' in warnings[0]
    for m in measurements:
        assert s.step(m).accepted
    _same(s.aligner, _direct(measurements))
    v = s.diagnostic_values()
    assert v['persistence'].startswith('off:') and v['persistence_errors'] == 0
    assert s.health().error
    with pytest.raises(PersistenceError, match='state_required'):
        AlignmentSession(CFG, SessionConfig(str(state), state_required=True)).resume()


def test_error_texts_are_bounded(measurements: list) -> None:
    s = AlignmentSession(CFG)
    s.reject(InputError('frame ' + 'x' * 1_000_000))
    assert len(s.last_error) <= MAX_ERROR_CHARS and s.last_error.endswith('...')
    assert len(s.diagnostic_values()['last_error']) <= MAX_ERROR_CHARS


_DISK_FREED = r"""
import json, resource, signal, sys
from ga_ros.core.window import AlignerConfig
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.replay.samples import aerial_sample
ms = aerial_sample(n_tracks=3, positions_per_swath=6, noise_pct=5.0, seed=9).measurements
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)      # an over-limit write fails with EFBIG
s = AlignmentSession(AlignerConfig(window_tracks=2), SessionConfig(sys.argv[1]))
s.resume()
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[2]), resource.RLIM_INFINITY))
half = len(ms) // 2
for m in ms[:half]:
    s.step(m)
full = (s.diagnostic_values(), [s.health().ok, s.health().error])
resource.setrlimit(resource.RLIMIT_FSIZE, (resource.RLIM_INFINITY, resource.RLIM_INFINITY))
s.step(ms[half])
again = (s.diagnostic_values(), [s.health().ok, s.health().error])
for m in ms[half + 1:]:
    s.step(m)
s.finish_track()                                   # a window update: the autosave snapshot
after = (s.diagnostic_values(), [s.health().ok, s.health().error])
print(json.dumps({'full': full, 'again': again, 'after': after,
                  'T': s.aligner.corrected_path().T_world_node.tolist()}, default=str))
"""


def test_failing_writes_are_reported_while_they_fail_and_clear_when_they_succeed(
        tmp_path: Path, measurements: list) -> None:
    """A full disk (a file-size limit) that gets space again: ``persistence`` reads
    ``failing`` (ERROR) while writes fail; once a write succeeds it is no longer failing, the
    inputs not saved are counted (WARN) until a snapshot holds them, then all is ``on``."""
    state = tmp_path / 'state'
    limit = 11 + 20 * RECORD.itemsize
    run = subprocess.run([sys.executable, '-c', _DISK_FREED, str(state), str(limit)],
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    out = json.loads(run.stdout)
    (v_full, h_full), (v_again, h_again), (v_after, h_after) = (
        out['full'], out['again'], out['after'])
    half = len(measurements) // 2
    assert v_full['persistence'].startswith('failing:') and h_full == [False, True]
    assert int(v_full['persistence_unsaved']) == half - 20
    assert v_again['persistence'] == 'on' and h_again == [False, False]   # WARN, not ERROR
    assert int(v_again['persistence_unsaved']) == half - 20
    assert v_after['persistence'] == 'on' and int(v_after['persistence_unsaved']) == 0
    assert h_after[1] is False and int(v_after['persistence_errors']) >= half - 20  # + snapshots
    again = AlignmentSession(CFG, SessionConfig(str(state)))   # the snapshot holds it all
    again.resume()
    np.testing.assert_allclose(again.aligner.corrected_path().T_world_node, np.array(out['T']),
                               atol=1e-9)
    again.close()
