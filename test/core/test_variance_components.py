"""Variance components per source (:mod:`ga_ros.core.quality.variance_components`).

The group redundancies are checked against a dense textbook computation (``R = I - A Q_x A' P``
on a tiny linear network); the estimated factors against the true noise of simulated sources
(:mod:`ga_ros.sim.sources`) over a Monte-Carlo; the fused trajectory against each source alone.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.linalg as sla

from ga_ros.core.measurement import Measurement, variance_group
from ga_ros.core.quality.control import quality_control
from ga_ros.core.quality.variance_components import (
    SourceGroups,
    VarianceComponent,
    VarianceComponentConfig,
    VarianceComponents,
    group_redundancy,
    solve_with_variance_components,
)
from ga_ros.core.solver import GaussianPrior, SolverConfig, solve
from ga_ros.errors import InputError
from ga_ros.sim.sources import (
    SourceSpec,
    chained_poses,
    multi_source_survey,
    sources_network,
)


def _rmse(T: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Position RMSE (m) and RMS translation error of the consecutive motions (m): the
    latter sums every interval's error, far less noisy than one random walk's position."""
    ate = float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))
    est = np.linalg.inv(T[:-1]) @ T[1:]
    true = np.linalg.inv(T_true[:-1]) @ T_true[1:]
    step = float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - true[:, :3, 3]) ** 2, axis=1))))
    return ate, step


# ------------------------------------------------------------------ the redundancy, by hand
def test_group_redundancy_matches_a_dense_computation() -> None:
    """Linear positions model (``p_j - p_i = t``): the group sums of ``diag(I - A Q_x A' P)``
    and of ``v' P v``, for two connection groups and a group of two position priors, computed
    with dense numpy, equal those of the sparse machinery; they add up to ``r - u``."""
    rng = np.random.default_rng(3)
    n = 6
    p_true = rng.normal(0, 5, (n, 3))
    pairs = [(0, 1), (1, 2), (2, 3), (3, 4), (4, 5), (0, 2), (1, 3), (2, 4), (0, 5), (1, 4)]
    group = [0, 0, 0, 0, 0, 1, 1, 1, 1, 1]
    ms = []
    for i, j in pairs:
        S = np.diag(rng.uniform(0.05, 0.3, 3) ** 2)
        cov = sla.block_diag(S, np.eye(3) * 1e-4)
        t = p_true[j] - p_true[i] + rng.multivariate_normal(np.zeros(3), S)
        ms.append(Measurement(i, j, 0, 0, np.r_[t, 0, 0, 0], cov))
    net = sources_network(n, ms)
    prior_nodes = [(3, np.diag([0.2, 0.3, 0.4]) ** 2), (5, np.diag([0.5, 0.1, 0.3]) ** 2)]
    priors = []
    for k, C in prior_nodes:
        T_mean = np.eye(4)
        T_mean[:3, 3] = p_true[k] + rng.multivariate_normal(np.zeros(3), C)
        priors.append(GaussianPrior(np.array([k]), T_mean[None], np.linalg.inv(C)))
    T0 = np.tile(np.eye(4), (n, 1, 1))
    T0[:, :3, 3] = p_true + rng.normal(0, 0.5, (n, 3))
    res = solve(net, T0, SolverConfig(model='linear'), fixed=[0], priors=priors)
    cost, red = group_redundancy(net, res, priors, np.array(group), np.array([2, 2]), 3)

    # dense: observations [connections' t; priors' p], unknowns p_1..p_5 (p_0 fixed)
    u = n - 1
    rows, l, P_blocks, gid = [], [], [], []
    for m, (i, j), g in zip(ms, pairs, group):
        A = np.zeros((3, 3 * u))
        if i > 0:
            A[:, 3 * (i - 1):3 * i] = -np.eye(3)
        A[:, 3 * (j - 1):3 * j] = np.eye(3)
        rows.append(A)
        l.append(m.z[:3] + (res.T_world_node[0, :3, 3] if i == 0 else 0.0))  # p_0 fixed
        P_blocks.append(np.linalg.inv(m.cov[:3, :3]))
        gid += [g] * 3
    for (k, C), p in zip(prior_nodes, priors):
        A = np.zeros((3, 3 * u))
        A[:, 3 * (k - 1):3 * k] = np.eye(3)
        rows.append(A)
        l.append(p.T_world_node[0, :3, 3])
        P_blocks.append(np.linalg.inv(C))
        gid += [2] * 3
    A = np.vstack(rows)
    lv = np.concatenate(l)
    P = sla.block_diag(*P_blocks)
    N = A.T @ P @ A
    Qx = np.linalg.inv(N)
    x = Qx @ A.T @ P @ lv
    v = A @ x - lv
    R = np.eye(A.shape[0]) - A @ Qx @ A.T @ P
    gid = np.array(gid)
    red_dense = np.array([np.trace(R[np.ix_(gid == g, gid == g)]) for g in range(3)])
    cost_dense = np.array([v[gid == g] @ (P[np.ix_(gid == g, gid == g)] @ v[gid == g])
                           for g in range(3)])
    np.testing.assert_allclose(x.reshape(u, 3), res.T_world_node[1:, :3, 3], atol=1e-8)
    np.testing.assert_allclose(red, red_dense, rtol=1e-8, atol=1e-9)
    np.testing.assert_allclose(cost, cost_dense, rtol=1e-6, atol=1e-10)
    q = quality_control(net, res, priors)
    assert red.sum() == pytest.approx(q.redundancy, rel=1e-8)


