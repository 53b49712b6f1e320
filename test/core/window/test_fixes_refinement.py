"""Absolute fixes in the background refinement and in the priors rebuilt after ``refine_batch``.

The survey is a straight line with rotations known to 1e-6 rad, so the se3 adjustment is the
linear positions problem whose weighted least-squares solution is written out with numpy
(``line_survey.wls_positions``), independently of the aligner.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from line_survey import feed, fixes_aligner, gnss_fix, line_survey, wls_positions

from ga_ros.core.window import TrackWindowAligner

SIGMA_T = 0.05  # m, odometry step noise per axis
SIGMA_FIX = 0.3  # m, fix noise per axis


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(25)


def _line_survey(rng, n_tracks: int, per_track: int):
    return line_survey(rng, n_tracks, per_track, SIGMA_T)


def _wls(n: int, z: np.ndarray, fixes: dict[int, np.ndarray]) -> np.ndarray:
    return wls_positions(n, z, SIGMA_T, {k: (p, SIGMA_FIX) for k, p in fixes.items()})


def _aligner(refine_every: int, **kw) -> TrackWindowAligner:
    return fixes_aligner(2, refine_every, refine_relinearize_sigma=0.0, **kw)


def _run(al: TrackWindowAligner, ms, fixes: dict[int, np.ndarray]) -> None:
    """Feed the survey, each fix right after its node's measurement; finish the last track."""
    feed(al, ms, {k: (p, SIGMA_FIX) for k, p in fixes.items()})
    al.finish_track()


def _fixes(rng, p_true: np.ndarray, nodes) -> dict[int, np.ndarray]:
    return {int(k): p_true[k] + rng.normal(0, SIGMA_FIX, 3) for k in nodes}


@pytest.mark.parametrize('horizon', [0, 3])
def test_refinement_with_fixes_gives_the_batch_solution(rng, horizon: int) -> None:
    """With the default policy (a refinement after every track) and fixes, the whole path at
    the end is the batch solution (the frozen tracks refined with their fixes and smoothed),
    without a final refine_batch; with the refinement off the frozen tracks stay where they
    froze."""
    n_tracks, per = 8, 6
    ms, z, p_true = _line_survey(rng, n_tracks, per)
    n = n_tracks * per
    fixes = _fixes(rng, p_true, range(2, n, 4))
    p_ref = _wls(n, z, fixes)
    on = _aligner(1, refine_horizon_tracks=horizon)
    _run(on, ms, fixes)
    assert on.handoff.n_refinements >= n_tracks - 3
    path = on.corrected_path()
    assert path.frozen[:per].all()
    err_on = np.abs(path.T_world_node[:, :3, 3] - p_ref).max()
    off = _aligner(0)
    _run(off, ms, fixes)
    err_off = np.abs(off.corrected_path().T_world_node[:, :3, 3] - p_ref).max()
    if horizon == 0:
        assert err_on < 2e-3
    else:  # retired tracks stay where the last refinement that covered them left them
        assert np.abs(path.T_world_node[-3 * per:, :3, 3] - p_ref[-3 * per:]).max() < 2e-3
    # the test can tell the two apart (and a bounded refinement still gets most of the way)
    assert err_off > (10 if horizon == 0 else 3) * max(err_on, 1e-3)
    # and refine_batch agrees with the refined path
    on.refine_batch()
    np.testing.assert_allclose(on.corrected_path().T_world_node[:, :3, 3], p_ref, atol=2e-3)


def test_online_estimate_with_refinement_no_worse_than_without(rng) -> None:
    """The newest track's estimate after each update, against the truth, with the refinement
    on and off (same data): the refinement does not make the published estimate worse."""
    n_tracks, per = 8, 6
    ms, _, p_true = _line_survey(rng, n_tracks, per)
    fixes = _fixes(rng, p_true, range(2, n_tracks * per, 4))
    errs = {}
    for every in (0, 1):
        al = _aligner(every)
        online = []
        for m in ms:
            if al.add_measurement(m):
                newest = al.corrected_path()
                sel = ~newest.frozen
                online.append(np.linalg.norm(newest.T_world_node[sel, :3, 3]
                                             - p_true[newest.node_ids[sel]], axis=1))
            if m.dst_id in fixes:
                al.add_fix(gnss_fix(m.dst_id, m.stamp_ns, fixes[m.dst_id], SIGMA_FIX))
        errs[every] = float(np.sqrt(np.mean(np.concatenate(online) ** 2)))
    assert errs[1] <= 1.01 * errs[0] + 1e-4


