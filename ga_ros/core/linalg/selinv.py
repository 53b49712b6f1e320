"""Marginal covariance blocks of many nodes: selected inversion of a normal matrix.

Two implementations of Takahashi's equations (``Sigma = N^-1`` on a sparsity pattern, from the
last column back, without any column of ``N^-1``):

* :class:`SelectedInverse`, on CHOLMOD's sparse Cholesky factor of ``N``, in place: ``Sigma``
  on the pattern of ``L`` (every node block and every connected pair), time about that of the
  factorisation, no memory beyond the factor. Used for large systems (batch adjustments of whole
  surveys; quality control).
* :func:`banded_marginal_blocks`, on the banded ``N`` (the block-tridiagonal selected inversion
  of :func:`ga_ros.core.linalg.banded.banded_selection`, which also serves the sparse joint
  priors):
  with a bandwidth-reducing node ordering (reverse Cuthill-McKee, or the principal axis) a
  survey's normal matrix is banded; cut into blocks of the band's width it is block
  tridiagonal, and its block Cholesky factor and Takahashi's backward recursion give every
  diagonal block in ``O(n b^2)`` operations and ``O(n b)`` memory (the RTS smoother in
  information form). For a window of five lawnmower tracks (6,000 unknowns) this needs no
  compiled kernel; for a whole survey the memory (unknowns x band) is prohibitive.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.kernels import AVAILABLE, jit
from ga_ros.core.linalg import lapack
from ga_ros.core.linalg.cholmod_ctypes import _Layout, _supernodal_layout
from ga_ros.errors import DegenerateGeometryError

if TYPE_CHECKING:
    pass


def banded_marginal_blocks(N: sp.spmatrix, d: int, max_band: int = 3000,
                           wanted: np.ndarray | None = None,
                           coords: np.ndarray | None = None) -> FloatArray | None:
    """Diagonal ``d x d`` blocks of ``N^-1`` for a symmetric positive definite ``N``.

    The block-tridiagonal selected inversion of :func:`~ga_ros.core.linalg.banded.banded_selection`
    with a band of width 0 (nodes of high degree, e.g. those of a dense joint prior, ordered
    last as a dense border).

    Parameters
    ----------
    N : (d u, d u) sparse symmetric matrix, ``u`` node blocks of size ``d``.
    d : block size (parameters per node).
    max_band : give up (return ``None``) if the reordered half-bandwidth or the border exceeds
        this many scalars; the caller then uses sparse solves.
    wanted : optional (k,) node blocks that are needed (blocks of other nodes are left as NaN).
        Default: all nodes.
    coords : optional (u, 3) node positions. Besides reverse Cuthill-McKee, the ordering along
        their principal axis is tried (for a survey strip it gives a narrower band); the
        ordering with the smaller band is used.

    Returns
    -------
    (u, d, d) covariance blocks in the original node order, or ``None`` (band too wide).
    """
    from ga_ros.core.linalg.banded import banded_selection  # lazy: cvxopt

    u = N.shape[0] // d
    nodes = np.arange(u, dtype=np.int64) if wanted is None or len(wanted) == 0 else \
        np.unique(np.asarray(wanted, dtype=np.int64))
    sel = banded_selection(N, d, nodes, 0, coords=coords, max_band=max_band)
    if sel is None:
        return None
    out = np.full((u, d, d), np.nan)
    out[nodes] = sel.band[:, 0]
    return 0.5 * (out + np.swapaxes(out, 1, 2))


# ------------------------------------------------------------ selected inversion on a factor
def supernodal_flops(starts: IntArray, nrows: IntArray, need: np.ndarray | None = None
                     ) -> tuple[float, float]:
    """Floating-point operations of a supernodal factor's dense blocks (the relaxed
    supernodes' explicit zeros included): ``(factorisation, selected inversion)``.

    Supernode ``k`` has ``m = starts[k+1] - starts[k]`` columns and ``r = nrows[k] - m`` rows
    below them. Its factorisation (``dpotrf``, ``dtrsm``, the update ``L_BJ L_BJ'``) costs
    ``m^3/3 + r m^2 + r^2 m``; its step of Takahashi's equations (:func:`_takahashi_py`:
    ``dtrtri`` and ``dlauum``, ``U = L_BJ L_JJ^-1``, ``Sigma_BJ = -Sigma_BB U``, the lower
    triangle of ``Sigma_BJ' U``) ``2 m^3/3 + 2 r m^2 + 2 r^2 m``. ``need``: the supernodes
    inverted (:attr:`SelectedInverse.need`), default all; the factorisation counts all.
    """
    m = np.diff(np.asarray(starts, dtype=np.int64)).astype(float)
    r = np.asarray(nrows, dtype=np.int64).astype(float) - m
    factor = m ** 3 / 3 + r * m ** 2 + r ** 2 * m
    inverse = 2 * m ** 3 / 3 + 2 * r * m ** 2 + 2 * r ** 2 * m
    if need is not None:
        inverse = inverse[np.asarray(need, dtype=bool)]
    return float(factor.sum()), float(inverse.sum())


def supernodes(colptr: IntArray, rowind: IntArray) -> IntArray:
    """First column of each (fundamental) supernode of a lower-triangular CSC factor, plus ``n``.

    Column ``j + 1`` continues the supernode of column ``j`` when it is ``j``'s parent in the
    elimination tree (the first sub-diagonal row of column ``j`` is ``j + 1``) and has one entry
    fewer: then both columns have the same rows below the supernode (the pattern of a Cholesky
    factor is closed: ``struct(j)`` without ``j`` lies in ``struct(parent(j))``).
    """
    colptr = np.asarray(colptr, dtype=np.int64)
    n = colptr.size - 1
    if n == 0:
        return np.zeros(1, dtype=np.int64)
    count = np.diff(colptr)
    j = np.arange(n - 1)
    second = np.where(count[:-1] > 1, colptr[:-2] + 1, 0)
    cont = (count[:-1] > 1) & (np.asarray(rowind)[second] == j + 1) & (count[1:] == count[:-1] - 1)
    starts = np.concatenate([[0], np.nonzero(~cont)[0] + 1, [n]])
    return starts.astype(np.int64)


def _lower_inverse_py(Ljj):  # pragma: no cover - without numba only
    """``(L^-1, L^-T L^-1)`` of a lower-triangular ``L`` (general inverse and product)."""
    Linv = np.tril(np.linalg.inv(Ljj))
    return Linv, Linv.T @ Linv


#: :func:`_lower_inverse_lapack` inverts triangles of up to this many columns with ``dtrtri``,
#: larger ones by halves (OpenBLAS's ``dtrtri`` runs at about a third of the flop rate of its
#: ``dtrmm``, so the halves' ``dtrmm`` products are cheaper than one large ``dtrtri``).
_TRTRI_LEAF = 128


def _trtri_at_blas(base, m, lda):  # pragma: no cover - compiled
    """Invert in place the lower triangle of ``m`` columns at address ``base`` (column-major,
    leading dimension ``lda``) by LAPACK's ``dtrtri``; a triangle wider than
    :data:`_TRTRI_LEAF` by halves, children before parents::

        [A 0; B C]^-1 = [A^-1 0; -C^-1 B A^-1  C^-1]    (two dtrmm on B)
    """
    # the halving tree in breadth-first order (first column, width); reversed: children first
    first, width = np.zeros(2 * m, dtype=np.int64), np.zeros(2 * m, dtype=np.int64)
    width[0], n_nodes, k = m, 1, 0
    while k < n_nodes:
        if width[k] > _TRTRI_LEAF:
            h = width[k] // 2
            first[n_nodes], width[n_nodes] = first[k], h
            first[n_nodes + 1], width[n_nodes + 1] = first[k] + h, width[k] - h
            n_nodes += 2
        k += 1
    ints = np.array([lda, 0, 0, 0], dtype=np.int32)  # lda, info, rows, cols
    one = np.array([1.0, -1.0])
    chars = np.array([76, 78, 82], dtype=np.int8)  # 'L', 'N', 'R'
    for k in range(n_nodes - 1, -1, -1):
        o, w = first[k], width[k]
        if w <= _TRTRI_LEAF:  # a leaf: dtrtri
            ints[2] = w
            _dtrtri(chars.ctypes.data, chars.ctypes.data + 1, ints.ctypes.data + 8,
                    base + 8 * o * (lda + 1), ints.ctypes.data, ints.ctypes.data + 4)
            continue
        h = w // 2
        ints[2], ints[3] = w - h, h
        a_ptr, c_ptr = base + 8 * o * (lda + 1), base + 8 * (o + h) * (lda + 1)
        b_ptr = base + 8 * (o + h + o * lda)
        # B := B A^-1 (right), then B := -C^-1 B (left); A, C already inverted in place
        _dtrmm(chars.ctypes.data + 2, chars.ctypes.data, chars.ctypes.data + 1,
               chars.ctypes.data + 1, ints.ctypes.data + 8, ints.ctypes.data + 12,
               one.ctypes.data, a_ptr, ints.ctypes.data, b_ptr, ints.ctypes.data)
        _dtrmm(chars.ctypes.data, chars.ctypes.data, chars.ctypes.data + 1,
               chars.ctypes.data + 1, ints.ctypes.data + 8, ints.ctypes.data + 12,
               one.ctypes.data + 8, c_ptr, ints.ctypes.data, b_ptr, ints.ctypes.data)


def _lower_inverse_lapack(Ljj):  # pragma: no cover - compiled
    """:func:`_lower_inverse_py` by LAPACK's ``dtrtri`` (:func:`_trtri_at_blas`) and ``dlauum``
    (``m^3 / 3`` flops each, against ``~4 m^3`` for a general inverse and product) on a
    column-major (Fortran-ordered) ``Ljj``, inverted in place; only the lower triangle of the
    second matrix is set."""
    m = Ljj.shape[0]
    _trtri_at(Ljj.ctypes.data, m, m)
    Sjj = Ljj.T.copy().T  # column-major too
    ints = np.array([m, 0], dtype=np.int32)
    chars = np.array([76], dtype=np.int8)  # 'L'
    _dlauum(chars.ctypes.data, ints.ctypes.data, Sjj.ctypes.data, ints.ctypes.data,
            ints.ctypes.data + 4)
    return Ljj, Sjj


def _in_place_step_py(x, q, m, r, lda, Sbb):  # pragma: no cover - without numba only
    """:func:`_in_place_step_blas` needs BLAS: without numba the copying path runs."""
    return 1


def _in_place_step_blas(x, q, m, r, lda, Sbb):  # pragma: no cover - compiled
    """Takahashi's step for one supernode stored as a column-major block (``lda`` rows: its
    ``m`` columns' own rows, then the ``r`` rows ``B`` below) at ``x[q]``, in place, without
    copying it out: ``L_JJ -> L_JJ^-1`` (:func:`_trtri_at_blas`), ``L_BJ -> U = L_BJ L_JJ^-1``
    (``dtrmm``), ``L_JJ^-1 -> L_JJ^-T L_JJ^-1`` (``dlauum``, lower triangle), then with the
    gathered ``Sigma_BB`` (``Sbb``, both triangles) ``Sigma_BJ = -Sigma_BB U`` (``dgemm``, into
    a temporary) and ``Sigma_JJ -= Sigma_BJ' U`` on its lower triangle (panels of
    :data:`_PANEL` columns), and ``Sigma_BJ`` over ``U``: the products of
    :func:`_takahashi_py`'s copying path, in the same order. Returns 0."""
    base = x.ctypes.data + 8 * q
    _trtri_at(base, m, lda)
    ints = np.array([r, m, lda, 0, 0, 0], dtype=np.int32)  # r, m, lda, info, rows, cols
    coef = np.array([1.0, -1.0, 0.0])
    chars = np.array([82, 76, 78, 84], dtype=np.int8)  # 'R', 'L', 'N', 'T'
    u_ptr = base + 8 * m
    if r:  # U = L_BJ L_JJ^-1, in place of L_BJ
        _dtrmm(chars.ctypes.data, chars.ctypes.data + 1, chars.ctypes.data + 2,
               chars.ctypes.data + 2, ints.ctypes.data, ints.ctypes.data + 4,
               coef.ctypes.data, base, ints.ctypes.data + 8, u_ptr, ints.ctypes.data + 8)
    _dlauum(chars.ctypes.data + 1, ints.ctypes.data + 4, base, ints.ctypes.data + 8,
            ints.ctypes.data + 12)
    if r == 0:
        return 0
    Sbj = np.empty((m, r)).T  # column-major, r x m
    # Sigma_BJ = -Sigma_BB U: M = K = r (lda of Sbb and ldc), N = m, ldb = lda
    _dgemm(chars.ctypes.data + 2, chars.ctypes.data + 2, ints.ctypes.data, ints.ctypes.data + 4,
           ints.ctypes.data, coef.ctypes.data + 8, Sbb.ctypes.data, ints.ctypes.data, u_ptr,
           ints.ctypes.data + 8, coef.ctypes.data + 16, Sbj.ctypes.data, ints.ctypes.data)
    # Sigma_JJ[c0:, c0:c1] -= Sigma_BJ[:, c0:]' U[:, c0:c1], the lower triangle by panels
    for c0 in range(0, m, _PANEL):
        c1 = min(m, c0 + _PANEL)
        ints[4], ints[5] = m - c0, c1 - c0
        _dgemm(chars.ctypes.data + 3, chars.ctypes.data + 2, ints.ctypes.data + 16,
               ints.ctypes.data + 20, ints.ctypes.data, coef.ctypes.data + 8,
               Sbj.ctypes.data + 8 * c0 * r, ints.ctypes.data, u_ptr + 8 * c0 * lda,
               ints.ctypes.data + 8, coef.ctypes.data, base + 8 * c0 * (lda + 1),
               ints.ctypes.data + 8)
    for i in range(m):  # Sigma_BJ over U
        o = q + i * lda + m
        for a in range(r):
            x[o + a] = Sbj[a, i]
    return 0


