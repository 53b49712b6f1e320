"""Per connection: redundancy numbers, Baarda's w-tests with the minimal detectable biases
(internal reliability), the multi-dimensional connection test, and the test of connections
outside the adjustment."""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import models
from ga_ros.core.network import ConnectionArrays
from ga_ros.core.quality.cofactors import propagate
from ga_ros.core.quality.config import b_method_alpha
from ga_ros.runtime import lazy_import

stats = lazy_import('scipy.stats')  # only the statistical tests need it (start-up)

#: Eigenvalues of the whitened ``Q_kk`` block below this count as zero redundancy.
_RANK_TOL = 1e-6


def redundancy_numbers(cov: FloatArray, B: FloatArray, Linv: FloatArray, G: FloatArray, r_c: int
                ) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Whitened ``Qw = I - L^-1 G L^-T``, ``Q_kk`` and the redundancy numbers.

    Returns
    -------
    ``Qw``, ``Q_kk``, the per-component and the per-connection redundancy numbers.
    """
    Qw = np.eye(r_c) - Linv @ G @ np.swapaxes(Linv, 1, 2)
    Qw = 0.5 * (Qw + np.swapaxes(Qw, 1, 2))
    LinvT = np.swapaxes(Linv, 1, 2)
    Q_kk = LinvT @ Qw @ Linv
    BT = np.swapaxes(B, 1, 2)
    R = cov @ BT @ Q_kk @ B  # (Q_vv P)_ii
    red_comp = np.einsum('mjj->mj', R)
    red = np.trace(Qw, axis1=1, axis2=2)
    return Qw, Q_kk, red_comp, red


def w_tests(cov: FloatArray, B: FloatArray, Q_kk: FloatArray, Pv: FloatArray, lam0: float
             ) -> tuple[FloatArray, FloatArray]:
    """w-test and MDB per observation component (``P Q_vv P = B' Q_kk B``)."""
    BT = np.swapaxes(B, 1, 2)
    var_pv = np.einsum('mjj->mj', BT @ Q_kk @ B)
    scale = np.maximum(np.abs(np.linalg.inv(cov)).max(axis=(1, 2)), 1e-300)
    ok = var_pv > _RANK_TOL * scale[:, None]
    w = np.where(ok, Pv / np.sqrt(np.where(ok, var_pv, 1.0)), 0.0)
    mdb = np.where(ok, np.sqrt(lam0 / np.where(ok, var_pv, 1.0)), np.inf)
    return w, mdb


def connection_tests(Linv: FloatArray, B: FloatArray, v: FloatArray, Qw: FloatArray,
                      lam0: float, power: float) -> tuple[FloatArray, IntArray, FloatArray]:
    """Connection test ``T = k_w' Qw^+ k_w`` with ``k_w = L^-1 B v``.

    Returns
    -------
    The statistics, their degrees of freedom and B-method critical values.
    """
    kw = (Linv @ (B @ v[:, :, None]))[:, :, 0]
    evals, evecs = np.linalg.eigh(Qw)
    keep = evals > _RANK_TOL
    proj = np.einsum('mji,mj->mi', evecs, kw)
    stat = np.sum(np.where(keep, proj ** 2 / np.where(keep, evals, 1.0), 0.0), axis=1)
    q = keep.sum(axis=1).astype(np.int64)
    stat = np.where(q > 0, stat, np.nan)
    crit = np.full(len(v), np.nan)
    for qq in np.unique(q[q > 0]):
        crit[q == qq] = stats.chi2.isf(b_method_alpha(lam0, power, int(qq)), int(qq))
    return stat, q, crit


def outside_tests(model: str, T: FloatArray, outside: ConnectionArrays, ocs: IntArray,
                   ocd: IntArray, Sigma_o: FloatArray, r_c: int, lam0: float, power: float
                   ) -> tuple[FloatArray, FloatArray]:
    """Test of connections outside the adjustment: statistics and critical values."""
    lo = models.linearise(model, T, outside.src, outside.dst, outside.z,
                          np.zeros_like(outside.z))
    C = lo.B @ outside.cov @ np.swapaxes(lo.B, 1, 2)
    C = C + propagate(lo.A_src, lo.A_dst, ocs, ocd, Sigma_o)
    out_stat = np.einsum('mi,mi->m', lo.f, np.linalg.solve(C, lo.f[:, :, None])[:, :, 0])
    out_crit = np.full(len(outside), stats.chi2.isf(b_method_alpha(lam0, power, r_c), r_c))
    return out_stat, out_crit
