"""Sparse assembly and Cholesky factorisation of normal matrices.

The normal matrix ``N = A' M^-1 A`` has one ``d x d`` block per node and one off-diagonal block
pair per connected node pair, so it has the sparsity of the connection graph. It is assembled from
per-connection blocks with a pattern computed once (:class:`BlockPattern`) and factored with
CHOLMOD (SuiteSparse, through cvxopt), reusing the symbolic analysis (fill-reducing ordering)
across iterations. The fill-reducing ordering is AMD of the *block* graph (one vertex per node,
``d^2`` times smaller than the scalar matrix), expanded to scalars, and is kept per pattern:
a sliding window whose pattern repeats every track pays for it once. Without cvxopt, SciPy's
SuperLU is used.

:func:`trailing_factor` orders chosen blocks last, so the trailing dense block of the factor is
the Cholesky factor of the Schur complement onto them (a partial factorisation): marginal
covariances and marginal information of a few nodes without inverting anything else.
"""

from __future__ import annotations

import ctypes
import glob
import os
import threading
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import lapack
from ga_ros.errors import DegenerateGeometryError
from ga_ros.runtime import lazy_import, openblas_coretype

try:  # CPython's BLAKE2 module: what hashlib.blake2b is, without loading OpenSSL (~5 ms)
    from _blake2 import blake2b as _blake2b
except ImportError:  # pragma: no cover - another interpreter
    from hashlib import blake2b as _blake2b

sla = lazy_import('scipy.linalg')  # only some functions need them (start-up)
sp = lazy_import('scipy.sparse')

try:  # CHOLMOD, bundled in the cvxopt wheel
    with openblas_coretype():
        import cvxopt
        from cvxopt import amd as _amd
        from cvxopt import cholmod as _cholmod

    _cholmod.options['supernodal'] = 2
    _cholmod.options['postorder'] = True
except ImportError:  # pragma: no cover - the pinned requirements include cvxopt
    cvxopt = None
    _amd = None
    _cholmod = None

#: Block orderings kept per pattern (a window's pattern repeats every track once it is full).
_ORDERINGS: OrderedDict[bytes, IntArray] = OrderedDict()
_MAX_ORDERINGS = 16
#: CHOLMOD input matrices kept per pattern (the few latest: a window's, its freeze's).
_MATRICES: OrderedDict[bytes, object] = OrderedDict()
_MAX_MATRICES = 4
#: Blocks assembled per pass by :meth:`BlockPattern.assemble` (bounds its temporaries).
_ASSEMBLY_CHUNK = 1 << 18
#: Patterns with fewer stored entries keep the position of every block entry (a gather per
#: assembly); larger ones compute them from each block's column and rank when assembling
#: (~180 MB less at 100,000 poses).
_POSITIONS_KEPT_BELOW = 1 << 22