_lower_inverse = _lower_inverse_py
_in_place_step = _in_place_step_py
_trtri_at = None  # _trtri_at_blas, compiled (the kernels' in-place triangle inversion)


def _times_lower_py(B, Linv):  # pragma: no cover - without numba only
    """``B Linv`` for a lower-triangular ``Linv`` (a general product)."""
    return B @ Linv


def _times_lower_blas(B, Linv):  # pragma: no cover - compiled
    """:func:`_times_lower_py` by BLAS's ``dtrmm`` (``r m^2`` flops instead of ``2 r m^2``), in
    place in ``B`` (returned); both column-major."""
    r, m = B.shape
    ints = np.array([r, m], dtype=np.int32)  # M = ldb, N = lda
    one = np.ones(1)
    chars = np.array([82, 76, 78, 78], dtype=np.int8)  # side 'R', uplo 'L', 'N', diag 'N'
    _dtrmm(chars.ctypes.data, chars.ctypes.data + 1, chars.ctypes.data + 2,
           chars.ctypes.data + 3, ints.ctypes.data, ints.ctypes.data + 4, one.ctypes.data,
           Linv.ctypes.data, ints.ctypes.data + 4, B.ctypes.data, ints.ctypes.data)
    return B


def _minus_product_py(S, U):  # pragma: no cover - without numba only
    """``-S U``."""
    return -(S @ U)


