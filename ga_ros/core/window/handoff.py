"""Handing the survey to the background refinement and installing its result (the aligner's
side of :mod:`ga_ros.core.window.refinement`).

After every ``refine_every_tracks``-th track a :class:`~ga_ros.core.window.refinement.
RefinementSnapshot` of the refinement's horizon goes to the worker
(:class:`~ga_ros.core.window.worker.RefinementWorker`); the result is installed in the update of
the track ``refine_lag_tracks`` later, after that update's freezes (frozen poses and
covariances refined, priors rebuilt at the refined estimate), and after its window adjustment
the window's correction of the prior nodes is carried back to every frozen node of the horizon
(:meth:`RefinementHandoff.smooth`).
"""

from __future__ import annotations

import time
from dataclasses import replace

import numpy as np

from ga_ros.core.solver import SolveResult
from ga_ros.core.window.config import AlignerConfig
from ga_ros.core.window.freeze import AbsorbedPrior, JointPrior, prior_nodes
from ga_ros.core.window.snapshot import RefinementResult, RefinementSnapshot
from ga_ros.core.window.state import WindowState, no_weighted
from ga_ros.core.window.update import carry_over
from ga_ros.core.window.worker import RefinementWorker
from ga_ros.errors import GaError, InputError
from ga_ros.geometry import se3
from ga_ros.runtime import blas_threads


