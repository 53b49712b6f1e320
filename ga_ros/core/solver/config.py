"""The settings of a solve (:class:`SolverConfig`)."""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

from ga_ros.core import models
from ga_ros.core.config_ranges import check_ranges, ranged
from ga_ros.core.solver.losses import ROBUST_LOSSES, RobustLoss, robust_loss
from ga_ros.errors import InputError

DAMPINGS = ('none', 'lm', 'dogleg')


FACTORS = ('supernodal', 'auto')


@dataclass(frozen=True)
class SolverConfig:
    """Settings of :func:`solve`.

    Attributes
    ----------
    model : constraint model, ``'se3'`` (full poses, default), ``'se2'`` (planar poses: 3 unknowns
        per node, for 2-D graphs), ``'paper'`` (eq. 1, positions) or ``'linear'`` (positions,
        ``R = I``); see :mod:`ga_ros.core.models`.
    max_iterations : cap on relinearisations.
    tolerance : stop when the largest correction ``max |d|`` is below this (m and rad).
    damping : ``'none'``: the paper's Gauss-Helmert iteration; ``'dogleg'``: Powell's dogleg
        trust region (Gauss-Newton steps while they decrease the cost, one factorisation per
        iteration even when a step is refused), for poor initial guesses; ``'lm'``:
        Levenberg-Marquardt (each refused step costs one more factorisation).
    robust_loss : a name of :data:`~ga_ros.core.solver.losses.LOSSES` (``'none'``,
        ``'huber'``, ``'cauchy'``) on each connection's Mahalanobis
        misclosure ``sqrt(w' M^-1 w)`` (iteratively reweighted).
    robust_scale : Mahalanobis distance at which the robust loss departs from least squares.
    reuse_factor_below : once a correction is smaller than this (m, rad), later iterations reuse
        the last factorisation of ``N`` (chord steps: the same fixed point ``u(x) = 0``, reached
        linearly instead of quadratically, at the cost of one solve instead of a factorisation).
        0 refactors every iteration.
    cost_tolerance : also stop (converged) when a full Gauss-Newton step lowers the cost by less
        than this fraction of it (GTSAM's ``relativeErrorTol``), or when the next chord step
        (``reuse_factor_below``) predicts a decrease ``-u' h`` below this fraction: the estimate
        is kept as it is, without that step (chord steps converge linearly, and along weakly
        observed modes a factor from a few metres away overshoots, so a small decrease of the
        step just taken says little about the distance left); 0 (default) stops on the
        correction size only.
    factor : ``'supernodal'`` (default) or ``'auto'``: below ~6,000 unknowns CHOLMOD may choose
        a simplicial factor of ``N`` when it has few flops per entry (a pose graph of ~1,700
        planar poses: ~2 ms less per solve). Selected inversion reads a simplicial factor
        through a copy; the window aligner uses ``'auto'`` (:data:`~ga_ros.core.window.config.
        ALIGNER_SOLVER`): its large windows stay supernodal, inverted in place.
    chord_decrease : dogleg only: after a Gauss-Newton step that lowered the cost by less than
        this fraction of it, the next iteration first tries the chord step ``-N_old^-1 u`` with
        the last factorisation (one solve instead of a factorisation) and keeps it when the new
        linearisation confirms it (see :func:`_chord_step`); when the decrease that step
        predicts, ``-u' h = h' N_old h``, shows that less than ``cost_tolerance`` of the cost
        is left to gain (:func:`_left_to_gain`), the iteration takes that step if it lowers the
        cost as predicted, and stops (converged) without assembling ``N``. Near the optimum
        this saves the iteration that only confirms convergence (all but its gradient and one
        cost evaluation), and on slowly (linearly) converging graphs such as torus3D most
        factorisations.
        Only with a ``cost_tolerance`` stop (chord steps converge linearly, so a stop on the
        correction size alone would need more iterations). 0 disables.
    """

    model: str = 'se3'
    max_iterations: int = ranged(20, 1, 1_000_000)
    tolerance: float = ranged(1e-8, 0.0, 1e3)
    damping: str = 'none'
    robust_loss: str = 'none'
    robust_scale: float = ranged(3.0, 0.0, 1e6)
    reuse_factor_below: float = 0.1
    cost_tolerance: float = 0.0
    chord_decrease: float = 0.05
    factor: str = 'supernodal'

    def __post_init__(self) -> None:
        models.check_model(self.model)
        check_ranges(self)
        if self.factor not in FACTORS:
            raise InputError(f'factor must be one of {FACTORS}, got {self.factor!r}')
        if self.damping not in DAMPINGS:
            raise InputError(f'damping must be one of {DAMPINGS}, got {self.damping!r}')
        if self.robust_loss not in ROBUST_LOSSES:
            raise InputError(f'robust_loss must be one of {ROBUST_LOSSES}, '
                             f'got {self.robust_loss!r}')
        if not (self.max_iterations >= 1 and self.tolerance > 0 and self.robust_scale > 0
                and 0.0 <= self.cost_tolerance < 1.0 and 0.0 <= self.chord_decrease < 1.0):
            raise InputError('max_iterations >= 1, tolerance > 0, robust_scale > 0, '
                             '0 <= cost_tolerance < 1 and 0 <= chord_decrease < 1 required')

    @cached_property
    def loss(self) -> RobustLoss:
        """The robust loss object of :attr:`robust_loss` and :attr:`robust_scale`."""
        return robust_loss(self.robust_loss, self.robust_scale)