def _minus_product_blas(S, U):  # pragma: no cover - compiled
    """:func:`_minus_product_py` by BLAS's ``dgemm`` for a symmetric ``S`` (its layout does
    not matter), column-major ``U``; the product column-major too."""
    r, m = U.shape
    out = np.empty((m, r)).T
    ints = np.array([r, m], dtype=np.int32)  # M = K = lda = ldb = ldc, N
    coef = np.array([-1.0, 0.0])
    chars = np.array([78, 78], dtype=np.int8)  # 'N', 'N'
    _dgemm(chars.ctypes.data, chars.ctypes.data + 1, ints.ctypes.data, ints.ctypes.data + 4,
           ints.ctypes.data, coef.ctypes.data, S.ctypes.data, ints.ctypes.data, U.ctypes.data,
           ints.ctypes.data, coef.ctypes.data + 8, out.ctypes.data, ints.ctypes.data)
    return out


def _lower_update_py(Sjj, Sbj, U):  # pragma: no cover - without numba only
    """``Sjj -= Sbj' U`` (symmetric; only the lower triangle of ``Sjj`` is read after)."""
    Sjj -= Sbj.T @ U


#: Column panel of :func:`_lower_update_blas` (a panel's product covers the rows from its
#: first column down: ~half the flops of the full product for a wide supernode).
_PANEL = 64


