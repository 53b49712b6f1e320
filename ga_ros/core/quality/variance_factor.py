"""The global test of the variance factor: the weighted cost ``v' P v`` (priors included), the
redundancy and ``chi2_{1-alpha}(r - u)``."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core import models
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior
from ga_ros.runtime import lazy_import

stats = lazy_import('scipy.stats')  # only the statistical tests need it (start-up)


def global_cost(network: ConnectionNetwork, model: str, T: FloatArray, v: FloatArray,
                 Pv: FloatArray, priors: Sequence[GaussianPrior], n_eq: int
                 ) -> tuple[float, int]:
    """The weighted cost ``v' P v`` plus the priors', and the number of equations."""
    cost = float(np.einsum('mi,mi->', v, Pv))
    for p in priors:
        idx = network.indices_of(p.node_ids)
        e, _ = models.prior_residual(model, T[idx], np.asarray(p.T_world_node, dtype=float))
        info = p.information
        ev = e.reshape(-1)
        cost += float(ev @ (info @ ev))
        dense = info.toarray() if hasattr(info, 'toarray') else np.asarray(info)
        # a prior adds as many equations as the rank of its information (as in solve)
        n_eq += int(np.linalg.matrix_rank(0.5 * (dense + dense.T), hermitian=True))
    return cost, n_eq


def global_test(cost: float, redundancy: int, alpha: float) -> tuple[float, float, bool]:
    """The global test of the variance factor (``sigma_prior = 1``).

    Returns
    -------
    ``sigma0^2 = cost / (r - u)``, the critical value ``chi2_{1-alpha}(r - u)`` and whether the
    test passes (``cost <= critical``); NaN, NaN, False without redundancy.
    """
    sigma0_sq = cost / redundancy if redundancy > 0 else float('nan')
    g_crit = float(stats.chi2.isf(alpha, redundancy)) if redundancy > 0 else float('nan')
    return sigma0_sq, g_crit, bool(redundancy > 0 and cost <= g_crit)
