"""Per-track work that does not grow with the survey (issue 14 item 3: memory and update time
flat at 100,000 poses).

Not timed: the tests check what an update touches and copies, against full copies of the
aligner's tables taken independently before each update.
"""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.state import Rollback
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

#: Window 2, horizon 3: tracks retire from the refinement from track 6 on.
CFG = dict(window_tracks=2, refine_executor='inline', refine_horizon_tracks=3,
           refine_relinearize_sigma=0.0)
N_TRACKS = 10


@pytest.fixture(scope='module')
def survey():
    sc = aerial_scenario(n_tracks=N_TRACKS, positions_per_swath=6)
    nm = perturb(sc.true_motions(), NoiseModel(3.0, sc.depth_m), np.random.default_rng(5))
    return sc, sc.measurements(nm.z, nm.cov)


def _by_track(ms):
    """The measurements in acquisition order, cut where a new track's first node arrives."""
    groups, track = [[]], ms[0].src_track
    for m in ms:
        if m.dst_track != track and m.dst_track > track:
            groups.append([])
            track = m.dst_track
        groups[-1].append(m)
    return groups


def _tables(al: TrackWindowAligner) -> dict[str, np.ndarray]:
    n = al.state.idarr.n
    return {'T': al.state.T[:n].copy(), 'cov21': al.state.cov.packed[:n].copy(),
            'frozen': al.state.frozen[:n].copy(), 'status': al.state.status.a.copy()}


@pytest.mark.parametrize('policy', ('weighted', 'marginal'))
def test_an_update_changes_no_row_before_its_mutable_rows(survey, policy) -> None:
    """Window adjustment, freezes, installed refinements (tracks retiring) and smoothing
    change only rows from :meth:`mutable_rows` on, which is what a failed update puts back;
    and that range (the rollback copy) stays of the window's and horizon's size while the
    survey grows."""
    sc, ms = survey
    al = TrackWindowAligner(AlignerConfig(freeze_policy=policy, **CFG), sc.T_world_node[0])
    copied, starts = [], []
    for group in _by_track(ms):
        if al.open_track is not None:
            before = _tables(al)
            lo, r0 = al.mutable_rows()
            copied.append(Rollback.of(al.state, al.mutable_rows()).nbytes)
            up = al.finish_track()
            assert not up.reason.startswith('failed')
            after = _tables(al)
            for key in ('T', 'cov21', 'frozen'):
                np.testing.assert_array_equal(after[key][:lo], before[key][:lo], err_msg=key)
            np.testing.assert_array_equal(after['status'][:r0], before['status'][:r0])
            starts.append(lo)
        al.add_measurements(group)
    al.close()
    assert al.state.retired >= 3 and starts[-1] > 0       # the bound moved on with the survey
    # what a whole-survey copy would take
    n_full = al.state.idarr.n * (128 + 168 + 1) + al.state.src.n
    steady = copied[CFG['refine_horizon_tracks'] + CFG['window_tracks'] + 1:]
    assert max(steady) < 1.15 * min(steady)          # flat once the horizon is full
    assert max(steady) < 0.6 * n_full


def test_a_failed_update_after_a_refinement_puts_back_the_retired_tracks(survey,
                                                                          monkeypatch) -> None:
    """An update that installs a refinement (tracks retire, the past prior changes) and then
    fails leaves every table, the priors and the refinement's horizon as they were; the survey
    then continues."""
    sc, ms = survey
    groups = _by_track(ms)
    al = TrackWindowAligner(AlignerConfig(**CFG), sc.T_world_node[0])
    for group in groups[:8]:
        al.add_measurements(group)
    assert al.state.retired >= 1
    before, book = _tables(al), (al.state.retired, al.state.past, list(al.state.priors))
    real = TrackWindowAligner._adjust

    def broken(self, *args, **kwargs):
        assert self.state.retired > book[0]  # the refinement was installed: more retired
        raise np.linalg.LinAlgError('Matrix is not positive definite')

    monkeypatch.setattr(TrackWindowAligner, '_adjust', broken)
    up = al.finish_track()
    assert up.reason.startswith('failed')
    after = _tables(al)
    for key in before:
        np.testing.assert_array_equal(after[key], before[key], err_msg=key)
    assert al.state.retired == book[0] and al.state.past is book[1]
    assert [p[0] is q[0] for p, q in zip(al.state.priors, book[2])] == [True] * len(book[2])
    assert '_smoothing' not in al.__dict__
    monkeypatch.setattr(TrackWindowAligner, '_adjust', real)
    for group in groups[8:]:
        al.add_measurements(group)
    assert al.finish_track().converged
    al.close()


def test_subnetwork_locates_ends_like_a_full_index(survey) -> None:
    """The window's network locates connection ends by binary search among its nodes: the
    same local indices as an index array over all nodes."""
    sc, ms = survey
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, refine_every_tracks=0),
                            sc.T_world_node[0])
    al.add_measurements(ms)
    rng = np.random.default_rng(3)
    nodes = rng.permutation(al.state.idarr.n)[:40]
    inside = np.zeros(al.state.idarr.n, bool)
    inside[nodes] = True
    conns = np.flatnonzero(inside[al.state.src.a] & inside[al.state.dst.a])
    assert conns.size > 5
    arrays = al.state.subnetwork(nodes, conns).arrays()
    full = np.full(al.state.idarr.n, -1)
    full[nodes] = np.arange(nodes.size)
    np.testing.assert_array_equal(arrays.src, full[al.state.src.a[conns]])
    np.testing.assert_array_equal(arrays.dst, full[al.state.dst.a[conns]])
