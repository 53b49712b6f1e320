"""Defensive numerics of the aligner: covariance ranges, implausible ids, and failed updates
that leave the previous state intact (only GaError ever escapes)."""

from __future__ import annotations

import numpy as np
import pytest

import ga_ros.core.window.update as window
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import GaError, InputError
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

CFG = AlignerConfig(window_tracks=2)


@pytest.fixture(scope='module')
def ms():
    sc = aerial_scenario(n_tracks=4, positions_per_swath=5)
    nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(11))
    return sc.measurements(nm.z, nm.cov)


def _with(m, **kw):
    d = dict(src_id=m.src_id, dst_id=m.dst_id, src_track=m.src_track, dst_track=m.dst_track,
             z=m.z, cov=m.cov, stamp_ns=m.stamp_ns, kind=m.kind)
    d.update(kw)
    return Measurement(**d)


def _snapshot(al):
    n = len(al.state.ids)
    st = al.state
    return (st.T[:n].copy(), st.cov[:n].copy(), st.frozen[:n].copy(), st.status.a.copy(),
            len(al.state.priors), al.stats.n_connections)


def _assert_same(a, b):
    for x, y in zip(a, b):
        np.testing.assert_array_equal(x, y)


def _run(ms, cfg=CFG, extra=None, at=None):
    """Feed ``ms`` (``extra`` inserted before index ``at``); returns the aligner and what was
    rejected, by reason."""
    al = TrackWindowAligner(cfg)
    feed = list(ms) if extra is None else ms[:at] + [extra] + ms[at:]
    res = al.add_measurements(feed)
    al.finish_track()
    return al, res.rejected


def _new_track_index(ms, track=2):
    return next(k for k, m in enumerate(ms) if m.dst_track == track)


@pytest.mark.parametrize('cov', [
    1e-20 * np.eye(6),                              # tiny: made the next window update fail
    1e308 * np.eye(6),                              # placeholder for "unknown"
    1e9 * np.eye(6),                                # another placeholder
    np.zeros((6, 6)),                               # "no covariance"
    np.diag([-1.0, 0, 0, 0, 0, 0]),                 # ROS convention for "unknown"
    np.diag([1e-10] * 3 + [1e3] * 3),               # condition number 1e13
], ids=['tiny', 'huge', 'big', 'zeros', 'ros_unknown', 'ill_conditioned'])
def test_out_of_range_covariances_are_rejected_and_the_survey_goes_on(ms, cov):
    at = _new_track_index(ms) + 3
    bad = _with(ms[at - 1], cov=cov)       # valid but for the covariance
    al, rejected = _run(ms, extra=bad, at=at)
    assert rejected == {'bad_covariance': 1}
    ref, _ = _run(ms)
    np.testing.assert_array_equal(al.corrected_path().node_ids, ref.corrected_path().node_ids)
    np.testing.assert_allclose(al.corrected_path().T_world_node, ref.corrected_path().T_world_node,
                               atol=1e-12)


def test_a_tiny_covariance_of_a_new_link_is_rejected_with_its_reason(ms):
    """Before the range check, 1e-20 I was accepted and broke every later window update."""
    al = TrackWindowAligner(CFG)
    at = _new_track_index(ms) + 3
    al.add_measurements(ms[:at])
    before = _snapshot(al)
    with pytest.raises(InputError, match='cov_min_eigenvalue') as err:
        al.add_measurement(_with(ms[at], cov=1e-20 * np.eye(6)))
    assert err.value.reason == 'bad_covariance'
    _assert_same(before, _snapshot(al))


def test_the_limits_are_configurable(ms):
    cov = np.diag([1e-8] * 3 + [1e3] * 3)        # condition number 1e11
    TrackWindowAligner(CFG).add_measurement(_with(ms[0], cov=cov))
    strict = TrackWindowAligner(AlignerConfig(window_tracks=2, cov_max_condition=1e10))
    with pytest.raises(InputError, match='cov_max_condition'):
        strict.add_measurement(_with(ms[0], cov=cov))
    lax = TrackWindowAligner(AlignerConfig(window_tracks=2, cov_min_eigenvalue=1e-30))
    lax.add_measurement(_with(ms[0], cov=1e-20 * np.eye(6)))
    with pytest.raises(InputError):
        AlignerConfig(cov_min_eigenvalue=0.0)
    with pytest.raises(InputError):
        AlignerConfig(cov_max_condition=0.5)


def test_a_far_ahead_track_id_is_rejected_and_does_not_end_the_survey(ms):
    at = _new_track_index(ms) + 3
    last = ms[at - 1]
    bad = _with(last, src_id=last.dst_id, src_track=last.dst_track, dst_id=last.dst_id + 1,
                dst_track=1_000_000)
    al, rejected = _run(ms, extra=bad, at=at)
    assert rejected == {'track_jump': 1}
    ref, _ = _run(ms)
    assert al.stats.n_nodes == ref.stats.n_nodes
    np.testing.assert_allclose(al.corrected_path().T_world_node, ref.corrected_path().T_world_node,
                               atol=1e-12)
    # with the check disabled the same message is accepted (and ends track 2)
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, max_track_jump=0))
    al.add_measurements(ms[:at])
    al.add_measurement(bad)
    assert al.open_track == 1_000_000


