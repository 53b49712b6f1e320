"""The large-problem paths of the batch solve: assembly and linearisation in parts."""

from __future__ import annotations

import numpy as np
import pytest
from solver_problems import make_problem, perturbed

from ga_ros.core import models
from ga_ros.core.linalg import blocks as assembly
from ga_ros.core.linalg.blocks import BlockPattern
from ga_ros.core.solver import GaussianPrior, SolverConfig, normal_matrix_at, problem, solve


def test_chunked_assembly_equals_one_pass(rng, monkeypatch):
    """``BlockPattern.assemble`` in chunks (large problems) sums the same values as in one
    pass, with fixed (-1) and upper (dropped) blocks among them."""

    u, d, k = 30, 6, 400
    rows = rng.integers(-1, u, size=k)
    cols = rng.integers(-1, u, size=k)
    rows = np.concatenate([rows, np.arange(u)])
    cols = np.concatenate([cols, np.arange(u)])
    pattern = BlockPattern(rows, cols, d, u)
    blocks = rng.normal(size=(rows.size, d, d))
    one = pattern.assemble(blocks)
    monkeypatch.setattr(assembly, '_ASSEMBLY_CHUNK', 7)
    np.testing.assert_allclose(pattern.assemble(blocks), one, rtol=1e-13, atol=1e-13)
    dense = np.zeros((u * d, u * d))
    for r, c, b in zip(rows, cols, blocks):
        if r >= c >= 0:
            dense[r * d:(r + 1) * d, c * d:(c + 1) * d] += b
    np.testing.assert_allclose(np.tril(pattern.lower_csc(one).toarray()), np.tril(dense),
                               atol=1e-12)


