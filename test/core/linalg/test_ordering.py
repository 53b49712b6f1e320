"""Fill-reducing orderings of the block graph (ga_ros.core.linalg.ordering)."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.linalg import ordering

pytestmark = pytest.mark.skipif(not ordering.HAVE_METIS, reason='pymetis is not installed')


def _grid(k: int, dim: int = 2) -> tuple[int, np.ndarray, np.ndarray]:
    """A k x k (x k) grid graph, each vertex linked to its axis neighbours, edges once each."""
    idx = np.arange(k ** dim).reshape((k,) * dim)
    rows, cols = [], []
    for ax in range(dim):
        rows.append(np.delete(idx, 0, axis=ax).ravel())
        cols.append(np.delete(idx, k - 1, axis=ax).ravel())
    return k ** dim, np.concatenate(rows), np.concatenate(cols)


def test_factor_flops_equal_a_dense_cholesky(rng):
    n, rows, cols = _grid(7)
    order = rng.permutation(n)
    A = np.eye(n)
    A[rows, cols] = A[cols, rows] = -1.0
    A += np.diag(-A.sum(axis=1) + 1.0)  # Laplacian + I
    L = np.linalg.cholesky(A[np.ix_(order, order)])
    counts = (np.abs(L) > 1e-12).sum(axis=0).astype(float)
    assert ordering.factor_flops(n, rows, cols, order) == pytest.approx(np.sum(counts ** 2))


@pytest.mark.parametrize('dim', [2, 3])
def test_the_order_with_fewer_flops_is_kept_on_large_graphs(dim):
    from ga_ros.core.linalg.blocks import BlockPattern
    from ga_ros.core.linalg.ordering import _block_amd

    n, rows, cols = _grid(64 if dim == 2 else 16, dim)  # 4096 >= METIS_MIN_BLOCKS: both tried
    assert n >= ordering.METIS_MIN_BLOCKS
    nd = ordering.nested_dissection(n, rows, cols)
    np.testing.assert_array_equal(np.sort(nd), np.arange(n))
    diag = np.arange(n)
    pattern = BlockPattern(np.concatenate([rows, diag]), np.concatenate([cols, diag]), 1, n)
    amd = _block_amd(pattern, np.ones(n, dtype=bool))
    best = ordering.best_block_order(n, rows, cols, amd)
    flops = {k: ordering.factor_flops(n, rows, cols, o) for k, o in (('nd', nd), ('amd', amd))}
    np.testing.assert_array_equal(best, nd if flops['nd'] < flops['amd'] else amd)
    if dim == 3:  # a 3-D mesh is nested dissection's textbook case (here about half the work)
        assert flops['nd'] < 0.8 * flops['amd']


def test_small_graphs_keep_amd():
    n, rows, cols = _grid(10)
    amd = np.arange(n)[::-1].copy()
    assert ordering.best_block_order(n, rows, cols, amd) is amd


def test_solve_with_nested_dissection_equals_solve_with_amd(rng, monkeypatch):
    from solver_problems import make_problem, perturbed

    from ga_ros.core.solver import SolverConfig, solve
    prob = make_problem(rng, 'se3', n=40, noise=5.0)
    T0 = perturbed(rng, prob.T_true, 0.05)
    cfg = SolverConfig(damping='dogleg', tolerance=1e-10)
    ordering._ORDERINGS.clear()
    ref = solve(prob.network, T0, cfg)
    used = []

    def nested(n, rows, cols, amd, analysis=None):
        used.append((amd, ordering.nested_dissection(n, rows, cols)))
        return used[-1][1]

    monkeypatch.setattr(ordering, 'best_block_order', nested)
    ordering._ORDERINGS.clear()
    nd = solve(prob.network, T0, cfg)
    ordering._ORDERINGS.clear()
    assert used and not np.array_equal(*used[0])  # another ordering was used
    np.testing.assert_allclose(nd.T_world_node, ref.T_world_node, atol=1e-9)
    assert nd.cost == pytest.approx(ref.cost, rel=1e-9)


def test_analysis_flops_equal_the_numeric_factor_and_adjacency_scipys(rng):
    """The flops of CHOLMOD's symbolic analysis equal ``sum c_j^2`` of the numeric factor's
    columns (the fallback) for random orders; the NumPy adjacency given to METIS equals
    ``scipy.sparse``'s (duplicates and self-loops dropped, both directions)."""
    import scipy.sparse as sp

    from ga_ros.core.linalg.cholmod import _direct_cholmod

    if _direct_cholmod() is None:
        pytest.skip('the direct CHOLMOD call is not available')
    n, rows, cols = _grid(9)
    rows = np.concatenate([rows, rows[:5], [3]])  # a duplicate edge and a self-loop
    cols = np.concatenate([cols, cols[:5], [3]])
    off = rows != cols
    r, c = np.maximum(rows[off], cols[off]), np.minimum(rows[off], cols[off])
    for _ in range(3):
        order = rng.permutation(n)
        assert ordering.factor_flops(n, rows, cols, order, _direct_cholmod().analysis_flops) \
            == pytest.approx(ordering._numeric_factor_flops(n, r, c, order), rel=1e-12)
    xadj, adjncy = ordering._adjacency(n, rows, cols)
    G = sp.csr_matrix((np.ones(2 * r.size), (np.concatenate([r, c]), np.concatenate([c, r]))),
                      shape=(n, n))
    G.sum_duplicates()
    G.sort_indices()
    np.testing.assert_array_equal(xadj, G.indptr)
    np.testing.assert_array_equal(adjncy, G.indices)
