"""``refinement.marginal_prior``: the one rule for the joint prior of absorbed terms (the
aligner's freeze and the refinement), checked against the dense Schur complement on every path
(sparse skeleton, partial factorisation, dense blocks, the fallbacks)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from ga_ros.core import refinement
from ga_ros.core.refinement import band_prior, marginal_prior, tangent_prior
from ga_ros.core.sparse import CovarianceSkeleton
from ga_ros.errors import DegenerateGeometryError
from ga_ros.geometry import se3

D = 6


def _strip(rng, u: int, reach: int = 2) -> np.ndarray:
    """A random SPD matrix of ``u`` 6x6 node blocks coupled up to ``reach`` nodes apart."""
    M = np.zeros((u * D, u * D))
    for i in range(u):
        for j in range(i, min(u, i + reach + 1)):
            B = rng.normal(size=(D, D)) * 0.3
            if i == j:
                B = B @ B.T + 5.0 * np.eye(D)
            M[i * D:(i + 1) * D, j * D:(j + 1) * D] = B
            M[j * D:(j + 1) * D, i * D:(i + 1) * D] = B.T
    return M + max(0.0, 1.0 - np.linalg.eigvalsh(M).min()) * np.eye(u * D)


def _schur(N: np.ndarray, u: np.ndarray, keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The dense Schur complement ``(H, g)`` of ``(N, u)`` onto the kept nodes."""
    cS = (np.nonzero(keep)[0][:, None] * D + np.arange(D)).ravel()
    cL = (np.nonzero(~keep)[0][:, None] * D + np.arange(D)).ravel()
    X = np.linalg.solve(N[np.ix_(cL, cL)], np.column_stack([N[np.ix_(cL, cS)], u[cL]]))
    H = N[np.ix_(cS, cS)] - N[np.ix_(cS, cL)] @ X[:, :-1]
    return 0.5 * (H + H.T), u[cS] - N[np.ix_(cS, cL)] @ X[:, -1]


@pytest.fixture
def problem():
    rng = np.random.default_rng(5)
    n = 60
    N = _strip(rng, n)
    u = rng.normal(size=n * D)
    keep = np.zeros(n, dtype=bool)
    keep[rng.permutation(n)[:30]] = True
    T = se3.exp(rng.normal(size=(n, 6)) * [5, 5, 5, 0.3, 0.3, 0.3])
    return N, u, keep, T, np.arange(100, 100 + n)


@pytest.mark.parametrize('dense_max', [10**9, 0])  # eliminated by dense blocks / trailing_factor
def test_the_exact_prior_is_the_tangent_prior_of_the_dense_schur_complement(
        problem, dense_max, monkeypatch):
    N, u, keep, T, nodes = problem
    monkeypatch.setattr(refinement, 'DENSE_SCHUR_MAX', dense_max)
    H, g = _schur(N, u, keep)
    mean, info = tangent_prior(T[keep], H, g)
    p = marginal_prior(nodes, sp.csc_matrix(N), u, keep, T[keep], -1, 0)
    np.testing.assert_array_equal(p.nodes, nodes[keep])
    np.testing.assert_allclose(p.information, info, rtol=1e-8, atol=1e-10 * np.abs(info).max())
    np.testing.assert_allclose(p.T_world_node, mean, atol=1e-10)
    assert p.rank == (H.shape[0] if dense_max == 0 else None)


@pytest.mark.parametrize('dense_input', [False, True])
def test_the_sparse_prior_is_the_band_prior_of_the_dense_covariance_skeleton(problem,
                                                                             dense_input):
    """Sparse ``N`` (selected inversion) and dense ``N`` (Cholesky) give the band prior of the
    skeleton of ``H^-1`` and the step ``H^-1 g``; without a gradient its covariance agrees with
    ``H^-1`` on the skeleton."""
    N, u, keep, T, nodes = problem
    H, g = _schur(N, u, keep)
    Sigma = np.linalg.inv(H)
    w, hubs = 3, 2
    mean, info = band_prior(T[keep], CovarianceSkeleton.of_dense(Sigma, D, w, hubs), Sigma @ g)
    p = marginal_prior(nodes, N if dense_input else sp.csr_matrix(N), u, keep, T[keep], w, hubs,
                       coords=T[:, :3, 3])
    K = p.information.toarray()
    np.testing.assert_allclose(K, info.toarray(), rtol=1e-8, atol=1e-10 * np.abs(K).max())
    np.testing.assert_allclose(p.T_world_node, mean, atol=1e-10)
    assert p.rank == K.shape[0]
    # at the terms' optimum (no gradient, mean = T) the covariance of the prior is H^-1 on the
    # skeleton
    p0 = marginal_prior(nodes, N if dense_input else sp.csr_matrix(N), np.zeros_like(u), keep,
                        T[keep], w, hubs)
    np.testing.assert_allclose(p0.T_world_node, T[keep], atol=1e-12)
    m = keep.sum()
    Kinv = np.linalg.inv(p0.information.toarray()).reshape(m, D, m, D)
    S4 = Sigma.reshape(m, D, m, D)
    for i in range(m):  # each node's marginal and its band neighbours' correlations are exact
        for j in range(i, min(m, i + w + 1)):
            np.testing.assert_allclose(Kinv[i, :, j], S4[i, :, j], rtol=1e-7,
                                       atol=1e-9 * np.abs(S4).max())


def test_a_kept_part_left_free_falls_back_to_the_exact_singular_prior(problem):
    """Kept nodes the terms leave free in some direction (``N`` singular there): the sparse
    skeleton cannot be formed (``DegenerateGeometryError`` inside), the prior is the exact
    Schur complement, singular, rank unknown."""
    N, u, keep, T, nodes = problem
    k = np.nonzero(keep)[0][0]
    c = np.arange(k * D, (k + 1) * D)
    N = N.copy()
    N[c, :] = 0.0
    N[:, c] = 0.0  # node k: no information at all
    u = u.copy()
    u[c] = 0.0
    H, g = _schur(N, u, keep)
    mean, info = tangent_prior(T[keep], H, g)
    p = marginal_prior(nodes, sp.csr_matrix(N), u, keep, T[keep], 3, 2)
    assert not sp.issparse(p.information) and p.rank is None
    np.testing.assert_allclose(p.information, info, rtol=1e-8, atol=1e-10 * np.abs(info).max())


def test_undetermined_eliminated_nodes_are_a_degenerate_geometry_error(problem):
    N, u, keep, T, nodes = problem
    k = np.nonzero(~keep)[0][0]
    c = np.arange(k * D, (k + 1) * D)
    N = N.copy()
    N[c, :] = 0.0
    N[:, c] = 0.0
    with pytest.raises(DegenerateGeometryError, match='undetermined'):
        marginal_prior(nodes, sp.csr_matrix(N), u, keep, T[keep], -1, 0)
