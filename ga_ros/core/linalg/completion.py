"""Covariance skeletons and their maximum-entropy completion: the information of a sparse
joint prior (Dempster's covariance selection on a band plus hubs), and the inverse of a stack of
symmetric positive definite matrices it is built from."""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg import lapack
from ga_ros.core.linalg.blocks import _MAX_PATTERNS, _blake2b, _kept
from ga_ros.core.linalg.runs import by_runs
from ga_ros.errors import DegenerateGeometryError
from ga_ros.runtime import lazy_import

sla = lazy_import('scipy.linalg')  # only some functions need them (start-up)
sp = lazy_import('scipy.sparse')


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
    one is not positive definite.

    A stack ``(m, k, k)`` of at least :data:`~ga_ros.core.linalg.runs.RUNS_FROM` matrices
    whose consecutive entries are mostly equal, bit for bit (an odometry stream's covariances),
    is inverted one matrix per run (:func:`~ga_ros.core.linalg.runs.by_runs`): each matrix's
    inverse is computed alone either way, so the result is the same bits (tested), for a
    fraction of the work (~5 us per 6x6 matrix)."""
    return by_runs(lambda A: _spd_inverse_each(A, error), M)


def _spd_inverse_each(M: FloatArray, error: str) -> FloatArray:
    """:func:`spd_inverse` of every matrix of the stack."""
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
    ``(d m, d m)`` covariance (zero where ``i + j >= m``), as
    :class:`~ga_ros.core.linalg.banded.BandSelection` holds it."""
    m = Sigma.shape[0] // d
    S4 = Sigma.reshape(m, d, m, d)
    i = np.repeat(np.arange(m), w + 1)
    j = i + np.tile(np.arange(w + 1), m)
    ok = j < m
    band = np.zeros((m, w + 1, d, d))
    band[i[ok], (j - i)[ok]] = S4[i[ok], :, j[ok], :]
    return band