class BlockPattern:
    """Where each entry of many dense ``d x d`` blocks lands in a sparse lower triangle (CSC).

    Only block *pairs* are sorted (not their ``d^2`` scalars): the scalar layout of a lower
    block column follows from its sorted block rows, the diagonal block first.

    Parameters
    ----------
    block_rows, block_cols : (k,) block coordinates (column index of the unknown block; -1 for a
        fixed node, whose entries are dropped). Every block column must hold its diagonal block.
    d : block size.
    n : number of unknown blocks.
    """

    def __init__(self, block_rows: IntArray, block_cols: IntArray, d: int, n: int) -> None:
        self.d = d
        self.size = d * n
        br = np.asarray(block_rows, dtype=np.int64)
        bc = np.asarray(block_cols, dtype=np.int64)
        keep_blk = (br >= 0) & (bc >= 0) & (br >= bc)
        self._keep_blk = keep_blk
        kbr, kbc = br[keep_blk], bc[keep_blk]
        key = kbc * max(n, 1) + kbr  # column-major: sorted by column, then row
        ukey, inv = np.unique(key, return_inverse=True)
        ucol, urow = ukey // max(n, 1), ukey % max(n, 1)
        self.n_blocks = n
        self.block_lower = (urow, ucol)  # unique lower block pairs (row >= col), column-major
        self.key = _blake2b(np.ascontiguousarray(ukey).tobytes()
                                   + np.int64(n).tobytes() + np.int64(d).tobytes(),
                                   digest_size=16).digest()
        nblk_col = np.bincount(ucol, minlength=n)
        if n and not np.array_equal(np.sort(ucol[urow == ucol]), np.arange(n)):
            raise DegenerateGeometryError('a block column has no diagonal block')
        first = np.concatenate([[0], np.cumsum(nblk_col)[:-1]])
        rank = np.arange(ukey.size) - first[ucol]  # 0 for the diagonal block
        a = np.arange(d)
        # entries per scalar column J*d + a: d * blocks - a
        counts = (d * nblk_col[:, None] - a[None, :]).reshape(-1)
        self.indptr = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        self.nnz = int(self.indptr[-1])
        self._ucol, self._urank = ucol, rank
        self._tril = (a[:, None] >= a[None, :]).reshape(-1)  # (d^2,) row-major: row >= col
        # the row of every stored entry: kept for small patterns, computed when asked for large
        # ones (~180 MB at 100,000 poses; only the analysis and CSC views read it)
        small = self.nnz < _POSITIONS_KEPT_BELOW
        # positions of the unique blocks' entries: computed once for both uses below
        upos = self._block_positions(np.arange(ukey.size)) if small else None
        self._indices = self._row_indices(upos) if small else None
        # which entries of each kept block land in the lower triangle: all of an off-diagonal
        # block, the lower triangle of a diagonal one (one flag per block, not per entry)
        self._kept_diag = (rank == 0)[inv]
        # each kept block's unique block, that block's column and rank in it: positions of
        # the entries of any kept blocks (:meth:`_positions`)
        self._kept_u = inv.astype(np.int32 if ukey.size < 2**31 else np.int64)
        self._pos: IntArray | None = None
        if small:  # kept: a gather instead of the arithmetic (int32: it fits)
            self._pos = upos[self._kept_u][self._valid(slice(None))]
        self._gather: IntArray | None = None  # built by assemble on first use
        self._kept_idx: IntArray | None = None  # the kept blocks (compiled assemble)
        self._full: tuple | None = None  # built by full_csc on first use
        self._valid_before: IntArray | None = None  # built by assemble_at on first use
        self._kept_rank: IntArray | None = None

    @staticmethod
    def from_matrix(N: sp.spmatrix, d: int) -> tuple[BlockPattern, FloatArray]:
        """The block pattern of a symmetric sparse matrix of ``d x d`` blocks and its lower
        triangle's values on it (every diagonal block is kept, even if zero)."""
        n = N.shape[0] // d
        Nb = sp.bsr_matrix(sp.csr_matrix(N), blocksize=(d, d))
        Nb.sort_indices()
        rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(Nb.indptr))
        cols = Nb.indices.astype(np.int64)
        diag = np.arange(n, dtype=np.int64)
        blocks = np.concatenate([Nb.data, np.zeros((n, d, d))])
        pattern = BlockPattern(np.concatenate([rows, diag]), np.concatenate([cols, diag]), d, n)
        return pattern, pattern.assemble(blocks)

    def assemble(self, blocks: FloatArray, compiled: bool = False) -> FloatArray:
        """Sum blocks ``(k, d, d)`` (block row, col) into the lower-triangle CSC values.

        More than :data:`_ASSEMBLY_CHUNK` blocks go in chunks, added in place: the temporaries
        (two copies of the blocks in one pass, ~1.4 GB for a survey of 100,000 poses) stay
        ~150 MB. ``compiled`` (a caller that runs the compiled kernels anyway, e.g. a window
        update): the blocks of a small pattern are added by one compiled loop instead of a
        gather and a ``bincount`` (the same sums in the same order; ~2x faster)."""
        small = blocks.shape[0] <= _ASSEMBLY_CHUNK
        if small and self._pos is not None and blocks.shape[0] == self._keep_blk.size:
            scatter = _scatter_kernel() if compiled else None
            if scatter is not None:  # no gather index (~1 M entries for a window) either
                if self._kept_idx is None:
                    self._kept_idx = np.flatnonzero(self._keep_blk)
                out = np.zeros(self.nnz)
                scatter(np.ascontiguousarray(blocks, dtype=float).reshape(-1), self._kept_idx,
                        self._kept_diag, self._tril, self._pos, out)
                return out
            # one gather of the kept entries (instead of two masked copies): ~2x faster
            if self._gather is None:
                self._gather = self._kept_entries()
            vals = blocks.reshape(-1)[self._gather]
            return np.bincount(self._pos, weights=vals, minlength=self.nnz)
        if small:
            vals = blocks[self._keep_blk].reshape(-1)[self._valid(slice(None)).reshape(-1)]
            pos = self._pos if self._pos is not None else self._positions(slice(None))
            return np.bincount(pos, weights=vals, minlength=self.nnz)
        keep, done = np.nonzero(self._keep_blk)[0], 0
        out = np.zeros(self.nnz)
        for a in range(0, keep.size, _ASSEMBLY_CHUNK):
            part = slice(a, a + _ASSEMBLY_CHUNK)
            vals = blocks[keep[part]].reshape(-1)[self._valid(part).reshape(-1)]
            pos = (self._pos[done:done + vals.size] if self._pos is not None
                   else self._positions(part))
            np.add.at(out, pos, vals)  # no nnz-long temporary
            done += vals.size
        return out

    def _kept_entries(self) -> IntArray:
        """``(len(_pos),)`` flat index, into the ``(k, d, d)`` block list this pattern was
        built from, of each entry that lands in the lower triangle, in the order of ``_pos``."""
        d2 = self.d * self.d
        it = np.int32 if self._keep_blk.size * d2 < 2**31 else np.int64  # half the traffic
        kept = np.flatnonzero(self._keep_blk).astype(it)
        return (kept[:, None] * it(d2) + np.arange(d2, dtype=it)[None, :])[
            self._valid(slice(None))]

    def assemble_at(self, blocks: FloatArray, index: IntArray, out: FloatArray) -> None:
        """Add blocks ``(k, d, d)`` that stand at the positions ``index`` of the block list
        this pattern was built from into ``out`` (lower-triangle CSC values, in place): the
        assembly of a large system a part at a time (``assemble`` of the whole list equals the
        sum over disjoint parts)."""
        d = self.d
        d2 = d * d
        if self._kept_rank is None:  # position among the kept blocks
            self._kept_rank = (np.cumsum(self._keep_blk) - 1).astype(np.int32)
        if self._valid_before is None and self._pos is not None:
            per = np.where(self._kept_diag, d * (d + 1) // 2, d2)
            self._valid_before = np.concatenate([[0], np.cumsum(per)])
        index = np.asarray(index, dtype=np.int64)
        keep = self._keep_blk[index]
        rank = self._kept_rank[index[keep]]
        valid = self._valid(rank)
        if self._pos is None:
            where = self._positions(rank)
        else:
            count = valid.sum(axis=1)
            first = np.repeat(self._valid_before[rank] - np.cumsum(count) + count, count)
            where = self._pos[first + np.arange(first.size)]
        # in place: a bincount would allocate an nnz-long array per part (~190 MB at 100,000
        # poses) and np.add.at is faster for a part's few million entries
        np.add.at(out, where, blocks[keep].reshape(-1, d2)[valid])

    @property
    def indices(self) -> IntArray:
        """(nnz,) int64 row of each stored entry of the lower-triangle CSC values."""
        return self._indices if self._indices is not None else self._row_indices()

    def _row_indices(self, upos: IntArray | None = None) -> IntArray:
        """(nnz,) row of each stored entry; ``upos``: the unique blocks' positions
        (:meth:`_block_positions` of all of them) if the caller has them."""
        d = self.d
        if upos is None:
            upos = self._block_positions(np.arange(self._ucol.size))
        valid = np.where((self._urank == 0)[:, None], self._tril[None, :], True)
        it = np.int32 if self.size < 2**31 else np.int64  # the temporaries: half the traffic
        rows = (self.block_lower[0].astype(it)[:, None] * it(d)
                + np.repeat(np.arange(d, dtype=it), d)[None, :])
        out = np.empty(self.nnz, dtype=np.int64)
        out[upos[valid]] = rows[valid]
        return out

    def _block_positions(self, u: IntArray) -> IntArray:
        """``(k, d^2)`` positions in the lower-triangle CSC values of the entries (row-major)
        of the unique blocks ``u`` (meaningless for the upper entries of a diagonal block);
        int32 when the values fit.

        Row ``b``, column ``a`` of a block of rank ``r`` in its block column lies
        ``r d + b - a`` entries after the start of scalar column ``a`` of that block column:
        after the ``d - a`` entries of the diagonal block's column ``a`` and ``r - 1`` earlier
        blocks of ``d`` rows (the diagonal block itself, ``r = 0``: ``b - a``)."""
        d = self.d
        a = np.arange(d)
        it = np.int32 if self.nnz < 2**31 else np.int64
        colstart = self.indptr[:-1].reshape(-1, d).astype(it)  # (block columns, a)
        start = colstart[self._ucol[u]] - a.astype(it)  # (k, a)
        start += (self._urank[u] * d).astype(it)[:, None]
        out = start[:, None, :] + a.astype(it)[None, :, None]  # (k, b, a)
        return out.reshape(-1, d * d)

    def _positions(self, kept) -> IntArray:
        """Positions in the lower-triangle CSC values of the entries of the kept blocks
        ``kept`` (an index or a slice of the kept blocks) that land there, block by block, each
        block's entries row-major (the order of ``_pos``)."""
        return self._block_positions(self._kept_u[kept])[self._valid(kept)]

    def _valid(self, kept) -> np.ndarray:
        """``(k, d^2)`` flags of the entries of the kept blocks ``kept`` (an index or a slice
        of the kept blocks) that land in the lower triangle."""
        return np.where(self._kept_diag[kept][:, None], self._tril[None, :], True)

    def matvec(self, data: FloatArray, x: FloatArray) -> FloatArray:
        """``N x`` for the symmetric matrix whose lower triangle is ``data`` (NumPy only: the
        dogleg's products need no ``scipy.sparse``)."""
        cols = np.repeat(np.arange(self.size), np.diff(self.indptr))
        x = np.asarray(x, dtype=float)
        y = np.bincount(self.indices, weights=data * x[cols], minlength=self.size)  # L x
        y += np.bincount(cols, weights=data * x[self.indices], minlength=self.size)  # L' x
        return y - data[self.indptr[:-1]] * x  # the diagonal entry heads each column

    def lower_csc(self, data: FloatArray) -> sp.csc_matrix:
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))

    def full_csc(self, data: FloatArray) -> sp.csc_matrix:
        """The symmetric matrix (both triangles), canonical, without explicit zeros (those of the
        sum ``L + L'`` of SciPy). A small pattern keeps where each entry comes from in
        ``data`` (a window's freeze builds one matrix of a repeating pattern per track)."""
        if self._full is None and self.nnz < _POSITIONS_KEPT_BELOW:
            L = self.lower_csc(np.arange(1.0, self.nnz + 1.0))  # positions, never zero
            F = (L + sp.tril(L, -1).T).tocsc()
            self._full = (F.indptr, F.indices, np.rint(F.data).astype(np.int64) - 1)
        if self._full is not None:
            indptr, indices, source = self._full
            vals = data[source]
            if vals.all():  # else: explicit zeros, dropped below as the sum drops them
                return sp.csc_matrix((vals, indices.copy(), indptr.copy()),
                                     shape=(self.size, self.size))
        L = self.lower_csc(data)
        return (L + sp.tril(L, -1).T).tocsc()


