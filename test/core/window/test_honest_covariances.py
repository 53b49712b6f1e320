"""Published covariances consistent with the actual errors; redundancy and gate bookkeeping."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp

from ga_ros.core.measurement import Measurement
from ga_ros.core.solver import GaussianPrior, SolverConfig, solve
from ga_ros.core.window import ALIGNER_SOLVER, AlignerConfig, TrackWindowAligner
from ga_ros.eval import position_nees
from ga_ros.geometry import se3
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb


def _monte_carlo(per_swath: int, runs: int, seed: int, **prior) -> tuple[dict, int]:
    """Mean position NEES per policy over ``runs`` noisy aerial surveys (6 tracks, 3 % noise,
    window 2): ``weighted``, ``marginal``, ``weighted+refine`` (background refinement after
    every track, inline: the same hand-off), ``weighted+horizon`` (the same with a refinement
    horizon of 3 tracks: the older tracks retire into the past prior), ``weighted+default``
    (horizon 3, a refinement only when the drift reaches the default
    ``refine_relinearize_sigma``), ``refined`` (the weighted aligner, then ``refine_batch``) and
    ``batch``; and how many sparse priors the aligners ended with."""
    sc = aerial_scenario(n_tracks=6, positions_per_swath=per_swath)
    rng = np.random.default_rng(seed)
    ids, truth = sc.node_ids[1:], sc.T_world_node[1:]
    nees = {k: [] for k in ('weighted', 'marginal', 'weighted+refine', 'weighted+horizon',
                            'weighted+default', 'refined', 'batch')}
    n_sparse = 0
    for _ in range(runs):
        nm = perturb(sc.true_motions(), NoiseModel(3.0, sc.depth_m), rng)
        ms = sc.measurements(nm.z, nm.cov)
        for policy in ('weighted+default', 'weighted+horizon', 'weighted+refine', 'marginal',
                       'weighted'):
            every = 1 if '+' in policy else 0
            horizon = 3 if policy.endswith(('+horizon', '+default')) else 0
            always = {} if policy.endswith('+default') else {'refine_relinearize_sigma': 0.0}
            cfg = AlignerConfig(window_tracks=2, freeze_policy=policy.split('+')[0],
                                refine_every_tracks=every, refine_executor='inline',
                                refine_horizon_tracks=horizon, **always, **prior)
            al = TrackWindowAligner(cfg, sc.T_world_node[0])
            al.add_measurements(ms)
            al.finish_track()
            if always:
                assert (al.state.retired > 0) == (horizon > 0)
            n_sparse += sum(sp.issparse(info) for _, _, info in al.state.priors)
            nees[policy].append(position_nees(al.corrected_path().T_world_node[1:],
                                               al.covariances(ids), truth))
        al.refine_batch()
        nees['refined'].append(position_nees(al.corrected_path().T_world_node[1:],
                                              al.covariances(ids), truth))
        batch = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z), SolverConfig(tolerance=1e-8))
        nees['batch'].append(position_nees(batch.T_world_node[1:], batch.covariance(ids),
                                            truth))
    return {k: float(np.mean(np.concatenate(v))) for k, v in nees.items()}, n_sparse


def test_position_nees_is_consistent_for_every_policy_batch_and_refinement():
    """Monte-Carlo (6 tracks x 8 nodes, 10 runs, 3 % noise, window of 2 tracks): the mean
    position NEES over all nodes and runs must be 3 +- 30 % and, each connection being counted
    once, equal to the batch one; also with the background refinement installed after every
    track (its relinearised priors count each connection once too), also with a refinement
    horizon shorter than the survey (the retired tracks' terms in one past prior), and with the
    default refinement that runs only when the drift demands it. The per-node
    priors of earlier versions gave 8.1 (weighted) and 8.3 (weighted, then refined) on this
    very survey: shared information was counted again at every update."""
    mean, _ = _monte_carlo(per_swath=4, runs=10, seed=7)
    for v in mean.values():
        assert 2.1 <= v <= 3.9, mean
        assert abs(v / mean['batch'] - 1.0) < 0.05, mean


def test_position_nees_stays_consistent_with_sparse_priors():
    """The same Monte-Carlo on longer swaths (6 tracks x 20 nodes, 8 runs) with block-sparse
    joint priors (``prior_band`` 3, ``prior_hubs`` 3: the boundary of 10 nodes is approximated,
    not kept dense) for every policy, the refining ones included: mean position NEES 3 +- 30 %
    and within 10 % of the batch one. A sparser skeleton is visibly overconfident here
    (marginal: 5.4 with band 1 and 2 hubs, 8.3 with band 1 and no hubs; batch 3.1)."""
    mean, n_sparse = _monte_carlo(per_swath=10, runs=8, seed=8, prior_band=3, prior_hubs=3)
    assert n_sparse >= 24  # every run and policy ends with sparse priors
    for v in mean.values():
        assert 2.1 <= v <= 3.9, mean
        assert abs(v / mean['batch'] - 1.0) < 0.1, mean


def test_refine_batch_publishes_the_batch_covariances():
    sc = aerial_scenario(n_tracks=5, positions_per_swath=5)
    nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(1))
    solver = replace(ALIGNER_SOLVER, tolerance=1e-10, max_iterations=30)
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, solver=solver), sc.T_world_node[0])
    al.add_measurements(sc.measurements(nm.z, nm.cov))
    al.refine_batch()
    batch = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z), SolverConfig(tolerance=1e-10))
    ids = sc.node_ids[1:]
    ref = batch.covariance(ids)
    assert al.corrected_path().frozen.any()
    np.testing.assert_allclose(al.covariances(ids), ref, rtol=1e-5,
                               atol=1e-8 * np.abs(ref).max())


def test_refine_batch_covariances_by_sparse_selected_inversion_equal_dense(monkeypatch):
    """With the selected inversion on the sparse factor forced (it serves surveys of 2,000
    poses and more), the covariances published after ``refine_batch`` are the diagonal blocks
    of the dense inverse of the batch normal matrix; the adjustment's factor, taken over by the
    selected inversion, still serves a joint covariance afterwards."""
    from ga_ros.core.solver import result

    monkeypatch.setattr(result, '_SPARSE_SELINV_UNKNOWNS', 0)
    sc = aerial_scenario(n_tracks=5, positions_per_swath=5)
    nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(1))
    al = TrackWindowAligner(AlignerConfig(window_tracks=2), sc.T_world_node[0])
    al.add_measurements(sc.measurements(nm.z, nm.cov))
    al.refine_batch()
    res = al.last_adjustment
    dense = np.linalg.inv(res.normal_matrix.toarray())
    col = {int(i): k for k, i in enumerate(res.free_node_ids)}
    ids = sc.node_ids[1:]
    ref = np.stack([dense[6 * col[int(i)]:6 * col[int(i)] + 6, 6 * col[int(i)]:6 * col[int(i)] + 6]
                    for i in ids])
    assert al.corrected_path().frozen.sum() >= 20
    np.testing.assert_allclose(al.covariances(ids), ref, rtol=1e-9, atol=1e-12 * np.abs(ref).max())
    a, b = col[int(ids[3])], col[int(ids[17])]
    idx = np.r_[6 * a:6 * a + 6, 6 * b:6 * b + 6]
    np.testing.assert_allclose(res._system.joint_covariance(ids[[3, 17]]),
                               dense[np.ix_(idx, idx)], rtol=1e-9,
                               atol=1e-12 * np.abs(ref).max())


def test_a_zero_weight_prior_adds_no_redundancy():
    """Redundancy = equations - unknowns, a prior's equations being the rank of its
    information: checked against the dense count ``trace(I - H)`` of the whitened hat matrix
    ``H = J (J'J)^-1 J'``, and sigma0^2 must not move when a zero-information prior is added."""
    sc = aerial_scenario(n_tracks=2, positions_per_swath=4)
    nm = perturb(sc.true_motions(), NoiseModel(3.0, sc.depth_m), np.random.default_rng(2))
    net = sc.network(nm.z, nm.cov)
    first = [int(sc.node_ids[0])]
    base = solve(net, sc.f2f(nm.z), SolverConfig(tolerance=1e-10), fixed=first)
    node = sc.node_ids[3:4]
    zero = GaussianPrior(node, base.T_world_node[3:4], np.zeros((6, 6)))
    with_zero = solve(net, sc.f2f(nm.z), SolverConfig(tolerance=1e-10), fixed=first,
                      priors=[zero])
    assert with_zero.n_equations == base.n_equations
    assert with_zero.redundancy == base.redundancy
    assert with_zero.sigma0_sq == pytest.approx(base.sigma0_sq, rel=1e-9)
    # a rank-3 prior (positions only) adds three equations; dense count of the same
    info = sp.csr_matrix(np.diag([4.0, 4.0, 4.0, 0.0, 0.0, 0.0]))
    half = GaussianPrior(node, base.T_world_node[3:4], info)
    res = solve(net, sc.f2f(nm.z), SolverConfig(tolerance=1e-10), fixed=first, priors=[half])
    N = res.normal_matrix.toarray()
    # whitened Jacobian rows: Cholesky factor of N gives J'J = N; the equations are those of the
    # connections (6 each) plus the non-zero rows of the prior's square-root information
    n_rows = 6 * net.n_connections + int(np.count_nonzero(np.linalg.eigvalsh(info.toarray())
                                                          > 1e-12))
    dense_redundancy = n_rows - np.linalg.matrix_rank(N)
    assert res.redundancy == dense_redundancy == base.redundancy + 3


def test_a_good_connection_gated_with_a_gross_one_is_readmitted():
    """A wrong cross-track match 100 m off drags the estimate so far that the gate also excludes
    some twenty good connections of the same update (swamping). Once the wrong one is out, the
    estimate agrees with them again: they are re-admitted and only the wrong one stays out."""
    sc = aerial_scenario(n_tracks=3, positions_per_swath=10)
    nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(3))
    ms = sc.measurements(nm.z, nm.cov)
    k = next(i for i, m in enumerate(ms) if m.kind == 'cross' and m.dst_track == 1)
    m = ms[k]
    wrong = se3.to_translation_rotvec(m.T_src_dst @ se3.from_translation_rotvec(
        np.array([100.0, -60.0, 0.0]), np.array([0.0, 0.0, 0.3])))
    ms[k] = Measurement(m.src_id, m.dst_id, m.src_track, m.dst_track, wrong, m.cov,
                        m.stamp_ns, 'cross')
    al = TrackWindowAligner(AlignerConfig(window_tracks=3), sc.T_world_node[0])
    ups = al.add_measurements(ms).updates + [al.finish_track()]
    assert sum(u.n_readmitted for u in ups) >= 10, [u.n_readmitted for u in ups]
    status = al.connection_arrays()[4]
    assert np.nonzero(status == 2)[0].tolist() == [k]
    assert al.stats.n_outliers == 1