def _lower_update_blas(Sjj, Sbj, U):  # pragma: no cover - compiled
    """:func:`_lower_update_py` on the lower triangle of ``Sjj`` only, panel by panel (BLAS's
    ``dgemm``; all column-major): ``Sjj[c0:, c0:c1] -= Sbj[:, c0:]' U[:, c0:c1]``."""
    r, m = U.shape
    ints = np.array([m, 0, 0, r], dtype=np.int32)  # ldc, rows, cols, k = lda = ldb
    coef = np.array([-1.0, 1.0])
    chars = np.array([84, 78], dtype=np.int8)  # 'T', 'N'
    for c0 in range(0, m, _PANEL):
        c1 = min(m, c0 + _PANEL)
        ints[1], ints[2] = m - c0, c1 - c0
        _dgemm(chars.ctypes.data, chars.ctypes.data + 1, ints.ctypes.data + 4,
               ints.ctypes.data + 8, ints.ctypes.data + 12, coef.ctypes.data,
               Sbj.ctypes.data + 8 * c0 * r, ints.ctypes.data + 12, U.ctypes.data + 8 * c0 * r,
               ints.ctypes.data + 12, coef.ctypes.data + 8, Sjj.ctypes.data + 8 * c0 * (m + 1),
               ints.ctypes.data)


_times_lower = _times_lower_py
_minus_product = _minus_product_py
_lower_update = _lower_update_py


def _takahashi_py(starts, pi, nrows, srows, colbase, x, where, need,
                  in_place):  # pragma: no cover - compiled
    """In place: the values of ``L`` (``P N P' = L L'``) become those of ``Sigma = N^-1``
    (permuted) on the pattern of ``L``.

    Supernode ``k`` has the columns ``starts[k] .. starts[k+1]-1`` and the sorted rows
    ``srows[pi[k] : pi[k] + nrows[k]]`` (its own columns first); the value at its ``z``-th row in
    column ``c`` is ``x[colbase[c] + z]`` (CHOLMOD's supernodal layout and a CSC factor both fit).
    Takahashi's equations per supernode (columns ``J``, rows ``B`` below them), from the last
    back (``Sigma L = L^-T``, upper triangular)::

        U = L_BJ L_JJ^-1,   Sigma_BJ = -Sigma_BB U,   Sigma_JJ = L_JJ^-T L_JJ^-1 - Sigma_BJ' U

    ``Sigma_BB`` lies on the pattern of later supernodes (closure of the factor's pattern), all
    already overwritten; it is gathered through ``where`` (row -> position in an ancestor's row
    list, -1 elsewhere). Only the supernodes with ``need[k]`` are inverted (the others keep
    ``L``): a set closed under ancestors (every ``Sigma_BB`` lies on ancestors). With
    ``in_place`` (the compiled kernels), a supernode stored as one column-major block (CHOLMOD's
    supernodal layout) is inverted where it lies (:func:`_in_place_step_blas`: the same products
    without copying its columns out and back), the others through copies of their columns.
    Returns 0; 1 if a needed entry is not on the pattern, 2 if rows are not sorted (nothing was
    changed then).
    """
    if not _rows_sorted(starts, pi, nrows, srows):
        return 2
    for t in range(starts.size - 2, -1, -1):
        if not need[t]:
            continue
        f = starts[t]
        m = starts[t + 1] - f
        r = nrows[t] - m
        q = colbase[f]
        if in_place and colbase[f + m - 1] == q + (m - 1) * nrows[t] and (
                m == 1 or colbase[f + 1] == q + nrows[t]):  # one column-major block
            Sbb = np.empty((r, r))
            if r and _gather_sigma_bb(srows[pi[t] + m:pi[t] + nrows[t]], starts, pi, nrows,
                                      srows, colbase, x, where, Sbb):
                return 1
            _in_place_step(x, q, m, r, nrows[t], Sbb)
            continue
        Ljj, Lbj = _read_supernode(x, colbase, f, m, r)
        Linv, Sjj = _lower_inverse(Ljj)  # Sjj: lower triangle of L_JJ^-T L_JJ^-1
        Sbj = np.empty((m, r)).T
        if r:
            U = _times_lower(Lbj, Linv)  # L_BJ L_JJ^-1 (in place of Lbj)
            Sbb = np.empty((r, r))
            if _gather_sigma_bb(srows[pi[t] + m:pi[t] + nrows[t]], starts, pi, nrows, srows,
                                colbase, x, where, Sbb):
                return 1
            Sbj = _minus_product(Sbb, U)  # -Sigma_BB U
            _lower_update(Sjj, Sbj, U)  # Sjj -= Sbj' U, its lower triangle
        _write_supernode(x, colbase, f, Sjj, Sbj)
    return 0


