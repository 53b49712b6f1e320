"""The journal holds every change of state (measurements, fixes, track ends, end of input, the
datum): a recovery from the journal alone (snapshot lost) reproduces the uninterrupted run's
state bit for bit (ROS-free, through the pipeline session)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from ga_ros.core.fixes import FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig
from ga_ros.core.window.persistence import state_arrays
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.pipeline.journal import (
    RECORD,
    Datum,
    MapOdom,
    MeasurementJournal,
    TrackEnd,
    clear_state,
    journal_path,
    read_journal,
    records_to_entries,
    recover,
)
from ga_ros.pipeline.journal.records import (
    encode_datum,
    encode_map_odom,
    encode_track_end,
    last_map_odom_entry,
)
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.sim.fix_survey import feed_entries, line_fix_survey

# a refinement after every track (refine_relinearize_sigma 0); the defaults and the plain window
# (refine_every_tracks=0), killed at many points and resumed to the end: test_journal_exact.py
CFG = AlignerConfig(window_tracks=2, datum='fixes', refine_every_tracks=1,
                    refine_executor='inline', fix_gate_prob=0.0, refine_relinearize_sigma=0.0)


def _survey(rng: np.random.Generator, n_tracks: int = 6, per: int = 7) -> list:
    """A line survey; fixes of two sources (``gnss0`` every third node, ``usbl1`` every
    fifth), each with a lever arm and the odometry offset's covariance."""
    return line_fix_survey(rng, n_tracks, per)


def feed(session: AlignmentSession, entries: list, start: int, stop: int,
         finish_after: int) -> None:
    """Give entries ``start:stop`` to ``session`` (measurements and fixes, a refused fix left
    out as live), ending the open track by hand after entry ``finish_after``."""
    for k in range(start, stop):
        feed_entries(session, entries[k:k + 1])
        if k == finish_after:
            session.finish_track('finish_track')


def _run(session: AlignmentSession, entries: list, finish_after: int) -> None:
    """Feed ``entries``, ending the open track by hand after entry ``finish_after`` (the next
    measurements of that track are then refused) and at the end of input."""
    feed(session, entries, 0, len(entries), finish_after)
    session.finish_track('end_of_input')


def _without_rejections(meta: dict) -> dict:
    """The scalar state without the rejection counters (refused inputs are not journaled: a
    recovery never sees them)."""
    meta = dict(meta, rejected=None)
    if 'fixes' in meta:
        meta['fixes'] = dict(meta['fixes'], stats=dict(meta['fixes']['stats'], rejected=None))
    return meta


def assert_same_state(a, b) -> None:
    """Every array and scalar of the two aligners' window states is identical (bit for bit),
    the rejection counters aside."""
    meta_a, arr_a = state_arrays(a.state)
    meta_b, arr_b = state_arrays(b.state)
    assert _without_rejections(meta_a) == _without_rejections(meta_b)
    assert arr_a.keys() == arr_b.keys()
    for name in arr_a:
        np.testing.assert_array_equal(arr_a[name], arr_b[name], err_msg=name)
    np.testing.assert_array_equal(a.corrected_path().T_world_node,
                                  b.corrected_path().T_world_node)


def _lose_snapshot(state) -> None:
    for p in (state, f'{state}.json'):
        if os.path.lexists(p):
            os.unlink(p)


def test_track_end_and_datum_records_round_trip() -> None:
    raw = (encode_track_end(TrackEnd(7, 'end_of_input')) + encode_datum(Datum((48.1, 11.5, 520.0)))
           + encode_track_end(TrackEnd(9, 'idle_timeout')))
    back = records_to_entries(np.frombuffer(raw, RECORD))
    assert back == [TrackEnd(7, 'end_of_input'), Datum((48.1, 11.5, 520.0)),
                    TrackEnd(9, 'idle_timeout')]


