"""The se3 linearisation in columns (core.columns) against the stacked reference
(models.between) and against central differences on the manifold."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core import columns, models
from ga_ros.geometry import se3


def _case(rng, m=60):
    """One connection per pair of nodes (src k, dst m + k): random, near-identity and near-pi
    misclosures; random SPD weights."""
    T = se3.exp(rng.normal(scale=[3, 3, 3, 1, 1, 1], size=(2 * m, 6)))
    src, dst = np.arange(m), np.arange(m, 2 * m)
    E = rng.normal(scale=[1, 1, 1, 0.5, 0.5, 0.5], size=(m, 6))
    E[: m // 4, 3:] *= 1e-7                       # near identity
    axis = rng.normal(size=(m // 4, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    E[m // 4: m // 2, 3:] = axis * (np.pi - rng.uniform(0, 5e-3, size=(m // 4, 1)))
    T_meas = se3.inverse(T[src]) @ T[dst] @ se3.inverse(se3.exp(E))  # so that log(...) = E
    L = rng.normal(scale=0.3, size=(m, 6, 6)) + 2 * np.eye(6)
    P = L @ np.swapaxes(L, 1, 2)
    return T, src, dst, T_meas, P, E


def _blocks(Ji, Jj, P):
    tr = np.swapaxes
    return [tr(Ja, 1, 2) @ P @ Jb for Ja, Jb in ((Ji, Ji), (Ji, Jj), (Jj, Ji), (Jj, Jj))]


def test_misclosure_equals_the_stacked_reference(rng):
    T, src, dst, T_meas, _, E = _case(rng)
    meas = columns.MeasuredInverse.of(se3.inverse(T_meas))
    e = columns.misclosure(T, src, dst, meas).e
    np.testing.assert_allclose(e, models.motion_misclosure('se3', T, src, dst, T_meas),
                               rtol=0, atol=1e-9)
    np.testing.assert_allclose(se3.exp(e), se3.exp(E), atol=1e-9)  # near pi: same rotation


@pytest.mark.parametrize('robust', [False, True])
def test_normal_blocks_equal_the_stacked_reference(rng, robust):
    T, src, dst, T_meas, P, _ = _case(rng)
    m = len(src)
    bt = models.between('se3', T, src, dst, T_meas)
    w = rng.uniform(0.1, 1.0, size=m)
    nb = columns.linearise(T, src, dst, columns.MeasuredInverse.of(se3.inverse(T_meas)),
                           columns.SqrtWeights.of(P),
                           (lambda r2: w) if robust else None).normal_blocks()
    Pw = P * w[:, None, None] if robust else P
    Ji, Jj = -bt.Jr_inv @ bt.Ad_ji, bt.Jr_inv
    for k, ref in enumerate(_blocks(Ji, Jj, Pw)):
        np.testing.assert_allclose(nb.blocks[k * m:(k + 1) * m], ref, rtol=1e-9,
                                   atol=1e-9 * np.abs(ref).max())
    Pe = (Pw @ bt.e[:, :, None])
    np.testing.assert_allclose(nb.g_src, (np.swapaxes(Ji, 1, 2) @ Pe)[:, :, 0], atol=1e-8)
    np.testing.assert_allclose(nb.g_dst, (np.swapaxes(Jj, 1, 2) @ Pe)[:, :, 0], atol=1e-8)
    np.testing.assert_allclose(nb.maha2, np.einsum('mi,mij,mj->m', bt.e, P, bt.e), rtol=1e-10)


def test_normal_blocks_match_central_differences(rng):
    """``J_a`` by central differences of ``e`` under ``T_a exp(h u_k)``; the blocks
    ``J_a' P J_b`` must agree (near-pi misclosures excluded: the log's branch cut)."""
    T, src, dst, T_meas, P, _ = _case(rng)
    keep = np.r_[0:15, 30:60]
    src, dst, T_meas, P = src[keep], dst[keep], T_meas[keep], P[keep]
    m = len(keep)
    meas = columns.MeasuredInverse.of(se3.inverse(T_meas))
    h = 1e-6
    J = {}
    for name, nodes in (('i', src), ('j', dst)):
        cols = []
        for k in range(6):
            step = np.zeros((len(nodes), 6))
            step[:, k] = h
            plus, minus = T.copy(), T.copy()
            plus[nodes] = T[nodes] @ se3.exp(step)
            minus[nodes] = T[nodes] @ se3.exp(-step)
            cols.append((columns.misclosure(plus, src, dst, meas).e
                         - columns.misclosure(minus, src, dst, meas).e) / (2 * h))
        J[name] = np.stack(cols, axis=2)
    nb = columns.linearise(T, src, dst, meas, columns.SqrtWeights.of(P)).normal_blocks()
    for k, ref in enumerate(_blocks(J['i'], J['j'], P)):
        np.testing.assert_allclose(nb.blocks[k * m:(k + 1) * m], ref, rtol=1e-5,
                                   atol=1e-5 * np.abs(ref).max())


def _planar_case(rng, m=60):
    """2-D poses and measured motions (random, near-identity and near-pi headings) with
    random SPD 3x3 weights."""
    from ga_ros.geometry import se2

    T = se2.exp(rng.normal(scale=[3, 3, 2], size=(2 * m, 3)))
    src, dst = np.arange(m), np.arange(m, 2 * m)
    E = rng.normal(scale=[1, 1, 0.5], size=(m, 3))
    E[: m // 4, 2] *= 1e-7
    E[m // 4: m // 2, 2] = np.pi - rng.uniform(1e-3, 5e-3, size=m // 4)
    T_meas = se3.inverse(T[src]) @ T[dst] @ se3.inverse(se2.exp(E))
    L = rng.normal(scale=0.3, size=(m, 3, 3)) + 2 * np.eye(3)
    return T, src, dst, T_meas, L @ np.swapaxes(L, 1, 2)


@pytest.mark.parametrize('robust', [False, True])
def test_planar_normal_blocks_equal_the_stacked_reference(rng, robust):
    T, src, dst, T_meas, P = _planar_case(rng)
    m = len(src)
    bt = models.between('se2', T, src, dst, T_meas)
    w = rng.uniform(0.1, 1.0, size=m)
    nb = columns.planar_linearise(T, src, dst, T_meas, P,
                                  (lambda r2: w) if robust else None).normal_blocks(2)
    assert nb.blocks.shape == (4 * m + 2, 3, 3)
    Pw = P * w[:, None, None] if robust else P
    Ji, Jj = -bt.Jr_inv @ bt.Ad_ji, bt.Jr_inv
    for k, ref in enumerate(_blocks(Ji, Jj, Pw)):
        np.testing.assert_allclose(nb.blocks[k * m:(k + 1) * m], ref, rtol=1e-9,
                                   atol=1e-9 * np.abs(ref).max())
    Pe = Pw @ bt.e[:, :, None]
    np.testing.assert_allclose(nb.e, bt.e, rtol=0, atol=1e-12)
    np.testing.assert_allclose(nb.g_src, (np.swapaxes(Ji, 1, 2) @ Pe)[:, :, 0], atol=1e-8)
    np.testing.assert_allclose(nb.g_dst, (np.swapaxes(Jj, 1, 2) @ Pe)[:, :, 0], atol=1e-8)
    np.testing.assert_allclose(nb.maha2, np.einsum('mi,mij,mj->m', bt.e, P, bt.e), rtol=1e-10)


def test_planar_sqrt_weights_factor_the_weights(rng):
    _, _, _, _, P = _planar_case(rng)
    U = columns._planar_sqrt_weights(P).transpose(2, 0, 1)
    np.testing.assert_allclose(np.swapaxes(U, 1, 2) @ U, P, rtol=1e-12, atol=1e-12)
    assert np.all(np.tril(U, -1) == 0)


def test_retract_equals_the_stacked_reference(rng):
    """``T exp(xi)`` in columns against :func:`se3.retract`: tiny, ordinary and large
    increments, and poses whose rotations drifted from orthonormal (the Bjorck step and the SVD
    projection)."""
    T = se3.exp(rng.normal(scale=[3, 3, 3, 1, 1, 1], size=(90, 6)))
    T[60:, :3, :3] *= 1 + rng.uniform(1e-9, 1e-3, size=(30, 1, 1))  # drifted rotations
    xi = rng.normal(size=(90, 6)) * np.repeat([1e-9, 1e-3, 2.0], 30)[:, None]
    got = columns.retract(T, xi)
    np.testing.assert_allclose(got, se3.retract(T, xi), rtol=0, atol=1e-12)
    R = got[:, :3, :3]
    np.testing.assert_allclose(np.swapaxes(R, 1, 2) @ R, np.broadcast_to(np.eye(3), R.shape),
                               atol=1e-12)
    np.testing.assert_array_equal(got[:, 3], np.broadcast_to([0, 0, 0, 1.0], (90, 4)))
