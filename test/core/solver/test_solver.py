"""The mixed-adjustment solver against independent computations."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
from scipy.optimize import least_squares
from solver_problems import make_problem, noisy_aerial_survey, perturbed, true_poses

from ga_ros.core import models
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import (
    GaussianPrior,
    SolverConfig,
    connection_cost,
    covariance_form_update,
    initial_guess_f2f,
    sequential_update,
    solve,
)
from ga_ros.errors import DegenerateGeometryError, InputError, NetworkError
from ga_ros.geometry import se3, so3

MODELS = ['se3', 'paper', 'linear']


def _node_perturb(model, T, idx, k, eps):
    d = models.dof(model)
    delta = np.zeros((1, d))
    delta[0, k] = eps
    return models.retract(model, T, np.array([idx]), delta)


@pytest.mark.parametrize('model', MODELS)
def test_jacobians_match_central_differences(rng, model):
    prob = make_problem(rng, model, n=6, noise=3.0)
    T = perturbed(rng, prob.T_true, 0.1)
    c = prob.network.arrays()
    v = rng.normal(scale=0.02, size=c.z.shape)
    lin = models.linearise(model, T, c.src, c.dst, c.z, v)
    d = models.dof(model)
    eps = 1e-6
    for k in range(d):
        for which, A in (('src', lin.A_src), ('dst', lin.A_dst)):
            num = np.zeros_like(lin.f)
            for q in range(len(c)):
                node = c.src[q] if which == 'src' else c.dst[q]
                fp = models.linearise(model, _node_perturb(model, T, node, k, eps), c.src[q:q + 1],
                                      c.dst[q:q + 1], c.z[q:q + 1], v[q:q + 1]).f[0]
                fm = models.linearise(model, _node_perturb(model, T, node, k, -eps),
                                      c.src[q:q + 1], c.dst[q:q + 1], c.z[q:q + 1],
                                      v[q:q + 1]).f[0]
                num[q] = (fp - fm) / (2 * eps)
            np.testing.assert_allclose(A[:, :, k], num, atol=1e-6, rtol=1e-6)
    for k in range(6):
        dv = np.zeros_like(v)
        dv[:, k] = eps
        fp = models.linearise(model, T, c.src, c.dst, c.z, v + dv).f
        fm = models.linearise(model, T, c.src, c.dst, c.z, v - dv).f
        np.testing.assert_allclose(lin.B[:, :, k], (fp - fm) / (2 * eps), atol=1e-6, rtol=1e-6)


@pytest.mark.parametrize('model', MODELS)
def test_noise_free_observations_recover_every_position(rng, model):
    prob = make_problem(rng, model, n=15)
    T0 = perturbed(rng, prob.T_true, 0.05)
    res = solve(prob.network, T0, SolverConfig(model=model, tolerance=1e-12, max_iterations=30))
    assert res.converged
    np.testing.assert_allclose(res.T_world_node[:, :3, 3], prob.T_true[:, :3, 3], atol=1e-9)
    assert res.cost < 1e-12
    if model == 'se3':
        np.testing.assert_allclose(res.T_world_node, prob.T_true, atol=1e-9)


def test_linear_model_equals_dense_brute_force(rng):
    prob = make_problem(rng, 'linear', n=10, noise=1.0)
    res = solve(prob.network, initial_guess_f2f(prob.network), SolverConfig(model='linear'))
    # dense weighted least squares over p_1..p_{n-1}, p_0 = the datum
    c = prob.network.arrays()
    n = prob.network.n_nodes
    W = np.linalg.inv(c.cov[:, :3, :3])
    H = np.zeros((3 * n, 3 * n))
    g = np.zeros(3 * n)
    for q in range(len(c)):
        Aq = np.zeros((3, 3 * n))
        Aq[:, 3 * c.dst[q]:3 * c.dst[q] + 3] = np.eye(3)
        Aq[:, 3 * c.src[q]:3 * c.src[q] + 3] = -np.eye(3)
        H += Aq.T @ W[q] @ Aq
        g += Aq.T @ W[q] @ c.z[q, :3]
    p0 = prob.T_true[0, :3, 3]
    Hf, gf = H[3:, 3:], g[3:] - H[3:, :3] @ p0
    p = np.linalg.solve(Hf, gf).reshape(-1, 3)
    np.testing.assert_allclose(res.T_world_node[1:, :3, 3], p, atol=1e-9)
    # the residuals are the adjusted observations' corrections: l = l_b + v satisfies f = 0
    lin = models.linearise('linear', res.T_world_node, c.src, c.dst, c.z, res.residuals)
    np.testing.assert_allclose(lin.f, 0.0, atol=1e-9)
    # covariance of the estimate is the inverse of the dense normal matrix
    np.testing.assert_allclose(res.covariance([3])[0], np.linalg.inv(Hf)[6:9, 6:9], atol=1e-12)


def test_se3_model_equals_generic_least_squares(rng):
    prob = make_problem(rng, 'se3', n=8, noise=1.0)
    net = prob.network
    c = net.arrays()
    res = solve(net, initial_guess_f2f(net), SolverConfig(tolerance=1e-12))
    Lw = np.linalg.cholesky(np.linalg.inv(c.cov))
    T_meas_inv = se3.inverse(se3.from_translation_rotvec(c.z[:, :3], c.z[:, 3:]))
    T0 = initial_guess_f2f(net)

    def fun(x):
        T = T0.copy()
        T[1:] = T0[1:] @ se3.exp(x.reshape(-1, 6))
        e = se3.log(T_meas_inv @ se3.inverse(T[c.src]) @ T[c.dst])
        return np.einsum('mji,mj->mi', Lw, e).ravel()

    sol = least_squares(fun, np.zeros(6 * (net.n_nodes - 1)), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    T_ref = T0.copy()
    T_ref[1:] = T0[1:] @ se3.exp(sol.x.reshape(-1, 6))
    np.testing.assert_allclose(res.T_world_node, T_ref, atol=1e-7)
    np.testing.assert_allclose(res.cost, 2 * sol.cost, rtol=1e-8)
    np.testing.assert_allclose(connection_cost(net, res.T_world_node), res.cost, rtol=1e-8)


def test_paper_model_equals_constrained_least_squares(rng):
    """Eq. 1 solved as min v'Pv with t eliminated through the constraint: an independent
    unconstrained formulation over (positions, rotation residuals)."""
    prob = make_problem(rng, 'paper', n=7, noise=1.0)
    net = prob.network
    c = net.arrays()
    res = solve(net, initial_guess_f2f(net), SolverConfig(model='paper', tolerance=1e-12))
    Lw = np.linalg.cholesky(np.linalg.inv(c.cov))
    n, m = net.n_nodes, len(c)
    p0 = prob.T_true[0, :3, 3]

    def fun(x):
        p = np.vstack([p0, x[:3 * (n - 1)].reshape(-1, 3)])
        vw = x[3 * (n - 1):].reshape(m, 3)
        R = so3.exp(c.z[:, 3:] + vw)
        vt = p[c.dst] - (R @ p[c.src][:, :, None])[:, :, 0] - c.z[:, :3]
        v = np.hstack([vt, vw])
        return np.einsum('mji,mj->mi', Lw, v).ravel()

    x0 = np.concatenate([res.T_world_node[1:, :3, 3].ravel() + 0.01, np.zeros(3 * m)])
    sol = least_squares(fun, x0, xtol=1e-15, ftol=1e-15, gtol=1e-15)
    np.testing.assert_allclose(res.T_world_node[1:, :3, 3], sol.x[:3 * (n - 1)].reshape(-1, 3),
                               atol=1e-7)
    np.testing.assert_allclose(res.cost, 2 * sol.cost, rtol=1e-7)


def _split(prob, n1):
    """Group 1: connections among nodes < n1; group 2: the rest."""
    g1, g2 = ConnectionNetwork(), ConnectionNetwork()
    ids = prob.network.node_ids
    for i in ids:
        if i < n1:
            g1.add_node(int(i))
        g2.add_node(int(i))
    c = prob.network.arrays()
    for q in range(len(c)):
        target = g1 if max(c.src[q], c.dst[q]) < n1 and q % 5 != 0 else g2
        target.add_connection(int(ids[c.src[q]]), int(ids[c.dst[q]]), c.z[q], c.cov[q])
    return g1, g2


@pytest.mark.parametrize('new_unknowns', [False, True])
def test_sequential_update_equals_batch_linear(rng, new_unknowns):
    prob = make_problem(rng, 'linear', n=14, noise=1.0)
    cfg = SolverConfig(model='linear', tolerance=1e-12)
    n1 = 9 if new_unknowns else 14
    g1, g2 = _split(prob, n1)
    r1 = solve(g1, initial_guess_f2f(g1), cfg)
    T_init = initial_guess_f2f(prob.network)
    T_init[:n1] = r1.T_world_node
    r2 = sequential_update(r1, g2, T_init, cfg)
    batch = solve(prob.network, initial_guess_f2f(prob.network), cfg)
    np.testing.assert_allclose(r2.T_world_node[:, :3, 3], batch.T_world_node[:, :3, 3],
                               atol=1e-9)
    ids = np.arange(1, 14)
    np.testing.assert_allclose(r2.covariance(ids), batch.covariance(ids), atol=1e-12)


def _seq_vs_batch_se3(seed, noise, n1):
    rng = np.random.default_rng(seed)
    prob = make_problem(rng, 'se3', n=14, noise=noise)
    cfg = SolverConfig(tolerance=1e-12)
    g1, g2 = _split(prob, n1)
    r1 = solve(g1, initial_guess_f2f(g1), cfg)
    T_init = initial_guess_f2f(prob.network)
    T_init[:n1] = r1.T_world_node
    r2 = sequential_update(r1, g2, T_init, cfg)
    batch = solve(prob.network, initial_guess_f2f(prob.network), cfg)
    ids = np.arange(1, 14)
    C = batch.covariance(ids)
    sd = np.sqrt(np.diagonal(C, axis1=1, axis2=2))
    gap = np.abs(se3.local(batch.T_world_node[1:], r2.T_world_node[1:]) / sd).max()
    cov_gap = np.abs(r2.covariance(ids) - C).max() / np.abs(C).max()
    return gap, cov_gap


@pytest.mark.parametrize('new_unknowns', [False, True])
def test_sequential_update_equals_batch_se3(new_unknowns):
    """Nonlinear: group 1 stays linearised at x1 (its observations are not revisited), so the
    sequential result equals the batch one up to second-order terms: the gap, in units of the
    estimate's standard deviation, is small and shrinks in proportion to the noise."""
    n1 = 9 if new_unknowns else 14
    gaps = [_seq_vs_batch_se3(3, noise, n1) for noise in (1.0, 0.1, 0.01)]
    (g1, c1), (g2, c2), (g3, c3) = gaps
    assert g1 < 0.05, gaps
    assert g2 < 0.2 * g1 and g3 < 0.2 * g2, gaps
    assert c1 < 0.05 and c3 < 1e-3, gaps