def test_at_convergence_every_group_agrees_with_its_residuals() -> None:
    """The fixed point of the estimate: ``v_k' P_k v_k / r_k`` is 1 for every group under the
    estimated weights, and the redundancies still sum to ``r - u``."""
    srcs = (SourceSpec('a', 2.0), SourceSpec('b', 4.0), SourceSpec('c', 3.0))
    sv = multi_source_survey(np.random.default_rng(0), srcs, n_nodes=120)
    ms = list(sv.measurements)
    net = sources_network(120, ms)
    groups = [variance_group(m) for m in ms]
    cfg = VarianceComponentConfig(tolerance=1e-3, max_iterations=60)
    res, vc = solve_with_variance_components(net, chained_poses(120, ms), groups, fixed=[0],
                                             config=cfg)
    assert vc.converged
    scale = np.array([vc.factor(g) for g in groups])
    from ga_ros.core.quality.variance_components import scaled_network

    scaled = scaled_network(net, scale)
    idx = np.array([['a', 'b', 'c'].index(g) for g in groups])
    cost, red = group_redundancy(scaled, res, [], idx, np.zeros(0, np.int64), 3)
    np.testing.assert_allclose(cost / red, 1.0, atol=2e-3)
    assert red.sum() == pytest.approx(res.redundancy, rel=1e-6)
    assert [c.redundancy for c in vc.components] == pytest.approx(red.tolist(), rel=1e-6)


# ------------------------------------------------------------------ simulated sources
THREE = (SourceSpec('odom0', 2.0), SourceSpec('odom1', 4.0), SourceSpec('odom2', 3.0))


@pytest.fixture(scope='module')
def three_source_runs() -> list[dict]:
    """Six simulated surveys of 200 keyframes, three sources of 2 / 4 / 3 % true noise, all
    stated as 5 % (the inputs' default): each alone, fused as today, fused with VCE."""
    runs = []
    n = 200
    for seed in range(6):
        sv = multi_source_survey(np.random.default_rng(100 + seed), THREE, n_nodes=n)
        ms = list(sv.measurements)
        T0 = chained_poses(n, ms)
        out = {'alone': {}}
        for s in THREE:
            mine = sv.of(s.name)
            out['alone'][s.name] = _rmse(solve(sources_network(n, mine), chained_poses(n, mine),
                                               fixed=[0]).T_world_node, sv.T_true)
        net = sources_network(n, ms)
        out['fused'] = _rmse(solve(net, T0, fixed=[0]).T_world_node, sv.T_true)
        res, vc = solve_with_variance_components(net, T0, [variance_group(m) for m in ms],
                                                 fixed=[0])
        out['vce'] = _rmse(res.T_world_node, sv.T_true)
        out['vc'] = vc
        runs.append(out)
    return runs


def test_factors_of_three_sources_match_their_true_noise(three_source_runs) -> None:
    """Over the Monte-Carlo the mean estimated factor of every source is within 10 % of the
    true ``(true sigma / stated sigma)^2`` (0.16, 0.64, 0.36); every estimate converged."""
    for run in three_source_runs:
        assert run['vc'].converged
    for s in THREE:
        est = np.array([run['vc'].factor(s.name) for run in three_source_runs])
        assert est.mean() == pytest.approx(s.true_factor, rel=0.10), (s.name, est)


