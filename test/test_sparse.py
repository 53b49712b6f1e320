"""Block assembly and the sparse Cholesky wrapper against dense computations."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ga_ros.core.sparse import BlockPattern, SparseCholesky


def test_block_pattern_assembles_like_coo(rng):
    n, d = 7, 3
    extra = [(int(a), int(b)) for a, b in rng.integers(-1, n, (40, 2))]
    pairs = [(i, i) for i in range(n)] + extra
    br = np.array([p[0] for p in pairs])
    bc = np.array([p[1] for p in pairs])
    blocks = rng.normal(size=(len(pairs), d, d))
    pat = BlockPattern(br, bc, d, n)
    got = pat.lower_csc(pat.assemble(blocks)).toarray()
    dense = np.zeros((n * d, n * d))
    for (i, j), B in zip(pairs, blocks):
        if i >= 0 and j >= 0:
            dense[i * d:(i + 1) * d, j * d:(j + 1) * d] += B
    np.testing.assert_allclose(got, np.tril(dense), atol=1e-12)
    sym = pat.full_csc(pat.assemble(blocks)).toarray()
    np.testing.assert_allclose(sym, np.tril(dense) + np.tril(dense, -1).T, atol=1e-12)


def test_cholesky_solves_like_dense(rng):
    n, d = 6, 6
    N = np.eye(n * d)
    for i in range(n - 1):  # a chain of Gram matrices: symmetric positive definite
        J = rng.normal(size=(d, 2 * d))
        N[i * d:(i + 2) * d, i * d:(i + 2) * d] += J.T @ J
    pairs = [(i, i) for i in range(n)] + [(i + 1, i) for i in range(n - 1)]
    blocks = np.array([N[i * d:(i + 1) * d, j * d:(j + 1) * d] for i, j in pairs])
    pat = BlockPattern(np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs]), d, n)
    data = pat.assemble(blocks)
    np.testing.assert_allclose(pat.full_csc(data).toarray(), N, atol=1e-12)
    b = rng.normal(size=(n * d, 3))
    chol = SparseCholesky(pat, data)
    np.testing.assert_allclose(chol.solve(b), np.linalg.solve(N, b), rtol=1e-9)
    chol.refactor(2 * data)
    np.testing.assert_allclose(chol.solve(b[:, 0]), np.linalg.solve(2 * N, b[:, 0]), rtol=1e-9)
    assert sp.issparse(pat.lower_csc(data))
