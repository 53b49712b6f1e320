"""The quality figures of one adjustment: the full report and the live summary."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.quality.config import QualityConfig
from ga_ros.errors import InputError


@dataclass
class QualityReport:
    """Quality figures of one adjustment, per connection in network connection order.

    Attributes
    ----------
    model : constraint model of the adjustment.
    cost : ``v' P v`` over connections plus the prior terms (the global test statistic,
        ``sigma_prior = 1``).
    redundancy : ``r - u`` (equations of connections and priors minus unknowns; a datum prior
        counted by ``tr(Q H)``, :attr:`GaussianPrior.weak
        <ga_ros.core.solver.priors.GaussianPrior.weak>`).
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
    redundancy: float
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
            'model': self.model, 'cost': float(self.cost), 'redundancy': self.redundancy,
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
        redundancy=round(report.redundancy), w_max=float(w_max.max()) if testable.any() else 0.0,
        w_max_src_id=src_id, w_max_dst_id=dst_id,
        n_w_rejected=int((w_max > report.w_critical).sum()), w_critical=float(report.w_critical),
        redundancy_number_min=float(rn[sel].min()) if sel.any() else float('nan'),
        mdb_median_m=float(np.median(t_mdb)) if t_mdb.size else float('inf'),
        mdb_median_rad=float(np.median(r_mdb)) if r_mdb.size else float('inf'),
        n_tested=int(sel.sum()), seconds=float(seconds))
