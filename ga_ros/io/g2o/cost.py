"""The pose-graph cost that judges a solution, independent of the solver (see
:mod:`ga_ros.io.g2o` for the convention)."""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.io.g2o.graph import PoseGraph
from ga_ros.io.g2o.planar import se3_to_se2


def _se3_log(T: FloatArray) -> FloatArray:
    """SE(3) logarithm ``[rho, phi]`` ``(m, 6)`` of ``(m, 4, 4)`` poses, written independently of
    the solver's :func:`ga_ros.geometry.so3.log` (trace and skew part): ``phi`` from the unit
    quaternion ``(v, w)`` of the rotation (:func:`ga_ros.geometry.se3.quat_from_matrix`,
    ``w >= 0``) as ``2 atan2(|v|, w) v / |v|``, ``rho = V(phi)^-1 t`` with
    ``V^-1 = I - W/2 + (1/theta^2 - cot(theta/2) / (2 theta)) W^2`` (``W = [phi]x``), whose last
    coefficient is evaluated by its series ``1/12 + theta^2/720 + theta^4/30240`` near 0."""
    q = se3.quat_from_matrix(T[:, :3, :3])
    v, w = q[:, :3], q[:, 3]
    s = np.linalg.norm(v, axis=1)
    tiny = s < 1e-8  # atan2(s, w) / s = (1 - s^2 / (3 w^2)) / w to rounding
    scale = np.where(tiny, 2.0 / w * (1.0 - s * s / (3.0 * w * w)),
                     2.0 * np.arctan2(s, w) / np.where(tiny, 1.0, s))
    phi = v * scale[:, None]
    theta = np.linalg.norm(phi, axis=1)
    small = theta < 1e-2
    th = np.where(small, 1.0, theta)
    coef = np.where(small, 1 / 12 + theta**2 / 720 + theta**4 / 30240,
                    1 / th**2 - np.cos(th / 2) / (2 * th * np.sin(th / 2)))
    W = np.zeros((len(T), 3, 3))
    W[:, 0, 1], W[:, 0, 2], W[:, 1, 2] = -phi[:, 2], phi[:, 1], -phi[:, 0]
    W -= np.swapaxes(W, 1, 2)
    Vinv = np.eye(3) - 0.5 * W + coef[:, None, None] * (W @ W)
    rho = (Vinv @ T[:, :3, 3:4])[:, :, 0]
    return np.concatenate([rho, phi], axis=1)


def _se2_log(xyt: FloatArray) -> FloatArray:
    """SE(2) logarithm ``[rho_x, rho_y, theta]`` of planar motions ``[x, y, theta]`` ``(m, 3)``
    (GTSAM ``Pose2::Logmap``): ``rho = V(theta)^-1 t``, ``V = [[s, -c], [c, s]]`` with
    ``s = sin(theta)/theta``, ``c = (1 - cos(theta))/theta``."""
    th = (xyt[:, 2] + np.pi) % (2 * np.pi) - np.pi
    small = np.abs(th) < 1e-4
    t = np.where(small, 1.0, th)
    s = np.where(small, 1 - th**2 / 6, np.sin(t) / t)
    c = np.where(small, th / 2 - th**3 / 24, (1 - np.cos(t)) / t)
    det = s * s + c * c
    x, y = xyt[:, 0], xyt[:, 1]
    return np.stack([(s * x + c * y) / det, (-c * x + s * y) / det, th], axis=1)


def edge_errors(graph: PoseGraph, T_world_node: FloatArray) -> FloatArray:
    """Per-edge error ``e = Log(T_meas^-1 T_i^-1 T_j)``, ``(m, 6)`` in 3-D (``[rho, phi]``),
    ``(m, 3)`` in 2-D (``[rho_x, rho_y, theta]``, poses projected to the plane)."""
    T = np.asarray(T_world_node, dtype=float)
    if T.shape != (graph.n_vertices, 4, 4):
        raise InputError(f'T_world_node must have shape ({graph.n_vertices}, 4, 4), '
                         f'got {T.shape}')
    if graph.dim == 3:
        Ti, Tj, M = T[graph.edge_src], T[graph.edge_dst], graph.T_meas
        Ri_t = np.swapaxes(Ti[:, :3, :3], 1, 2)
        Rm_t = np.swapaxes(M[:, :3, :3], 1, 2)
        R_ij = Ri_t @ Tj[:, :3, :3]
        t_ij = (Ri_t @ (Tj[:, :3, 3] - Ti[:, :3, 3])[:, :, None])[:, :, 0]
        D = np.zeros_like(Ti)
        D[:, :3, :3] = Rm_t @ R_ij
        D[:, :3, 3] = (Rm_t @ (t_ij - M[:, :3, 3])[:, :, None])[:, :, 0]
        D[:, 3, 3] = 1.0
        return _se3_log(D)
    v = se3_to_se2(T)
    vm = se3_to_se2(graph.T_meas)
    a, b = v[graph.edge_src], v[graph.edge_dst]

    def rot_t(theta, x):  # R(theta)^T x for stacks of 2-vectors
        c, s = np.cos(theta), np.sin(theta)
        return np.stack([c * x[:, 0] + s * x[:, 1], -s * x[:, 0] + c * x[:, 1]], axis=1)

    t_ij = rot_t(a[:, 2], b[:, :2] - a[:, :2])
    rel = np.column_stack([rot_t(vm[:, 2], t_ij - vm[:, :2]), b[:, 2] - a[:, 2] - vm[:, 2]])
    return _se2_log(rel)


def graph_cost(graph: PoseGraph, T_world_node: FloatArray) -> float:
    """Pose-graph cost ``sum_k e_k' Omega_k e_k`` (the convention of the benchmark's reference
    optima: GTSAM's between-factor error with g2o's information, see module docstring).

    Independent of the solver: it is what judges a solution.

    Parameters
    ----------
    graph : the graph (edges, information, dimension).
    T_world_node : (n, 4, 4) vertex poses in the graph's vertex order.
    """
    e = edge_errors(graph, T_world_node)
    return float(np.einsum('ki,kij,kj->', e, graph.information, e))