@pytest.mark.parametrize('model', ['linear', 'se3'])
def test_covariance_form_agrees_with_information_form(rng, model):
    prob = make_problem(rng, model, n=10, noise=1.0)
    cfg = SolverConfig(model=model, tolerance=1e-12, max_iterations=1, reuse_factor_below=0)
    g1, g2 = _split(prob, 10)
    r1 = solve(g1, initial_guess_f2f(g1), SolverConfig(model=model, tolerance=1e-12))
    T2_cov, Q2 = covariance_form_update(r1, g2, cfg)
    # one information-form step from the same linearisation point
    r2 = sequential_update(r1, g2, r1.T_world_node, cfg)
    np.testing.assert_allclose(T2_cov, r2.T_world_node, atol=1e-9)
    if model == 'linear':  # N at the solution == N of the step for a linear model
        np.testing.assert_allclose(Q2, np.linalg.inv(r2.normal_matrix.toarray()), atol=1e-12)


def test_huge_weight_equals_fixed_and_zero_weight_equals_unknown(rng):
    prob = make_problem(rng, 'se3', n=10, noise=1.0)
    net = prob.network
    T0 = initial_guess_f2f(net)
    fixed = solve(net, T0, SolverConfig(tolerance=1e-12))
    heavy = solve(net, T0, SolverConfig(tolerance=1e-12), fixed=[],
                  priors=[GaussianPrior(np.array([0]), T0[:1], np.eye(6) * 1e14)])
    np.testing.assert_allclose(heavy.T_world_node, fixed.T_world_node, atol=1e-7)
    np.testing.assert_allclose(heavy.covariance([5]), fixed.covariance([5]), rtol=1e-5)
    weak = solve(net, T0, SolverConfig(tolerance=1e-12), fixed=[0],
                 priors=[GaussianPrior(np.array([5]), T0[5:6] @ se3.exp(np.ones(6)),
                                       np.eye(6) * 1e-12)])
    np.testing.assert_allclose(weak.T_world_node, fixed.T_world_node, atol=1e-8)
    # a prior with real weight moves the node towards the prior and shrinks its covariance
    mid = solve(net, T0, SolverConfig(tolerance=1e-12), fixed=[0],
                priors=[GaussianPrior(np.array([5]), prob.T_true[5:6],
                                      sp.csr_matrix(np.linalg.inv(fixed.covariance([5])[0])))])
    assert np.trace(mid.covariance([5])[0]) < np.trace(fixed.covariance([5])[0])