class SparseCholesky:
    """Factor of a symmetric positive definite matrix given by its lower triangle (CSC).

    Reuse one instance across matrices with the same pattern: :meth:`refactor` keeps the ordering.
    Raises :class:`DegenerateGeometryError` when the matrix is not positive definite (e.g. a datum
    is missing or part of the network is unconstrained). ``auto``: a small, very sparse matrix
    may get a simplicial factor (:meth:`_DirectCholmod.analyse`), which selected inversion
    reads through a copy; the default is supernodal (read in place).
    """

    def __init__(self, pattern: BlockPattern, data: FloatArray,
                 trailing: IntArray | None = None, analysis=None, auto: bool = False) -> None:
        self.pattern = pattern
        self.n = pattern.size
        self._auto = auto
        self._trailing = None if trailing is None else np.asarray(trailing, dtype=np.int64)
        self._symbolic = analysis  # a kept symbolic factor of this pattern (keep_analysis)
        self._permuted: _Permuted | None = None  # P N P' for the direct factorisation
        self._A = None
        self._F = None
        self._lu = None
        self.refactor(data)

    @property
    def analysis(self):
        """The symbolic analysis (ordering, supernodes) the next :meth:`refactor` reuses, or
        ``None`` before the first factorisation."""
        return self._symbolic

    def keep_analysis(self, analysis) -> None:
        """Keep only ``analysis`` (a symbolic factor of this pattern, e.g. after a selected
        inversion overwrote the numeric factor in place): the next :meth:`refactor` factors
        anew on it."""
        self._symbolic = analysis

    def refactor(self, data: FloatArray) -> None:
        """Numeric factorisation of new values on the same pattern (ordering reused).

        With the bundled CHOLMOD reachable through ``ctypes`` (:func:`_direct_cholmod`), the
        values are handed to ``cholmod_l_factorize`` where they lie: no copy of ``N``'s values
        and row indices into cvxopt, none into CHOLMOD's packed input (~0.75 GB for a survey of
        100,000 poses); the factor is the same (same library, same input)."""
        if not np.isfinite(data).all():
            raise DegenerateGeometryError('normal matrix has NaN or inf entries')
        p = self.pattern
        self._data = data
        if _cholmod is not None:
            direct = _direct_cholmod()
            if self._symbolic is None:
                self._permuted = None
                if direct is not None:  # no cvxopt copy of the pattern (~40 ms for a window)
                    self._symbolic = direct.analyse(p, self._ordering(), self._trailing is None,
                                                    self._auto)
                if self._symbolic is None:
                    if self._A is None:
                        self._A = _cvxopt_pattern(p, keep=direct is None)
                    self._symbolic = self._analyse()
                if direct is not None:
                    self._A = None  # only the analysis needs cvxopt's copy of the pattern
            try:
                if direct is not None:
                    if self._permuted is None and p.nnz >= _PERMUTE_FROM_NNZ:
                        self._permuted = direct.permuted(p, self._symbolic)
                    direct.factorize(p, data, self._symbolic, self._permuted)
                else:
                    self._A.V = cvxopt.matrix(np.ascontiguousarray(data, dtype=float))
                    _cholmod.numeric(self._A, self._symbolic)
            except ArithmeticError as exc:
                self._symbolic = None
                raise DegenerateGeometryError(
                    'the normal matrix is singular (not positive definite): some unknowns are not '
                    'determined by the observations; fix a datum (first node) or add priors'
                ) from exc
            self._F = self._symbolic
        else:  # pragma: no cover
            from scipy.sparse.linalg import splu
            N = p.full_csc(data)
            try:
                self._lu = splu(N, permc_spec='MMD_AT_PLUS_A')
            except RuntimeError as exc:
                raise DegenerateGeometryError('the normal matrix is singular') from exc

    def release_values(self) -> None:
        """Let go of the values last factored (the caller assembles new ones): a factor read
        out later (:meth:`trailing_lower`, selected inversion) cannot be recomputed for a
        solve then, until :meth:`refactor` is given values again."""
        self._data = None

    def _ordering(self) -> IntArray:
        """The scalar fill-reducing ordering: the block ordering, or the trailing blocks last."""
        if self._trailing is None:
            return block_ordering(self.pattern)
        return _trailing_ordering(self.pattern, self._trailing)

    def _analyse(self):
        """CHOLMOD's symbolic analysis with the block ordering (trailing blocks last, kept in
        place: no postordering then), through cvxopt."""
        pvec = cvxopt.matrix(np.ascontiguousarray(self._ordering(), dtype=np.int64), tc='i')
        # only the ordering given (no second analysis with AMD); trailing blocks stay last
        saved = dict(_cholmod.options)
        _cholmod.options['nmethods'] = 1
        _cholmod.options['postorder'] = self._trailing is None
        try:
            return _cholmod.symbolic(self._A, p=pvec, uplo='L')
        finally:
            _cholmod.options.clear()
            _cholmod.options.update(saved)

    def permutation(self) -> IntArray:
        """``p`` of the factorisation ``P N P' = L L'``: row ``k`` of ``L`` is unknown ``p[k]``."""
        x = cvxopt.matrix(np.arange(self.n, dtype=float))
        _cholmod.solve(self._F, x, sys=7)
        return np.rint(np.array(x).ravel()).astype(np.int64)

    def trailing_lower(self, m: int) -> tuple[FloatArray, IntArray]:
        """The last ``m`` rows and columns of ``L`` (dense lower triangular) and the unknowns
        they belong to, in that order."""
        who = self.permutation()[self.n - m:]
        F = _cholmod.getfactor(self._F)  # this turns CHOLMOD's factor back into a symbolic one
        self._F = None
        self._symbolic = self._permuted = None  # analysed again if the factor is used again
        s0 = self.n - m
        colptr, rowind, values = F.CCS  # cvxopt matrices: read through the buffer protocol
        J = np.asarray(colptr).ravel()
        start = int(J[s0])
        rows = np.asarray(rowind).ravel()[start:]
        vals = np.asarray(values).ravel()[start:]
        cols = np.repeat(np.arange(s0, self.n), np.diff(J[s0:]))
        L = np.zeros((m, m))
        L[rows - s0, cols - s0] = vals
        return L, who

    def solve(self, b: FloatArray) -> FloatArray:
        """Solve ``N x = b`` for ``b`` of shape ``(n,)`` or ``(n, k)``."""
        b = np.asarray(b, dtype=float)
        if self._F is None and _cholmod is not None:  # the factor was read out: factor again
            if self._data is None:
                raise DegenerateGeometryError('this factor was read out and its values released:'
                                              ' refactor() it before solving')
            self.refactor(self._data)
        if self._F is not None:
            B = cvxopt.matrix(np.asfortranarray(b.reshape(self.n, -1)))
            _cholmod.solve(self._F, B)
            x = np.array(B).reshape(b.shape)
        else:  # pragma: no cover
            x = self._lu.solve(b)
        if not np.isfinite(x).all():
            raise DegenerateGeometryError('solving the normal equations produced NaN/inf: '
                                          'the problem is singular or badly scaled')
        return x


#: Guards the caches of :func:`_kept` (the freeze ahead reads them from a background thread).
_KEPT_LOCK = threading.Lock()


def _kept(cache: OrderedDict, limit: int, key: bytes, build):
    """``cache[key]``, built by ``build()`` on a miss; the ``limit`` most recent are kept.
    Thread-safe; ``build`` runs outside the lock (two threads missing at once may each build
    it, one value is kept)."""
    with _KEPT_LOCK:
        value = cache.get(key)
        if value is not None:
            cache.move_to_end(key)
            return value
    value = build()
    with _KEPT_LOCK:
        cache[key] = value
        cache.move_to_end(key)
        while len(cache) > limit:
            cache.popitem(last=False)
    return value


#: Block patterns kept by the block coordinates they were built from (the few latest).
_PATTERNS: OrderedDict[bytes, BlockPattern] = OrderedDict()
_MAX_PATTERNS = 4


def kept_block_pattern(block_rows: IntArray, block_cols: IntArray, d: int, n: int
                       ) -> BlockPattern:
    """:class:`BlockPattern` of these block coordinates, kept for the few latest (a window
    update solves problems of one repeating pattern: building it sorts every block again)."""
    key = _blake2b(block_rows.tobytes() + block_cols.tobytes()
                          + np.array([d, n], dtype=np.int64).tobytes(), digest_size=16).digest()
    return _kept(_PATTERNS, _MAX_PATTERNS, key,
                 lambda: BlockPattern(block_rows, block_cols, d, n))