def test_fusion_with_factors_beats_every_source_alone(three_source_runs) -> None:
    """Independent errors: fused with the estimated factors, the consecutive motions are
    better than the best source's alone and than the fusion with the stated (equal) weights in
    every run; the position RMSE (one random walk per run: noisy) is below the best source's
    alone on average."""
    runs = three_source_runs
    best_step = np.array([min(a[1] for a in r['alone'].values()) for r in runs])
    vce_step = np.array([r['vce'][1] for r in runs])
    fused_step = np.array([r['fused'][1] for r in runs])
    assert (vce_step < best_step).all(), (vce_step, best_step)
    assert (vce_step < fused_step).all(), (vce_step, fused_step)
    best_ate = np.array([min(a[0] for a in r['alone'].values()) for r in runs])
    assert np.mean([r['vce'][0] for r in runs]) < best_ate.mean()


def test_two_sources_alone_cannot_be_told_apart() -> None:
    """Two sources measuring the same motions and nothing else: only the sum of their
    variances is observable (their difference), so both get the same factor, their mean, and
    the fused solution is the one with the stated weights. A third source separates them."""
    two = (SourceSpec('odom0', 1.0), SourceSpec('odom1', 4.0))
    sv = multi_source_survey(np.random.default_rng(7), two, n_nodes=150)
    ms = list(sv.measurements)
    net = sources_network(150, ms)
    T0 = chained_poses(150, ms)
    res, vc = solve_with_variance_components(net, T0, [variance_group(m) for m in ms],
                                             fixed=[0])
    f0, f1 = vc.factor('odom0'), vc.factor('odom1')
    assert f0 == pytest.approx(f1, rel=1e-6)
    assert f0 == pytest.approx(np.mean([s.true_factor for s in two]), rel=0.15)
    plain = solve(net, T0, fixed=[0])
    np.testing.assert_allclose(res.T_world_node, plain.T_world_node, atol=1e-6)


def test_a_poorly_determined_group_keeps_its_stated_covariance() -> None:
    """A loop-closure source with a handful of connections (redundancy below
    ``min_redundancy``) is not estimated: factor 1, flagged, and named in no warning."""
    one = (SourceSpec('odom0', 1.0),)
    loops = SourceSpec('loops', 2.0, 1.0)   # stated 2x too small in sigma
    sv = multi_source_survey(np.random.default_rng(1), one, n_nodes=100, loop=loops,
                             loop_every=40, loop_span=20)
    ms = list(sv.measurements)
    groups = [variance_group(m) for m in ms]
    assert set(groups) == {'odom0', 'loops.cross'}   # a named source's cross-track group
    _, vc = solve_with_variance_components(sources_network(100, ms), chained_poses(100, ms),
                                           groups, fixed=[0])
    loop = next(c for c in vc.components if c.group == 'loops.cross')
    assert loop.redundancy < VarianceComponentConfig().min_redundancy
    assert not loop.estimated and loop.factor == 1.0
    assert not any('loops' in w for w in vc.warnings())


def test_warning_says_by_how_much_in_variance_and_in_sigma() -> None:
    """Factor 16 (variance): the covariance is 16x too small, the sigmas 4x; a factor of 1/4:
    4x too large (sigmas 2x); a factor close to 1 or within its uncertainty: no warning."""
    cfg = VarianceComponentConfig()
    vc = VarianceComponents((
        VarianceComponent('odom1', 16.0, 500.0, 16.0 * np.sqrt(2 / 500), 300, True),
        VarianceComponent('fix0', 0.25, 200.0, 0.25 * np.sqrt(2 / 200), 100, True),
        VarianceComponent('odom0', 1.3, 500.0, 1.3 * np.sqrt(2 / 500), 300, True),
        VarianceComponent('cross', 3.0, 12.0, 3.0 * np.sqrt(2 / 12), 4, True)), 5, True, cfg)
    w = vc.warnings()
    assert len(w) == 2
    assert w[0].startswith("odom1's stated covariance is 16x too small (its sigmas 4x")
    assert w[1].startswith("fix0's stated covariance is 4x too large (its sigmas 2x")
    d = vc.as_dict()
    assert d['odom1']['factor'] == 16.0 and d['odom1']['dof'] == 500.0
    assert d['_estimation'] == {'iterations': 5, 'converged': True}


