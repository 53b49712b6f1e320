"""Selected inversion (banded, and on the sparse Cholesky factor) against the dense inverse."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.linalg.selinv import SelectedInverse, banded_marginal_blocks, supernodes


def _random_graph_spd(rng, u, d, extra):
    pairs = [(i, i + 1) for i in range(u - 1)]
    pairs += [tuple(sorted(rng.choice(u, 2, replace=False))) for _ in range(extra)]
    N = np.zeros((u * d, u * d))
    for i, j in pairs:
        J = rng.normal(size=(d, 2 * d))
        idx = np.r_[i * d:(i + 1) * d, j * d:(j + 1) * d]
        N[np.ix_(idx, idx)] += J.T @ J
    N[:d, :d] += np.eye(d)
    return N


def test_blocks_equal_dense_inverse(rng):
    for u, d, extra in ((40, 6, 30), (25, 3, 10), (1, 6, 0)):
        N = _random_graph_spd(rng, u, d, extra)
        blocks = banded_marginal_blocks(sp.csr_matrix(N), d)
        inv = np.linalg.inv(N)
        ref = np.stack([inv[i * d:(i + 1) * d, i * d:(i + 1) * d] for i in range(u)])
        np.testing.assert_allclose(blocks, ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())


def test_wanted_subset_equals_dense_inverse(rng):
    u, d = 60, 6
    N = _random_graph_spd(rng, u, d, 20)
    inv = np.linalg.inv(N)
    wanted = np.array([0, 3, 7, 41])
    blocks = banded_marginal_blocks(sp.csr_matrix(N), d, wanted=wanted)
    for i in wanted:
        np.testing.assert_allclose(blocks[i], inv[i * d:(i + 1) * d, i * d:(i + 1) * d],
                                   rtol=1e-8, atol=1e-12)


def test_principal_axis_ordering_gives_the_same_blocks(rng):
    """A strip of nodes (a 3 x 30 grid): ordered along its long axis."""
    d, rows, cols = 3, 3, 30
    u = rows * cols
    xy = np.array([(c, r, 0.0) for r in range(rows) for c in range(cols)])
    N = np.eye(u * d)
    for i in range(u):
        for j in range(i + 1, u):
            if np.abs(xy[i] - xy[j]).max() <= 1:
                J = rng.normal(size=(d, 2 * d))
                idx = np.r_[i * d:(i + 1) * d, j * d:(j + 1) * d]
                N[np.ix_(idx, idx)] += J.T @ J
    inv = np.linalg.inv(N)
    blocks = banded_marginal_blocks(sp.csr_matrix(N), d, coords=xy)
    ref = np.stack([inv[i * d:(i + 1) * d, i * d:(i + 1) * d] for i in range(u)])
    np.testing.assert_allclose(blocks, ref, rtol=1e-8, atol=1e-12)


def test_gives_up_when_band_too_wide(rng):
    N = _random_graph_spd(rng, 30, 6, 200)
    assert banded_marginal_blocks(sp.csr_matrix(N), 6, max_band=12) is None


def test_dense_border_nodes_give_the_same_blocks(rng):
    """A chain whose last nodes share a dense joint prior (a frozen track's Schur complement):
    they are ordered last as a dense border; every block still equals the dense inverse."""
    d, u, k = 6, 80, 20
    N = _random_graph_spd(rng, u, d, 0)
    # nodes 0..k-1 are also linked to the chain every other node, the prior over them is dense
    prior_nodes = np.arange(k)
    J = rng.normal(size=(k * d, k * d))
    idx = (prior_nodes[:, None] * d + np.arange(d)).ravel()
    N[np.ix_(idx, idx)] += J.T @ J / k
    for i in prior_nodes:
        j = k + 3 * i
        Jc = rng.normal(size=(d, 2 * d))
        ij = np.r_[i * d:(i + 1) * d, j * d:(j + 1) * d]
        N[np.ix_(ij, ij)] += Jc.T @ Jc
    inv = np.linalg.inv(N)
    ref = np.stack([inv[i * d:(i + 1) * d, i * d:(i + 1) * d] for i in range(u)])
    blocks = banded_marginal_blocks(sp.csr_matrix(N), d)
    np.testing.assert_allclose(blocks, ref, rtol=1e-8, atol=1e-10 * np.abs(ref).max())
    wanted = np.array([25, 50, 79, 3])
    blocks = banded_marginal_blocks(sp.csr_matrix(N), d, wanted=wanted)
    np.testing.assert_allclose(blocks[wanted], ref[wanted], rtol=1e-8,
                               atol=1e-10 * np.abs(ref).max())


def _selected(N: np.ndarray, d: int, copy: bool = False) -> SelectedInverse:
    pattern, data = BlockPattern.from_matrix(sp.csr_matrix(N), d)
    si = SelectedInverse(SparseCholesky(pattern, data), copy=copy)
    assert si.in_place != copy  # CHOLMOD's supernodal factor is recognised
    return si


def _block_pairs(N: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray]:
    """Node pairs (both orders) with a non-zero block in ``N``, diagonal included."""
    u = N.shape[0] // d
    nz = np.abs(N.reshape(u, d, u, d)).sum(axis=(1, 3)) > 0
    return np.nonzero(nz)


def test_sparse_factor_blocks_equal_dense_inverse(rng):
    """Diagonal blocks and the blocks of every connected pair (both orders), on random graphs
    (block sizes 6 and 3, a single node, a chain, many extra edges), equal the dense inverse:
    in CHOLMOD's supernodal factor in place and on the ``getfactor`` copy."""
    cases = ((40, 6, 30), (25, 3, 10), (1, 6, 0), (60, 6, 0), (30, 6, 200))
    for (u, d, extra), copy in zip(cases + cases, [False] * 5 + [True] * 5):
        N = _random_graph_spd(rng, u, d, extra) + 0.1 * np.eye(u * d)  # a chain is ill-posed
        inv = np.linalg.inv(N)
        si = _selected(N, d, copy)
        rows, cols = _block_pairs(N, d)
        ref = np.stack([inv[i * d:(i + 1) * d, j * d:(j + 1) * d] for i, j in zip(rows, cols)])
        np.testing.assert_allclose(si.blocks(rows, cols), ref, rtol=1e-8,
                                   atol=1e-10 * np.abs(inv).max())
        diag = si.diagonal_blocks(np.arange(u)[::-1])
        ref = np.stack([inv[i * d:(i + 1) * d, i * d:(i + 1) * d] for i in range(u)][::-1])
        np.testing.assert_allclose(diag, ref, rtol=1e-8, atol=1e-10 * np.abs(inv).max())
        np.testing.assert_array_equal(diag, np.swapaxes(diag, 1, 2))


def test_sparse_factor_agrees_with_banded_path(rng):
    """The two selected inversions give the same blocks on a strip (3 x 40 grid) with a dense
    joint prior over its first nodes (the shape of a survey with a frozen boundary)."""
    d, u, k = 6, 120, 12
    N = _random_graph_spd(rng, u, d, 0)
    for i in range(u - 3):
        J = rng.normal(size=(d, 2 * d))
        idx = np.r_[i * d:(i + 1) * d, (i + 3) * d:(i + 4) * d]
        N[np.ix_(idx, idx)] += J.T @ J
    J = rng.normal(size=(k * d, k * d))
    N[:k * d, :k * d] += J.T @ J / k
    banded = banded_marginal_blocks(sp.csr_matrix(N), d)
    sparse = _selected(N, d).diagonal_blocks(np.arange(u))
    np.testing.assert_allclose(sparse, banded, rtol=1e-9, atol=1e-12 * np.abs(banded).max())


def test_sparse_factor_refuses_blocks_off_the_pattern(rng):
    import pytest

    from ga_ros.errors import DegenerateGeometryError

    # a chain: nodes 0 and 29 are not connected (a ridge: the bare chain of rank-6 links is
    # numerically singular for this seed, and the factorisation refused it before the test)
    N = _random_graph_spd(rng, 30, 6, 0) + 0.1 * np.eye(180)
    si = _selected(N, 6)
    with pytest.raises(DegenerateGeometryError, match='pattern'):
        si.blocks(np.array([29]), np.array([0]))


def test_supernodes_of_a_factor_pattern():
    """An arrow (every column linked to the last) is one supernode per column but the last two;
    a dense lower triangle is one supernode; their columns share the rows below them."""
    n = 5
    dense = sp.csc_matrix(np.tril(np.ones((n, n))))
    np.testing.assert_array_equal(supernodes(dense.indptr, dense.indices), [0, n])
    arrow = np.eye(n)
    arrow[n - 1, :] = 1.0
    A = sp.csc_matrix(arrow)
    np.testing.assert_array_equal(supernodes(A.indptr, A.indices), [0, 1, 2, 3, n])


def test_python_kernels_give_the_compiled_blocks(rng, monkeypatch):
    """Without numba (or with ``GA_ROS_JIT=0``) the same kernels run as Python: same blocks."""
    import ga_ros.core.linalg.selinv as selinv

    N = _random_graph_spd(rng, 12, 6, 8) + 0.1 * np.eye(72)
    inv = np.linalg.inv(N)
    monkeypatch.setattr(selinv, '_KERNELS', {'_takahashi': selinv._takahashi_py,
                                             '_offsets': selinv._offsets_py})
    for copy in (False, True):
        si = _selected(N, 6, copy)
        rows, cols = _block_pairs(N, 6)
        ref = np.stack([inv[i * 6:i * 6 + 6, j * 6:j * 6 + 6] for i, j in zip(rows, cols)])
        np.testing.assert_allclose(si.blocks(rows, cols), ref, rtol=1e-8,
                                   atol=1e-10 * np.abs(inv).max())


def test_supernodes_inverted_in_place_equal_the_copying_path(rng, monkeypatch):
    """The compiled kernels invert each supernode of CHOLMOD's supernodal factor where it lies
    (``_in_place_step_blas``: leading dimension its row count, no copies of its columns); the
    values equal, bit for bit, those of the path that copies the columns out and back, on a
    factor with wide supernodes (halved triangles, several panels) and rows below them."""
    import ga_ros.core.linalg.selinv as selinv

    if not selinv.COMPILED:
        pytest.skip('the in-place step needs the compiled kernels')
    u, d = 100, 6
    N = np.zeros((u * d, u * d))
    for block in (slice(0, 60 * d), slice(40 * d, u * d)):  # two cliques sharing 20 nodes
        J = rng.normal(size=(N[block, block].shape[0],) * 2)
        N[block, block] += J @ J.T / J.shape[0] + 0.5 * np.eye(J.shape[0])
    rows, cols = _block_pairs(N, d)
    si = _selected(N, d)
    assert selinv._IN_PLACE
    widths = np.diff(si._lay.starts)
    assert widths.max() > 2 * selinv._TRTRI_LEAF
    assert ((widths > selinv._PANEL) & (si._lay.nrows > widths)).any()  # panels, rows below
    in_place = si.blocks(rows, cols)
    monkeypatch.setattr(selinv, '_IN_PLACE', False)
    np.testing.assert_array_equal(_selected(N, d).blocks(rows, cols), in_place)
    inv = np.linalg.inv(N)
    ref = np.stack([inv[i * d:(i + 1) * d, j * d:(j + 1) * d] for i, j in zip(rows, cols)])
    np.testing.assert_allclose(in_place, ref, rtol=1e-8, atol=1e-10 * np.abs(inv).max())


def test_wide_supernodes_equal_the_dense_inverse(rng):
    """A dense coupling of 70 nodes is one supernode of 420 columns: its triangle is inverted by
    halves (wider than ``_TRTRI_LEAF``), and its blocks and those of a chain hanging below it
    still equal the dense inverse."""
    import ga_ros.core.linalg.selinv as selinv

    u, d = 100, 6
    N = _random_graph_spd(rng, u, d, 0) + 0.1 * np.eye(u * d)
    J = rng.normal(size=(70 * d, 70 * d))
    N[-70 * d:, -70 * d:] += J @ J.T / (70 * d)  # the last 70 nodes, all coupled
    si = _selected(N, d)
    assert np.diff(si._lay.starts).max() > 2 * selinv._TRTRI_LEAF
    inv = np.linalg.inv(N)
    rows, cols = _block_pairs(N, d)
    ref = np.stack([inv[i * d:(i + 1) * d, j * d:(j + 1) * d] for i, j in zip(rows, cols)])
    np.testing.assert_allclose(si.blocks(rows, cols), ref, rtol=1e-8,
                               atol=1e-10 * np.abs(inv).max())


def test_selected_columns_invert_only_their_ancestors(rng):
    """``columns``: only the supernodes of those nodes and their ancestors are inverted; every
    block among those nodes (diagonal and connected pairs) equals the dense inverse, on the
    in-place factor and the copy, and a block outside them is refused."""
    import pytest

    from ga_ros.errors import DegenerateGeometryError

    u, d = 90, 6
    N = _random_graph_spd(rng, u, d, 0) + 0.1 * np.eye(u * d)
    for i in range(u - 3):  # a strip: most supernodes are not ancestors of a few nodes
        J = rng.normal(size=(d, 2 * d))
        idx = np.r_[i * d:(i + 1) * d, (i + 3) * d:(i + 4) * d]
        N[np.ix_(idx, idx)] += J.T @ J
    inv = np.linalg.inv(N)
    cols = np.arange(20, 35)
    pattern, data = BlockPattern.from_matrix(sp.csr_matrix(N), d)
    for copy in (False, True):
        si = SelectedInverse(SparseCholesky(pattern, data), copy=copy, columns=cols)
        assert 0.0 < si.inverted < 1.0
        rows, cl = _block_pairs(N, d)
        keep = np.isin(rows, cols) & np.isin(cl, cols)
        ref = np.stack([inv[i * d:(i + 1) * d, j * d:(j + 1) * d]
                        for i, j in zip(rows[keep], cl[keep])])
        np.testing.assert_allclose(si.blocks(rows[keep], cl[keep]), ref, rtol=1e-8,
                                   atol=1e-10 * np.abs(inv).max())
        outside = np.setdiff1d(np.arange(u), cols)
        with pytest.raises(DegenerateGeometryError, match='selected columns'):
            si.diagonal_blocks(outside)


def test_path_solves_give_the_dense_inverse_and_leave_the_factor(rng):
    """Few nodes' diagonal blocks by forward solves along their elimination-tree paths equal
    the dense inverse, on random graphs (block sizes 6 and 3, a chain, many extra edges, one
    node); the factor stays usable (a solve afterwards is unchanged)."""
    from ga_ros.core.linalg.selinv import path_marginal_blocks

    for u, d, extra in ((40, 6, 30), (25, 3, 10), (1, 6, 0), (60, 6, 0), (30, 6, 200)):
        N = _random_graph_spd(rng, u, d, extra) + 0.1 * np.eye(u * d)
        inv = np.linalg.inv(N)
        chol = SparseCholesky(*BlockPattern.from_matrix(sp.csr_matrix(N), d))
        b = rng.normal(size=u * d)
        x0 = chol.solve(b)
        nodes = np.unique(np.r_[0, u - 1, rng.choice(u, min(u, 4), replace=False)])
        got = path_marginal_blocks(chol, nodes)
        ref = np.stack([inv[i * d:(i + 1) * d, i * d:(i + 1) * d] for i in nodes])
        np.testing.assert_allclose(got, ref, rtol=1e-9, atol=1e-12 * np.abs(inv).max())
        np.testing.assert_array_equal(got, np.swapaxes(got, 1, 2))
        np.testing.assert_array_equal(chol.solve(b), x0)


def test_path_solves_give_way_to_full_solves_where_the_paths_are_long(rng):
    """``cheaper_than_solve``: on a long chain the path of a node deep in the elimination tree
    visits many supernodes, so the path solves decline (None) and the caller solves; where the
    estimate keeps the paths (a node near the root), the blocks equal the dense inverse."""
    from ga_ros.core.linalg import selinv

    u, d = 400, 6
    N = _random_graph_spd(rng, u, d, 0) + 0.1 * np.eye(u * d)
    chol = SparseCholesky(*BlockPattern.from_matrix(sp.csr_matrix(N), d))
    chol.solve(np.ones(u * d))  # factored
    lay = selinv._supernodal_layout(chol._F, chol.n)
    pos = np.empty_like(lay.perm)
    pos[lay.perm] = np.arange(lay.perm.size)
    visits = {c: selinv._path_visits(lay, pos, np.array([c]), d) for c in range(u)}
    n_super = lay.starts.size - 1
    assert all(1 <= v <= n_super for v in visits.values())
    flops = 4 * lay.x.size * d
    deep = [c for c, v in visits.items() if v * selinv.PATH_VISIT_FLOPS > flops]
    short = [c for c, v in visits.items() if v * selinv.PATH_VISIT_FLOPS <= flops]
    assert deep and short  # a long chain has both
    assert selinv.path_marginal_blocks(chol, np.array(deep[:3]), cheaper_than_solve=True) is None
    inv = np.linalg.inv(N)
    got = selinv.path_marginal_blocks(chol, np.array(short[:1]), cheaper_than_solve=True)
    c = short[0]
    np.testing.assert_allclose(got[0], inv[c * d:(c + 1) * d, c * d:(c + 1) * d], rtol=1e-9,
                               atol=1e-12 * np.abs(inv).max())


def test_the_block_inverse_is_scipys_solve_triangular_bit_for_bit():
    # banded._lower_inverse calls LAPACK's trtrs as scipy.linalg.solve_triangular does, without
    # its per-call checks: the same bits for C- and Fortran-ordered factors, the same errors
    from scipy.linalg import solve_triangular

    from ga_ros.core.linalg import banded

    rng = np.random.default_rng(5)
    for b in (1, 6, 12, 48):
        eye = np.eye(b)
        for _ in range(20):
            M = rng.normal(size=(b, b))
            D = np.linalg.cholesky(M @ M.T + 1e-3 * np.eye(b))
            for F in (D, np.asfortranarray(D)):
                np.testing.assert_array_equal(banded._lower_inverse(F, eye),
                                              solve_triangular(F, eye, lower=True))
    D[1, 1] = 0.0
    with pytest.raises(np.linalg.LinAlgError):
        banded._lower_inverse(D, eye)
    D[1, 1] = np.nan
    with pytest.raises(ValueError):
        banded._lower_inverse(D, eye)


def test_flops_of_the_supernodes(rng):
    """:func:`supernodal_flops`: a dense matrix is one supernode, ``n^3/3`` to factor and
    ``2 n^3/3`` to invert; on a sparse factor the count is ``sum_j c_j^2`` over its columns
    (``c_j`` the rows of column ``j``, read from the factor's copy) up to lower-order terms; an
    inversion restricted to some columns counts only the supernodes it inverted."""
    from ga_ros.core.linalg.selinv import _csc_layout, supernodal_flops

    d = 6
    J = rng.normal(size=(40 * d, 30 * d))
    dense = J.T @ J + np.eye(30 * d)
    pattern, data = BlockPattern.from_matrix(sp.csr_matrix(dense), d)
    si = SelectedInverse(SparseCholesky(pattern, data))
    n = 30 * d
    assert si.flops == pytest.approx((n ** 3 / 3, 2 * n ** 3 / 3))
    N = _random_graph_spd(rng, 120, d, 150) + 0.1 * np.eye(120 * d)
    pattern, data = BlockPattern.from_matrix(sp.csr_matrix(N), d)
    lay = _csc_layout(SparseCholesky(pattern, data))  # every stored entry, zeros included
    width = np.diff(lay.starts)
    k = np.repeat(np.arange(width.size), width)
    counts = lay.nrows[k] - (np.arange(k.size) - lay.starts[k])  # rows of each column
    factor, inverse = supernodal_flops(lay.starts, lay.nrows)
    assert factor == pytest.approx(float(np.sum(counts.astype(float) ** 2)), rel=0.05)
    assert inverse == pytest.approx(2 * factor, rel=0.05)
    part = SelectedInverse(SparseCholesky(pattern, data), columns=np.arange(10, 20))
    assert part.flops[0] == pytest.approx(factor)
    assert 0 < part.flops[1] < inverse
    assert part.flops[1] == pytest.approx(supernodal_flops(lay.starts, lay.nrows,
                                                           part.need)[1])
