"""Weighted parameters and sequential priors (paper Sec. III-E, III-D): :class:`GaussianPrior`,
its validated form inside a problem, its rank and its terms of the normal equations."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import models
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import DegenerateGeometryError, InputError
from ga_ros.runtime import lazy_import

sp = lazy_import('scipy.sparse')  # only some functions need it (start-up)

@dataclass(frozen=True)
class GaussianPrior:
    """Known values of some node parameters (weighted parameters, paper Sec. III-E).

    Attributes
    ----------
    node_ids : (k,) node ids.
    T_world_node : (k, 4, 4) prior mean poses (for the position models only the translation
        counts).
    information : (d k, d k) inverse covariance (dense array or scipy.sparse), node-major, each
        node's block in the order ``[x y z rx ry rz]`` (se3, d = 6), ``[x y rz]`` (se2, d = 3)
        or ``[x y z]`` (positions, d = 3), of the residual of
        :func:`~ga_ros.core.models.prior_residual` (se3: ``[R_mean' (p - p_mean),
        log(R_mean' R)]``, the right perturbation ``T_mean exp(e)`` to first order).
    rank : the rank of ``information`` (the number of equations the prior adds to the
        redundancy), when the caller knows it (e.g. positive definite by construction: ``d k``);
        ``None`` (default): the solver determines it (a Cholesky, or an eigen-decomposition of a
        singular information), and only when it needs it (the variance factor).
    weak : a datum prior (the weak gauge prior of ``datum='fixes'``), not an observation: its
        mean is the initial estimate, not a random draw with its covariance, so its residual is
        about zero whatever its information. It then counts in the redundancy only with the
        equations the other observations leave to it, ``tr(Q H)`` (``Q`` the marginal
        covariances of its nodes; block-diagonal information), not its rank: about 0 where
        the fixes determine the datum, its rank where it alone does. Its redundancy number
        ``rank - tr(Q H)`` is left out of the variance factor's redundancy.
    """

    node_ids: IntArray
    T_world_node: FloatArray
    information: FloatArray | sp.spmatrix
    rank: int | None = None
    weak: bool = False

    @staticmethod
    def from_covariances(node_ids, T_world_node, cov: FloatArray) -> GaussianPrior:
        """Block-diagonal prior from per-node covariances ``(k, d, d)``."""
        cov = np.asarray(cov, dtype=float)
        info = np.linalg.inv(cov)
        info = 0.5 * (info + np.swapaxes(info, 1, 2))
        return GaussianPrior(np.asarray(node_ids, dtype=np.int64),
                             np.asarray(T_world_node, dtype=float),
                             sp.block_diag(list(info), format='csr'))


# ------------------------------------------------------------------------------ internals
@dataclass
class _PriorData:
    idx: IntArray  # (k,) node indices
    T_mean: FloatArray
    H_blocks: FloatArray  # (b, d, d) non-zero d x d blocks of the information
    blk_r: IntArray  # (b,) block row (position in idx)
    blk_c: IntArray
    information: FloatArray | sp.spmatrix  # as given (for the rank, when it is asked for)
    known_rank: int | None = None  # the prior's own rank, or computed on first use
    blocked: sp.bsr_matrix | None = None  # the information as (d, d) blocks, for products
    weak: bool = False  # a datum prior (GaussianPrior.weak)

    def weighted(self, e: FloatArray) -> FloatArray:
        """``H e`` ``(k, d)`` of residuals ``e`` ``(k, d)`` (one sparse product)."""
        return (self.blocked @ e.reshape(-1)).reshape(e.shape)

    @property
    def rank(self) -> int:
        """Rank of the information: the number of equations the prior adds. Given with the
        prior (:attr:`GaussianPrior.rank`) or computed once, when the variance factor needs it
        (not for a linearisation alone, e.g. :func:`normal_matrix_at`)."""
        if self.known_rank is None:
            self.known_rank = _information_rank(self.H_blocks, self.blk_r, self.blk_c,
                                                self.information)
        return self.known_rank

    @staticmethod
    def build(network: ConnectionNetwork, prior: GaussianPrior, d: int) -> _PriorData:
        ids = np.asarray(prior.node_ids, dtype=np.int64).ravel()
        k = ids.size
        if np.unique(ids).size != k:
            raise InputError('a prior names a node more than once; give each node once')
        Tm = np.asarray(prior.T_world_node, dtype=float)
        if Tm.shape != (k, 4, 4) or not np.isfinite(Tm).all():
            raise InputError(f'prior mean must be finite with shape ({k}, 4, 4), got {Tm.shape}')
        H = prior.information
        if H.shape != (d * k, d * k):
            raise InputError(f'prior information must be ({d * k}, {d * k}) for {k} nodes with '
                             f'{d} parameters each, got {H.shape}')
        if sp.issparse(H) and H.format == 'bsr' and H.blocksize == (d, d):
            Hb = H.copy()  # already in blocks (the window's joint priors): no conversion
        else:
            Hb = sp.bsr_matrix(sp.csr_matrix(H), blocksize=(d, d))
        Hb.sort_indices()
        if not np.isfinite(Hb.data).all():
            raise InputError('prior information has NaN or inf entries')
        rows = np.repeat(np.arange(k), np.diff(Hb.indptr))
        cols = Hb.indices.astype(np.int64)
        rank = prior.rank
        if rank is not None and not 0 <= int(rank) <= d * k:
            raise InputError(f'prior rank must be in [0, {d * k}] for {k} nodes, got {rank}')
        return _PriorData(network.indices_of(ids), Tm, Hb.data, rows, cols, H,
                          None if rank is None else int(rank), Hb,
                          bool(getattr(prior, 'weak', False)))


def information_rank(information: FloatArray | sp.spmatrix, d: int = 6) -> int:
    """Rank of a prior's information ``(d k, d k)`` (dense or sparse, ``d x d`` blocks): the
    number of equations it adds to the redundancy (see :attr:`GaussianPrior.rank`)."""
    Hb = sp.bsr_matrix(sp.csr_matrix(information), blocksize=(d, d))
    Hb.sort_indices()
    rows = np.repeat(np.arange(Hb.shape[0] // d), np.diff(Hb.indptr))
    return _information_rank(Hb.data, rows, Hb.indices.astype(np.int64), information)


def _information_rank(blocks: FloatArray, rows: IntArray, cols: IntArray, H) -> int:
    """Rank of a prior's information matrix: the number of independent equations it adds to
    the redundancy (a zero-weight prior adds none).

    Block-diagonal information (per-node priors): the ranks of its blocks. Otherwise a
    Cholesky decides full rank (sparse for a sparse, e.g. block-banded, information), and only
    a singular matrix pays for an eigen-decomposition.
    """
    if blocks.size == 0 or not np.any(blocks):
        return 0
    if np.array_equal(rows, cols):
        return int(np.linalg.matrix_rank(0.5 * (blocks + np.swapaxes(blocks, 1, 2)),
                                         hermitian=True).sum())
    if sp.issparse(H):  # a sparse Cholesky on the block pattern
        try:
            pattern = BlockPattern(rows, cols, blocks.shape[1], H.shape[0] // blocks.shape[1])
            SparseCholesky(pattern, pattern.assemble(blocks))
            return int(H.shape[0])
        except DegenerateGeometryError:  # singular: the eigen-decomposition below
            pass
    Hd = H.toarray() if sp.issparse(H) else np.asarray(H, dtype=float)
    Hd = 0.5 * (Hd + Hd.T)
    try:
        np.linalg.cholesky(Hd)
        return int(Hd.shape[0])
    except np.linalg.LinAlgError:
        return int(np.linalg.matrix_rank(Hd, hermitian=True))


def _add_priors(model, T, prior_data, col, u, blocks: list | None,
                compiled: bool = False) -> float:
    """Add the prior terms to ``u`` and ``blocks`` (in place; ``None``: the gradient only);
    return their cost. ``compiled`` (se3): each prior's terms from the compiled kernel
    :func:`ga_ros.core.kernels.se3_prior` (the same sums to rounding, ~150 us of NumPy calls
    per prior less: a window has a few priors and takes ~8 linearisations per update)."""
    if compiled and model == 'se3':
        from ga_ros.core import kernels

        cost = 0.0
        for pd in prior_data:
            c, b = kernels.se3_prior(T, pd.idx, pd.T_mean, pd.H_blocks, pd.blk_r, pd.blk_c,
                                     col, u, blocks is not None)
            if blocks is not None:
                blocks.append(b)
            cost += c
        return cost
    cost = 0.0
    for pd in prior_data:
        e, J = models.prior_residual(model, T[pd.idx], pd.T_mean)
        JT = np.swapaxes(J, 1, 2)
        if blocks is not None:  # block (a, b) of J' H J = J_a' H_ab J_b
            blocks.append(JT[pd.blk_r] @ pd.H_blocks @ J[pd.blk_c])
        He = pd.weighted(e)
        g = (JT @ He[:, :, None])[:, :, 0]
        c = col[pd.idx]
        u[c[c >= 0]] += g[c >= 0]  # a prior's nodes are distinct
        cost += float(np.sum(e * He))
    return cost


def _prior_cost(model: str, T: FloatArray, prior_data) -> float:
    total = 0.0
    for pd in prior_data:
        e, _ = models.prior_residual(model, T[pd.idx], pd.T_mean)
        total += float(np.sum(e * pd.weighted(e)))
    return total
