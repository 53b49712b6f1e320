"""Where a background refinement runs: :class:`RefinementWorker`, a separate process
('spawn' start method: safe beside the DDS threads of a live node), a thread of this process,
inline at the hand-off, or (``'auto'``) inline when the snapshot is small and in the process
otherwise (ROS-free).

A worker process keeps the smoothing steps of its last refinement
(:func:`~ga_ros.core.window.elimination.smooth`'s gains, 60-80 MB for a horizon of 25-30
200-pose tracks) and applies them when the aligner sends the prior nodes' corrections
(:meth:`RefinementWorker.smooth`), so the hand-off receives poses, covariances and priors only.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
import time
from concurrent.futures import (
    BrokenExecutor,
    Executor,
    Future,
    ProcessPoolExecutor,
    ThreadPoolExecutor,
)
from dataclasses import replace

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.window.elimination import smoothed
from ga_ros.core.window.refinement import refine_snapshot
from ga_ros.core.window.snapshot import RefinementResult, RefinementSnapshot, SmoothingStep
from ga_ros.errors import InputError

#: Where a refinement runs: a separate process ('spawn' start method: safe beside the DDS threads
#: of a live node), a thread of this process, inline at the hand-off (same result, blocking), or
#: ``'auto'``: inline for a snapshot of fewer than :data:`INLINE_BELOW_CONNECTIONS` connections,
#: else in the process.
REFINE_EXECUTORS = ('auto', 'process', 'thread', 'inline')

#: ``'auto'`` solves a snapshot with fewer connections than this inline at the hand-off. Such a
#: refinement takes ~50 us of CPU per node (~0.1 s for the Plaza run's 2,500-node horizon);
#: handing it to a worker process costs more: the worker's start (interpreter, NumPy, SciPy,
#: ga_ros and the compiled kernels loaded again, ~0.8 s of CPU once) and the snapshot, result
#: and smoothing through pipes at every hand-off. The result is the same bit for bit (the
#: executors run the same :func:`refine_snapshot`); only its CPU moves onto the update that
#: installs it. A larger snapshot (the aerial survey's horizon: ~25,000 connections) runs in
#: the worker process, in parallel with the updates.
INLINE_BELOW_CONNECTIONS = 4000


#: In a worker process: the smoothing steps of its last refinement, by its ``after_tracks``
#: (:func:`_refine_in_worker`, :func:`_smooth_in_worker`).
_KEPT_STEPS: dict[int, tuple[SmoothingStep, ...]] = {}


def _refine_in_worker(snap: RefinementSnapshot) -> RefinementResult:
    """:func:`refine_snapshot` in the worker process, keeping the smoothing steps there.

    The steps hold a dense gain per eliminated group (~0.7 M values per 200-pose track, 60-80 MB
    for a horizon of 25-30 such tracks); shipping them to the aligner's process would cost it
    ~30 ms of CPU at every hand-off (pickles through the pipe), and their transient copies let its
    heap grow. The aligner sends the prior nodes' corrections instead
    (:meth:`RefinementWorker.smooth`) and receives the corrections of the frozen nodes.
    """
    res = refine_snapshot(snap)
    _KEPT_STEPS.clear()
    if not res.ok:
        return res
    _KEPT_STEPS[res.after_tracks] = res.smoothing
    return replace(res, smoothing=(), smoothing_kept=True)


def _smooth_in_worker(after_tracks: int, nodes: IntArray, d_nodes: FloatArray
                      ) -> tuple[IntArray, FloatArray]:
    """:func:`smoothed` with the steps kept by :func:`_refine_in_worker` (in the worker)."""
    steps = _KEPT_STEPS.pop(after_tracks, None)
    if steps is None:
        raise InputError(f'the worker no longer holds the smoothing of refinement '
                         f'{after_tracks}')
    return smoothed(steps, nodes, d_nodes)


def _exit_with_parent(parent_pid: int) -> None:
    """In the worker process: exit when the aligner's process is gone (killed with SIGKILL,
    say), instead of living on as an orphan."""
    def watch() -> None:
        while os.getppid() == parent_pid:
            time.sleep(1.0)
        os._exit(0)

    threading.Thread(target=watch, name='ga_refine_parent', daemon=True).start()


_SPAWN_LOCK = threading.Lock()


def _preparation_without_main(prepare):
    """``multiprocessing.spawn.get_preparation_data`` without the parent's main module."""
    def without_main(name: str) -> dict:
        data = prepare(name)
        data.pop('init_main_from_path', None)
        data.pop('init_main_from_name', None)
        return data
    return without_main


class _WorkerProcess(multiprocessing.context.SpawnProcess):
    """A spawned process that does not run the parent's main module again.

    A spawned child normally re-imports the script that started the parent (as
    ``__mp_main__``): a script without an ``if __name__ == '__main__':`` guard would run again
    in the refinement worker (its output twice, a second survey, a second worker refused in
    bootstrap). The worker needs nothing from it (its job and data come from ``ga_ros``), so
    the start-up data it receives leave the main module out (the rest -- ``sys.path``, working
    directory, authentication key -- is unchanged).
    """

    @staticmethod
    def _Popen(process_obj):  # noqa: N802 - multiprocessing's name
        from multiprocessing import spawn

        with _SPAWN_LOCK:
            prepare = spawn.get_preparation_data
            spawn.get_preparation_data = _preparation_without_main(prepare)
            try:
                return multiprocessing.context.SpawnProcess._Popen(process_obj)
            finally:
                spawn.get_preparation_data = prepare