def test_source_groups_find_a_connection_by_its_identity() -> None:
    z = np.array([1.0, 0.1, 0, 0, 0, 0.02])
    a = Measurement(0, 1, 0, 0, z, np.eye(6), source='odom0')
    b = Measurement(0, 1, 0, 0, z + 1e-9, np.eye(6), source='odom1')
    c = Measurement(3, 9, 0, 1, z, np.eye(6), kind='cross')
    g = SourceGroups()
    for m in (a, b, c):
        g.add(m)
    assert g.of([0, 0, 3, 5], [1, 1, 9, 6], np.vstack([z, z + 1e-9, z, z])) == [
        'odom0', 'odom1', 'cross', 'motion']
    assert variance_group(Measurement(0, 1, 0, 0, z, np.eye(6))) == 'motion'
    assert variance_group(Measurement(0, 1, 0, 0, z, np.eye(6), kind='bridge')) == 'bridge'


def test_bad_groups_are_refused() -> None:
    sv = multi_source_survey(np.random.default_rng(0), (SourceSpec('a', 1.0),), n_nodes=5)
    ms = list(sv.measurements)
    with pytest.raises(InputError, match='group names'):
        solve_with_variance_components(sources_network(5, ms), chained_poses(5, ms), ['a'],
                                       fixed=[0])
    with pytest.raises(InputError, match='max_iterations'):
        VarianceComponentConfig(max_iterations=0)


def test_honest_covariances_leave_the_solution_bit_for_bit() -> None:
    """Stated covariances that are right (true = stated noise): no factor differs
    significantly from 1, none is applied and the solution is the plain adjustment's, bit for
    bit; the factors are still reported, each within 3 of its sigmas of 1."""
    honest = (SourceSpec('odom0', 5.0), SourceSpec('odom1', 5.0))
    sv = multi_source_survey(np.random.default_rng(5), honest, n_nodes=150,
                             loop=SourceSpec('loops', 3.0, 3.0), loop_every=5, loop_span=20)
    ms = list(sv.measurements)
    net, T0 = sources_network(150, ms), chained_poses(150, ms)
    res, vc = solve_with_variance_components(net, T0, [variance_group(m) for m in ms],
                                             fixed=[0])
    assert all(c.estimated and not c.applied for c in vc.components), vc.components
    assert all(abs(c.factor - 1) <= 3 * c.sigma for c in vc.components)
    plain = solve(net, T0, fixed=[0])
    np.testing.assert_array_equal(res.T_world_node, plain.T_world_node)
    assert vc.warnings() == []


def test_fix_source_factor_from_its_priors() -> None:
    """Absolute fixes (one weighted parameter per fixed node, group ``fix0``) that state half
    their true sigma (factor 4) beside honest odometry: the fixes' factor comes out within 3 of
    its sigmas of 4 and above 2 (named in a warning), the odometry's within 3 sigmas of 1."""
    from ga_ros.geometry import se3

    rng = np.random.default_rng(4)
    n = 200
    sv = multi_source_survey(rng, (SourceSpec('odom0', 3.0, 3.0),), n_nodes=n)
    ms = list(sv.measurements)
    true_sigma = np.array([0.5, 0.5, 0.5, 0.02, 0.02, 0.02])
    info = np.diag(1.0 / (true_sigma / 2) ** 2)   # stated: half the true sigma
    priors = []
    for k in range(2, n, 2):
        xi = rng.normal(0, true_sigma)
        priors.append(GaussianPrior(np.array([k]), (sv.T_true[k] @ se3.exp(xi[None]))[0][None],
                                    info))
    net = sources_network(n, ms)
    _, vc = solve_with_variance_components(net, chained_poses(n, ms), ['odom0'] * len(ms),
                                           priors=priors, prior_groups=['fix0'] * len(priors))
    fix = next(c for c in vc.components if c.group == 'fix0')
    odom = next(c for c in vc.components if c.group == 'odom0')
    assert vc.converged
    assert abs(fix.factor - 4.0) < 3 * fix.sigma and fix.factor > 2, fix
    assert abs(odom.factor - 1.0) < 3 * odom.sigma, odom
    assert any(w.startswith("fix0's stated covariance is") for w in vc.warnings())
