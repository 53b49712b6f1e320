"""Stacks of small matrices with runs of equal ones (a source's connections mostly share its
stated covariance): a per-matrix function applied once per run."""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray

#: From this many matrices on, :func:`by_runs` looks for runs of equal ones.
RUNS_FROM = 32


def by_runs(fn, M: FloatArray) -> FloatArray:
    """``fn(M)`` for a function ``fn`` of a stack ``(m, k, k)`` that treats each matrix alone
    (``np.linalg.cholesky``, :func:`~ga_ros.core.linalg.completion.spd_inverse`): from
    :data:`RUNS_FROM` matrices on, when at least half of them equal the one before, bit for
    bit, applied to the first of each run of equal ones and gathered (fresh rows, the same
    bits)."""
    M = np.asarray(M)
    if M.ndim == 3 and M.shape[0] >= RUNS_FROM and M.dtype == np.float64:
        flat = np.ascontiguousarray(M).reshape(M.shape[0], -1).view(np.int64)  # exact bits
        new = np.empty(M.shape[0], dtype=bool)
        new[0] = True
        np.any(flat[1:] != flat[:-1], axis=1, out=new[1:])
        starts = np.flatnonzero(new)
        if 2 * starts.size <= M.shape[0]:
            return fn(M[starts])[np.cumsum(new) - 1]
    return fn(M)
