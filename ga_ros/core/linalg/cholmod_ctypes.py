"""CHOLMOD reached through ``ctypes`` (the library bundled in the cvxopt wheel, CHOLMOD 3 of
SuiteSparse 5): its structs, the symbolic analysis and numeric factorisation called on NumPy's
own arrays (:class:`_DirectCholmod`), and a supernodal factor's arrays viewed in place
(:func:`_supernodal_layout`, read by selected inversion).

Every layout is checked against CHOLMOD 3's documented defaults before use; on any other build
these return ``None`` and :class:`ga_ros.core.linalg.cholmod.SparseCholesky` keeps to cvxopt's
interface.
"""

from __future__ import annotations

import ctypes
import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg.blocks import BlockPattern, _expand_cols, _permutation_kernel, _Permuted

#: CHOLMOD's ordering codes (cholmod_core.h).
_CHOLMOD_GIVEN, _CHOLMOD_AMD = 1, 2


class _CholmodFactor(ctypes.Structure):
    """``cholmod_factor`` of CHOLMOD 3 (SuiteSparse 5, bundled in the cvxopt wheel)."""

    _fields_ = ([(f, ctypes.c_size_t) for f in ('n', 'minor')]
                + [(f, ctypes.c_void_p) for f in ('Perm', 'ColCount', 'IPerm')]
                + [('nzmax', ctypes.c_size_t)]
                + [(f, ctypes.c_void_p) for f in ('p', 'i', 'x', 'z', 'nz', 'next', 'prev')]
                + [(f, ctypes.c_size_t) for f in ('nsuper', 'ssize', 'xsize', 'maxcsize',
                                                  'maxesize')]
                + [(f, ctypes.c_void_p) for f in ('super', 'pi', 'px', 's')]
                + [(f, ctypes.c_int) for f in ('ordering', 'is_ll', 'is_super', 'is_monotonic',
                                               'itype', 'xtype', 'dtype', 'useGPU')])


class _CholmodSparse(ctypes.Structure):
    """``cholmod_sparse`` (CHOLMOD 3, SuiteSparse 5: the library bundled in the cvxopt wheel)."""

    _fields_ = ([(f, ctypes.c_size_t) for f in ('nrow', 'ncol', 'nzmax')]
                + [(f, ctypes.c_void_p) for f in ('p', 'i', 'nz', 'x', 'z')]
                + [(f, ctypes.c_int) for f in ('stype', 'itype', 'xtype', 'dtype', 'sorted',
                                               'packed')])


class _CommonHead(ctypes.Structure):
    """The first fields of ``cholmod_common`` (CHOLMOD 3), up to ``print``: read to check the
    layout (their defaults) before ``print`` is set to 0."""

    _fields_ = ([('dbound', ctypes.c_double), ('grow0', ctypes.c_double),
                 ('grow1', ctypes.c_double), ('grow2', ctypes.c_size_t),
                 ('maxrank', ctypes.c_size_t), ('supernodal_switch', ctypes.c_double)]
                + [(f, ctypes.c_int) for f in ('supernodal', 'final_asis', 'final_super',
                                               'final_ll', 'final_pack', 'final_monotonic',
                                               'final_resymbol')]
                + [('zrelax', ctypes.c_double * 3), ('nrelax', ctypes.c_size_t * 3)]
                + [(f, ctypes.c_int) for f in ('prefer_zomplex', 'prefer_upper',
                                               'quick_return_if_not_posdef', 'prefer_binary',
                                               'print')])


class _CholmodMethod(ctypes.Structure):
    """``cholmod_common.method[i]`` (CHOLMOD 3)."""

    _fields_ = ([(f, ctypes.c_double) for f in ('lnz', 'fl', 'prune_dense', 'prune_dense2',
                                                'nd_oksep')]
                + [('other_1', ctypes.c_double * 4), ('nd_small', ctypes.c_size_t),
                   ('other_2', ctypes.c_size_t * 4)]
                + [(f, ctypes.c_int) for f in ('aggressive', 'order_for_lu', 'nd_compress',
                                               'nd_camd', 'nd_components', 'ordering')]
                + [('other_3', ctypes.c_size_t * 4)])


