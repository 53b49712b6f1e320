"""LAPACK and BLAS routines called from the compiled (numba) kernels, and the band
completion's kernel.

SciPy's LAPACK/BLAS (``scipy.linalg.cython_lapack``, ``cython_blas``: the OpenBLAS SciPy
bundles) is registered with LLVM under named symbols (``ga_ros_<name>``), so the kernels that
call it stay cacheable on disk (a ctypes pointer would not). Used by the selected inversion
(:mod:`ga_ros.core.linalg.selinv`) and the maximum-entropy band completion
(:func:`ga_ros.core.linalg.completion._band_completion`).
"""

from __future__ import annotations

import ctypes
import threading

import numpy as np

from ga_ros.core.kernels import AVAILABLE, jit

#: The kernels here are compiled (numba installed, ``GA_ROS_JIT`` not ``0``); without, callers
#: take their NumPy/SciPy path.
COMPILED = AVAILABLE
#: Number of arguments (all pointers, Fortran convention) of each routine the kernels call.
_ARGUMENTS = {'dtrtri': 6, 'dlauum': 5, 'dtrmm': 11, 'dgemm': 13, 'dpotrf': 5, 'dpotrs': 8}
_HANDLES: dict = {}
_LOCK = threading.Lock()
_dpotrf = _dpotrs = None  # the handles _separator_solves calls (set before compiling it)
_SEPARATORS = None  # _separator_solves, compiled


def _register(name: str) -> bool:
    """Register SciPy's LAPACK (or BLAS) routine ``name`` with LLVM as ``ga_ros_<name>``;
    ``False`` if it cannot be found."""
    try:
        import llvmlite.binding as llvm
        from scipy.linalg import cython_blas, cython_lapack

        api = ctypes.pythonapi
        api.PyCapsule_GetName.restype = ctypes.c_char_p
        api.PyCapsule_GetName.argtypes = [ctypes.py_object]
        api.PyCapsule_GetPointer.restype = ctypes.c_void_p
        api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        table = cython_lapack.__pyx_capi__
        cap = table[name] if name in table else cython_blas.__pyx_capi__[name]
        address = api.PyCapsule_GetPointer(cap, api.PyCapsule_GetName(cap))
        llvm.add_symbol(f'ga_ros_{name}', address)
    except (ImportError, KeyError, ValueError, TypeError):  # pragma: no cover
        return False
    return True


def routines(*names: str) -> tuple | None:
    """numba handles (``ExternalFunction``, every argument a pointer) of the named routines,
    for a kernel to call; ``None`` if one cannot be registered (the caller's other path)."""
    from ga_ros.runtime import import_numba

    numba = import_numba()

    with _LOCK:
        for name in names:
            if name not in _HANDLES:
                if not _register(name):
                    return None
                _HANDLES[name] = numba.types.ExternalFunction(
                    f'ga_ros_{name}', numba.types.void(*[numba.types.intp] * _ARGUMENTS[name]))
        return tuple(_HANDLES[name] for name in names)


def _separator_solves(ext, r, w, d, Bt):  # pragma: no cover - compiled
    """``Bt[k] = Sigma_FF^-1 Sigma_Fk`` for the separators ``F = {k+1 .. k+w}`` of a covariance
    band ``ext`` (``(r + w, w + 1, d, d)``, ``ext[i, j] = Sigma_{i, i+j}``, padded after the end)
    by one Cholesky factorisation (``dpotrf``) and solve (``dpotrs``) each, the separator read
    from the band into column-major storage
    (:func:`ga_ros.core.linalg.completion._separator_solves_scipy`
    does the same with SciPy's LAPACK). Returns 0,
    or ``k + 1`` if separator ``k`` is not positive definite."""
    n = w * d
    S = np.empty((n, n)).T  # column-major
    Bk = np.empty((d, n)).T
    ints = np.array([n, d, 0], dtype=np.int32)  # n = lda = ldb, nrhs, info
    lower = np.array([76], dtype=np.int8)  # 'L'
    for k in range(r):
        for b in range(w):  # lower triangle: block (a, b), a >= b, is ext[k+1+b, a-b]'
            for a in range(b, w):
                blk = ext[k + 1 + b, a - b]
                for y in range(d):
                    for x in range(d):
                        S[a * d + x, b * d + y] = blk[y, x]
        for a in range(w):
            blk = ext[k, 1 + a]
            for y in range(d):
                for x in range(d):
                    Bk[a * d + x, y] = blk[y, x]
        _dpotrf(lower.ctypes.data, ints.ctypes.data, S.ctypes.data, ints.ctypes.data,
                ints.ctypes.data + 8)
        if ints[2]:
            return k + 1
        _dpotrs(lower.ctypes.data, ints.ctypes.data, ints.ctypes.data + 4, S.ctypes.data,
                ints.ctypes.data, Bk.ctypes.data, ints.ctypes.data, ints.ctypes.data + 8)
        Bt[k] = Bk
    return 0


def separator_solves(ext: np.ndarray, r: int, w: int, d: int, Bt: np.ndarray) -> int | None:
    """:func:`_separator_solves`, compiled on first use; ``None`` if it cannot be (no numba,
    ``GA_ROS_JIT=0`` or the routines not found: the caller solves with SciPy instead)."""
    global _dpotrf, _dpotrs, _SEPARATORS
    if not COMPILED:
        return None
    if _SEPARATORS is None:
        handles = routines('dpotrf', 'dpotrs')
        if handles is None:  # pragma: no cover - SciPy without them
            return None
        _dpotrf, _dpotrs = handles
        _SEPARATORS = jit(_separator_solves)
    return int(_SEPARATORS(ext, r, w, d, Bt))
