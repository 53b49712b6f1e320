"""Blocks of the cofactor matrix ``Q_x = N^-1`` that quality control needs, and their
propagation to the connections (``A_i Q_x A_i'``), from sparse solves with the Cholesky factor of
``N``; never a dense inverse."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import scipy.sparse as sp

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior, normal_matrix_at
from ga_ros.errors import SolverError

#: Node columns of ``N^-1`` solved for at a time (bounds the memory to ``n x (chunk d)``).
_CHUNK = 128


def normal_matrix(network: ConnectionNetwork, T: FloatArray, model: str, fixed: IntArray,
                   free_ids: IntArray, priors: Sequence[GaussianPrior], As: FloatArray,
                   Ad: FloatArray, Linv: FloatArray, cs: IntArray, cd: IntArray, d: int
                   ) -> tuple[sp.spmatrix, sp.spmatrix | None]:
    """``N = A' M^-1 A`` with unit weights at the solution, plus the priors' part.

    Returns
    -------
    The whole normal matrix and the priors' part (``None`` without priors).
    """
    AsT, AdT = np.swapaxes(As, 1, 2), np.swapaxes(Ad, 1, 2)
    Minv = np.swapaxes(Linv, 1, 2) @ Linv
    N_all = _assemble([AsT @ Minv @ As, AsT @ Minv @ Ad, AdT @ Minv @ As, AdT @ Minv @ Ad],
                      [cs, cs, cd, cd], [cs, cd, cs, cd], d, free_ids.size)
    N_prior = None
    if priors:
        N_with, ids_all, _ = normal_matrix_at(network, T, model, fixed=fixed, priors=priors)
        N_conn, _, _ = normal_matrix_at(network, T, model, fixed=fixed)
        if not np.array_equal(ids_all, free_ids):
            raise SolverError('internal: unknown order of the normal matrix differs')
        N_prior = (N_with - N_conn).tocsr()
        N_prior.eliminate_zeros()
        N_all = (N_all + N_prior).tocsr()
    return N_all, N_prior


def sigma_blocks(N_all: sp.spmatrix, N_prior: sp.spmatrix | None, d: int, cs: IntArray,
                  cd: IntArray, ocs: IntArray, ocd: IntArray
                  ) -> tuple[FloatArray, sp.bsr_matrix | None]:
    """Blocks of ``Q_x = N^-1`` on the connected pairs, the outside pairs and the prior's
    pattern, in that order; also the prior's part as a block matrix (``None`` without)."""
    pr = [cs, cs, cd]
    pc = [cs, cd, cd]
    if ocs.size:
        pr += [ocs, ocs, ocd]
        pc += [ocs, ocd, ocd]
    bsr = None
    if N_prior is not None:
        bsr = sp.bsr_matrix(N_prior, blocksize=(d, d))
        prow = np.repeat(np.arange(bsr.shape[0] // d), np.diff(bsr.indptr))
        pr.append(prow)
        pc.append(bsr.indices.astype(np.int64))
    return inverse_blocks(N_all, d, np.concatenate(pr), np.concatenate(pc)), bsr


def propagate(A_src: FloatArray, A_dst: FloatArray, cs: IntArray, cd: IntArray,
               Sigma: FloatArray) -> FloatArray:
    """``A_i Q_x A_i'`` per connection from the blocks ``Sigma = [Q_ss; Q_sd; Q_dd]`` (3 m)
    (a fixed endpoint, column -1, contributes nothing)."""
    m = cs.size
    As = np.where((cs >= 0)[:, None, None], A_src, 0.0)
    Ad = np.where((cd >= 0)[:, None, None], A_dst, 0.0)
    AsT, AdT = np.swapaxes(As, 1, 2), np.swapaxes(Ad, 1, 2)
    G = As @ Sigma[:m] @ AsT + Ad @ Sigma[2 * m:3 * m] @ AdT
    cross = As @ Sigma[m:2 * m] @ AdT
    return G + cross + np.swapaxes(cross, 1, 2)


def _assemble(blocks: list[FloatArray], rows: list[IntArray], cols: list[IntArray], d: int,
              n: int) -> sp.csr_matrix:
    """Sparse ``(d n, d n)`` sum of ``d x d`` blocks at block coordinates (-1: dropped)."""
    blk = np.concatenate(blocks)
    br, bc = np.concatenate(rows), np.concatenate(cols)
    ok = (br >= 0) & (bc >= 0)
    a = np.arange(d)
    r = np.broadcast_to(br[ok, None, None] * d + a[None, :, None], (int(ok.sum()), d, d))
    c = np.broadcast_to(bc[ok, None, None] * d + a[None, None, :], (int(ok.sum()), d, d))
    return sp.coo_matrix((blk[ok].ravel(), (r.ravel(), c.ravel())),
                         shape=(d * n, d * n)).tocsr()


def inverse_blocks(N: sp.spmatrix, d: int, rows: IntArray, cols: IntArray,
                   selected: bool | None = None) -> FloatArray:
    """Blocks ``(rows[k], cols[k])`` of ``N^-1`` (``d x d`` node blocks; -1 gives a zero block).

    Pairs on the block pattern of ``N`` (a diagonal block, a connected node pair) come from
    selected inversion on the sparse Cholesky factor
    (:class:`~ga_ros.core.linalg.selinv.SelectedInverse`); any other pair (e.g. the ends of an
    excluded
    connection), or every pair with ``selected=False`` (the default without compiled kernels),
    from the node columns of ``N^-1`` solved for in chunks with the factor. No dense inverse is
    formed.
    """
    from ga_ros.core.linalg import selinv  # lazy: numba

    if selected is None:
        selected = selinv.COMPILED
    bsr = sp.bsr_matrix(sp.csr_matrix(N), blocksize=(d, d))
    bsr.sort_indices()
    n = bsr.shape[0] // d
    brow = np.repeat(np.arange(n), np.diff(bsr.indptr))
    pattern = BlockPattern(brow, bsr.indices.astype(np.int64), d, n)
    chol = SparseCholesky(pattern, pattern.assemble(bsr.data))
    out = np.zeros((rows.size, d, d))
    todo = np.nonzero((rows >= 0) & (cols >= 0))[0]
    if selected and todo.size:
        got = selinv.SelectedInverse(chol).blocks(rows[todo], cols[todo], off_pattern='nan')
        ok = np.isfinite(got).all(axis=(1, 2))
        out[todo[ok]] = got[ok]
        todo = todo[~ok]  # off the pattern: solved for below (the factor is computed again)
    needed = np.unique(cols[todo])
    for start in range(0, needed.size, _CHUNK):
        chunk = needed[start:start + _CHUNK]
        E = np.zeros((n * d, chunk.size * d))
        for k, c in enumerate(chunk):
            E[c * d:(c + 1) * d, k * d:(k + 1) * d] = np.eye(d)
        X = chol.solve(E).reshape(n, d, chunk.size, d)
        pos = np.full(n, -1, dtype=np.int64)
        pos[chunk] = np.arange(chunk.size)
        sel = todo[pos[cols[todo]] >= 0]
        out[sel] = X[rows[sel], :, pos[cols[sel]], :]
    return out
