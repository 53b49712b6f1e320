"""Gaps that heal: a measurement whose source node is unknown is held, read backwards or bridged
(ga_ros.core.gaps through AlignmentSession.step), never dropped; a re-delivered gap gives the
gap-free result; an unfilled gap is bridged, its nodes marked until a real connection joins them;
held measurements and bridges survive a restart."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ga_ros.core.gaps import GapConfig, GapHealer, Route, reversed_measurement
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig
from ga_ros.errors import Reason
from ga_ros.geometry import se3
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.replay.samples import aerial_sample

# a refinement after every track (refine_relinearize_sigma 0): its batch solve removes the
# window solver's stopping differences between two orders of the same data (without it the
# estimates agree to ~2e-5 m, the window's cost tolerance, instead of 1e-6)
WINDOW = AlignerConfig(window_tracks=2, refine_relinearize_sigma=0.0)


@pytest.fixture(scope='module')
def sample():
    return aerial_sample(n_tracks=3, positions_per_swath=6, noise_pct=5.0, seed=9)


def _slice_of_nodes(ms: list, first: int, stop: int) -> tuple[int, int]:
    """Indices ``[i, j)`` of the measurements introducing nodes ``first .. stop - 1`` (the
    sample sends each node's measurements together, in node order)."""
    i = next(k for k, m in enumerate(ms) if m.dst_id == first)
    j = next(k for k, m in enumerate(ms) if m.dst_id == stop)
    return i, j


def _run(stream: list, gaps: GapConfig = GapConfig(), state: str = '') -> AlignmentSession:
    session = AlignmentSession(WINDOW, SessionConfig(state, gaps=gaps))
    for m in stream:
        session.step(m)
    session.finish_track()
    return session


def _by_id(session: AlignmentSession):
    cp = session.aligner.corrected_path()
    order = np.argsort(cp.node_ids)
    return cp.node_ids[order], cp.T_world_node[order]


def test_reversed_measurement_carries_the_same_distribution(rng: np.random.Generator) -> None:
    """Monte-Carlo: perturb ``T_src_dst`` on the right with samples of its covariance, invert,
    and measure the right perturbation of the inverse; its sample covariance is the reversed
    measurement's (a check independent of the adjoint formula)."""
    A = rng.normal(size=(6, 6)) * np.array([0.05] * 3 + [0.02] * 3)
    cov = A @ A.T + 1e-4 * np.eye(6)
    m = Measurement(3, 7, 1, 1, np.array([1.0, -0.4, 0.3, 0.2, -0.5, 0.8]), cov, 5, 'cross')
    r = reversed_measurement(m)
    assert (r.src_id, r.dst_id, r.src_track, r.dst_track, r.kind) == (7, 3, 1, 1, 'cross')
    np.testing.assert_allclose(r.T_src_dst @ m.T_src_dst, np.eye(4), atol=1e-12)
    d = rng.multivariate_normal(np.zeros(6), cov, size=40000)
    T_inv = se3.inverse(m.T_src_dst @ se3.exp(d))
    e = se3.log(se3.inverse(r.T_src_dst) @ T_inv)
    emp = np.cov(e.T)
    sd = np.sqrt(np.diag(r.cov))
    np.testing.assert_allclose(emp / np.outer(sd, sd), r.cov / np.outer(sd, sd), atol=0.03)


def test_routes_of_a_gap() -> None:
    healer = GapHealer()
    cov = np.eye(6) * 1e-4
    z = np.array([1.0, 0, 0, 0, 0, 0])
    healer.admitted(Measurement(0, 1, 0, 0, z, cov, 1, 'consecutive'))
    healer.admitted(Measurement(1, 2, 0, 0, z, cov, 2, 'consecutive'))
    healer.admitted(Measurement(2, 3, 0, 1, z, cov, 3, 'consecutive'))
    assert healer.route(Measurement(3, 4, 1, 1, z, cov, 4)) is Route.ADMIT
    assert healer.route(Measurement(5, 6, 1, 1, z, cov, 6)) is Route.HOLD       # both unknown
    assert healer.route(Measurement(5, 3, 1, 1, z, cov, 6, 'cross')) is Route.REVERSE
    assert healer.route(Measurement(9, 2, 0, 0, z, cov, 6, 'cross')) is Route.HOPELESS
    healer.hold(Measurement(5, 6, 1, 1, z, cov, 6))
    # held measurements hold back a new track, not the open one
    assert healer.route(Measurement(3, 7, 1, 2, z, cov, 7)) is Route.HOLD
    assert healer.route(Measurement(3, 7, 1, 2, z, cov, 7), front=True) is Route.ADMIT
    assert GapHealer(GapConfig(enabled=False)).route(Measurement(5, 6, 1, 1, z, cov)) \
        is Route.ADMIT


def test_a_refilled_gap_gives_the_gap_free_estimate(sample) -> None:
    """Three nodes' measurements (15-17, mid track 1) arrive 10 measurements late: the session
    holds what starts at them and reaches the estimate of the in-order run (to the solver's
    tolerance); the aligner alone loses nodes."""
    ms = sample.measurements
    i, j = _slice_of_nodes(ms, 15, 18)
    late = ms[:i] + ms[j:j + 10] + ms[i:j] + ms[j + 10:]
    ref = _run(ms)
    session = AlignmentSession(WINDOW)
    held_max = 0
    for m in late:
        out = session.step(m)
        assert out.accepted
        held_max = max(held_max, session.diagnostic_values()['held_measurements'])
    session.finish_track()
    values = session.diagnostic_values()
    assert held_max > 0 and values['held_measurements'] == 0
    assert values['bridges'] == 0 and values['unjoined_nodes'] == 0 and values['rejected'] == 0
    assert values['measurements_accepted'] == len(ms)
    ids, T = _by_id(session)
    ref_ids, ref_T = _by_id(ref)
    np.testing.assert_array_equal(ids, ref_ids)
    np.testing.assert_allclose(T, ref_T, atol=1e-6)
    np.testing.assert_allclose(session.aligner.covariances(ids[-5:]),
                               ref.aligner.covariances(ids[-5:]), rtol=1e-5, atol=1e-12)
    alone = _run(late, GapConfig(enabled=False))
    assert alone.n_nodes() < len(ids) and alone.counts.rejected[Reason.UNKNOWN_SOURCE] > 0


def _unfilled(ms: list) -> list:
    """Nodes 15-17 never arrive, and node 18 only has connections from them: the piece that
    starts there has no connection to a known node until node 19's."""
    i, j = _slice_of_nodes(ms, 15, 18)
    return ms[:i] + [m for m in ms[j:] if not (m.dst_id == 18 and m.src_id < 15)]


def _position_errors(session: AlignmentSession, gt) -> tuple[np.ndarray, np.ndarray]:
    ids, T = _by_id(session)
    T_gt = gt.T_world_node[np.searchsorted(gt.node_ids, ids)]
    return ids, np.linalg.norm(T[:, :3, 3] - T_gt[:, :3, 3], axis=1)


def test_an_unfilled_gap_is_bridged_marked_and_joined(sample) -> None:
    """The held piece is bridged after its wait (3 measurements here): its nodes enter the path
    marked as not joined; node 19's cross connections join it. Every node of the gap-free run
    is kept (the gap's nodes re-enter through later measurements, read backwards), and the
    position errors against the ground truth stay within 1.5 times the gap-free run's largest
    (plus 1 cm)."""
    ms = sample.measurements
    stream = _unfilled(ms)
    session = AlignmentSession(WINDOW, SessionConfig(gaps=GapConfig(wait_measurements=3)))
    marked = []
    for m in stream:
        out = session.step(m)
        assert out.accepted
        if any(a.kind == 'bridge' for a in out.admitted):
            bridge = next(a for a in out.admitted if a.kind == 'bridge')
            cp = session.aligner.corrected_path()
            flags = session.unjoined(cp.node_ids)
            marked = cp.node_ids[flags].tolist()
            assert session.diagnostic_values()['unjoined_nodes'] == len(marked) > 0
            assert bridge.dst_id in marked and 0 not in marked
            assert not session.health().ok
    session.finish_track()
    assert marked, 'no bridge was made'
    values = session.diagnostic_values()
    assert values['bridges'] == 1 and values['unjoined_nodes'] == 0 and values['rejected'] == 0
    ref = _run(ms)
    ids, err = _position_errors(session, sample.ground_truth)
    ref_ids, ref_err = _position_errors(ref, sample.ground_truth)
    np.testing.assert_array_equal(ids, ref_ids)
    assert err.max() <= 1.5 * ref_err.max() + 0.01, (err.max(), ref_err.max())


def test_a_gap_refilled_after_its_bridge_is_joined_by_the_real_motions(sample) -> None:
    """The gap's measurements arrive after the bridge (still inside the window): they are taken
    as real connections; the bridge's weight is negligible against them, so the estimate is the
    gap-free one to 1 mm."""
    ms = sample.measurements
    i, j = _slice_of_nodes(ms, 15, 18)
    stream = ms[:i] + ms[j:j + 12] + ms[i:j] + ms[j + 12:]
    session = _run(stream, GapConfig(wait_measurements=3))
    values = session.diagnostic_values()
    assert values['bridges'] >= 1 and values['unjoined_nodes'] == 0 and values['rejected'] == 0
    ids, T = _by_id(session)
    ref_ids, ref_T = _by_id(_run(ms))
    np.testing.assert_array_equal(ids, ref_ids)
    assert np.abs(T[:, :3, 3] - ref_T[:, :3, 3]).max() < 1e-3


def test_a_source_in_an_older_track_is_rejected_not_held(sample) -> None:
    ms = sample.measurements
    session = AlignmentSession(WINDOW)
    k = next(k for k, m in enumerate(ms) if m.dst_track == 1)
    for m in ms[:k + 3]:
        session.step(m)
    ghost = Measurement(9999, ms[k].dst_id, 0, 1, ms[k].z, ms[k].cov, ms[k].stamp_ns, 'cross')
    out = session.step(ghost)
    assert not out.accepted and out.reason is Reason.UNKNOWN_SOURCE
    assert session.diagnostic_values()['held_measurements'] == 0


@pytest.mark.parametrize('cut, compact, lose_snapshot', [
    ('held', 1000, False), ('bridged', 1000, False), ('held', 1, True), ('bridged', 1, True),
    ('bridged', 1, False)])
def test_held_measurements_and_bridges_survive_a_restart(tmp_path: Path, sample, cut: str,
                                                         compact: int,
                                                         lose_snapshot: bool) -> None:
    """A session stopped (not closed: as by kill -9) while measurements are held, or after a
    bridge, and resumed on its state file ends where the uninterrupted session ends; also from
    a journal compacted at every update (its base, the bridge kept beside it), alone."""
    ms = sample.measurements
    stream = _unfilled(ms)
    gaps = GapConfig(wait_measurements=3)
    i, _ = _slice_of_nodes(ms, 15, 18)
    stop = i + (2 if cut == 'held' else 6)
    if compact == 1 and cut == 'bridged':  # past the next track end: a compaction after it
        stop = next(k for k, m in enumerate(stream) if k > stop and m.src_track != m.dst_track)
        stop += 2
    state = tmp_path / 's.npz'
    first = AlignmentSession(WINDOW, SessionConfig(str(state), gaps=gaps,
                                                   compact_records=compact))
    first.resume()
    for m in stream[:stop]:
        first.step(m)
    before = first.diagnostic_values()
    assert (before['held_measurements'] > 0) if cut == 'held' else (before['bridges'] == 1)
    first.journal.close()  # no close(): no final fsync or snapshot
    if compact == 1 and cut == 'bridged':
        assert first.journal.layout.has_base and first.journal.layout.n_context >= 1
    if lose_snapshot:
        state.unlink()
    second = AlignmentSession(WINDOW, SessionConfig(str(tmp_path / 's.npz'), gaps=gaps))
    second.resume()
    after = second.diagnostic_values()
    for key in ('held_measurements', 'unjoined_nodes', 'nodes'):
        assert after[key] == before[key], key
    for m in stream[stop:]:
        second.step(m)
    second.finish_track()
    ref = _run(stream, gaps)
    ids, T = _by_id(second)
    ref_ids, ref_T = _by_id(ref)
    np.testing.assert_array_equal(ids, ref_ids)
    np.testing.assert_allclose(T, ref_T, atol=1e-6)
    assert second.diagnostic_values()['unjoined_nodes'] == 0


def test_replay_of_a_bag_with_a_gap_keeps_every_node(tmp_path: Path, sample) -> None:
    """``ga-ros replay`` drives the same session: a bag missing three nodes' measurements (and
    node 18's links to known nodes) still gives a path of every node, none rejected, and the
    summary says how the gap was healed."""
    import json

    from ga_ros.replay.config import ReplayConfig
    from ga_ros.replay.pipeline import replay
    from ga_ros.replay.samples import write_measurement_bag

    bag = write_measurement_bag(tmp_path / 'in', _unfilled(sample.measurements),
                                sample.ground_truth)
    r = replay(bag, tmp_path / 'out', ReplayConfig(plot=False))
    assert r.error is None and r.rejected == {}
    assert r.n_nodes == sample.ground_truth.node_ids.size
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert summary['gaps']['bridges'] + summary['gaps']['reversed_measurements'] > 0
    assert summary['gaps']['unjoined_nodes'] == []


def test_a_piece_never_joined_stays_marked_with_the_bridge_covariance(sample) -> None:
    """Two tracks; after the gap (nodes 15-17) nothing connects the rest of track 1 to a known
    node but the bridge: its nodes stay marked, the session warns, and their published
    covariances carry the bridge's uncertainty (standard deviation >= its 100 m) while the
    joined nodes' stay below 1 m."""
    ms = [m for m in sample.measurements if m.dst_track < 2]
    i, j = _slice_of_nodes(ms, 15, 18)
    stream = ms[:i] + [m for m in ms[j:] if m.src_id >= 15]
    session = _run(stream, GapConfig(wait_measurements=3))
    values = session.diagnostic_values()
    assert values['bridges'] == 1 and values['rejected'] == 0
    cp = session.aligner.corrected_path()
    flags = session.unjoined(cp.node_ids)
    assert flags.sum() == values['unjoined_nodes'] == np.count_nonzero(cp.node_ids >= 15)
    assert not session.health().ok and 'bridge' in session.health().message
    sd = np.sqrt(np.diagonal(session.aligner.covariances(cp.node_ids), axis1=1, axis2=2))
    assert sd[flags, :3].min() >= 100.0 * 0.99
    assert sd[~flags & (cp.node_ids > 0), :3].max() < 1.0


def test_a_measurement_taken_reversed_is_a_duplicate_when_it_comes_again(tmp_path: Path,
                                                                          sample) -> None:
    """Re-delivered (e.g. a transient-local history after a restart), a measurement the session
    took reversed is a duplicate, not a second connection; also after a restart."""
    ms = sample.measurements
    i, j = _slice_of_nodes(ms, 15, 18)
    stream = ms[:i] + ms[j:j + 10]
    state = str(tmp_path / 's.npz')
    session = AlignmentSession(WINDOW, SessionConfig(state))
    session.resume()
    for m in stream:
        session.step(m)
    n_conn = session.diagnostic_values()['connections']
    assert session.counts.reversed > 0
    again = [session.step(m) for m in stream[i:]]
    assert all(not o.accepted and o.reason is Reason.DUPLICATE for o in again)
    assert session.diagnostic_values()['connections'] == n_conn
    session.journal.close()
    second = AlignmentSession(WINDOW, SessionConfig(state))
    second.resume()
    assert second.diagnostic_values()['connections'] == n_conn
    again = [second.step(m) for m in stream[i:]]
    assert all(not o.accepted and o.reason is Reason.DUPLICATE for o in again)


@pytest.mark.parametrize('bad', ['nan_id', 'nan_z', 'shape', 'stamp', 'kind'])
def test_malformed_measurements_from_unknown_nodes_get_the_aligners_reason(sample,
                                                                            bad: str) -> None:
    ms = sample.measurements
    session = AlignmentSession(WINDOW)
    for m in ms[:10]:
        session.step(m)
    good = Measurement(500, 501, 0, 0, ms[3].z, ms[3].cov, ms[3].stamp_ns, 'consecutive')
    m = {'nan_id': lambda: Measurement(float('nan'), 501, 0, 0, good.z, good.cov),
         'nan_z': lambda: Measurement(500, 501, 0, 0, good.z * np.nan, good.cov),
         'shape': lambda: Measurement(500, 501, 0, 0, good.z[:5], good.cov),
         'stamp': lambda: Measurement(500, 501, 0, 0, good.z, good.cov, 1.5),
         'kind': lambda: Measurement(500, 501, 0, 0, good.z, good.cov, 0, 'loop')}[bad]()
    out = session.step(m)
    assert not out.accepted and out.reason is not Reason.UNKNOWN_SOURCE
    assert out.reason == {'nan_id': 'bad_id', 'nan_z': 'non_finite', 'shape': 'bad_shape',
                          'stamp': 'bad_stamp', 'kind': 'bad_kind'}[bad]
    assert session.diagnostic_values()['held_measurements'] == 0


def test_the_end_of_a_track_bridges_what_is_still_held(sample) -> None:
    """With the default waits (300 arrivals, 30 s) nothing is bridged during the stream; the
    track end (``~/finish_track``, the end of input) admits the held measurements behind a
    bridge, and the next measurements continue from them."""
    ms = _unfilled(sample.measurements)
    i, _ = _slice_of_nodes(sample.measurements, 15, 18)
    session = AlignmentSession(WINDOW)
    for m in ms[:i + 2]:
        session.step(m)
    held = session.diagnostic_values()['held_measurements']
    assert held == 2 and session.diagnostic_values()['bridges'] == 0
    n_nodes = session.n_nodes()
    session.finish_track()
    values = session.diagnostic_values()
    assert values['held_measurements'] == 0 and values['bridges'] == 1
    assert session.n_nodes() == n_nodes + 3  # the bridged node and the held ones' new nodes
    assert values['unjoined_nodes'] == 3 and values['rejected'] == 0


def test_an_absolute_fix_joins_the_piece_of_its_node(sample) -> None:
    """The anchor of absolute fixes (``AlignmentSession.add_fix`` calls it): a fix on
    any node of a bridged piece joins the whole piece; a fix on an unknown node changes
    nothing."""
    ms = [m for m in sample.measurements if m.dst_track < 2]
    i, j = _slice_of_nodes(ms, 15, 18)
    session = _run(ms[:i] + [m for m in ms[j:] if m.src_id >= 15], GapConfig(wait_measurements=3))
    assert session.gaps.n_unjoined > 0
    assert not session.gaps.anchor(10**6)
    assert session.gaps.anchor(int(session.aligner.corrected_path().node_ids[-1]))
    assert session.gaps.n_unjoined == 0 and session.health().ok
