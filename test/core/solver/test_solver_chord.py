"""Dogleg chord steps (issue 10: fewer factorisations): near the optimum an iteration first tries
the last factorisation, and keeps the step only when the new linearisation confirms it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from solver_problems import make_problem, perturbed

from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.solver import SolverConfig, solve, steps, termination
from ga_ros.core.solver.problem import _Problem

DOGLEG = SolverConfig(damping='dogleg', max_iterations=100, tolerance=1e-8, cost_tolerance=1e-5)


def _problem(seed: int):
    rng = np.random.default_rng(seed)
    prob = make_problem(rng, 'se3', n=40, noise=3.0, gaps=(1, 2, 5, 11))
    return prob, perturbed(rng, prob.T_true, 0.3)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_chord_steps_save_factorisations_at_the_same_optimum(seed):
    prob, T0 = _problem(seed)
    chord = solve(prob.network, T0, DOGLEG)
    plain = solve(prob.network, T0, replace(DOGLEG, chord_decrease=0.0))
    # the optimum by the undamped iteration from the truth, to the last digit
    ref = solve(prob.network, prob.T_true, SolverConfig(tolerance=1e-12, max_iterations=50))
    assert chord.converged and plain.converged
    assert plain.factorisations == plain.iterations
    assert chord.factorisations < chord.iterations  # at least one chord step was kept
    assert chord.factorisations < plain.factorisations
    for res in (chord, plain):  # both stop within the cost tolerance of the optimum
        assert ref.cost <= res.cost * (1 + 1e-12) and res.cost - ref.cost <= 1e-5 * ref.cost
    assert all(b <= a * (1 + 1e-12) for a, b in zip(chord.cost_history[1:],
                                                    chord.cost_history[2:]))


def test_chord_steps_need_a_cost_tolerance_stop():
    """Stopping on the correction size alone, every iteration factors (chord steps converge
    linearly: they would need more iterations to reach a tight step tolerance)."""
    prob, T0 = _problem(3)
    res = solve(prob.network, T0, replace(DOGLEG, cost_tolerance=0.0, tolerance=1e-10))
    assert res.converged and res.factorisations == res.iterations


def _state_at(prob, T, chol_scale: float):
    """A dogleg state at T whose last factor is of ``chol_scale * N(T)``, and the system."""
    cfg = DOGLEG
    free = np.ones(prob.network.n_nodes, dtype=bool)
    free[0] = False
    p = _Problem.build('se3', prob.network.arrays(), [], cfg, free)
    sysd = p.linear_system(T, p.consistent(T, p.zero_residuals()))
    data = sysd.normal_values(p.pattern)
    state = steps._Trust(chol=SparseCholesky(p.pattern, chol_scale * data), cost=p.cost_at(T))
    return p, sysd, data, state


def test_chord_with_the_current_factor_is_the_gauss_newton_step():
    prob, T0 = _problem(4)
    p, sysd, data, state = _state_at(prob, T0, 1.0)
    step = steps._chord_step(p, T0, sysd, data, -state.chol.solve(sysd.u), state)
    assert step is not None and step.accepted and step.gauss_newton
    # the Gauss-Newton step by a dense solve of N, retracted: the same poses
    h = -np.linalg.solve(p.pattern.full_csc(data).toarray(), sysd.u)
    np.testing.assert_allclose(step.T, p.retract(T0, h), atol=1e-9)
    assert step.cost < state.cost


@pytest.mark.parametrize('scale', [10.0, 0.1])
def test_chord_with_a_stale_factor_is_refused(scale):
    """A factor of 10 N (steps ten times too short) or N / 10 (ten times too long) disagrees
    with the new linearisation: the caller factors instead."""
    prob, T0 = _problem(5)
    p, sysd, data, state = _state_at(prob, T0, scale)
    assert steps._chord_step(p, T0, sysd, data, -state.chol.solve(sysd.u), state) is None


#: The window aligner's undamped iteration (window.ALIGNER_SOLVER): chord steps below 20 m.
UNDAMPED = SolverConfig(max_iterations=10, tolerance=1e-6, cost_tolerance=1e-6,
                        reuse_factor_below=20.0)


def test_the_gradient_ahead_is_the_linearisation_at_its_point():
    """After a step, the fused kernel's gradient system at the new point (what the next chord
    step and the step's cost use) equals the full linearisation there (the blocks' path), and
    the next gradient at that very point is it, at another point a new one."""
    from ga_ros.core import kernels
    if not kernels.AVAILABLE:
        pytest.skip('numba not installed')
    prob, T0 = _problem(6)
    free = np.ones(prob.network.n_nodes, dtype=bool)
    free[0] = False
    p = _Problem.build('se3', prob.network.arrays(), [], UNDAMPED, free)
    p.jit = True
    T1 = prob.T_true.copy()
    ahead = p.gradient_ahead(T1, 0.5)
    assert ahead is not None and ahead.blocks is None
    full = p.linear_system(T1, None)  # independent: the system with N's blocks
    np.testing.assert_allclose(ahead.u, full.u, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(ahead.w, p.misclosure(T1), rtol=0, atol=0)
    assert ahead.cost0 == pytest.approx(p.cost_at(T1), rel=1e-12)
    assert p.gradient(T1, None) is ahead  # handed to the next chord step once
    assert p.gradient(T1, None) is not ahead
    p.gradient_ahead(T1, 0.5)
    assert p.gradient(T1.copy(), None) is not ahead  # another point: computed anew
    # a step above reuse_factor_below (the next iteration factors) or a robust loss: none
    assert p.gradient_ahead(T1, 25.0) is None
    robust = _Problem.build('se3', prob.network.arrays(), [],
                                   replace(UNDAMPED, robust_loss='huber'), free)
    robust.jit = True
    assert robust.gradient_ahead(T1, 0.5) is None


def test_undamped_chord_steps_fused_equal_the_numpy_iteration(monkeypatch):
    """The undamped iteration with chord steps (the window's), its residuals and costs from
    the fused kernel (no separate misclosure pass), takes the same steps to the same estimate
    as the NumPy path, which computes the misclosure and the cost apart."""
    from ga_ros.core import kernels
    if not kernels.AVAILABLE:
        pytest.skip('numba not installed')
    prob, T0 = _problem(7)
    calls = []
    misclosure = _Problem.misclosure
    monkeypatch.setattr(_Problem, 'misclosure',
                        lambda self, T: calls.append(1) or misclosure(self, T))
    fused = solve(prob.network, T0, UNDAMPED, jit=True)
    fused_calls = len(calls)  # only after a step of 20 m or more (the next one factors)
    assert fused.factorisations < fused.iterations  # chord steps were taken
    monkeypatch.setattr(kernels, 'AVAILABLE', False)
    ref = solve(prob.network, T0, UNDAMPED, jit=True)
    assert fused_calls < len(calls) - fused_calls  # the NumPy path computes them apart
    assert (fused.iterations, fused.factorisations, fused.reason) == (
        ref.iterations, ref.factorisations, ref.reason)
    np.testing.assert_allclose(fused.cost_history, ref.cost_history, rtol=1e-10)
    np.testing.assert_allclose(fused.T_world_node, ref.T_world_node, atol=1e-9)
    np.testing.assert_allclose(fused.residuals, ref.residuals, atol=1e-9)


def test_measured_motions_given_equal_measured_motions_computed():
    """``solve(measured=...)`` (the window's kept ``T_meas`` and inverses) gives the solve
    that computes them from ``z``, bit for bit; wrong shapes are refused."""
    from ga_ros.errors import InputError
    from ga_ros.geometry import se3
    prob, T0 = _problem(8)
    z = prob.network.arrays().z
    T_meas = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
    given = solve(prob.network, T0, UNDAMPED, measured=(T_meas, se3.inverse(T_meas)))
    ref = solve(prob.network, T0, UNDAMPED)
    np.testing.assert_array_equal(given.T_world_node, ref.T_world_node)
    assert given.cost == ref.cost
    with pytest.raises(InputError, match='measured'):
        solve(prob.network, T0, UNDAMPED, measured=(T_meas[1:], T_meas[1:]))


def test_left_to_gain_is_the_geometric_series_of_the_decreases():
    """What is left after a chord step predicting ``p``: the sum ``p + p r + p r^2 + ...``
    (summed term by term here) with ``r`` the larger contraction of the two decreases known."""
    history = [10.0, 9.0, 8.5]  # the last step achieved 0.5
    for p, previous in ((0.05, 0.6), (0.4, 0.45), (1e-6, 0.5)):
        r = max(p / previous, p / 0.5)
        series = sum(p * r ** k for k in range(2000))
        assert termination._left_to_gain(p, previous, history) == pytest.approx(series, rel=1e-9)
    assert termination._left_to_gain(0.6, 0.5, history) == np.inf  # not contracting
    assert termination._left_to_gain(0.1, np.nan, history) == np.inf  # no earlier prediction


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_the_converged_chord_iteration_assembles_no_normal_matrix(seed, monkeypatch):
    """The iteration whose chord step shows that less than ``cost_tolerance`` is left stops
    on the gradient alone: ``N`` is assembled in the other iterations only, and the cost is
    within the tolerance of the optimum (the undamped iteration from the truth)."""
    from ga_ros.core.linalg.blocks import BlockPattern

    prob, T0 = _problem(seed)
    assembled = []
    assemble = BlockPattern.assemble
    monkeypatch.setattr(BlockPattern, 'assemble',
                        lambda self, blocks, *a: assembled.append(1) or assemble(self, blocks, *a))
    res = solve(prob.network, T0, DOGLEG)
    assert res.converged and res.reason == 'cost_converged'
    assert len(assembled) == res.iterations - 1
    ref = solve(prob.network, prob.T_true, SolverConfig(tolerance=1e-12, max_iterations=50))
    assert ref.cost <= res.cost * (1 + 1e-12) and res.cost - ref.cost <= 1e-5 * ref.cost


def test_auto_factor_reaches_the_supernodal_solution(rng):
    """``factor='auto'`` (a simplicial factor where CHOLMOD finds it cheaper) changes only the
    factorisation: the same iterations and estimate as the supernodal default."""
    prob, T0 = _problem(6)
    sup = solve(prob.network, T0, DOGLEG)
    auto = solve(prob.network, T0, replace(DOGLEG, factor='auto'))
    assert auto.iterations == sup.iterations and auto.factorisations == sup.factorisations
    np.testing.assert_allclose(auto.T_world_node, sup.T_world_node, atol=1e-9)
    assert auto.cost == pytest.approx(sup.cost, rel=1e-12)
    with pytest.raises(Exception, match='factor must be one of'):
        replace(DOGLEG, factor='dense')