@pytest.mark.parametrize('refine_every', [0, 1])
def test_fixes_keep_pulling_after_refine_batch(rng, refine_every: int) -> None:
    """A run continued after refine_batch: the rebuilt priors keep the frozen nodes' fixes, so
    the continued path is still the batch solution of every fix (the fixes of the first half are
    all shifted by 0.5 m along x: losing them would move the path back)."""
    n_tracks, per = 8, 6
    ms, z, p_true = _line_survey(rng, n_tracks, per)
    n = n_tracks * per
    half = n // 2
    fixes = {k: p + [0.5, 0, 0] for k, p in _fixes(rng, p_true, range(2, half, 3)).items()}
    al = _aligner(refine_every)
    _run(al, ms[:half - 1], fixes)  # to the end of a track
    al.refine_batch()
    assert al.corrected_path().frozen.any()
    _run(al, ms[half - 1:], {})
    p_ref = _wls(n, z, fixes)
    p_hat = al.corrected_path().T_world_node[:, :3, 3]
    assert np.abs(p_hat[-per:] - p_ref[-per:]).max() < 2e-3  # the newest track
    # without the first half's fixes the end of the path is about 0.5 m further back
    p_nofix = _wls(n, z, {})
    assert np.abs(p_ref[-1, 0] - p_nofix[-1, 0]) > 0.3


def test_fixes_added_to_a_leaving_track_after_the_snapshot_are_not_lost(rng) -> None:
    """A fix on a node of a track that freezes before the refinement's hand-off, added after
    its snapshot (refine_lag_tracks = 2), must not be dropped by the installed priors."""
    n_tracks, per = 8, 6
    ms, z, p_true = _line_survey(rng, n_tracks, per)
    n = n_tracks * per
    fixes = _fixes(rng, p_true, range(2, n, 4))
    al = _aligner(1, refine_lag_tracks=2)
    pending = {}
    for m in ms:
        al.add_measurement(m)
        k = m.dst_id
        if k in fixes:
            pending[k] = m.stamp_ns
        # each fix arrives one track late (a slow GNSS pipeline), before its node freezes
        for j, stamp in list(pending.items()):
            if k - j >= per:
                al.add_fix(gnss_fix(j, stamp, fixes[j], SIGMA_FIX))
                del pending[j]
    al.finish_track()
    used = {t.node_id for t in al.state.fixes.terms if t.fix.source == 'gnss'}
    assert len(used) >= len(fixes) - 2
    p_ref = _wls(n, z, {k: p for k, p in fixes.items() if k in used})
    # the window's newest track is the batch solution only if no frozen fix was dropped
    p_hat = al.corrected_path().T_world_node[:, :3, 3]
    assert np.abs(p_hat[-per:] - p_ref[-per:]).max() < 2e-3


