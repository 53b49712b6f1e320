"""Process-level settings of the BLAS libraries, applied by the library itself.

* :func:`blas_threads`: the solver wraps its dense and sparse factorisations in this context, so a
  user importing :mod:`ga_ros.core` gets the benchmark's speed without pinning threads.
* :func:`openblas_coretype`: the OpenBLAS bundled in the cvxopt wheel (0.3.15) does not recognise
  recent CPUs (AMD Zen 3/4, Intel Sapphire Rapids...) and falls back to its oldest x86-64 kernel
  (``Prescott``); CHOLMOD's dense supernodal updates then run 1.5-3x slower. The kernel is chosen
  from the CPU flags while cvxopt loads, without leaking the setting to other libraries or child
  processes.
* :func:`limit_blas_threads`: a process-wide limit that entry points (CLI, nodes) keep alive;
  :func:`openblas_threads_at_load`: the same thread count while the libraries load (the CLI).
* :func:`keep_freed_memory`: glibc's allocator tuned for a short batch process;
  :func:`fewer_collections`: the garbage collector's thresholds for a command-line process.
* :func:`import_scipy`: SciPy's first import without the NumPy submodules it never uses
  (start-up of the command line; the entry points run it before the first SciPy submodule is
  imported), :func:`lazy_import`: a module imported on first use.
* :func:`import_numba`: numba without its coverage support in a process that is not measuring
  coverage (numba imports ``coverage`` whenever it is installed: ~0.1 s of CPU per process).
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.util
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from threadpoolctl import ThreadpoolController

_controller: ThreadpoolController | None = None
#: ``len(sys.modules)`` when :data:`_controller` scanned the loaded libraries.
_controller_modules = -1


def default_blas_threads() -> int:
    """``$GA_ROS_BLAS_THREADS`` or 1: the solver's dense blocks are small (a few hundred rows), and
    a threaded OpenBLAS spins on cores that other processes hold, which makes such a Cholesky up
    to two orders of magnitude slower (figures: docs/benchmarks.md, "Figures behind constants")."""
    try:
        return max(1, int(os.environ.get('GA_ROS_BLAS_THREADS', '1')))
    except ValueError:
        return 1


#: NumPy submodules that NumPy imports lazily and SciPy's solve path never uses.
_UNUSED_NUMPY_SUBMODULES = ('testing', 'f2py', 'ma', 'polynomial', 'ctypeslib', 'char', 'rec',
                            'strings', 'matlib')


def import_scipy() -> None:
    """Import SciPy's array-API layer without importing NumPy submodules it does not use.

    SciPy 1.17's first import of any submodule builds a copy of the ``numpy`` namespace
    (``scipy._lib.array_api_compat.numpy``) with ``from numpy import *`` and ``getattr`` over
    ``dir(numpy)``, which imports every lazily loaded NumPy submodule: ``numpy.testing``
    (``unittest``), ``numpy.f2py`` (a Fortran parser compiling ~100 regular expressions),
    ``numpy.ma``, ... -- 0.15-0.4 s of every process's start-up (``python -X importtime``). Here
    the copy is built while those submodules are hidden from ``numpy.__all__`` and ``dir(numpy)``,
    and a module ``__getattr__`` (PEP 562) on the copy forwards any later access to ``numpy``,
    so attribute access behaves as before (the submodule is imported on first use). Nothing is
    changed when SciPy's layer is already imported.
    """
    if 'scipy._lib._array_api' in sys.modules:
        return
    import numpy

    hidden = {n for n in _UNUSED_NUMPY_SUBMODULES if f'numpy.{n}' not in sys.modules}
    all_names, dir_fn = numpy.__all__, numpy.__dir__
    numpy.__all__ = [n for n in all_names if n not in hidden]
    numpy.__dir__ = lambda: [n for n in dir_fn() if n not in hidden]
    try:
        import scipy._lib._array_api  # noqa: F401
    except ImportError:  # another SciPy layout: nothing to speed up
        pass
    finally:
        numpy.__all__, numpy.__dir__ = all_names, dir_fn
    compat = sys.modules.get('scipy._lib.array_api_compat.numpy')
    if compat is not None and not hasattr(compat, '__getattr__'):
        compat.__getattr__ = lambda name: getattr(numpy, name)


class _LazyModule:
    """Stands for a module until its first attribute access, which imports it."""

    def __init__(self, name: str) -> None:
        self._name = name

    def __getattr__(self, attr: str):
        return getattr(importlib.import_module(self._name), attr)

    def __repr__(self) -> str:
        return f'<lazy module {self._name!r}>'


def import_numba():
    """The ``numba`` module, imported without loading ``coverage`` unless it is already loaded.

    numba's coverage support (``numba.misc.coverage_support``) imports ``coverage`` whenever the
    package is installed (a test or development environment), ~0.1 s of CPU and 10 MiB in every
    process that loads a compiled kernel, to report compiled lines to a coverage run. Outside a
    coverage run (``coverage`` not in ``sys.modules``) the import is blocked while numba loads
    and unblocked afterwards, so a later ``import coverage`` works; numba then reports no compiled
    lines, which only a coverage run started after the first kernel would have wanted.
    """
    numba = sys.modules.get('numba')
    if numba is not None:
        return numba
    if 'coverage' in sys.modules:
        import numba
        return numba
    sys.modules['coverage'] = None  # type: ignore[assignment]  # import coverage -> ImportError
    try:
        import numba
    finally:
        if 'coverage' in sys.modules and sys.modules['coverage'] is None:
            del sys.modules['coverage']
    return numba


def lazy_import(name: str):
    """Module ``name``, imported on its first attribute access.

    For modules that a module needs in some functions only: ``sp = lazy_import('scipy.sparse')``
    at the top keeps ``sp.csr_matrix(...)`` as written, while a process that never touches
    ``sp`` (a batch solve of a g2o file) never pays for importing it (~0.15 s of start-up for
    ``scipy.sparse``). Nothing is looked up until then (an ``import`` elsewhere imports the
    module as usual); an attribute access costs one ``sys.modules`` look-up more.
    """
    return sys.modules.get(name) or _LazyModule(name)


class _ScipyFirst:
    """``sys.meta_path`` hook: before the first import of a SciPy submodule, run
    :func:`import_scipy` (once; the hook then removes itself)."""

    @classmethod
    def find_spec(cls, name: str, path=None, target=None):
        if name.startswith('scipy.'):
            with contextlib.suppress(ValueError):
                sys.meta_path.remove(cls)
            import_scipy()
        return None


def scipy_imports_trimmed() -> None:
    """Run :func:`import_scipy` before the first import of a SciPy submodule, whoever imports
    it (nothing is imported now; the entry points call it first)."""
    if 'scipy._lib._array_api' not in sys.modules and _ScipyFirst not in sys.meta_path:
        sys.meta_path.insert(0, _ScipyFirst)


def _load_blas() -> None:
    import numpy  # noqa: F401  (threadpoolctl only sees libraries that are loaded)

    scipy_imports_trimmed()  # import_scipy() when a submodule is first needed
    _preload_scipy_blas()
    with contextlib.suppress(ImportError), openblas_coretype():
        import cvxopt  # noqa: F401  (its bundled OpenBLAS, with the kernel for this CPU)


def _preload_scipy_blas() -> None:
    """Load the OpenBLAS bundled in the SciPy wheel (``scipy.libs/libscipy_openblas*.so``)
    without importing ``scipy.linalg``, so that a thread limit set now covers it.

    Importing ``scipy.linalg`` costs ~0.15 s of start-up (it parses its docstrings), and a batch
    solve never uses it; the library is found without importing ``scipy`` either (~15 ms). When
    ``scipy.linalg`` is imported later, the dynamic loader finds the library already loaded
    (same soname) and the limit holds. A SciPy without a bundled OpenBLAS (a system build) is
    left alone: its BLAS is limited once it is loaded.
    """
    try:
        spec = importlib.util.find_spec('scipy')  # does not import it
    except (ImportError, ValueError):
        return
    if spec is None or not spec.submodule_search_locations:
        return
    libs = Path(list(spec.submodule_search_locations)[0]).resolve().parent / 'scipy.libs'
    for lib in sorted(libs.glob('libscipy_openblas*.so*')):
        with contextlib.suppress(OSError):
            ctypes.CDLL(str(lib))


def _blas_controller() -> ThreadpoolController:
    """The process's thread-pool controller: loading the BLAS libraries and threadpoolctl's scan
    of the loaded libraries are paid by the entry point's :func:`limit_blas_threads` or else by
    the first :func:`blas_threads`, and again only when modules were imported since the last
    scan (an extension module such as OpenCV's or rclpy's may bring a BLAS pool of its own,
    which a controller made before it would not limit)."""
    global _controller, _controller_modules
    if _controller is None or len(sys.modules) != _controller_modules:
        if _controller is None:
            _load_blas()
        _controller = ThreadpoolController()
        _controller_modules = len(sys.modules)
    return _controller


def limit_blas_threads(n: int | None = None) -> contextlib.AbstractContextManager:
    """Limit the BLAS/LAPACK thread pools (NumPy's, SciPy's and CHOLMOD's OpenBLAS) to ``n``
    threads until the returned object's ``restore_original_limits()`` (or the end of its
    ``with`` block).

    The default ``n`` is :func:`default_blas_threads`. Keep the returned object for as long as
    the limit is meant to hold.
    """
    return _blas_controller().limit(
        limits=default_blas_threads() if n is None else max(1, int(n)), user_api='blas')


#: :func:`background_blas_limit`'s process-wide limit, once set (kept for the process's life).
_BACKGROUND_LIMIT: list = []


def background_blas_limit() -> None:
    """Set the process-wide BLAS thread limit (:func:`limit_blas_threads`, the one the
    update's :func:`blas_threads` contexts use) once and keep it, before work starts in a
    background thread (the window's freeze ahead, the online calibration's estimate): that
    thread runs under it, since a :func:`blas_threads` context entered there would restore the
    update thread's limits midway. Call it outside any :func:`blas_threads` context."""
    if not _BACKGROUND_LIMIT:
        _BACKGROUND_LIMIT.append(limit_blas_threads())


@contextlib.contextmanager
def blas_threads(n: int | None = None) -> Iterator[None]:
    """Context in which the BLAS pools use ``n`` threads (default :func:`default_blas_threads`).

    The libraries are inspected once per process (:func:`_blas_controller`), so entering the
    context costs microseconds and can wrap every solve.
    """
    with limit_blas_threads(n):
        yield


#: :func:`fewer_collections`: the collector's thresholds (allocations, gen-0 runs, gen-1 runs).
COMMAND_GC_THRESHOLDS = (50_000, 20, 100)


def fewer_collections() -> None:
    """Run the cyclic garbage collector less often in a command-line process.

    CPython's default (a generation-0 pass every 700 container allocations) runs ~50 passes,
    some over every live object, while a command imports its modules and reads its input:
    ~4 % of the CPU of a small ``ga-ros solve`` process (docs/benchmarks.md, "Start-up"). The
    thresholds :data:`COMMAND_GC_THRESHOLDS` keep cycles collected (every 50,000 allocations)
    at a memory cost of a few MiB at most; the entry point sets them once, before importing.
    """
    import gc

    gc.set_threshold(*COMMAND_GC_THRESHOLDS)


#: glibc's ``mallopt`` parameters (malloc.h).
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3


def keep_freed_memory(mmap_threshold_mib: int = 64, trim_threshold_mib: int = 128) -> bool:
    """Let glibc's allocator serve blocks below ``mmap_threshold_mib`` from the heap and keep
    up to ``trim_threshold_mib`` of freed heap, for a short process that allocates many
    same-sized temporaries (a batch solve: each iteration's ``(m, 6, 6)`` arrays).

    By default glibc maps every block above 128 KiB (raised dynamically up to 32 MiB) with
    ``mmap`` and unmaps it when freed, so the next iteration's temporaries fault their pages in
    again, about a tenth of a short solve's CPU (docs/benchmarks.md, "Figures behind constants
    in the code"). A long-running process (a node)
    keeps glibc's defaults. Returns whether the settings took (glibc's ``mallopt`` found and
    accepting them); elsewhere (another C library, another OS) nothing is changed.
    """
    if not sys.platform.startswith('linux'):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the process's C library
    except (OSError, AttributeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return (mallopt(_M_MMAP_THRESHOLD, int(mmap_threshold_mib) << 20) == 1
            and mallopt(_M_TRIM_THRESHOLD, int(trim_threshold_mib) << 20) == 1)


def _cpu_flags() -> set[str]:
    try:
        with open('/proc/cpuinfo', encoding='ascii', errors='replace') as f:
            for line in f:
                if line.startswith('flags'):
                    return set(line.split(':', 1)[1].split())
    except OSError:
        pass
    return set()


def best_openblas_coretype() -> str | None:
    """OpenBLAS kernel name for this x86-64 CPU (``SkylakeX`` with AVX-512, ``Haswell`` with
    AVX2 + FMA), or ``None`` elsewhere (ARM64 and older CPUs: OpenBLAS's own detection)."""
    if hasattr(os, 'uname'):  # POSIX: without importing `platform` (start-up)
        machine = os.uname().machine
    else:  # pragma: no cover
        import platform

        machine = platform.machine()
    if machine.lower() not in ('x86_64', 'amd64'):
        return None
    flags = _cpu_flags()
    if {'avx512f', 'avx512bw', 'avx512vl', 'avx512dq'} <= flags:
        return 'SkylakeX'
    if {'avx2', 'fma'} <= flags:
        return 'Haswell'
    return None


#: OpenBLAS's variables for its thread count, read once when a library loads.
_OPENBLAS_THREAD_VARIABLES = ('OPENBLAS_NUM_THREADS',)


@contextlib.contextmanager
def openblas_threads_at_load(n: int | None = None) -> Iterator[None]:
    """Set ``OPENBLAS_NUM_THREADS`` to ``n`` (default :func:`default_blas_threads`; unless the
    user set it) while the BLAS libraries load, restored afterwards (child processes get the
    environment as it was).

    An OpenBLAS that loads with more threads starts a pool whose threads spin before they
    sleep, and :func:`limit_blas_threads` then shrinks it: ~0.08 s of CPU of a small
    ``ga-ros solve`` process for NumPy's, SciPy's and cvxopt's libraries on 2 cores
    (docs/benchmarks.md, "Start-up"). Loaded within this context, each library starts with
    ``n`` threads, the limit the entry point keeps anyway. For entry points only: in a
    library user's process the libraries keep the thread count they load with.
    """
    if any(v in os.environ for v in _OPENBLAS_THREAD_VARIABLES):
        yield
        return
    os.environ['OPENBLAS_NUM_THREADS'] = str(default_blas_threads() if n is None
                                             else max(1, int(n)))
    try:
        yield
    finally:
        os.environ.pop('OPENBLAS_NUM_THREADS', None)


@contextlib.contextmanager
def openblas_coretype() -> Iterator[None]:
    """Set ``OPENBLAS_CORETYPE`` (unless the user did) while a bundled OpenBLAS loads; the
    variable is restored afterwards, so it reaches neither NumPy's OpenBLAS (already loaded and
    detecting correctly) nor child processes."""
    if 'OPENBLAS_CORETYPE' in os.environ:
        yield
        return
    core = best_openblas_coretype()
    if core is None:
        yield
        return
    os.environ['OPENBLAS_CORETYPE'] = core
    try:
        yield
    finally:
        os.environ.pop('OPENBLAS_CORETYPE', None)