def _rows_sorted(starts, pi, nrows, srows):  # pragma: no cover - compiled
    """Whether the rows of every supernode (layout of :func:`_takahashi_py`) ascend strictly."""
    for k in range(starts.size - 1):
        for z in range(pi[k] + 1, pi[k] + nrows[k]):
            if srows[z] <= srows[z - 1]:
                return False
    return True


def _supernode_of_column(starts, c):  # pragma: no cover - compiled
    """The supernode holding column ``c``: the last ``k`` with ``starts[k] <= c`` (binary
    search)."""
    lo, hi = 0, starts.size - 1
    while hi - lo > 1:
        mid = (lo + hi) // 2
        if starts[mid] <= c:
            lo = mid
        else:
            hi = mid
    return lo


def _read_supernode(x, colbase, f, m, r):  # pragma: no cover - compiled
    """The ``m`` columns from ``f`` of a supernode with ``r`` rows below them, as
    ``(L_JJ (m, m), L_BJ (r, m))``, both column-major (the factor's columns copy
    contiguously); the upper triangle of ``L_JJ`` is zero."""
    Ljj = np.zeros((m, m)).T
    Lbj = np.empty((m, r)).T
    for i in range(m):
        q = colbase[f + i]
        for a in range(i, m):
            Ljj[a, i] = x[q + a]
        for a in range(r):
            Lbj[a, i] = x[q + m + a]
    return Ljj, Lbj


def _write_supernode(x, colbase, f, Sjj, Sbj):  # pragma: no cover - compiled
    """Store ``Sigma_JJ`` (its lower triangle) and ``Sigma_BJ`` in place of the columns of
    :func:`_read_supernode`."""
    m, r = Sjj.shape[0], Sbj.shape[0]
    for i in range(m):
        q = colbase[f + i]
        for a in range(i, m):
            x[q + a] = Sjj[a, i]
        for a in range(r):
            x[q + m + a] = Sbj[a, i]


def _gather_sigma_bb(B, starts, pi, nrows, srows, colbase, x, where,
                     Sbb):  # pragma: no cover - compiled
    """``Sigma_BB`` (both triangles) into ``Sbb (r, r)`` for the sorted rows ``B (r,)``, from
    the already inverted supernodes that hold them as columns, one ancestor's run of rows at a
    time (positions in its row list through ``where``, left at -1). Returns 0; 1 if an entry
    is not on the pattern (``where`` is left dirty then)."""
    r = B.size
    zs = np.empty(r, dtype=np.int64)
    a = 0
    while a < r:  # the rows of B that are columns of one ancestor supernode
        lo = _supernode_of_column(starts, B[a])
        q0, nt, lt = pi[lo], nrows[lo], starts[lo + 1]
        for z in range(nt):
            where[srows[q0 + z]] = z
        b = a
        while b < r and B[b] < lt:
            b += 1
        for l2 in range(a, r):  # the rows' positions in this ancestor, once
            z = where[B[l2]]
            if z < 0:
                return 1
            zs[l2] = z
        for mm in range(a, b):
            base = colbase[B[mm]]
            for l2 in range(mm, r):
                v = x[base + zs[l2]]
                Sbb[l2, mm] = v
                Sbb[mm, l2] = v
        for z in range(nt):
            where[srows[q0 + z]] = -1
        a = b
    return 0


def _offsets_py(starts, pi, nrows, srows, colbase, rows, cols, out):  # pragma: no cover
    """``out[e]`` = the position in the values of the layout of :func:`_takahashi_py` of the
    entry (``rows[e] >= cols[e]``), by binary searches (-1 if it is not on the pattern);
    returns the number of entries not on the pattern."""
    missing = 0
    for e in range(rows.size):
        c, r = cols[e], rows[e]
        lo = _supernode_of_column(starts, c)
        a, b = pi[lo] + (c - starts[lo]), pi[lo] + nrows[lo]
        while a < b:
            mid = (a + b) // 2
            if srows[mid] < r:
                a = mid + 1
            else:
                b = mid
        if a < pi[lo] + nrows[lo] and srows[a] == r:
            out[e] = colbase[c] + a - pi[lo]
        else:
            out[e] = -1
            missing += 1
    return missing


_KERNELS: dict = {}
#: The steps the kernels call, compiled with them.
_HELPERS = ('_rows_sorted', '_supernode_of_column', '_read_supernode', '_write_supernode',
            '_gather_sigma_bb', '_in_place_step')
