"""The window update: building the window problem and solving it (paper Sec. III-D, IV).

When a track ends, the mixed adjustment runs over the nodes of the latest ``window_tracks``
tracks (plus the frozen nodes their connections touch, as weighted parameters with their joint
priors). It is warm-started from the previous estimate; the new track's nodes are first
pre-aligned alone (:mod:`ga_ros.core.prealign`). After each solve the outlier gate
(:mod:`ga_ros.core.window.gate`) excludes gross outliers among the cross connections and
re-admits excluded ones the new estimate agrees with, and the window is solved again until
nothing changes. :class:`WindowUpdate` keeps what one update hands the next (the connections'
weights, the pre-alignment's factor, the quality control).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg.completion import spd_inverse
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.prealign import prealign
from ga_ros.core.solver import GaussianPrior, SolveResult, information_rank, solve
from ga_ros.core.window.config import AlignerConfig, UpdateResult
from ga_ros.core.window.freeze import JointPrior
from ga_ros.core.window.gate import QualityCache, outliers, readmissible
from ga_ros.core.window.state import WindowState
from ga_ros.geometry import se3


@dataclass(frozen=True)
class ConnectionTerms:
    """Per-connection terms of a window's connections that depend on the measurement only,
    kept from one update to the next (:meth:`WindowUpdate.connection_terms`)."""

    rows: IntArray  # (m,) sorted connection rows
    cov: FloatArray  # (m, 6, 6) S, unpacked from the connection table
    weights: FloatArray  # (m, 6, 6) S^-1
    T_meas: FloatArray  # (m, 4, 4) the measured motions T_src_dst
    T_meas_inv: FloatArray  # (m, 4, 4) their inverses

    @classmethod
    def empty(cls, m: int = 0, rows: IntArray | None = None) -> ConnectionTerms:
        """Terms of ``m`` connections (rows ``rows``, none by default), not yet filled."""
        return cls(np.zeros(0, np.int64) if rows is None else rows, np.empty((m, 6, 6)),
                   np.empty((m, 6, 6)), np.empty((m, 4, 4)), np.empty((m, 4, 4)))


class WindowProblem(NamedTuple):
    """The window adjustment's problem (:meth:`WindowUpdate.window_problem`).

    Attributes
    ----------
    net : the network of ``nodes`` and ``conns``.
    nodes : (k,) node rows: the window's (``win_nodes``) first, then the frozen ones its
        connections or priors touch (weighted parameters).
    win_nodes : (w,) sorted node rows of the window's tracks.
    conns : (m,) sorted rows of the active connections among ``nodes``.
    fixed : the datum's id if it is among ``nodes``.
    priors : the joint priors (and marginal ones of frozen nodes outside every joint prior).
    """

    net: ConnectionNetwork
    nodes: IntArray
    win_nodes: IntArray
    conns: IntArray
    fixed: list
    priors: list[GaussianPrior]


def carry_over(T_init: FloatArray, nodes: IntArray, prev_nodes: IntArray,
               T_prev: FloatArray) -> FloatArray:
    """``T_init`` (poses of ``nodes``) with the poses of the nodes that were also in the previous
    problem (``prev_nodes``, estimate ``T_prev``) taken from that estimate."""
    out = T_init.copy()
    if prev_nodes.size == 0 or nodes.size == 0:
        return out
    pos = np.full(int(max(nodes.max(), prev_nodes.max())) + 1, -1, dtype=np.int64)
    pos[prev_nodes] = np.arange(prev_nodes.size)
    k = pos[nodes]
    out[k >= 0] = T_prev[k[k >= 0]]
    return out


class WindowUpdate:
    """Builds and solves the window problem of a :class:`WindowState` (see the module
    docstring); the aligner calls :meth:`adjust` at each track end.

    Parameters
    ----------
    state : the aligner's state (read; the adjustment's estimate, connection status, outlier
        count and last adjustment are written).
    config : the aligner's settings.
    """

    def __init__(self, state: WindowState, config: AlignerConfig) -> None:
        self.state, self.config = state, config
        # weights S^-1 and measured motions of the last window's connections: an update
        # computes them only for the connections that entered the window since
        self.terms = ConnectionTerms.empty()
        # the factor of the last pre-alignment (its symbolic analysis), for the next track's
        self.prealign_factor = None
        self.quality = QualityCache()
        # the variance factor of each connection row (online variance components applied);
        # None: the stated covariances
        self.weight_factors: Callable[[IntArray], FloatArray] | None = None
        # (net, conns, priors) of the last adjustment's final solve
        self.problem: tuple[ConnectionNetwork, IntArray, list[GaussianPrior]] | None = None

    def window_problem(self, window_tracks: list[int]) -> WindowProblem:
        """The adjustment of the nodes of ``window_tracks`` (:class:`WindowProblem`)."""
        win_nodes = np.sort(np.concatenate([self.state.track_nodes[t] for t in window_tracks]
                                           or [np.zeros(0, dtype=np.int64)]))
        in_win = np.zeros(len(self.state.ids), dtype=bool)
        in_win[win_nodes] = True
        conns = self.state.track_connections(window_tracks)
        conns = conns[self.state.status.a[conns] == 0]
        # nodes of a track still open (after a reload) are not part of this adjustment
        known = in_win | self.state.frozen[:len(self.state.ids)]
        conns = conns[known[self.state.src.a[conns]] & known[self.state.dst.a[conns]]]
        src, dst = self.state.src.a[conns], self.state.dst.a[conns]
        ids = self.state.idarr.a
        ext = np.unique(np.concatenate([src[~in_win[src]], dst[~in_win[dst]]]))
        # joint priors (Schur complements of frozen terms) touching the window or its frozen
        # neighbours; under the weighted policy their nodes are frozen boundary nodes
        priors_idx = []
        touched = in_win.copy()
        touched[ext] = True
        for p, (idx, _, _) in enumerate(self.state.priors):
            if touched[idx].any():
                priors_idx.append(p)
                ext = np.union1d(ext, idx[~in_win[idx]])
        nodes = np.concatenate([win_nodes, ext])
        net = self.state.subnetwork(nodes, conns, self.connection_terms(conns).cov)
        free_datum = self.config.datum == 'fixes'
        fixed = [self.state.ids[0]] if (nodes == 0).any() and not free_datum else []
        priors = []
        # Frozen nodes touched by window connections are weighted parameters (Sec. III-E): they
        # stay unknowns of the adjustment, with a joint prior that carries only the information
        # of the connections absorbed when they froze (see
        # FreezePolicy.marginalise), so nothing
        # is counted twice; they are not written back. A frozen node outside every joint prior
        # (a state saved by an older version) falls back to its marginal covariance.
        covered = np.concatenate([self.state.priors[p][0] for p in priors_idx]
                                 or [np.zeros(0, np.int64)])
        weighted = ext[((ext != 0) | free_datum) & ~np.isin(ext, covered)]
        if weighted.size:
            priors.append(GaussianPrior.from_covariances(ids[weighted], self.state.T[weighted],
                                                         self.state.cov[weighted]))
        for p in priors_idx:
            idx, mean, info = prior = self.ranked(p)
            priors.append(GaussianPrior(ids[idx], mean, info, rank=prior.rank))
        # absolute fixes of the nodes that are not frozen (a frozen node's are in its joint
        # prior): weighted parameters (ga_ros.core.fixes)
        priors += self.state.fixes.priors(nodes[~self.state.frozen[nodes]], self.state.T, ids)
        return WindowProblem(net, nodes, win_nodes, conns, fixed, priors)

    def ranked(self, p: int) -> JointPrior:
        """Prior ``p`` with its rank (determined here once if it came without one: a state
        file, a dense prior)."""
        prior = self.state.priors[p]
        if getattr(prior, 'rank', None) is None:
            prior = self.state.priors[p] = JointPrior(*prior, rank=information_rank(prior[2], 6))
        return prior

    def connection_terms(self, conns: IntArray) -> ConnectionTerms:
        """The covariances, weights and measured motions of connections (sorted rows), with
        :attr:`weight_factors` applied (covariances times the factor, weights divided)."""
        return scaled_terms(self.stated_terms(conns), self.weight_factors)

    def stated_terms(self, conns: IntArray) -> ConnectionTerms:
        """The stated covariances, weights and measured motions of connections (sorted rows),
        those of the last call reused (a window keeps most of its connections from one update
        to the next)."""
        self.terms = out = connection_terms(self.state, self.terms, conns)
        return out

    def last(self) -> SolveResult | None:
        """The last window adjustment. A restored state recomputes it on first use (its
        covariances are needed only to freeze the next leaving track or to answer covariance
        queries), so loading a snapshot does not solve anything."""
        st = self.state
        pending, st.last_pending = st.last_pending, None
        if pending is not None:
            net, nodes, _, _, fixed, priors = self.window_problem(pending)
            st.last_result = solve(net, st.T[nodes], self.config.solver_config(), fixed=fixed,
                                   priors=priors, jit=True)
        return st.last_result

    def set_last(self, res: SolveResult | None) -> None:
        """Make ``res`` the last window adjustment (none pending)."""
        self.state.last_pending = None
        self.state.last_result = res

    def adjust(self, window_tracks: list[int], track: int, t0: float,
               factor_lock=None) -> UpdateResult:
        """Adjust the window of ``window_tracks`` after ``track`` ended (``t0``: the update's
        start, ``time.perf_counter()``): solve, gate, re-admit, solve again until nothing
        changes (the absolute fixes' gate too, :meth:`FixBook.gate_adjusted
        <ga_ros.core.fixes.FixBook.gate_adjusted>`, its covariances under ``factor_lock``); the
        window's poses and the last adjustment are written to the state."""
        cfg = self.config
        scfg = cfg.solver_config()
        n_out = 0
        readmitted: set[int] = set()
        # the sequential update (paper Sec. III-D): start from the previous estimate, at its
        # optimum for the old connections (window nodes and the frozen nodes it adjusted as
        # weighted parameters), the new track from its chained consecutive motions
        res, (prev_nodes, T_prev) = None, self.state.T_weighted
        fix_rounds, fixes_out = 0, set()
        while True:
            net, nodes, win_nodes, conns, fixed, priors = self.window_problem(window_tracks)
            # (after the gate changed the problem: from the current estimate)
            T_init = carry_over(self.state.T[nodes], nodes, prev_nodes, T_prev)
            terms = self.connection_terms(conns)
            weights, measured = terms.weights, (terms.T_meas, terms.T_meas_inv)
            if res is None:
                # the nodes no adjustment has seen yet (the new track's dead-reckoned chain)
                # first at their optimum given the others (prealign, paper Sec. III-D)
                fresh = np.nonzero(~np.isin(win_nodes, self.state.last_window))[0]
                if 0 < fresh.size < win_nodes.size:
                    factor, self.prealign_factor = self.prealign_factor, None
                    pre = prealign(net, T_init, fresh, weights=weights, jit=True, factor=factor,
                                   measured=measured)
                    T_init = pre.T_world_node
                    self.prealign_factor = pre.factor  # the next track's
            # the factor of the last solve (its symbolic analysis): same pattern as a rule
            donor = res if res is not None else self.state.last_result
            res = solve(net, T_init, scfg, fixed=fixed, priors=priors, jit=True,
                        weights=weights, measured=measured,
                        factor_at_solution=not scfg.cost_tolerance > 0,
                        factor=donor.release_factor() if donor is not None else None)
            prev_nodes, T_prev = nodes, res.T_world_node
            bad = outliers(self.state, self.config, res, conns, net, priors, weights,
                           self.quality)
            if bad.size == 0:
                back = readmissible(self.state, self.config, window_tracks, nodes, res,
                                    readmitted)
                if back.size == 0:
                    if fix_rounds < 50 and self.state.fixes.gate_adjusted(
                            nodes, res, self.state.idarr.a, self.state.frozen, fixes_out,
                            factor_lock):
                        fix_rounds += 1
                        continue
                    break
                self.state.status.a[back] = 0  # consistent now: back into the adjustment
                readmitted.update(back.tolist())
                continue
            if n_out >= 50:
                break
            self.state.status.a[bad] = 2
            n_out += int(bad.size)
        n_win = win_nodes.size
        self.problem = (net, conns, priors)
        self.state.T[win_nodes] = res.T_world_node[:n_win]
        self.state.T_weighted = (nodes[n_win:].copy(), res.T_world_node[n_win:].copy())
        self.set_last(res)
        self.state.last_window = win_nodes
        self.state.n_outliers += n_out - len(readmitted)
        return UpdateResult(
            track_id=track, iterations=res.iterations, converged=res.converged,
            sigma0_sq=res.sigma0_sq, update_ms=1e3 * (time.perf_counter() - t0),
            n_window_nodes=int(n_win), n_window_connections=int(conns.size),
            n_tracks_in_window=len(window_tracks), n_outliers=n_out, reason=res.reason,
            n_priors=len(priors), n_unknowns=res.n_unknowns, n_readmitted=len(readmitted),
            quality=self.quality.summary(net, res, priors, conns, self.config,
                                         self.state.n_updates))


def scaled_terms(terms: ConnectionTerms,
                 weight_factors: Callable[[IntArray], FloatArray] | None) -> ConnectionTerms:
    """``terms`` with each connection's variance factor applied (covariance times
    ``weight_factors(rows)``, weight divided by it); ``terms`` itself when there are no factors
    or all are 1 (the default ``variance_components: off``)."""
    if weight_factors is None:
        return terms
    f = weight_factors(terms.rows)
    if (f == 1.0).all():
        return terms
    return ConnectionTerms(terms.rows, terms.cov * f[:, None, None],
                           terms.weights / f[:, None, None], terms.T_meas, terms.T_meas_inv)


def connection_terms(state: WindowState, kept: ConnectionTerms, conns: IntArray
                     ) -> ConnectionTerms:
    """The :class:`ConnectionTerms` of the connection rows ``conns`` (sorted): those of
    ``kept`` copied, the others computed from the connection table of ``state`` (the same
    values either way: each depends on its own measurement only). Changes nothing, so a freeze
    computed in the background may call it with the last update's terms."""
    if conns is kept.rows:  # the same rows again (the gate after the adjustment)
        return kept
    pos = np.searchsorted(kept.rows, conns)
    hit = pos < kept.rows.size
    hit[hit] = kept.rows[pos[hit]] == conns[hit]
    at = pos[hit]
    out = ConnectionTerms.empty(conns.size, conns)
    out.cov[hit], out.weights[hit], out.T_meas[hit], out.T_meas_inv[hit] = (
        kept.cov[at], kept.weights[at], kept.T_meas[at], kept.T_meas_inv[at])
    if not hit.all():
        new = conns[~hit]
        out.cov[~hit] = cov = state.ccov.a[new]
        out.weights[~hit] = spd_inverse(cov, "a connection's covariance is not positive definite")
        z = state.z.a[new]
        T_meas = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
        out.T_meas[~hit], out.T_meas_inv[~hit] = T_meas, se3.inverse(T_meas)
    return out
