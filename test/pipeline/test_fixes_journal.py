"""The measurement journal records absolute fixes: a crash loses none since the last state file,
and recovery replays them in order with the measurements."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.fixes import FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.pipeline.journal import (
    RECORD,
    encode_fix,
    encode_records,
    journal_path,
    read_journal,
    records_to_entries,
    recover,
)
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.sim.fix_survey import line_fix_survey

CFG = AlignerConfig(window_tracks=2, datum='fixes', refine_every_tracks=1,
                    refine_executor='inline', fix_gate_prob=0.0)


def _survey(rng: np.random.Generator, n_tracks: int = 5, per: int = 6):
    """A line survey with a fix (lever arm, odometry offset covariance) on every third node."""
    return line_fix_survey(rng, n_tracks, per, sources=((3, 'gnss0', 0.3),))


@pytest.fixture
def entries():
    return _survey(np.random.default_rng(3))


def _feed(target, entries) -> None:
    for e in entries:
        if isinstance(e, Measurement):
            (target.step if isinstance(target, AlignmentSession) else target.add_measurement)(e)
        else:
            target.add_fix(*e)


def test_fix_records_round_trip(entries) -> None:
    term, _ = next(e for e in entries if not isinstance(e, Measurement))
    m = next(e for e in entries if isinstance(e, Measurement))
    raw = encode_records([m]) + encode_fix(term) + encode_records([m])
    back = records_to_entries(np.frombuffer(raw, RECORD))
    assert len(back) == 3 and _same(back[0], m) and _same(back[2], m)
    fix = back[1]
    assert isinstance(fix, FixTerm) and fix.node_id == term.node_id
    assert fix.fix.stamp_ns == term.fix.stamp_ns and fix.fix.source == term.fix.source
    np.testing.assert_allclose(fix.T_node_sensor, term.T_node_sensor, atol=1e-12)
    np.testing.assert_allclose(fix.fix.T_map_sensor, term.fix.T_map_sensor, atol=1e-12)
    np.testing.assert_array_equal(fix.fix.information, term.fix.information)
    # a fix record without its second half (damage) is skipped, the rest kept
    cut = np.frombuffer(encode_fix(term)[:RECORD.itemsize] + encode_records([m]), RECORD)
    left = records_to_entries(cut)
    assert len(left) == 1 and _same(left[0], m)


def _same(a: Measurement, b: Measurement) -> bool:
    return (isinstance(a, Measurement) and (a.src_id, a.dst_id, a.stamp_ns, a.kind)
            == (b.src_id, b.dst_id, b.stamp_ns, b.kind) and np.array_equal(a.z, b.z)
            and np.array_equal(a.cov, b.cov))


def test_a_crash_loses_no_fix_and_recovery_replays_them_in_order(tmp_path, entries) -> None:
    """A session journals measurements and fixes (state file saved after each update); it is
    killed mid-track; recovery gives the state of an aligner fed the same entries."""
    state = tmp_path / 'state.ga'
    cut = max(k for k, e in enumerate(entries) if not isinstance(e, Measurement)) - 1
    cut += 2  # just after the last fix, mid-track
    session = AlignmentSession(CFG, SessionConfig(str(state), True))
    assert session.resume() is None
    _feed(session, entries[:cut])
    n_fixes = len(session.aligner.state.fixes)
    session.journal.close()  # killed: nothing else saved
    session.aligner.close()
    logged = read_journal(journal_path(state))
    assert sum(isinstance(e, FixTerm) for e in logged) == n_fixes - 1  # all but the gauge
    res = recover(state, CFG)
    assert res.source == 'snapshot+journal' and res.records_rejected == 0
    ref = TrackWindowAligner(CFG)
    _feed(ref, entries[:cut])
    got = res.aligner
    assert len(got.state.fixes) == len(ref.state.fixes)
    for al in (got, ref):
        al.finish_track()
    np.testing.assert_allclose(got.corrected_path().T_world_node,
                               ref.corrected_path().T_world_node, atol=1e-9)
    np.testing.assert_allclose(np.array(got.state.fixes.info), np.array(ref.state.fixes.info),
                               rtol=1e-12, atol=1e-12)
    got.close()
    ref.close()


def test_without_the_fix_records_recovery_would_differ(tmp_path, entries) -> None:
    """The fixes matter: the same measurements without the fixes give another path (so the
    test above can fail)."""
    cut = len(entries) - 3
    a, b = TrackWindowAligner(CFG), TrackWindowAligner(CFG)
    _feed(a, entries[:cut])
    _feed(b, [e for e in entries[:cut] if isinstance(e, Measurement)])
    for al in (a, b):
        al.finish_track()
    d = np.abs(a.corrected_path().T_world_node[:, :3, 3]
               - b.corrected_path().T_world_node[:, :3, 3]).max()
    assert d > 0.05
