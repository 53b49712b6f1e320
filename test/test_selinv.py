"""Selected inversion against the dense inverse."""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from ga_ros.core.selinv import banded_marginal_blocks


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
