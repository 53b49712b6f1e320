"""The planar model ``se2``: SE(2) helpers against SE(3) restricted to the plane, Jacobians
against central differences, and solutions against the SE(3) embedding of the same graph."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ga_ros.core import models
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.solver.linearise import _consistent_residuals, _inv_spd, _linear_system, _Terms
from ga_ros.geometry import se2, se3

AX = se2.AXES


def _planar_xi(rng, n, scale=1.0):
    """Tangents ``[x y theta]`` with random, near-zero and near-pi angles."""
    xi = rng.normal(scale=scale, size=(n, 3))
    xi[: n // 4, 2] *= 1e-6
    xi[n // 4: n // 2, 2] = np.pi - rng.uniform(0, 1e-3, size=n // 2 - n // 4)
    return xi


def _embed(xi):
    out = np.zeros(xi.shape[:-1] + (6,))
    out[..., AX] = xi
    return out


def test_se2_helpers_are_se3_restricted_to_the_plane(rng):
    xi = _planar_xi(rng, 40)
    T = se2.exp(xi)
    np.testing.assert_allclose(T, se3.exp(_embed(xi)), atol=1e-12)
    np.testing.assert_allclose(se2.Planar.from_matrix(T).log(), se3.log(T)[:, AX], atol=1e-9)
    np.testing.assert_allclose(se2.right_jacobian_inv(xi),
                               se3.right_jacobian_inv(_embed(xi))[:, AX[:, None], AX],
                               atol=1e-9)
    np.testing.assert_allclose(se2.adjoint(se2.Planar.from_matrix(T)),
                               se3.adjoint(T)[:, AX[:, None], AX], atol=1e-12)
    T2 = se2.exp(_planar_xi(rng, 40))
    np.testing.assert_allclose(se2.local(T, T2), se3.local(T, T2)[:, AX], atol=1e-9)
    np.testing.assert_allclose(se2.retract(T, xi), se3.retract(T, _embed(xi)), atol=1e-12)
    # one pose at a time: the shapes of one pose, the values of the stack's rows
    assert se2.local(T[3], T2[3]).shape == (3,) and se2.retract(T[3], xi[3]).shape == (4, 4)
    np.testing.assert_array_equal(se2.local(T[3], T2[3]), se2.local(T, T2)[3])


def _planar_graph(rng, n=12, extra=10, planar_info=True):
    """A planar graph: a chain plus random short loop closures, block-diagonal 6x6 covariances
    (random SPD ``[x y rz]`` block, unit elsewhere), noisy planar measurements."""
    T_true = se2.exp(np.cumsum(rng.normal(scale=[1.0, 0.3, 0.4], size=(n, 3)), axis=0))
    loop_src = rng.integers(0, n - 2, size=extra)
    loop_dst = np.minimum(loop_src + rng.integers(2, 6, size=extra), n - 1)
    src = np.concatenate([np.arange(n - 1), loop_src])
    dst = np.concatenate([np.arange(1, n), loop_dst])
    m = src.size
    L = np.tril(rng.normal(scale=0.02, size=(m, 3, 3)), -1) + np.diag([0.1, 0.1, 0.05])
    S3 = L @ np.swapaxes(L, 1, 2)
    cov = np.broadcast_to(np.eye(6), (m, 6, 6)).copy()
    cov[:, AX[:, None], AX] = S3
    noise = np.linalg.cholesky(S3) @ rng.normal(size=(m, 3, 1))
    T_meas = se3.inverse(T_true[src]) @ T_true[dst] @ se2.exp(noise[:, :, 0])
    z = se3.to_translation_rotvec(T_meas)
    net = ConnectionNetwork()
    for i in range(n):
        net.add_node(i)
    net.add_connections(src, dst, z, cov)
    return net, T_true


def _node_perturb(T, idx, k, eps):
    delta = np.zeros((1, 3))
    delta[0, k] = eps
    return models.retract('se2', T, np.array([idx]), delta)


def test_se2_jacobians_match_central_differences(rng):
    net, T_true = _planar_graph(rng)
    T = se2.retract(T_true, rng.normal(scale=0.1, size=(T_true.shape[0], 3)))
    c = net.arrays()
    T_meas = se3.from_translation_rotvec(c.z[:, :3], c.z[:, 3:])
    bt = models.between('se2', T, c.src, c.dst, T_meas)
    v = rng.normal(scale=0.05, size=(len(c), 3))
    lin = models.linearise('se2', T, c.src, c.dst, c.z, v)
    eps = 1e-6
    for k in range(3):
        for which, A_short, A_gen in (('src', -bt.Jr_inv @ bt.Ad_ji, lin.A_src),
                                      ('dst', bt.Jr_inv, lin.A_dst)):
            num_e, num_f = np.zeros_like(bt.e), np.zeros_like(lin.f)
            for q in range(len(c)):
                node = c.src[q] if which == 'src' else c.dst[q]
                s, d = c.src[q:q + 1], c.dst[q:q + 1]
                Tp, Tm = _node_perturb(T, node, k, eps), _node_perturb(T, node, k, -eps)
                num_e[q] = (models.motion_misclosure('se2', Tp, s, d, T_meas[q:q + 1])[0]
                            - models.motion_misclosure('se2', Tm, s, d, T_meas[q:q + 1])[0])
                num_f[q] = (models.linearise('se2', Tp, s, d, c.z[q:q + 1], v[q:q + 1]).f[0]
                            - models.linearise('se2', Tm, s, d, c.z[q:q + 1], v[q:q + 1]).f[0])
            np.testing.assert_allclose(A_short[:, :, k], num_e / (2 * eps), atol=1e-6)
            np.testing.assert_allclose(A_gen[:, :, k], num_f / (2 * eps), atol=1e-6)
    for k in range(3):
        dv = np.zeros_like(v)
        dv[:, k] = eps
        fp = models.linearise('se2', T, c.src, c.dst, c.z, v + dv).f
        fm = models.linearise('se2', T, c.src, c.dst, c.z, v - dv).f
        np.testing.assert_allclose(lin.B[:, :, k], (fp - fm) / (2 * eps), atol=1e-6)
    np.testing.assert_allclose(bt.e, models.motion_misclosure('se3', T, c.src, c.dst,
                                                              T_meas)[:, AX], atol=1e-9)


def test_se2_shortcut_system_equals_the_general_gauss_helmert_system(rng):
    net, T_true = _planar_graph(rng)
    T = se2.retract(T_true, rng.normal(scale=0.1, size=(T_true.shape[0], 3)))
    c = net.arrays()
    S = models.observation_covariance('se2', c.cov)
    v = _consistent_residuals('se2', T, c, np.zeros((len(c), 3)))
    col = np.arange(net.n_nodes) - 1
    cfg = SolverConfig(model='se2')
    terms = _Terms('se2', c, S, [], cfg, col, 3)
    general = _linear_system(terms, T, v)
    short = _linear_system(replace(terms, P=_inv_spd(S)), T, v)
    np.testing.assert_allclose(short.all_blocks(), general.all_blocks(), rtol=1e-7, atol=1e-6)
    np.testing.assert_allclose(short.u, general.u, rtol=1e-7, atol=1e-7)
    np.testing.assert_allclose(short.cost0, general.cost0, rtol=1e-9)


@pytest.mark.parametrize('damping', ['none', 'dogleg'])
def test_se2_solution_equals_the_se3_embedding(rng, damping):
    """Same optimum, cost, redundancy and ``[x y rz]`` marginal covariances as the SE(3)
    embedding of the planar graph (the out-of-plane unknowns decouple at planar poses)."""
    net, T_true = _planar_graph(rng, n=30, extra=25)
    T0 = se2.retract(T_true, rng.normal(scale=0.05, size=(T_true.shape[0], 3)))
    r2 = solve(net, T0, SolverConfig(model='se2', damping=damping, tolerance=1e-10))
    r3 = solve(net, T0, SolverConfig(model='se3', damping=damping, tolerance=1e-10))
    assert r2.converged and r3.converged
    np.testing.assert_allclose(r2.T_world_node, r3.T_world_node, atol=1e-6)
    assert r2.cost == pytest.approx(r3.cost, rel=1e-9)
    assert r2.redundancy == r3.redundancy // 2
    np.testing.assert_allclose(r2.residuals, r3.residuals, atol=1e-6)
    ids = net.node_ids[1:]
    np.testing.assert_allclose(r2.covariance(ids), r3.covariance(ids)[:, AX[:, None], AX],
                               rtol=1e-6, atol=1e-12)


def test_intel_planar_solve_reaches_the_se3_embedding_optimum(pose_graph_dir):
    from ga_ros.io.g2o import graph_cost, read_g2o
    from ga_ros.pipeline.pose_graph import GraphSolveConfig, solve_graph
    g = read_g2o(pose_graph_dir / 'intel.g2o')
    planar = solve_graph(g)
    embedded = solve_graph(g, GraphSolveConfig(planar=False))
    assert planar.cost == pytest.approx(embedded.cost, rel=1e-6)
    assert planar.cost == pytest.approx(graph_cost(g, planar.T_world_node), rel=1e-12)
    np.testing.assert_allclose(planar.T_world_node[:, :3, 3], embedded.T_world_node[:, :3, 3],
                               atol=1e-4)
