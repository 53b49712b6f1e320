"""The batch path's memory savings change no number: the direct CHOLMOD factorisation, released
values, connection networks stored as arrays."""

from __future__ import annotations

import numpy as np
import pytest

import ga_ros.core.linalg.blocks as assembly
import ga_ros.core.linalg.cholmod as cholmod
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.linalg.cholmod_ctypes import _supernodal_layout
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import DegenerateGeometryError, NetworkError

pytestmark = pytest.mark.skipif(cholmod._direct_cholmod() is None,
                                reason='the CHOLMOD library bundled with cvxopt was not found')


def _random_normal_matrix(rng, n: int = 400, m: int = 1600, d: int = 6, ridge: float = 1e-3):
    """A pattern of ``n`` blocks with ``m`` random connections and the lower triangle of
    ``sum J' J`` over them plus ``ridge I`` (SPD for ``ridge > 0``)."""
    src = rng.integers(0, n, m)
    dst = (src + rng.integers(1, 30, m)) % n
    diag = np.arange(n)
    pattern = BlockPattern(np.concatenate([src, src, dst, dst, diag]),
                           np.concatenate([src, dst, src, dst, diag]), d, n)
    J = rng.standard_normal((m, d, d))
    H = J @ np.swapaxes(J, 1, 2)
    blocks = np.concatenate([H, -H, -H, H, np.broadcast_to(ridge * np.eye(d), (n, d, d))])
    return pattern, pattern.assemble(blocks)


def _factor_values(chol: SparseCholesky) -> np.ndarray:
    lay = _supernodal_layout(chol._F, chol.n)
    assert lay is not None
    return lay.x.copy()


@pytest.mark.parametrize('permute_from, in_place', [(0, True), (0, False), (1 << 40, False)])
def test_direct_factorisation_equals_cvxopts(rng, monkeypatch, permute_from, in_place):
    """The factor computed by ``cholmod_l_factorize`` on the pattern's own arrays (or, for large
    patterns, on ``P N P'`` gathered by the project under the natural ordering) is bit for bit
    cvxopt's (``cholmod.numeric`` on its packed copy), first and refactored with new values; the
    solves agree with a dense solve."""
    monkeypatch.setattr(cholmod, '_PERMUTE_FROM_NNZ', permute_from)
    if not in_place:
        monkeypatch.setattr(assembly, '_PERMUTE', [None])  # P N P' gathered into a copy
    pattern, data = _random_normal_matrix(rng)
    kept = data.copy()
    data2 = data.copy()
    data2[pattern.indptr[:-1]] += rng.random(pattern.size)  # the diagonal: still SPD
    direct = SparseCholesky(pattern, data)
    assert (direct._permuted is not None) == (permute_from == 0)
    np.testing.assert_array_equal(data, kept)  # permuted in place and back
    x_direct = _factor_values(direct)
    direct.refactor(data2)
    x2_direct = _factor_values(direct)
    monkeypatch.setattr(cholmod, '_DIRECT', [None])  # cvxopt's numeric
    via_cvxopt = SparseCholesky(pattern, data)
    np.testing.assert_array_equal(_factor_values(via_cvxopt), x_direct)
    via_cvxopt.refactor(data2)
    np.testing.assert_array_equal(_factor_values(via_cvxopt), x2_direct)
    b = rng.standard_normal(pattern.size)
    N = pattern.full_csc(data2).toarray()
    np.testing.assert_allclose(direct.solve(b), np.linalg.solve(N, b), rtol=1e-8, atol=1e-10)


@pytest.mark.parametrize('inverse', [False, True])
def test_permutation_in_place_equals_gather(rng, inverse):
    """The in-place permutation (cycle by cycle) is the gather ``x[where]``, or its inverse."""
    kernel = assembly._permutation_kernel()
    if kernel is None:
        pytest.skip('numba is not installed: the values are gathered into a copy')
    where = np.concatenate([np.arange(10), 10 + rng.permutation(990)])  # fixed points too
    x = rng.standard_normal(1000)
    y = x.copy()
    kernel(y, where, inverse, np.zeros(x.size, dtype=np.bool_))
    if inverse:
        expected = np.empty_like(x)
        expected[where] = x
    else:
        expected = x[where]
    np.testing.assert_array_equal(y, expected)


