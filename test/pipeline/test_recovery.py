"""Crash recovery from a snapshot and its journal (pipeline/journal/, ROS-free): every intact
measurement is recovered, damaged files are moved aside and never deleted, foreign files and
planted links are never touched."""

from __future__ import annotations

import os

import numpy as np
import pytest

from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import save_state
from ga_ros.errors import CorruptFileError, ForeignFileError, UnsafePathError
from ga_ros.pipeline.journal import (
    RECORD,
    MeasurementJournal,
    journal_path,
    read_journal,
    recover,
    scan_journal,
)
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

CFG = AlignerConfig(window_tracks=2)
HEADER = 11


@pytest.fixture(scope='module')
def ms():
    sc = aerial_scenario(n_tracks=3, positions_per_swath=5)
    nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(7))
    return sc.measurements(nm.z, nm.cov)


def _live(ms, state, n):
    """What the node does: journal every accepted measurement, snapshot after each update
    (with the journal's record count); then the process is killed (nothing else saved)."""
    al, journal = TrackWindowAligner(CFG), MeasurementJournal(journal_path(state))
    for m in ms[:n]:
        ups = al.add_measurement(m)
        journal.append(m)
        if ups:
            save_state(al, state, journal_records=journal.count)
    journal.close()
    return al


def _reference(ms, n):
    al = TrackWindowAligner(CFG)
    al.add_measurements(ms[:n])
    return al


def _same(a, b):
    pa, pb = a.corrected_path(), b.corrected_path()
    np.testing.assert_array_equal(pa.node_ids, pb.node_ids)
    np.testing.assert_allclose(pa.T_world_node, pb.T_world_node, atol=1e-9)
    assert a.stats.n_connections == b.stats.n_connections


def _cut(ms):
    """Mid-track 2: two snapshots written, the journal holds records after the last one."""
    return next(k for k, m in enumerate(ms) if m.dst_track == 2) + 6


def test_snapshot_plus_journal_tail(tmp_path, ms):
    state, n = tmp_path / 'state', _cut(ms)
    _live(ms, state, n)
    res = recover(state, CFG)
    assert res.source == 'snapshot+journal' and res.records_replayed == n - res.snapshot_records
    assert res.records_replayed > 0 and res.moved_aside == [] and res.journal_records == n
    _same(res.aligner, _reference(ms, n))
    again = recover(state, CFG)   # the checkpoint made snapshot and journal agree
    assert again.source == 'snapshot' and again.records_replayed == 0
    _same(again.aligner, _reference(ms, n))


def test_corrupt_journal_header_keeps_the_snapshot_and_the_records(tmp_path, ms):
    state, n = tmp_path / 'state', _cut(ms)
    _live(ms, state, n)
    j = journal_path(state)
    data = bytearray(j.read_bytes())
    data[:HEADER] = b'XXXXXXXXXXX'
    j.write_bytes(bytes(data))
    res = recover(state, CFG)
    assert res.source == 'snapshot+journal' and len(res.moved_aside) == 1
    assert res.moved_aside[0].read_bytes() == bytes(data)        # kept as it was
    assert any('header' in m for m in res.messages)
    _same(res.aligner, _reference(ms, n))
    assert len(read_journal(j)) == n                             # repaired, appendable
    MeasurementJournal(j).append(ms[n])


@pytest.mark.parametrize('damage', ['garbled', 'bytes_missing'])
def test_damaged_record_in_the_middle(tmp_path, ms, damage):
    """A garbled record loses that measurement only; a stretch of missing bytes is skipped by
    re-synchronising on the next record that verifies."""
    state, n = tmp_path / 'state', _cut(ms)
    _live(ms, state, n)
    j = journal_path(state)
    k = n - 3                      # a record after the last snapshot
    at = HEADER + k * RECORD.itemsize
    data = bytearray(j.read_bytes())
    if damage == 'garbled':
        data[at + 60:at + 90] = b'\xff' * 30
    else:
        del data[at + 10:at + 10 + 100]
    j.write_bytes(bytes(data))
    scan = scan_journal(j)
    assert scan.damaged and scan.records.size == n - 1
    res = recover(state, CFG)
    assert len(res.moved_aside) == 1 and res.moved_aside[0].read_bytes() == bytes(data)
    # the measurements that survive: all but record k (the aligner takes what still connects)
    ref = TrackWindowAligner(CFG)
    ref.add_measurements(ms[:k] + ms[k + 1:n])
    _same(res.aligner, ref)
    assert len(read_journal(j)) == n - 1