def test_freeze_computed_ahead_with_fixes_is_used_and_exact(rng) -> None:
    """The freeze computed ahead in the background stays valid when a fix arrives on another
    track (each fix here ends the track that gets it), and gives the freeze computed at the
    track end exactly; a fix on the leaving track itself invalidates it."""
    n_tracks, per = 8, 6
    ms, _, p_true = _line_survey(rng, n_tracks, per)
    fixes = _fixes(rng, p_true, range(2, n_tracks * per, 4))
    paths, used = [], []
    for ahead in (True, False):
        al = _aligner(1, freeze_ahead=ahead)
        _run(al, ms, fixes)
        paths.append(al.corrected_path().T_world_node)
        used.append(al.ahead.n_ahead[0])
        al.close()
    assert used[0] >= n_tracks - 3 and used[1] == 0
    np.testing.assert_allclose(paths[0], paths[1], atol=1e-9)
    # a fix added to the leaving track after the plan started: the plan is not used
    al = _aligner(0, freeze_ahead=True)
    for m in ms[:3 * per - 1]:
        al.add_measurement(m)
    al.finish_track()  # tracks 0-2 finished, window of 2: track 1 leaves at the next update
    node = per + 1  # a node of track 1
    al.add_fix(gnss_fix(node, ms[node - 1].stamp_ns, p_true[node], SIGMA_FIX))
    before = list(al.ahead.n_ahead)
    for m in ms[3 * per - 1:4 * per - 1]:
        al.add_measurement(m)
    al.finish_track()
    assert al.ahead.n_ahead[1] == before[1] + 1


def _datum_alone(ms, per: int):
    """The survey's measurements with the datum (node 0) alone in track 0 and the other nodes
    in tracks of ``per`` (as a session makes them when a fix on the first keyframe ends a
    track)."""
    def track(i: int) -> int:
        return 0 if i == 0 else (i - 1) // per + 1
    return [replace(m, src_track=track(m.src_id), dst_track=track(m.dst_id)) for m in ms]


def test_datum_alone_in_its_track_freezes_and_the_horizon_stays_bounded(rng) -> None:
    """The first measurement runs from track 0 (the datum alone) to track 1: track 0 ends there
    and freezes like any track. Otherwise its node stays unfrozen: no track retires from the
    refinement's horizon, and each refinement and each update's rollback copy covers the whole
    survey. The work of each refinement (snapshot nodes, connections, fixes and past prior
    nodes it sums and eliminates) and each update's copy stop growing once the horizon is
    full, and the newest tracks are the batch solution of all data."""
    n_tracks, per, horizon = 24, 4, 3
    line = _line_survey(rng, n_tracks, per)
    ms, z, p_true = _datum_alone(line.measurements, per), line.z, line.p_true
    n = n_tracks * per
    fixes = _fixes(rng, p_true, range(0, n, 2))
    al = _aligner(1, refine_horizon_tracks=horizon)
    work, copied = [], []
    for m in ms:
        for _ in al.add_measurement(m):
            snap = al.handoff.snap
            if snap is not None:
                work.append(snap.node_ids.size + snap.src.size + len(snap.fixes)
                            + sum(p.nodes.size for p in snap.past))
            lo, r0 = al.mutable_rows()
            copied.append((al.state.idarr.n - lo) + (al.state.src.n - r0))
        if m.dst_id in fixes:
            al.add_fix(gnss_fix(m.dst_id, m.stamp_ns, fixes[m.dst_id], SIGMA_FIX))
    al.finish_track()
    assert 0 in al.state.finished and al.state.frozen[0]
    assert al.state.retired >= n_tracks - horizon - 2 - 3
    # flat: the last third of the survey costs no more than the middle third (the horizon
    # fills in the first third)
    third = len(work) // 3
    assert max(work[-third:]) <= max(work[third:2 * third]), work
    third = len(copied) // 3
    assert max(copied[-third:]) <= max(copied[third:2 * third]), copied
    assert max(work) < 0.5 * (2 * n + len(fixes))  # far from the whole survey's
    p_ref = _wls(n, z, fixes)
    p_hat = al.corrected_path().T_world_node[:, :3, 3]
    assert np.abs(p_hat[-per:] - p_ref[-per:]).max() < 2e-3