class _CommonOrdering(ctypes.Structure):
    """``cholmod_common`` of CHOLMOD 3 up to ``postorder``: the fields of the symbolic
    analysis that cvxopt's ``cholmod.symbolic`` sets from ``cholmod.options``."""

    _fields_ = (_CommonHead._fields_
                + [('precise', ctypes.c_int), ('try_catch', ctypes.c_int),
                   ('error_handler', ctypes.c_void_p), ('nmethods', ctypes.c_int),
                   ('current', ctypes.c_int), ('selected', ctypes.c_int),
                   ('method', _CholmodMethod * 10), ('postorder', ctypes.c_int),
                   ('default_nesdis', ctypes.c_int)])


def _defaults_of_cholmod3(c: _CommonOrdering) -> bool:
    """Whether a freshly started ``cholmod_common`` has CHOLMOD 3's documented defaults at the
    offsets of :class:`_CommonOrdering` (else the layout is another version's)."""
    m = c.method
    return (c.nmethods == 0 and c.postorder == 1 and c.default_nesdis == 0
            and [x.ordering for x in m] == [_CHOLMOD_GIVEN, _CHOLMOD_AMD, 3, 4, 0, 4, 4, 4, 5, 2]
            and [x.nd_small for x in m] == [200] * 5 + [20000, 4] + [200] * 3
            and [x.prune_dense for x in m] == [10.0] * 7 + [-1.0] + [10.0] * 2
            and all(x.prune_dense2 == -1.0 and x.nd_oksep == 1.0 and x.aggressive == 1
                    and x.order_for_lu == 0 and x.nd_compress == 1 for x in m))


