"""The outlier gate of the window update and the re-admission of excluded connections.

Gross outliers among overlap (cross) connections are detected after each window adjustment
(``AlignerConfig.gate``: a chi-square test on the Mahalanobis misclosure, or Baarda's w-test
of the quality control) and excluded (status 2); excluded connections of the window are
re-tested at each new estimate and re-admitted when consistent (:func:`readmissible`).
"""

from __future__ import annotations

import time

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.chi2 import chi2_quantile
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.quality import QualityReport, QualitySummary, quality_control, summarise
from ga_ros.core.solver import GaussianPrior, SolveResult
from ga_ros.core.window.config import AlignerConfig
from ga_ros.core.window.state import WindowState
from ga_ros.geometry import se3


class QualityCache:
    """The quality control of the last window adjustment (computed once per solution, for the
    w-test gate and the update's summary) and the largest ``|w|`` of every connection tested."""

    def __init__(self) -> None:
        self.last: tuple[SolveResult, QualityReport, float] | None = None
        self.conn_w: dict[int, float] = {}

    def report(self, net: ConnectionNetwork, res: SolveResult, priors: list[GaussianPrior],
               config: AlignerConfig) -> tuple[QualityReport, float]:
        """Quality control of a window adjustment (computed once per solution) and its time (s).
        The per-connection ``max |w|`` is kept for :meth:`connection_w`."""
        cached = self.last
        if cached is not None and cached[0] is res:
            return cached[1], cached[2]
        t0 = time.perf_counter()
        rep = quality_control(net, res, priors, config.quality_config())
        seconds = time.perf_counter() - t0
        self.last = (res, rep, seconds)
        return rep, seconds

    def summary(self, net: ConnectionNetwork, res: SolveResult, priors: list[GaussianPrior],
                conns: IntArray, config: AlignerConfig, n_updates: int
                ) -> QualitySummary | None:
        """The QC summary of the final window adjustment (``None`` when ``quality`` is off, or not
        due: every ``quality_every``-th update, ``n_updates`` done before this one)."""
        cached = self.last
        due = (n_updates + 1) % int(config.quality_every) == 0
        if not config.quality or not (due or (cached is not None and cached[0] is res)):
            return None
        rep, seconds = self.report(net, res, priors, config)
        w = np.where(rep.redundancy_numbers >= rep.config.min_redundancy, rep.w_max, np.nan)
        self.conn_w.update(zip(conns.tolist(), w.tolist()))
        return summarise(rep, net, seconds=seconds)

    def connection_w(self, m: int) -> FloatArray:
        """(m,) largest ``|w|`` (Baarda's w-test statistic) of every connection at the last
        window adjustment that contained it, by connection row; NaN
        when never tested (``quality`` off, untestable, or not adjusted since a reload)."""
        w = self.conn_w
        out = np.full(m, np.nan)
        if w:
            k = np.fromiter(w.keys(), np.int64, len(w))
            out[k[k < out.size]] = np.fromiter(w.values(), float, len(w))[k < out.size]
        return out


def outliers(state: WindowState, config: AlignerConfig, res: SolveResult, conns: IntArray,
             net: ConnectionNetwork, priors: list[GaussianPrior], weights: FloatArray,
             quality: QualityCache) -> IntArray:
    """Cross connections the gate excludes after an adjustment.

    ``'chi2'``: every one whose squared Mahalanobis misclosure at the solution exceeds the
    chi-square quantile (6 dof); for the se3 model ``v' P v = w' M^-1 w``. ``'w-test'``:
    the worst cross connections whose w-test rejects (data snooping, see
    :class:`AlignerConfig`). ``weights``: (m, 6, 6) the connections' ``S^-1``."""
    prob = config.outlier_chi2_prob
    cross = state.cross.a[conns]
    if prob <= 0 or not cross.any():
        return np.zeros(0, dtype=np.int64)
    if config.gate == 'w-test':
        rep, _ = quality.report(net, res, priors, config)
        ratio = np.where(cross, np.nan_to_num(rep.test_ratio('w'), nan=0.0), 0.0)
        return conns[ratio > 1.0]
    P = weights
    v = res.residuals
    maha2 = np.einsum('mi,mij,mj->m', v, P, v)
    return conns[cross & (maha2 > chi2_quantile(6, prob))]


def readmissible(state: WindowState, config: AlignerConfig, window_tracks: list[int],
                 nodes: IntArray, res: SolveResult, tried: set[int]) -> IntArray:
    """Excluded connections of the window that the new estimate agrees with.

    A connection excluded by the gate (status 2) whose two ends are unknowns of this
    adjustment is re-tested at its estimate: the misclosure ``e = log(T_meas^-1 T_i^-1
    T_j)`` with covariance ``S + J Q_x J'`` (the connection's own plus the propagated
    uncertainty of the two poses, ``J = [-Ad(T_ij^-1), I]``, small-misclosure Jacobian)
    must pass the same chi-square quantile (6 dof) as the gate. Each connection is
    re-admitted at most once per update, so the gate cannot oscillate.
    """
    prob = config.outlier_chi2_prob
    if prob <= 0:
        return np.zeros(0, dtype=np.int64)
    conns = state.track_connections(window_tracks)
    conns = conns[state.status.a[conns] == 2]
    if tried:
        conns = conns[~np.isin(conns, np.fromiter(tried, np.int64))]
    local = np.full(len(state.ids), -1, dtype=np.int64)
    local[nodes] = np.arange(nodes.size)
    conns = conns[(local[state.src.a[conns]] >= 0) & (local[state.dst.a[conns]] >= 0)]
    if conns.size == 0:
        return conns
    i, j = local[state.src.a[conns]], local[state.dst.a[conns]]
    T = res.T_world_node
    T_ij = se3.inverse(T[i]) @ T[j]
    z = state.z.a[conns]
    e = se3.log(se3.inverse(se3.from_translation_rotvec(z[:, :3], z[:, 3:])) @ T_ij)
    J = np.zeros((conns.size, 6, 12))
    J[:, :, :6] = -se3.adjoint(se3.inverse(T_ij))
    J[:, :, 6:] = np.eye(6)
    Q = np.zeros((conns.size, 12, 12))
    ids = res.node_ids
    free = np.isin(ids, res.free_node_ids)
    ends = np.stack([i, j], axis=1)
    for start in range(0, conns.size, 64):  # the joint covariance of <= 128 nodes at once
        part = ends[start:start + 64]
        nodes_free = np.unique(part[free[part]])
        if nodes_free.size == 0:
            continue
        cov = res._system.joint_covariance(ids[nodes_free])
        cov = cov.reshape(nodes_free.size, 6, nodes_free.size, 6).transpose(0, 2, 1, 3)
        pos = np.searchsorted(nodes_free, part)
        for a in range(2):
            for b in range(2):
                both = free[part[:, a]] & free[part[:, b]]
                Q[start:start + 64][both, 6 * a:6 * a + 6, 6 * b:6 * b + 6] = \
                    cov[pos[both, a], pos[both, b]]
    C = state.ccov.a[conns] + J @ Q @ np.swapaxes(J, 1, 2)
    maha2 = np.einsum('mi,mi->m', e, np.linalg.solve(C, e[:, :, None])[:, :, 0])
    return conns[maha2 <= chi2_quantile(6, prob)].astype(np.int64)
