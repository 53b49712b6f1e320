"""The compiled se3 kernels against the NumPy reference (geometry.se3 / models.between)."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core import kernels, models
from ga_ros.geometry import se3, so3

pytestmark = pytest.mark.skipif(not kernels.AVAILABLE, reason='numba is not installed')


def _case(rng, m=60, n=20):
    """Poses and measurements whose misclosures are random, near identity and near pi."""
    T = se3.exp(rng.normal(scale=[3, 3, 3, 1, 1, 1], size=(n, 6)))
    src = rng.integers(0, n, size=m)
    dst = (src + rng.integers(1, n, size=m)) % n
    E = rng.normal(scale=[1, 1, 1, 0.5, 0.5, 0.5], size=(m, 6))
    E[: m // 4, 3:] *= 1e-7                       # near identity
    axis = rng.normal(size=(m // 4, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    E[m // 4: m // 2, 3:] = axis * (np.pi - rng.uniform(0, 5e-3, size=(m // 4, 1)))
    T_meas = se3.inverse(se3.exp(E)) @ se3.inverse(T[src]) @ T[dst]  # so that log(...) = E
    L = rng.normal(scale=0.3, size=(m, 6, 6)) + 2 * np.eye(6)
    P = L @ np.swapaxes(L, 1, 2)
    return T, src, dst, T_meas, P


@pytest.fixture(autouse=True)
def _always_compiled(monkeypatch):
    monkeypatch.setattr(kernels, 'MIN_CONNECTIONS', 0)
    monkeypatch.setattr(kernels, 'AFTER_ITERATIONS', 0)


def test_se3_kernels_equal_the_numpy_reference(rng):
    T, src, dst, T_meas, P = _case(rng)
    Tm_inv = np.ascontiguousarray(se3.inverse(T_meas))
    e, blocks, gi, gj, maha = kernels.se3_system(T, src, dst, Tm_inv, P)
    ref = models.between('se3', T, src, dst, T_meas)
    np.testing.assert_allclose(e, ref.e, atol=1e-9)
    np.testing.assert_allclose(kernels.se3_misclosure(T, src, dst, Tm_inv), ref.e, atol=1e-9)
    # independent products: J_i = -J Ad, J_j = J
    J_i, J_j = -ref.Jr_inv @ ref.Ad_ji, ref.Jr_inv
    tr = np.swapaxes
    m = src.size
    for k, (Ja, Jb) in enumerate(((J_i, J_i), (J_i, J_j), (J_j, J_i), (J_j, J_j))):
        np.testing.assert_allclose(blocks[k * m:(k + 1) * m], tr(Ja, 1, 2) @ P @ Jb,
                                   rtol=1e-8, atol=1e-8)
    Pe = (P @ ref.e[:, :, None])
    np.testing.assert_allclose(gi, (tr(J_i, 1, 2) @ Pe)[:, :, 0], rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(gj, (tr(J_j, 1, 2) @ Pe)[:, :, 0], rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(maha, np.einsum('mi,mi->m', ref.e, Pe[:, :, 0]), rtol=1e-10)


def test_se3_kernel_log_near_pi_round_trips(rng):
    axis = rng.normal(size=(50, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    w = axis * (np.pi - rng.uniform(0, 1e-2, size=(50, 1)))
    T = se3.from_rt(so3.exp(w), rng.normal(size=(50, 3)))
    eye = np.broadcast_to(np.eye(4), (50, 4, 4)).copy()
    idx = np.arange(50)
    e = kernels.se3_misclosure(np.concatenate([eye[:1], T]), np.zeros(50, dtype=np.int64),
                               idx + 1, eye)
    np.testing.assert_allclose(se3.exp(e), T, atol=1e-9)


@pytest.mark.parametrize('robust_loss', ['none', 'cauchy'])
def test_solve_with_the_kernels_equals_solve_without(rng, monkeypatch, robust_loss):
    from solver_problems import make_problem, perturbed

    from ga_ros.core.solver import SolverConfig, solve
    prob = make_problem(rng, 'se3', n=12, noise=5.0)
    T0 = perturbed(rng, prob.T_true, 0.1)
    cfg = SolverConfig(damping='dogleg', robust_loss=robust_loss, tolerance=1e-10)
    fast = solve(prob.network, T0, cfg)
    monkeypatch.setattr(kernels, 'AVAILABLE', False)
    ref = solve(prob.network, T0, cfg)
    k = min(len(fast.cost_history), len(ref.cost_history))  # the last step is below 1e-10
    # once the cost is flat to rounding (1e-15 relative), when a step is refused depends on
    # the order of the floating-point operations (NumPy columns against the compiled loop)
    assert abs(fast.iterations - ref.iterations) <= 2
    np.testing.assert_allclose(fast.cost_history[:k], ref.cost_history[:k], rtol=1e-9)
    np.testing.assert_allclose(fast.T_world_node, ref.T_world_node, atol=1e-9)
    np.testing.assert_allclose(fast.residuals, ref.residuals, atol=1e-9)
    np.testing.assert_allclose(fast.covariance(prob.network.node_ids[1:4]),
                               ref.covariance(prob.network.node_ids[1:4]), rtol=1e-7, atol=1e-12)


def test_se3_prior_kernel_equals_the_numpy_prior_terms(rng):
    """kernels.se3_prior against _add_priors' NumPy terms (independent: models.prior_residual,
    a sparse product for H e, stacked products for the blocks): residuals at random, near
    identity and near-pi rotations, a fixed node, zero blocks in the information."""
    import scipy.sparse as sp

    from ga_ros.core.solver.priors import _add_priors, _PriorData

    n, k = 30, 9
    T = se3.exp(rng.normal(scale=[5, 5, 5, 1, 1, 1], size=(n, 6)))
    idx = np.sort(rng.choice(n, k, replace=False))
    E = rng.normal(scale=[1, 1, 1, 0.5, 0.5, 0.5], size=(k, 6))
    E[:3, 3:] *= 1e-7  # near identity
    axis = rng.normal(size=(3, 3))
    E[3:6, 3:] = axis / np.linalg.norm(axis, axis=1, keepdims=True) * (np.pi - 2e-3)
    T_mean = T[idx] @ se3.inverse(se3.exp(E))
    A = rng.normal(size=(6 * k, 6 * k))
    H = A @ A.T
    H[:6, 18:] = H[18:, :6] = 0.0  # blocks absent from the pattern
    Hb = sp.bsr_matrix(H, blocksize=(6, 6))
    Hb.sort_indices()
    rows = np.repeat(np.arange(k), np.diff(Hb.indptr))
    pd = _PriorData(idx, T_mean, Hb.data, rows, Hb.indices.astype(np.int64), H, None, Hb)
    col = np.arange(n) - 1  # node 0 fixed
    u_ref = rng.normal(size=(n - 1, 6))
    u = u_ref.copy()
    blocks_ref, blocks = [], []
    cost_ref = _add_priors('se3', T, [pd], col, u_ref, blocks_ref)
    cost = _add_priors('se3', T, [pd], col, u, blocks, compiled=True)
    assert cost == pytest.approx(cost_ref, rel=1e-12)
    np.testing.assert_allclose(u, u_ref, rtol=1e-12, atol=1e-12 * np.abs(u_ref).max())
    np.testing.assert_allclose(blocks[0], blocks_ref[0], rtol=1e-12,
                               atol=1e-12 * np.abs(blocks_ref[0]).max())
    u2 = u_ref.copy()  # the gradient alone
    assert _add_priors('se3', T, [pd], col, u2, None, compiled=True) == cost


def test_se3_retract_kernel_equals_columns_retract(rng):
    """kernels.se3_retract bit for bit as columns.retract (the same operations per pose), and
    ``None`` (the caller's fallback with the SVD projection) for a rotation off by > 1e-6."""
    from ga_ros.core import columns

    T = se3.exp(rng.normal(scale=[50, 50, 50, 2, 2, 2], size=(300, 6)))
    for scale in (1e-9, 1e-5, 0.1, 3.0):
        xi = rng.normal(scale=scale, size=(300, 6))
        assert np.array_equal(kernels.se3_retract(T, xi), columns.retract(T, xi))
    bad = T.copy()
    bad[7, :3, :3] *= 1.0 + 1e-5
    assert kernels.se3_retract(bad, np.zeros((300, 6))) is None


def test_scatter_rows_equals_bincount(rng):
    """kernels.scatter_rows bit for bit as the per-column np.bincount of _scatter_gradient."""
    from ga_ros.core.solver.linearise import _scatter_gradient

    u = rng.normal(size=(200, 6))
    c = rng.integers(-1, 200, size=2000)
    g = rng.normal(size=(2000, 6))
    ref, out = u.copy(), u.copy()
    _scatter_gradient(ref, c, g)
    kernels.scatter_rows(out, c, g)
    assert np.array_equal(out, ref)
