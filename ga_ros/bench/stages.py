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
