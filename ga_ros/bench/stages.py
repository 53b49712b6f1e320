"""Where a window update's CPU goes: the stages of :data:`STAGES`, timed in every thread, and
the CPU of the whole process tree (:func:`ga_ros.bench.cpu.all_cpu_seconds`), for
``ga-ros bench window`` and ``ga-ros bench fixes``.

A stage's CPU is the ``time.thread_time()`` of the thread that runs it, between entering and
leaving one of its functions; a stage function called inside another timed function counts in
the outer one only (the stage of the outermost timed call on that thread's stack), or, with
``exclusive``, in its own stage, the outer one counting only the rest; either way the stages of
a thread add up to at most its CPU. The update call runs on the caller's thread
("track end"); the freeze computed ahead (``freeze_ahead``) runs in a background thread and the
background refinement in a worker process ("background").
"""

from __future__ import annotations

import inspect
import threading
import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager

from ga_ros.core.fixes import FixBook
from ga_ros.core.linalg import blocks as _blocks
from ga_ros.core.linalg import cholmod as _cholmod
from ga_ros.core.solver.problem import _Problem
from ga_ros.core.window import freeze as _freeze
from ga_ros.core.window import update as _update
from ga_ros.core.window import worker as _worker
from ga_ros.core.window.aligner import TrackWindowAligner
from ga_ros.core.window.gate import QualityCache
from ga_ros.core.window.handoff import RefinementHandoff

#: The stages of a window update and the functions that do them (owner, attribute).
#: ``assembly``: the window problem (node and connection sets, the connections' kept terms),
#: linearisation and normal matrices (the window's and the absorbed terms' at a freeze), the
#: gradient after each step; ``factorisation``: sparse Cholesky factorisations (the window's,
#: the pre-alignment's); ``solves``: triangular solves (the steps', the few covariances of
#: the fixes' gate); ``covariances``: the leaving track's published marginal covariances
#: (selected inversion of the window's factor);
#: ``priors``: the joint prior the leaving track's absorbed terms leave on the frozen
#: boundary (their factorisation, selected inversion and band completion) and its
#: installation; ``quality tests``: the outlier gate, re-admission, the absolute fixes' gate,
#: the update's quality summary; ``outputs``: what a node publishes after an update (the
#: corrected path or one node's pose, the newest adjusted node's covariance); ``process
#: hand-off``: the background refinement's snapshot, installation and smoothing, as seen by
#: the aligner's process (the worker process's own CPU is counted in the tree's CPU, not per
#: stage).
STAGES: dict[str, tuple[tuple[object, str], ...]] = {
    'assembly': ((_update.WindowUpdate, 'window_problem'),
                 (_update.WindowUpdate, 'connection_terms'),
                 (_Problem, 'linear_system'), (_blocks.BlockPattern, 'assemble'),
                 (_Problem, 'gradient'), (_Problem, 'gradient_ahead')),
    'factorisation': ((_cholmod.SparseCholesky, '__init__'),
                      (_cholmod.SparseCholesky, 'refactor')),
    'solves': ((_cholmod.SparseCholesky, 'solve'), (_cholmod.SparseCholesky, 'forward')),
    'covariances': ((_freeze, 'marginal_covariances'),),
    'priors': ((_freeze.FreezePolicy, 'marginalise'), (_freeze.FreezePolicy, 'absorption'),
               (_freeze, 'new_prior'), (_freeze, 'install_freeze')),
    'quality tests': ((_update, 'outliers'), (_update, 'readmissible'),
                      (QualityCache, 'summary'), (FixBook, 'gate_adjusted')),
    'outputs': ((TrackWindowAligner, 'corrected_path'), (TrackWindowAligner, 'pose'),
                (TrackWindowAligner, 'covariance')),
    'process hand-off': ((RefinementHandoff, 'start'), (RefinementHandoff, 'install_due'),
                         (RefinementHandoff, 'smooth')),
}


class StageClock:
    """CPU milliseconds per ``(thread role, stage)`` while :func:`timed_stages` is active.

    ``role`` is ``'track end'`` for the thread that created the clock and ``'background'`` for
    any other thread. :meth:`take` returns the totals since the last call and starts anew.
    """

    def __init__(self) -> None:
        self.main = threading.get_ident()
        self._lock = threading.Lock()
        self._totals: dict[tuple[str, str], float] = defaultdict(float)
        self._local = threading.local()

    def role(self) -> str:
        return 'track end' if threading.get_ident() == self.main else 'background'

    def add(self, stage: str, ms: float) -> None:
        with self._lock:
            self._totals[(self.role(), stage)] += ms

    def take(self) -> dict[tuple[str, str], float]:
        with self._lock:
            out, self._totals = dict(self._totals), defaultdict(float)
        return out

    def _stack(self) -> list[float]:
        """This thread's timed calls in progress: the ms of the nested ones each has seen."""
        stack = getattr(self._local, 'stack', None)
        if stack is None:
            stack = self._local.stack = []
        return stack

    def depth(self) -> int:
        return len(self._stack())

    def enter(self) -> None:
        self._stack().append(0.0)

    def leave(self, ms: float) -> float:
        """End the innermost timed call, which took ``ms``; returns the ms of the timed calls
        nested in it, and counts ``ms`` as nested in the call around it."""
        stack = self._stack()
        nested = stack.pop()
        if stack:
            stack[-1] += ms
        return nested


