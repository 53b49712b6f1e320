"""Marginal covariance blocks of many nodes: selected inversion of a banded normal matrix.

With a bandwidth-reducing node ordering (reverse Cuthill-McKee), a survey's normal matrix is
banded with half-bandwidth ``b``; cut into ``b x b`` blocks it is block tridiagonal. Its block
Cholesky factor ``N = L L'`` (diagonal blocks ``D_k``, sub-diagonal blocks ``C_k``) and the
backward recursion of Takahashi's equations (``L' Sigma = L^-1``, upper part zero) give every
diagonal block of ``Sigma = N^-1``::

    Sigma_KK = D_K^-T D_K^-1
    Sigma_kk = D_k^-T (I + C_k' Sigma_{k+1,k+1} C_k) D_k^-1

in ``O(n b^2)`` operations, without forming any column of ``N^-1`` (the RTS smoother in
information form). For a window of five lawnmower tracks (6,000 unknowns) this is a few tens of
milliseconds, versus seconds for 1,200 sparse solves.
"""

from __future__ import annotations

import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
from scipy.sparse.csgraph import reverse_cuthill_mckee

from ga_ros.arrays import FloatArray
from ga_ros.errors import DegenerateGeometryError


def banded_marginal_blocks(N: sp.spmatrix, d: int, max_band: int = 3000,
                           wanted: np.ndarray | None = None,
                           coords: np.ndarray | None = None) -> FloatArray | None:
    """Diagonal ``d x d`` blocks of ``N^-1`` for a symmetric positive definite ``N``.

    Parameters
    ----------
    N : (d u, d u) sparse symmetric matrix, ``u`` node blocks of size ``d``.
    d : block size (parameters per node).
    max_band : give up (return ``None``) if the reordered half-bandwidth exceeds this many
        scalars; the caller then uses sparse solves.
    wanted : optional (k,) node blocks that are needed; the backward recursion stops once it
        has passed them (blocks of other nodes are left as NaN). Default: all nodes.
    coords : optional (u, 3) node positions. Besides reverse Cuthill-McKee, the ordering along
        their principal axis is tried (for a survey strip it gives a narrower band); the
        ordering with the smaller band is used.

    Returns
    -------
    (u, d, d) covariance blocks in the original node order, or ``None`` (band too wide).
    """
    N = sp.csr_matrix(N)
    n = N.shape[0]
    u = n // d
    coo = N.tocoo()
    G = sp.coo_matrix((np.ones(coo.nnz), (coo.row // d, coo.col // d)), shape=(u, u)).tocsr()
    rows_n, cols_n = coo.row // d, coo.col // d
    candidates = [reverse_cuthill_mckee(G, symmetric_mode=True)]
    if coords is not None and len(coords) == u and u > 2:
        xyz = np.asarray(coords, dtype=float) - np.mean(coords, axis=0)
        axis = np.linalg.svd(xyz, full_matrices=False)[2][0]
        candidates.append(np.argsort(xyz @ axis, kind='stable'))

    def node_band(order: np.ndarray) -> int:
        pos = np.empty(u, dtype=np.int64)
        pos[order] = np.arange(u)
        return int(np.abs(pos[rows_n] - pos[cols_n]).max()) if coo.nnz else 0

    order = min(candidates, key=node_band)
    if wanted is None or len(wanted) == 0:
        first_needed = 0
    else:
        pos = np.empty(u, dtype=np.int64)
        pos[order] = np.arange(u)
        first_needed = int(pos[np.asarray(wanted, dtype=np.int64)].min())
    perm = (order[:, None] * d + np.arange(d)[None, :]).ravel()
    inv = np.empty(n, dtype=np.int64)
    inv[perm] = np.arange(n)
    r, c = inv[coo.row], inv[coo.col]
    band = int(np.abs(r - c).max()) if coo.nnz else 0
    b = max(d, -(-(band + 1) // d) * d)
    if b > max_band:
        return None
    nb = -(-n // b)
    size = nb * b
    # dense diagonal and sub-diagonal blocks of the permuted matrix (padded with identity)
    br, bc = r // b, c // b
    diag = br == bc
    lin = (br[diag] * b + r[diag] % b) * b + c[diag] % b
    A = np.bincount(lin, weights=coo.data[diag], minlength=nb * b * b).reshape(nb, b, b)
    low = br == bc + 1
    lin = (bc[low] * b + r[low] % b) * b + c[low] % b
    C = np.bincount(lin, weights=coo.data[low],
                    minlength=max(nb - 1, 0) * b * b).reshape(max(nb - 1, 0), b, b)
    pad = np.arange(n, size)
    A[pad // b, pad % b, pad % b] = 1.0
    # block Cholesky: D_k D_k' = A_k - C_{k-1} C_{k-1}'; C_k <- C_k D_k^-T
    Dinv = np.empty_like(A)
    eye = np.eye(b)
    for k in range(nb):
        if k:
            A[k] -= C[k - 1] @ C[k - 1].T
        try:
            D = np.linalg.cholesky(A[k])
        except np.linalg.LinAlgError as exc:
            raise DegenerateGeometryError('normal matrix is not positive definite') from exc
        Dinv[k] = sla.solve_triangular(D, eye, lower=True)
        if k < nb - 1:
            C[k] = C[k] @ Dinv[k].T
    # backward recursion over the diagonal blocks of Sigma
    out = np.full((u, d, d), np.nan)
    Sigma_next = None
    stop = (first_needed * d) // b
    for k in range(nb - 1, stop - 1, -1):
        if Sigma_next is None:
            S = Dinv[k].T @ Dinv[k]
        else:
            S = Dinv[k].T @ (eye + C[k].T @ Sigma_next @ C[k]) @ Dinv[k]
        Sigma_next = S
        lo, hi = k * b, min((k + 1) * b, n)
        for q in range(lo // d, hi // d):
            s = q * d - lo
            out[order[q]] = S[s:s + d, s:s + d]
    return 0.5 * (out + np.swapaxes(out, 1, 2))
