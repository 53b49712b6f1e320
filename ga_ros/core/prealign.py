"""Pre-alignment of a new track before the window adjustment (paper Sec. III-D).

The paper's sequential update adjusts a second group of unknowns from the estimate of the
first: the unknowns of the first group start at their previous estimate, those of the second
(the new track's nodes) from the first group's. Online, the new track arrives as its
frame-to-frame chain, dead-reckoned from the previous track's end; at 10 % noise on the aerial
survey it has drifted 10-16 m by its end, so a Gauss-Newton iteration of the whole window
started there takes a first step of that size and needs two or three numeric factorisations of
the window to converge.

:func:`prealign` first solves the new track's nodes alone: their connections (the consecutive
ones along the track, the cross connections to the already adjusted nodes and the one to the
previous track's end) with every other node held fixed at its previous estimate. That problem
is small and banded (the new track's nodes only: 1,224 unknowns for a 204-pose double track
against 6,732 for the window), so its iterations cost a few milliseconds each. Its solution is
the new track's conditional optimum given the previous estimate. The window's optimum still
differs from it along the survey's weak bending modes (on the aerial survey at 10 % noise the
window's first correction is 1.5-11 m), but the window's Gauss-Newton iteration now starts
inside its basin: the factorisation at its start stays usable for the following steps (chord
steps, :attr:`~ga_ros.core.solver.SolverConfig.reuse_factor_below`), so a window update takes
one numeric factorisation as a rule. Without the pre-alignment the chord steps diverge.

When the new track's connections form a tree hanging off the held nodes (one per new node:
its consecutive motions and the link to the previous track, no cross connection, as in an
odometry survey with fixes), the conditional optimum is the chain itself, every connection
satisfied exactly: it is chained from the held nodes without a solve (``reason`` ``'tree'``).

The pre-alignment changes only the starting point of the window adjustment, never its
optimum: the window is still solved to the same tolerance with every connection and prior.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.linalg.cholesky import SparseCholesky
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.errors import GaError
from ga_ros.geometry import se3

#: Settings of the pre-alignment solve: one Gauss-Newton step (measured: one step moves the
#: window's result as much as 2-10 steps do), with the step and cost tolerances and the chord
#: threshold of a longer solve should ``max_iterations`` be raised. Only the window's starting
#: point depends on them.
PREALIGN_SOLVER = SolverConfig(max_iterations=1, tolerance=1e-4, cost_tolerance=1e-6,
                               reuse_factor_below=0.5)


@dataclass(frozen=True)
class Prealignment:
    """Outcome of :func:`prealign`.

    Attributes
    ----------
    T_world_node : (n, 4, 4) poses of every node of the network (index order): the free nodes
        at their conditional optimum, the others as given.
    iterations : Gauss-Newton iterations of the pre-alignment solve (0: not run).
    reason : the solve's stop reason, ``'tree'`` (the free nodes' connections form a tree
        hanging off the held nodes: its exact solution, chained, no solve), ``'no_anchor'``
        (no connection from a free node to a held node: nothing to align against),
        ``'nothing_free'``, or ``'failed: ...'`` (the solve raised; the poses are then the
        given ones and the window adjustment reports the problem itself).
    n_free : free nodes (the new track's).
    n_connections : connections of the pre-alignment problem.
    factor : the solve's sparse factor (:meth:`~ga_ros.core.solver.SolveResult.release_factor`),
        for the next pre-alignment's ``factor`` (the pattern repeats track to track: its
        symbolic analysis is reused), or ``None``.
    """

    T_world_node: FloatArray
    iterations: int
    reason: str
    n_free: int
    n_connections: int
    factor: SparseCholesky | None = None


def prealign(network: ConnectionNetwork, T_init: FloatArray, free_idx: IntArray,
             config: SolverConfig = PREALIGN_SOLVER, weights: FloatArray | None = None,
             jit: bool = False, factor: SparseCholesky | None = None,
             measured: tuple[FloatArray, FloatArray] | None = None) -> Prealignment:
    """Solve the nodes ``free_idx`` of ``network`` alone, every other node held at ``T_init``.

    Parameters
    ----------
    network : the window's connections (index order of ``T_init``).
    T_init : (n, 4, 4) starting poses ``T_world_node`` of every node of ``network``.
    free_idx : (k,) indices (into the network's nodes) of the nodes to adjust, e.g. the new
        track's, which start at their dead-reckoned chain.
    config : solver settings (:data:`PREALIGN_SOLVER`); the model must be ``'se3'``.
    weights : (m, 6, 6) weights ``S^-1`` of every connection of ``network`` when the caller
        has them (the window aligner's), else computed.
    jit : the compiled se3 kernels from the first linearisation (:func:`~ga_ros.core.solver.
        solve`'s ``jit``).
    factor : the previous pre-alignment's :attr:`Prealignment.factor` (``solve``'s
        ``factor``: its symbolic analysis is reused if the pattern is the same).
    measured : ``(T_meas, T_meas^-1)``, (m, 4, 4) each, of every connection of ``network``
        when the caller has them (:func:`~ga_ros.core.solver.solve`'s ``measured``).

    Returns
    -------
    Prealignment
        The poses of every node (only the free ones changed) and the solve's summary.
    """
    T = np.asarray(T_init, dtype=float)
    free_idx = np.unique(np.asarray(free_idx, dtype=np.int64))
    n = network.n_nodes
    if free_idx.size == 0:
        return Prealignment(T, 0, 'nothing_free', 0, 0)
    conn = network.arrays()
    is_free = np.zeros(n, dtype=bool)
    is_free[free_idx] = True
    sel = np.nonzero(is_free[conn.src] | is_free[conn.dst])[0]
    held = np.zeros(n, dtype=bool)
    held[conn.src[sel]] = True
    held[conn.dst[sel]] = True
    held &= ~is_free
    if not held.any():
        return Prealignment(T, 0, 'no_anchor', int(free_idx.size), int(sel.size))
    if sel.size == free_idx.size:  # as many connections as free nodes: maybe a tree
        chained = _tree_chain(T, is_free, conn.src[sel], conn.dst[sel],
                              None if measured is None else measured[0][sel],
                              None if measured is None else measured[1][sel], conn.z[sel])
        if chained is not None:
            return Prealignment(chained, 0, 'tree', int(free_idx.size), int(sel.size), factor)
    nodes = np.concatenate([free_idx, np.nonzero(held)[0]])
    local = np.full(n, -1, dtype=np.int64)
    local[nodes] = np.arange(nodes.size)
    ids = network.node_ids
    sub = ConnectionNetwork.from_arrays(ids[nodes], network.track_ids[nodes],
                                        local[conn.src[sel]], local[conn.dst[sel]],
                                        conn.z[sel], conn.cov[sel])
    try:
        res = solve(sub, T[nodes], config, fixed=ids[nodes[free_idx.size:]].tolist(),
                    jit=jit, weights=None if weights is None else weights[sel], factor=factor,
                    measured=None if measured is None else (measured[0][sel], measured[1][sel]))
    except GaError as exc:
        return Prealignment(T, 0, f'failed: {exc}', int(free_idx.size), int(sel.size))
    out = T.copy()
    out[free_idx] = res.T_world_node[:free_idx.size]
    return Prealignment(out, res.iterations, res.reason, int(free_idx.size), int(sel.size),
                        res.release_factor())


def _tree_chain(T: FloatArray, is_free: np.ndarray, src: IntArray, dst: IntArray,
                T_meas: FloatArray | None, T_meas_inv: FloatArray | None,
                z: FloatArray) -> FloatArray | None:
    """The free nodes chained from the held ones along their connections ``src -> dst``
    (``T_dst = T_src T_meas``), when those connections (one per free node) form a tree
    hanging off the held nodes: every free node then has one path to a held node, and the
    chained poses satisfy every connection exactly, the least-squares optimum with zero
    residuals whatever the weights (the new track's dead-reckoned chain, without a cross
    connection). ``None`` if they do not (a cycle, or a part not reached from a held node).
    ``T_meas`` / ``T_meas_inv``: the measured motions and their inverses (computed from the
    measurements ``z`` if not given)."""
    if T_meas is None:
        T_meas = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
        T_meas_inv = se3.inverse(T_meas)
    edges: dict[int, list[tuple[int, int]]] = {}
    for k, (a, b) in enumerate(zip(src.tolist(), dst.tolist())):
        edges.setdefault(a, []).append((k, b))
        edges.setdefault(b, []).append((k, a))
    out = T.copy()
    done = ~is_free
    used = np.zeros(src.size, dtype=bool)
    queue = [i for i in edges if done[i]]
    reached = 0
    while queue:
        i = queue.pop()
        for k, j in edges[i]:
            if used[k]:
                continue
            if done[j]:  # both ends known: a cycle (or two anchors joined): not a tree
                return None
            used[k] = True
            out[j] = out[i] @ (T_meas[k] if src[k] == i else T_meas_inv[k])
            done[j] = True
            reached += 1
            queue.append(j)
    return out if reached == int(is_free.sum()) else None
