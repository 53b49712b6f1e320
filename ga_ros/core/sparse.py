"""Sparse assembly and Cholesky factorisation of normal matrices.

The normal matrix ``N = A' M^-1 A`` has one ``d x d`` block per node and one off-diagonal block
pair per connected node pair, so it has the sparsity of the connection graph. It is assembled from
per-connection blocks with a pattern computed once (:class:`BlockPattern`) and factored with
CHOLMOD (SuiteSparse, through cvxopt), reusing the symbolic analysis (fill-reducing ordering)
across iterations. Without cvxopt, SciPy's SuperLU is used.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import DegenerateGeometryError
from ga_ros.runtime import openblas_coretype

try:  # CHOLMOD, bundled in the cvxopt wheel
    with openblas_coretype():
        import cvxopt
        from cvxopt import cholmod as _cholmod

    _cholmod.options['supernodal'] = 2
    _cholmod.options['postorder'] = True
except ImportError:  # pragma: no cover - the pinned requirements include cvxopt
    cvxopt = None
    _cholmod = None


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
        nblk_col = np.bincount(ucol, minlength=n)
        if n and not np.array_equal(np.unique(ucol[urow == ucol]), np.arange(n)):
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
        self._pos = pos[self._pos_valid]

    def assemble(self, blocks: FloatArray) -> FloatArray:
        """Sum blocks ``(k, d, d)`` (block row, col) into the lower-triangle CSC values."""
        vals = blocks[self._keep_blk].reshape(-1)[self._pos_valid]
        return np.bincount(self._pos, weights=vals, minlength=self.nnz)

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

    def __init__(self, pattern: BlockPattern, data: FloatArray) -> None:
        self.pattern = pattern
        self.n = pattern.size
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
        if _cholmod is not None:
            values = cvxopt.matrix(np.ascontiguousarray(data, dtype=float))
            if self._A is None:
                self._A = cvxopt.spmatrix(values, cvxopt.matrix(p.indices.astype(np.int64)),
                                          cvxopt.matrix(_expand_cols(p.indptr)),
                                          (self.n, self.n))
            else:
                self._A.V = values
            if self._symbolic is None:
                self._symbolic = _cholmod.symbolic(self._A, uplo='L')
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

    def solve(self, b: FloatArray) -> FloatArray:
        """Solve ``N x = b`` for ``b`` of shape ``(n,)`` or ``(n, k)``."""
        b = np.asarray(b, dtype=float)
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


def _expand_cols(indptr: IntArray) -> IntArray:
    return np.repeat(np.arange(indptr.size - 1, dtype=np.int64), np.diff(indptr))


def block_diagonal(blocks: FloatArray) -> sp.csr_matrix:
    """Sparse block-diagonal matrix from ``(k, d, d)`` blocks."""
    return sp.block_diag(list(blocks), format='csr') if len(blocks) else sp.csr_matrix((0, 0))