@pytest.mark.parametrize('snapshot, compact', [(False, 0), (True, 0), (False, 10), (True, 10)])
def test_recovery_reproduces_a_survey_with_fixes_track_ends_and_end_of_input(tmp_path, snapshot,
                                                                             compact):
    """Killed after the end of input (the last track closed by it, another by hand): the
    journal alone, or snapshot + journal, gives the live state bit for bit; also when the
    journal was compacted at the window updates (its base + the records after it)."""
    entries = _survey(np.random.default_rng(11))
    state = tmp_path / 'state'
    live = AlignmentSession(CFG, SessionConfig(str(state), compact_records=compact))
    assert live.resume() is None
    finish_after = next(k for k, e in enumerate(entries)
                        if isinstance(e, Measurement) and e.dst_track == 2) + 3
    _run(live, entries, finish_after)
    live.journal_datum((48.1, 11.5, 520.0))
    al = live.aligner
    assert al.open_track is None or al.open_track in al.state.finished
    live.journal.close()  # killed: nothing else written
    logged = read_journal(journal_path(state))
    ends = [e for e in logged if isinstance(e, TrackEnd)]
    if compact:  # only what followed the last compaction (the end of input and the datum)
        assert live.journal.layout.has_base and live.journal.since_base == 2
        assert [e.cause for e in ends] == ['end_of_input']
    else:
        assert [e.cause for e in ends] == ['finish_track', 'end_of_input']
        assert {e.fix.source for e in logged if isinstance(e, FixTerm)} == {'gnss0', 'usbl1'}
    if not snapshot:
        _lose_snapshot(state)
    res = recover(state, CFG)
    assert res.source == ('snapshot+journal' if snapshot else 'journal')
    assert res.datum == (48.1, 11.5, 520.0)
    assert_same_state(res.aligner, live.aligner)
    res.aligner.close()
    live.aligner.close()


def test_without_the_track_end_records_the_last_track_stays_open(tmp_path):
    """The records matter (the test above can fail): replaying the measurements and fixes
    without the track ends leaves the last track open, its nodes not adjusted."""
    entries = _survey(np.random.default_rng(11))
    state = tmp_path / 'state'
    live = AlignmentSession(CFG, SessionConfig(str(state)))
    live.resume()
    _run(live, entries, len(entries))
    live.journal.close()
    _lose_snapshot(state)
    scan = np.fromfile(journal_path(state), np.uint8)[11:].view(RECORD)
    kept = scan[scan['kind'] != 0x3D]
    with open(journal_path(state), 'wb') as f:
        f.write(b'GAJOURNAL2\n' + kept.tobytes())
    res = recover(state, CFG)
    assert res.aligner.open_track is not None
    assert res.aligner.open_track not in res.aligner.state.finished
    d = np.abs(res.aligner.corrected_path().T_world_node
               - live.aligner.corrected_path().T_world_node).max()
    assert d > 1e-3
    res.aligner.close()
    live.aligner.close()


def _compacted(tmp_path, n_entries: int | None = None):
    """A session on the survey with the journal compacted at every window update, killed
    mid-track (after ``n_entries`` entries); returns the state path and the live session."""
    entries = _survey(np.random.default_rng(11))
    entries = entries[:n_entries] if n_entries else entries[:-4]
    state = tmp_path / 'state'
    live = AlignmentSession(CFG, SessionConfig(str(state), compact_records=1))
    live.resume()
    feed_entries(live, entries)
    live.journal.close()
    assert live.journal.layout.has_base and (live.journal.since_base > 0 or n_entries)
    return state, live


def test_a_compacted_journal_keeps_its_base_through_damage_and_torn_records(tmp_path):
    """Torn last record: ignored (cut off before the next append); a damaged record after the
    base: the journal is moved aside and rewritten with its base and the intact records;
    either way the state is the live one (from the snapshot, or from the base alone)."""
    state, live = _compacted(tmp_path)
    jpath = journal_path(state)
    with open(jpath, 'ab') as f:
        f.write(b'\x01' * 100)   # a torn record
    res = recover(state, CFG, checkpoint=False)
    assert res.source == 'snapshot+journal' and not res.moved_aside
    assert_same_state(res.aligner, live.aligner)
    res.aligner.close()
    _lose_snapshot(state)
    raw = bytearray(jpath.read_bytes())
    lay_end = len(raw) - 100 - RECORD.itemsize * live.journal.since_base
    raw[lay_end + 5] ^= 0xFF     # the first record after the base (and its context) damaged
    jpath.write_bytes(bytes(raw))
    res = recover(state, CFG)
    assert res.source == 'journal' and len(res.moved_aside) == 1
    again = recover(state, CFG, checkpoint=False)   # the repaired journal kept the base
    assert again.records_rejected == 0
    j = MeasurementJournal(jpath)
    assert j.layout.has_base and j.count == live.journal.count - 1
    for r in (res, again):
        r.aligner.close()
    live.aligner.close()


def test_a_snapshot_older_than_the_base_gives_way_to_it(tmp_path):
    """A snapshot holding fewer records than the journal's base (its write failed after an
    update the journal was compacted at): the base is used, then the records after it."""
    state, live = _compacted(tmp_path)
    older, _ = _compacted(tmp_path / 'older', n_entries=20)
    state.write_bytes(older.read_bytes())   # a snapshot of fewer records
    res = recover(state, CFG, checkpoint=False)
    assert res.source == 'journal' and any('the base is used' in t for t in res.messages)
    assert_same_state(res.aligner, live.aligner)
    res.aligner.close()
    live.aligner.close()