class RefinementHandoff:
    """The background refinement of a :class:`WindowState`: the worker, the snapshot it is
    solving, and the result installed but not yet smoothed.

    Parameters
    ----------
    state : the aligner's state (read for snapshots; frozen poses, covariances, priors and
        the retired tracks written at an installation).
    config : the aligner's settings (``refine_*``, ``freeze_policy``, ``prior_*``).
    """

    def __init__(self, state: WindowState, config: AlignerConfig) -> None:
        self.state, self.config = state, config
        self.refiner = RefinementWorker(config.refine_executor)
        self.snap: RefinementSnapshot | None = None  # the snapshot being solved
        self.snap_updates = -1  # the update count when it was taken
        self.n_refinements = 0
        # the installed refinement and its first node, until its smoothing
        self.smoothing: tuple[RefinementResult, int] | None = None

    def start(self) -> None:
        """Hand a snapshot to the refinement worker after every ``refine_every_tracks``-th
        track (once a track will be frozen at the hand-off; one refinement in flight at most);
        it is installed in the update of the track ``refine_lag_tracks`` later, after that
        update's freezes (:meth:`install_due`)."""
        cfg = self.config
        n_done = len(self.state.finished)
        n = len(self.state.ids)
        if (cfg.refine_every_tracks <= 0 or n_done % cfg.refine_every_tracks
                or self.refiner.pending_due is not None
                or self.state.open_track not in self.state.finished):
            return
        due = n_done + cfg.refine_lag_tracks
        order = self.state.finished_order()
        leaving = tuple(int(t) for t in
                        self.state.unfrozen_tail(order[:max(0, due - cfg.window_tracks)]))
        if not leaving and not self.state.frozen[:n].any():
            return  # nothing will be frozen at the hand-off: the window is the batch solution
        if not self.relinearize_due(len(order)):
            return  # the priors' linearisation points still hold: the window's priors stand
        self.snap = replace(self.snapshot(), leaving=leaving)
        self.snap_updates = self.state.n_updates
        self.refiner.submit(self.snap, due)

    def relinearize_due(self, n_finished: int) -> bool:
        """Whether a refinement triggered after the ``n_finished``-th track runs: the frozen
        nodes may have moved from their priors' linearisation points by
        ``refine_relinearize_sigma`` standard deviations (:attr:`WindowState.refine_drift
        <ga_ros.core.window.state.WindowState.refine_drift>`, :meth:`measure`), or the tracks
        not retired reach twice the horizon (so the snapshot, the retirement and the cost of a
        refinement stay bounded by the horizon). Depends on the data only (replay == live)."""
        cfg = self.config
        horizon = int(cfg.refine_horizon_tracks)
        return (self.state.refine_drift >= cfg.refine_relinearize_sigma
                or (horizon > 0 and n_finished - self.state.retired >= 2 * horizon))

    def measure(self, prev_weighted: tuple, installed: bool, factor_step: float = 0.0
                ) -> float:
        """After a window adjustment: update and return :attr:`WindowState.refine_drift
        <ga_ros.core.window.state.WindowState.refine_drift>`.

        ``prev_weighted`` is the state's ``T_weighted`` before the adjustment (where it started
        the frozen nodes it had adjusted; the others started at their frozen pose, the
        linearisation point of the prior that holds them, or the installed refinement's). The
        adjustment's largest correction of a frozen node it adjusts as a weighted parameter, in
        that node's standard deviations (per coordinate ``[x y z rx ry rz]``, from its published
        covariance; a coordinate of zero variance, the datum's, is not counted), is added to the
        drift since the last installed refinement, or starts it if this update ``installed`` one
        (its priors are linearised at its estimate, where the adjustment started). The sum bounds
        how far any of those nodes is from its prior's linearisation point (triangle
        inequality). ``factor_step``: the adjustment's change of the online variance factors
        (``variance_components='apply'``), in standard deviations
        (:func:`~ga_ros.core.window.aligner.factor_drift`), is added too: the priors weight
        the sources with the factors of their linearisation. A prior on other nodes (the
        ``'marginal'`` policy's, on window nodes) makes the drift infinite: every trigger
        refines, as with ``refine_relinearize_sigma = 0``.
        """
        st = self.state
        nodes, T_end = st.T_weighted
        step = 0.0
        held = np.concatenate([p[0] for p in st.priors] or [np.zeros(0, np.int64)])
        if not np.isin(held, nodes).all():
            # a prior on nodes the adjustment does not hold as weighted parameters (the
            # 'marginal' policy's, on window nodes): not measured, so every trigger refines
            step = np.inf
        elif nodes.size:
            T_start = carry_over(st.T[nodes], nodes, *prev_weighted)
            d = np.abs(se3.local(T_start, T_end))
            var = np.diagonal(st.cov[nodes], axis1=1, axis2=2)
            ok = var > 0
            if ok.any():
                step = float((d[ok] / np.sqrt(var[ok])).max())
        step += float(factor_step)
        step = step if np.isfinite(step) else np.inf  # a failed measure: refine
        st.refine_drift = step if installed else st.refine_drift + step
        return st.refine_drift

    def snapshot(self, n_nodes: int | None = None, n_conns: int | None = None,
                  whole: bool = False, n_fixes: int | None = None) -> RefinementSnapshot:
        """Copy of the data a refinement needs: the horizon's nodes (every one whose track has
        not been retired, or all of them if ``whole``), the connections between them, the past
        prior and the weighted parameters of the nodes' absolute fixes; only the first
        ``n_nodes`` nodes, ``n_conns`` connections and ``n_fixes`` fixes (default all: a
        restored aligner's pending refinement saw fewer)."""
        n = len(self.state.ids) if n_nodes is None else int(n_nodes)
        m = len(self.state.src) if n_conns is None else int(n_conns)
        book = self.state.fixes
        k = len(book) if n_fixes is None else int(n_fixes)
        cfg = self.config
        scfg = cfg.solver_config()
        order = self.state.finished_order()  # tracks start at increasing rows
        while order and self.state.track_nodes.start(order[-1]) >= n:
            order = order[:-1]
        retired = 0 if whole else min(self.state.retired, len(order))
        f, rows, past = 0, None, ()
        if retired:
            f = int(self.state.track_nodes.start(order[retired]))
            rows = self.state.horizon_rows(f, m)
            past = tuple(AbsorbedPrior(idx - f, mean, info) for idx, mean, info in self.state.past)
        sel = slice(0, m) if rows is None else rows
        # a slice is a view, to be copied; a row array (fancy indexing) gives a copy already
        take = (lambda a: a[sel].copy()) if rows is None else (lambda a: a[sel])
        horizon = int(cfg.refine_horizon_tracks)
        fix_rows, fix_T, fix_info = book.prior_terms(np.arange(f, n), self.state.T, k)
        fixes = tuple(AbsorbedPrior(np.array([r - f], np.int64), fix_T[a:a + 1], fix_info[a])
                      for a, r in enumerate(fix_rows.tolist()))
        return RefinementSnapshot(
            after_tracks=len(order), node_ids=self.state.idarr.a[f:n].copy(),
            track_ids=self.state.trackarr.a[f:n].copy(), T_world_node=self.state.T[f:n].copy(),
            frozen=self.state.frozen[f:n].copy(),
            track_order=tuple(int(t) for t in order[retired:]),
            src=self.state.src.a[sel] - f, dst=self.state.dst.a[sel] - f, z=take(self.state.z.a),
            cov21=take(self.state.ccov.packed), status=take(self.state.status.a),
            freeze_policy=cfg.freeze_policy,
            solver=replace(scfg, max_iterations=max(20, scfg.max_iterations)),
            prior_band=int(cfg.prior_band), prior_hubs=int(cfg.prior_hubs), first_node=f,
            past=past, retire_max=max(0, len(order) - retired - horizon) if horizon else 0,
            conn_rows=rows, connections_total=m, fixes=fixes,
            fix_used=book.used(np.arange(f, n), k), n_fixes=k,
            free_datum=cfg.datum == 'fixes')

    def install_due(self) -> tuple[int, str, float] | None:
        """Install the refinement due at this update (waiting for it); returns ``(after_tracks,
        reason, wait + install ms)`` or ``None`` if none was due. A failed refinement, or one
        that cannot be installed, leaves the state as it was."""
        t0 = time.perf_counter()
        res = self.refiner.take(len(self.state.finished))
        if res is None:
            return None
        snap, self.snap = self.snap, None
        reason = res.reason
        if res.ok and snap is not None:
            try:
                with blas_threads():
                    self.install(snap, res)
                self.n_refinements += 1
            except (GaError, np.linalg.LinAlgError, ValueError) as exc:
                reason = f'not installed: {type(exc).__name__}: {exc}'
        elif not reason.startswith('failed'):
            reason = f'failed: {reason}'
        return res.after_tracks, reason, 1e3 * (time.perf_counter() - t0)

    def install(self, snap: RefinementSnapshot, res: RefinementResult) -> None:
        """The refined estimate becomes the frozen one (after this update's freezes, before its
        window adjustment).

        The result was computed for the state predicted at this point
        (:func:`~ga_ros.core.window.refinement.predict_freezes`); if the frozen nodes or the
        absorbed
        connections differ, nothing is installed. Otherwise the frozen nodes take the refined
        poses and covariances and the joint priors are the rebuilt ones (relinearised at the
        refined estimate, each absorbed connection in exactly one). If no update ran since the
        snapshot (``refine_lag_tracks = 1``) the window nodes also start from the refined poses.
        After the adjustment :meth:`smooth` carries the window's correction of the prior nodes
        back to every frozen node.
        """
        f, n_s = snap.first_node, snap.node_ids.size
        n = len(self.state.ids)
        rows = (np.arange(snap.src.size) if snap.conn_rows is None else snap.conn_rows)
        # the horizon's connections now: the snapshot's and those that arrived since
        now = np.arange(len(self.state.src)) if f == 0 else self.state.horizon_rows(f)
        status = self.state.status.a[now]
        predicted = np.zeros(now.size, dtype=bool)
        predicted[np.searchsorted(now, rows[res.absorbed])] = True
        if (not np.array_equal(self.state.frozen[f:f + n_s], res.frozen)
                or self.state.frozen[f + n_s:n].any()
                or not np.array_equal(status == 1, predicted)):
            raise InputError('the frozen nodes or absorbed connections changed since the '
                             'snapshot')
        frozen_rows = f + np.nonzero(res.frozen)[0]
        book = self.state.fixes
        then = np.asarray(snap.fix_used if snap.fix_used is not None else [], np.int64)
        then = then[np.isin(np.array([book.rows[i] for i in then.tolist()], np.int64),
                            frozen_rows)]
        if not np.array_equal(book.used(frozen_rows), then):
            raise InputError('the absolute fixes of the frozen nodes changed since the snapshot')
        past = np.concatenate([p.nodes for p in snap.past] + [p.nodes for p in snap.fixes]
                              or [np.zeros(0, np.int64)])
        need = prior_nodes(self.state.frozen[f:n], self.state.src.a[now] - f,
                           self.state.dst.a[now] - f,
                           status, self.config.freeze_policy, past, snap.datum)
        have = np.zeros(n - f, dtype=bool)
        for p in res.priors:
            have[p.nodes] = True
        if (need & ~have).any():
            raise InputError('a node eliminated by the refinement has a connection to the window '
                             'that arrived after the snapshot (refine_lag_tracks too large for '
                             'this survey)')
        frozen = np.nonzero(res.frozen)[0]
        if self.state.n_updates == self.snap_updates:
            # the newer nodes (the track being finished) follow the last snapshot node rigidly:
            # their frame-to-frame chain starts there
            last = f + n_s - 1
            move = res.T_world_node[n_s - 1] @ se3.inverse(self.state.T[last])
            self.state.T[last + 1:n] = move @ self.state.T[last + 1:n]
            self.state.T[f:f + n_s] = res.T_world_node
        else:
            self.state.T[f + frozen] = res.T_world_node[frozen]
        self.state.cov[f + frozen] = res.frozen_cov
        self.state.priors = [JointPrior.absorbed(p, f) for p in res.priors]
        self.state.T_weighted = no_weighted()  # refined instead
        self.smoothing = (res, f)
        # bounded refinement: the tracks it retired leave the horizon, with their prior
        self.state.retired += res.retired
        self.state.past = [JointPrior.absorbed(p, f) for p in res.past]

    def smooth(self, res: SolveResult | None) -> str | None:
        """Carry the window's correction of the prior nodes back to every frozen node of the
        installed refinement's horizon.

        The installed refinement kept the back substitution of its eliminations
        (:class:`~ga_ros.core.window.elimination.SmoothingStep`); the window adjustment ``res``
        just
        moved the
        prior nodes from the refined estimate ``T_r`` by ``d_S = log(T_r^-1 T)``; each frozen node
        then moves to its conditional mean ``T_r exp(d)`` under the absorbed connections (the
        batch solution of all data received, in the linear limit; of the horizon's data and the
        past prior under a bounded refinement). A process worker applies the steps it kept
        (:meth:`~ga_ros.core.window.worker.RefinementWorker.smooth`); returns why the smoothing
        could not be done (that worker died), else ``None``.
        """
        refined, f = self.smoothing or (None, 0)
        self.smoothing = None
        if refined is None or res is None:
            return None
        T_lin = refined.T_world_node
        where = {int(i): k for k, i in enumerate(res.node_ids.tolist())}
        idx = np.unique(np.concatenate([p[0] for p in self.state.priors]
                                       or [np.zeros(0, np.int64)]))
        k = np.array([where.get(int(i), -1) for i in self.state.ids[idx].tolist()], dtype=np.int64)
        idx, k = idx[k >= 0], k[k >= 0]
        d_idx = se3.local(T_lin[idx - f], res.T_world_node[k])  # one batched call
        try:
            nodes, d = self.refiner.smooth(refined, idx - f, d_idx)
        except InputError as exc:  # the worker died: the refined poses stand, unsmoothed
            return str(exc)
        sel = self.state.frozen[f + nodes] & ((nodes > 0) | (f > 0)
                                              | (self.config.datum == 'fixes'))  # the datum stays
        nodes, d = nodes[sel], d[sel]
        if nodes.size:
            self.state.T[f + nodes] = T_lin[nodes] @ se3.exp(d)
        return None

    def pending(self) -> dict | None:
        """What a snapshot file needs to restart the pending refinement exactly: its hand-off
        track count, and the number of nodes and connections its snapshot held (the state is
        that of the last update plus the measurements received since). ``None`` if there is
        none, or if an update ran since its snapshot (``refine_lag_tracks > 1``: a restored
        aligner then starts the next refinement at its next trigger)."""
        snap, due = self.snap, self.refiner.pending_due
        if snap is None or due is None or self.state.n_updates != self.snap_updates:
            return None
        return {'due': int(due), 'nodes': int(snap.first_node + snap.node_ids.size),
                'connections': int(snap.connections_total),
                'leaving': [int(t) for t in snap.leaving], 'fixes': int(snap.n_fixes)}

    def resume(self, pending: dict | None) -> None:
        """Restart the refinement described by :meth:`pending` (a restored aligner),
        from the same data, so the path continues as without the interruption."""
        if not pending or self.config.refine_every_tracks <= 0:
            return
        n_fixes = pending.get('fixes')  # older state files: no fixes
        self.snap = replace(self.snapshot(int(pending['nodes']), int(pending['connections']),
                                          n_fixes=None if n_fixes is None else int(n_fixes)),
                            leaving=tuple(int(t) for t in pending['leaving']))
        self.snap_updates = self.state.n_updates
        self.refiner.drop()
        self.refiner.submit(self.snap, int(pending['due']))

    def first_row(self) -> int | None:
        """The first node row the pending refinement can change (``None``: none pending)."""
        return None if self.snap is None else int(self.snap.first_node)

    def drop(self) -> None:
        """Drop the pending refinement (its inputs were replaced)."""
        self.refiner.drop()
        self.snap = None

    def close(self) -> None:
        """Stop the worker (a pending result is dropped); a later refinement starts a new one."""
        self.refiner.close()
