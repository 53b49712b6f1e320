"""Computing the next freeze ahead of time, in a background thread (``freeze_ahead``).

Right after a successful update the freeze of the track that the next update will freeze (the
oldest of a full window) is computed in a background thread from the state that update left;
the next update uses it if nothing it depends on changed meanwhile
(:meth:`FreezeAhead.take`), else computes the freeze itself. The result is the same either way.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable

import numpy as np

from ga_ros.arrays import IntArray
from ga_ros.core.solver import SolveResult
from ga_ros.core.window.freeze import FreezePlan
from ga_ros.core.window.state import WindowState
from ga_ros.runtime import background_blas_limit

#: ``plan(track, res, last_window, priors, n_nodes, n_conns) -> FreezePlan``: the freeze of a
#: track from the state's first ``n_nodes`` nodes and ``n_conns`` connections.
PlanFreeze = Callable[[int, SolveResult, IntArray, list, int, int], FreezePlan]


class AheadFreeze:
    """The freeze of the next leaving track, computed in a background thread right after an
    update from the state that update left, with what it was computed from, so that the next
    update can check it still applies."""

    def __init__(self, track: int, res: SolveResult, window: IntArray, priors: list,
                 n_nodes: int, n_conns: int) -> None:
        self.track, self.res, self.window, self.priors = track, res, window, priors
        self.n_nodes, self.n_conns = n_nodes, n_conns
        self.fixes = np.zeros(0, np.int64)  # the used fixes of the track's nodes
        self.plan: FreezePlan | None = None
        self.cpu_ms = 0.0  # CPU time of the worker thread
        self.thread: threading.Thread | None = None

    def run(self, compute: PlanFreeze) -> None:
        """Compute the plan (BLAS limited by the process-wide limit of
        :func:`~ga_ros.runtime.background_blas_limit`: a ``blas_threads()`` context here would
        undo one of the caller's thread midway)."""
        c0 = time.thread_time()
        try:
            self.plan = compute(self.track, self.res, self.window, self.priors, self.n_nodes,
                                self.n_conns)
        except BaseException:  # noqa: BLE001
            # no plan: the update computes the freeze itself (and reports an error that recurs)
            pass
        self.cpu_ms = 1e3 * (time.thread_time() - c0)

    def wait(self) -> None:
        """Wait for the thread (if started)."""
        if self.thread is not None:
            self.thread.join()


class FreezeAhead:
    """The freeze being computed ahead (:attr:`job`) and how many were used or recomputed
    (:attr:`n_ahead`: ``[installed from the background, recomputed at the track end]``)."""

    def __init__(self, state: WindowState) -> None:
        self.state = state
        self.job: AheadFreeze | None = None
        self.n_ahead = [0, 0]

    def start(self, window_tracks: int, res: SolveResult | None, plan: PlanFreeze) -> None:
        """After a successful update (last adjustment ``res``): start computing, with ``plan``,
        the freeze of the track that the next update will freeze (the oldest of a full window
        of ``window_tracks``). :meth:`take` checks at the next update that nothing it depends
        on changed meanwhile."""
        self.drop()
        st = self.state
        finished = st.finished_order()
        K = window_tracks
        if len(finished) < K or res is None:
            return
        track = finished[-K]
        rows = st.track_nodes[track]
        if st.frozen[rows[0]]:
            return
        job = AheadFreeze(track, res, st.last_window, list(st.priors), len(st.ids), st.src.n)
        job.fixes = st.fixes.used(np.asarray(rows, np.int64))
        background_blas_limit()   # from now on (outside any blas_threads() context)
        job.thread = threading.Thread(target=job.run, args=(plan,), daemon=True,
                                      name=f'ga_ros-freeze-track-{track}')
        self.job = job
        job.thread.start()

    def wait(self) -> float:
        """Wait until the freeze being computed ahead is ready; returns the CPU milliseconds it
        took (0 if none)."""
        job = self.job
        if job is None:
            return 0.0
        job.wait()
        return job.cpu_ms

    def drop(self) -> None:
        """Forget the freeze computed ahead (after waiting for its thread: it may be using the
        last adjustment's factor)."""
        job, self.job = self.job, None
        if job is not None:
            job.wait()

    def take(self, track: int) -> FreezePlan | None:
        """The freeze of ``track`` computed ahead, if it was and still applies: same last
        adjustment, priors and absolute fixes, and no connection added since touches the
        track (the nodes and connections added since are outside what it read). ``None``:
        compute it now."""
        job, self.job = self.job, None
        if job is None:
            return None
        job.wait()
        plan = job.plan
        st = self.state
        valid = (plan is not None and job.track == track and job.res is st.last_result
                 and st.last_pending is None and job.window is st.last_window
                 and len(job.priors) == len(st.priors)
                 and all(a[0] is b[0] for a, b in zip(job.priors, st.priors)))
        if valid:  # the track's fixes as the plan read them (none added, excluded, re-admitted)
            valid = np.array_equal(st.fixes.used(plan.nodes), job.fixes)
        if valid:
            nc = job.n_conns
            mine = np.zeros(len(st.ids), dtype=bool)
            mine[plan.nodes] = True
            valid = not (mine[st.src.a[nc:]] | mine[st.dst.a[nc:]]).any()
        self.n_ahead[0 if valid else 1] += 1
        return plan if valid else None
