"""Quality control of one adjustment (:func:`quality_control`), and a solve that carries it
(:func:`checked_solve`). The formulas are in :mod:`ga_ros.core.quality`."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy.sparse as sp

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import models
from ga_ros.core.network import ConnectionArrays, ConnectionNetwork
from ga_ros.core.quality.cofactors import normal_matrix, propagate, sigma_blocks
from ga_ros.core.quality.config import QualityConfig
from ga_ros.core.quality.reliability import (
    connection_tests,
    outside_tests,
    redundancy_numbers,
    w_tests,
)
from ga_ros.core.quality.report import QualityReport
from ga_ros.core.quality.variance_factor import global_cost, global_test
from ga_ros.core.solver import GaussianPrior, SolverConfig, SolveResult, solve
from ga_ros.errors import InputError


@dataclass(frozen=True)
class _Cofactors:
    """The adjustment linearised at the solution, and the blocks of ``Q_x = N^-1`` it needs.

    Attributes
    ----------
    lin : per-connection ``A``, ``B`` and misclosure at ``(l0 = l_b + v, x)``.
    Linv : (m, r_c, r_c) inverse of the Cholesky factor of ``M = B S B'``.
    cs, cd : (m,) unknown (column) index of each connection's source / destination (-1: fixed).
    ocs, ocd : (k,) the same for the connections outside the adjustment.
    Sigma : blocks of ``Q_x`` on the connected pairs (3 m: ``[Q_ss; Q_sd; Q_dd]``), the outside
        pairs (3 k) and the priors' pattern, in that order.
    prior_blocks : the priors' part of ``N`` as a block matrix (``None`` without priors).
    """

    lin: models.Linearisation
    Linv: FloatArray
    cs: IntArray
    cd: IntArray
    ocs: IntArray
    ocd: IntArray
    Sigma: FloatArray
    prior_blocks: sp.bsr_matrix | None


def quality_control(network: ConnectionNetwork, result: SolveResult,
                    priors: Sequence[GaussianPrior] = (),
                    config: QualityConfig | None = None,
                    outside: ConnectionArrays | None = None) -> QualityReport:
    """Global test, redundancy numbers, w-tests, connection tests and MDBs of an adjustment.

    Parameters
    ----------
    network : the connections that were adjusted (same order as ``result.residuals``).
    result : the solution (:func:`ga_ros.core.solver.solve`); its estimate, residuals ``v`` and
        datum (free nodes) are used; ``N`` is re-assembled at the estimate with unit weights.
    priors : the weighted parameters the solution used (they count in ``r - u``).
    config : test settings.
    outside : optional connections that are *not* in the adjustment (node indices of
        ``network``), to be tested against it (e.g. for re-admission): the predicted misclosure
        ``w_o = f(l_b, x)`` has covariance ``M_o + A_o Q_x A_o'`` under H0, so
        ``T_o = w_o' (M_o + A_o Q_x A_o')^-1 w_o ~ chi2(r_c)``; the report's
        ``outside_statistic`` and ``outside_critical`` hold ``T_o`` and its B-method critical
        value.

    Returns
    -------
    QualityReport

    Raises
    ------
    InputError
        The result does not belong to the network.
    DegenerateGeometryError
        Singular normal matrix.
    """
    cfg = config or QualityConfig()
    conn = network.arrays()
    m = len(conn)
    if result.residuals.shape != (m, 6) or result.T_world_node.shape[0] != network.n_nodes:
        raise InputError('the result does not belong to this network (different connection or '
                         'node count); pass the network that was solved')
    model, T, v = result.model, result.T_world_node, result.residuals
    cf = _cofactors(network, result, priors, outside)
    B = cf.lin.B
    r_c = cf.lin.f.shape[1]
    G = propagate(cf.lin.A_src, cf.lin.A_dst, cf.cs, cf.cd, cf.Sigma[:3 * m])
    Qw, Q_kk, red_comp, red = redundancy_numbers(conn.cov, B, cf.Linv, G, r_c)
    # P v = B' k
    Pv = np.linalg.solve(conn.cov, v[:, :, None])[:, :, 0]
    lam0 = cfg.lambda0
    w, mdb = w_tests(conn.cov, B, Q_kk, Pv, lam0)
    stat, q, crit = connection_tests(cf.Linv, B, v, Qw, lam0, cfg.power)

    # global test
    cost, n_eq = global_cost(network, model, T, v, Pv, priors, m * r_c)
    redundancy = n_eq - result.free_node_ids.size * models.dof(model)
    if any(getattr(p, 'weak', False) for p in priors):
        # a datum prior counts by tr(Q H), not its rank (GaussianPrior.weak; the solver's)
        redundancy = result.redundancy
    n_out = cf.ocs.size
    out_stat = np.zeros(0)
    out_crit = np.zeros(0)
    if n_out:
        out_stat, out_crit = outside_tests(model, T, outside, cf.ocs, cf.ocd,
                                           cf.Sigma[3 * m:3 * m + 3 * n_out], r_c, lam0,
                                           cfg.power)
    prior_red = 0.0
    if cf.prior_blocks is not None:
        # r_prior = k d - tr(Q_x N_prior) = k d - sum of Sigma .* N_prior over its pattern
        S_p = cf.Sigma[3 * (m + n_out):]
        prior_red = n_eq - m * r_c - float(np.sum(S_p * cf.prior_blocks.data))
    sigma0_sq, g_crit, passed = global_test(cost, redundancy, cfg.alpha)
    return QualityReport(
        model=model, cost=cost, redundancy=redundancy, sigma0_sq=float(sigma0_sq),
        global_critical=g_crit, global_passed=passed,
        redundancy_numbers=red, redundancy_components=red_comp, prior_redundancy=prior_red,
        w=w, connection_statistic=stat, connection_dof=q, connection_critical=crit, mdb=mdb,
        lambda0=lam0, w_critical=cfg.w_critical, config=cfg, outside_statistic=out_stat,
        outside_critical=out_crit)


def connection_redundancy(network: ConnectionNetwork, result: SolveResult,
                          priors: Sequence[GaussianPrior] = ()) -> FloatArray:
    """(m,) the redundancy numbers ``r_i = tr((Q_vv P)_ii)`` of the connections alone (as
    :func:`quality_control` computes them, without its tests)."""
    conn = network.arrays()
    m = len(conn)
    if result.residuals.shape != (m, 6) or result.T_world_node.shape[0] != network.n_nodes:
        raise InputError('the result does not belong to this network (different connection or '
                         'node count); pass the network that was solved')
    cf = _cofactors(network, result, priors, None)
    G = propagate(cf.lin.A_src, cf.lin.A_dst, cf.cs, cf.cd, cf.Sigma[:3 * m])
    return redundancy_numbers(conn.cov, cf.lin.B, cf.Linv, G, cf.lin.f.shape[1])[3]


def _cofactors(network: ConnectionNetwork, result: SolveResult,
               priors: Sequence[GaussianPrior], outside: ConnectionArrays | None) -> _Cofactors:
    """Linearise at the solution, assemble ``N`` with unit weights and take the blocks of
    ``N^-1`` that the tests need (:class:`_Cofactors`)."""
    conn = network.arrays()
    model, T = result.model, result.T_world_node
    d = models.dof(model)
    free_ids = result.free_node_ids
    fixed = np.setdiff1d(network.node_ids, free_ids)
    col = np.full(network.n_nodes, -1, dtype=np.int64)
    col[network.indices_of(free_ids)] = np.arange(free_ids.size)

    # per-connection A, B, M at (l0 = l_b + v, x)
    lin = models.linearise(model, T, conn.src, conn.dst, conn.z, result.residuals)
    B = lin.B
    M = B @ conn.cov @ np.swapaxes(B, 1, 2)
    L = np.linalg.cholesky(M)
    Linv = np.linalg.inv(L)
    cs, cd = col[conn.src], col[conn.dst]
    As = np.where((cs >= 0)[:, None, None], lin.A_src, 0.0)
    Ad = np.where((cd >= 0)[:, None, None], lin.A_dst, 0.0)
    N_all, N_prior = normal_matrix(network, T, model, fixed, free_ids, priors, As, Ad, Linv,
                                   cs, cd, d)
    n_out = 0 if outside is None else len(outside)
    empty = np.zeros(0, dtype=np.int64)
    ocs, ocd = (col[outside.src], col[outside.dst]) if n_out else (empty, empty)
    Sigma, bsr = sigma_blocks(N_all, N_prior, d, cs, cd, ocs, ocd)
    return _Cofactors(lin, Linv, cs, cd, ocs, ocd, Sigma, bsr)


def checked_solve(network: ConnectionNetwork, T_init: FloatArray,
                  solver_config: SolverConfig | None = None,
                  fixed: Sequence[int] | None = None,
                  priors: Sequence[GaussianPrior] = (),
                  config: QualityConfig | None = None) -> SolveResult:
    """:func:`ga_ros.core.solver.solve` followed by :func:`quality_control`: the returned result
    carries the :class:`QualityReport` in ``result.quality`` (parameters as for ``solve``;
    ``config``: the test settings)."""
    res = solve(network, T_init, solver_config, fixed=fixed, priors=priors)
    return replace(res, quality=quality_control(network, res, priors, config))