@pytest.mark.slow
def test_monte_carlo_statistical_consistency():
    """Mean variance factor ~ 1 and NEES ~ 6 per node over many noisy realisations."""
    rng = np.random.default_rng(7)
    runs, n = 150, 8
    T_true = true_poses(rng, n)
    s0, nees = [], []
    for _ in range(runs):
        net = ConnectionNetwork()
        for i in range(n):
            net.add_node(i)
        cov = np.diag((0.5 * np.array([0.05, 0.05, 0.05, 0.01, 0.01, 0.01])) ** 2)
        Lc = np.linalg.cholesky(cov)
        for g in (1, 2, 3):
            for i in range(n - g):
                eps = Lc @ rng.normal(size=6)
                z = se3.to_translation_rotvec(se3.relative(T_true[i], T_true[i + g])
                                              @ se3.exp(-eps))
                net.add_connection(i, i + g, z, cov)
        res = solve(net, initial_guess_f2f(net), SolverConfig(tolerance=1e-10))
        s0.append(res.sigma0_sq)
        C = res.covariance(np.arange(1, n))
        e = se3.local(res.T_world_node[1:], T_true[1:])
        nees.extend(np.einsum('ki,kij,kj->k', e, np.linalg.inv(C), e))
    redundancy = res.redundancy
    s0 = np.array(s0)
    se_mean = np.sqrt(2.0 / redundancy / runs)
    assert abs(s0.mean() - 1.0) < 4 * se_mean, (s0.mean(), se_mean)
    nees = np.array(nees)
    assert abs(nees.mean() - 6.0) < 4 * nees.std() / np.sqrt(runs) + 0.1, nees.mean()