def test_clearing_a_compacted_state_drops_the_base(tmp_path):
    state, live = _compacted(tmp_path)
    live.aligner.close()
    clear_state(state)
    j = MeasurementJournal(journal_path(state))
    assert j.count == 0 and not j.layout.has_base
    assert recover(state, CFG).source == 'empty'


def test_measurements_keep_their_source_through_the_journal(tmp_path):
    """The source (the group of a variance factor) comes back from the journal file, with the
    covariance bit for bit; HELD / REVERSED flags and the kind are unchanged by it."""
    from ga_ros.pipeline.journal import HELD, SOURCED
    from ga_ros.pipeline.journal.records import encode_records

    rng = np.random.default_rng(3)
    ms = []
    for k, source in enumerate(['odom0', '', 'gnss_ü', 'odom1' * 24, 'x' * 121]):
        A = rng.normal(size=(6, 6))
        cov = A @ A.T + np.eye(6)
        ms.append(Measurement(k, k + 1, 0, 0, rng.normal(size=6), cov, 10 + k,
                              ('consecutive', 'cross', 'bridge')[k % 3], source))
    path = tmp_path / 'j.journal'
    journal = MeasurementJournal(path)
    journal.open()
    journal.append_many(ms[:3])
    journal.append_many(ms[3:], HELD)
    journal.close()
    back = read_journal(path)
    assert [m.source for m in back] == [m.source for m in ms[:4]] + ['']  # 121 bytes: too long
    for a, b in zip(ms, back):
        assert (a.src_id, a.dst_id, a.kind, a.stamp_ns) == (b.src_id, b.dst_id, b.kind,
                                                            b.stamp_ns)
        assert np.array_equal(a.cov, b.cov) and np.array_equal(a.z, b.z)
    kinds = np.frombuffer(encode_records(ms), RECORD)['kind']
    assert ((kinds & SOURCED) != 0).tolist() == [True, False, True, True, False]


def _map_odom(k: float) -> np.ndarray:
    return se3.from_translation_rotvec(np.array([3.0 + k, -2.0, 0.25]),
                                       np.array([0.0, 0.0, 0.7 + k]))


def test_map_odom_records_round_trip_and_are_skipped_as_entries() -> None:
    """A ``map -> odom`` record holds the transform exactly; the last one is read back and a
    replay skips them (they are not the aligner's)."""
    raw = (encode_map_odom(MapOdom(_map_odom(0.1))) + encode_track_end(TrackEnd(3))
           + encode_map_odom(MapOdom(_map_odom(0.2))))
    recs = np.frombuffer(raw, RECORD)
    np.testing.assert_array_equal(last_map_odom_entry(recs).T_map_odom, _map_odom(0.2))
    assert last_map_odom_entry(recs[:1]) is not None and last_map_odom_entry(recs[1:2]) is None
    assert records_to_entries(recs) == [TrackEnd(3)]
    with pytest.raises(InputError, match='finite'):
        encode_map_odom(MapOdom(np.full((4, 4), np.nan)))


@pytest.mark.parametrize('compact', [0, 1])
def test_the_last_map_odom_survives_a_restart_and_compaction(tmp_path, compact) -> None:
    """Journaled after updates (an unchanged one not again), the last ``map -> odom`` comes back
    from a recovery, also when the journal was compacted after it (its base then holds the
    state and the record is kept) and from the journal alone; a reset forgets it."""
    entries = _survey(np.random.default_rng(11))
    state = tmp_path / 'state'
    live = AlignmentSession(CFG, SessionConfig(str(state), compact_records=compact))
    live.resume()
    feed_entries(live, entries[:20])
    live.journal_map_odom(_map_odom(0.1))
    before = live.journal.count
    live.journal_map_odom(_map_odom(0.1))
    assert live.journal.count == before   # the same transform: not journaled again
    feed_entries(live, entries[20:40])
    live.journal_map_odom(_map_odom(0.2))
    feed_entries(live, entries[40:50])
    if compact:
        assert live.compact(force=True)
    live.journal.close()
    live.aligner.close()
    res = recover(state, CFG, checkpoint=False)
    np.testing.assert_array_equal(res.map_odom, _map_odom(0.2))
    res.aligner.close()
    _lose_snapshot(state)
    res = recover(state, CFG, checkpoint=False)
    np.testing.assert_array_equal(res.map_odom, _map_odom(0.2))
    res.aligner.close()
    again = AlignmentSession(CFG, SessionConfig(str(state)))
    assert again.resume() is not None
    np.testing.assert_array_equal(again.map_odom, _map_odom(0.2))
    again.reset()
    assert again.map_odom is None
    again.close()
    res = recover(state, CFG, checkpoint=False)
    assert res.map_odom is None
    res.aligner.close()
