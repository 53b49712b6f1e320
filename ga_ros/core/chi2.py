"""Chi-square quantiles without SciPy's special functions (start-up of ``ga-ros solve``).

``ga-ros solve`` prints the 95 % interval of ``chi2(r)`` for its variance-factor test. SciPy's
``chdtri`` gives it, but importing :mod:`scipy.special` costs ~0.1-0.15 s of every run (it
builds its array-API wrappers and parses ~170 docstrings), about a tenth of the whole process
on a small graph. This module computes the same quantile with the standard library: the
regularised lower incomplete gamma function ``P(a, x)`` by its power series below ``x = a + 1``
and by Lentz's continued fraction of ``Q = 1 - P`` above (Press et al., *Numerical Recipes*,
3rd ed., Sec. 6.2), and the quantile by Newton's method on ``P`` from the Wilson-Hilferty
approximation. A test checks it against ``scipy.stats.chi2.ppf`` to 1e-10 relative.
:mod:`ga_ros.core.quality` keeps SciPy's distributions (its tests need more than quantiles).
"""

from __future__ import annotations

import functools
import math

from ga_ros.errors import InputError

try:  # the C function behind statistics.NormalDist().inv_cdf, without importing statistics
    from _statistics import _normal_dist_inv_cdf  # (decimal, fractions, random: ~10 ms)
except ImportError:  # pragma: no cover - another interpreter
    from statistics import NormalDist

    def _normal_dist_inv_cdf(p: float, mu: float, sigma: float) -> float:
        return NormalDist(mu, sigma).inv_cdf(p)

_EPS = 1e-15
_TINY = 1e-300


def _log_prefactor(a: float, x: float) -> float:
    """``log(x^a e^-x / Gamma(a))``."""
    return a * math.log(x) - x - math.lgamma(a)


def gamma_p(a: float, x: float) -> float:
    """Regularised lower incomplete gamma function ``P(a, x)`` (``a > 0``, ``x >= 0``)."""
    p, q = _gamma_pq(a, x)
    return p if p <= 0.5 else 1.0 - q


def _gamma_pq(a: float, x: float) -> tuple[float, float]:
    """``(P(a, x), Q(a, x))``, each of them accurate where it is the small one."""
    if x <= 0.0:
        return 0.0, 1.0
    if x < a + 1.0:  # series: P = pre / a * sum_n x^n / ((a+1)...(a+n))
        term = total = 1.0 / a
        ap = a
        for _ in range(100000):
            ap += 1.0
            term *= x / ap
            total += term
            if abs(term) < abs(total) * _EPS:
                break
        p = min(1.0, total * math.exp(_log_prefactor(a, x)))
        return p, 1.0 - p
    # continued fraction of Q (modified Lentz)
    b = x + 1.0 - a
    c = 1.0 / _TINY
    d = 1.0 / b
    h = d
    for i in range(1, 100000):
        an = -i * (i - a)
        b += 2.0
        d = an * d + b
        d = _TINY if abs(d) < _TINY else d
        c = b + an / c
        c = _TINY if abs(c) < _TINY else c
        d = 1.0 / d
        delta = d * c
        h *= delta
        if abs(delta - 1.0) < _EPS:
            break
    q = min(1.0, math.exp(_log_prefactor(a, x)) * h)
    return 1.0 - q, q


@functools.lru_cache(maxsize=256)
def chi2_quantile(dof: float, p: float) -> float:
    """The ``p`` quantile of the chi-square distribution with ``dof`` degrees of freedom
    (``scipy.stats.chi2.ppf(p, dof)``), ``0 < p < 1``. Remembered for the last 256 pairs
    (a gate asks the same few again at every update; ~60 us each)."""
    if not (dof > 0 and 0.0 < p < 1.0):
        raise InputError(f'chi2_quantile needs dof > 0 and 0 < p < 1, got {dof}, {p}')
    a = 0.5 * dof
    z = _normal_dist_inv_cdf(p, 0.0, 1.0)  # NormalDist().inv_cdf(p)
    h = 2.0 / (9.0 * dof)  # Wilson-Hilferty: chi2 ~ dof (1 - h + z sqrt(h))^3
    x = max(0.5 * dof * max(1.0 - h + z * math.sqrt(h), 1e-3) ** 3, 1e-300)
    lo, hi = 0.0, math.inf  # bracket of the root, narrowed by every evaluation
    for _ in range(200):  # safeguarded Newton on P(a, x) = p, x = chi2 / 2
        pp, qq = _gamma_pq(a, x)
        f = pp - p if p <= 0.5 else (1.0 - p) - qq  # P(a, x) - p, from the accurate tail
        if f > 0:
            hi = x
        else:
            lo = x
        dens = math.exp((a - 1.0) * math.log(x) - x - math.lgamma(a))  # dP/dx
        x_new = x - f / dens if dens > 0 else math.nan
        if not lo < x_new < hi:  # outside the bracket: bisect (or double while unbounded)
            x_new = 2.0 * x if math.isinf(hi) else 0.5 * (lo + hi)
        if abs(x_new - x) <= 1e-14 * x:
            return 2.0 * x_new
        x = x_new
    return 2.0 * x
