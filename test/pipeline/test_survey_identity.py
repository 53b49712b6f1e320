"""A session resuming a saved state decides on the first measurement whether it is the same
survey (pipeline/session/survey_identity.py, ROS-free): the same survey re-delivered (from its
start, or a bounded history's tail) resumes with the re-deliveries counted as duplicates;
another survey moves the saved state to a dated folder (nothing deleted) and starts afresh,
its result identical to a session that never had a state."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.pipeline.journal import journal_path
from ga_ros.pipeline.session import AlignmentSession, SessionConfig
from ga_ros.pipeline.session.survey_identity import continues
from ga_ros.replay.samples import aerial_sample


@pytest.fixture(scope='module')
def surveys():
    a = aerial_sample(n_tracks=3, positions_per_swath=6, seed=12).measurements
    b = aerial_sample(n_tracks=3, positions_per_swath=6, seed=13).measurements
    return a, b


def _reference(ms):
    """An aligner (defaults) fed ``ms`` then a track end: the uninterrupted run."""
    al = TrackWindowAligner(AlignerConfig())
    al.add_measurements(ms)
    al.finish_track()
    return al.corrected_path()


def _session(state, warnings):
    s = AlignmentSession(AlignerConfig(), SessionConfig(str(state), lock_owner='test'),
                         warn=warnings.append)
    s.resume()
    return s


def _feed(s, ms):
    for m in ms:
        s.step(m)


def _end(s):
    s.finish_track('end_of_input')
    path = s.aligner.corrected_path()
    s.close()
    return path


def test_the_same_survey_redelivered_resumes(tmp_path, surveys) -> None:
    a, _ = surveys
    state, warns = tmp_path / 'state', []
    s = _session(state, warns)
    _feed(s, a[:len(a) // 2])                   # then the node is killed (the files stay)
    s.close()
    s = _session(state, warns)
    assert s.survey_check_pending
    _feed(s, a)                                 # the publisher's whole history again
    got = _end(s)
    ref = _reference(a)
    assert s.previous_survey is None and not list(tmp_path.glob('state.survey-*'))
    assert s.counts.rejected['duplicate'] == len(a) // 2
    np.testing.assert_array_equal(got.node_ids, ref.node_ids)
    np.testing.assert_allclose(got.T_world_node, ref.T_world_node, atol=1e-9)
    assert not [w for w in warns if 'different survey' in w]


def test_a_bounded_history_tail_resumes(tmp_path, surveys) -> None:
    """The publisher kept only its last measurements: the first one re-delivered is one the
    state holds (or the next one): the same survey."""
    a, _ = surveys
    state, warns = tmp_path / 'state', []
    k = 2 * len(a) // 3
    s = _session(state, warns)
    _feed(s, a[:k])
    s.close()
    for first in (k - 10, k):                   # a tail overlapping what was held, or not
        assert continues(_resumed(state).aligner, a[first])[0]
    s = _session(state, warns)
    _feed(s, a[k - 10:])
    got = _end(s)
    np.testing.assert_allclose(got.T_world_node, _reference(a).T_world_node, atol=1e-9)
    assert s.previous_survey is None and s.counts.rejected['duplicate'] == 10


def _resumed(state):
    s = AlignmentSession(AlignerConfig(), SessionConfig(str(state), autosave=False))
    s.resume()
    return s


def test_another_survey_moves_the_state_aside(tmp_path, surveys) -> None:
    a, b = surveys
    state, warns = tmp_path / 'state', []
    s = _session(state, warns)
    _feed(s, a)
    _end(s)
    saved = {p.name: p.read_bytes() for p in tmp_path.iterdir() if p.name != 'state.lock'}
    s = _session(state, warns)
    _feed(s, b)
    got = _end(s)
    folders = list(tmp_path.glob('state.survey-*'))
    assert len(folders) == 1 and s.previous_survey == folders[0]
    moved = {p.name: p.read_bytes() for p in folders[0].iterdir()}
    assert moved == saved                        # every file of survey A, unchanged
    assert s.counts.rejected.get('duplicate', 0) == 0 and s.counts.accepted == len(b)
    ref = _reference(b)
    np.testing.assert_array_equal(got.node_ids, ref.node_ids)
    np.testing.assert_allclose(got.T_world_node, ref.T_world_node, atol=1e-9)
    line = [w for w in warns if w.startswith('a different survey')]
    assert len(line) == 1 and str(folders[0]) in line[0] and 'new survey starts' in line[0]
    # the new survey's own state resumes after a crash, itself
    s = _session(state, [])
    assert s.n_nodes() == len(ref.node_ids) and journal_path(state).exists()
    s.close()


def test_what_belongs_to_a_survey(surveys) -> None:
    """The rules, one by one, against an independent reading of the measurements."""
    a, b = surveys
    al = TrackWindowAligner(AlignerConfig())
    k = len(a) // 2
    al.add_measurements(a[:k])
    assert continues(al, a[0])[0]               # re-delivered from the start
    assert continues(al, a[k])[0]               # the next one
    assert not continues(al, b[0])[0]           # same ids and stamps, another motion
    m = a[k]
    later = type(m)(10**6, 10**6 + 1, m.dst_track + 5, m.dst_track + 5, m.z, m.cov,
                    m.stamp_ns + 10**12)
    earlier = type(m)(10**6, 10**6 + 1, 0, 0, m.z, m.cov, a[0].stamp_ns - 1)
    assert continues(al, later)[0]              # goes on after a gap
    assert not continues(al, earlier)[0]        # older, unknown nodes: another survey
    h = a[3]                                    # a held connection, its motion decides
    assert continues(al, type(h)(h.src_id, h.dst_id, h.src_track, h.dst_track, h.z, h.cov,
                                 h.stamp_ns + 1))[0]
    assert not continues(al, type(h)(h.src_id, h.dst_id, h.src_track, h.dst_track,
                                     h.z + 1e-6, h.cov, h.stamp_ns))[0]
    # another source's measurement of the newest motion (a second odometry): the same survey;
    # of an older motion, another survey (as above)
    n = next(x for x in reversed(a[:k]) if x.dst_id == al.newest_node_id)
    assert continues(al, type(n)(n.src_id, n.dst_id, n.src_track, n.dst_track, n.z + 1e-3,
                                 n.cov, n.stamp_ns, n.kind, 'odom1'))[0]
    assert not continues(al, type(n)(n.src_id, n.dst_id, n.src_track, n.dst_track, n.z + 1e-3,
                                     n.cov, n.stamp_ns + 1, n.kind, 'odom1'))[0]
    # a new connection to a held node from an unknown one: the node's stamp decides
    assert continues(al, type(h)(10**6, h.dst_id, 9, h.dst_track, h.z, h.cov, h.stamp_ns))[0]
    assert not continues(al, type(h)(10**6, h.dst_id, 9, h.dst_track, h.z, h.cov,
                                     h.stamp_ns + 1))[0]
