"""Variance components per source, estimated online: after each window adjustment of a
track-window aligner (:class:`~ga_ros.core.window.TrackWindowAligner`).

The batch estimate (:mod:`ga_ros.core.quality.variance_components`) iterates whole
adjustments until every group's ``v_k' P_k v_k`` equals its redundancy ``r_k``. Online, each
window adjustment is one step of that iteration: for every connection it contained, the
adjustment gives the weighted squared residual under the *stated* weights
``c_i = v_i' S_i^-1 v_i`` and the redundancy number ``r_i = tr((Q_vv P)_ii)`` under the weights
it used. The book keeps, per connection, the values of the last adjustment that contained it
(a connection absorbed into a joint prior keeps those of its last window: absorbed tracks still
count), and per group ``k``

    ``C_k = sum c_i``, ``R_k = sum r_i``, ``s_k = C_k / R_k``

(with the weights ``P_i = S_i^-1 / s_k`` this is Förstner's step ``s_k <- s_k v_k' P_k v_k /
r_k``; at its fixed point ``v_k' P_k v_k = r_k``). ``R_k`` is the group's degrees of freedom and
``sigma(s_k) = s_k sqrt(2 / R_k)`` the factor's standard deviation.

Damping: a group whose ``R_k`` is below ``min_redundancy`` is not estimated (factor 1: its
stated covariance stands); above, the factor is shrunk towards 1 in proportion, with a prior
of ``prior_dof`` degrees of freedom: ``s_k = (C_k / R_k) ^ (R_k / (R_k + prior_dof))``
(:func:`~ga_ros.core.quality.variance_components.damped_factor`, as the calibration's noise
factors; ``C_k / R_k`` clipped to ``factor_bounds``; a ratio, so a factor of 1/25 is shrunk
as little as one of 25). A factor is in *variance*: 4 says the stated covariance is 4x too small
(the stated sigmas 2x).

Sources measuring the same motions (two odometry streams) are split by their own consistency
(:mod:`ga_ros.core.quality.source_consistency`, fed by :meth:`OnlineVarianceComponents.observe`,
read after each recorded adjustment): the sources it estimates (10 terms or more) share one
scale ``lambda = sum_k (C_k / f_k) / sum_k R_k`` over them (damped with ``sum_k R_k`` as
above) and get ``lambda f_k``; their residuals alone show only the sum of their variances.

Absolute fixes (:mod:`ga_ros.core.fixes`) are observations too: each fix source
(``gnss0``, ``amcl0``, ...) is a group of its own, booked per fix
(:meth:`OnlineVarianceComponents.register_fix`,
:meth:`~OnlineVarianceComponents.record_fixes`) with ``c_f = e_f' L_f e_f`` (``e_f`` the
fix's misclosure at the adjusted pose, ``L_f`` its stated information, the odometry offset's
covariance included) and ``r_f = tr(I - J Q J' L_f / s)`` over its known dimensions (``J``
the sensor Jacobian, ``Q`` the node's marginal covariance, ``s`` the factor the adjustment
used). Several fixes merged into one node prior keep their own values. The gauge prior of
``datum='fixes'`` is no observation and has no group.

Everything here depends on the adjustments only (never on timing), so a replay and a live node
get the same factors; the sums are recomputed from the per-connection values (no running
totals whose rounding would depend on the order of updates).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.measurement import Measurement
from ga_ros.core.quality.source_consistency import SourceConsistency
from ga_ros.core.quality.variance_components import (
    VarianceComponent,
    damped_factor,
    factor_sigma,
)
from ga_ros.errors import InputError

ONLINE_MODES = ('off', 'apply')


@dataclass(frozen=True)
class OnlineVarianceConfig:
    """Settings of the online variance components.

    Attributes
    ----------
    mode : ``'off'`` (nothing estimated) or ``'apply'`` (each window adjustment weights every
        connection by its group's current factor, so the solution and the published
        covariances use them). There is no report-only mode online: a factor estimated from
        the stated weights alone (one step of the iteration) is biased towards 1 wherever the
        groups share the redundancy (a source stated 4x too small shows about 2); only the
        iteration, which changes the weights, converges to the factor.
    min_redundancy : a group with less accumulated redundancy ``R_k`` keeps factor 1.
    prior_dof : degrees of freedom of the prior ``s = 1`` the estimate is shrunk towards (in
        log: ``s = (C / R) ^ (R / (R + prior_dof))``).
    factor_bounds : the factors are clipped to this range.
    warn_ratio, warn_sigmas : a factor above ``warn_ratio`` or below ``1 / warn_ratio``, more
        than ``warn_sigmas`` of its sigmas from 1, is named in a warning.
    max_inner_iterations : ``'apply'``: after a track's window adjustment, the window is
        adjusted again with the new factors at most this many times, until no factor changes
        by more than ``tolerance`` (relative).
    """

    mode: str = 'off'
    min_redundancy: float = 20.0
    prior_dof: float = 10.0
    factor_bounds: tuple[float, float] = (1e-3, 1e3)
    warn_ratio: float = 2.0
    warn_sigmas: float = 3.0
    max_inner_iterations: int = 8
    tolerance: float = 0.01

    def __post_init__(self) -> None:
        if self.mode not in ONLINE_MODES:
            raise InputError(f'variance_components must be one of {ONLINE_MODES}, got '
                             f'{self.mode!r}')
        if not self.min_redundancy >= 0 or not self.prior_dof >= 0:
            raise InputError('variance_min_redundancy and variance_prior_dof must be >= 0')
        lo, hi = self.factor_bounds
        if not 0 < lo < 1 < hi:
            raise InputError('variance factor_bounds must be (lo, hi) with 0 < lo < 1 < hi')


class OnlineVarianceComponents:
    """The per-group book of the online estimate (module docstring).

    Connections are registered in arrival order (:meth:`register`, one group name each; the
    row is the aligner's connection row); :meth:`record` stores an adjustment's values of some
    rows; :meth:`components` and :meth:`factors_of` read the current factors.

    Parameters
    ----------
    config : settings.
    """

    def __init__(self, config: OnlineVarianceConfig | None = None) -> None:
        self.config = config or OnlineVarianceConfig()
        self.names: list[str] = []
        self._group = np.zeros(64, dtype=np.int32)
        self._cost = np.zeros(64)
        self._red = np.zeros(64)
        self.n = 0
        # the absolute fixes, by fix index: group (-1: none, the gauge prior), cost, redundancy
        self._fgroup = np.zeros(0, dtype=np.int32)
        self._fcost = np.zeros(0)
        self._fred = np.zeros(0)
        #: each source's own consistency against the others measuring the same motions
        self.consistency = SourceConsistency()
        # its split ({source: (factor, dof)}) as of the last recorded adjustment: the factors
        # change with the adjustments only
        self._split: dict[str, tuple[float, float]] = {}

    # --------------------------------------------------------------------- input
    def register(self, group: str) -> int:
        """Register the next connection row with its group; returns the row."""
        if group not in self.names:
            self.names.append(group)
        if self.n == self._group.size:
            size = 2 * self.n
            self._group = np.resize(self._group, size)
            self._cost = np.concatenate([self._cost, np.zeros(size - self.n)])
            self._red = np.concatenate([self._red, np.zeros(size - self.n)])
        self._group[self.n] = self.names.index(group)
        self.n += 1
        return self.n - 1

    @property
    def n_fixes(self) -> int:
        """The number of fixes registered."""
        return int(self._fgroup.size)

    def register_fix(self, group: str | None) -> int:
        """Register the next absolute fix (the fix book's next index) with its source's group
        (``None``: no group, the gauge prior); returns its index."""
        k = -1
        if group is not None:
            if group not in self.names:
                self.names.append(group)
            k = self.names.index(group)
        self._fgroup = np.append(self._fgroup, np.int32(k))
        self._fcost = np.append(self._fcost, 0.0)
        self._fred = np.append(self._fred, 0.0)
        return self.n_fixes - 1

    def record_fixes(self, fixes: IntArray, cost: FloatArray, redundancy: FloatArray) -> None:
        """Store the values of one adjustment for the fixes ``fixes`` (registered indices):
        ``cost`` ``e' L e`` under the stated information, ``redundancy`` ``r_f`` under the
        weights the adjustment used (0 and 0 for a fix it excluded)."""
        fixes = np.asarray(fixes, dtype=np.int64)
        ok = fixes < self.n_fixes
        self._fcost[fixes[ok]] = np.asarray(cost, float)[ok]
        self._fred[fixes[ok]] = np.asarray(redundancy, float)[ok]

    def fix_factors_of(self, fixes: IntArray, factors: FloatArray | None = None) -> FloatArray:
        """``(k,)`` the factor of each fix's group (1 for the gauge prior and unregistered
        fixes), from ``factors`` (per group, :meth:`factors` by default)."""
        fixes = np.asarray(fixes, dtype=np.int64)
        given = self.factors() if factors is None else np.asarray(factors, float)
        f = np.ones(len(self.names) + 1)
        f[:given.size] = given
        ok = fixes < self.n_fixes
        g = np.full(fixes.size, -1, np.int64)
        g[ok] = self._fgroup[fixes[ok]]
        return f[g]

    def record(self, rows: IntArray, cost: FloatArray, redundancy: FloatArray) -> None:
        """Store the values of one adjustment for connection ``rows`` (registered): ``cost``
        ``v_i' S_i^-1 v_i`` under the stated covariance, ``redundancy`` ``r_i`` under the
        weights the adjustment used. Rows not registered (a state restored without groups) are
        ignored."""
        rows = np.asarray(rows, dtype=np.int64)
        ok = rows < self.n
        self._cost[rows[ok]] = np.asarray(cost, float)[ok]
        self._red[rows[ok]] = np.asarray(redundancy, float)[ok]
        self._split = self.consistency.split(min_terms=10, bounds=self.config.factor_bounds)

    # -------------------------------------------------------------------- output
    def sums(self) -> tuple[FloatArray, FloatArray, IntArray]:
        """Per group (order of :attr:`names`): ``C_k``, ``R_k`` and the observation count."""
        k = len(self.names)
        g = self._group[:self.n]
        fg = self._fgroup >= 0
        fgi = self._fgroup[fg]
        return (np.bincount(g, weights=self._cost[:self.n], minlength=k)
                + np.bincount(fgi, weights=self._fcost[fg], minlength=k),
                np.bincount(g, weights=self._red[:self.n], minlength=k)
                + np.bincount(fgi, weights=self._fred[fg], minlength=k),
                np.bincount(g, minlength=k) + np.bincount(fgi, minlength=k))

    def observe(self, m: Measurement) -> None:
        """Take a measurement the aligner accepted into its source's consistency
        (:mod:`ga_ros.core.quality.source_consistency`)."""
        self.consistency.add(m)

    def factors(self) -> FloatArray:
        """Per group, the damped factor in use (1 while ``R_k < min_redundancy``)."""
        return self._estimate()[0]

    def _estimate(self) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Per group: the damped factor in use, ``estimated``, and the degrees of freedom
        of its sigma (module docstring)."""
        cfg = self.config
        C, R, _ = self.sums()
        est = R >= max(cfg.min_redundancy, 1e-9)
        lo, hi = cfg.factor_bounds
        s = damped_factor(C, R, cfg.prior_dof, cfg.factor_bounds)
        dof = R.copy()
        split = self._split
        tied = np.array([g in split for g in self.names], dtype=bool)
        if tied.any():
            nu = np.array([split[g][1] if g in split else 0.0 for g in self.names])
            q = np.array([split[g][0] if g in split else 1.0 for g in self.names])
            R_t = float(R[tied].sum())
            lam = float(damped_factor(float(np.sum(C[tied] / q[tied])), R_t, cfg.prior_dof,
                                      cfg.factor_bounds))
            s = np.where(tied, np.clip(lam * q, lo, hi), s)
            est = np.where(tied, R_t >= max(cfg.min_redundancy, 1e-9), est)
            dof = np.where(tied, 1.0 / (1.0 / max(R_t, 1e-300) + 1.0 / np.maximum(nu, 1e-300)),
                           dof)
        return np.where(est, s, 1.0), est, dof

    def factors_of(self, rows: IntArray, factors: FloatArray | None = None) -> FloatArray:
        """``(m,)`` the factor of each connection row's group (1 for unregistered rows), from
        ``factors`` (per group, :meth:`factors` by default)."""
        rows = np.asarray(rows, dtype=np.int64)
        given = self.factors() if factors is None else np.asarray(factors, float)
        f = np.ones(len(self.names) + 1)  # groups new since ``factors``: 1; the last: unknown
        f[:given.size] = given
        g = np.where(rows < self.n, self._group[np.minimum(rows, max(self.n - 1, 0))], -1)
        return f[g]

    def components(self) -> tuple[VarianceComponent, ...]:
        """Every group's factor with its degrees of freedom and sigma (``applied``: the
        weights use it, ``mode='apply'`` and estimated)."""
        cfg = self.config
        C, R, count = self.sums()
        f, estimated, dof = self._estimate()
        out = []
        for k, name in enumerate(self.names):
            est = bool(estimated[k])
            sigma = float(factor_sigma(f[k], dof[k]))
            out.append(VarianceComponent(
                group=name, factor=float(f[k]), redundancy=float(R[k]), sigma=sigma,
                observations=int(count[k]), estimated=est,
                significant=est and abs(f[k] - 1.0) > cfg.warn_sigmas * sigma,
                applied=est and cfg.mode == 'apply'))
        return tuple(out)

    def as_dict(self) -> dict:
        """``{group: {factor, dof, sigma, observations, estimated, significant, applied}}``
        plus the mode under ``'_estimation'`` (``summary.json``'s
        ``online_variance_components``)."""
        out: dict = {c.group: c.as_dict() for c in self.components()}
        out['_estimation'] = {'mode': self.config.mode, 'online': True}
        return out

    def diagnostic_values(self) -> dict[str, str]:
        """``/diagnostics`` key/values: ``variance/<group>/factor``, ``.../dof``,
        ``.../sigma`` (``factor`` 1 and ``not estimated`` while poorly determined)."""
        out = {}
        for c in self.components():
            key = f'variance/{c.group}/'
            out[key + 'factor'] = f'{c.factor:.4g}' if c.estimated else '1 (not estimated)'
            out[key + 'dof'] = f'{c.redundancy:.1f}'
            out[key + 'sigma'] = f'{c.sigma:.3g}'
        return out

    def warnings(self) -> list[str]:
        """One line per group whose factor is far from 1, saying by how much its stated
        covariance is off (``"odom1's stated covariance is 4x too small ..."``)."""
        cfg = self.config
        return [warning_line(c) for c in self.components()
                if c.estimated and np.isfinite(c.sigma)
                and (c.factor >= cfg.warn_ratio or c.factor <= 1.0 / cfg.warn_ratio)
                and abs(c.factor - 1.0) > cfg.warn_sigmas * c.sigma]

    # ----------------------------------------------------------------- persistence
    def arrays(self) -> dict:
        """Plain arrays of the book (a snapshot file): group names, per-row group, cost and
        redundancy, the same per fix (``fix_group``, ``fix_cost``, ``fix_redundancy``) and the
        sources' consistency (``consistency``, :meth:`SourceConsistency.arrays
        <ga_ros.core.quality.source_consistency.SourceConsistency.arrays>`)."""
        return {'names': list(self.names), 'group': self._group[:self.n].copy(),
                'cost': self._cost[:self.n].copy(), 'redundancy': self._red[:self.n].copy(),
                'fix_group': self._fgroup.copy(), 'fix_cost': self._fcost.copy(),
                'fix_redundancy': self._fred.copy(), 'consistency': self.consistency.arrays(),
                'split_names': list(self._split),
                'split': np.asarray(list(self._split.values()), float).reshape(-1, 2)}

    @classmethod
    def from_arrays(cls, config: OnlineVarianceConfig, values: dict
                    ) -> OnlineVarianceComponents:
        """The book of :meth:`arrays`."""
        book = cls(config)
        book.names = [str(s) for s in values['names']]
        g = np.asarray(values['group'], dtype=np.int32)
        book.n = g.size
        size = max(64, 2 * g.size)
        book._group = np.zeros(size, np.int32)
        book._cost, book._red = np.zeros(size), np.zeros(size)
        book._group[:g.size] = g
        book._cost[:g.size] = np.asarray(values['cost'], float)
        book._red[:g.size] = np.asarray(values['redundancy'], float)
        if values.get('fix_group') is not None:  # books saved without fixes: none
            book._fgroup = np.asarray(values['fix_group'], np.int32).copy()
            book._fcost = np.asarray(values['fix_cost'], float).copy()
            book._fred = np.asarray(values['fix_redundancy'], float).copy()
        if values.get('consistency') is not None:  # books saved without it: none yet
            book.consistency = SourceConsistency.from_arrays(values['consistency'])
            book._split = {str(k): (float(f), float(nu)) for k, (f, nu) in
                           zip(values['split_names'], np.asarray(values['split']).reshape(-1, 2))}
        return book


def warning_line(c: VarianceComponent) -> str:
    """The WARN line of a factor far from 1."""
    ratio = c.factor if c.factor > 1 else 1.0 / c.factor
    how = 'small' if c.factor > 1 else 'large'
    return (f"{c.group}'s stated covariance is {ratio:.3g}x too {how} (its sigmas "
            f'{np.sqrt(ratio):.3g}x; variance factor {c.factor:.3g} +- {c.sigma:.2g}, '
            f'{c.redundancy:.0f} dof)')
