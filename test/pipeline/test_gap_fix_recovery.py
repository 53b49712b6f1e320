"""A gap healed by absolute fixes survives a crash: the session anchors the piece of a fixed node
in its gap healer (ga_ros.core.gaps) when it takes the fix, and again when it rebuilds the healer
from a recovered state (snapshot + journal), so the recovered session marks the same nodes as
joined and ends with the same poses as the uninterrupted one."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ga_ros.core.fixes import AbsoluteFix, FixTerm, identity_offset
from ga_ros.core.gaps import GapConfig
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig
from ga_ros.geometry import se3
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.replay.samples import aerial_sample

CFG = AlignerConfig(window_tracks=2, datum='fixes', refine_every_tracks=1,
                    refine_executor='inline', fix_gate_prob=0.0)
GAPS = GapConfig(wait_measurements=3)
#: Nodes with a fix: two before the gap (nodes 15-17 never arrive), two on the piece after it.
FIXED = (4, 9, 19, 21)


@pytest.fixture(scope='module')
def sample():
    return aerial_sample(n_tracks=3, positions_per_swath=6, noise_pct=5.0, seed=9)


def _stream(sample) -> list[Measurement]:
    """Two tracks; nodes 15-17 never arrive and nothing but the bridge links the rest of track
    1 to a known node: only the fixes on nodes 19 and 21 join that piece."""
    ms = [m for m in sample.measurements if m.dst_track < 2]
    i = next(k for k, m in enumerate(ms) if m.dst_id == 15)
    j = next(k for k, m in enumerate(ms) if m.dst_id == 18)
    return ms[:i] + [m for m in ms[j:] if m.src_id >= 15]


def _fixes(sample, rng: np.random.Generator) -> dict[int, FixTerm]:
    """A GNSS-like fix (0.3 m, yaw 0.1 rad; roll and pitch unknown) on each node of
    :data:`FIXED`, at its ground-truth pose plus noise."""
    gt = sample.ground_truth
    out = {}
    for node in FIXED:
        T = gt.T_world_node[int(np.searchsorted(gt.node_ids, node))]
        noise = np.concatenate([rng.normal(0.0, 0.3, 3), [0.0, 0.0, rng.normal(0.0, 0.1)]])
        fix = AbsoluteFix.from_covariance(node * 10**9, T @ se3.exp(noise),
                                          np.diag([0.09] * 3 + [-1.0, -1.0, 0.01]), 'gnss0')
        out[node] = FixTerm(node, identity_offset(), fix)
    return out


def _feed(session: AlignmentSession, stream: list[Measurement], waiting: dict[int, FixTerm]
          ) -> None:
    """Step the measurements; after each, give the session the waiting fixes whose node it now
    holds (as the node's fix feeder does)."""
    for m in stream:
        assert session.step(m).accepted
        for node in [n for n in waiting if session.gaps.knows(n)]:
            session.add_fix(waiting.pop(node))


def _by_id(session: AlignmentSession) -> tuple[np.ndarray, np.ndarray]:
    cp = session.aligner.corrected_path()
    order = np.argsort(cp.node_ids)
    return cp.node_ids[order], cp.T_world_node[order]


def test_a_gap_healed_by_fixes_survives_a_crash(tmp_path: Path, sample) -> None:
    stream = _stream(sample)
    fixes = _fixes(sample, np.random.default_rng(4))
    ref = AlignmentSession(CFG, SessionConfig(gaps=GAPS))
    _feed(ref, stream, dict(fixes))
    ref.finish_track()
    assert ref.diagnostic_values()['bridges'] == 1
    assert ref.aligner.fix_stats.added == len(FIXED)

    # the crash: after the last fix, mid-track, with the piece after the gap joined by it
    stop = next(k for k, m in enumerate(stream) if m.dst_id == 22)
    state = str(tmp_path / 's.npz')
    first = AlignmentSession(CFG, SessionConfig(state, gaps=GAPS))
    assert first.resume() is None
    waiting = dict(fixes)
    _feed(first, stream[:stop], waiting)
    assert not waiting, 'every fix was taken before the crash'
    before = first.diagnostic_values()
    assert before['bridges'] == 1 and before['unjoined_nodes'] == 0 and first.health().ok
    first.journal.close()  # killed: no final fsync, no snapshot
    first.aligner.close()

    second = AlignmentSession(CFG, SessionConfig(state, gaps=GAPS))
    assert second.resume().startswith('snapshot')
    after = second.diagnostic_values()
    for key in ('nodes', 'held_measurements', 'unjoined_nodes'):
        assert after[key] == before[key], key
    assert second.health() == first.health()
    _feed(second, stream[stop:], {})
    second.finish_track()

    ids, T = _by_id(second)
    ref_ids, ref_T = _by_id(ref)
    np.testing.assert_array_equal(ids, ref_ids)
    np.testing.assert_allclose(T, ref_T, atol=1e-6)
    np.testing.assert_array_equal(second.unjoined(ids), ref.unjoined(ref_ids))
    assert second.diagnostic_values()['unjoined_nodes'] == 0
    assert second.health() == ref.health()
    for s in (ref, second):
        s.close()


def test_without_the_fixes_the_piece_stays_unjoined(sample) -> None:
    """The fixes are what joins the piece after the gap (so the test above can fail)."""
    session = AlignmentSession(CFG, SessionConfig(gaps=GAPS))
    _feed(session, _stream(sample), {})
    session.finish_track()
    cp = session.aligner.corrected_path()
    assert session.unjoined(cp.node_ids).sum() == np.count_nonzero(cp.node_ids >= 15) > 0
    session.close()