def test_assemble_at_in_disjoint_parts_equals_assemble(rng):
    """Blocks added a part at a time (any disjoint parts, any order) sum to ``assemble``."""
    u, d, k = 20, 3, 300
    rows = np.concatenate([rng.integers(-1, u, size=k), np.arange(u)])
    cols = np.concatenate([rng.integers(-1, u, size=k), np.arange(u)])
    pattern = BlockPattern(rows, cols, d, u)
    blocks = rng.normal(size=(rows.size, d, d))
    out = np.zeros(pattern.nnz)
    for part in np.array_split(rng.permutation(rows.size), 6):
        pattern.assemble_at(blocks[part], part, out)
    np.testing.assert_allclose(out, pattern.assemble(blocks), rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize('model, loss, damping', [('se3', 'none', 'none'),
                                                  ('se3', 'cauchy', 'lm'),
                                                  ('se2', 'huber', 'dogleg')])
def test_solve_linearised_in_parts_equals_one_pass(rng, monkeypatch, model, loss, damping):
    """The connections linearised and assembled a few at a time (large problems) give the same
    adjustment as in one pass: estimate, cost, variance factor, weights, covariances, with a
    prior and robust losses; ``normal_matrix_at`` too."""
    prob = make_problem(rng, model, n=14, noise=1.0, gaps=(1, 2, 5))
    net = prob.network
    T0 = perturbed(rng, prob.T_true, 0.02)
    ids = net.node_ids
    prior = GaussianPrior.from_covariances(ids[3:5], prob.T_true[3:5],
                                           np.stack([np.eye(models.dof(model))] * 2))
    cfg = SolverConfig(model=model, robust_loss=loss, damping=damping, tolerance=1e-10)
    ref = solve(net, T0, cfg, priors=[prior], fixed=[int(ids[0])])
    N_ref = normal_matrix_at(net, ref.T_world_node, model, fixed=[int(ids[0])])[0]
    monkeypatch.setattr(problem, '_PARTS_ABOVE', 5)
    monkeypatch.setattr(problem, '_CONNECTIONS_PER_PART', 5)
    res = solve(net, T0, cfg, priors=[prior], fixed=[int(ids[0])])
    np.testing.assert_allclose(res.T_world_node, ref.T_world_node, rtol=0, atol=1e-10)
    assert res.iterations == ref.iterations
    np.testing.assert_allclose(res.cost, ref.cost, rtol=1e-9)
    np.testing.assert_allclose(res.sigma0_sq, ref.sigma0_sq, rtol=1e-9)
    np.testing.assert_allclose(res.weights, ref.weights, rtol=1e-9)
    np.testing.assert_allclose(res.covariance(ids[1:]), ref.covariance(ids[1:]), rtol=1e-8,
                               atol=1e-14)
    N = normal_matrix_at(net, ref.T_world_node, model, fixed=[int(ids[0])])[0]
    np.testing.assert_allclose(N.toarray(), N_ref.toarray(), rtol=1e-12, atol=1e-9)


def test_positions_computed_equal_kept_positions(rng, monkeypatch):
    """Large patterns compute their entries' positions when assembling instead of keeping
    them: ``assemble`` (one pass, in chunks) and ``assemble_at`` give the same values."""
    u, d, k = 25, 6, 500
    rows = np.concatenate([rng.integers(-1, u, size=k), np.arange(u)])
    cols = np.concatenate([rng.integers(-1, u, size=k), np.arange(u)])
    blocks = rng.normal(size=(rows.size, d, d))
    kept = BlockPattern(rows, cols, d, u)
    monkeypatch.setattr(assembly, '_POSITIONS_KEPT_BELOW', 0)
    computed = BlockPattern(rows, cols, d, u)
    assert kept._pos is not None and computed._pos is None
    np.testing.assert_array_equal(computed.indices, kept.indices)
    one = kept.assemble(blocks)
    np.testing.assert_array_equal(computed.assemble(blocks), one)
    parts = [np.zeros(kept.nnz), np.zeros(kept.nnz)]
    for idx in np.array_split(rng.permutation(rows.size), 5):
        kept.assemble_at(blocks[idx], idx, parts[0])
        computed.assemble_at(blocks[idx], idx, parts[1])
    np.testing.assert_array_equal(parts[1], parts[0])
    monkeypatch.setattr(assembly, '_ASSEMBLY_CHUNK', 7)
    np.testing.assert_array_equal(computed.assemble(blocks), kept.assemble(blocks))


def test_normal_matrix_at_with_the_compiled_kernels_equals_numpy(rng, monkeypatch):
    """``normal_matrix_at(jit=True)`` (the freeze's absorbed terms) linearises in the compiled
    se3 kernel from the first call and gives the NumPy linearisation's ``N`` and ``u`` to
    rounding, with a joint prior among the terms."""
    from ga_ros.core import kernels

    if not kernels.AVAILABLE:
        pytest.skip('the compiled kernels are not available')
    prob = make_problem(rng, 'se3', n=14, noise=1.0, gaps=(1, 2, 5))
    net, ids = prob.network, prob.network.node_ids
    T = perturbed(rng, prob.T_true, 0.05)
    prior = GaussianPrior.from_covariances(ids[3:6], prob.T_true[3:6], np.stack([np.eye(6)] * 3))
    calls = []
    compiled = kernels.se3_system
    monkeypatch.setattr(kernels, 'se3_system',
                        lambda *a, **k: calls.append(1) or compiled(*a, **k))
    N_np, free_np, u_np = normal_matrix_at(net, T, 'se3', fixed=[int(ids[0])], priors=[prior])
    assert not calls  # one linearisation: NumPy unless asked
    N_jit, free_jit, u_jit = normal_matrix_at(net, T, 'se3', fixed=[int(ids[0])], priors=[prior],
                                              jit=True)
    assert calls
    np.testing.assert_array_equal(free_jit, free_np)
    scale = np.abs(N_np.toarray()).max()
    np.testing.assert_allclose(N_jit.toarray(), N_np.toarray(), rtol=1e-12, atol=1e-12 * scale)
    np.testing.assert_allclose(u_jit, u_np, rtol=1e-12, atol=1e-12 * np.abs(u_np).max())