_dtrtri = _dlauum = _dtrmm = _dgemm = None  # LAPACK/BLAS routines of the compiled kernels
#: Supernodes stored as one block are inverted where they lie (set once the kernels are
#: compiled with BLAS: :func:`_in_place_step_blas`).
_IN_PLACE = False
#: The kernels are compiled (numba installed, ``GA_ROS_JIT`` not ``0``); without, they run as
#: plain Python (correct, but only for small systems: callers choose another path then).
COMPILED = AVAILABLE


def _kernel(name: str):
    """The numba-compiled kernel (cached on disk), or the Python one (:data:`COMPILED`)."""
    global _lower_inverse, _dtrtri, _dlauum, _times_lower, _minus_product, _lower_update
    global _dtrmm, _dgemm, _trtri_at, _in_place_step, _IN_PLACE
    fn = _KERNELS.get(name)
    if fn is None:
        fn = globals()[name + '_py']
        if COMPILED:
            routines = lapack.routines('dtrtri', 'dlauum', 'dtrmm', 'dgemm')
            if _lower_inverse is _lower_inverse_py and routines is not None:
                _dtrtri, _dlauum, _dtrmm, _dgemm = routines
                _trtri_at = jit(_trtri_at_blas)
                _lower_inverse = jit(_lower_inverse_lapack)
                _in_place_step = jit(_in_place_step_blas)
                _IN_PLACE = True
                _times_lower = jit(_times_lower_blas)
                _minus_product = jit(_minus_product_blas)
                _lower_update = jit(_lower_update_blas)
            g = globals()
            for helper in _HELPERS:  # a compiled kernel calls compiled globals
                if not hasattr(g[helper], 'py_func'):
                    g[helper] = jit(g[helper])
            fn = jit(fn)
        _KERNELS[name] = fn
    return fn


def _csc_layout(chol) -> _Layout:
    """The factor read out with ``cholmod.getfactor`` (a simplicial copy: ~2x the factor's
    memory at the peak), its supernodes found from the pattern (:func:`supernodes`)."""
    from ga_ros.core.linalg.cholmod import _cholmod

    perm = chol.permutation()
    F = _cholmod.getfactor(chol._F)
    colptr, rowind, values = F.CCS  # views of cvxopt's buffers (writable), which they keep
    colptr = np.asarray(colptr, dtype=np.int64).ravel()
    rowind = np.asarray(rowind, dtype=np.int64).ravel()
    starts = supernodes(colptr, rowind)
    pi = colptr[starts[:-1]]
    k = np.repeat(np.arange(starts.size - 1), np.diff(starts))
    colbase = colptr[:-1] - (np.arange(colptr.size - 1) - starts[k])
    return _Layout(starts, pi, np.diff(colptr)[starts[:-1]], rowind, colbase,
                   np.asarray(values, dtype=float).ravel(), perm, (F,))