class _DirectCholmod:
    """``cholmod_l_factorize`` of the CHOLMOD library that cvxopt loaded, called through
    ``ctypes`` on a ``cholmod_sparse`` header over the pattern's and the values' own arrays.

    cvxopt's ``cholmod.numeric`` copies the lower triangle (values and int64 row indices) into a
    new matrix on every call, and the caller had copied the values into a cvxopt matrix before;
    here CHOLMOD reads NumPy's arrays. Each thread has its own ``cholmod_common`` (the call
    releases the GIL: a background refinement may factor at the same time). The factor object
    stays cvxopt's (its analysis, solves and ``getfactor`` are cvxopt's).

    Parameters
    ----------
    path : the CHOLMOD shared library cvxopt loaded.
    model : makes a symbolic factor of cvxopt's own (any), whose capsule name and destructor
        the factors of :meth:`analyse` copy.
    """

    _COMMON_BYTES = 1 << 16  # larger than cholmod_common (a few KiB)

    def __init__(self, path: str, model: Callable[[], object]) -> None:
        lib = ctypes.CDLL(path)
        self._factorize = lib.cholmod_l_factorize
        self._factorize.restype = ctypes.c_int
        self._factorize.argtypes = [ctypes.c_void_p] * 3
        self._start = lib.cholmod_l_start
        self._start.argtypes = [ctypes.c_void_p]
        self._free_work = lib.cholmod_l_free_work
        self._free_work.argtypes = [ctypes.c_void_p]
        self._local = threading.local()
        self._capsule_pointer = ctypes.pythonapi.PyCapsule_GetPointer
        self._capsule_pointer.restype = ctypes.c_void_p
        self._capsule_pointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
        if self._common() is None:
            raise OSError('unexpected cholmod_common layout')
        self._analyze = lib.cholmod_l_analyze_p
        self._analyze.restype = ctypes.c_void_p
        self._analyze.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p,
                                  ctypes.c_size_t, ctypes.c_void_p]
        self._free_factor = lib.cholmod_l_free_factor
        self._free_factor.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        self._capsule = self._capsule_maker(model)

    def _capsule_maker(self, model: Callable[[], object]):
        """A function wrapping a ``cholmod_factor *`` into a capsule exactly as cvxopt's
        ``cholmod.symbolic`` does (its name string and its destructor, read from a factor of
        cvxopt's own), or ``None`` if the ordering fields of ``cholmod_common`` are not where
        CHOLMOD 3 has them (then the analysis stays cvxopt's)."""
        if not _defaults_of_cholmod3(_CommonOrdering.from_buffer(self._common())):
            return None
        api = ctypes.pythonapi
        get_name, get_destructor, new = (api.PyCapsule_GetName, api.PyCapsule_GetDestructor,
                                         api.PyCapsule_New)
        get_name.restype = get_destructor.restype = ctypes.c_void_p
        get_name.argtypes = get_destructor.argtypes = [ctypes.py_object]
        new.restype = ctypes.py_object
        new.argtypes = [ctypes.c_void_p] * 3
        self._model = model()  # kept: its name
        name, destructor = get_name(self._model), get_destructor(self._model)
        if ctypes.string_at(name) != b'CHOLMOD FACTOR D L' or not destructor:
            return None
        return lambda factor: new(factor, name, destructor)

    def analyse(self, pattern: BlockPattern, perm: IntArray, postorder: bool,
                auto: bool = False):
        """``cholmod_l_analyze_p`` of the lower-triangle pattern with the ordering ``perm``
        alone (cvxopt's ``symbolic`` with ``nmethods = 1``, supernodal), on a
        ``cholmod_sparse`` header over the pattern's own arrays: the same factor object as
        cvxopt's, without first copying the pattern into a cvxopt matrix. ``None`` when not
        available (the caller uses cvxopt).

        ``auto`` (below :data:`_AUTO_SUPERNODAL_BELOW` unknowns, not for a trailing factor,
        ``postorder`` False): CHOLMOD chooses, simplicial when its flops per factor entry are
        few (its ``supernodal_switch`` rule), where a supernodal factorisation is mostly the
        overhead of thousands of tiny BLAS calls (on the intel graph, 5,181 unknowns, simplicial
        takes about half the time of supernodal). :meth:`factorize` makes a
        simplicial factor ``L L'`` too, so a matrix that is not positive definite is refused
        alike."""
        if self._capsule is None:
            return None
        auto = auto and postorder and pattern.size < _AUTO_SUPERNODAL_BELOW
        factor, _ = self._analysed(pattern.indptr, pattern.indices, perm, 1 if auto else 2,
                                   postorder)
        if not factor:
            return None
        try:
            return self._capsule(factor)
        except Exception:  # pragma: no cover - the capsule could not be made
            self._free_factor(ctypes.byref(ctypes.c_void_p(factor)), self._common())
            return None

    def analysis_flops(self, indptr: IntArray, indices: IntArray, perm: IntArray
                       ) -> float | None:
        """The flop count CHOLMOD's symbolic analysis (simplicial, ``cholmod_l_analyze_p``
        with the ordering ``perm`` alone) predicts for factoring a matrix of the given lower
        triangle pattern (CSC, int64; the diagonal included), without a numeric factorisation;
        ``None`` when not available (:meth:`analyse`'s conditions)."""
        if self._capsule is None:
            return None
        factor, flops = self._analysed(indptr, indices, perm, 0, False)
        if factor:
            self._free_factor(ctypes.byref(ctypes.c_void_p(factor)), self._common())
        return flops if factor and flops > 0 else None

    def _analysed(self, indptr: IntArray, indices: IntArray, perm: IntArray, supernodal: int,
                  postorder: bool) -> tuple[int, float]:
        """``cholmod_l_analyze_p`` of a lower-triangle pattern (CSC) with the ordering ``perm``
        alone (``nmethods = 1``; ``supernodal`` 0 simplicial, 2 supernodal), on a
        ``cholmod_sparse`` header over the arrays themselves: the ``cholmod_factor *`` (0 on
        failure; the caller owns it) and the flops of its factorisation."""
        n = indptr.size - 1
        indptr = np.ascontiguousarray(indptr, dtype=np.int64)
        indices = np.ascontiguousarray(indices, dtype=np.int64)
        pvec = np.ascontiguousarray(perm, dtype=np.int64)
        A = _CholmodSparse(n, n, int(indptr[-1]), indptr.ctypes.data, indices.ctypes.data,
                           None, None, None, -1, 2, 0, 0, 1, 1)  # lower, long, pattern only
        common = self._common()
        c = _CommonOrdering.from_buffer(common)
        saved = (c.supernodal, c.nmethods, c.postorder)
        c.supernodal, c.nmethods, c.postorder = supernodal, 1, int(bool(postorder))
        try:
            factor = self._analyze(ctypes.addressof(A), pvec.ctypes.data, None, 0, common)
            flops = float(c.method[c.selected].fl) if factor else 0.0
        finally:
            c.supernodal, c.nmethods, c.postorder = saved
            self._free_work(common)
        return factor or 0, flops

    def _common(self):
        """This thread's ``cholmod_common`` (started, ``print = 0``), or ``None`` if its
        defaults are not those of CHOLMOD 3 (another build: the caller uses cvxopt then)."""
        common = getattr(self._local, 'common', None)
        if common is None:
            buf = ctypes.create_string_buffer(self._COMMON_BYTES)
            if not self._start(buf):
                return None
            head = _CommonHead.from_buffer(buf)
            expected = (head.dbound == 0.0 and head.grow0 == 1.2 and head.grow2 == 5
                        and head.maxrank == 8 and head.supernodal_switch == 40.0
                        and head.final_asis == 1 and list(head.zrelax) == [0.8, 0.1, 0.05]
                        and list(head.nrelax) == [4, 16, 48] and head.prefer_upper == 1
                        and head.print == 3)
            if not expected:
                return None
            head.print = 0  # not-positive-definite is reported by an exception, not printed
            common = self._local.common = buf
        return common

    def _factor(self, capsule) -> tuple[int, _CholmodFactor]:
        address = self._capsule_pointer(capsule, b'CHOLMOD FACTOR D L')
        return address, _CholmodFactor.from_address(address)

    def permuted(self, pattern: BlockPattern, capsule) -> _Permuted:
        """The lower triangle of ``P N P'`` for the analysed factor ``capsule`` (``P`` its final
        permutation, postordering included): its CSC pattern and where each of its entries is
        in ``N``'s values (the same layout as CHOLMOD's own permuted copy)."""
        _, L = self._factor(capsule)
        n = pattern.size
        perm = np.ctypeslib.as_array(ctypes.cast(L.Perm, ctypes.POINTER(ctypes.c_int64)),
                                     shape=(n,))
        pinv = np.empty(n, dtype=np.int64)
        pinv[perm] = np.arange(n)
        lo = pinv[_expand_cols(pattern.indptr)]
        hi = pinv[pattern.indices]
        swap = hi < lo  # (row, col) of P N P': the lower one of the pair
        lo[swap], hi[swap] = hi[swap], lo[swap]
        del swap
        key = lo * n
        key += hi
        order = np.argsort(key, kind='stable')
        del key
        indptr = np.concatenate([[0], np.cumsum(np.bincount(lo, minlength=n))]).astype(np.int64)
        del lo
        indices = hi[order]
        return _Permuted(order.astype(np.int32 if pattern.nnz < 2**31 else np.int64), indptr,
                         indices)

    def factorize(self, pattern: BlockPattern, data: FloatArray, capsule,
                  permuted: _Permuted | None = None) -> None:
        """Numeric factorisation of the lower triangle ``data`` on ``pattern`` into the
        analysed factor ``capsule`` (cvxopt's). Raises ``ArithmeticError`` if the matrix is not
        positive definite, ``MemoryError`` if CHOLMOD fails otherwise.

        Given the ``permuted`` pattern (:meth:`permuted`), ``P N P'`` is gathered into it and
        the factor told, for this call, that its ordering is the natural one: CHOLMOD then
        factors the matrix as it is, instead of building ``triu(P N P')`` and its transpose
        (two copies of ``N``, values and row indices: ~0.7 GB for a survey of 100,000 poses;
        the gathered values are one copy of the values alone, half of that)."""
        n = pattern.size
        in_place = False
        if permuted is None:
            x = np.ascontiguousarray(data, dtype=np.float64)
            indptr = np.ascontiguousarray(pattern.indptr, dtype=np.int64)
            indices = np.ascontiguousarray(pattern.indices, dtype=np.int64)
        else:
            x = np.asarray(data, dtype=np.float64)
            permute = _permutation_kernel()
            # permuted where they lie (and back afterwards) when the compiled kernel and a
            # writable array allow it, else gathered into a copy
            in_place = permute is not None and x.flags.writeable and x.flags.c_contiguous
            if in_place:
                permute(x, permuted.where, False, np.zeros(x.size, dtype=np.bool_))
            else:
                x = x[permuted.where]
            indptr, indices = permuted.indptr, permuted.indices
        A = _CholmodSparse(n, n, int(indptr[-1]), indptr.ctypes.data, indices.ctypes.data,
                           None, x.ctypes.data, None, -1, 2, 1, 0, 1, 1)  # lower, long, real
        address, L = self._factor(capsule)
        ordering = L.ordering
        if permuted is not None:
            L.ordering = 0  # CHOLMOD_NATURAL: A is P N P' (the permutation stays for solves)
        common = self._common()
        head = _CommonHead.from_buffer(common)
        final_ll, head.final_ll = head.final_ll, 1  # simplicial too: L L', not L D L'
        try:
            ok = self._factorize(ctypes.addressof(A), address, common)
        finally:
            L.ordering = ordering
            head.final_ll = final_ll
            self._free_work(common)
            if in_place:  # the caller's values back in their order
                permute(x, permuted.where, True, np.zeros(x.size, dtype=np.bool_))
        if not ok:
            raise MemoryError('CHOLMOD could not factor the normal matrix (out of memory?)')
        if L.minor < n:
            raise ArithmeticError('not positive definite')


