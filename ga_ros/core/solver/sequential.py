"""The sequential solution (paper Sec. III-D): information form and covariance form."""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core import models
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver.config import SolverConfig
from ga_ros.core.solver.iterate import solve
from ga_ros.core.solver.linearise import _consistent_residuals
from ga_ros.core.solver.result import SolveResult
from ga_ros.errors import InputError, NetworkError


# ------------------------------------------------------------------- sequential (Sec. III-D)
def sequential_update(previous: SolveResult, group2: ConnectionNetwork, T_init: FloatArray,
                      config: SolverConfig | None = None) -> SolveResult:
    """Sequential solution (paper Sec. III-D, information form of docs/method.md Sec. 4).

    Group 1 is represented only by ``previous`` (its estimate ``x1`` and normal matrix ``N1``);
    its observations are not used again. ``group2`` holds the new observations; it must contain
    every node of ``previous`` (same ids) and may add new nodes (new unknowns ``y``).

    Parameters
    ----------
    previous : result of the group-1 solution (carries ``x1`` and ``N1``).
    group2 : network of all nodes (old and new) with only the new connections.
    T_init : (n, 4, 4) initial poses in ``group2`` index order: the previous estimate for old nodes
        and e.g. an F2F extrapolation for new ones.
    config : solver settings (the model must match ``previous``).
    """
    cfg = config or SolverConfig(model=previous.model)
    if cfg.model != previous.model:
        raise InputError(f"model {cfg.model!r} differs from the previous solution's "
                         f'{previous.model!r}')
    missing = np.setdiff1d(previous.node_ids, group2.node_ids)
    if missing.size:
        raise NetworkError(f'group 2 must contain every node of the previous solution; missing '
                           f'{missing[:10].tolist()}')
    sysm = previous._system
    fixed = [int(i) for i in sysm.node_ids[~sysm.free]]
    return solve(group2, T_init, cfg, fixed=fixed, priors=[previous.prior()])


def covariance_form_update(previous: SolveResult, group2: ConnectionNetwork,
                           config: SolverConfig | None = None) -> tuple[FloatArray, FloatArray]:
    """One sequential step in covariance form (docs/method.md Sec. 4), no new unknowns.

    ``K = Q1 A2' (M2 + A2 Q1 A2')^-1``, ``x2 = x1 - K w2(x1)``, ``Q2 = Q1 - K A2 Q1``.

    Dense in the number of unknowns: meant for small problems and for checking the information
    form (:func:`sequential_update`), which is what the package uses.

    Returns
    -------
    T_world_node : (n, 4, 4) updated poses (group-2 index order, equal to ``previous`` order).
    Q2 : (u, u) updated cofactor matrix of the free unknowns.
    """
    cfg = config or SolverConfig(model=previous.model)
    if not np.array_equal(np.sort(previous.node_ids), np.sort(group2.node_ids)) or \
            group2.n_nodes != previous.node_ids.size:
        raise InputError('the covariance form handles no new unknowns: group 2 must have '
                         'exactly the nodes of the previous solution')
    sysm = previous._system
    d = sysm.d
    order = group2.indices_of(previous.node_ids)
    T1 = np.empty_like(previous.T_world_node)
    T1[order] = previous.T_world_node
    free = np.zeros(group2.n_nodes, dtype=bool)
    free[order[sysm.free]] = True
    col = np.full(group2.n_nodes, -1, dtype=np.int64)
    col[order[sysm.free]] = np.arange(int(sysm.free.sum()))
    N1 = previous.normal_matrix.toarray()
    Q1 = np.linalg.inv(N1)
    conn = group2.arrays()
    o = models.observations_per_connection(cfg.model)
    v0 = _consistent_residuals(cfg.model, T1, conn, np.zeros((len(conn), o)))
    lin = models.linearise(cfg.model, T1, conn.src, conn.dst, conn.z, v0)
    m, r = lin.f.shape
    A2 = np.zeros((m * r, Q1.shape[0]))
    rows = np.arange(m * r).reshape(m, r)
    for k in range(m):
        for node, Ablk in ((conn.src[k], lin.A_src[k]), (conn.dst[k], lin.A_dst[k])):
            if col[node] >= 0:
                A2[rows[k][:, None], col[node] * d + np.arange(d)] += Ablk
    M2 = np.zeros((m * r, m * r))
    Mb = lin.B @ models.observation_covariance(cfg.model, conn.cov) @ np.swapaxes(lin.B, 1, 2)
    for k in range(m):
        M2[rows[k][:, None], rows[k]] = Mb[k]
    w2 = (lin.f - (lin.B @ v0[:, :, None])[:, :, 0]).reshape(-1)  # w = f + B (l_b - l0)
    K = Q1 @ A2.T @ np.linalg.inv(M2 + A2 @ Q1 @ A2.T)
    dx = -K @ w2
    Q2 = Q1 - K @ A2 @ Q1
    T2 = models.retract(cfg.model, T1, np.nonzero(free)[0], dx.reshape(-1, d)[col[free]])
    return T2, 0.5 * (Q2 + Q2.T)