@contextmanager
def timed_stages(stages: dict[str, tuple[tuple[object, str], ...]] | None = None,
                 exclusive: bool = False) -> Iterator[StageClock]:
    """Time the functions of ``stages`` (default :data:`STAGES`; wrapped while active, then put
    back) into a :class:`StageClock`; ``exclusive``: a timed call nested in another counts in
    its own stage (module doc)."""
    clock = StageClock()
    stages = STAGES if stages is None else stages

    def wrap(stage: str, fn):
        if isinstance(fn, staticmethod | classmethod):
            raise TypeError('stage functions are plain functions or methods')

        def timed(*args, **kwargs):
            if clock.depth() and not exclusive:
                return fn(*args, **kwargs)
            clock.enter()
            c0 = time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                ms = 1e3 * (time.thread_time() - c0)
                clock.add(stage, ms - clock.leave(ms))
        return timed

    saved = [(owner, name, inspect.getattr_static(owner, name))
             for targets in stages.values() for owner, name in targets]
    try:
        for stage, targets in stages.items():
            for owner, name in targets:
                setattr(owner, name, wrap(stage, inspect.getattr_static(owner, name)))
        yield clock
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)


#: Where the counted work of an update runs (:func:`counted_work`), by the functions that do
#: it (owner, attribute): ``window`` (the window adjustment: its solves, the gate's re-solves),
#: ``pre-alignment`` (the new track's nodes alone), ``freeze`` (the leaving track's covariances
#: and joint prior, at the track end or computed ahead in the background thread),
#: ``refinement`` (the background refinement run in this process: inline or in a thread; a
#: worker process's is not seen). Work outside them counts under ``other`` (the final
#: ``refine_batch``, a restored state's first solve). The innermost part on a thread's stack
#: counts (a pre-alignment inside the window's update is a pre-alignment).
WORK_PARTS: dict[str, tuple[tuple[object, str], ...]] = {
    'window': ((_update.WindowUpdate, 'adjust'),),
    'pre-alignment': ((_update, 'prealign'),),
    'freeze': ((_freeze.FreezePolicy, 'plan'), (_freeze, 'install_freeze')),
    'refinement': ((_worker, 'refine_snapshot'),),
}

#: The work counted (:func:`counted_work`): ``linearisations``, the normal matrix ``N`` and
#: gradient assembled at an estimate (:meth:`_Problem.linear_system
#: <ga_ros.core.solver.problem._Problem.linear_system>`, also through
#: :func:`~ga_ros.core.solver.normal_matrix_at`); ``gradients``, a gradient pass without ``N``
#: (a chord step's, the fused kernel's :meth:`_Problem.gradient`, the one computed ahead with
#: the step's cost included); ``costs``, a cost evaluated alone (:meth:`_Problem.cost_at`);
#: ``factorisations``, a numeric sparse Cholesky factorisation
#: (:meth:`SparseCholesky.refactor <ga_ros.core.linalg.cholmod.SparseCholesky.refactor>`, which
#: a new factor runs too).
WORK_KINDS = ('linearisations', 'gradients', 'costs', 'factorisations')


class WorkCount:
    """Counts of :data:`WORK_KINDS` per part of :data:`WORK_PARTS` while :func:`counted_work`
    is active; :meth:`take` returns ``{(part, kind): count}`` since the last call."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts: dict[tuple[str, str], int] = defaultdict(int)
        self._local = threading.local()

    def parts(self) -> list[str]:
        """This thread's parts in progress, innermost last."""
        parts = getattr(self._local, 'parts', None)
        if parts is None:
            parts = self._local.parts = []
        return parts

    def add(self, kind: str) -> None:
        parts = self.parts()
        with self._lock:
            self._counts[(parts[-1] if parts else 'other', kind)] += 1

    def take(self) -> dict[tuple[str, str], int]:
        with self._lock:
            out, self._counts = dict(self._counts), defaultdict(int)
        return out


@contextmanager
def counted_work() -> Iterator[WorkCount]:
    """Count the linearisations, gradient passes, cost evaluations and factorisations
    (:data:`WORK_KINDS`) by part (:data:`WORK_PARTS`) into a :class:`WorkCount` (the functions
    wrapped while active, then put back)."""
    count = WorkCount()

    def part(name: str, fn):
        def in_part(*args, **kwargs):
            parts = count.parts()
            parts.append(name)
            try:
                return fn(*args, **kwargs)
            finally:
                parts.pop()
        return in_part

    def counted(kind: str, fn):
        def call(*args, **kwargs):
            count.add(kind)
            return fn(*args, **kwargs)
        return call

    gradient = inspect.getattr_static(_Problem, 'gradient')

    def gradient_pass(self, T, v):
        # a pass of its own: not the one gradient_ahead computed at this T, nor the
        # linear_system (counted) that the NumPy paths run instead
        if self._ahead[0] is not T and self.fused_gradient:
            count.add('gradients')
        return gradient(self, T, v)

    wrapped = [(owner, name, part(p, inspect.getattr_static(owner, name)))
               for p, targets in WORK_PARTS.items() for owner, name in targets]
    wrapped += [(_Problem, 'linear_system',
                 counted('linearisations', inspect.getattr_static(_Problem, 'linear_system'))),
                (_Problem, 'cost_at',
                 counted('costs', inspect.getattr_static(_Problem, 'cost_at'))),
                (_Problem, 'gradient', gradient_pass),
                (_cholmod.SparseCholesky, 'refactor',
                 counted('factorisations',
                         inspect.getattr_static(_cholmod.SparseCholesky, 'refactor')))]
    saved = [(owner, name, inspect.getattr_static(owner, name)) for owner, name, _ in wrapped]
    try:
        for owner, name, fn in wrapped:
            setattr(owner, name, fn)
        yield count
    finally:
        for owner, name, fn in reversed(saved):
            setattr(owner, name, fn)