class _WorkerContext(multiprocessing.context.SpawnContext):
    """The 'spawn' start method with :class:`_WorkerProcess`."""

    Process = _WorkerProcess


class RefinementWorker:
    """Runs :func:`refine_snapshot` off the update path and hands results back in order.

    At most one refinement is in flight. The executor (a one-worker process pool with the
    'spawn' start method that does not re-run the parent's main module, :class:`_WorkerProcess`;
    a one-worker thread pool; or none for ``'inline'``) is created on the
    first submission and shut down by :meth:`close` (also when the worker is garbage collected).

    Parameters
    ----------
    executor : one of :data:`REFINE_EXECUTORS`; ``'auto'`` chooses ``'inline'`` or
        ``'process'`` per snapshot (:data:`INLINE_BELOW_CONNECTIONS`).
    """

    def __init__(self, executor: str = 'auto') -> None:
        if executor not in REFINE_EXECUTORS:
            raise InputError(f'refine_executor must be one of {REFINE_EXECUTORS}, '
                             f'got {executor!r}')
        self.kind = executor
        self._pool: Executor | None = None
        self._pending: tuple[int, Future | RefinementSnapshot] | None = None

    @property
    def pending_due(self) -> int | None:
        """Track count at whose update the pending refinement is installed (``None``: none)."""
        return None if self._pending is None else self._pending[0]

    def submit(self, snap: RefinementSnapshot, due: int) -> None:
        """Start refining ``snap``; its result is due at the update of the ``due``-th track."""
        if self._pending is not None:
            raise InputError('a refinement is already in flight')
        kind = self.kind
        if kind == 'auto':
            kind = 'inline' if len(snap.src) < INLINE_BELOW_CONNECTIONS else 'process'
        if kind == 'inline':
            self._pending = (due, snap)
            return
        job = _refine_in_worker if kind == 'process' else refine_snapshot
        try:
            future = self._executor().submit(job, snap)
        except BrokenExecutor:  # the worker process died (its result said so): a new one
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None
            future = self._executor().submit(job, snap)
        self._pending = (due, future)

    def _executor(self) -> Executor:
        """The executor, created on first use."""
        if self._pool is None:
            if self.kind in ('process', 'auto'):
                self._pool = ProcessPoolExecutor(
                    max_workers=1, mp_context=_WorkerContext(),
                    initializer=_exit_with_parent, initargs=(os.getpid(),))
            else:
                self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix='ga_refine')
        return self._pool

    def smooth(self, res: RefinementResult, nodes: IntArray, d_nodes: FloatArray
               ) -> tuple[IntArray, FloatArray]:
        """Back substitution of an installed result (:func:`smoothed`): in this process from
        ``res.smoothing``, or in the worker process that kept the steps
        (``res.smoothing_kept``; it is idle at this point of the hand-off, the next snapshot is
        submitted after the update). Raises :class:`InputError` if the worker is gone."""
        if not res.smoothing_kept:
            return smoothed(res.smoothing, nodes, d_nodes)
        if self._pool is None:
            raise InputError('the refinement worker that kept the smoothing is gone')
        try:
            return self._pool.submit(_smooth_in_worker, res.after_tracks, nodes,
                                     d_nodes).result()
        except InputError:
            raise
        except Exception as exc:  # noqa: BLE001 - a crashed worker must not end the survey
            raise InputError(f'smoothing in the worker failed: {type(exc).__name__}: '
                             f'{exc}') from exc

    def take(self, n_tracks: int) -> RefinementResult | None:
        """The pending result if it is due at the update of the ``n_tracks``-th track (waits
        for it), else ``None``. A worker that died yields a failed result."""
        if self._pending is None or self._pending[0] > n_tracks:
            return None
        _, job = self._pending
        self._pending = None
        if isinstance(job, RefinementSnapshot):
            return refine_snapshot(job)
        try:
            return job.result()
        except Exception as exc:  # noqa: BLE001 - a crashed worker must not end the survey
            return RefinementResult(-1, False, f'worker failed: {type(exc).__name__}: {exc}',
                                    np.zeros((0, 4, 4)), np.zeros((0, 6, 6)), (),
                                    np.zeros(0, bool), np.zeros(0, np.int64), (), 0, 0.0)

    def drop(self) -> None:
        """Forget the pending refinement (a reset, a restored state)."""
        if self._pending is not None and isinstance(self._pending[1], Future):
            self._pending[1].cancel()
        self._pending = None

    def close(self) -> None:
        """Drop the pending refinement and shut the executor down (without waiting)."""
        self.drop()
        if self._pool is not None:
            self._pool.shutdown(wait=False, cancel_futures=True)
            self._pool = None

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:  # noqa: BLE001, S110 - interpreter shutdown
            pass
