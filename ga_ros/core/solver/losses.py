"""Robust losses on a connection's Mahalanobis misclosure, as classes, and their one registry.

A loss ``rho(r^2)`` of the squared Mahalanobis distance ``r^2 = w' M^-1 w`` is minimised by
iteratively reweighted least squares: each iteration weights a connection by
``rho'(r^2) = weight(r)`` (Triggs et al., "Bundle adjustment -- a modern synthesis", Sec. 3.3;
GTSAM's ``noiseModel::mEstimator``). :data:`LOSSES` is the registry that
:class:`~ga_ros.core.solver.config.SolverConfig`, the pose-graph pipeline and the command line
read their choices from: a new loss is one class here and one registry entry.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import ClassVar

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError


class RobustLoss(ABC):
    """A robust loss with scale ``c`` (the Mahalanobis distance where it departs from least
    squares).

    Attributes
    ----------
    name : the registry key (``SolverConfig.robust_loss``, ``--robust``).
    scale : ``c`` (dimensionless: a Mahalanobis distance), > 0.
    """

    name: ClassVar[str]

    def __init__(self, scale: float = 3.0) -> None:
        if not scale > 0:
            raise InputError(f'the robust scale must be > 0, got {scale}')
        self.scale = float(scale)

    @abstractmethod
    def rho(self, r2: FloatArray) -> FloatArray:
        """The cost of squared Mahalanobis distances ``r2`` (``r2`` itself for least
        squares)."""

    @abstractmethod
    def weight(self, r: FloatArray) -> FloatArray:
        """The IRLS weight ``d rho / d r^2`` at the Mahalanobis distances ``r >= 0``."""

    def __repr__(self) -> str:
        return f'{type(self).__name__}(scale={self.scale})'


class TrivialLoss(RobustLoss):
    """Least squares: ``rho(r^2) = r^2``, weight 1 (``'none'``)."""

    name = 'none'

    def rho(self, r2: FloatArray) -> FloatArray:
        return r2

    def weight(self, r: FloatArray) -> FloatArray:
        return np.ones_like(r)


class HuberLoss(RobustLoss):
    """Huber: ``r^2`` up to ``r = c``, then ``2 c r - c^2`` (weight ``c / r``)."""

    name = 'huber'

    def rho(self, r2: FloatArray) -> FloatArray:
        c = self.scale
        r = np.sqrt(np.maximum(r2, 0.0))
        return np.where(r <= c, r2, 2.0 * c * r - c * c)

    def weight(self, r: FloatArray) -> FloatArray:
        c = self.scale
        return np.where(r <= c, 1.0, c / np.maximum(r, 1e-300))


class CauchyLoss(RobustLoss):
    """Cauchy (Lorentzian): ``c^2 log(1 + r^2 / c^2)`` (weight ``1 / (1 + r^2 / c^2)``)."""

    name = 'cauchy'

    def rho(self, r2: FloatArray) -> FloatArray:
        c = self.scale
        return c * c * np.log1p(r2 / (c * c))

    def weight(self, r: FloatArray) -> FloatArray:
        return 1.0 / (1.0 + (r / self.scale) ** 2)


#: The robust losses by name: the one list of choices (solver settings, CLI, pipelines).
LOSSES: dict[str, type[RobustLoss]] = {cls.name: cls
                                        for cls in (TrivialLoss, HuberLoss, CauchyLoss)}
#: Their names, ``'none'`` first.
ROBUST_LOSSES: tuple[str, ...] = tuple(LOSSES)


def robust_loss(name: str, scale: float = 3.0) -> RobustLoss:
    """The loss registered as ``name`` with scale ``c = scale``.

    Raises
    ------
    InputError
        An unknown name (the message lists :data:`ROBUST_LOSSES`) or ``scale <= 0``.
    """
    try:
        cls = LOSSES[name]
    except (KeyError, TypeError):
        raise InputError(f'robust_loss must be one of {ROBUST_LOSSES}, got {name!r}') from None
    return cls(scale)
