"""Banded joint covariances: the block-tridiagonal selected inversion of a sparse normal matrix
(the band of the window's sparse joint priors, whose completion is in
:mod:`ga_ros.core.linalg.completion`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import DegenerateGeometryError
from ga_ros.runtime import lazy_import

sla = lazy_import('scipy.linalg')  # only some functions need them (start-up)
sp = lazy_import('scipy.sparse')


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
    reach, order, pos = _narrowest_ordering(G, coords, rn, cn, pa, pc)
    bn = min(reach + 1, max(u, 1))
    b = bn * d
    if max_band is not None and b > max_band:
        return None
    A, Lsub = _tridiagonal_blocks(N, d, pos, bn)
    Dinv = _block_cholesky(A, Lsub)
    x = None
    if rhs is not None:
        x = _block_solve(Dinv, Lsub, (order[:, None] * d + np.arange(d)).ravel(), rhs)
    Sdiag, Ssub = _block_takahashi(Dinv, Lsub)
    return _pair_blocks(Sdiag, Ssub, pos, pa, pc, d), x, bn


def _narrowest_ordering(G: sp.csr_matrix, coords: FloatArray | None, rn: IntArray,
                        cn: IntArray, pa: IntArray, pc: IntArray
                        ) -> tuple[int, IntArray, IntArray]:
    """The candidate node ordering (:func:`_band_orderings`) with the smallest reach: the
    largest distance in that order between the two nodes of an entry ``(rn, cn)`` of the
    matrix or of a wanted pair ``(pa, pc)``. Returns ``(reach, order, pos)``, ``pos`` the
    inverse permutation of ``order``."""
    u = G.shape[0]
    best = None
    for order in _band_orderings(G, coords):
        pos = np.empty(u, dtype=np.int64)
        pos[order] = np.arange(u)
        reach = max(int(np.abs(pos[rn] - pos[cn]).max(initial=0)),
                    int(np.abs(pos[pa] - pos[pc]).max(initial=0)))
        if best is None or reach < best[0]:
            best = (reach, order, pos)
    return best


def _tridiagonal_blocks(N: sp.coo_matrix, d: int, pos: IntArray, bn: int
                        ) -> tuple[FloatArray, FloatArray]:
    """``N`` with its node blocks moved to ``pos``, cut into ``(nb, b, b)`` diagonal blocks
    and ``(nb - 1, b, b)`` sub-diagonal blocks of ``bn`` nodes (``b = bn d`` scalars; every
    entry lies in one of them: ``bn`` exceeds the reordered half-bandwidth); the scalars past
    the last node are identity padding."""
    u = N.shape[0] // d
    b = bn * d
    nb = -(-u // bn)
    pr = pos[N.row // d] * d + N.row % d
    pcs = pos[N.col // d] * d + N.col % d
    kr, kc = pr // b, pcs // b
    same, low = kr == kc, kr == kc + 1
    A = np.bincount((kr[same] * b + pr[same] % b) * b + pcs[same] % b, weights=N.data[same],
                    minlength=nb * b * b).reshape(nb, b, b)
    Lsub = np.bincount((kc[low] * b + pr[low] % b) * b + pcs[low] % b, weights=N.data[low],
                       minlength=max(nb - 1, 0) * b * b).reshape(max(nb - 1, 0), b, b)
    pad = np.arange(u * d, nb * b)
    A[pad // b, pad % b, pad % b] = 1.0
    return A, Lsub


def _lower_inverse(D: FloatArray, eye: FloatArray) -> FloatArray:
    """``D^-1`` of a lower-triangular ``D`` (``eye``: the identity of its size):
    ``scipy.linalg.solve_triangular(D, eye, lower=True)`` bit for bit (its LAPACK call,
    ``trtrs`` on ``D`` or, C-ordered, on its Fortran-ordered transpose) without its per-call
    checks and dispatch (~0.1 ms each, a Python loop calls it once per block; tested)."""
    if not np.isfinite(D).all():
        raise ValueError('array must not contain infs or NaNs')
    if D.flags.f_contiguous:
        x, info = sla.lapack.dtrtrs(D, eye, lower=1, trans=0)
    else:
        x, info = sla.lapack.dtrtrs(D.T, eye, lower=0, trans=1)
    if info > 0:
        raise np.linalg.LinAlgError(f'singular matrix: resolution failed at diagonal '
                                    f'{info - 1}')
    return x


def _block_cholesky(A: FloatArray, Lsub: FloatArray) -> FloatArray:
    """Block Cholesky factor of the block-tridiagonal matrix of diagonal blocks ``A`` and
    sub-diagonal blocks ``Lsub``, in place: ``A[k]`` becomes the Schur complement whose
    Cholesky factor is ``D_k``, ``Lsub[k]`` the factor's sub-diagonal block ``L_k``. Returns
    the inverses ``D_k^-1`` ``(nb, b, b)``.

    Raises
    ------
    DegenerateGeometryError
        The matrix is not positive definite.
    """
    nb, b = A.shape[:2]
    Dinv = np.empty_like(A)
    eye = np.eye(b)
    for k in range(nb):
        if k:
            A[k] -= Lsub[k - 1] @ Lsub[k - 1].T
        try:
            D = np.linalg.cholesky(A[k])
        except np.linalg.LinAlgError as exc:
            raise DegenerateGeometryError('the matrix is not positive definite (the absorbed '
                                          'terms leave a direction undetermined)') from exc
        Dinv[k] = _lower_inverse(D, eye)
        if k < nb - 1:
            Lsub[k] = Lsub[k] @ Dinv[k].T
    return Dinv


def _block_solve(Dinv: FloatArray, Lsub: FloatArray, perm: IntArray, rhs: FloatArray
                 ) -> FloatArray:
    """``N^-1 rhs`` by forward and back substitution with the block factor of
    :func:`_block_cholesky`; ``perm`` lists the original scalar of each reordered one."""
    nb, b = Dinv.shape[:2]
    r = np.asarray(rhs, dtype=float)
    n = perm.size
    y = np.zeros((nb * b,) + r.shape[1:])
    y[:n] = r[perm]
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
    x[perm] = y.reshape((nb * b,) + r.shape[1:])[:n]
    return x


def _block_takahashi(Dinv: FloatArray, Lsub: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Diagonal and sub-diagonal blocks of ``N^-1`` from the block factor of
    :func:`_block_cholesky` by Takahashi's backward recursion (see :func:`banded_selection`)."""
    nb = Dinv.shape[0]
    Sdiag = np.empty_like(Dinv)
    Ssub = np.empty_like(Lsub)
    for k in range(nb - 1, -1, -1):
        if k == nb - 1:
            Sdiag[k] = Dinv[k].T @ Dinv[k]
        else:
            Ssub[k] = -Sdiag[k + 1] @ Lsub[k] @ Dinv[k]
            Sdiag[k] = Dinv[k].T @ (Dinv[k] - Lsub[k].T @ Ssub[k])
    return Sdiag, Ssub


def _pair_blocks(Sdiag: FloatArray, Ssub: FloatArray, pos: IntArray, pa: IntArray,
                 pc: IntArray, d: int) -> FloatArray:
    """Node blocks ``Sigma_{pa_k, pc_k}`` ``(k, d, d)`` read from the diagonal and
    sub-diagonal blocks of :func:`_block_takahashi` (nodes at ``pos`` in the block order)."""
    nb, b = Sdiag.shape[:2]
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
    return blk


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
