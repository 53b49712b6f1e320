"""Fill-reducing orderings of a normal matrix's block graph: AMD or nested dissection.

The normal matrix has one ``d x d`` block per node and the sparsity of the connection graph, so
its fill-reducing ordering is computed on that *block* graph (one vertex per node) and expanded
to scalars (:func:`ga_ros.core.linalg.ordering.block_ordering`). AMD is cheap and best on small or
chain-like graphs; on large graphs with many loops (a survey of overlapping tracks, a torus or
a sphere lattice) nested dissection (METIS, through ``pymetis``) leaves less fill: the paper's
aerial survey 6.75 -> 5.21 GFlop per factorisation, torus3D 1.38 -> 1.02 (``ga-ros bench
linalg``). Neither wins everywhere, so on graphs of at least :data:`METIS_MIN_BLOCKS` nodes
both are computed and the one whose factor of the block graph costs fewer flops is kept
(CHOLMOD's own rule is alike: it tries METIS when AMD's fill is high). The block graph is
``d^2`` times smaller than the matrix, and the flops come from CHOLMOD's symbolic analysis, so
the comparison costs a few milliseconds (aerial survey: METIS ~18 ms, both flop counts ~4 ms);
importing ``pymetis`` costs ~20-25 ms once per process, which is why small graphs (one
factorisation of a few tens of milliseconds) keep AMD without trying.
"""

from __future__ import annotations

import importlib.util
from collections import OrderedDict
from collections.abc import Callable

import numpy as np

from ga_ros.arrays import IntArray
from ga_ros.core.linalg.blocks import BlockPattern, _kept
from ga_ros.runtime import openblas_coretype

try:  # AMD, bundled in the cvxopt wheel (with CHOLMOD: ga_ros.core.linalg.cholmod)
    with openblas_coretype():
        import cvxopt
        from cvxopt import amd as _amd
except ImportError:  # pragma: no cover - the pinned requirements include cvxopt
    cvxopt = None
    _amd = None

#: Block graphs of at least this many nodes also try nested dissection.
METIS_MIN_BLOCKS = 4000
#: ``pymetis`` is installed (pinned in requirements.txt; without it AMD is used everywhere).
HAVE_METIS = importlib.util.find_spec('pymetis') is not None


def _sorted_unique(x: IntArray) -> IntArray:
    """``np.unique(x)`` of an integer array by a sort: NumPy 2.4's ``np.unique`` without
    ``return_inverse`` hashes, ~10 ms for the 70,000 keys of an aerial survey's block graph
    against ~0.5 ms for this."""
    x = np.sort(x)
    return x[np.concatenate([[True], x[1:] != x[:-1]])] if x.size else x


def _adjacency(n: int, rows: IntArray, cols: IntArray) -> tuple[IntArray, IntArray]:
    """CSR adjacency ``(xadj, adjncy)`` of the graph of ``n`` vertices with the edges
    ``rows[k] -- cols[k]`` (both directions, each neighbour once, self-loops dropped), in NumPy
    (no ``scipy.sparse``: its first import costs a batch solve ~40 ms)."""
    off = rows != cols
    a = np.concatenate([rows[off], cols[off]]).astype(np.int64)
    b = np.concatenate([cols[off], rows[off]]).astype(np.int64)
    return _compressed(_sorted_unique(a * n + b), n)  # by vertex, then neighbour


