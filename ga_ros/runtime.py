"""Process-level settings that entry points (CLI, nodes, benchmarks) apply once at start-up."""

from __future__ import annotations

import os

from threadpoolctl import threadpool_limits


def limit_blas_threads(n: int | None = None) -> threadpool_limits:
    """Limit the BLAS/LAPACK thread pools (NumPy's and CHOLMOD's OpenBLAS) to ``n`` threads.

    The solver works on many small dense blocks; with OpenBLAS's default one thread per core,
    a machine whose cores are shared with other processes (a robot's computer, CI) spends most
    of the time in spinning threads: a 234 x 234 Cholesky was measured 100x slower. The default
    ``n`` is ``$GA_ROS_BLAS_THREADS`` or 1. Keep the returned object alive for the limit to hold.
    """
    import numpy  # noqa: F401  (threadpoolctl only sees libraries that are loaded)
    import scipy.linalg  # noqa: F401

    try:
        import cvxopt  # noqa: F401
    except ImportError:  # pragma: no cover
        pass
    if n is None:
        n = int(os.environ.get('GA_ROS_BLAS_THREADS', '1'))
    return threadpool_limits(limits=max(1, int(n)), user_api='blas')
