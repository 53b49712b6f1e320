"""Block assembly and the sparse Cholesky wrapper against dense computations."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholesky import SparseCholesky, trailing_factor
from ga_ros.core.linalg.ordering import block_ordering


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


def test_full_matrix_of_a_kept_layout_equals_the_sum_of_its_triangles(rng):
    """``full_csc`` keeps where each entry of the symmetric matrix comes from (a freeze builds
    one per track on a repeating pattern): for new values on the same pattern it equals
    ``L + L'`` (SciPy's sum) array for array, and with an explicit zero it drops it as the
    sum does."""
    n, d = 8, 3
    pairs = [(i, i) for i in range(n)] + [(i + 1, i) for i in range(n - 1)] + [(7, 2), (5, 0)]
    pat = BlockPattern(np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs]), d, n)

    def by_sum(data):
        L = pat.lower_csc(data)
        return (L + sp.tril(L, -1).T).tocsc()

    for k in range(3):  # the first call builds the layout, the next ones reuse it
        data = pat.assemble(rng.normal(size=(len(pairs), d, d)))
        if k == 2:
            data[5] = 0.0  # an explicit zero: not stored, as in the sum
        got, ref = pat.full_csc(data), by_sum(data)
        for name in ('indptr', 'indices', 'data'):
            np.testing.assert_array_equal(getattr(got, name), getattr(ref, name))
    assert pat._full is not None


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


def _random_block_spd(rng, n, d, density=0.3):
    """A sparse symmetric positive definite matrix of ``n`` blocks of ``d`` and its pattern."""
    links = {(i + 1, i) for i in range(n - 1)}
    links |= {(int(a), int(b)) for a, b in rng.integers(0, n, (int(density * n * n), 2)) if a > b}
    pairs = [(i, i) for i in range(n)] + sorted(links)
    N = np.eye(n * d)
    for i, j in links:  # each link a Gram matrix over its two blocks
        J = rng.normal(size=(d, 2 * d))
        rows = np.r_[i * d:(i + 1) * d, j * d:(j + 1) * d]
        N[np.ix_(rows, rows)] += J.T @ J
    blocks = np.array([N[i * d:(i + 1) * d, j * d:(j + 1) * d] for i, j in pairs])
    pat = BlockPattern(np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs]), d, n)
    return N, pat, pat.assemble(blocks)


def test_trailing_factor_is_the_schur_complement_of_the_dense_matrix(rng):
    n, d = 30, 6
    N, pat, data = _random_block_spd(rng, n, d)
    np.testing.assert_allclose(pat.full_csc(data).toarray(), N, atol=1e-12)
    blocks = np.array([17, 3, 25, 4])  # any order: rows of L follow it
    rows = (blocks[:, None] * d + np.arange(d)).ravel()
    rest = np.setdiff1d(np.arange(n * d), rows)
    schur = N[np.ix_(rows, rows)] - N[np.ix_(rows, rest)] @ np.linalg.solve(
        N[np.ix_(rest, rest)], N[np.ix_(rest, rows)])
    b = rng.normal(size=n * d)
    tf = trailing_factor(pat, data, blocks, b)
    np.testing.assert_allclose(tf.information(), schur, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.tril(tf.L), tf.L)                 # lower triangular
    np.testing.assert_allclose(tf.solution, np.linalg.solve(N, b), rtol=1e-9, atol=1e-12)
    Sigma = np.linalg.inv(N)
    want = np.array([Sigma[k * d:(k + 1) * d, k * d:(k + 1) * d] for k in blocks])
    np.testing.assert_allclose(tf.marginal_blocks(), want, rtol=1e-9, atol=1e-12)


def test_block_ordering_is_kept_per_pattern_and_a_read_out_factor_still_solves(rng):
    n, d = 20, 3
    N, pat, data = _random_block_spd(rng, n, d)
    perm = block_ordering(pat)
    assert sorted(perm.tolist()) == list(range(n * d))
    assert np.array_equal(perm.reshape(n, d) % d, np.tile(np.arange(d), (n, 1)))  # whole blocks
    twin = BlockPattern(*pat.block_lower, d, n)                    # same pattern, new object
    assert twin.key == pat.key and block_ordering(twin) is perm
    chol = SparseCholesky(pat, data, trailing=np.array([5, 0]))
    L, who = chol.trailing_lower(2 * d)
    assert np.array_equal(who, np.r_[15:18, 0:3])
    b = rng.normal(size=n * d)
    np.testing.assert_allclose(chol.solve(b), np.linalg.solve(N, b), rtol=1e-9)  # factored again
    again, _ = BlockPattern.from_matrix(sp.csc_matrix(N), d)
    assert again.key == pat.key


def test_direct_analysis_gives_cvxopts_factor(rng, monkeypatch):
    """The symbolic analysis through ``cholmod_l_analyze_p`` directly (no cvxopt copy of the
    pattern) gives the factor of cvxopt's ``cholmod.symbolic``: the same permutation, the same
    supernodes and the same values after the numeric factorisation, for the block ordering and
    with trailing blocks; both solve like the dense matrix."""
    import pytest

    from ga_ros.core.linalg.cholmod import _direct_cholmod
    from ga_ros.core.linalg.cholmod_ctypes import _supernodal_layout

    direct = _direct_cholmod()
    if direct is None or direct._capsule is None:
        pytest.skip('the direct CHOLMOD calls are not available here')
    N, pat, data = _random_block_spd(rng, 40, 6, density=0.08)
    b = rng.normal(size=N.shape[0])
    for trailing in (None, np.array([3, 17, 8])):
        fast = SparseCholesky(pat, data, trailing=trailing)
        with monkeypatch.context() as m:
            m.setattr(direct, '_capsule', None)  # cvxopt's symbolic analysis
            ref = SparseCholesky(pat, data, trailing=trailing)
        assert ref._A is None and fast._A is None
        np.testing.assert_array_equal(fast.permutation(), ref.permutation())
        a, r = _supernodal_layout(fast._F, fast.n), _supernodal_layout(ref._F, ref.n)
        assert a is not None and r is not None
        np.testing.assert_array_equal(a.starts, r.starts)
        np.testing.assert_array_equal(a.srows[:a.pi[-1] + a.nrows[-1]],
                                      r.srows[:r.pi[-1] + r.nrows[-1]])
        np.testing.assert_array_equal(a.x, r.x)
        np.testing.assert_allclose(fast.solve(b), np.linalg.solve(N, b), rtol=1e-9)
        fast.refactor(2 * data)  # the analysis is reused
        np.testing.assert_allclose(fast.solve(b), np.linalg.solve(2 * N, b), rtol=1e-9)


def test_compiled_assembly_equals_the_numpy_one_bit_for_bit(rng):
    """The compiled loop of ``assemble(compiled=True)`` adds the same entries in the same order
    as the gather and ``bincount``: diagonal blocks (lower triangle only), blocks given twice,
    blocks of fixed nodes (-1) and upper ones dropped."""
    from ga_ros.core import kernels
    if not kernels.AVAILABLE:
        pytest.skip('numba not installed')
    n, d = 9, 6
    extra = [(int(a), int(b)) for a, b in rng.integers(-1, n, (60, 2))]
    pairs = [(i, i) for i in range(n)] + extra + [(3, 3), (5, 2), (5, 2)]
    pat = BlockPattern(np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs]), d, n)
    blocks = rng.normal(size=(len(pairs), d, d))
    np.testing.assert_array_equal(pat.assemble(blocks, compiled=True), pat.assemble(blocks))
    dense = np.zeros((n * d, n * d))  # and both are the blocks' sum (independent)
    for (i, j), B in zip(pairs, blocks):
        if i >= 0 and j >= 0:
            dense[i * d:(i + 1) * d, j * d:(j + 1) * d] += B
    np.testing.assert_allclose(pat.lower_csc(pat.assemble(blocks, compiled=True)).toarray(),
                               np.tril(dense), atol=1e-12)


def test_auto_factor_of_a_sparse_chain_is_simplicial_and_refuses_an_indefinite_matrix(rng):
    """``auto`` lets CHOLMOD factor a small chain simplicially (few flops per entry): it solves
    like the dense matrix, and like a supernodal factor refuses a matrix with a negative
    eigenvalue (a simplicial factor is L L' here, not L D L', which would accept it)."""
    import pytest

    from ga_ros.core.linalg.cholmod import _direct_cholmod
    from ga_ros.errors import DegenerateGeometryError

    direct = _direct_cholmod()
    if direct is None:
        pytest.skip('the direct CHOLMOD call is not available')
    n, d = 60, 3
    N = np.eye(n * d)
    for i in range(n - 1):
        J = rng.normal(size=(d, 2 * d))
        N[i * d:(i + 2) * d, i * d:(i + 2) * d] += J.T @ J
    pairs = [(i, i) for i in range(n)] + [(i + 1, i) for i in range(n - 1)]
    pat = BlockPattern(np.array([p[0] for p in pairs]), np.array([p[1] for p in pairs]), d, n)

    def values(M):
        return pat.assemble(np.array([M[i * d:(i + 1) * d, j * d:(j + 1) * d] for i, j in pairs]))

    b = rng.normal(size=n * d)
    for auto, simplicial in ((True, True), (False, False)):
        chol = SparseCholesky(pat, values(N), auto=auto)
        assert (direct._factor(chol._F)[1].is_super == 0) == simplicial
        np.testing.assert_allclose(chol.solve(b), np.linalg.solve(N, b), rtol=1e-9)
    bad = N.copy()
    bad[7, 7] = -50.0  # indefinite: the dense eigenvalues say so
    assert np.linalg.eigvalsh(bad).min() < 0
    for auto in (True, False):
        with pytest.raises(DegenerateGeometryError):
            SparseCholesky(pat, values(bad), auto=auto)


@pytest.mark.parametrize('fmt', ['csc', 'csr', 'coo'])
def test_compiled_from_matrix_equals_the_numpy_conversion(rng, fmt):
    """``BlockPattern.from_matrix`` with the compiled kernels (one pass for the blocks, one
    for the values) gives the pattern and values of the SciPy/NumPy conversion bit for bit,
    on a symmetric block matrix with absent blocks, zero entries inside stored blocks,
    explicit zeros, a block column with its diagonal block only and duplicate entries (COO);
    and its values are ``N``'s lower triangle (an independent dense check)."""
    from ga_ros.core.linalg import blocks as blk

    if blk._from_matrix_kernels() is None:
        pytest.skip('numba not installed')
    n, d = 40, 6
    dense = np.zeros((n * d, n * d))
    for i in range(n):
        dense[i * d:(i + 1) * d, i * d:(i + 1) * d] = rng.normal(size=(d, d))
    for i, j in rng.integers(0, n - 1, (70, 2)):  # block column n - 1: its diagonal only
        dense[i * d:(i + 1) * d, j * d:(j + 1) * d] = rng.normal(size=(d, d))
    dense[rng.random(dense.shape) < 0.2] = 0.0  # zeros inside stored blocks
    dense = dense + dense.T
    for i in range(1, n, 2):  # odd block rows: no entry in their blocks' first column
        for j in range(i):  # (found after the even ones of that block column: sorted)
            dense[i * d:(i + 1) * d, j * d] = dense[j * d, i * d:(i + 1) * d] = 0.0
    N = sp.coo_matrix(dense)
    if fmt == 'coo':  # a duplicate entry split in two halves
        N = sp.coo_matrix((np.r_[N.data, 0.5 * N.data[:5]], (np.r_[N.row, N.row[:5]],
                                                               np.r_[N.col, N.col[:5]])),
                          shape=N.shape)
        N.data[:5] *= 0.5
    else:
        N = N.asformat(fmt)
        N.data[::17] = 0.0  # explicit zeros stay stored
    fast, fv = BlockPattern.from_matrix(N, d)
    ref, rv = BlockPattern._from_matrix_numpy(N, d)
    assert fast.key == ref.key and fast.nnz == ref.nnz
    for a, b in zip(fast.block_lower, ref.block_lower):
        assert np.array_equal(a, b)
    assert np.array_equal(fast.indptr, ref.indptr) and np.array_equal(fast.indices, ref.indices)
    assert np.array_equal(fv.view(np.int64), rv.view(np.int64))  # bit for bit
    want = sp.tril(sp.csc_matrix(N)).toarray()
    np.testing.assert_array_equal(fast.lower_csc(fv).toarray(), want)
    # the pattern assembles a block list of its pairs as one built from them does
    blocks = rng.normal(size=(fast.block_lower[0].size, d, d))
    twin = BlockPattern(*fast.block_lower, d, n)
    assert np.array_equal(fast.assemble(blocks), twin.assemble(blocks))
    assert np.array_equal(fast.assemble(blocks, compiled=True), twin.assemble(blocks))
