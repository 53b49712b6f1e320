"""The mixed adjustment (Gauss-Helmert) solver: batch, weighted parameters, sequential update.

Notation follows docs/method.md and the paper (Sec. III): observations ``l_b`` with weight
``P = S^-1``, residuals ``v``, unknowns ``x``, constraints ``f(l, x) = 0`` linearised as
``A d + B v + w = 0`` with ``w = f(l0, x0) + B (l_b - l0)``. Per connection
``M = B S B'`` (block diagonal), ``N = A' M^-1 A``, ``u = A' M^-1 w``, ``d = -N^-1 u`` (eq. 15),
``k = -M^-1 (A d + w)``, ``v = S B' k`` (eq. 16), ``sigma0^2 = v' P v / (r - u)``,
``Q_x = N^-1`` (eq. 17).

Weighted parameters (Sec. III-E) and the sequential update (Sec. III-D) are both a
:class:`GaussianPrior`: a second observation group ``x - l_p = 0`` with covariance ``S_p`` (or
information ``N_1``), which adds ``A_p' S_p^-1 A_p`` to ``N``. The sequential update
(:func:`sequential_update`) uses only the previous estimate and its normal matrix, never the old
observations.

The package: :mod:`.config` (:class:`SolverConfig`), :mod:`.losses` (robust losses and their
registry), :mod:`.priors` (:class:`GaussianPrior`), :mod:`.problem` (the problem built once),
:mod:`.linearise` (the linear system of an iteration), :mod:`.steps` (damped steps),
:mod:`.termination` (stopping rules), :mod:`.iterate` (:func:`solve`), :mod:`.result`
(:class:`SolveResult`), :mod:`.sequential` (Sec. III-D) and :mod:`.evaluate` (helpers).
"""

from ga_ros.core.solver.config import DAMPINGS, FACTORS, SolverConfig
from ga_ros.core.solver.evaluate import connection_cost, initial_guess_f2f, normal_matrix_at
from ga_ros.core.solver.iterate import solve
from ga_ros.core.solver.losses import (
    LOSSES,
    ROBUST_LOSSES,
    CauchyLoss,
    HuberLoss,
    RobustLoss,
    TrivialLoss,
    robust_loss,
)
from ga_ros.core.solver.priors import GaussianPrior, information_rank
from ga_ros.core.solver.problem import WarmStart
from ga_ros.core.solver.result import SolveResult
from ga_ros.core.solver.sequential import covariance_form_update, sequential_update

__all__ = [
    'DAMPINGS', 'FACTORS', 'LOSSES', 'ROBUST_LOSSES', 'CauchyLoss', 'GaussianPrior', 'HuberLoss',
    'RobustLoss', 'SolveResult', 'SolverConfig', 'TrivialLoss', 'WarmStart', 'connection_cost',
    'covariance_form_update', 'information_rank', 'initial_guess_f2f', 'normal_matrix_at',
    'robust_loss', 'sequential_update', 'solve',
]