def test_a_node_id_of_two_to_the_53_after_500_is_rejected(ms):
    al = TrackWindowAligner(CFG)
    al.add_measurements(ms[:10])
    last = ms[9]
    with pytest.raises(InputError, match='max_node_id_jump') as err:
        al.add_measurement(_with(last, src_id=last.dst_id, dst_id=2**53))
    assert err.value.reason == 'id_jump'
    assert 2**53 not in al.corrected_path().node_ids.tolist()
    al.add_measurement(_with(last, src_id=last.dst_id, dst_id=last.dst_id + 5000))  # a gap is ok


@pytest.mark.parametrize('kw, reason', [
    (dict(kind='loop'), 'bad_kind'),
    (dict(stamp_ns=None), 'bad_stamp'),
    (dict(z=['a'] * 6), 'invalid'),
    (dict(cov='identity'), 'invalid'),
])
def test_no_exception_but_a_ga_error_escapes_add_measurement(ms, kw, reason):
    al = TrackWindowAligner(CFG)
    al.add_measurements(ms[:5])
    before = _snapshot(al)
    with pytest.raises(GaError) as err:
        al.add_measurement(_with(ms[5], **kw))
    assert err.value.reason == reason and al.stats.n_rejected == {reason: 1}
    _assert_same(before, _snapshot(al))


def test_a_failed_update_restores_the_previous_state_and_is_retried(ms, monkeypatch):
    """A numerical failure in the middle of an update (here while freezing, after part of the
    state was changed) is reported in the result; nothing escapes and nothing is half-done."""
    al = TrackWindowAligner(CFG)
    k3 = _new_track_index(ms, 3)
    al.add_measurements(ms[:k3])        # tracks 0, 1 finished; track 2 open
    before = _snapshot(al)
    real_freeze = TrackWindowAligner._freeze

    def broken_freeze(self, track):
        self.state.frozen[:3] = True
        self.state.cov[:3] = np.nan
        raise np.linalg.LinAlgError('Matrix is not positive definite')

    monkeypatch.setattr(TrackWindowAligner, '_freeze', broken_freeze)
    up = al.finish_track()
    assert up.reason.startswith('failed') and 'LinAlgError' in up.reason
    _assert_same(before, _snapshot(al))
    monkeypatch.setattr(TrackWindowAligner, '_freeze', real_freeze)
    assert al.add_measurements(ms[k3:]).n_rejected == 0
    assert al.finish_track().converged            # track 2 is adjusted in this window
    ref = TrackWindowAligner(CFG)
    ref.add_measurements(ms)
    ref.finish_track()
    np.testing.assert_allclose(al.corrected_path().T_world_node,
                               ref.corrected_path().T_world_node, atol=0.2)


def test_a_solver_exception_inside_an_update_does_not_escape(ms, monkeypatch):
    al = TrackWindowAligner(CFG)
    al.strict = False  # a ValueError: raised under the test suite's strict updates
    k3 = _new_track_index(ms, 3)
    al.add_measurements(ms[:k3])
    before = _snapshot(al)

    def broken_solve(*args, **kwargs):
        raise ValueError('array must not contain infs or NaNs')

    monkeypatch.setattr(window, 'solve', broken_solve)
    ups = al.add_measurement(ms[k3])             # ends track 2: its update fails
    assert len(ups) == 1 and ups[0].reason.startswith('failed: ValueError')
    _assert_same(before[:3], tuple(x[:len(before[0])] for x in _snapshot(al)[:3]))
    assert al.open_track == 3
    monkeypatch.undo()
    al.add_measurements(ms[k3 + 1:])
    assert al.finish_track().converged
    assert al.stats.n_nodes == len({m.dst_id for m in ms} | {ms[0].src_id})


def test_a_repeated_covariance_is_checked_once_but_a_changed_one_again(ms):
    """The same stated covariance, byte for byte, is not checked again (the aligner keeps the
    last one admitted); the stored result is exactly what the full check gives, and a
    covariance that differs in any byte (even the same array changed in place) is checked."""
    al, ref = TrackWindowAligner(CFG), TrackWindowAligner(CFG)
    shared = np.array(ms[0].cov, dtype=float)
    for m in ms[:6]:
        al.add_measurement(_with(m, cov=shared))
    for m in ms[:6]:
        ref.add_measurement(_with(m, cov=np.array(shared)))  # a fresh array each time
    np.testing.assert_array_equal(al.state.ccov.a[:6], ref.state.ccov.a[:6])
    shared[0, 0] = -1.0  # the same array, now not positive definite
    before = _snapshot(al)
    with pytest.raises(InputError) as err:
        al.add_measurement(_with(ms[6], cov=shared))
    assert err.value.reason == 'bad_covariance'
    _assert_same(before, _snapshot(al))
    strict = AlignerConfig(window_tracks=2, cov_max_condition=1.0)  # another configuration
    al.config = strict
    with pytest.raises(InputError, match='cov_max_condition'):
        al.add_measurement(_with(ms[6], cov=np.array(ms[0].cov, dtype=float)))


def test_pose_is_the_corrected_paths_row(ms):
    al = TrackWindowAligner(CFG)
    al.add_measurements(ms)
    al.finish_track()
    path = al.corrected_path()
    for k in (0, len(path.node_ids) // 2, len(path.node_ids) - 1):
        np.testing.assert_array_equal(al.pose(int(path.node_ids[k])), path.T_world_node[k])
    T = al.pose(int(path.node_ids[0]))
    T[:] = 0.0  # a copy: the estimate stays
    np.testing.assert_array_equal(al.pose(int(path.node_ids[0])), path.T_world_node[0])
    with pytest.raises(InputError, match='unknown node'):
        al.pose(10**9)