def _cvxopt_pattern(pattern: BlockPattern, keep: bool = True):
    """CHOLMOD's input matrix for a pattern (values are set before each factorisation). Building
    it sorts every entry again (~15 ms for 260,000 entries), so it is kept per pattern too
    (``keep``, or a pattern small enough to keep its entry positions; a large one not when only
    the symbolic analysis needs it: :func:`_direct_cholmod`)."""
    keep = keep or pattern.nnz < _POSITIONS_KEPT_BELOW

    def build():
        return cvxopt.spmatrix(
            cvxopt.matrix(np.zeros(pattern.nnz)), cvxopt.matrix(pattern.indices.astype(np.int64)),
            cvxopt.matrix(_expand_cols(pattern.indptr)), (pattern.size, pattern.size))

    return _kept(_MATRICES, _MAX_MATRICES, pattern.key, build) if keep else build()


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


#: CHOLMOD's ordering codes (cholmod_core.h).
_CHOLMOD_GIVEN, _CHOLMOD_AMD = 1, 2


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
    stays cvxopt's (its analysis, solves and ``getfactor`` are cvxopt's)."""

    _COMMON_BYTES = 1 << 16  # larger than cholmod_common (a few KiB)

    def __init__(self, path: str) -> None:
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
        self._capsule = self._capsule_maker()

    def _capsule_maker(self):
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
        self._model = _cholmod.symbolic(cvxopt.spmatrix([1.0], [0], [0]))  # kept: its name
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
        overhead of thousands of tiny BLAS calls (intel, 5,181 unknowns: analysis 0.9 -> 0.5
        ms, factorisation 1.7 -> 1.0 ms, solve 0.19 -> 0.08 ms). :meth:`factorize` makes a
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


def _permute_py(x, where, inverse, seen):  # pragma: no cover - compiled
    """In place, cycle by cycle: ``x[k] <- x[where[k]]`` for every ``k`` (a gather without a
    copy), or with ``inverse`` its inverse, ``x[where[k]] <- x[k]``. ``seen``: (x.size,) False."""
    for s in range(x.size):
        if seen[s]:
            continue
        tmp = x[s]
        j = s
        while True:
            seen[j] = True
            k = where[j]
            if inverse:
                nxt = x[k]
                x[k] = tmp
                tmp = nxt
                if k == s:
                    break
            elif k == s:
                x[j] = tmp
                break
            else:
                x[j] = x[k]
            j = k


_PERMUTE: list = []  # [the compiled _permute_py or None], compiled on first use


def _scatter_add_py(flat, kept, diag, tril, pos, out):  # pragma: no cover - compiled
    """Add the entries of the kept blocks ``kept`` of ``flat`` (the ``(k, d, d)`` blocks,
    flattened) into ``out`` at ``pos``: block by block, each block's entries row-major, of a
    diagonal block (``diag``) only those on or below the diagonal (``tril``). The entries and
    their order are those of :meth:`BlockPattern._kept_entries`, so the sums are
    ``np.bincount(pos, weights=flat[_kept_entries()])``'s, without the gathered copy."""
    d2 = tril.size
    p = 0
    for b in range(kept.size):
        base = kept[b] * d2
        lower = diag[b]
        for e in range(d2):
            if lower and not tril[e]:
                continue
            out[pos[p]] += flat[base + e]
            p += 1


_SCATTER: list = []  # [the compiled _scatter_add_py or None], compiled on first use


def _compiled(slot: list, fn):
    """``fn`` compiled with numba (cached on disk) on first use and kept in ``slot`` (a
    one-element list), or ``None`` without numba."""
    if not slot:
        from ga_ros.core.kernels import AVAILABLE

        compiled = None
        if AVAILABLE:
            import numba

            compiled = numba.njit(cache=True, nogil=True)(fn)
        slot.append(compiled)
    return slot[0]


def _scatter_kernel():
    """:func:`_scatter_add_py` compiled, or ``None`` without numba
    (:meth:`BlockPattern.assemble` gathers and counts with NumPy then)."""
    return _compiled(_SCATTER, _scatter_add_py)


def _permutation_kernel():
    """:func:`_permute_py` compiled, or ``None`` without numba (the values are gathered into
    a copy then)."""
    return _compiled(_PERMUTE, _permute_py)


@dataclass(frozen=True)
class _Permuted:
    """The lower triangle of ``P N P'`` in CSC: ``where`` (its entries' positions in ``N``'s
    values), ``indptr``, ``indices`` (int64, as CHOLMOD's long interface reads them)."""

    where: IntArray
    indptr: IntArray
    indices: IntArray


_DIRECT: list = []  # [the _DirectCholmod or None], found on first use
#: From this many stored entries of ``N`` on, the direct factorisation hands CHOLMOD ``N``
#: already permuted (:meth:`_DirectCholmod.permuted`: an argsort of the entries once per
#: analysis, ~0.1 s per million; a window's few hundred thousand entries are factored as given).
_PERMUTE_FROM_NNZ = 1 << 22
#: Below this many unknowns a factor asked for ``auto`` is simplicial or supernodal as CHOLMOD
#: chooses (:meth:`_DirectCholmod.analyse`); from it on it is supernodal.
_AUTO_SUPERNODAL_BELOW = 6000


def _direct_cholmod() -> _DirectCholmod | None:
    """The direct CHOLMOD call (:class:`_DirectCholmod`), or ``None`` when the library cvxopt
    bundles is not found or not the expected version (then cvxopt's ``numeric`` is used);
    ``GA_ROS_DIRECT_CHOLMOD=0`` turns it off."""
    if not _DIRECT:
        found = None
        if cvxopt is not None and os.environ.get('GA_ROS_DIRECT_CHOLMOD', '1') != '0':
            libs = glob.glob(os.path.join(os.path.dirname(os.path.dirname(cvxopt.__file__)),
                                          'cvxopt.libs', 'libcholmod*.so.3.*'))
            try:
                found = _DirectCholmod(libs[0]) if len(libs) == 1 else None
            except (OSError, AttributeError):
                found = None
        _DIRECT.append(found)
    return _DIRECT[0]


def block_ordering(pattern: BlockPattern) -> IntArray:
    """Fill-reducing scalar permutation of a block pattern: AMD (or, on large graphs, nested
    dissection: :mod:`ga_ros.core.ordering`) of its block graph, each block's ``d`` unknowns kept
    together. Kept per pattern (:data:`_ORDERINGS`)."""
    from ga_ros.core.ordering import best_block_order

    amd = lambda: _block_amd(pattern, np.ones(pattern.n_blocks, dtype=bool))  # noqa: E731
    direct = _direct_cholmod()  # the orderings' flops from CHOLMOD's symbolic analysis
    flops = None if direct is None else direct.analysis_flops
    return _kept(_ORDERINGS, _MAX_ORDERINGS, pattern.key, lambda: _expand(
        best_block_order(pattern.n_blocks, *pattern.block_lower, amd(), flops), pattern.d))


def _trailing_ordering(pattern: BlockPattern, trailing: IntArray) -> IntArray:
    """AMD of the blocks not in ``trailing``, then ``trailing`` in the given order."""
    rest = np.ones(pattern.n_blocks, dtype=bool)
    rest[trailing] = False
    return _expand(np.concatenate([_block_amd(pattern, rest), trailing]), pattern.d)


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


def _expand(block_perm: IntArray, d: int) -> IntArray:
    return (np.asarray(block_perm, dtype=np.int64)[:, None] * d + np.arange(d)).ravel()