def test_initial_guess_is_frame_to_frame_integration(rng):
    prob = make_problem(rng, 'se3', n=9, noise=1.0)
    c = prob.network.arrays()
    chain = [k for k in range(len(c)) if c.dst[k] == c.src[k] + 1]
    motions = se3.from_translation_rotvec(c.z[chain, :3], c.z[chain, 3:])
    np.testing.assert_allclose(initial_guess_f2f(prob.network), se3.integrate(np.eye(4), motions),
                               atol=1e-12)


def test_robust_loss_downweights_a_wrong_connection(rng):
    prob = make_problem(rng, 'se3', n=12, noise=1.0)
    net = prob.network
    wrong = se3.to_translation_rotvec(se3.relative(prob.T_true[2], prob.T_true[9])
                                      @ se3.exp(np.array([3.0, -2.0, 1.0, 0.2, 0, 0])))
    net.add_connection(2, 9, wrong, np.diag([0.05, 0.05, 0.05, 0.01, 0.01, 0.01]) ** 2)
    T0 = initial_guess_f2f(net)
    plain = solve(net, T0, SolverConfig(tolerance=1e-10))
    for loss in ('huber', 'cauchy'):
        robust = solve(net, T0, SolverConfig(tolerance=1e-10, robust_loss=loss,
                                             max_iterations=100))
        err_plain = np.linalg.norm(plain.T_world_node[:, :3, 3] - prob.T_true[:, :3, 3], axis=1)
        err_rob = np.linalg.norm(robust.T_world_node[:, :3, 3] - prob.T_true[:, :3, 3], axis=1)
        assert err_rob.mean() < 0.5 * err_plain.mean(), loss
        assert robust.weights[-1] < 0.2


