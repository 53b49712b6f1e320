"""Helpers for users: an F2F initial guess, the between-factor cost of a network and its normal
matrix at given poses."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import models
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver.config import SolverConfig
from ga_ros.core.solver.linearise import _inv_spd
from ga_ros.core.solver.priors import GaussianPrior, _PriorData
from ga_ros.core.solver.problem import _Problem
from ga_ros.geometry import se3
from ga_ros.runtime import lazy_import

sp = lazy_import('scipy.sparse')  # only some functions need it (start-up)

# ------------------------------------------------------------------------ helpers for users
def initial_guess_f2f(network: ConnectionNetwork,
                      T_world_first: FloatArray | None = None) -> FloatArray:
    """Frame-to-frame (F2F) initial poses: chain the measured motions along a spanning tree.

    The tree prefers connections between nodes adjacent in insertion order (consecutive
    frames), so on a survey it is exactly the F2F integration of the consecutive motions.

    Returns
    -------
    (n, 4, 4) poses ``T_world_node``; the first node is at ``T_world_first`` (identity default).
    """
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree  # lazy: start-up

    n = network.n_nodes
    T = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    if T_world_first is not None:
        T[0] = T_world_first
    conn = network.arrays()
    if n <= 1 or len(conn) == 0:
        return T
    network.check_connected([int(network.node_ids[0])])
    gap = np.abs(conn.dst - conn.src).astype(float)
    G = sp.coo_matrix((gap + 1e-9 * np.arange(len(conn)) / len(conn), (conn.src, conn.dst)),
                      shape=(n, n)).tocsr()
    tree = minimum_spanning_tree(G)
    tree = tree + tree.T
    order, pred = breadth_first_order(tree, 0, directed=False, return_predecessors=True)
    # measured motion for each (parent -> child) tree edge
    lookup: dict[tuple[int, int], int] = {}
    for k in range(len(conn)):
        lookup.setdefault((int(conn.src[k]), int(conn.dst[k])), k)
    T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    for child in order[1:]:
        parent = int(pred[child])
        k = lookup.get((parent, int(child)))
        if k is not None:
            T[child] = T[parent] @ T_meas[k]
        else:
            T[child] = T[parent] @ se3.inverse(T_meas[lookup[(int(child), parent)]])
    return T


def connection_cost(network: ConnectionNetwork, T_world_node: FloatArray) -> float:
    """``sum e' Omega e`` over connections, ``e = log(T_meas^-1 T_i^-1 T_j)`` in
    ``[rho, phi]`` order and ``Omega = cov^-1`` (the g2o/GTSAM between-factor cost)."""
    conn = network.arrays()
    T = np.asarray(T_world_node, dtype=float)
    T_meas = se3.from_translation_rotvec(conn.z[:, :3], conn.z[:, 3:])
    e = se3.log(se3.inverse(T_meas) @ se3.inverse(T[conn.src]) @ T[conn.dst])
    return float(np.einsum('mi,mij,mj->', e, _inv_spd(conn.cov), e))


def normal_matrix_at(network: ConnectionNetwork, T: FloatArray, model: str = 'se3',
                     fixed: Sequence[int] = (),
                     priors: Sequence[GaussianPrior] = (),
                     weights: FloatArray | None = None,
                     measured: tuple[FloatArray, FloatArray] | None = None,
                     jit: bool = False
                     ) -> tuple[sp.csc_matrix, IntArray, FloatArray]:
    """Normal matrix ``N = A' M^-1 A`` and ``u = A' M^-1 w`` (+ prior terms) linearised at ``T``.

    Unlike :func:`solve`, no datum is required and nothing is factored, so ``N`` may be
    singular; it is what marginalisation (Schur complements) works on. ``weights`` (m, 6, 6)
    ``cov^-1`` and ``measured`` (the measured motions ``T_src_dst`` and their inverses, (m, 4, 4)
    each) of the network's connections, in its order, where the caller has them (as
    :func:`solve` takes them: the same values, not computed again). ``jit``: linearise with the
    compiled se3 kernels (as :func:`solve`'s ``jit``: the caller has loaded them; the same
    values to rounding, ~1e-16 relative).

    Returns
    -------
    N : (d u, d u) symmetric CSC over the free nodes.
    free_ids : (u,) ids of the free nodes, in the order of ``N``'s blocks.
    u : (d u,) half the gradient of the cost at ``T`` (the Gauss-Newton step is ``-N^-1 u``).
    """
    d = models.dof(model)
    conn = network.arrays()
    free = np.ones(network.n_nodes, dtype=bool)
    if len(fixed):
        free[network.indices_of(list(fixed))] = False
    prior_data = [_PriorData.build(network, p, d) for p in priors]
    prob = _Problem.build(model, conn, prior_data, SolverConfig(model=model), free, P=weights,
                          measured=measured)
    prob.jit = jit
    T = np.asarray(T, dtype=float)
    sysd = prob.linear_system(T, prob.consistent(T, prob.zero_residuals()))
    pattern = prob.pattern
    return pattern.full_csc(sysd.normal_values(pattern)), network.node_ids[free], sysd.u