@dataclass
class TrailingFactor:
    """Partial factorisation of ``N`` with some node blocks ordered last (:func:`trailing_factor`).

    Attributes
    ----------
    L : (t, t) dense lower-triangular factor of the Schur complement of the other blocks onto
        the trailing ones, ``S = L L'`` (``S^-1`` is their joint marginal covariance), rows and
        columns in the order of ``blocks`` (``d`` unknowns each).
    d : unknowns per block.
    solution : ``N^-1 rhs`` when a right-hand side was given.
    """

    L: FloatArray
    d: int
    solution: FloatArray | None = None

    def information(self) -> FloatArray:
        """``S = L L'``, the Schur complement (marginal information) of the trailing blocks."""
        S = self.L @ self.L.T
        return 0.5 * (S + S.T)

    def marginal_blocks(self) -> FloatArray:
        """Diagonal ``d x d`` blocks of ``S^-1`` (the trailing nodes' marginal covariances),
        ``(k, d, d)``, from ``S^-1 = L^-T L^-1`` without forming ``S^-1``."""
        d = self.d
        Li = sla.lapack.dtrtri(self.L, lower=1)[0]
        if not np.isfinite(Li).all():
            raise DegenerateGeometryError('the trailing Schur complement is singular')
        k = Li.shape[0] // d
        C = Li.reshape(Li.shape[0], k, d)
        out = np.einsum('iab,iac->abc', C, C)
        return 0.5 * (out + np.swapaxes(out, 1, 2))


def trailing_factor(pattern: BlockPattern, data: FloatArray, blocks: IntArray,
                    rhs: FloatArray | None = None) -> TrailingFactor:
    """Factor ``N`` (lower triangle ``data`` on ``pattern``) with the node blocks ``blocks``
    ordered last, the others by AMD of their block graph.

    The trailing ``t = d len(blocks)`` rows of the factor hold the Cholesky factor of the Schur
    complement ``S = N_BB - N_BR N_RR^-1 N_RB`` (a partial factorisation: the rest is eliminated
    by the sparse factorisation, never inverted). Costs one sparse factorisation plus a dense
    ``t x t`` trailing block. With ``rhs`` (shape ``(n,)`` or ``(n, k)``), ``N^-1 rhs`` is
    returned too (from the same factor).

    Raises
    ------
    DegenerateGeometryError
        ``N`` is not positive definite, or CHOLMOD did not keep the blocks last.
    """
    if _cholmod is None:  # pragma: no cover
        raise DegenerateGeometryError('partial factorisation needs CHOLMOD (cvxopt)')
    blocks = np.asarray(blocks, dtype=np.int64)
    chol = SparseCholesky(pattern, data, trailing=blocks)
    x = None if rhs is None else chol.solve(rhs)
    d = pattern.d
    L, who = chol.trailing_lower(d * blocks.size)
    want = _expand(blocks, d)
    if not np.array_equal(who, want):
        if not np.array_equal(np.sort(who), np.sort(want)):
            raise DegenerateGeometryError('CHOLMOD did not keep the requested blocks last')
        # same set, other order: S is the same matrix permuted; refactor it densely
        pos = np.empty(pattern.size, dtype=np.int64)
        pos[who] = np.arange(who.size)
        q = pos[want]
        S = (L @ L.T)[np.ix_(q, q)]
        L = np.linalg.cholesky(0.5 * (S + S.T))
    return TrailingFactor(L, d, x)


def _expand_cols(indptr: IntArray) -> IntArray:
    return np.repeat(np.arange(indptr.size - 1, dtype=np.int64), np.diff(indptr))


def block_diagonal(blocks: FloatArray) -> sp.csr_matrix:
    """Sparse block-diagonal matrix from ``(k, d, d)`` blocks."""
    return sp.block_diag(list(blocks), format='csr') if len(blocks) else sp.csr_matrix((0, 0))


# ------------------------------------------------------------- sparse (banded) joint priors
@dataclass(frozen=True)
class BandSelection:
    """Band of the joint covariance of chosen nodes, from :func:`banded_selection`.

    Attributes
    ----------
    band : (m, w + 1, d, d) blocks ``band[i, j] = Sigma_{t_i, t_{i+j}}`` of ``Sigma = N^-1``
        for the targets ``t`` in the given order (zero where ``i + j >= m``).
    solution : ``N^-1 rhs`` when a right-hand side was given.
    block_nodes : node blocks per diagonal block of the block-tridiagonal factorisation (its
        cost is ``O(u b^2 d^3)`` for ``u`` nodes, ``b`` this number).
    """

    band: FloatArray
    solution: FloatArray | None
    block_nodes: int