class SelectedInverse:
    """``Sigma = N^-1`` on the pattern of the Cholesky factor of ``N`` (selected inversion).

    The CHOLMOD factor of ``N`` (a :class:`~ga_ros.core.linalg.cholesky.SparseCholesky`, ordered
    by the
    project's block ordering: AMD of the node graph, each node's ``d`` unknowns together) is
    overwritten in place by Takahashi's equations (:func:`_takahashi_py`, compiled with numba),
    supernode by supernode with dense products, in CHOLMOD's own supernodal storage (viewed
    through ``ctypes``, no copy; if that layout is not recognised, a ``getfactor`` copy is used).
    The extra memory is one dense ``rows x rows`` block of the widest supernode: no band, no
    dense column, no second factor. Every entry of ``Sigma`` on the pattern of ``N`` is on the
    pattern of ``L`` (``P N P'`` lies within ``L + L'``), so the diagonal blocks of all nodes and
    the cross blocks of all connected node pairs can be read (:meth:`blocks`).

    Parameters
    ----------
    chol : the factored ``N`` (``d x d`` node blocks). Its factor is taken over: ``chol`` is left
        without one and factors again (with a new analysis) on its next solve.
    copy : read the factor out with ``getfactor`` even when the in-place layout is available.
    columns : the block columns (nodes of ``N``) whose entries will be read, if only some: then
        only their supernodes and those supernodes' ancestors in the elimination tree are
        inverted (every entry of ``Sigma`` that Takahashi's equations need for them lies there),
        and only blocks whose two nodes are among ``columns`` can be read. Default: all.

    Raises
    ------
    DegenerateGeometryError
        No CHOLMOD, or the factor's pattern is not that of a Cholesky factor.
    """

    def __init__(self, chol, copy: bool = False, columns: IntArray | None = None) -> None:
        from ga_ros.core.linalg.cholmod import _cholmod

        if _cholmod is None or chol._F is None:  # pragma: no cover - cvxopt is pinned
            raise DegenerateGeometryError('selected inversion needs a CHOLMOD factor (cvxopt)')
        self.d = chol.pattern.d
        lay = None if copy else _supernodal_layout(chol._F, chol.n)
        self.in_place = lay is not None
        if lay is None:
            lay = _csc_layout(chol)
        chol._F = chol._symbolic = chol._permuted = None  # the values become Sigma's
        self._lay = lay
        self._pos = np.empty_like(lay.perm)
        self._pos[lay.perm] = np.arange(lay.perm.size)
        where = np.full(lay.perm.size, -1, dtype=np.int64)
        ns = lay.starts.size - 1
        self._need = np.ones(ns, dtype=bool)
        if columns is not None:
            self._need = self._ancestors(np.asarray(columns, dtype=np.int64))
        kernel = _kernel('_takahashi')
        status = kernel(lay.starts, lay.pi, lay.nrows, lay.srows, lay.colbase, lay.x, where,
                        self._need, _IN_PLACE)
        if status:
            raise DegenerateGeometryError('the factor pattern is not that of a Cholesky factor '
                                          f'(code {status}): report this with the graph')

    @property
    def nnz(self) -> int:
        """Stored entries of ``L`` (and of ``Sigma``; supernodal storage counts whole blocks)."""
        return int(self._lay.x.size)

    @property
    def flops(self) -> tuple[float, float]:
        """``(factorisation, this selected inversion)`` flops of the factor's supernodes
        (:func:`supernodal_flops`; the inversion over the supernodes it inverted)."""
        return supernodal_flops(self._lay.starts, self._lay.nrows, self._need)

    @property
    def need(self) -> np.ndarray:
        """``(supernodes,)`` which supernodes were inverted (all, unless ``columns``)."""
        return self._need

    @property
    def inverted(self) -> float:
        """Fraction of the supernodes inverted (1 unless ``columns`` selected some)."""
        return float(self._need.mean()) if self._need.size else 1.0

    def _supernode_of(self, scalar_cols: IntArray) -> IntArray:
        """Supernode of each column of the permuted factor."""
        return np.searchsorted(self._lay.starts, scalar_cols, side='right') - 1

    def _ancestors(self, columns: IntArray) -> np.ndarray:
        """Supernodes holding the scalar columns of the node columns ``columns``, and all their
        ancestors (a supernode's parent holds the first row below its own columns; parents
        come after their children in the factor)."""
        lay, d = self._lay, self.d
        starts = lay.starts
        ns = starts.size - 1
        width = np.diff(starts)
        below = lay.nrows > width
        parent = np.full(ns, -1, dtype=np.int64)
        parent[below] = self._supernode_of(lay.srows[lay.pi[below] + width[below]])
        need = np.zeros(ns, dtype=bool)
        need[self._supernode_of(self._pos[(columns[:, None] * d + np.arange(d)).ravel()])] = True
        for k in np.nonzero(parent >= 0)[0].tolist():  # ascending: children before parents
            if need[k]:
                need[parent[k]] = True
        return need

    def blocks(self, rows: IntArray, cols: IntArray, off_pattern: str = 'raise') -> FloatArray:
        """Blocks ``(rows[k], cols[k])`` of ``Sigma`` (``d x d`` node blocks, columns of ``N``),
        ``(k, d, d)``. Each pair should be a diagonal block or a connected pair of ``N``; a pair
        off the factor's pattern raises :class:`DegenerateGeometryError` (``off_pattern=
        'raise'``) or comes back as NaN (``'nan'``)."""
        return self.at(self.offsets(rows, cols, off_pattern))

    def offsets(self, rows: IntArray, cols: IntArray, off_pattern: str = 'raise') -> IntArray:
        """Where the blocks ``(rows[k], cols[k])`` of :meth:`blocks` lie in the factor's values,
        ``(k, d, d)`` (-1: off the pattern, with ``off_pattern='nan'``). They depend on the
        symbolic analysis only: the same for every factor of one analysis, so a caller that
        reads the same blocks of many factors computes them once (:meth:`at`)."""
        d = self.d
        rows = np.asarray(rows, dtype=np.int64)
        cols = np.asarray(cols, dtype=np.int64)
        a = np.arange(d)
        sr = self._pos[(rows[:, None, None] * d + a[None, :, None])]  # (k, d, 1)
        sc = self._pos[(cols[:, None, None] * d + a[None, None, :])]  # (k, 1, d)
        sr, sc = np.broadcast_arrays(sr, sc)
        lo, hi = np.minimum(sr, sc).ravel(), np.maximum(sr, sc).ravel()
        if not self._need.all() and not self._need[self._supernode_of(lo)].all():
            raise DegenerateGeometryError('a requested block is outside the selected columns '
                                          'of this SelectedInverse (its columns argument)')
        out = np.empty(lo.size, dtype=np.int64)
        lay = self._lay
        missing = _kernel('_offsets')(lay.starts, lay.pi, lay.nrows, lay.srows, lay.colbase,
                                      hi, lo, out)
        if missing and off_pattern == 'raise':
            raise DegenerateGeometryError('a requested block is not on the pattern of the '
                                          'normal matrix: only node and connected-pair blocks')
        return out.reshape(rows.size, d, d)

    def at(self, offsets: IntArray) -> FloatArray:
        """The values of ``Sigma`` at positions from :meth:`offsets` (NaN where -1)."""
        offsets = np.asarray(offsets, dtype=np.int64)
        out = self._lay.x[offsets]
        if (offsets < 0).any():
            out[offsets < 0] = np.nan
        return out

    def diagonal_blocks(self, nodes: IntArray) -> FloatArray:
        """Marginal covariance blocks ``(k, d, d)`` of the given node columns (symmetrised)."""
        nodes = np.asarray(nodes, dtype=np.int64)
        out = self.blocks(nodes, nodes)
        return 0.5 * (out + np.swapaxes(out, 1, 2))



