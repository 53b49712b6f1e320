"""When an iteration stops (:func:`_stop_reason`: converged on the correction or on the cost),
the cost left to gain before a chord step, and whether a chord step is kept."""

from __future__ import annotations

import numpy as np

from ga_ros.core.solver.config import SolverConfig
from ga_ros.core.solver.steps import _Step


def _left_to_gain(predicted: float, previous: float, history: list[float]) -> float:
    """The cost still to gain before a dogleg chord step, estimated from the decrease it
    predicts (``predicted = -u' h = h' N_old h``): with the contraction ``r`` of the decreases,
    the geometric series ``predicted / (1 - r)`` (``inf`` when ``r >= 1``). ``r`` is the larger
    of ``predicted`` over the decrease the last step predicted (``previous``) and over the one it
    achieved (``history[-2] - history[-1]``).

    A chord step right after a converging Gauss-Newton step predicts a decrease thousands of
    times below the last one (parking-garage 2e-9 after 1.5e-3, sphere2500 1.5e-5 after 0.06):
    what is left is that prediction. On a graph that converges linearly (torus3D from the
    file's guess: each chord step predicts ~0.93 of the one before, and achieves twice what it
    predicted) the steps left add up to many predictions, and the prediction alone would stop
    too early (+0.013 % cost on torus3D).
    """
    last = history[-2] - history[-1] if len(history) > 1 else 0.0
    r = max(predicted / previous if previous > 0 else np.inf,
            predicted / last if last > 0 else np.inf)
    return predicted / (1.0 - r) if r < 1.0 else np.inf


def _chord_kept(predicted: float, cost_before: float, cost: float) -> bool:
    """Whether an undamped chord step ``dx = -N_old^-1 u`` (the last factorisation reused,
    :attr:`SolverConfig.reuse_factor_below`) is kept: the cost must fall from ``cost_before``
    to ``cost`` by at least a quarter of the decrease its quadratic model predicts,
    ``predicted = -u' dx = dx' N_old dx`` (the dogleg's acceptance ratio), up to rounding
    (``1e-9`` of the cost). A stale factor (e.g. after a correction that turned the network's
    rotations) fails it: the step is undone and the iteration factors ``N`` at the same point.
    """
    return cost_before - cost >= 0.25 * predicted - 1e-9 * abs(cost_before)


def _stop_reason(step: _Step, history: list[float], cfg: SolverConfig) -> str | None:
    """Why the iteration stops after ``step`` (its cost appended to ``history``):
    ``'converged'`` (the largest correction below ``tolerance``), ``'cost_converged'`` (a full
    Gauss-Newton step lowered the cost by less than ``cost_tolerance`` of it), else ``None``."""
    if step.step < cfg.tolerance:
        return 'converged'
    if step.gauss_newton and 0 <= history[-2] - history[-1] < cfg.cost_tolerance * history[-1]:
        return 'cost_converged'
    return None
