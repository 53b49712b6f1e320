"""Dogleg chord steps (issue 10: fewer factorisations): near the optimum an iteration first tries
the last factorisation, and keeps the step only when the new linearisation confirms it."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from solver_problems import make_problem, perturbed

from ga_ros.core import solver
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.sparse import SparseCholesky

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
    p = solver._Problem.build('se3', prob.network.arrays(), [], cfg, free)
    sysd = p.linear_system(T, p.consistent(T, p.zero_residuals()))
    data = sysd.normal_values(p.pattern)
    state = solver._Trust(chol=SparseCholesky(p.pattern, chol_scale * data), cost=p.cost_at(T))
    return p, sysd, data, state


def test_chord_with_the_current_factor_is_the_gauss_newton_step():
    prob, T0 = _problem(4)
    p, sysd, data, state = _state_at(prob, T0, 1.0)
    step = solver._chord_step(p, T0, sysd, data, -state.chol.solve(sysd.u), state)
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
    assert solver._chord_step(p, T0, sysd, data, -state.chol.solve(sysd.u), state) is None


def test_left_to_gain_is_the_geometric_series_of_the_decreases():
    """What is left after a chord step predicting ``p``: the sum ``p + p r + p r^2 + ...``
    (summed term by term here) with ``r`` the larger contraction of the two decreases known."""
    history = [10.0, 9.0, 8.5]  # the last step achieved 0.5
    for p, previous in ((0.05, 0.6), (0.4, 0.45), (1e-6, 0.5)):
        r = max(p / previous, p / 0.5)
        series = sum(p * r ** k for k in range(2000))
        assert solver._left_to_gain(p, previous, history) == pytest.approx(series, rel=1e-9)
    assert solver._left_to_gain(0.6, 0.5, history) == np.inf  # not contracting
    assert solver._left_to_gain(0.1, np.nan, history) == np.inf  # no earlier prediction


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_the_converged_chord_iteration_assembles_no_normal_matrix(seed, monkeypatch):
    """The iteration whose chord step shows that less than ``cost_tolerance`` is left stops
    on the gradient alone: ``N`` is assembled in the other iterations only, and the cost is
    within the tolerance of the optimum (the undamped iteration from the truth)."""
    from ga_ros.core.sparse import BlockPattern

    prob, T0 = _problem(seed)
    assembled = []
    assemble = BlockPattern.assemble
    monkeypatch.setattr(BlockPattern, 'assemble',
                        lambda self, blocks: assembled.append(1) or assemble(self, blocks))
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