#: Below this many unknowns a factor asked for ``auto`` is simplicial or supernodal as CHOLMOD
#: chooses (:meth:`_DirectCholmod.analyse`); from it on it is supernodal.
_AUTO_SUPERNODAL_BELOW = 6000


@dataclass
class _Layout:
    """A factor's values and pattern as :func:`_takahashi_py` reads them; ``keep`` holds the
    objects that own the memory."""

    starts: IntArray
    pi: IntArray
    nrows: IntArray
    srows: IntArray
    colbase: IntArray
    x: FloatArray
    perm: IntArray
    keep: tuple


def _supernodal_layout(capsule, n: int) -> _Layout | None:
    """CHOLMOD's supernodal factor in place (no copy): its arrays viewed through ``ctypes``.
    ``None`` if the factor does not look as expected (another CHOLMOD build): the caller then
    reads it out with ``getfactor``."""
    api = ctypes.pythonapi
    api.PyCapsule_GetPointer.restype = ctypes.c_void_p
    api.PyCapsule_GetPointer.argtypes = [ctypes.py_object, ctypes.c_char_p]
    api.PyCapsule_GetName.restype = ctypes.c_char_p
    api.PyCapsule_GetName.argtypes = [ctypes.py_object]
    try:
        name = api.PyCapsule_GetName(capsule)
        if name != b'CHOLMOD FACTOR D L':
            return None
        L = _CholmodFactor.from_address(api.PyCapsule_GetPointer(capsule, name))
    except (TypeError, ValueError):  # pragma: no cover - not a capsule
        return None
    ns = int(L.nsuper)
    if not (L.n == n and L.minor == n and L.is_super == 1 and L.is_ll == 1 and L.xtype == 1
            and L.dtype == 0 and L.itype == 2 and 0 < ns <= n and L.ssize > 0 and L.xsize > 0
            and all((L.super, L.pi, L.px, L.s, L.x, L.Perm))):
        return None

    def view(ptr, count, ctype):
        return np.ctypeslib.as_array(ctypes.cast(ptr, ctypes.POINTER(ctype)), shape=(count,))

    sup = view(L.super, ns + 1, ctypes.c_int64).astype(np.int64)
    pi = view(L.pi, ns + 1, ctypes.c_int64).astype(np.int64)
    px = view(L.px, ns + 1, ctypes.c_int64).astype(np.int64)
    perm = view(L.Perm, n, ctypes.c_int64).astype(np.int64)
    width, nrows = np.diff(sup), np.diff(pi)
    if (sup[0] != 0 or sup[-1] != n or pi[0] != 0 or pi[-1] > L.ssize or px[0] != 0
            or px[-1] > L.xsize or (width <= 0).any() or (nrows < width).any()
            or (np.diff(px) < nrows * width).any()
            or not np.array_equal(np.sort(perm), np.arange(n))):
        return None
    x = view(L.x, int(L.xsize), ctypes.c_double)
    srows = view(L.s, int(L.ssize), ctypes.c_int64)
    step = np.diff(srows[:pi[-1]]) > 0
    step[pi[1:-1] - 1] = True  # a new supernode may start lower
    if not step.all():  # rows not sorted within a supernode
        return None
    k = np.repeat(np.arange(ns), width)
    colbase = px[k] + (np.arange(n) - sup[k]) * nrows[k]  # column-major nrows x width blocks
    return _Layout(sup, pi[:-1], nrows, srows, colbase, x, perm, (capsule,))
