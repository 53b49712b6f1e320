"""BLAS settings chosen by the library itself (issue 10, item 6)."""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys

import numpy as np
import pytest
from threadpoolctl import threadpool_info

from ga_ros import runtime


def _python_lines(code: str) -> list[str]:
    """What a fresh interpreter running ``code`` prints, line by line."""
    return subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                          check=True).stdout.splitlines()


def _blas_threads() -> set[int]:
    return {i['num_threads'] for i in threadpool_info() if i['user_api'] == 'blas'}


def test_blas_threads_context_limits_every_pool_and_restores_it():
    import ga_ros.core.linalg.cholmod  # noqa: F401  (loads CHOLMOD's OpenBLAS too)

    before = {i['filepath']: i['num_threads'] for i in threadpool_info()}
    with runtime.blas_threads(1):
        assert _blas_threads() == {1}
    after = {i['filepath']: i['num_threads'] for i in threadpool_info()}
    assert after == before


def test_solve_runs_inside_the_thread_limit(monkeypatch):
    """solve() enters the limit itself, so a plain `import ga_ros.core` user gets it."""
    from ga_ros.core import solver
    from ga_ros.core.network import ConnectionNetwork
    from ga_ros.core.solver import iterate

    seen = []
    real = iterate._iterate

    def spy(prob, T, **kwargs):
        seen.append(_blas_threads())
        return real(prob, T, **kwargs)

    monkeypatch.setattr(iterate, '_iterate', spy)
    net = ConnectionNetwork()
    for i in range(3):
        net.add_node(i)
    net.add_connection(0, 1, [1, 0, 0, 0, 0, 0], np.eye(6))
    net.add_connection(1, 2, [1, 0, 0, 0, 0, 0], np.eye(6))
    solver.solve(net, solver.initial_guess_f2f(net))
    assert seen == [{runtime.default_blas_threads()}]


@pytest.mark.skipif(runtime.best_openblas_coretype() is None,
                    reason='OpenBLAS detects the kernel itself on this CPU')
def test_cholmod_openblas_runs_the_kernel_chosen_for_this_cpu():
    """The cvxopt wheel's OpenBLAS 0.3.15 would fall back to Prescott on newer CPUs; the
    library chooses the kernel from the CPU flags, without leaking OPENBLAS_CORETYPE."""
    code = ('import os, ga_ros.core.linalg.cholmod; from threadpoolctl import threadpool_info; '
            "print([i['architecture'] for i in threadpool_info() if 'cvxopt' in i['filepath']]"
            "[0], os.environ.get('OPENBLAS_CORETYPE'))")
    env = {k: v for k, v in __import__('os').environ.items() if k != 'OPENBLAS_CORETYPE'}
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         env=env, check=True).stdout.split()
    assert out == [runtime.best_openblas_coretype(), 'None']


def test_import_scipy_leaves_unused_numpy_submodules_unloaded_but_reachable():
    """The start-up shortcut of runtime.import_scipy: SciPy's copy of the numpy namespace is
    built without importing numpy.testing / f2py / ma, and still reaches them on access."""
    code = ('import sys\n'
            'from ga_ros.runtime import import_scipy\n'
            'import_scipy()\n'
            'import scipy.sparse.csgraph, scipy.linalg\n'
            "print(sorted(m for m in ('numpy.testing', 'numpy.f2py', 'numpy.ma') "
            'if m in sys.modules))\n'
            'import numpy\n'
            'import scipy._lib.array_api_compat.numpy as compat\n'
            'print(compat.testing is numpy.testing, compat.ma.masked is numpy.ma.masked)\n'
            "print('testing' in numpy.__all__, 'testing' in dir(numpy))\n")
    assert _python_lines(code) == ['[]', 'True True', 'True True']


def test_lazy_import_imports_on_first_use_and_entry_points_import_scipy_cheaply():
    """runtime.lazy_import defers the import to the first attribute access; after an entry
    point's limit_blas_threads(), the first SciPy submodule import goes through import_scipy
    (SciPy's copy of the numpy namespace without numpy.testing / f2py / ma)."""
    code = ('import sys\n'
            'from ga_ros.runtime import lazy_import, limit_blas_threads\n'
            "fr = lazy_import('fractions')\n"
            "print('fractions' in sys.modules, fr.Fraction(2, 6) == fr.Fraction(1, 3),\n"
            "      'fractions' in sys.modules)\n"
            'keep = limit_blas_threads()\n'
            'import scipy.sparse.csgraph\n'
            "print(sorted(m for m in ('numpy.testing', 'numpy.f2py', 'numpy.ma') "
            'if m in sys.modules))\n')
    assert _python_lines(code) == ['False True True', '[]']