@pytest.mark.parametrize('damping', ['lm', 'dogleg'])
@pytest.mark.parametrize('seed', [0, 1, 2])
def test_damping_converges_from_a_poor_initial_guess(seed, damping):
    rng = np.random.default_rng(seed)
    prob = make_problem(rng, 'se3', n=12)
    T0 = perturbed(rng, prob.T_true, 0.6)
    res = solve(prob.network, T0, SolverConfig(damping=damping, tolerance=1e-12,
                                               max_iterations=100))
    np.testing.assert_allclose(res.T_world_node, prob.T_true, atol=1e-8)
    assert all(b <= a * (1 + 1e-12) for a, b in zip(res.cost_history[1:], res.cost_history[2:]))
    if damping == 'dogleg':  # refused steps move along the same dogleg path: no refactoring
        assert res.factorisations <= res.iterations


def test_dogleg_from_a_far_start_reaches_the_undamped_optimum():
    """One factorisation per iteration, and the optimum equals the undamped iteration's from
    the true poses."""
    rng = np.random.default_rng(7)
    prob = make_problem(rng, 'se3', n=10, noise=2.0)
    T0 = perturbed(rng, prob.T_true, 0.6)
    res = solve(prob.network, T0, SolverConfig(damping='dogleg', tolerance=1e-10,
                                               max_iterations=200))
    ref = solve(prob.network, prob.T_true, SolverConfig(tolerance=1e-12))
    assert res.converged
    assert res.factorisations <= res.iterations
    np.testing.assert_allclose(res.cost, ref.cost, rtol=1e-9)
    np.testing.assert_allclose(res.T_world_node, ref.T_world_node, atol=1e-6)


# ------------------------------------------------------------------------------ bad input
def _base():
    net = ConnectionNetwork()
    for i in range(3):
        net.add_node(i)
    net.add_connection(0, 1, [1, 0, 0, 0, 0, 0], np.eye(6))
    return net


@pytest.mark.parametrize('cov, msg', [
    (np.diag([1, 1, 1, 1, 1, -1.0]), 'not positive definite'),
    (np.eye(6) + np.triu(np.ones((6, 6)), 1), 'not symmetric'),
    (np.full((6, 6), np.nan), 'NaN'),
    (np.eye(5), '6x6'),
])
def test_bad_covariance_is_rejected_and_changes_nothing(cov, msg):
    net = _base()
    with pytest.raises(InputError, match=msg):
        net.add_connection(1, 2, [1, 0, 0, 0, 0, 0], cov)
    assert net.n_connections == 1


@pytest.mark.parametrize('src, dst, z, err, msg', [
    (1, 1, [1, 0, 0, 0, 0, 0], NetworkError, 'itself'),
    (1, 7, [1, 0, 0, 0, 0, 0], NetworkError, 'unknown node'),
    (1, 2, [np.inf, 0, 0, 0, 0, 0], InputError, 'NaN or inf'),
    (1, 2, [1, 0, 0], InputError, '6 entries'),
])
def test_bad_connection_is_rejected(src, dst, z, err, msg):
    net = _base()
    with pytest.raises(err, match=msg):
        net.add_connection(src, dst, z, np.eye(6))
    assert net.n_connections == 1


def test_batch_add_is_all_or_nothing():
    net = _base()
    covs = np.stack([np.eye(6), np.diag([1, 1, 1, 1, 1, 0.0])])
    with pytest.raises(InputError, match='#1'):
        net.add_connections([1, 0], [2, 2], np.zeros((2, 6)), covs)
    assert net.n_connections == 1