def _compressed(key: IntArray, n: int) -> tuple[IntArray, IntArray]:
    """Compressed rows (or columns) ``(indptr, indices)`` of an ``n x n`` pattern from its
    entries' sorted, distinct keys ``major * n + minor``."""
    indptr = np.concatenate([[0], np.cumsum(np.bincount(key // n, minlength=n))])
    return indptr.astype(np.int64), key % n


def nested_dissection(n: int, rows: IntArray, cols: IntArray) -> IntArray:
    """METIS nested-dissection order of a graph of ``n`` vertices (``pymetis``).

    Parameters
    ----------
    n : number of vertices.
    rows, cols : (k,) its edges, each once (self-loops are ignored).

    Returns
    -------
    (n,) vertex order: position ``k`` holds the vertex eliminated ``k``-th.
    """
    import pymetis

    xadj, adjncy = _adjacency(n, rows, cols)
    perm, _ = pymetis.nested_dissection(pymetis.CSRAdjacency(xadj, adjncy))
    return np.asarray(perm, dtype=np.int64)


def factor_flops(n: int, rows: IntArray, cols: IntArray, order: IntArray,
                 analysis: Callable[[IntArray, IntArray, IntArray], float | None] | None = None
                 ) -> float:
    """The work of one Cholesky factorisation of a graph's matrix under ``order``: the flop
    count of a symbolic analysis, ``analysis(indptr, indices, order)`` of the matrix's lower
    triangle (CSC, diagonal included; e.g. CHOLMOD's,
    :meth:`ga_ros.core.linalg.cholmod_ctypes._DirectCholmod.analysis_flops`: no numeric
    factorisation), or, without one (or when it returns ``None``), ``sum_j c_j^2`` over the
    columns of the factor (``c_j`` its non-zeros) from a numeric factorisation; the two are
    equal.

    The matrix factored is the graph Laplacian plus the identity (positive definite, the
    pattern of the graph).
    """
    off = rows != cols
    r, c = np.maximum(rows[off], cols[off]), np.minimum(rows[off], cols[off])
    if analysis is not None:
        diag = np.arange(n, dtype=np.int64)
        flops = analysis(*_compressed(  # the lower triangle by column, then row
            _sorted_unique(np.concatenate([c * n + r, diag * n + diag])), n), order)
        if flops is not None:
            return flops
    return _numeric_factor_flops(n, r, c, order)


def _numeric_factor_flops(n: int, r: IntArray, c: IntArray, order: IntArray) -> float:
    """``sum_j c_j^2`` of the factor of ``L + I`` (``L`` the Laplacian of the edges
    ``r[k] > c[k]``) under ``order``, from CHOLMOD's symbolic and numeric phases (cvxopt)."""
    from cvxopt import cholmod

    deg = np.bincount(np.concatenate([r, c]), minlength=n).astype(float)
    diag = np.arange(n, dtype=np.int64)
    A = cvxopt.spmatrix(cvxopt.matrix(np.concatenate([deg + 1.0, -np.ones(r.size)])),
                        cvxopt.matrix(np.concatenate([diag, r])),
                        cvxopt.matrix(np.concatenate([diag, c])), (n, n))
    saved = dict(cholmod.options)
    cholmod.options['nmethods'] = 1
    cholmod.options['supernodal'] = 0  # simplicial: getfactor reads it directly
    try:
        F = cholmod.symbolic(A, p=cvxopt.matrix(np.asarray(order, dtype=np.int64), tc='i'),
                             uplo='L')
        cholmod.numeric(A, F)
        L = cholmod.getfactor(F)
    finally:
        cholmod.options.clear()
        cholmod.options.update(saved)
    counts = np.diff(np.asarray(L.CCS[0]).ravel()).astype(float)
    return float(np.sum(counts * counts))


def best_block_order(n: int, rows: IntArray, cols: IntArray, amd: IntArray,
                     analysis: Callable[[IntArray, IntArray, IntArray], float | None] | None
                     = None) -> IntArray:
    """The AMD order ``amd`` of a block graph, or its nested-dissection order when the graph
    has at least :data:`METIS_MIN_BLOCKS` vertices and the factor costs fewer flops with it
    (:func:`factor_flops`, with ``analysis`` if given)."""
    if n < METIS_MIN_BLOCKS or not HAVE_METIS:
        return amd
    nd = nested_dissection(n, rows, cols)
    if factor_flops(n, rows, cols, nd, analysis) < factor_flops(n, rows, cols, amd, analysis):
        return nd
    return amd


def _block_amd(pattern: BlockPattern, keep: np.ndarray) -> IntArray:
    """AMD order (block indices) of the blocks ``keep`` of the block graph."""
    idx = np.nonzero(keep)[0]
    if idx.size <= 1 or _amd is None:
        return idx
    local = np.full(keep.size, -1, dtype=np.int64)
    local[idx] = np.arange(idx.size)
    r, c = local[pattern.block_lower[0]], local[pattern.block_lower[1]]
    ok = (r >= 0) & (c >= 0)
    r, c = r[ok], c[ok]
    G = cvxopt.spmatrix(cvxopt.matrix(np.ones(r.size)), cvxopt.matrix(r), cvxopt.matrix(c),
                        (idx.size, idx.size))
    return idx[np.array(_amd.order(G, uplo='L')).ravel().astype(np.int64)]


#: Block orderings kept per pattern (a window's pattern repeats every track once it is full).
_ORDERINGS: OrderedDict[bytes, IntArray] = OrderedDict()


_MAX_ORDERINGS = 16


def block_ordering(pattern: BlockPattern,
                   flops: Callable[[IntArray, IntArray, IntArray], float | None] | None = None
                   ) -> IntArray:
    """Fill-reducing scalar permutation of a block pattern: AMD (or, on large graphs, nested
    dissection) of its block graph (:func:`best_block_order`), each block's ``d`` unknowns
    kept together. ``flops``: the flop count of a symbolic analysis (CHOLMOD's, given by
    :class:`~ga_ros.core.linalg.cholmod.SparseCholesky`), else counted from a numeric
    factorisation. Kept per pattern (:data:`_ORDERINGS`)."""
    amd = lambda: _block_amd(pattern, np.ones(pattern.n_blocks, dtype=bool))  # noqa: E731
    return _kept(_ORDERINGS, _MAX_ORDERINGS, pattern.key, lambda: _expand(
        best_block_order(pattern.n_blocks, *pattern.block_lower, amd(), flops),
        pattern.d))


def _trailing_ordering(pattern: BlockPattern, trailing: IntArray) -> IntArray:
    """AMD of the blocks not in ``trailing``, then ``trailing`` in the given order."""
    rest = np.ones(pattern.n_blocks, dtype=bool)
    rest[trailing] = False
    return _expand(np.concatenate([_block_amd(pattern, rest), trailing]), pattern.d)


def _expand(block_perm: IntArray, d: int) -> IntArray:
    return (np.asarray(block_perm, dtype=np.int64)[:, None] * d + np.arange(d)).ravel()
