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
    nb = columns.normal_blocks(T, src, dst, columns.MeasuredInverse.of(se3.inverse(T_meas)),
                               columns.SqrtWeights.of(P), (lambda r2: w) if robust else None)
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
    nb = columns.normal_blocks(T, src, dst, meas, columns.SqrtWeights.of(P))
    for k, ref in enumerate(_blocks(J['i'], J['j'], P)):
        np.testing.assert_allclose(nb.blocks[k * m:(k + 1) * m], ref, rtol=1e-5,
                                   atol=1e-5 * np.abs(ref).max())