def test_library_scans_do_not_repeat_in_every_solve():
    """The entry point's limit_blas_threads() and solve()'s blas_threads() share one
    ThreadpoolController, scanned again only when modules were imported since (the first
    solve imports the solver's modules): threadpoolctl's scan of the loaded libraries does not
    run inside each timed solve; the limit holds in the solve and after it."""
    code = ('import numpy as np, threadpoolctl\n'
            'count = [0]\n'
            'init = threadpoolctl.ThreadpoolController.__init__\n'
            'def counted(self, *a, **k):\n'
            '    count[0] += 1\n'
            '    init(self, *a, **k)\n'
            'threadpoolctl.ThreadpoolController.__init__ = counted\n'
            'from ga_ros.runtime import limit_blas_threads\n'
            'keep = limit_blas_threads(1)\n'
            'from ga_ros.core import solver\n'
            'from ga_ros.core.network import ConnectionNetwork\n'
            'net = ConnectionNetwork()\n'
            'for i in range(3):\n'
            '    net.add_node(i)\n'
            'net.add_connection(0, 1, [1, 0, 0, 0, 0, 0], np.eye(6))\n'
            'net.add_connection(1, 2, [1, 0, 0, 0, 0, 0], np.eye(6))\n'
            'solver.solve(net, solver.initial_guess_f2f(net))\n'
            'first = count[0]\n'
            'for _ in range(3):\n'
            '    solver.solve(net, solver.initial_guess_f2f(net))\n'
            'scans = count[0] - first\n'
            'info = threadpoolctl.threadpool_info()  # a scan of its own\n'
            "print(scans, sorted({i['num_threads'] for i in info if i['user_api'] == 'blas'}))\n")
    assert _python_lines(code)[-1] == '0 [1]'


@pytest.mark.parametrize('tuned', [False, True])
def test_keep_freed_memory_serves_large_arrays_from_the_heap(tuned):
    """runtime.keep_freed_memory (a batch solve's process): a 4 MiB array comes from the heap
    (glibc's mallinfo2: no new mmapped block) instead of its own mapping, as by default."""
    code = ('import ctypes, sys\n'
            'import numpy as np\n'
            'from ga_ros.runtime import keep_freed_memory\n'
            'class Info(ctypes.Structure):\n'
            "    _fields_ = [(n, ctypes.c_size_t) for n in ('arena', 'ordblks', 'smblks',\n"
            "                'hblks', 'hblkhd', 'usmblks', 'fsmblks', 'uordblks', 'fordblks',\n"
            "                'keepcost')]\n"
            'try:\n'
            '    info = ctypes.CDLL(None).mallinfo2\n'
            'except AttributeError:\n'
            "    print('skip'); sys.exit()\n"
            'info.restype = Info\n'
            f'print(keep_freed_memory() if {tuned} else False)\n'
            'before = info().hblks\n'
            'a = np.ones(1 << 19)\n'
            'print(info().hblks - before)\n')
    out = _python_lines(code)
    if out == ['skip']:
        pytest.skip('not glibc >= 2.33')
    assert out == (['True', '0'] if tuned else ['False', '1'])


def test_blas_libraries_load_with_the_entry_points_thread_count():
    """In a fresh process without ``OPENBLAS_NUM_THREADS``, the entry point's libraries (NumPy's,
    SciPy's, cvxopt's OpenBLAS) start with :func:`runtime.default_blas_threads` threads (no
    pool to shrink) and the variable is gone again afterwards (child processes get the
    environment as it was); a user's own setting is left as it is."""
    code = ('import os\n'
            'from ga_ros import runtime\n'
            'with runtime.openblas_threads_at_load(1):\n'
            '    inside = os.environ.get("OPENBLAS_NUM_THREADS")\n'
            '    import numpy\n'
            '    runtime._preload_scipy_blas()\n'
            'from threadpoolctl import threadpool_info\n'
            'print(inside, os.environ.get("OPENBLAS_NUM_THREADS"),\n'
            '      sorted({i["num_threads"] for i in threadpool_info()\n'
            '              if i["internal_api"] == "openblas"}))\n')
    env = {k: v for k, v in os.environ.items() if k not in ('OPENBLAS_NUM_THREADS',
                                                            'OMP_NUM_THREADS')}
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         env=env, check=True).stdout.split()
    assert out[:2] == ['1', 'None'] and out[2:] == ['[1]']
    env['OPENBLAS_NUM_THREADS'] = '2'
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True,
                         env=env, check=True).stdout.split()
    assert out[:2] == ['2', '2']  # the user's setting, untouched


@pytest.mark.skipif(importlib.util.find_spec('numba') is None
                    or importlib.util.find_spec('coverage') is None,
                    reason='needs numba and coverage installed (numba imports coverage then)')
@pytest.mark.skipif('COV_CORE_SOURCE' in os.environ,
                    reason='under pytest-cov every subprocess starts inside a coverage run')
def test_compiled_kernels_load_without_coverage_unless_a_coverage_run_loaded_it():
    """numba imports ``coverage`` when installed; a kernel loaded outside a coverage run must not
    (its CPU is the start-up of every process that loads one), and one inside a coverage run
    must keep numba's coverage support. A later ``import coverage`` still works."""
    outside = _python_lines(
        'import sys\n'
        'from ga_ros.core import kernels\n'
        'kernels._compile()\n'
        'import numpy as np\n'
        'out = np.zeros(3)\n'
        'kernels._so3_log(np.eye(3), out)\n'
        'import numba.misc.coverage_support as c\n'
        "print('coverage' in sys.modules, c.coverage_available, out.tolist())\n"
        'import coverage\n'
        "print(coverage.Coverage is not None)\n")
    assert outside == ['False False [0.0, 0.0, 0.0]', 'True']
    inside = _python_lines(
        'import sys, coverage\n'
        'from ga_ros import runtime\n'
        'runtime.import_numba()\n'
        'import numba.misc.coverage_support as c\n'
        'print(c.coverage_available)\n')
    assert inside == ['True']