def test_corrupt_snapshot_is_moved_aside_and_the_journal_replayed(tmp_path, ms):
    state, n = tmp_path / 'state', _cut(ms)
    _live(ms, state, n)
    data = bytearray(state.read_bytes())
    data[-100] ^= 0xFF
    state.write_bytes(bytes(data))
    res = recover(state, CFG)
    assert res.source == 'journal' and res.records_replayed == n
    assert res.moved_aside[0].read_bytes() == bytes(data)
    _same(res.aligner, _reference(ms, n))
    assert recover(state, CFG).source == 'snapshot'              # a fresh snapshot was written


def test_a_foreign_state_file_is_refused_and_untouched(tmp_path, ms):
    state = tmp_path / 'notes.txt'
    state.write_text('not a state\n')
    with pytest.raises(ForeignFileError):
        recover(state, CFG)
    assert state.read_text() == 'not a state\n'
    # beside a journal with intact records: rebuilt from the journal, the file left untouched
    MeasurementJournal(journal_path(state)).append(ms[0])
    res = recover(state, CFG)
    assert res.snapshot_refused and res.source == 'journal' and res.records_replayed == 1
    assert state.read_text() == 'not a state\n'
    with pytest.raises(ForeignFileError):
        save_state(TrackWindowAligner(CFG), state)
    assert sorted(p.name for p in tmp_path.iterdir()) == ['notes.txt', 'notes.txt.journal']


def test_a_planted_journal_symlink_is_never_followed(tmp_path, ms):
    victim = tmp_path / 'victim'
    victim.write_bytes(b'precious')
    state = tmp_path / 'state'
    os.symlink(victim, journal_path(state))
    with pytest.raises(UnsafePathError):
        MeasurementJournal(journal_path(state)).append(ms[0])
    with pytest.raises(UnsafePathError):
        recover(state, CFG)
    assert victim.read_bytes() == b'precious' and os.path.islink(journal_path(state))


def test_a_torn_last_record_is_not_damage(tmp_path, ms):
    state, n = tmp_path / 'state', _cut(ms)
    _live(ms, state, n)
    with open(journal_path(state), 'ab') as f:
        f.write(b'\x01' * 50)                                    # killed mid-write
    res = recover(state, CFG)
    assert res.moved_aside == [] and res.journal_records == n
    _same(res.aligner, _reference(ms, n))
    j = MeasurementJournal(journal_path(state))
    j.append(ms[n])                                              # the torn bytes are cut off
    j.close()
    assert len(read_journal(journal_path(state))) == n + 1


def test_an_old_journal_is_converted_and_a_bad_one_refused_for_appending(tmp_path, ms):
    from ga_ros.pipeline.journal import RECORD_V1, encode_records
    state = tmp_path / 'state'
    v2 = np.frombuffer(encode_records(ms[:5]), RECORD)
    v1 = np.zeros(5, RECORD_V1)
    for name in RECORD_V1.names:
        v1[name] = v2[name]
    journal_path(state).write_bytes(b'GAJOURNAL1\n' + v1.tobytes())
    with pytest.raises(CorruptFileError):
        MeasurementJournal(journal_path(state)).append(ms[5])
    res = recover(state, CFG)
    assert res.source == 'journal' and res.records_replayed == 5 and res.moved_aside == []
    MeasurementJournal(journal_path(state)).append(ms[5])
    assert len(read_journal(journal_path(state))) == 6


def test_clear_state_removes_only_our_files(tmp_path, ms):
    from ga_ros.pipeline.journal import clear_state, write_snapshot_info
    state, n = tmp_path / 'state', _cut(ms)
    _live(ms, state, n)
    write_snapshot_info(state, n)
    assert len(clear_state(state)) == 3
    assert not state.exists() and read_journal(journal_path(state)) == []
    assert recover(state, CFG).source == 'empty'
    notes = tmp_path / 'notes'
    notes.write_text('mine')
    MeasurementJournal(journal_path(notes)).append(ms[0])
    with pytest.raises(ForeignFileError):
        clear_state(notes)
    assert notes.read_text() == 'mine' and len(read_journal(journal_path(notes))) == 1


def test_journal_and_recovery_are_ros_free():
    """recover() is what the node calls, but it needs no ROS: importable with rclpy blocked."""
    import subprocess
    import sys
    code = ("import sys\nfor n in ('rclpy', 'nav_msgs', 'std_msgs', 'rosidl_runtime_py'):\n"
            "    sys.modules[n] = None\n"
            "import ga_ros.pipeline.journal, ga_ros.core.window.persistence\n")
    subprocess.run([sys.executable, '-c', code], check=True, timeout=60)