@pytest.mark.parametrize('permute_from', [0, 1 << 40])
def test_direct_factorisation_reports_a_singular_matrix(rng, monkeypatch, permute_from):
    """A matrix that is not positive definite raises DegenerateGeometryError (not a print from
    CHOLMOD), and the same factor object works again with good values."""
    monkeypatch.setattr(cholmod, '_PERMUTE_FROM_NNZ', permute_from)
    pattern, data = _random_normal_matrix(rng, ridge=0.0)  # the sum of differences: singular
    with pytest.raises(DegenerateGeometryError, match='not positive definite'):
        SparseCholesky(pattern, data)
    pattern2, good = _random_normal_matrix(np.random.default_rng(7))
    chol = SparseCholesky(pattern2, good)
    bad = good.copy()
    bad[pattern2.indptr[:-1]] = -1.0  # negative diagonal
    with pytest.raises(DegenerateGeometryError):
        chol.refactor(bad)
    chol.refactor(good)
    b = np.ones(pattern2.size)
    np.testing.assert_allclose(pattern2.matvec(good, chol.solve(b)), b, atol=1e-8)


def test_released_values_are_needed_only_after_a_read_out(rng):
    """After ``release_values`` the factor still solves; once read out (selected inversion,
    trailing blocks) it asks for values instead of silently factoring stale ones."""
    pattern, data = _random_normal_matrix(rng, n=60, m=200)
    chol = SparseCholesky(pattern, data)
    chol.release_values()
    b = rng.standard_normal(pattern.size)
    x = chol.solve(b)
    np.testing.assert_allclose(pattern.matvec(data, x), b, atol=1e-8)
    chol.trailing_lower(6)
    with pytest.raises(DegenerateGeometryError, match='refactor'):
        chol.solve(b)
    chol.refactor(data)
    np.testing.assert_allclose(chol.solve(b), x, rtol=1e-10, atol=1e-12)


def _connections(rng, n: int, m: int):
    src = rng.integers(0, n, m)
    dst = (src + rng.integers(1, n, m)) % n
    z = rng.standard_normal((m, 6))
    A = rng.standard_normal((m, 6, 6))
    cov = A @ np.swapaxes(A, 1, 2) + np.eye(6)
    return src, dst, z, cov


def test_bulk_connections_equal_single_insertions(rng):
    """``add_connections`` on a new network stores arrays only; the network equals one filled a
    connection at a time, and the duplicate rules hold for connections added afterwards."""
    n, m = 30, 200
    src, dst, z, cov = _connections(rng, n, m)
    bulk, single = ConnectionNetwork(), ConnectionNetwork()
    for net in (bulk, single):
        for i in range(n):
            net.add_node(100 + i, i // 10)
    bulk.add_connections(100 + src, 100 + dst, z, cov)
    assert bulk._src is None  # no per-connection Python objects
    for k in range(m):
        single.add_connection(100 + src[k], 100 + dst[k], z[k], cov[k])
    a, b = bulk.arrays(), single.arrays()
    for f in ('src', 'dst', 'z', 'cov'):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))
    assert bulk.n_connections == single.n_connections == m
    with pytest.raises(NetworkError, match='re-delivered'):
        bulk.add_connection(100 + src[5], 100 + dst[5], z[5], cov[5])
    k = bulk.add_connection(100 + src[5], 100 + dst[5], z[5] + 1.0, cov[5])
    assert k == m and bulk.n_connections == m + 1
    np.testing.assert_array_equal(bulk.arrays().z[m], z[5] + 1.0)


def test_bulk_insertion_is_atomic_and_validated(rng):
    """A bad connection in a later bulk insertion adds none of them; an array-stored network
    keeps its connections."""
    n, m = 20, 50
    src, dst, z, cov = _connections(rng, n, m)
    net = ConnectionNetwork()
    for i in range(n):
        net.add_node(i)
    net.add_connections(src, dst, z, cov)
    before = net.arrays()
    z_bad = z.copy()
    z_bad[7, 2] = np.nan
    with pytest.raises(Exception, match='NaN'):
        net.add_connections(src, dst, z_bad, cov)
    cov_dup = cov.copy()
    with pytest.raises(NetworkError, match='re-delivered'):
        net.add_connections(src[:3], dst[:3], z[:3], cov_dup[:3])
    after = net.arrays()
    assert net.n_connections == m
    np.testing.assert_array_equal(after.z, before.z)
    net.add_connections(src[:3], dst[:3], z[:3] + 1.0, cov[:3])
    assert net.n_connections == m + 3


def test_network_from_arrays_keeps_arrays_only(rng):
    """``from_arrays`` keeps the given arrays (no per-connection lists) until a connection is
    added; then both agree."""
    n, m = 15, 40
    src, dst, z, cov = _connections(rng, n, m)
    net = ConnectionNetwork.from_arrays(np.arange(n), np.zeros(n, np.int64), src, dst, z, cov)
    assert net._src is None and net.n_connections == m
    net.add_connection(0, 1, np.ones(6), np.eye(6))
    c = net.arrays()
    assert net.n_connections == m + 1
    np.testing.assert_array_equal(c.src[:m], src)
    np.testing.assert_array_equal(c.cov[:m], cov)
    np.testing.assert_array_equal(c.z[m], np.ones(6))
