"""The per-track window update: the paper's sequential update, its gate and its input checks,
each against an independent computation."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.stats import chi2
from solver_problems import noisy_aerial_survey

from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import SolverConfig, sequential_update
from ga_ros.core.window import ALIGNER_SOLVER, AlignerConfig, TrackWindowAligner
from ga_ros.core.window.admission import check_covariance, covariance_within_limits
from ga_ros.core.window.gate import readmissible
from ga_ros.core.window.persistence import load_state, save_state
from ga_ros.geometry import se3


def _updates(al, ms):
    """Feed ``ms``; yield after each track end (the open track finished last)."""
    for m in ms + [None]:
        ups = al.add_measurement(m) if m is not None else [al.finish_track()]
        if ups:
            yield ups


def test_each_update_equals_the_papers_sequential_update_in_the_linear_limit():
    """At tiny noise the adjustment is linear: the aligner's update of track k (a
    Gauss-Newton solve of the window warm-started from the previous estimate) equals the
    paper's sequential update (Sec. III-D) computed by ``sequential_update``: the previous
    solution's estimate and normal matrix as group 1, only the connections that came with
    track k as group 2."""
    sc, nm, ms = noisy_aerial_survey(4, 10, 0.001, 7)
    tight = replace(ALIGNER_SOLVER, tolerance=1e-12, cost_tolerance=0.0, max_iterations=30)
    al = TrackWindowAligner(AlignerConfig(window_tracks=10, solver=tight, refine_every_tracks=0),
                            sc.T_world_node[0])
    previous, seen, checked = None, 0, 0
    for _ in _updates(al, ms):
        res = al.last_adjustment
        # the measurement that ended the track (first of the next) is applied after the update
        n_conn = al.state.src.n - (1 if al.open_track is not None else 0)
        if previous is not None:
            # group 2: every node of the window, the connections that arrived since
            ids = res.node_ids
            index = {int(i): k for k, i in enumerate(ids)}
            src, dst, z, _, _ = al.connection_arrays()
            new = np.arange(seen, n_conn)
            new = new[np.isin(src[new], ids) & np.isin(dst[new], ids)]
            group2 = ConnectionNetwork.from_arrays(
                ids, sc.track_ids[np.searchsorted(sc.node_ids, ids)],
                np.array([index[int(i)] for i in src[new]]),
                np.array([index[int(i)] for i in dst[new]]), z[new],
                al.connection_covariances()[new])
            T0 = np.empty((ids.size, 4, 4))
            old = np.isin(ids, previous.node_ids)
            T0[old] = previous.T_world_node[np.searchsorted(previous.node_ids, ids[old])]
            # new track: chained from the previous estimate, as the aligner starts it
            T0[~old] = sc.f2f(nm.z)[np.searchsorted(sc.node_ids, ids[~old])]
            move = T0[np.nonzero(old)[0][-1]] @ se3.inverse(
                sc.f2f(nm.z)[np.searchsorted(sc.node_ids, ids[old][-1])])
            T0[~old] = move @ T0[~old]
            seq = sequential_update(previous, group2, T0, SolverConfig(tolerance=1e-12,
                                                                       max_iterations=30))
            # (the gap is second order in the noise: 2e-8 m at 0.01 %, 2e-10 m at 0.001 %)
            np.testing.assert_allclose(res.T_world_node[:, :3, 3], seq.T_world_node[:, :3, 3],
                                       rtol=0, atol=1e-9)
            np.testing.assert_allclose(res.T_world_node[:, :3, :3],
                                       seq.T_world_node[:, :3, :3], rtol=0, atol=1e-11)
            checked += 1
        previous, seen = res, n_conn
    assert checked == 3


def test_an_update_runs_one_solve_when_the_gate_excludes_nothing(monkeypatch):
    """Clean data: each track end is one window solve (no second solve for the gate), of at
    most a few Gauss-Newton iterations started from the previous estimate."""
    import ga_ros.core.window.update as window

    sc, nm, ms = noisy_aerial_survey(5, 10, 3.0, 2)
    calls = []
    real = window.solve

    def counted(*args, **kwargs):
        res = real(*args, **kwargs)
        calls.append(res.iterations)
        return res

    monkeypatch.setattr(window, 'solve', counted)
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, refine_every_tracks=0),
                            sc.T_world_node[0])
    per_update = []
    for _ in _updates(al, ms):
        per_update.append(list(calls))
        calls.clear()
    assert al.stats.n_outliers == 0
    assert [len(c) for c in per_update] == [1] * 5, per_update
    assert max(c[0] for c in per_update) <= ALIGNER_SOLVER.max_iterations


def test_readmission_test_equals_the_per_connection_computation():
    """The vectorised re-admission test gives the decision of the per-connection formula
    (misclosure ``e`` against ``S + J Q J'``, ``Q`` the joint covariance of the two poses from
    the adjustment), computed here one connection at a time."""
    sc, nm, ms = noisy_aerial_survey(3, 10, 2.0, 4)
    al = TrackWindowAligner(AlignerConfig(window_tracks=3, refine_every_tracks=0),
                            sc.T_world_node[0])
    for _ in _updates(al, ms):
        pass
    window = al.stats.tracks_in_window
    net, nodes, _, conns, _, _ = al.updater.window_problem(window)
    res = al.last_adjustment
    cross = conns[al.state.cross.a[conns]]
    rng = np.random.default_rng(0)
    pick = rng.choice(cross, size=40, replace=False)
    # half of them get a misclosure near the test's threshold, so both decisions occur
    z_saved = al.state.z.a[pick].copy()
    al.state.z.a[pick, :3] += rng.normal(size=(40, 3)) * 10 ** rng.uniform(-3, 1, size=(40, 1))
    al.state.status.a[pick] = 2
    got = set(readmissible(al.state, al.config, window, nodes, res, set()).tolist())
    local = {int(i): k for k, i in enumerate(nodes)}
    free = set(res.free_node_ids.tolist())
    want = set()
    for c in pick.tolist():
        i, j = local[int(al.state.src.a[c])], local[int(al.state.dst.a[c])]
        T_ij = se3.inverse(res.T_world_node[i]) @ res.T_world_node[j]
        z = al.state.z.a[c]
        e = se3.log(se3.inverse(se3.from_translation_rotvec(z[:3], z[3:])) @ T_ij)
        J = np.concatenate([-se3.adjoint(se3.inverse(T_ij)), np.eye(6)], axis=1)
        pair = [int(res.node_ids[i]), int(res.node_ids[j])]
        Q = np.zeros((12, 12))
        sel = [a for a in range(2) if pair[a] in free]
        if sel:
            cols = np.concatenate([np.arange(6 * a, 6 * a + 6) for a in sel])
            Q[np.ix_(cols, cols)] = res.covariance([pair[a] for a in sel])[0] if len(sel) == 1 \
                else res._system.joint_covariance(np.array(pair))
        C = al.state.ccov.a[c] + J @ Q @ J.T
        if e @ np.linalg.solve(C, e) <= chi2.ppf(al.config.outlier_chi2_prob, 6):
            want.add(c)
    al.state.z.a[pick] = z_saved
    assert got == want
    assert 0 < len(want) < 40


@pytest.mark.parametrize('seed', range(3))
def test_covariance_check_shortcut_never_accepts_what_the_exact_checks_reject(seed):
    """The one-Cholesky shortcut of the covariance check against the eigenvalue tests it
    replaces: whatever it accepts passes them (returned symmetrised exactly as they would),
    and ordinary covariances are decided by it. Covariances are drawn with eigenvalues around
    every limit (1e-12 smallest, 1e6 largest, condition 1e12)."""
    cfg = AlignerConfig()
    al = TrackWindowAligner(cfg)
    rng = np.random.default_rng(seed)

    decided = 0
    for _ in range(400):
        Q, _ = np.linalg.qr(rng.normal(size=(6, 6)))
        lo = 10 ** rng.uniform(-14, 2)
        hi = lo * 10 ** rng.uniform(0, 13)
        ev = np.concatenate([[lo, hi], 10 ** rng.uniform(np.log10(lo), np.log10(hi), 4)])
        cov = (Q * ev) @ Q.T
        if rng.random() < 0.2:
            cov[0, 1] += 1e-5 * np.abs(cov).max()  # asymmetric beyond the tolerance
        exact_ev = np.linalg.eigvalsh(0.5 * (cov + cov.T))
        amax = np.abs(cov).max()
        exact_ok = (np.abs(cov - cov.T).max() <= 1e-6 * amax and amax <= cfg.cov_max_eigenvalue
                    and exact_ev[0] > 1e-12 * amax and exact_ev[0] >= cfg.cov_min_eigenvalue
                    and exact_ev[-1] <= cfg.cov_max_condition * exact_ev[0])
        fast = covariance_within_limits(al.config, cov)
        if fast is not None:
            decided += 1
            assert exact_ok, (ev, exact_ev)
            np.testing.assert_array_equal(fast, check_covariance(al.config, cov, 'c'))
        if exact_ok and hi / lo < 1e9 and lo > 1e-11 and hi < 1e5:
            assert fast is not None  # well inside the limits: no eigen-decomposition
    assert decided > 50


def test_restored_aligner_starts_its_next_update_where_the_saved_one_would(tmp_path):
    """The weighted parameters' last estimates are part of the saved state: a restored
    aligner's next update (frozen neighbours in the window) equals the uninterrupted one's."""
    sc, nm, ms = noisy_aerial_survey(5, 10, 3.0, 6)
    cfg = AlignerConfig(window_tracks=2, refine_every_tracks=0)
    ref = TrackWindowAligner(cfg, sc.T_world_node[0])
    al = TrackWindowAligner(cfg, sc.T_world_node[0])
    cut = next(k for k, m in enumerate(ms) if m.src_track == 3) + 5
    for m in ms[:cut]:
        ref.add_measurement(m)
        al.add_measurement(m)
    assert al.state.T_weighted[0].size > 0
    save_state(al, tmp_path / 's.ga')
    back = load_state(tmp_path / 's.ga').aligner
    np.testing.assert_array_equal(back.state.T_weighted[0], al.state.T_weighted[0])
    np.testing.assert_array_equal(back.state.T_weighted[1], al.state.T_weighted[1])
    for m in ms[cut:]:
        ref.add_measurement(m)
        back.add_measurement(m)
    ref.finish_track()
    back.finish_track()
    np.testing.assert_allclose(back.corrected_path().T_world_node,
                               ref.corrected_path().T_world_node, rtol=0, atol=1e-12)


def test_a_handed_over_factor_gives_the_same_solution_and_the_donor_stays_usable():
    """``solve(factor=previous.release_factor())`` (the window's reuse of the last symbolic
    analysis) changes nothing in the result, and the donor still answers its own covariances
    (factored anew) after the factor was refactored for the next problem."""
    from ga_ros.core.solver import solve

    sc, nm, _ = noisy_aerial_survey(3, 10, 3.0, 1)
    net, T0 = sc.network(nm.z, nm.cov), sc.f2f(nm.z)
    cfg = SolverConfig(tolerance=1e-10)
    first = solve(net, T0, cfg)
    cov_first = first.covariance([5, 17])
    T1 = T0 @ se3.exp(np.full((T0.shape[0], 6), 1e-3))  # another start, same pattern
    reused = solve(net, T1, cfg, factor=first.release_factor())
    fresh = solve(net, T1, cfg)
    np.testing.assert_allclose(reused.T_world_node, fresh.T_world_node, rtol=0, atol=1e-12)
    assert reused.factorisations == fresh.factorisations
    np.testing.assert_allclose(reused.covariance([5, 17]), fresh.covariance([5, 17]),
                               rtol=1e-10, atol=0)
    np.testing.assert_allclose(first.covariance([5, 17]), cov_first, rtol=1e-10, atol=0)


def test_freeze_covariances_by_selected_inversion_keep_the_analysis_for_the_next_solve():
    """The leaving nodes' covariances by selected inversion on the last solve's own factor
    equal the dense inverse of its normal matrix; the factor handed on afterwards keeps its
    symbolic analysis, and a solve with it equals a fresh one."""
    from ga_ros.core.linalg import selinv
    from ga_ros.core.solver import solve
    from ga_ros.core.window.freeze import marginal_covariances as _marginal_covariances

    if not selinv.COMPILED:
        pytest.skip('numba is not installed')
    sc, nm, _ = noisy_aerial_survey(3, 10, 3.0, 1)
    net, T0 = sc.network(nm.z, nm.cov), sc.f2f(nm.z)
    cfg = SolverConfig(tolerance=1e-10)
    res = solve(net, T0, cfg)
    ids = res.free_node_ids[:40]
    Sigma = np.linalg.inv(res.normal_matrix.toarray())
    ref = np.stack([Sigma[6 * k:6 * k + 6, 6 * k:6 * k + 6] for k in range(40)])
    got = _marginal_covariances(res, ids)
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-10 * np.abs(ref).max())
    factor = res.release_factor()
    assert factor is not None and factor._symbolic is not None  # the analysis survives
    T1 = T0 @ se3.exp(np.full((T0.shape[0], 6), 1e-3))
    reused = solve(net, T1, cfg, factor=factor)
    fresh = solve(net, T1, cfg)
    np.testing.assert_allclose(reused.T_world_node, fresh.T_world_node, rtol=0, atol=1e-12)


@pytest.mark.parametrize('refine', [0, 1])
def test_window_priors_carry_their_rank_and_no_solve_recounts_it(monkeypatch, refine):
    """The joint priors built by a freeze (and by the refinement) carry the rank of their
    information: equal to the rank the solver determines by itself (full: positive definite
    by construction), so no window update factors a prior's information only to count its
    equations; a linearisation alone (``normal_matrix_at``) never asks for it."""
    from ga_ros.core.solver import priors

    sc, nm, ms = noisy_aerial_survey(6, 10, 3.0, 3)
    counted = []
    real = priors._information_rank

    def rank(*args):
        counted.append(1)
        return real(*args)

    monkeypatch.setattr(priors, '_information_rank', rank)
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, prior_band=3, prior_hubs=2,
                                          refine_every_tracks=refine, refine_executor='inline'),
                            sc.T_world_node[0])
    n_priors = 0
    for ups in _updates(al, ms):
        assert all(not str(u.reason).startswith('failed') for u in ups)
        for prior in al.state.priors:
            assert prior.rank is not None
            dense = prior[2].toarray() if hasattr(prior[2], 'toarray') else prior[2]
            assert prior.rank == np.linalg.matrix_rank(dense, hermitian=True) == dense.shape[0]
        n_priors += len(al.state.priors)
    al.close()
    assert n_priors > 0
    assert counted == []



@pytest.mark.parametrize('policy', ['weighted', 'marginal'])
def test_a_freeze_with_the_windows_connection_terms_equals_one_computing_them(monkeypatch,
                                                                             policy):
    """A freeze reuses the last window's weights and measured motions of the connections it
    absorbs (:func:`~ga_ros.core.window.update.connection_terms`) instead of computing them
    again from the connection table: the prior is bit for bit the one computed without them,
    at every freeze of a survey (both policies)."""
    from ga_ros.core.window import freeze

    sc, nm, ms = noisy_aerial_survey(6, 10, 3.0, 4)
    real = freeze.FreezePolicy.marginalise
    compared = []

    def both(self, state, L, priors, n, nc, band, hubs, terms=None):
        got = real(self, state, L, priors, n, nc, band, hubs, terms)
        ref = real(self, state, L, priors, n, nc, band, hubs, None)
        assert terms is not None
        np.testing.assert_array_equal(got[0], ref[0])
        assert got[1] == ref[1] and (got[2] is None) == (ref[2] is None)
        if ref[2] is not None:
            for a, b in zip(got[2], ref[2]):
                a = a.toarray() if hasattr(a, 'toarray') else a
                b = b.toarray() if hasattr(b, 'toarray') else b
                np.testing.assert_array_equal(a, b)
        compared.append(ref[2] is not None)
        return got

    monkeypatch.setattr(freeze.FreezePolicy, 'marginalise', both)
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, freeze_policy=policy, prior_band=3,
                                          prior_hubs=2, refine_every_tracks=0),
                            sc.T_world_node[0])
    for ups in _updates(al, ms):
        assert all(not str(u.reason).startswith('failed') for u in ups)
    al.close()
    assert len(compared) >= 3 and any(compared)
