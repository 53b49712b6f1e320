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

try:  # CHOLMOD, bundled in the cvxopt wheel
    import cvxopt
    from cvxopt import cholmod as _cholmod

    _cholmod.options['supernodal'] = 2
    _cholmod.options['postorder'] = True
except ImportError:  # pragma: no cover - the pinned requirements include cvxopt
    cvxopt = None
    _cholmod = None


class BlockPattern:
    """Where each entry of ``n_blocks`` dense ``d x d`` blocks lands in a sparse lower triangle.

    Parameters
    ----------
    block_rows, block_cols : (k,) block coordinates (column index of the unknown block; -1 for a
        fixed node, whose entries are dropped).
    d : block size.
    n : number of unknown blocks.
    """

    def __init__(self, block_rows: IntArray, block_cols: IntArray, d: int, n: int) -> None:
        self.d = d
        self.size = d * n
        br = np.asarray(block_rows, dtype=np.int64)
        bc = np.asarray(block_cols, dtype=np.int64)
        a = np.arange(d)
        rows = (br[:, None, None] * d + a[None, :, None]).repeat(d, axis=2)
        cols = (bc[:, None, None] * d + a[None, None, :]).repeat(d, axis=1)
        rows = rows.reshape(-1)
        cols = cols.reshape(-1)
        keep = (np.repeat(br, d * d) >= 0) & (np.repeat(bc, d * d) >= 0) & (rows >= cols)
        self._keep = keep
        lin = rows[keep] * self.size + cols[keep]
        uniq, self._inv = np.unique(lin, return_inverse=True)
        self.rows = uniq // self.size
        self.cols = uniq % self.size
        self.nnz = uniq.size
        # CSC ordering of the unique entries (sorted by column, then row)
        order = np.lexsort((self.rows, self.cols))
        self._csc_order = order
        self.indices = self.rows[order]
        counts = np.bincount(self.cols, minlength=self.size)
        self.indptr = np.concatenate([[0], np.cumsum(counts)])

    def assemble(self, blocks: FloatArray) -> FloatArray:
        """Sum blocks ``(k, d, d)`` into the lower-triangle values, in CSC order."""
        vals = blocks.reshape(-1)[self._keep]
        data = np.bincount(self._inv, weights=vals, minlength=self.nnz)
        return data[self._csc_order]

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
