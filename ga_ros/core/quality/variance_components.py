"""Variance components per group of observations (Helmert / Förstner variance-component
estimation): one variance factor per source, estimated from the redundancy of the adjustment.

The observations of an adjustment are split into groups ``k`` (an odometry source's motions,
the cross-track connections, an absolute-fix source, ...). Each group's stated covariances are
scaled by a factor ``s_k``: ``S_k = s_k S_k,stated``. Förstner's simplified iterative estimate
(Förstner 1979; Koch 1999, Sec. 3.6.3; Teunissen & Amiri-Simkooei 2008) is, per iteration,

    ``s_k <- s_k * (v_k' P_k v_k) / r_k``,

with ``v_k' P_k v_k`` the group's weighted squared residuals under its current weights
``P_k = S_k^-1`` and ``r_k`` the group's redundancy: the sum of its redundancy numbers
``r_i = tr((Q_vv P)_ii)`` (:func:`ga_ros.core.quality.quality_control`) for connections, and
``rank(N_p) - tr(Q_x N_p)`` for weighted parameters (priors, ``N_p`` their part of the normal
matrix). The adjustment is repeated with the new weights until every group's
``v_k' P_k v_k / r_k`` is within ``tolerance`` of 1 (the simple iteration converges linearly;
every third step is extrapolated with Aitken's method). At convergence
``v_k' P_k v_k = r_k`` for every group: each group's covariances agree with its own
residuals. The sum of the ``r_k`` is the redundancy ``r - u`` of the whole adjustment.

A factor is in *variance*: ``s_k = 4`` says that the stated covariance is 4x too small, i.e. the
stated standard deviations are 2x too small. Its standard deviation is
``sigma(s_k) = s_k sqrt(2 / r_k)`` (the group's ``v' P v`` is ``s_k chi2(r_k)``). A group whose
redundancy is below ``min_redundancy`` is *poorly determined*: its factor is not estimated and
stays 1 (its stated covariance is used as it is). A factor that does not differ significantly
from 1 (by more than ``significance`` of its sigmas) is reported but not applied: where no
factor is significant, the solution is the one with the stated covariances, bit for bit.

With a single group the estimate is the global variance factor ``sigma0^2`` and the solution
does not change (only the covariances scale); with several, the relative weights change and
with them the solution: two sources stated with the same covariance but of different noise are
weighted by their own noise.

Two sources measuring the same motions and nothing else show only the sum of their variances;
the ``split`` of :func:`solve_with_variance_components` (each source's own consistency,
:mod:`ga_ros.core.quality.source_consistency`) ties them to one scale with its ratios.

References: W. Förstner, *Ein Verfahren zur Schätzung von Varianz- und Kovarianzkomponenten*,
AVN 86, 1979; K.-R. Koch, *Parameter Estimation and Hypothesis Testing in Linear Models*,
Springer 1999; P.J.G. Teunissen, A.R. Amiri-Simkooei, *Least-squares variance component
estimation*, J. Geodesy 82, 2008.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import models
from ga_ros.core.measurement import Measurement, source_or_group, variance_group
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.quality.cofactors import inverse_blocks
from ga_ros.core.quality.control import connection_redundancy
from ga_ros.core.quality.source_consistency import SourceConsistency
from ga_ros.core.solver import (
    GaussianPrior,
    SolverConfig,
    SolveResult,
    information_rank,
    normal_matrix_at,
    solve,
)
from ga_ros.errors import InputError


@dataclass(frozen=True)
class VarianceComponentConfig:
    """Settings of the variance-component estimation.

    Attributes
    ----------
    max_iterations : adjustments with re-estimated weights at most (>= 1).
    tolerance : stop when every estimated group's ``v_k' P_k v_k / r_k`` is within this
        fraction of 1 (the factors agree with the residuals they give).
    min_redundancy : a group with less redundancy ``r_k`` is not estimated (factor 1).
    factor_bounds : the factors are clipped to this range (a group with a nearly zero residual
        would otherwise get an infinite weight).
    significance : a factor is applied only where it differs from 1 by more than this many of
        its sigmas; where none does, the result is the adjustment with the stated covariances
        (bit for bit).
    apply : use the significant factors in the returned solution; ``False``: estimate and
        report them only (the solution is the one with the stated covariances).
    warn_ratio : a factor above ``warn_ratio`` or below ``1 / warn_ratio`` that is significant
        (more than ``warn_sigmas`` of its standard deviation from 1) is named in a warning.
    warn_sigmas : see ``warn_ratio``.
    """

    max_iterations: int = 30
    tolerance: float = 0.005
    min_redundancy: float = 10.0
    factor_bounds: tuple[float, float] = (1e-4, 1e4)
    significance: float = 3.0
    apply: bool = True
    warn_ratio: float = 2.0
    warn_sigmas: float = 3.0

    def __post_init__(self) -> None:
        if int(self.max_iterations) < 1:
            raise InputError('variance components: max_iterations must be >= 1')
        if not self.tolerance > 0 or not self.min_redundancy >= 0:
            raise InputError('variance components: tolerance must be > 0 and min_redundancy '
                             '>= 0')
        lo, hi = self.factor_bounds
        if not 0 < lo < 1 < hi:
            raise InputError('variance components: factor_bounds must be (lo, hi) with '
                             '0 < lo < 1 < hi')


@dataclass(frozen=True)
class VarianceComponent:
    """The estimated variance factor of one group of observations.

    Attributes
    ----------
    group : the group's name (a source: ``odom0``, ``cross``, ``fixes``, ...).
    factor : estimated variance / stated variance (1: the stated covariances are right; 4:
        they are 4x too small, the stated sigmas 2x). 1 when not estimated.
    redundancy : ``r_k``, the group's share of the redundancy (its degrees of freedom) in the
        last adjustment.
    sigma : standard deviation of ``factor``, ``factor sqrt(2 / r_k)`` (inf when ``r_k = 0``).
    observations : connections (or priors) in the group.
    estimated : ``redundancy >= min_redundancy``: the factor was estimated.
    significant : estimated and different from 1 by more than ``significance`` of its sigmas.
    applied : significant and applied (``apply``): the solution and its covariances use it
        (else the stated covariance).
    """

    group: str
    factor: float
    redundancy: float
    sigma: float
    observations: int
    estimated: bool
    significant: bool = True
    applied: bool = True

    def as_dict(self) -> dict:
        """Plain JSON-ready numbers (``summary.json``'s ``variance_components``)."""
        return {'factor': float(self.factor), 'dof': float(self.redundancy),
                'sigma': float(self.sigma), 'observations': int(self.observations),
                'estimated': bool(self.estimated), 'significant': bool(self.significant),
                'applied': bool(self.applied)}


@dataclass(frozen=True)
class VarianceComponents:
    """The variance factors of every group, and how the estimation ended.

    Attributes
    ----------
    components : one per group, in order of first appearance (connections, then priors).
    iterations : adjustments made.
    converged : every estimated group's ``v_k' P_k v_k / r_k`` was within ``tolerance`` of 1
        in the last adjustment.
    config : the settings.
    """

    components: tuple[VarianceComponent, ...]
    iterations: int
    converged: bool
    config: VarianceComponentConfig = field(default_factory=VarianceComponentConfig)

    def factor(self, group: str) -> float:
        """The factor of ``group`` (1 for an unknown group)."""
        return next((c.factor for c in self.components if c.group == group), 1.0)

    def as_dict(self) -> dict:
        """``{group: {factor, dof, sigma, observations, estimated, significant, applied}}``
        plus ``iterations`` and ``converged`` under ``'_estimation'``."""
        out: dict = {c.group: c.as_dict() for c in self.components}
        out['_estimation'] = {'iterations': int(self.iterations),
                              'converged': bool(self.converged)}
        return out

    def warnings(self) -> list[str]:
        """One line per group whose factor is far from 1 (see
        :class:`VarianceComponentConfig`), saying by how much its stated covariance is off."""
        cfg = self.config
        out = []
        for c in self.components:
            if not c.significant or not np.isfinite(c.sigma):
                continue
            far = c.factor >= cfg.warn_ratio or c.factor <= 1.0 / cfg.warn_ratio
            if not far or abs(c.factor - 1.0) <= cfg.warn_sigmas * c.sigma:
                continue
            ratio = c.factor if c.factor > 1 else 1.0 / c.factor
            how = 'small' if c.factor > 1 else 'large'
            out.append(f"{c.group}'s stated covariance is {ratio:.3g}x too {how} (its sigmas "
                       f'{np.sqrt(ratio):.3g}x; variance factor {c.factor:.3g} +- '
                       f'{c.sigma:.2g}, {c.redundancy:.0f} dof)')
        return out


def damped_factor(cost: FloatArray, redundancy: FloatArray, prior_dof: float,
                  bounds: tuple[float, float]) -> FloatArray:
    """The variance factor of a group from its residuals, damped while it is poorly determined:
    Förstner's estimate ``C / R`` (``C = v' S^-1 v`` the weighted squared residuals under the
    *stated* covariances ``S``, ``R`` the redundancy under the weights in use) shrunk towards
    the prior ``s = 1`` of ``prior_dof`` degrees of freedom, in log:

        ``s = (C / R) ^ (R / (R + prior_dof))``

    (``C / R`` clipped to ``bounds`` first; a ratio, so 1/25 is shrunk as little as 25). The
    estimate depends continuously on the residuals and the redundancy, and tends to 1 as the
    redundancy vanishes: a group that loses its redundancy when it is re-weighted (its weight
    grows, its residuals shrink) is pulled back towards its stated covariance instead of
    collapsing to 0. Arrays (or floats) of the same shape; a factor is in variance (4: the
    stated covariance is 4x too small)."""
    lo, hi = bounds
    R = np.asarray(redundancy, dtype=float)
    raw = np.clip(np.asarray(cost, dtype=float) / np.maximum(R, 1e-300), lo, hi)
    return np.exp(np.log(raw) * R / np.maximum(R + prior_dof, 1e-300))


def factor_sigma(factor: FloatArray, dof: FloatArray) -> FloatArray:
    """Standard deviation of a variance factor estimated with ``dof`` degrees of freedom:
    ``factor sqrt(2 / dof)`` (``v' P v`` is ``factor chi2(dof)``); inf where ``dof <= 0``."""
    d = np.asarray(dof, dtype=float)
    return np.where(d > 0, np.asarray(factor, float) * np.sqrt(2.0 / np.maximum(d, 1e-300)),
                    np.inf)


def scaled_network(network: ConnectionNetwork, scale: FloatArray) -> ConnectionNetwork:
    """A copy of ``network`` with every connection's covariance multiplied by ``scale`` (m,)."""
    conn = network.arrays()
    return ConnectionNetwork.from_arrays(network.node_ids, network.track_ids, conn.src,
                                         conn.dst, conn.z, conn.cov * scale[:, None, None])


def scaled_prior(prior: GaussianPrior, factor: float) -> GaussianPrior:
    """``prior`` with its covariance multiplied by ``factor`` (its information divided)."""
    return replace(prior, information=prior.information / factor)


def solve_with_variance_components(
        network: ConnectionNetwork, T_init: FloatArray, groups: Sequence[str],
        solver_config: SolverConfig | None = None, fixed: Sequence[int] | None = None,
        priors: Sequence[GaussianPrior] = (), prior_groups: Sequence[str] = (),
        config: VarianceComponentConfig | None = None,
        split: Mapping[str, tuple[float, float]] | None = None
        ) -> tuple[SolveResult, VarianceComponents]:
    """Adjust with the variance factor of every group estimated (module doc).

    Parameters
    ----------
    network : the connections, each with its stated covariance ``[x y z rx ry rz]``.
    T_init : (n, 4, 4) initial poses ``T_world_node`` (network index order).
    groups : (m,) group name of every connection, in network connection order.
    solver_config, fixed : as for :func:`ga_ros.core.solver.solve`.
    priors : weighted parameters (absolute fixes, ...), with their stated information.
    prior_groups : group name of every prior (same length as ``priors``); a name may be shared
        with connections' groups (they then get one factor).
    config : settings.
    split : ``{group: (factor, dof)}``, each source's own consistency against the other
        sources measuring the same motions (:mod:`ga_ros.core.quality.source_consistency`).
        The groups named share one estimated scale ``lambda`` and keep these factors' ratios
        (``s_k = lambda f_k``; ``lambda <- lambda sum_k v_k' P_k v_k / sum_k r_k`` over them):
        two sources measuring the same motions and nothing else give residuals that determine
        only the sum of their variances, never its split, so the simple iteration would drift
        along the undetermined ratio. Their sigma is ``s_k sqrt(2 / sum_k r_k + 2 / dof_k)``.

    Returns
    -------
    The solution with the applied factors (its covariances, ``result.covariance``, are those
    of the scaled weights; with none applied, the adjustment with the stated covariances) and
    the factors.

    Raises
    ------
    InputError
        ``groups`` / ``prior_groups`` do not match the connections / priors.
    DegenerateGeometryError, SolverError
        As :func:`~ga_ros.core.solver.solve`.
    """
    cfg = config or VarianceComponentConfig()
    scfg = solver_config or SolverConfig()
    m = network.n_connections
    labels = np.asarray([str(g) for g in groups], dtype=object)
    p_labels = [str(g) for g in prior_groups]
    if labels.shape != (m,):
        raise InputError(f'variance components: {labels.size} group names for {m} connections')
    if len(p_labels) != len(priors):
        raise InputError(f'variance components: {len(p_labels)} group names for '
                         f'{len(priors)} priors')
    names = list(dict.fromkeys(list(labels) + p_labels))
    conn_index = np.array([names.index(g) for g in labels], dtype=np.int64)
    prior_index = np.array([names.index(g) for g in p_labels], dtype=np.int64)
    lo, hi = cfg.factor_bounds
    split = dict(split or {})
    tied = np.array([g in split for g in names], dtype=bool)
    split_dof = np.array([float(split[g][1]) if g in split else np.inf for g in names])
    factor = np.clip([float(split[g][0]) if g in split else 1.0 for g in names], lo, hi)
    stated_first = bool(np.all(factor == 1.0))
    T = np.asarray(T_init, dtype=float)
    history: list[FloatArray] = []
    converged = False
    iterations = 0
    first: SolveResult | None = None
    while True:
        net = scaled_network(network, factor[conn_index])
        pri = [scaled_prior(p, 1.0 if p.weak else factor[k])
               for p, k in zip(priors, prior_index)]
        res = solve(net, T, scfg, fixed=fixed, priors=pri)
        if stated_first:
            first = first or res   # with the stated covariances
        T = res.T_world_node
        iterations += 1
        cost, red = group_redundancy(net, res, pri, conn_index, prior_index, len(names))
        estimated = red >= max(cfg.min_redundancy, 1e-9)
        ratio = np.ones(len(names))
        ratio[estimated] = cost[estimated] / red[estimated]
        if tied.any():  # the tied groups: one scale, pooled
            estimated[tied] = red[tied].sum() >= max(cfg.min_redundancy, 1e-9)
            ratio[tied] = cost[tied].sum() / max(red[tied].sum(), 1e-300)
        if not estimated.any() or np.abs(ratio[estimated] - 1.0).max() < cfg.tolerance:
            converged = True
            break
        if iterations >= cfg.max_iterations:
            break
        factor = np.where(estimated, np.clip(factor * ratio, lo, hi),
                          np.where(tied, factor, 1.0))
        history.append(np.log(factor))
        if len(history) == 3:
            factor = np.clip(np.exp(_aitken(*history)), lo, hi)
            history = [np.log(factor)]
    dof = np.where(tied, red[tied].sum() if tied.any() else 0.0, red)
    sigma = np.where(dof > 0, factor * np.sqrt(2.0 / np.maximum(dof, 1e-300)
                                               + 2.0 / split_dof), np.inf)
    significant = estimated & (np.abs(factor - 1.0) > cfg.significance * sigma)
    applied = significant & cfg.apply
    if not applied.any() and first is not None:
        res = first   # every stated covariance stands: the adjustment with them
    elif not applied.any():  # from the initial poses: the adjustment with them, bit for bit
        res = solve(network, np.asarray(T_init, dtype=float), scfg, fixed=fixed,
                    priors=list(priors))
        iterations += 1
    elif (applied != estimated).any():
        use = np.where(applied, factor, 1.0)
        res = solve(scaled_network(network, use[conn_index]), T, scfg, fixed=fixed,
                    priors=[scaled_prior(p, 1.0 if p.weak else use[k])
                            for p, k in zip(priors, prior_index)])
        iterations += 1
    counts = np.bincount(np.concatenate([conn_index, prior_index]), minlength=len(names))
    comps = tuple(
        VarianceComponent(
            group=g, factor=float(factor[k]), redundancy=float(red[k]), sigma=float(sigma[k]),
            observations=int(counts[k]), estimated=bool(estimated[k]),
            significant=bool(significant[k]), applied=bool(applied[k]))
        for k, g in enumerate(names))
    return res, VarianceComponents(comps, iterations, converged, cfg)


def _aitken(x0: FloatArray, x1: FloatArray, x2: FloatArray) -> FloatArray:
    """Aitken's extrapolation of three successive iterates (log factors) to the fixed point,
    each step limited to 5x the last one (the simple iteration converges linearly, slowly
    where two groups are hard to tell apart)."""
    d1, d2 = x1 - x0, x2 - x1
    den = d2 - d1
    ok = np.abs(den) > 1e-12
    step = np.where(ok, -d2 * d2 / np.where(ok, den, 1.0), 0.0)
    return x2 + np.clip(step, -5.0 * np.abs(d2), 5.0 * np.abs(d2))


def group_redundancy(network: ConnectionNetwork, result: SolveResult,
                     priors: Sequence[GaussianPrior], conn_index: np.ndarray,
                     prior_index: np.ndarray, n_groups: int) -> tuple[FloatArray, FloatArray]:
    """Per group: the weighted squared residuals ``v_k' P_k v_k`` and the redundancy ``r_k``.

    ``network`` and ``priors`` carry the weights the adjustment ``result`` used. The
    connections' redundancy numbers are those of :func:`~ga_ros.core.quality.quality_control`
    (:func:`~ga_ros.core.quality.control.connection_redundancy`);
    a prior's redundancy is ``rank(N_p) - tr(Q_x N_p)`` with ``N_p`` its part of the normal
    matrix (``Q_x = N^-1`` on ``N_p``'s block pattern, from the sparse factor).

    Returns
    -------
    (n_groups,) costs and (n_groups,) redundancies.
    """
    conn = network.arrays()
    v = result.residuals
    Pv = np.linalg.solve(conn.cov, v[:, :, None])[:, :, 0]
    cost = np.bincount(conn_index, weights=np.einsum('mi,mi->m', v, Pv), minlength=n_groups)
    red = np.bincount(conn_index, weights=connection_redundancy(network, result, priors),
                      minlength=n_groups)
    if priors:
        p_cost, p_red = prior_redundancy(network, result, priors)
        cost += np.bincount(prior_index, weights=p_cost, minlength=n_groups)
        red += np.bincount(prior_index, weights=p_red, minlength=n_groups)
    return cost, red


def prior_redundancy(network: ConnectionNetwork, result: SolveResult,
                     priors: Sequence[GaussianPrior]) -> tuple[FloatArray, FloatArray]:
    """Per prior: its weighted squared residual ``e' N_p e`` and its redundancy
    ``rank(N_p) - tr(Q_x N_p)`` at the solution ``result`` (which used these ``priors``); 0 and
    0 for a datum prior (:attr:`GaussianPrior.weak
    <ga_ros.core.solver.priors.GaussianPrior.weak>`: no observation, never scaled).

    ``N_p`` is the prior's part of the normal matrix over the free nodes (the difference of the
    normal matrices with and without it), ``Q_x`` the inverse of the whole one.
    """
    model, T = result.model, result.T_world_node
    d = models.dof(model)
    free_ids = result.free_node_ids
    fixed = np.setdiff1d(network.node_ids, free_ids)
    N_all, ids, _ = normal_matrix_at(network, T, model, fixed=fixed, priors=priors)
    N_conn, _, _ = normal_matrix_at(network, T, model, fixed=fixed)
    cost = np.zeros(len(priors))
    red = np.zeros(len(priors))
    parts = []
    for k, p in enumerate(priors):
        idx = network.indices_of(p.node_ids)
        e, _ = models.prior_residual(model, T[idx], np.asarray(p.T_world_node, dtype=float))
        ev = e.reshape(-1)
        cost[k] = float(ev @ (p.information @ ev))
        N_with, _, _ = normal_matrix_at(network, T, model, fixed=fixed, priors=[p])
        N_p = sp.bsr_matrix((N_with - N_conn).tocsr(), blocksize=(d, d))
        N_p.eliminate_zeros()
        N_p.sort_indices()
        rank = p.rank if p.rank is not None else information_rank(p.information, d)
        parts.append((k, N_p, rank))
    rows = [np.repeat(np.arange(Np.shape[0] // d), np.diff(Np.indptr)) for _, Np, _ in parts]
    cols = [Np.indices.astype(np.int64) for _, Np, _ in parts]
    if ids.size:
        Q = inverse_blocks(N_all, d, np.concatenate(rows), np.concatenate(cols))
    start = 0
    for (k, N_p, rank), r in zip(parts, rows):
        n_b = r.size
        trace = float(np.sum(Q[start:start + n_b] * N_p.data)) if n_b else 0.0
        red[k] = rank - trace
        start += n_b
    weak = np.array([bool(p.weak) for p in priors], dtype=bool)
    cost[weak] = red[weak] = 0.0
    return cost, red


class SourceGroups:
    """The variance group of every measurement given to an aligner
    (:func:`ga_ros.core.measurement.variance_group`), found again by the connection's identity
    (its two node ids and its measured motion, bit for bit).

    Parameters
    ----------
    unknown : the group of a connection that was never recorded.
    """

    def __init__(self, unknown: str = 'motion') -> None:
        self.unknown = unknown
        self._by: dict[tuple[int, int, bytes], str] = {}
        #: the source of the connections that have one and a group other than it (a named
        #: source's cross-track connections)
        self._source: dict[tuple[int, int, bytes], str] = {}
        #: each source's own consistency against the others measuring the same motions
        self.consistency = SourceConsistency(keep=4096)

    def add(self, m: Measurement) -> None:
        """Record the group of one measurement (and its source's consistency)."""
        key = _key(m.src_id, m.dst_id, m.z)
        self._by[key] = group = variance_group(m)
        if source_or_group(m) != group:
            self._source[key] = m.source
        self.consistency.add(m)

    def split(self) -> dict[str, tuple[float, float]]:
        """:func:`solve_with_variance_components`'s ``split``: each source's consistency
        factor and dof, where it has 10 terms."""
        return self.consistency.split(min_terms=10)

    def __len__(self) -> int:
        return len(self._by)

    def source_names(self) -> list[str]:
        """The sources of the recorded measurements, sorted (a connection without a source
        by its group: ``motion``, ``cross``, ``bridge``)."""
        return sorted(set(self._source.values())
                      | {g for k, g in self._by.items() if k not in self._source})

    def of(self, src_ids: IntArray, dst_ids: IntArray, z: FloatArray) -> list[str]:
        """The groups of connections given by node ids ``(m,)`` and motions ``(m, 6)``."""
        return [self._by.get(_key(a, b, zz), self.unknown)
                for a, b, zz in zip(np.asarray(src_ids).tolist(), np.asarray(dst_ids).tolist(),
                                    np.asarray(z, dtype=float).reshape(-1, 6))]

    def sources(self, src_ids: IntArray, dst_ids: IntArray, z: FloatArray) -> list[str]:
        """As :meth:`of`, the source of each connection where it has one
        (:func:`~ga_ros.core.measurement.source_or_group`: a camera's cross-track connections
        are its own, ``cam0``, not their group ``cam0.cross``), else its group."""
        keys = [_key(a, b, zz) for a, b, zz in zip(
            np.asarray(src_ids).tolist(), np.asarray(dst_ids).tolist(),
            np.asarray(z, dtype=float).reshape(-1, 6))]
        return [self._source.get(k) or self._by.get(k, self.unknown) for k in keys]


def _key(src_id: int, dst_id: int, z: FloatArray) -> tuple[int, int, bytes]:
    return int(src_id), int(dst_id), np.ascontiguousarray(z, dtype=np.float64).tobytes()