def test_duplicate_policies():
    keep = _base()
    keep.add_connection(0, 1, [1.1, 0, 0, 0, 0, 0], np.eye(6))
    assert keep.n_connections == 2
    with pytest.raises(NetworkError, match='identical'):
        keep.add_connection(0, 1, [1.1, 0, 0, 0, 0, 0], np.eye(6))
    rej = ConnectionNetwork(duplicates='reject')
    rej.add_node(0)
    rej.add_node(1)
    rej.add_connection(0, 1, [1, 0, 0, 0, 0, 0], np.eye(6))
    with pytest.raises(NetworkError, match='already connected'):
        rej.add_connection(1, 0, [-1, 0, 0, 0, 0, 0], np.eye(6))
    rep = ConnectionNetwork(duplicates='replace')
    rep.add_node(0)
    rep.add_node(1)
    rep.add_connection(0, 1, [1, 0, 0, 0, 0, 0], np.eye(6))
    rep.add_connection(0, 1, [2, 0, 0, 0, 0, 0], np.eye(6))
    assert rep.n_connections == 1 and rep.arrays().z[0, 0] == 2


def test_disconnected_nodes_are_named():
    net = _base()
    net.add_node(5)
    net.add_connection(2, 5, [1, 0, 0, 0, 0, 0], np.eye(6))
    with pytest.raises(NetworkError, match='2, 5'):
        solve(net, np.broadcast_to(np.eye(4), (4, 4, 4)).copy())


def test_missing_datum_is_singular():
    net = _base()
    net.add_connection(1, 2, [1, 0, 0, 0, 0, 0], np.eye(6))
    with pytest.raises(DegenerateGeometryError):
        solve(net, initial_guess_f2f(net), fixed=[])
    # a prior too weak in some direction is also caught (rank-deficient information)
    with pytest.raises(DegenerateGeometryError):
        solve(net, initial_guess_f2f(net), fixed=[],
              priors=[GaussianPrior(np.array([0]), np.eye(4)[None], np.diag([1.0] * 5 + [0]))])


def test_bad_initial_guess_shape_and_values():
    net = _base()
    net.add_connection(1, 2, [1, 0, 0, 0, 0, 0], np.eye(6))
    with pytest.raises(InputError, match='shape'):
        solve(net, np.zeros((2, 4, 4)))
    bad = initial_guess_f2f(net)
    bad[1, 0, 0] = np.nan
    with pytest.raises(InputError, match='NaN'):
        solve(net, bad)


@pytest.mark.parametrize('damping', ['none', 'lm', 'dogleg'])
def test_reaches_the_reference_optimum_of_smallgrid3d(pose_graph_dir, damping):
    """From the file's own (poor) initial guess: the residuals pass through rotations beyond pi,
    where the adjusted observations must stay on the principal branch of the log."""
    from ga_ros.io.g2o import graph_cost, read_g2o
    g = read_g2o(pose_graph_dir / 'smallGrid3D.g2o')
    res = solve(g.network, g.T_init, SolverConfig(damping=damping, max_iterations=60,
                                                  tolerance=1e-9))
    assert res.converged
    if damping == 'dogleg':  # one factorisation per iteration, refused steps included
        assert res.factorisations == res.iterations
    cost = graph_cost(g, res.T_world_node)
    assert abs(cost - 1035.851) / 1035.851 < 1e-4
    assert abs(res.cost - cost) / cost < 1e-9


