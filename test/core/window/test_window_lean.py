"""The lean window update (issues 10 and 15): chord iterations that evaluate the gradient only,
a stop on the decrease the next chord step predicts, priors kept in blocks; each shortcut
checked against the exact computation (the full linear system, dense matrices, a tight
re-solve)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse as sp
from solver_problems import noisy_aerial_survey

from ga_ros.core import kernels
from ga_ros.core.solver import GaussianPrior, SolverConfig, normal_matrix_at, solve
from ga_ros.core.solver.priors import _PriorData
from ga_ros.core.solver.problem import _Problem
from ga_ros.core.window import ALIGNER_SOLVER
from ga_ros.errors import InputError
from ga_ros.geometry import se3


def _survey_problem(seed: int = 0):
    """A small aerial survey at 10 % noise, its tight optimum, a joint prior on a few nodes."""
    sc, nm, _ = noisy_aerial_survey(3, 12, 10.0, seed)
    net = sc.network(nm.z, nm.cov)
    ref = solve(net, sc.f2f(nm.z), SolverConfig(tolerance=1e-11, max_iterations=50))
    return sc, net, ref


def _joint_prior(rng, net, T, nodes, fmt: str) -> GaussianPrior:
    k = nodes.size
    A = rng.normal(size=(6 * k, 6 * k))
    H = A @ A.T / (6 * k) + np.eye(6 * k)
    H[np.abs(np.subtract.outer(np.arange(6 * k) // 6, np.arange(6 * k) // 6)) > 1] = 0.0
    info = {'dense': H, 'csr': sp.csr_matrix(H), 'bsr': sp.bsr_matrix(H, blocksize=(6, 6))}[fmt]
    mean = T[nodes] @ se3.exp(rng.normal(scale=0.01, size=(k, 6)))
    return GaussianPrior(net.node_ids[nodes], mean, info)


@pytest.mark.parametrize('compiled', [True, False])
@pytest.mark.parametrize('loss', ['none', 'huber'])
def test_gradient_equals_the_full_linear_system(compiled, loss, monkeypatch, rng):
    """The gradient-only evaluation of a chord iteration gives the full linearisation's
    ``u``, misclosure, robust weights and cost (the compiled kernel without its blocks, and the
    fallback that drops them), priors included."""
    if compiled and not kernels.AVAILABLE:
        pytest.skip('numba is not installed')
    monkeypatch.setattr(kernels, 'AVAILABLE', compiled)
    sc, net, ref = _survey_problem()
    T = ref.T_world_node @ se3.exp(rng.normal(scale=0.02, size=(net.n_nodes, 6)))
    prior = _joint_prior(rng, net, T, np.arange(5, 12), 'bsr')
    cfg = SolverConfig(robust_loss=loss, robust_scale=1.0)
    free = np.ones(net.n_nodes, dtype=bool)
    free[0] = False
    pd = [_PriorData.build(net, prior, 6)]
    prob = _Problem.build('se3', net.arrays(), pd, cfg, free)
    prob.jit = True
    assert prob.compiled == compiled
    v = prob.consistent(T, prob.zero_residuals())
    full = prob.linear_system(T, v)
    grad = prob.gradient(T, v)
    assert grad.blocks is None
    np.testing.assert_allclose(grad.u, full.u, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(grad.w, full.w, rtol=0, atol=1e-14)
    np.testing.assert_allclose(grad.weights, full.weights, rtol=1e-14)
    assert grad.cost0 == pytest.approx(full.cost0, rel=1e-13)
    if loss == 'huber':
        assert (grad.weights < 1).any()  # the robust weights took part


def test_prior_blocks_and_products_equal_the_dense_information(rng):
    """A prior given in (6, 6) blocks is taken as it is; dense, CSR and BSR give the same
    blocks, and ``H e`` by the blocked product equals the dense one."""
    sc, net, ref = _survey_problem()
    nodes = np.arange(3, 11)
    built = {}
    for fmt in ('dense', 'csr', 'bsr'):
        prior = _joint_prior(np.random.default_rng(7), net, ref.T_world_node, nodes, fmt)
        built[fmt] = _PriorData.build(net, prior, 6)
    H = _joint_prior(np.random.default_rng(7), net, ref.T_world_node, nodes, 'dense').information
    e = rng.normal(size=(nodes.size, 6))
    for fmt, pd in built.items():
        np.testing.assert_array_equal(pd.blk_r, built['dense'].blk_r, err_msg=fmt)
        np.testing.assert_array_equal(pd.blk_c, built['dense'].blk_c, err_msg=fmt)
        np.testing.assert_allclose(pd.H_blocks, built['dense'].H_blocks, rtol=0, atol=0)
        np.testing.assert_allclose(pd.weighted(e), (H @ e.reshape(-1)).reshape(-1, 6),
                                   rtol=1e-13, atol=1e-13)
    with pytest.raises(InputError, match='more than once'):
        _PriorData.build(net, GaussianPrior(net.node_ids[[3, 3]], ref.T_world_node[[3, 3]],
                                                   np.eye(12)), 6)


def _bent(T: np.ndarray, metres: float) -> np.ndarray:
    """Poses bent along the survey by up to ``metres`` (a smooth, weakly observed mode)."""
    x = T[:, 0, 3]
    s = (x - x.min()) / max(np.ptp(x), 1e-9)
    d = np.zeros((T.shape[0], 6))
    d[:, 1] = metres * np.sin(np.pi * s)
    d[:, 5] = 0.5 * metres / max(np.ptp(x), 1.0) * np.cos(np.pi * s)
    out = se3.exp(d) @ T
    out[0] = T[0]
    return out


@pytest.mark.parametrize('seed', [0, 1])
@pytest.mark.parametrize('metres', [3.0, 10.0])
def test_chord_steps_stop_where_the_next_step_predicts_too_little(seed, metres):
    """From a start bent by metres along the survey's weak mode (as a new track leaves the
    window), the aligner's settings take one factorisation, then chord steps; they stop where
    the next chord step predicts a decrease below ``cost_tolerance`` times the cost. There,
    independently (dense ``N`` and ``u`` at the stop), the full Gauss-Newton step predicts less
    than twice that, and the cost is within it of the optimum (measured: 0.01-0.3 of it)."""
    sc, net, ref = _survey_problem(seed)
    cfg = ALIGNER_SOLVER
    res = solve(net, _bent(ref.T_world_node, metres), cfg, factor_at_solution=False)
    assert res.reason == 'cost_converged' and res.factorisations == 1, res.reason
    assert res.iterations > 2  # chord steps were taken
    N, _, u = normal_matrix_at(net, res.T_world_node, 'se3', [int(net.node_ids[0])])
    decrement = float(u @ np.linalg.solve(N.toarray(), u))
    assert decrement < 2 * cfg.cost_tolerance * res.cost, (decrement, res.cost)
    assert 0 <= res.cost - ref.cost < 2 * cfg.cost_tolerance * res.cost


def test_the_stop_takes_no_step():
    """When the chord step after the Gauss-Newton step predicts too little, the solve ends at
    the Gauss-Newton step's estimate (the chord step is not taken: along the weak modes the
    old factor overshoots, metres on the aerial window, for a decrease below the tolerance)."""
    sc, net, ref = _survey_problem(0)
    T0 = _bent(ref.T_world_node, 1.0)
    res = solve(net, T0, ALIGNER_SOLVER, factor_at_solution=False)
    first = solve(net, T0, replace(ALIGNER_SOLVER, max_iterations=1), factor_at_solution=False)
    assert res.reason == 'cost_converged' and res.iterations == 2 and res.factorisations == 1
    np.testing.assert_array_equal(res.T_world_node, first.T_world_node)
    assert res.cost == first.cost
