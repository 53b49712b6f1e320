"""``solve(..., warm=WarmStart(...))``: the caches a caller hands the next solve, the same as
the keywords of the same names (the window aligner's call path)."""

from __future__ import annotations

import numpy as np
import pytest
from solver_problems import make_problem, perturbed

from ga_ros.core.solver import SolverConfig, WarmStart, solve
from ga_ros.errors import InputError
from ga_ros.geometry import se3


def test_warm_start_equals_the_keywords_and_reuses_the_factor(rng):
    prob = make_problem(rng, 'se3', n=30, noise=1.0)
    T0 = perturbed(rng, prob.T_true, 0.05)
    cfg = SolverConfig(tolerance=1e-10)
    conn = prob.network.arrays()
    weights = np.linalg.inv(conn.cov)
    T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    measured = (T_meas, se3.inverse(T_meas))
    cold = solve(prob.network, T0, cfg)
    first = solve(prob.network, T0, cfg, weights=weights, measured=measured)
    factor = first.release_factor()
    warm = solve(prob.network, T0, cfg,
                 warm=WarmStart(weights=weights, measured=measured, factor=factor))
    for res in (first, warm):  # the same adjustment: the caches change no number beyond rounding
        np.testing.assert_allclose(res.T_world_node, cold.T_world_node, rtol=0, atol=1e-9)
        assert res.cost == pytest.approx(cold.cost, rel=1e-9)
    # the factor handed over is the one the warm solve refactored (its symbolic analysis)
    assert warm.release_factor() is factor


def test_warm_and_keywords_together_or_unknown_keywords_are_refused(rng):
    prob = make_problem(rng, 'se3', n=6, noise=1.0)
    with pytest.raises(InputError, match='either'):
        solve(prob.network, prob.T_true, warm=WarmStart(), jit=True)
    with pytest.raises(InputError, match='unknown keywords'):
        solve(prob.network, prob.T_true, factr=None)
