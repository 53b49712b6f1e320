"""Iterative data snooping (Baarda 1968): adjust, test every connection, remove the worst one,
re-adjust until no test rejects; optionally re-admit the removed connections that agree with the
final adjustment."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.network import ConnectionArrays, ConnectionNetwork
from ga_ros.core.quality.config import QualityConfig
from ga_ros.core.quality.control import quality_control
from ga_ros.core.quality.report import QualityReport
from ga_ros.core.solver import GaussianPrior, SolverConfig, SolveResult, solve
from ga_ros.errors import InputError


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
    _check_arguments(scfg, until, per_iteration)
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
        back = _agreeing(conn, out, net, res, priors, cfg)
        if not back.any():
            break
        kept[out[back]] = True
        removed = [int(k) for k in out[~back]]
        ratios = [r for r, b in zip(ratios, back) if not b]
        net = _subnetwork(network, kept)
    return SnoopingResult(result=res, report=rep, network=net, kept=kept,
                          removed=np.asarray(removed, dtype=np.int64),
                          removed_ratio=np.asarray(ratios, dtype=float), iterations=it)


def _check_arguments(scfg: SolverConfig, until: str, per_iteration: int) -> None:
    """Refuse the arguments :func:`data_snooping` cannot work with (:class:`InputError`)."""
    if scfg.robust_loss != 'none':
        raise InputError("data snooping re-adjusts by least squares: use robust_loss='none'")
    if until not in ('local', 'global'):
        raise InputError(f"until must be 'local' or 'global', got {until!r}")
    if per_iteration < 1:
        raise InputError(f'per_iteration must be >= 1, got {per_iteration}')


def _agreeing(conn: ConnectionArrays, removed: IntArray, net: ConnectionNetwork,
              res: SolveResult, priors: Sequence[GaussianPrior], cfg: QualityConfig
              ) -> BoolArray:
    """Which removed connections (indices into ``conn``) agree with the adjustment ``res`` of
    ``net``: their test as connections outside it (``outside`` of :func:`quality_control`)
    does not reject."""
    outside = ConnectionArrays(conn.src[removed], conn.dst[removed], conn.z[removed],
                               conn.cov[removed])
    chk = quality_control(net, res, priors, cfg, outside=outside)
    return chk.outside_statistic <= chk.outside_critical


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
