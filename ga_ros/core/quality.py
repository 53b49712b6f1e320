"""Statistical quality control of an adjustment (Baarda's testing and reliability theory).

Given a network, the solution of :func:`ga_ros.core.solver.solve` and the priors it used, this
module computes, for the mixed (Gauss-Helmert) model of METHOD.md Sec. 2:

* the **global test** of the variance factor (Koch 1999, Sec. 4.3; Leick, *GPS Satellite
  Surveying*, Sec. 4.9): ``T = v' P v / sigma_prior^2 ~ chi2(r - u)`` under ``H0``;
  rejected when ``T > chi2_{1-alpha}(r - u)`` (``sigma_prior = 1``: the covariances are
  taken as given);
* the **redundancy numbers** (Baarda 1968; Teunissen, *Testing Theory*, Sec. 4): the diagonal
  blocks of ``R = Q_vv P``. With ``M = B S B'``, ``G_i = A_i Q_x A_i'`` and
  ``Q_kk = M^-1 (M - A Q_x A') M^-1`` (cofactor of the Lagrange multipliers ``k``),
  the block of connection ``i`` is ``R_ii = S_i B_i' Q_kk,ii B_i`` and its trace is
  ``r_i = tr(I - M_i^-1 G_i)``. They sum to the redundancy ``r - u`` over connections and
  weighted parameters (priors). Only the blocks of ``Q_x = N^-1`` on connected node pairs are
  needed; they come from sparse solves with the Cholesky factor of ``N``, never a dense inverse;
* **standardised residuals and the w-test** (Baarda's data snooping, for correlated
  observations: Teunissen, Sec. 4.4): ``w_j = (P v)_j / sqrt((P Q_vv P)_jj)`` with
  ``P Q_vv P = B' Q_kk B``; ``w_j ~ N(0, 1)`` under ``H0``, critical value
  ``z_{1-alpha0/2}``;
* the **multi-dimensional test of a whole connection** (Teunissen, Sec. 4.3, ``q``-dimensional
  bias ``C_q nabla`` with ``C_q`` the connection's equations): ``T_i = k_i' Q_kk,ii^+ k_i``,
  ``chi2(q_i)`` under ``H0`` with ``q_i = rank(Q_kk,ii)`` (``q_i < r_c`` for a connection whose
  redundancy is partly zero; a bridge, ``r_i = 0``, cannot be tested);
* the **B-method** of testing (Baarda 1968): ``lambda0`` is the non-centrality that the 1-D
  test of level ``alpha0`` detects with power ``gamma0`` (Baarda's ``beta0``, default 0.80);
  the ``q``-dimensional test uses the level ``alpha_q`` that detects the same ``lambda0`` with
  the same power;
* the **minimal detectable bias** (internal reliability) of every observation component:
  ``|nabla_j| = sqrt(lambda0 / (P Q_vv P)_jj)`` (observation units, m or rad);
* **iterative data snooping** (:func:`data_snooping`): adjust, test every connection, remove the
  one with the largest test ratio, re-adjust (with :func:`ga_ros.core.solver.solve`) and repeat
  until no test rejects.

References: W. Baarda, *A testing procedure for use in geodetic networks*, Netherlands
Geodetic Commission, 1968; P.J.G. Teunissen, *Testing Theory*, Delft, 2000/2006;
E.M. Mikhail, *Observations and Least Squares*, 1976 (Ch. 5 and 9, the general model);
A. Leick, *GPS Satellite Surveying*, Ch. 4 (quality control).

The quality figures are those of the *least-squares* adjustment: a result solved with a robust
loss is re-assessed with unit weights.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, field, replace
from functools import lru_cache

import numpy as np
import scipy.sparse as sp
from scipy.optimize import brentq
from scipy.stats import chi2, ncx2, norm

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core import models
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.network import ConnectionArrays, ConnectionNetwork
from ga_ros.core.solver import GaussianPrior, SolverConfig, SolveResult, normal_matrix_at, solve
from ga_ros.errors import InputError, SolverError

#: Eigenvalues of the whitened ``Q_kk`` block below this count as zero redundancy.
_RANK_TOL = 1e-6
#: Node columns of ``N^-1`` solved for at a time (bounds the memory to ``n x (chunk d)``).
_CHUNK = 128
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
        return float(norm.isf(self.alpha0 / 2.0))


@lru_cache(maxsize=256)
def noncentrality(alpha: float, power: float, q: int) -> float:
    """``lambda`` such that a ``chi2(q)`` test of level ``alpha`` rejects ``chi2'(q, lambda)``
    with probability ``power`` (Baarda's ``lambda0(alpha0, beta0, q)``)."""
    c = chi2.isf(alpha, q)
    return float(brentq(lambda lam: ncx2.sf(c, q, lam) - power, 1e-9, 1e4, xtol=1e-12))


@lru_cache(maxsize=256)
def b_method_alpha(lambda0: float, power: float, q: int) -> float:
    """Level ``alpha_q`` of a ``q``-dimensional test that detects ``lambda0`` with ``power``
    (the B-method: every test is as sensitive as the 1-D w-test)."""
    def excess(log_alpha: float) -> float:
        return float(ncx2.sf(chi2.isf(np.exp(log_alpha), q), q, lambda0)) - power

    return float(np.exp(brentq(excess, np.log(1e-15), np.log(0.999), xtol=1e-12)))


@dataclass
class QualityReport:
    """Quality figures of one adjustment, per connection in network connection order.

    Attributes
    ----------
    model : constraint model of the adjustment.
    cost : ``v' P v`` over connections plus the prior terms (the global test statistic,
        ``sigma_prior = 1``).
    redundancy : ``r - u`` (equations of connections and priors minus unknowns).
    sigma0_sq : a-posteriori variance factor ``cost / (r - u)``.
    global_critical : ``chi2_{1-alpha}(r - u)``.
    global_passed : ``cost <= global_critical``.
    redundancy_numbers : (m,) ``r_i = tr((Q_vv P)_ii)`` per connection, in [0, r_c].
    redundancy_components : (m, 6) diagonal of ``(Q_vv P)_ii`` per observation component
        ``[x y z rx ry rz]``.
    prior_redundancy : redundancy of the weighted parameters (priors); with the connections'
        it sums to ``r - u``.
    w : (m, 6) Baarda's w-statistics of the observation components (0 where untestable).
    connection_statistic : (m,) ``T_i = k_i' Q_kk,ii^+ k_i`` (chi2(q_i) under H0; NaN when
        ``q_i = 0``).
    connection_dof : (m,) ``q_i``, rank of the connection's ``Q_kk`` block.
    connection_critical : (m,) ``chi2_{1-alpha_q}(q_i)`` (B-method level for ``q_i``).
    mdb : (m, 6) minimal detectable bias per observation component (m, rad; inf where the
        component has no redundancy).
    lambda0, w_critical : the B-method's non-centrality and the w-test's critical value.
    config : the settings.
    outside_statistic, outside_critical : (k,) test of connections outside the adjustment
        (see ``outside`` of :func:`quality_control`); empty when none were given.
    """

    model: str
    cost: float
    redundancy: int
    sigma0_sq: float
    global_critical: float
    global_passed: bool
    redundancy_numbers: FloatArray
    redundancy_components: FloatArray
    prior_redundancy: float
    w: FloatArray
    connection_statistic: FloatArray
    connection_dof: IntArray
    connection_critical: FloatArray
    mdb: FloatArray
    lambda0: float
    w_critical: float
    config: QualityConfig = field(default_factory=QualityConfig)
    outside_statistic: FloatArray = field(default_factory=lambda: np.zeros(0))
    outside_critical: FloatArray = field(default_factory=lambda: np.zeros(0))

    @property
    def w_max(self) -> FloatArray:
        """(m,) largest ``|w|`` of each connection."""
        return np.abs(self.w).max(axis=1) if self.w.size else np.zeros(0)

    def test_ratio(self, test: str | None = None) -> FloatArray:
        """(m,) test statistic over its critical value (> 1: rejected; NaN: untestable)."""
        test = test or self.config.snoop_test
        if test == 'w':
            ratio = self.w_max / self.w_critical
            return np.where(self.redundancy_numbers >= self.config.min_redundancy, ratio, np.nan)
        with np.errstate(invalid='ignore', divide='ignore'):
            ratio = self.connection_statistic / self.connection_critical
        return np.where(self.redundancy_numbers >= self.config.min_redundancy, ratio, np.nan)

    def rejected(self, test: str | None = None) -> BoolArray:
        """(m,) connections whose local test rejects ``H0`` (no gross error)."""
        ratio = self.test_ratio(test)
        return np.nan_to_num(ratio, nan=0.0) > 1.0

    def summary(self) -> dict:
        """Plain numbers for JSON / diagnostics."""
        rn = self.redundancy_numbers
        finite_mdb = self.mdb[np.isfinite(self.mdb)]
        t_mdb = self.mdb[:, :3]
        t_mdb = t_mdb[np.isfinite(t_mdb)]
        ratio = self.test_ratio()
        worst = int(np.nanargmax(ratio)) if np.isfinite(ratio).any() else -1
        return {
            'model': self.model, 'cost': float(self.cost), 'redundancy': int(self.redundancy),
            'sigma0_sq': float(self.sigma0_sq), 'global_alpha': self.config.alpha,
            'global_critical': float(self.global_critical),
            'global_passed': bool(self.global_passed),
            'connections': int(rn.size),
            'redundancy_numbers_sum': float(rn.sum()),
            'prior_redundancy': float(self.prior_redundancy),
            'redundancy_number_min': float(rn.min()) if rn.size else float('nan'),
            'redundancy_number_mean': float(rn.mean()) if rn.size else float('nan'),
            'untestable_connections': int((rn < self.config.min_redundancy).sum()),
            'alpha0': self.config.alpha0, 'power': self.config.power,
            'lambda0': float(self.lambda0), 'w_critical': float(self.w_critical),
            'w_max': float(self.w_max.max()) if rn.size else 0.0,
            'rejected_connections': int(self.rejected().sum()),
            'worst_connection': worst,
            'mdb_translation_median_m': float(np.median(t_mdb)) if t_mdb.size else float('inf'),
            'mdb_max_finite': float(finite_mdb.max()) if finite_mdb.size else float('inf'),
        }


@dataclass(frozen=True)
class QualitySummary:
    """The quality figures of one adjustment that a user reads live (diagnostics, the replay's
    ``summary.json``, :class:`ga_ros.core.window.UpdateResult`).

    Attributes
    ----------
    global_passed : the global test of the variance factor passes (``T <= chi2_{1-alpha}``).
    sigma0_sq : a-posteriori variance factor ``T / (r - u)`` (1 when the covariances are honest).
    redundancy : ``r - u``.
    w_max : largest ``|w|`` over every component of every tested connection (0: none tested).
    w_max_src_id, w_max_dst_id : node ids of the connection with ``w_max`` (-1: none).
    n_w_rejected : tested connections with ``max |w| > w_critical`` (Baarda's w-test).
    w_critical : ``z_{1-alpha0/2}`` (3.29 for ``alpha0 = 0.001``).
    redundancy_number_min : smallest redundancy number ``r_i`` of the tested connections
        (0: a connection no other one checks).
    mdb_median_m, mdb_median_rad : median minimal detectable bias of the tested connections'
        translation (m) and rotation (rad) components (finite ones; inf when none).
    n_tested : connections the figures cover.
    seconds : wall time of the quality control (s).
    """

    global_passed: bool
    sigma0_sq: float
    redundancy: int
    w_max: float
    w_max_src_id: int
    w_max_dst_id: int
    n_w_rejected: int
    w_critical: float
    redundancy_number_min: float
    mdb_median_m: float
    mdb_median_rad: float
    n_tested: int
    seconds: float = 0.0

    def as_dict(self) -> dict:
        """Plain JSON-ready numbers (``summary.json``, ``ga-ros solve --json``)."""
        return {k: (bool(v) if isinstance(v, (bool, np.bool_)) else
                    int(v) if isinstance(v, (int, np.integer)) else float(v))
                for k, v in asdict(self).items()}


def summarise(report: QualityReport, network: ConnectionNetwork,
              tested: BoolArray | None = None, seconds: float = 0.0) -> QualitySummary:
    """The :class:`QualitySummary` of a report, over the connections in ``tested`` (mask in
    network connection order; default every connection).

    The global test and ``sigma0^2`` always belong to the whole adjustment; the per-connection
    figures (``w``, ``r_i``, MDB) are taken over ``tested`` only, e.g. a window's cross-track
    connections. Untestable connections (``r_i < min_redundancy``) count for ``r_i`` but not for
    the w-test.
    """
    m = report.redundancy_numbers.size
    sel = np.ones(m, dtype=bool) if tested is None else np.asarray(tested, dtype=bool)
    if sel.shape != (m,):
        raise InputError(f'tested must be a mask of the {m} connections, got shape {sel.shape}')
    rn = report.redundancy_numbers
    testable = sel & (rn >= report.config.min_redundancy)
    w_max = np.where(testable, report.w_max, 0.0) if m else np.zeros(0)
    src_id = dst_id = -1
    if testable.any():
        k = int(np.argmax(w_max))
        conn = network.arrays()
        src_id, dst_id = int(network.node_ids[conn.src[k]]), int(network.node_ids[conn.dst[k]])
    t_mdb = report.mdb[sel][:, :3]
    r_mdb = report.mdb[sel][:, 3:]
    t_mdb, r_mdb = t_mdb[np.isfinite(t_mdb)], r_mdb[np.isfinite(r_mdb)]
    return QualitySummary(
        global_passed=bool(report.global_passed), sigma0_sq=float(report.sigma0_sq),
        redundancy=int(report.redundancy), w_max=float(w_max.max()) if testable.any() else 0.0,
        w_max_src_id=src_id, w_max_dst_id=dst_id,
        n_w_rejected=int((w_max > report.w_critical).sum()), w_critical=float(report.w_critical),
        redundancy_number_min=float(rn[sel].min()) if sel.any() else float('nan'),
        mdb_median_m=float(np.median(t_mdb)) if t_mdb.size else float('inf'),
        mdb_median_rad=float(np.median(r_mdb)) if r_mdb.size else float('inf'),
        n_tested=int(sel.sum()), seconds=float(seconds))


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


def _normal_matrix(network: ConnectionNetwork, T: FloatArray, model: str, fixed: IntArray,
                   free_ids: IntArray, priors: Sequence[GaussianPrior], As: FloatArray,
                   Ad: FloatArray, Linv: FloatArray, cs: IntArray, cd: IntArray, d: int
                   ) -> tuple[sp.spmatrix, sp.spmatrix | None]:
    """``N = A' M^-1 A`` with unit weights at the solution, plus the priors' part.

    Returns
    -------
    The whole normal matrix and the priors' part (``None`` without priors).
    """
    AsT, AdT = np.swapaxes(As, 1, 2), np.swapaxes(Ad, 1, 2)
    Minv = np.swapaxes(Linv, 1, 2) @ Linv
    N_all = _assemble([AsT @ Minv @ As, AsT @ Minv @ Ad, AdT @ Minv @ As, AdT @ Minv @ Ad],
                      [cs, cs, cd, cd], [cs, cd, cs, cd], d, free_ids.size)
    N_prior = None
    if priors:
        N_with, ids_all, _ = normal_matrix_at(network, T, model, fixed=fixed, priors=priors)
        N_conn, _, _ = normal_matrix_at(network, T, model, fixed=fixed)
        if not np.array_equal(ids_all, free_ids):
            raise SolverError('internal: unknown order of the normal matrix differs')
        N_prior = (N_with - N_conn).tocsr()
        N_prior.eliminate_zeros()
        N_all = (N_all + N_prior).tocsr()
    return N_all, N_prior


def _sigma_blocks(N_all: sp.spmatrix, N_prior: sp.spmatrix | None, d: int, cs: IntArray,
                  cd: IntArray, ocs: IntArray, ocd: IntArray
                  ) -> tuple[FloatArray, sp.bsr_matrix | None]:
    """Blocks of ``Q_x = N^-1`` on the connected pairs, the outside pairs and the prior's
    pattern, in that order; also the prior's part as a block matrix (``None`` without)."""
    pr = [cs, cs, cd]
    pc = [cs, cd, cd]
    if ocs.size:
        pr += [ocs, ocs, ocd]
        pc += [ocs, ocd, ocd]
    bsr = None
    if N_prior is not None:
        bsr = sp.bsr_matrix(N_prior, blocksize=(d, d))
        prow = np.repeat(np.arange(bsr.shape[0] // d), np.diff(bsr.indptr))
        pr.append(prow)
        pc.append(bsr.indices.astype(np.int64))
    return _inverse_blocks(N_all, d, np.concatenate(pr), np.concatenate(pc)), bsr


def _redundancy(cov: FloatArray, B: FloatArray, Linv: FloatArray, G: FloatArray, r_c: int
                ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Whitened ``Qw = I - L^-1 G L^-T``, ``Q_kk`` and the redundancy numbers.

    Returns
    -------
    ``Qw``, ``Q_kk``, the per-component and the per-connection redundancy numbers.
    """
    Qw = np.eye(r_c) - Linv @ G @ np.swapaxes(Linv, 1, 2)
    Qw = 0.5 * (Qw + np.swapaxes(Qw, 1, 2))
    LinvT = np.swapaxes(Linv, 1, 2)
    Q_kk = LinvT @ Qw @ Linv
    BT = np.swapaxes(B, 1, 2)
    R = cov @ BT @ Q_kk @ B  # (Q_vv P)_ii
    red_comp = np.einsum('mjj->mj', R)
    red = np.trace(Qw, axis1=1, axis2=2)
    return Qw, Q_kk, red_comp, red


def _w_tests(cov: FloatArray, B: FloatArray, Q_kk: FloatArray, Pv: FloatArray, lam0: float
             ) -> tuple[FloatArray, FloatArray]:
    """w-test and MDB per observation component (``P Q_vv P = B' Q_kk B``)."""
    BT = np.swapaxes(B, 1, 2)
    var_pv = np.einsum('mjj->mj', BT @ Q_kk @ B)
    scale = np.maximum(np.abs(np.linalg.inv(cov)).max(axis=(1, 2)), 1e-300)
    ok = var_pv > _RANK_TOL * scale[:, None]
    w = np.where(ok, Pv / np.sqrt(np.where(ok, var_pv, 1.0)), 0.0)
    mdb = np.where(ok, np.sqrt(lam0 / np.where(ok, var_pv, 1.0)), np.inf)
    return w, mdb


def _connection_tests(Linv: FloatArray, B: FloatArray, v: FloatArray, Qw: FloatArray,
                      lam0: float, power: float) -> tuple[FloatArray, IntArray, FloatArray]:
    """Connection test ``T = k_w' Qw^+ k_w`` with ``k_w = L^-1 B v``.

    Returns
    -------
    The statistics, their degrees of freedom and B-method critical values.
    """
    kw = (Linv @ (B @ v[:, :, None]))[:, :, 0]
    evals, evecs = np.linalg.eigh(Qw)
    keep = evals > _RANK_TOL
    proj = np.einsum('mji,mj->mi', evecs, kw)
    stat = np.sum(np.where(keep, proj ** 2 / np.where(keep, evals, 1.0), 0.0), axis=1)
    q = keep.sum(axis=1).astype(np.int64)
    stat = np.where(q > 0, stat, np.nan)
    crit = np.full(len(v), np.nan)
    for qq in np.unique(q[q > 0]):
        crit[q == qq] = chi2.isf(b_method_alpha(lam0, power, int(qq)), int(qq))
    return stat, q, crit


def _global_cost(network: ConnectionNetwork, model: str, T: FloatArray, v: FloatArray,
                 Pv: FloatArray, priors: Sequence[GaussianPrior], n_eq: int
                 ) -> tuple[float, int]:
    """The weighted cost ``v' P v`` plus the priors', and the number of equations."""
    cost = float(np.einsum('mi,mi->', v, Pv))
    for p in priors:
        idx = network.indices_of(p.node_ids)
        e, _ = models.prior_residual(model, T[idx], np.asarray(p.T_world_node, dtype=float))
        info = p.information
        ev = e.reshape(-1)
        cost += float(ev @ (info @ ev))
        dense = info.toarray() if hasattr(info, 'toarray') else np.asarray(info)
        # a prior adds as many equations as the rank of its information (as in solve)
        n_eq += int(np.linalg.matrix_rank(0.5 * (dense + dense.T), hermitian=True))
    return cost, n_eq


def _outside_tests(model: str, T: FloatArray, outside: ConnectionArrays, ocs: IntArray,
                   ocd: IntArray, Sigma_o: FloatArray, r_c: int, lam0: float, power: float
                   ) -> tuple[FloatArray, FloatArray]:
    """Test of connections outside the adjustment: statistics and critical values."""
    lo = models.linearise(model, T, outside.src, outside.dst, outside.z,
                          np.zeros_like(outside.z))
    C = lo.B @ outside.cov @ np.swapaxes(lo.B, 1, 2)
    C = C + _propagate(lo.A_src, lo.A_dst, ocs, ocd, Sigma_o)
    out_stat = np.einsum('mi,mi->m', lo.f, np.linalg.solve(C, lo.f[:, :, None])[:, :, 0])
    out_crit = np.full(len(outside), chi2.isf(b_method_alpha(lam0, power, r_c), r_c))
    return out_stat, out_crit


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
    model = result.model
    d = models.dof(model)
    T = result.T_world_node
    v = result.residuals
    free_ids = result.free_node_ids
    fixed = np.setdiff1d(network.node_ids, free_ids)
    col = np.full(network.n_nodes, -1, dtype=np.int64)
    col[network.indices_of(free_ids)] = np.arange(free_ids.size)

    # per-connection A, B, M at (l0 = l_b + v, x)
    lin = models.linearise(model, T, conn.src, conn.dst, conn.z, v)
    B = lin.B
    r_c = lin.f.shape[1]
    M = B @ conn.cov @ np.swapaxes(B, 1, 2)
    L = np.linalg.cholesky(M)
    Linv = np.linalg.inv(L)
    cs, cd = col[conn.src], col[conn.dst]
    As = np.where((cs >= 0)[:, None, None], lin.A_src, 0.0)
    Ad = np.where((cd >= 0)[:, None, None], lin.A_dst, 0.0)
    N_all, N_prior = _normal_matrix(network, T, model, fixed, free_ids, priors, As, Ad, Linv,
                                    cs, cd, d)
    n_out = 0 if outside is None else len(outside)
    empty = np.zeros(0, dtype=np.int64)
    ocs, ocd = (col[outside.src], col[outside.dst]) if n_out else (empty, empty)
    Sigma, bsr = _sigma_blocks(N_all, N_prior, d, cs, cd, ocs, ocd)
    G = _propagate(lin.A_src, lin.A_dst, cs, cd, Sigma[:3 * m])
    Qw, Q_kk, red_comp, red = _redundancy(conn.cov, B, Linv, G, r_c)
    # P v = B' k
    Pv = np.linalg.solve(conn.cov, v[:, :, None])[:, :, 0]
    lam0 = cfg.lambda0
    w, mdb = _w_tests(conn.cov, B, Q_kk, Pv, lam0)
    stat, q, crit = _connection_tests(Linv, B, v, Qw, lam0, cfg.power)

    # global test
    cost, n_eq = _global_cost(network, model, T, v, Pv, priors, m * r_c)
    redundancy = n_eq - free_ids.size * d
    out_stat = np.zeros(0)
    out_crit = np.zeros(0)
    if n_out:
        out_stat, out_crit = _outside_tests(model, T, outside, ocs, ocd,
                                            Sigma[3 * m:3 * m + 3 * n_out], r_c, lam0,
                                            cfg.power)
    prior_red = 0.0
    if bsr is not None:
        # r_prior = k d - tr(Q_x N_prior) = k d - sum of Sigma .* N_prior over its pattern
        S_p = Sigma[3 * (m + n_out):]
        prior_red = n_eq - m * r_c - float(np.sum(S_p * bsr.data))
    sigma0_sq = cost / redundancy if redundancy > 0 else float('nan')
    g_crit = float(chi2.isf(cfg.alpha, redundancy)) if redundancy > 0 else float('nan')
    return QualityReport(
        model=model, cost=cost, redundancy=int(redundancy), sigma0_sq=float(sigma0_sq),
        global_critical=g_crit, global_passed=bool(redundancy > 0 and cost <= g_crit),
        redundancy_numbers=red, redundancy_components=red_comp, prior_redundancy=prior_red,
        w=w, connection_statistic=stat, connection_dof=q, connection_critical=crit, mdb=mdb,
        lambda0=lam0, w_critical=cfg.w_critical, config=cfg, outside_statistic=out_stat,
        outside_critical=out_crit)


def _propagate(A_src: FloatArray, A_dst: FloatArray, cs: IntArray, cd: IntArray,
               Sigma: FloatArray) -> FloatArray:
    """``A_i Q_x A_i'`` per connection from the blocks ``Sigma = [Q_ss; Q_sd; Q_dd]`` (3 m)
    (a fixed endpoint, column -1, contributes nothing)."""
    m = cs.size
    As = np.where((cs >= 0)[:, None, None], A_src, 0.0)
    Ad = np.where((cd >= 0)[:, None, None], A_dst, 0.0)
    AsT, AdT = np.swapaxes(As, 1, 2), np.swapaxes(Ad, 1, 2)
    G = As @ Sigma[:m] @ AsT + Ad @ Sigma[2 * m:3 * m] @ AdT
    cross = As @ Sigma[m:2 * m] @ AdT
    return G + cross + np.swapaxes(cross, 1, 2)


def _assemble(blocks: list[FloatArray], rows: list[IntArray], cols: list[IntArray], d: int,
              n: int) -> sp.csr_matrix:
    """Sparse ``(d n, d n)`` sum of ``d x d`` blocks at block coordinates (-1: dropped)."""
    blk = np.concatenate(blocks)
    br, bc = np.concatenate(rows), np.concatenate(cols)
    ok = (br >= 0) & (bc >= 0)
    a = np.arange(d)
    r = np.broadcast_to(br[ok, None, None] * d + a[None, :, None], (int(ok.sum()), d, d))
    c = np.broadcast_to(bc[ok, None, None] * d + a[None, None, :], (int(ok.sum()), d, d))
    return sp.coo_matrix((blk[ok].ravel(), (r.ravel(), c.ravel())),
                         shape=(d * n, d * n)).tocsr()


def _inverse_blocks(N: sp.spmatrix, d: int, rows: IntArray, cols: IntArray,
                   selected: bool | None = None) -> FloatArray:
    """Blocks ``(rows[k], cols[k])`` of ``N^-1`` (``d x d`` node blocks; -1 gives a zero block).

    Pairs on the block pattern of ``N`` (a diagonal block, a connected node pair) come from
    selected inversion on the sparse Cholesky factor
    (:class:`~ga_ros.core.linalg.selinv.SelectedInverse`); any other pair (e.g. the ends of an
    excluded
    connection), or every pair with ``selected=False`` (the default without compiled kernels),
    from the node columns of ``N^-1`` solved for in chunks with the factor. No dense inverse is
    formed.
    """
    from ga_ros.core.linalg import selinv  # lazy: numba

    if selected is None:
        selected = selinv.COMPILED
    bsr = sp.bsr_matrix(sp.csr_matrix(N), blocksize=(d, d))
    bsr.sort_indices()
    n = bsr.shape[0] // d
    brow = np.repeat(np.arange(n), np.diff(bsr.indptr))
    pattern = BlockPattern(brow, bsr.indices.astype(np.int64), d, n)
    chol = SparseCholesky(pattern, pattern.assemble(bsr.data))
    out = np.zeros((rows.size, d, d))
    todo = np.nonzero((rows >= 0) & (cols >= 0))[0]
    if selected and todo.size:
        got = selinv.SelectedInverse(chol).blocks(rows[todo], cols[todo], off_pattern='nan')
        ok = np.isfinite(got).all(axis=(1, 2))
        out[todo[ok]] = got[ok]
        todo = todo[~ok]  # off the pattern: solved for below (the factor is computed again)
    needed = np.unique(cols[todo])
    for start in range(0, needed.size, _CHUNK):
        chunk = needed[start:start + _CHUNK]
        E = np.zeros((n * d, chunk.size * d))
        for k, c in enumerate(chunk):
            E[c * d:(c + 1) * d, k * d:(k + 1) * d] = np.eye(d)
        X = chol.solve(E).reshape(n, d, chunk.size, d)
        pos = np.full(n, -1, dtype=np.int64)
        pos[chunk] = np.arange(chunk.size)
        sel = todo[pos[cols[todo]] >= 0]
        out[sel] = X[rows[sel], :, pos[cols[sel]], :]
    return out


# ------------------------------------------------------------------------------ snooping
@dataclass
class SnoopingResult:
    """Outcome of :func:`data_snooping`.

    Attributes
    ----------
    result : the final adjustment (without the removed connections).
    report : its quality report (in the order of ``kept``).
    network : the network of the kept connections.
    kept : (m,) mask over the input connections.
    removed : indices of the removed connections (input order), in the order of removal.
    removed_ratio : the test ratio (statistic / critical value) of each at its removal.
    iterations : number of adjustments made.
    """

    result: SolveResult
    report: QualityReport
    network: ConnectionNetwork
    kept: BoolArray
    removed: IntArray
    removed_ratio: FloatArray
    iterations: int


def data_snooping(network: ConnectionNetwork, T_init: FloatArray,
                  solver_config: SolverConfig | None = None,
                  fixed: Sequence[int] | None = None,
                  priors: Sequence[GaussianPrior] = (),
                  config: QualityConfig | None = None,
                  max_removals: int | None = None,
                  per_iteration: int = 1, until: str = 'local',
                  readmit: bool = False) -> SnoopingResult:
    """Iterative data snooping (Baarda 1968): remove the worst connection and re-adjust until no
    local test rejects.

    Parameters
    ----------
    network, T_init, solver_config, fixed, priors : as for :func:`ga_ros.core.solver.solve`
        (the solver must use ``robust_loss='none'``: snooping is the alternative to it).
    config : test settings (``snoop_test`` chooses the statistic).
    max_removals : stop after removing this many connections (default: a third of them).
    per_iteration : remove up to this many rejected connections per adjustment (the worst
        first, at most one per node, so that one gross error does not take its neighbours with
        it). 1 is Baarda's procedure; more trades exactness for speed on large networks.
    until : ``'local'``: stop when no local test rejects; ``'global'``: stop as soon as the
        global test of the variance factor passes (Baarda's detection-identification loop; on
        a large network one gross error hardly moves the global statistic, hence the default).
    readmit : when no test rejects any more, test the removed connections against the final
        adjustment (``outside`` of :func:`quality_control`) and put back those that agree with
        it (e.g. one removed early while a gross error nearby distorted the estimate); then
        snoop once more, without a second re-admission. Off by default: not yet shown to help
        on the benchmark (with a loose ``alpha0`` the second round removes more).

    Returns
    -------
    SnoopingResult
    """
    cfg = config or QualityConfig()
    scfg = solver_config or SolverConfig()
    if scfg.robust_loss != 'none':
        raise InputError("data snooping re-adjusts by least squares: use robust_loss='none'")
    if until not in ('local', 'global'):
        raise InputError(f"until must be 'local' or 'global', got {until!r}")
    if per_iteration < 1:
        raise InputError(f'per_iteration must be >= 1, got {per_iteration}')
    conn = network.arrays()
    m = len(conn)
    limit = m // 3 if max_removals is None else int(max_removals)
    kept = np.ones(m, dtype=bool)
    removed: list[int] = []
    ratios: list[float] = []
    T = np.asarray(T_init, dtype=float)
    net = network
    it = 0
    for round_ in range(2 if readmit else 1):
        while True:
            it += 1
            res = solve(net, T, scfg, fixed=fixed, priors=priors)
            rep = quality_control(net, res, priors, cfg)
            T = res.T_world_node
            ratio = np.nan_to_num(rep.test_ratio(), nan=0.0)
            budget = min(per_iteration, limit - len(removed))
            if budget <= 0 or not (ratio > 1.0).any() or (until == 'global' and
                                                         rep.global_passed):
                break
            kept_idx = np.nonzero(kept)[0]
            chosen = _worst_apart(ratio, net.arrays(), budget)
            removed.extend(int(kept_idx[k]) for k in chosen)
            ratios.extend(float(ratio[k]) for k in chosen)
            kept[kept_idx[chosen]] = False
            net = _subnetwork(network, kept)
        if round_ == 1 or not removed:
            break
        out = np.asarray(removed, dtype=np.int64)
        outside = ConnectionArrays(conn.src[out], conn.dst[out], conn.z[out], conn.cov[out])
        chk = quality_control(net, res, priors, cfg, outside=outside)
        back = chk.outside_statistic <= chk.outside_critical
        if not back.any():
            break
        kept[out[back]] = True
        removed = [int(k) for k in out[~back]]
        ratios = [r for r, b in zip(ratios, back) if not b]
        net = _subnetwork(network, kept)
    return SnoopingResult(result=res, report=rep, network=net, kept=kept,
                          removed=np.asarray(removed, dtype=np.int64),
                          removed_ratio=np.asarray(ratios, dtype=float), iterations=it)


def _worst_apart(ratio: FloatArray, conn: ConnectionArrays, budget: int) -> list[int]:
    """Up to ``budget`` rejected connections (``ratio > 1``), worst first, no two sharing a
    node."""
    used: set[int] = set()
    chosen: list[int] = []
    for k in np.argsort(-ratio):
        if ratio[k] <= 1.0 or len(chosen) >= budget:
            break
        s, d = int(conn.src[k]), int(conn.dst[k])
        if s in used or d in used:
            continue
        used.update((s, d))
        chosen.append(int(k))
    return chosen


def _subnetwork(network: ConnectionNetwork, keep: BoolArray) -> ConnectionNetwork:
    """The network with only the connections in ``keep`` (same nodes)."""
    c = network.arrays()
    return ConnectionNetwork.from_arrays(network.node_ids, network.track_ids, c.src[keep],
                                         c.dst[keep], c.z[keep], c.cov[keep])