def test_fixes_enter_the_refinement_as_one_prior_with_the_same_normal_equations(rng) -> None:
    """The frozen fixes of a refinement's snapshot become one block-diagonal prior
    (``elimination.gaussian``): the normal matrix and gradient equal those of one prior per fix
    bit for bit, and the datum-free solve of the snapshot is unchanged."""
    import scipy.sparse as sp

    from ga_ros.core.solver import GaussianPrior, normal_matrix_at
    from ga_ros.core.window.elimination import gaussian, normal_terms

    n_tracks, per = 8, 6
    ms, z, p_true = _line_survey(rng, n_tracks, per)
    fixes = _fixes(rng, p_true, range(1, n_tracks * per, 3))
    al = _aligner(0)
    feed(al, ms, {k: (p, SIGMA_FIX) for k, p in fixes.items()})
    snap = al.handoff.snapshot()
    al.close()
    assert len(snap.fixes) > 5
    merged = gaussian(snap, snap.fixes)
    assert len(merged) == 1 and merged[0].node_ids.size == len(snap.fixes)
    each = [GaussianPrior(snap.node_ids[p.nodes], p.T_world_node, p.information)
            for p in snap.fixes]
    conns = np.arange(snap.src.size)
    free, N_merged, u_merged = normal_terms(snap, conns, snap.T_world_node, snap.fixes)
    net = al.state.subnetwork(np.arange(snap.node_ids.size), conns)
    # normal_terms linearises with the compiled kernels: the same path here
    N_each, _, u_each = normal_matrix_at(net, snap.T_world_node, 'se3', [], each, jit=True)
    assert free.size == snap.node_ids.size
    assert (sp.csr_matrix(N_merged) != sp.csr_matrix(N_each)).nnz == 0
    assert np.array_equal(u_merged, u_each)


def test_rebuilt_priors_from_the_smoothing_factor_equal_a_dense_elimination(rng, monkeypatch
                                                                            ) -> None:
    """Tracks of 60 nodes with a fix at each end: the rebuilt prior is on the last frozen node,
    with ~1,400 unknowns eliminated, so it comes from the smoothing's factor of ``N_LL``
    (:func:`~ga_ros.core.window.elimination.priors_from_smoothing`, no second factorisation).
    It equals the track-by-track dense elimination of the same snapshot (an independent
    Schur complement) and the partial factorisation's (:func:`sparse_priors`) to rounding; the
    smoothing is unchanged."""
    import ga_ros.core.window.elimination as elim

    n_tracks, per = 6, 60
    ms, z, p_true = _line_survey(rng, n_tracks, per)
    al = _aligner(0)
    _run(al, ms, _fixes(rng, p_true, range(per - 1, n_tracks * per, per)))
    snap = al.handoff.snapshot()
    T = snap.T_world_node
    taken = []
    orig = elim.priors_from_smoothing
    monkeypatch.setattr(elim, 'priors_from_smoothing',
                        lambda *a: taken.append(orig(*a)) or taken[-1])
    fast, steps = elim.eliminate_absorbed(snap, T)
    assert len(taken) == 1 and taken[0] is not None and len(fast) == 1
    free, N, u = elim.normal_terms(snap, np.nonzero(snap.status == 1)[0], T,
                                   snap.past + snap.frozen_fixes())
    keep = np.isin(free, fast[0].nodes)
    partial = elim.sparse_priors(free, N.tocsr(), u, keep, T, -1, 0)
    monkeypatch.setattr(elim, 'SPARSE_FROM_TRACK_NODES', 10 ** 9)
    dense, dense_steps = elim.eliminate_absorbed(snap, T)
    for other in (dense, partial):
        assert len(other) == 1
        np.testing.assert_array_equal(fast[0].nodes, other[0].nodes)
        Ia, Ib = np.asarray(other[0].information), np.asarray(fast[0].information)
        np.testing.assert_allclose(Ib, Ia, rtol=1e-8, atol=1e-10 * np.abs(Ia).max())
        np.testing.assert_allclose(fast[0].T_world_node, other[0].T_world_node, atol=1e-9)
    S = fast[0].nodes
    dS = 1e-3 * rng.normal(size=(S.size, 6))
    nd, d_dense = elim.smoothed(dense_steps, S, dS)
    nf, d_fast = elim.smoothed(steps, S, dS)
    np.testing.assert_array_equal(nd, nf)
    np.testing.assert_allclose(d_fast, d_dense, rtol=1e-5, atol=1e-6 * np.abs(d_dense).max())
