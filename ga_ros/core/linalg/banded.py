"""Banded joint covariances: block-tridiagonal selected inversion, covariance skeletons and
their completion (the sparse joint priors of the window)."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg import lapack
from ga_ros.core.linalg.blocks import _MAX_PATTERNS, _blake2b, _kept
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
    """:func:`ga_ros.core.linalg.lapack.separator_solves` without numba: ``Bt[k] = Sigma_FF^-1
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
