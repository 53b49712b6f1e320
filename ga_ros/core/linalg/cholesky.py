"""The sparse Cholesky interface, and partial factorisations built on it.

:class:`CholeskyFactor` is what the solver, the window and the covariances use of a factor;
:class:`SparseCholesky` (:mod:`ga_ros.core.linalg.cholmod`) is its implementation, the one place
to change to swap the sparse Cholesky. :func:`trailing_factor` orders chosen blocks last, so the
trailing dense block of the factor is the Cholesky factor of the Schur complement onto them (a
partial factorisation): marginal covariances and marginal information of a few nodes without
inverting anything else.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholmod import SparseCholesky, _cholmod
from ga_ros.core.linalg.ordering import _expand
from ga_ros.errors import DegenerateGeometryError
from ga_ros.runtime import lazy_import

sla = lazy_import('scipy.linalg')  # only some functions need them (start-up)
sp = lazy_import('scipy.sparse')


class CholeskyFactor(Protocol):
    """A sparse Cholesky factor ``P N P' = L L'`` of a symmetric positive definite matrix
    given by its lower triangle on a :class:`~ga_ros.core.linalg.blocks.BlockPattern` (CSC).

    Implemented by :class:`SparseCholesky` (CHOLMOD); a replacement implements these members.
    """

    pattern: BlockPattern
    n: int

    def refactor(self, data: FloatArray) -> None:
        """Numeric factorisation of new values on the same pattern (symbolic analysis reused);
        raises :class:`DegenerateGeometryError` when not positive definite."""

    def release_values(self) -> None:
        """Let go of the values last factored."""

    def solve(self, b: FloatArray) -> FloatArray:
        """``N^-1 b`` for ``b`` of shape ``(n,)`` or ``(n, k)``."""

    def permutation(self) -> IntArray:
        """``p`` of ``P N P' = L L'``: row ``k`` of ``L`` is unknown ``p[k]``."""

    def trailing_lower(self, m: int) -> tuple[FloatArray, IntArray]:
        """The last ``m`` rows and columns of ``L`` and the unknowns they belong to."""


__all__ = ['CholeskyFactor', 'SparseCholesky', 'TrailingFactor', 'trailing_factor']


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
