"""Settings of the statistical tests (Baarda's B-method) and the non-centralities they use."""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from ga_ros.errors import InputError
from ga_ros.runtime import lazy_import

optimize = lazy_import('scipy.optimize')  # only the tests' settings need them (start-up)
stats = lazy_import('scipy.stats')

#: The statistics :func:`~ga_ros.core.quality.snooping.data_snooping` can snoop with.
SNOOP_TESTS = ('connection', 'w')


@dataclass(frozen=True)
class QualityConfig:
    """Settings of the tests (B-method of Baarda).

    Attributes
    ----------
    alpha : significance level of the global test of the variance factor.
    alpha0 : significance level of the 1-D w-test (Baarda: 0.001, critical value 3.29).
    power : ``gamma0`` (Baarda's ``beta0``), the probability of detecting a bias of size
        ``lambda0`` with the 1-D test (Baarda: 0.80, giving ``lambda0 = 17.07``).
    snoop_test : data-snooping statistic: ``'connection'`` (the ``q``-dimensional test of a
        whole connection, level ``alpha_q`` of the B-method) or ``'w'`` (the largest 1-D
        w-statistic of the connection's components, level ``alpha0``).
    min_redundancy : connections with a redundancy number below this are not tested (their
        errors are not detectable, and removing them would break the network).
    """

    alpha: float = 0.05
    alpha0: float = 0.001
    power: float = 0.80
    snoop_test: str = 'connection'
    min_redundancy: float = 1e-3

    def __post_init__(self) -> None:
        for name in ('alpha', 'alpha0', 'power'):
            val = getattr(self, name)
            if not 0.0 < val < 1.0:
                raise InputError(f'{name} must be in (0, 1), got {val}')
        if self.power <= self.alpha0:
            raise InputError('power must exceed alpha0 (a test cannot be weaker than chance)')
        if self.snoop_test not in SNOOP_TESTS:
            raise InputError(f'snoop_test must be one of {SNOOP_TESTS}, got {self.snoop_test!r}')
        if not 0.0 <= self.min_redundancy < 1.0:
            raise InputError(f'min_redundancy must be in [0, 1), got {self.min_redundancy}')

    @property
    def lambda0(self) -> float:
        """Non-centrality detected by the 1-D test (level ``alpha0``) with probability
        ``power``: ``P(chi2'(1, lambda0) > chi2_{1-alpha0}(1)) = power``."""
        return noncentrality(self.alpha0, self.power, 1)

    @property
    def w_critical(self) -> float:
        """Critical value of ``|w|``: ``z_{1-alpha0/2}``."""
        return float(stats.norm.isf(self.alpha0 / 2.0))


@lru_cache(maxsize=256)
def noncentrality(alpha: float, power: float, q: int) -> float:
    """``lambda`` such that a ``chi2(q)`` test of level ``alpha`` rejects ``chi2'(q, lambda)``
    with probability ``power`` (Baarda's ``lambda0(alpha0, beta0, q)``)."""
    c = stats.chi2.isf(alpha, q)
    return float(optimize.brentq(lambda lam: stats.ncx2.sf(c, q, lam) - power, 1e-9, 1e4,
                                 xtol=1e-12))


@lru_cache(maxsize=256)
def b_method_alpha(lambda0: float, power: float, q: int) -> float:
    """Level ``alpha_q`` of a ``q``-dimensional test that detects ``lambda0`` with ``power``
    (the B-method: every test is as sensitive as the 1-D w-test)."""
    def excess(log_alpha: float) -> float:
        return float(stats.ncx2.sf(stats.chi2.isf(np.exp(log_alpha), q), q, lambda0)) - power

    return float(np.exp(optimize.brentq(excess, np.log(1e-15), np.log(0.999), xtol=1e-12)))
