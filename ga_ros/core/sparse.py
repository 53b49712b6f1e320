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

import hashlib
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import DegenerateGeometryError
from ga_ros.runtime import openblas_coretype

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
        self.key = hashlib.blake2b(np.ascontiguousarray(ukey).tobytes()
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
        # position of (unique block u, row b, col a) in the CSC data
        ra = rank[:, None, None]
        bb = a[None, :, None]
        aa = a[None, None, :]
        colstart = self.indptr[:-1].reshape(n, d)[ucol][:, None, :]  # (u, 1, a)
        off = np.where(ra == 0, bb - aa, (d - aa) + (ra - 1) * d + bb)
        valid = (ra > 0) | (bb >= aa)
        pos_u = np.where(valid, colstart + off, -1)  # (u, d, d)
        rows_u = urow[:, None, None] * d + bb + 0 * aa
        self.indices = np.empty(self.nnz, dtype=np.int64)
        self.indices[pos_u[valid]] = np.broadcast_to(rows_u, pos_u.shape)[valid]
        pos = pos_u[inv].reshape(-1)
        self._pos_valid = pos >= 0
        # int32 when it fits: half the pattern's largest array (~300 MB at 100,000 poses)
        self._pos = pos[self._pos_valid].astype(np.int32 if self.nnz < 2**31 else np.int64)
        self._valid_before: IntArray | None = None  # built by assemble_at on first use

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

    def assemble(self, blocks: FloatArray) -> FloatArray:
        """Sum blocks ``(k, d, d)`` (block row, col) into the lower-triangle CSC values.

        More than :data:`_ASSEMBLY_CHUNK` blocks go in chunks: the temporaries (two copies of
        the blocks in one pass, ~1.4 GB for a survey of 100,000 poses) stay ~150 MB."""
        if blocks.shape[0] <= _ASSEMBLY_CHUNK:
            vals = blocks[self._keep_blk].reshape(-1)[self._pos_valid]
            return np.bincount(self._pos, weights=vals, minlength=self.nnz)
        keep, d2, done = np.nonzero(self._keep_blk)[0], self.d * self.d, 0
        out = np.zeros(self.nnz)
        for a in range(0, keep.size, _ASSEMBLY_CHUNK):
            valid = self._pos_valid[a * d2:(a + _ASSEMBLY_CHUNK) * d2]
            vals = blocks[keep[a:a + _ASSEMBLY_CHUNK]].reshape(-1)[valid]
            out += np.bincount(self._pos[done:done + vals.size], weights=vals,
                               minlength=self.nnz)
            done += vals.size
        return out

    def assemble_at(self, blocks: FloatArray, index: IntArray, out: FloatArray) -> None:
        """Add blocks ``(k, d, d)`` that stand at the positions ``index`` of the block list
        this pattern was built from into ``out`` (lower-triangle CSC values, in place): the
        assembly of a large system a part at a time (``assemble`` of the whole list equals the
        sum over disjoint parts)."""
        d2 = self.d * self.d
        if self._valid_before is None:
            per = self._pos_valid.reshape(-1, d2).sum(axis=1)
            self._valid_before = np.concatenate([[0], np.cumsum(per)])
            self._kept_rank = np.cumsum(self._keep_blk) - 1  # position among the kept blocks
        index = np.asarray(index, dtype=np.int64)
        keep = self._keep_blk[index]
        rank = self._kept_rank[index[keep]]
        valid = self._pos_valid.reshape(-1, d2)[rank]
        count = valid.sum(axis=1)
        first = np.repeat(self._valid_before[rank] - np.cumsum(count) + count, count)
        where = self._pos[first + np.arange(first.size)]
        out += np.bincount(where, weights=blocks[keep].reshape(-1, d2)[valid],
                           minlength=self.nnz)

    def matvec(self, data: FloatArray, x: FloatArray) -> FloatArray:
        """``N x`` for the symmetric matrix whose lower triangle is ``data``."""
        L = self.lower_csc(data)
        diag = data[self.indptr[:-1]]  # the diagonal entry heads each column
        return L @ x + L.T @ x - diag * x

    def lower_csc(self, data: FloatArray) -> sp.csc_matrix:
        return sp.csc_matrix((data, self.indices, self.indptr), shape=(self.size, self.size))

    def full_csc(self, data: FloatArray) -> sp.csc_matrix:
        """The symmetric matrix (both triangles)."""
        L = self.lower_csc(data)
        return (L + sp.tril(L, -1).T).tocsc()


class SparseCholesky:
    """Factor of a symmetric positive definite matrix given by its lower triangle (CSC).

    Reuse one instance across matrices with the same pattern: :meth:`refactor` keeps the ordering.
    Raises :class:`DegenerateGeometryError` when the matrix is not positive definite (e.g. a datum
    is missing or part of the network is unconstrained).
    """

    def __init__(self, pattern: BlockPattern, data: FloatArray,
                 trailing: IntArray | None = None) -> None:
        self.pattern = pattern
        self.n = pattern.size
        self._trailing = None if trailing is None else np.asarray(trailing, dtype=np.int64)
        self._symbolic = None
        self._A = None
        self._F = None
        self._lu = None
        self.refactor(data)

    def refactor(self, data: FloatArray) -> None:
        """Numeric factorisation of new values on the same pattern (ordering reused)."""
        if not np.isfinite(data).all():
            raise DegenerateGeometryError('normal matrix has NaN or inf entries')
        p = self.pattern
        self._data = data
        if _cholmod is not None:
            values = cvxopt.matrix(np.ascontiguousarray(data, dtype=float))
            if self._A is None:
                self._A = _cvxopt_pattern(p)
            self._A.V = values  # the matrix may be shared with factors of the same pattern
            if self._symbolic is None:
                self._symbolic = self._analyse()
            try:
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

    def _analyse(self):
        """CHOLMOD's symbolic analysis with the block ordering (trailing blocks last, kept in
        place: no postordering then)."""
        p = self.pattern
        if self._trailing is None:
            perm = block_ordering(p)
        else:
            perm = _trailing_ordering(p, self._trailing)
        pvec = cvxopt.matrix(np.ascontiguousarray(perm, dtype=np.int64), tc='i')
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
        self._symbolic = None  # analysed again if the factor is used again
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


def _kept(cache: OrderedDict, limit: int, key: bytes, build):
    """``cache[key]``, built by ``build()`` on a miss; the ``limit`` most recent are kept."""
    value = cache.get(key)
    if value is None:
        value = cache[key] = build()
        while len(cache) > limit:
            cache.popitem(last=False)
    else:
        cache.move_to_end(key)
    return value


def _cvxopt_pattern(pattern: BlockPattern):
    """CHOLMOD's input matrix for a pattern (values are set before each factorisation). Building
    it sorts every entry again (~0.1 s for a window), so it is kept per pattern too."""
    return _kept(_MATRICES, _MAX_MATRICES, pattern.key, lambda: cvxopt.spmatrix(
        cvxopt.matrix(np.zeros(pattern.nnz)), cvxopt.matrix(pattern.indices.astype(np.int64)),
        cvxopt.matrix(_expand_cols(pattern.indptr)), (pattern.size, pattern.size)))


def block_ordering(pattern: BlockPattern) -> IntArray:
    """Fill-reducing scalar permutation of a block pattern: AMD (or, on large graphs, nested
    dissection: :mod:`ga_ros.core.ordering`) of its block graph, each block's ``d`` unknowns kept
    together. Kept per pattern (:data:`_ORDERINGS`)."""
    from ga_ros.core.ordering import best_block_order

    amd = lambda: _block_amd(pattern, np.ones(pattern.n_blocks, dtype=bool))  # noqa: E731
    return _kept(_ORDERINGS, _MAX_ORDERINGS, pattern.key, lambda: _expand(
        best_block_order(pattern.n_blocks, *pattern.block_lower, amd()), pattern.d))


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