def banded_selection(N: sp.spmatrix, d: int, targets: IntArray, w: int,
                     coords: FloatArray | None = None,
                     rhs: FloatArray | None = None,
                     max_band: int | None = None) -> BandSelection | None:
    """Blocks ``Sigma_{t_i, t_j}``, ``|i - j| <= w``, of ``Sigma = N^-1`` (selected inversion).

    The nodes are ordered along a narrow band (reverse Cuthill-McKee of the block graph, or
    their positions along the principal axis of ``coords``: the narrower of the two), cut into
    diagonal blocks of ``b`` nodes with ``b`` larger than both the half-bandwidth of ``N`` and
    the distance between any two targets whose pair is wanted, so ``N`` is block tridiagonal
    and every wanted pair lies in one diagonal or sub-diagonal block. The block Cholesky factor
    (diagonal ``D_k``, sub-diagonal ``L_k``) and Takahashi's backward recursion give those
    blocks of ``Sigma`` without any other part of it::

        Sigma_{k+1,k} = -Sigma_{k+1,k+1} L_k D_k^-1,
        Sigma_{k,k} = D_k^-T (D_k^-1 - L_k' Sigma_{k+1,k})

    Linear in the number of nodes for a strip (``O(u b^2 d^3)``), never a dense inverse.
    Nodes of high degree (the hubs of an earlier sparse prior, coupled to a whole swath) would
    widen the band to everything; they are ordered last as a border ``P`` instead: with
    ``Z = N_QQ^-1 N_QP`` (solves with the banded factor) and ``S = N_PP - N_PQ Z``,
    ``Sigma_QQ = N_QQ^-1 + Z S^-1 Z'``, ``Sigma_QP = -Z S^-1``, ``Sigma_PP = S^-1``.

    Parameters
    ----------
    N : (d u, d u) sparse symmetric positive definite matrix of ``u`` node blocks.
    d : block size.
    targets : (m,) node blocks whose band is wanted, in band order.
    w : half-bandwidth of the band in targets (>= 0).
    coords : optional (u, 3) node positions (their principal axis is tried as an ordering).
    rhs : optional (d u,) or (d u, k) right-hand side, solved with the same factor.
    max_band : give up (return ``None``) if a diagonal block of the factorisation or the border
        would exceed this many scalars (the caller then takes another way). Default: no limit.

    Raises
    ------
    DegenerateGeometryError
        ``N`` is not positive definite.
    """
    N = sp.csr_matrix(N)
    u = N.shape[0] // d
    t = np.asarray(targets, dtype=np.int64)
    m = t.size
    pair_i = np.repeat(np.arange(m), w + 1)
    pair_j = pair_i + np.tile(np.arange(w + 1), m)
    ok = pair_j < m
    pair_i, pair_j = pair_i[ok], pair_j[ok]
    pa, pc = t[pair_i], t[pair_j]
    coo = N.tocoo()
    G = sp.csr_matrix((np.ones(coo.nnz), (coo.row // d, coo.col // d)), shape=(u, u))
    degree = np.diff(G.indptr)
    border = degree > max(16.0, 4.0 * float(np.median(degree))) if u > 2 else \
        np.zeros(u, dtype=bool)
    if not 0 < border.sum() < u // 2:
        out = _banded_pairs(N, d, pa, pc, coords, rhs, max_band)
    elif max_band is not None and int(border.sum()) * d > max_band:
        out = None
    else:
        out = _bordered_pairs(N, d, border, pa, pc, coords, rhs, max_band)
    if out is None:
        return None
    blocks, x, bn = out
    band = np.zeros((m, w + 1, d, d))
    band[pair_i, pair_j - pair_i] = blocks
    return BandSelection(band, x, bn)


def _bordered_pairs(N: sp.csr_matrix, d: int, border: np.ndarray, pa: IntArray, pc: IntArray,
                    coords: FloatArray | None, rhs: FloatArray | None,
                    max_band: int | None = None
                    ) -> tuple[FloatArray, FloatArray | None, int] | None:
    """:func:`_banded_pairs` with the ``border`` nodes eliminated last (see
    :func:`banded_selection`)."""
    u = N.shape[0] // d
    q_nodes, p_nodes = np.nonzero(~border)[0], np.nonzero(border)[0]
    qs = (q_nodes[:, None] * d + np.arange(d)).ravel()
    ps = (p_nodes[:, None] * d + np.arange(d)).ravel()
    local = np.full(u, -1, dtype=np.int64)
    local[q_nodes] = np.arange(q_nodes.size)
    local[p_nodes] = np.arange(p_nodes.size)
    NQP = N[qs][:, ps].toarray()
    r = None if rhs is None else np.reshape(np.asarray(rhs, dtype=float), (N.shape[0], -1))
    b = NQP if r is None else np.column_stack([NQP, r[qs]])
    both_q = ~border[pa] & ~border[pc]
    inner = _banded_pairs(N[qs][:, qs], d, local[pa[both_q]], local[pc[both_q]],
                          None if coords is None else np.asarray(coords)[q_nodes], b, max_band)
    if inner is None:
        return None
    blk_q, y, bn = inner
    p = ps.size
    Z = y[:, :p]
    S = N[ps][:, ps].toarray() - NQP.T @ Z
    try:
        Sinv = sla.cho_solve(sla.cho_factor(0.5 * (S + S.T)), np.eye(p))
    except np.linalg.LinAlgError as exc:
        raise DegenerateGeometryError('the matrix is not positive definite') from exc
    ZS = Z @ Sinv
    nq, npn = q_nodes.size, p_nodes.size
    ZS4 = ZS.reshape(nq, d, npn, d)
    blocks = np.zeros((pa.size, d, d))
    la, lc = local[pa], local[pc]
    # Sigma_QQ = N_QQ^-1 + Z S^-1 Z', Sigma_QP = -Z S^-1, Sigma_PP = S^-1
    ZSq = ZS.reshape(nq, d, p)
    Zq = Z.reshape(nq, d, p)
    blocks[both_q] = blk_q + ZSq[la[both_q]] @ np.swapaxes(Zq[lc[both_q]], 1, 2)
    qp = ~border[pa] & border[pc]
    blocks[qp] = -ZS4[la[qp], :, lc[qp], :]
    pq = border[pa] & ~border[pc]
    blocks[pq] = -np.swapaxes(ZS4[lc[pq], :, la[pq], :], 1, 2)
    pp = border[pa] & border[pc]
    blocks[pp] = Sinv.reshape(npn, d, npn, d)[la[pp], :, lc[pp], :]
    x = None
    if r is not None:
        yQ = y[:, p:]
        xP = Sinv @ (r[ps] - NQP.T @ yQ)
        xfull = np.empty_like(r)
        xfull[qs] = yQ - Z @ xP
        xfull[ps] = xP
        x = xfull.reshape(np.shape(rhs))
    return blocks, x, bn


def _banded_pairs(N: sp.spmatrix, d: int, pa: IntArray, pc: IntArray,
                  coords: FloatArray | None, rhs: FloatArray | None,
                  max_band: int | None = None
                  ) -> tuple[FloatArray, FloatArray | None, int] | None:
    """Blocks ``Sigma_{pa_k, pc_k}`` of ``N^-1`` and ``N^-1 rhs`` by the block-tridiagonal
    selected inversion of :func:`banded_selection` (no border), and the block size (nodes);
    ``None`` if a block would exceed ``max_band`` scalars."""
    N = sp.coo_matrix(N)
    u = N.shape[0] // d
    rn, cn = N.row // d, N.col // d
    G = sp.csr_matrix((np.ones(rn.size), (rn, cn)), shape=(u, u))
    best = None
    for order in _band_orderings(G, coords):
        pos = np.empty(u, dtype=np.int64)
        pos[order] = np.arange(u)
        reach = max(int(np.abs(pos[rn] - pos[cn]).max(initial=0)),
                    int(np.abs(pos[pa] - pos[pc]).max(initial=0)))
        if best is None or reach < best[0]:
            best = (reach, order, pos)
    reach, order, pos = best
    bn = min(reach + 1, max(u, 1))
    b = bn * d
    if max_band is not None and b > max_band:
        return None
    nb = -(-u // bn)
    # scalar position of each entry of N; diagonal and sub-diagonal blocks, identity padding
    pr = pos[rn] * d + N.row % d
    pcs = pos[cn] * d + N.col % d
    kr, kc = pr // b, pcs // b
    same, low = kr == kc, kr == kc + 1
    A = np.bincount((kr[same] * b + pr[same] % b) * b + pcs[same] % b, weights=N.data[same],
                    minlength=nb * b * b).reshape(nb, b, b)
    Lsub = np.bincount((kc[low] * b + pr[low] % b) * b + pcs[low] % b, weights=N.data[low],
                       minlength=max(nb - 1, 0) * b * b).reshape(max(nb - 1, 0), b, b)
    pad = np.arange(u * d, nb * b)
    A[pad // b, pad % b, pad % b] = 1.0
    Dinv = np.empty_like(A)
    for k in range(nb):
        if k:
            A[k] -= Lsub[k - 1] @ Lsub[k - 1].T
        try:
            D = np.linalg.cholesky(A[k])
        except np.linalg.LinAlgError as exc:
            raise DegenerateGeometryError('the matrix is not positive definite (the absorbed '
                                          'terms leave a direction undetermined)') from exc
        Dinv[k] = sla.solve_triangular(D, np.eye(b), lower=True)
        if k < nb - 1:
            Lsub[k] = Lsub[k] @ Dinv[k].T
    x = None
    if rhs is not None:
        r = np.asarray(rhs, dtype=float)
        perm = (order[:, None] * d + np.arange(d)).ravel()
        y = np.zeros((nb * b,) + r.shape[1:])
        y[:u * d] = r[perm]
        y = y.reshape((nb, b) + r.shape[1:])
        for k in range(nb):
            if k:
                y[k] -= Lsub[k - 1] @ y[k - 1]
            y[k] = Dinv[k] @ y[k]
        for k in range(nb - 1, -1, -1):
            if k < nb - 1:
                y[k] -= Lsub[k].T @ y[k + 1]
            y[k] = Dinv[k].T @ y[k]
        x = np.empty_like(r)
        x[perm] = y.reshape((nb * b,) + r.shape[1:])[:u * d]
    Sdiag = np.empty_like(A)
    Ssub = np.empty_like(Lsub)
    for k in range(nb - 1, -1, -1):
        if k == nb - 1:
            Sdiag[k] = Dinv[k].T @ Dinv[k]
        else:
            Ssub[k] = -Sdiag[k + 1] @ Lsub[k] @ Dinv[k]
            Sdiag[k] = Dinv[k].T @ (Dinv[k] - Lsub[k].T @ Ssub[k])
    blk = np.zeros((pa.size, d, d))
    if pa.size:
        # Sigma_{a c}: in one diagonal block, or c's block just after a's (or before)
        a_s = pos[pa][:, None, None] * d + np.arange(d)[None, :, None]
        c_s = pos[pc][:, None, None] * d + np.arange(d)[None, None, :]
        ka, kc2 = a_s // b, c_s // b
        blk = np.where(ka == kc2, Sdiag[ka, a_s % b, c_s % b], 0.0)
        after = kc2 == ka + 1
        if after.any():
            blk = np.where(after, Ssub[np.minimum(ka, nb - 2), c_s % b, a_s % b], blk)
        before = ka == kc2 + 1
        if before.any():
            blk = np.where(before, Ssub[np.minimum(kc2, nb - 2), a_s % b, c_s % b], blk)
    return blk, x, bn


def _band_orderings(G: sp.csr_matrix, coords: FloatArray | None) -> list[IntArray]:
    """Candidate narrow-band node orderings: reverse Cuthill-McKee, principal axis."""
    from scipy.sparse.csgraph import reverse_cuthill_mckee

    u = G.shape[0]
    out = [np.asarray(reverse_cuthill_mckee(G, symmetric_mode=True), dtype=np.int64)]
    if coords is not None and len(coords) == u and u > 2:
        xyz = np.asarray(coords, dtype=float) - np.mean(coords, axis=0)
        axis = np.linalg.svd(xyz, full_matrices=False)[2][0]
        out.append(np.argsort(xyz @ axis, kind='stable').astype(np.int64))
    return out


def skeleton_layout(m: int, w: int, n_hubs: int) -> tuple[IntArray, IntArray]:
    """Positions (``0..m-1``, band order) of the ``h`` hub nodes of a
    :class:`CovarianceSkeleton` (evenly spread, ends included) and of the other nodes."""
    h = min(max(int(n_hubs), 0), m)
    hubs = np.unique(np.rint(np.linspace(0, m - 1, h)).astype(np.int64)) if h else \
        np.zeros(0, dtype=np.int64)
    rest = np.setdiff1d(np.arange(m, dtype=np.int64), hubs)
    return rest, hubs


@dataclass(frozen=True)
class CovarianceSkeleton:
    """The entries of a covariance ``Sigma`` over ``m`` nodes that its sparse completion keeps.

    The nodes are split (:func:`skeleton_layout`) into ``h`` hub nodes spread along the band
    order and the others; kept are the band of half-bandwidth ``w`` among the others, every
    covariance between a hub and any node, and the hubs' joint covariance. That pattern is
    chordal (a band plus a clique of hubs joined to everything), so its maximum-entropy
    completion has a closed form (:meth:`information`). The hubs carry the long-range
    (low-frequency) correlations that a band alone would lose: a band keeps each node's
    marginal but makes the mean of many nodes look better known than it is.

    Attributes
    ----------
    rest, hubs : positions (band order) of the other nodes and of the hubs.
    band : (m - h, w + 1, d, d) ``band[i, j] = Sigma_{r_i, r_{i+j}}`` over the others.
    cross : (h, m - h, d, d) ``Sigma_{hub a, r_i}``.
    hub_cov : (h d, h d) the hubs' joint covariance.
    """

    rest: IntArray
    hubs: IntArray
    band: FloatArray
    cross: FloatArray
    hub_cov: FloatArray

    @staticmethod
    def of_dense(Sigma: FloatArray, d: int, w: int, n_hubs: int) -> CovarianceSkeleton:
        """The skeleton of a dense ``(d m, d m)`` covariance."""
        m = Sigma.shape[0] // d
        rest, hubs = skeleton_layout(m, w, n_hubs)
        S4 = Sigma.reshape(m, d, m, d)
        rs = (rest[:, None] * d + np.arange(d)).ravel()
        band = dense_band(Sigma[np.ix_(rs, rs)], d, w)
        cross = S4[hubs[:, None], :, rest[None, :], :]  # (h, r, d, d)
        hs = (hubs[:, None] * d + np.arange(d)).ravel()
        return CovarianceSkeleton(rest, hubs, band, cross, Sigma[np.ix_(hs, hs)])

    def information(self) -> sp.bsr_matrix:
        """Information ``K`` of the maximum-entropy Gaussian with this skeleton (Dempster's
        covariance selection), in the original node order (``d x d`` blocks, both triangles).

        For the chordal pattern with cliques ``C_k = hubs + {r_k, ..., r_{k+w}}`` and
        separators ``C_k`` minus ``r_k``::

            K = sum_k pad(Sigma_{C_k C_k}^-1) - sum_k pad(Sigma_{sep_k sep_k}^-1)

        ``K`` is zero outside the pattern, positive definite when every clique's covariance is,
        and ``K^-1`` equals ``Sigma`` on the pattern (every node's marginal among it); with
        ``w >= m - h - 1`` it is the exact ``Sigma^-1``.

        Raises
        ------
        DegenerateGeometryError
            A clique's covariance is not positive definite.
        """
        return _completion(self.band, self.cross, self.hub_cov, self.rest, self.hubs)


def band_information(band: FloatArray) -> sp.bsr_matrix:
    """:meth:`CovarianceSkeleton.information` of a band alone (no hubs): ``band`` (m, w + 1,
    d, d), ``band[i, j] = Sigma_{i, i+j}``."""
    m, _, d, _ = band.shape
    return _completion(band, np.zeros((0, m, d, d)), np.zeros((0, 0)),
                       np.arange(m, dtype=np.int64), np.zeros(0, dtype=np.int64))


def _completion(band: FloatArray, cross: FloatArray, hub_cov: FloatArray, rest: IntArray,
                hubs: IntArray) -> sp.bsr_matrix:
    """Maximum-entropy completion with hubs, as the hubs' Gaussian and the others given them:
    with ``A = Sigma_HH``, ``X = Sigma_RH``, ``B = X A^-1`` and ``C`` the conditional covariance
    ``Sigma_RR - B X'`` (needed on the band only), ``K_RR`` is the band completion of ``C``,
    ``K_RH = -K_RR B`` and ``K_HH = A^-1 + B' K_RR B`` (equal to the clique formula of
    :meth:`CovarianceSkeleton.information`; tested against it)."""
    r, w1, d, _ = band.shape
    h = hubs.size
    if h:
        X = cross.transpose(1, 3, 0, 2).reshape(r * d, h * d)  # Sigma_{rest, hubs}
        Ainv = _spd_inverse(hub_cov[None])[0]
        B = X @ Ainv
        B3, X3 = B.reshape(r, d, h * d), X.reshape(r, d, h * d)
        cond = band.copy()
        for o in range(min(w1, r)):  # band offset o: (B X')_{a, a+o}, by views (no gathers)
            cond[:r - o, o] -= B3[:r - o] @ np.swapaxes(X3[o:], 1, 2)
    else:
        cond = band
    Kband = _band_completion(cond) if r else np.zeros((0, w1, d, d))
    w = Kband.shape[1] - 1
    lay = _completion_layout(rest, hubs, w)
    bblk = Kband.reshape(r * (w + 1), d, d)[lay.keep]
    data = [bblk, np.swapaxes(bblk[lay.off], 1, 2)]
    if h:
        # K_RH = -K_RR B, band by band: (K_RR B)_a = sum_b K_ab B_b over |a - b| <= w
        Krh3 = np.zeros((r, d, h * d))
        for o in range(w + 1):
            Kb = Kband[:r - o, o]  # K_{a, a+o}
            Krh3[:r - o] -= Kb @ B3[o:]
            if o:
                Krh3[o:] -= np.swapaxes(Kb, 1, 2) @ B3[:r - o]
        Krh = Krh3.reshape(r * d, h * d)
        Khh = Ainv - B.T @ Krh
        Khh = 0.5 * (Khh + Khh.T)
        rh = Krh.reshape(r, d, h, d).transpose(0, 2, 1, 3)  # (r, h, d, d): block (rest, hub)
        rhb = rh.reshape(r * h, d, d)
        data += [rhb, np.swapaxes(rhb, 1, 2),
                 Khh.reshape(h, d, h, d).transpose(0, 2, 1, 3).reshape(h * h, d, d)]
    m = r + h
    return sp.bsr_matrix((np.concatenate(data)[lay.order], lay.indices.copy(),
                          lay.indptr.copy()), shape=(m * d, m * d))


@dataclass(frozen=True)
class _CompletionLayout:
    """Where the blocks of :func:`_completion`'s information go, by the skeleton alone: ``keep``
    (of the ``r (w + 1)`` band slots those inside the band), ``off`` (of those, the
    off-diagonal ones, stored twice), and the BSR layout of the blocks in the order they are
    listed (band, its transposes, rest-hub, hub-rest, hub-hub): ``order``, ``indices``,
    ``indptr``."""

    keep: np.ndarray
    off: np.ndarray
    order: IntArray
    indices: IntArray
    indptr: IntArray


def band_pairs(r: int, w: int) -> tuple[IntArray, IntArray, np.ndarray]:
    """The block pairs ``(i, j)``, ``i <= j <= i + w``, ``j < r``, of a band of half-width ``w``
    over ``r`` nodes, row by row, and which of the ``r (w + 1)`` slots ``[i, j - i]`` of a
    ``(r, w + 1, ...)`` band array they are (the slots past the last node are not)."""
    i = np.repeat(np.arange(r), w + 1)
    j = i + np.tile(np.arange(w + 1), r)
    keep = j < r
    return i[keep], j[keep], keep


#: Layouts of :func:`_completion` by the skeleton (one per prior shape; the latest few).
_COMPLETION_LAYOUTS: OrderedDict[bytes, _CompletionLayout] = OrderedDict()


def _completion_layout(rest: IntArray, hubs: IntArray, w: int) -> _CompletionLayout:
    """The :class:`_CompletionLayout` of a skeleton (kept: a freeze builds one prior of the
    same shape per track)."""
    key = _blake2b(np.int64(w).tobytes() + np.int64(rest.size).tobytes() + rest.tobytes()
                   + hubs.tobytes(), digest_size=16).digest()
    return _kept(_COMPLETION_LAYOUTS, _MAX_PATTERNS, key,
                 lambda: _build_completion_layout(rest, hubs, w))


def _build_completion_layout(rest: IntArray, hubs: IntArray, w: int) -> _CompletionLayout:
    """:func:`_completion_layout` computed."""
    r, h = rest.size, hubs.size
    i, j, keep = band_pairs(r, w)
    off = i != j
    rows = [rest[i], rest[j[off]]]
    cols = [rest[j], rest[i[off]]]
    if h:
        ri, ha = np.repeat(np.arange(r), h), np.tile(np.arange(h), r)
        rows += [rest[ri], hubs[ha], np.repeat(hubs, h)]
        cols += [hubs[ha], rest[ri], np.tile(hubs, h)]
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    order = np.lexsort((cols, rows))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=r + h))])
    return _CompletionLayout(keep, off, order, cols[order], indptr)


def _spd_inverse(S: FloatArray) -> FloatArray:
    """Inverses of a stack of (symmetrised) SPD clique covariances (:func:`spd_inverse`)."""
    return spd_inverse(0.5 * (S + np.swapaxes(S, 1, 2)),
                       'a clique of the covariance skeleton is not positive definite')


def spd_inverse(M: FloatArray, error: str) -> FloatArray:
    """Inverses of a stack ``(..., k, k)`` of symmetric positive definite matrices by Cholesky
    (the lower triangles are read); raises :class:`DegenerateGeometryError` with ``error`` if
    one is not positive definite."""
    try:
        L = np.linalg.cholesky(M)
    except np.linalg.LinAlgError as exc:
        raise DegenerateGeometryError(error) from exc
    Linv = np.linalg.inv(L)
    return np.swapaxes(Linv, -1, -2) @ Linv


def _separator_solves_scipy(ext: FloatArray, cross: FloatArray, r: int, w: int, d: int,
                            Bt: FloatArray) -> int:
    """:func:`ga_ros.core.lapack.separator_solves` without numba: ``Bt[k] = Sigma_FF^-1
    Sigma_Fk`` (``cross[k]`` is ``Sigma_Fk``) by SciPy's ``dpotrf``/``dpotrs``, the separators
    gathered from the band first. Returns 0, or ``k + 1`` if separator ``k`` is not positive
    definite."""
    sep = np.empty((r, w, d, w, d))
    for a in range(w):  # row a of F_i is node i + 1 + a
        sep[:, a, :, a:, :] = ext[1 + a:1 + a + r, :w - a].transpose(0, 2, 1, 3)
        sep[:, a + 1:, :, a, :] = np.swapaxes(ext[1 + a:1 + a + r, 1:w - a], -1, -2)
    sep = sep.reshape(r, w * d, w * d)
    potrf, potrs = sla.lapack.dpotrf, sla.lapack.dpotrs
    for k in range(r):
        c, info = potrf(sep[k].T, lower=1, clean=0)  # symmetric: F-ordered view of sep[k]
        if info:
            return k + 1
        Bt[k] = potrs(c, cross[k], lower=1)[0]
    return 0


def _band_completion(band: FloatArray) -> FloatArray:
    """``K`` on the band (``(r, w + 1, d, d)``, ``K[i, j] = K_{i, i+j}``) of the maximum-entropy
    completion of a covariance band (cliques ``C_k = {k..k+w}``, separators ``{k+1..k+w}``).

    The completion of a band is a Markov chain of order ``w`` along the nodes: node ``i`` given
    the ``w`` nodes after it (``F_i``) is ``x_i = B_i x_F + e_i``, ``B_i = Sigma_iF Sigma_FF^-1``,
    ``D_i = Sigma_ii - B_i Sigma_Fi``, so ``K = sum_i G_i' D_i^-1 G_i`` with ``G_i = [I, -B_i]``
    over ``{i} + F_i``. Equal to the clique formula of
    :meth:`CovarianceSkeleton.information` (one solve with each separator instead of the
    inverses of every clique and separator; batched over the nodes, the last ones padded with
    identity blocks beyond the end).
    """
    r, w1, d, _ = band.shape
    w = min(w1 - 1, r - 1)
    if w <= 0:  # single-node cliques
        return _spd_inverse(band[:, 0])[:, None]
    # the band and w padding nodes after the end (identity covariance, uncorrelated)
    ext = np.zeros((r + w, w + 1, d, d))
    ext[:r] = band[:, :w + 1]
    for j in range(1, w + 1):
        ext[r - j:r, j] = 0.0  # beyond the last node
    ext[r:, 0] = np.eye(d)
    # Sigma_Fi (w d x d) of every node; B_i' = Sigma_FF^-1 Sigma_Fi, one Cholesky factorisation
    # of each separator Sigma_FF (w d x w d) (faster than a batch LU)
    cross = np.ascontiguousarray(np.swapaxes(ext[:r, 1:], -1, -2)).reshape(r, w * d, d)
    Bt = np.empty_like(cross)  # (r, w d, d)
    # compiled: the separators read from the band, LAPACK called directly
    status = lapack.separator_solves(ext, r, w, d, Bt)
    if status is None:  # the same with SciPy's LAPACK
        status = _separator_solves_scipy(ext, cross, r, w, d, Bt)
    if status:
        raise DegenerateGeometryError('a clique of the covariance skeleton is not positive '
                                      'definite')
    Dm = band[:, 0] - np.swapaxes(cross, 1, 2) @ Bt
    # every clique C_i = {i} + F_i is positive definite iff every D_i is (one Cholesky each
    # below, no separate one of the separators): C_i is iff F_i and D_i are, and F_i is a
    # principal block of C_{i+1} (the last ones: identity padding), so from the end back
    Dinv = _spd_inverse(Dm)  # (r, d, d)
    G = np.concatenate([np.broadcast_to(np.eye(d), (r, d, d)),
                        -np.swapaxes(Bt, 1, 2)], axis=2)  # (r, d, (w + 1) d)
    DG = Dinv @ G
    # clique i adds its block (p, q >= p), G_p' D_i^-1 G_q, to K_{i+p, i+q}; accumulated
    # transposed (K_{i+q, i+p} = (D_i^-1 G_q)' G_p: the products' blocks stack as stored)
    KbandT = np.zeros((r + w, w + 1, d, d))
    for p in range(w + 1):
        Kp = np.swapaxes(DG[:, :, p * d:], 1, 2) @ G[:, :, p * d:(p + 1) * d]  # (r, (w+1-p) d, d)
        KbandT[p:p + r, :w + 1 - p] += Kp.reshape(r, w + 1 - p, d, d)
    return np.swapaxes(KbandT[:r], 2, 3)


def dense_band(Sigma: FloatArray, d: int, w: int) -> FloatArray:
    """The band ``(m, w + 1, d, d)``, ``band[i, j] = Sigma_{i, i+j}``, of a dense
    ``(d m, d m)`` covariance (zero where ``i + j >= m``), as :class:`BandSelection` holds it."""
    m = Sigma.shape[0] // d
    S4 = Sigma.reshape(m, d, m, d)
    i = np.repeat(np.arange(m), w + 1)
    j = i + np.tile(np.arange(w + 1), m)
    ok = j < m
    band = np.zeros((m, w + 1, d, d))
    band[i[ok], (j - i)[ok]] = S4[i[ok], :, j[ok], :]
    return band