def test_se3_shortcut_system_equals_the_general_gauss_helmert_system(rng):
    """At residuals consistent with x, the se3 shortcut (J' P J, J' P e) and the general
    mixed-model form (A' M^-1 A, A' M^-1 w with M = B S B') are the same linear system."""
    from ga_ros.core.solver.linearise import (
        _consistent_residuals,
        _inv_spd,
        _linear_system,
        _Terms,
    )
    prob = make_problem(rng, 'se3', n=9, noise=5.0)
    net = prob.network
    c = net.arrays()
    T = perturbed(rng, prob.T_true, 0.2)
    v = _consistent_residuals('se3', T, c, np.zeros_like(c.z))
    col = np.arange(net.n_nodes) - 1
    cfg = SolverConfig()
    terms = _Terms('se3', c, c.cov, [], cfg, col, 6)
    general = _linear_system(terms, T, v)
    short = _linear_system(replace(terms, P=_inv_spd(c.cov)), T, v)
    np.testing.assert_allclose(short.all_blocks(), general.all_blocks(), rtol=1e-7, atol=1e-6)
    np.testing.assert_allclose(short.u, general.u, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(short.cost0, general.cost0, rtol=1e-9)


def test_cost_tolerance_stops_earlier_at_the_same_optimum(pose_graph_dir):
    """GTSAM-style stop on the relative cost decrease of a Gauss-Newton step: fewer iterations,
    the cost within that fraction of the step-size-converged one."""
    from ga_ros.io.g2o import read_g2o
    g = read_g2o(pose_graph_dir / 'smallGrid3D.g2o')
    strict = solve(g.network, g.T_init, SolverConfig(damping='dogleg', max_iterations=60,
                                                     tolerance=1e-10))
    early = solve(g.network, g.T_init, SolverConfig(damping='dogleg', max_iterations=60,
                                                    tolerance=1e-10, cost_tolerance=1e-6))
    assert early.converged and early.reason == 'cost_converged'
    assert early.iterations < strict.iterations
    assert abs(early.cost - strict.cost) <= 1e-6 * strict.cost


def test_few_node_covariances_by_path_solves_equal_full_solves(monkeypatch):
    """Covariances of a few nodes of a large system come from forward solves along the
    nodes' elimination-tree paths (``_PATH_FROM_UNKNOWNS``): equal to the full solves'
    (rounding: 1e-10 relative), and to the selected inversion of every node's block."""
    from ga_ros.core.solver import result as result_mod

    sc, nm, _ = noisy_aerial_survey(3, 30, 5.0, 0)
    net = sc.network(nm.z, nm.cov)
    res = solve(net, sc.f2f(nm.z), SolverConfig(tolerance=1e-8))
    ids = res.free_node_ids[[0, 7, -2, -1]]
    monkeypatch.setattr(result_mod, '_PATH_FROM_UNKNOWNS', 0)
    sysm = res._system
    assert sysm._path_blocks(ids) is not None  # the factor is read in place: the path solves
    got = res.covariance(ids)
    monkeypatch.setattr(result_mod, '_PATH_FROM_UNKNOWNS', 10 ** 9)
    ref = res.covariance(ids)  # full solves with the same factor
    np.testing.assert_allclose(got, ref, rtol=1e-10, atol=1e-12 * np.abs(ref).max())
    every = res.covariance(res.free_node_ids)  # > _MANY_NODES: the selected inversion
    idx = [int(np.nonzero(res.free_node_ids == i)[0][0]) for i in ids]
    np.testing.assert_allclose(got, every[idx], rtol=1e-9, atol=1e-12 * np.abs(ref).max())


def test_covariances_by_forward_solves_equal_the_dense_inverse(rng):
    """A few nodes' marginal covariances come from forward solves ``Y_k' Y_k`` with
    ``Y_k = L^-1 P E_k`` (half of a full solve): equal to the dense inverse of ``N`` and to the
    full solves' blocks to round-off, a fixed node's block zero."""
    prob = make_problem(rng, 'se3', n=12, noise=1.0)
    net = prob.network
    res = solve(net, initial_guess_f2f(net), SolverConfig(tolerance=1e-12))
    sysm = res._system
    ids = np.array([0, 3, 7, 11])  # node 0: the datum, fixed
    fwd = sysm._forward_blocks(ids)
    if fwd is None:
        pytest.skip('no CHOLMOD factor (cvxopt): covariances come from full solves')
    Ninv = np.linalg.inv(res.normal_matrix.toarray())
    free = list(res.free_node_ids)
    for k, i in enumerate(ids.tolist()):
        if i not in free:
            np.testing.assert_array_equal(fwd[k], 0.0)
            continue
        a = 6 * free.index(i)
        ref = Ninv[a:a + 6, a:a + 6]
        np.testing.assert_allclose(fwd[k], ref, rtol=0, atol=1e-12 * np.abs(ref).max())
        np.testing.assert_array_equal(fwd[k], fwd[k].T)
    X, cols = sysm._columns(ids[1:])
    for k, c in enumerate(cols.tolist()):
        blk = X[6 * c:6 * c + 6, 6 * k:6 * k + 6]
        np.testing.assert_allclose(fwd[k + 1], 0.5 * (blk + blk.T), rtol=0,
                                   atol=1e-13 * np.abs(blk).max())
    np.testing.assert_array_equal(res.covariance(ids), fwd)