def path_marginal_blocks(chol, cols: IntArray, cheaper_than_solve: bool = False
                         ) -> FloatArray | None:
    """Diagonal ``d x d`` blocks of ``N^-1`` for a few block columns ``cols``, from the factor
    ``P N P' = L L'`` of ``chol`` (left intact): ``Sigma_kk = Y' Y`` with ``Y = L^-1 P E_k``.

    A forward solve from the unit columns of node ``k`` fills only the rows of the supernodes on
    the elimination-tree path from node ``k``'s supernodes to the root, so only those are read
    (one dense triangular solve and one product per supernode on the path): for a window's
    newest node a small part of a full forward and backward solve. Exact (rounding aside: a
    solve's block to ~1e-12 relative, tested).

    Parameters
    ----------
    chol : a factored :class:`~ga_ros.core.linalg.cholmod.SparseCholesky` (``d x d`` blocks).
    cols : (k,) block columns of ``N``.
    cheaper_than_solve : also ``None`` when the paths visit so many supernodes that a full
        forward and backward solve of the ``k d`` unit columns is estimated cheaper (each
        supernode on a path costs a few NumPy calls, :data:`PATH_VISIT_FLOPS`): the paths of
        nodes deep in the elimination tree (a window's older fix nodes) are long.

    Returns
    -------
    ``(k, d, d)`` symmetric blocks, or ``None`` if the factor is not CHOLMOD's supernodal one
    viewed in place, or if ``cheaper_than_solve`` and the solve is cheaper (the caller then
    solves).
    """
    import heapq

    import scipy.linalg as sla

    if getattr(chol, '_F', None) is None:
        return None
    lay = _supernodal_layout(chol._F, chol.n)
    if lay is None:
        return None
    d = chol.pattern.d
    pos = np.empty_like(lay.perm)
    pos[lay.perm] = np.arange(lay.perm.size)
    starts = lay.starts
    width = np.diff(starts)
    offset = lay.colbase[starts[:-1]]  # where each supernode's column-major block starts
    cols = np.asarray(cols, dtype=np.int64)
    if cheaper_than_solve and _path_visits(lay, pos, cols, d) * PATH_VISIT_FLOPS > (
            4 * lay.x.size * cols.size * d):  # forward + backward solve, k d columns
        return None
    out = np.empty((cols.size, d, d))
    for i, c in enumerate(cols.tolist()):
        rows = pos[c * d + np.arange(d)]  # rows of L holding node c's unknowns
        rhs: dict[int, FloatArray] = {}  # supernode -> its rows of the right-hand side
        for a, (r, s) in enumerate(zip(rows.tolist(), (np.searchsorted(
                starts, rows, side='right') - 1).tolist())):
            rhs.setdefault(s, np.zeros((width[s], d)))[r - starts[s], a] = 1.0
        heap = list(rhs)
        heapq.heapify(heap)  # a parent comes after its children: ascending is bottom-up
        acc = np.zeros((d, d))
        while heap:
            s = heapq.heappop(heap)
            w, m, p = int(width[s]), int(lay.nrows[s]), int(offset[s])
            block = lay.x[p:p + m * w].reshape(w, m).T  # the supernode's m x w values
            ys = sla.solve_triangular(block[:w], rhs.pop(s), lower=True, check_finite=False)
            acc += ys.T @ ys
            if m > w:  # the rows below: the ancestors on the path
                below = lay.srows[lay.pi[s] + w:lay.pi[s] + m]
                upd = block[w:] @ ys
                owner = np.searchsorted(starts, below, side='right') - 1
                for t in np.unique(owner).tolist():
                    sel = owner == t
                    tgt = rhs.get(t)
                    if tgt is None:
                        tgt = rhs[t] = np.zeros((width[t], d))
                        heapq.heappush(heap, t)
                    tgt[below[sel] - starts[t]] -= upd[sel]
        out[i] = 0.5 * (acc + acc.T)
    return out


#: The cost of visiting one supernode in :func:`path_marginal_blocks` (a triangular solve, a
#: product and a few NumPy calls, ~30-50 us of Python) in floating-point operations of a
#: compiled sparse solve (~1-2 GFLOP/s on one core): the exchange rate of its
#: ``cheaper_than_solve`` choice.
PATH_VISIT_FLOPS = 60_000


def _path_visits(lay, pos: IntArray, cols: IntArray, d: int) -> int:
    """How many supernodes :func:`path_marginal_blocks` visits for the block columns ``cols``
    (each column's union of the elimination-tree paths from its rows' supernodes to the
    root). ``pos``: the row of ``L`` of each column of ``N``."""
    starts = lay.starts
    width = np.diff(starts)
    below = lay.nrows > width  # the parent owns the first row below the diagonal block
    parent = np.full(width.size, -1, np.int64)
    parent[below] = np.searchsorted(starts, lay.srows[lay.pi[below] + width[below]],
                                    side='right') - 1
    parent = parent.tolist()
    owners = (np.searchsorted(starts, pos[(cols[:, None] * d + np.arange(d)).ravel()],
                              side='right') - 1).reshape(cols.size, d).tolist()
    total = 0
    for own in owners:
        seen: set[int] = set()
        for s in own:
            while s >= 0 and s not in seen:
                seen.add(s)
                s = parent[s]
        total += len(seen)
    return total
