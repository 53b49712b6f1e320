"""ROS-free view of the connection network for drawing (node positions, per-connection residual).

Kept out of the node's callbacks (STYLE habit 2) and free of rclpy, so it is unit-tested directly.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.network import ConnectionNetwork
from ga_ros.geometry import se3

#: Connection status codes of :meth:`TrackWindowAligner.connection_arrays`.
ACTIVE, ABSORBED, OUTLIER = 0, 1, 2


@dataclass(frozen=True)
class ConnectionView:
    """What the markers show.

    Attributes
    ----------
    p_world_node : (n, 3) node positions in the world (map) frame, m, path order.
    src_index, dst_index : (m,) indices into ``p_world_node`` of each connection's ends.
    normalized_residual : (m,) Mahalanobis norm ``sqrt(e' cov^-1 e)`` of the misclosure
        ``e = log(T_meas^-1 T_world_src^-1 T_world_dst)`` (unitless; NaN when the connection's
        covariance is not available).
    status : (m,) 0 active, 1 absorbed into a marginal prior, 2 excluded as an outlier.
    w : (m,) largest ``|w|`` (Baarda's w-test) of each connection at its last adjustment (NaN:
        not tested), or ``None`` when quality control is off.
    """

    p_world_node: FloatArray
    src_index: IntArray
    dst_index: IntArray
    normalized_residual: FloatArray
    status: IntArray
    w: FloatArray | None = None


def misclosure_mahalanobis(T_world_src: FloatArray, T_world_dst: FloatArray, z: FloatArray,
                           cov: FloatArray) -> FloatArray:
    """``sqrt(e' cov^-1 e)`` with ``e = log(T_meas^-1 T_world_src^-1 T_world_dst)``, ``(m,)``.

    Parameters
    ----------
    T_world_src, T_world_dst : (m, 4, 4) poses of the connections' ends.
    z : (m, 6) measured ``[t, w]`` of ``T_src_dst`` (m, rad).
    cov : (m, 6, 6) covariances, order ``[x y z rx ry rz]``.
    """
    z = np.asarray(z, dtype=float).reshape(-1, 6)
    if z.shape[0] == 0:
        return np.zeros(0)
    T_meas = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
    e = se3.misclosure(T_meas, T_world_src, T_world_dst)
    sol = np.linalg.solve(np.asarray(cov, dtype=float), e[:, :, None])[:, :, 0]
    return np.sqrt(np.maximum(np.einsum('mi,mi->m', e, sol), 0.0))


def normalized_residuals(network: ConnectionNetwork, T_world_node: FloatArray) -> FloatArray:
    """Mahalanobis misclosure of every connection of ``network``, ``(m,)``, at poses
    ``T_world_node`` ``(n, 4, 4)`` in the network's node index order."""
    conn = network.arrays()
    T = np.asarray(T_world_node, dtype=float)
    return misclosure_mahalanobis(T[conn.src], T[conn.dst], conn.z, conn.cov)


def network_view(node_ids: IntArray, T_world_node: FloatArray, src_id: IntArray,
                 dst_id: IntArray, z: FloatArray, cov: FloatArray | None,
                 status: IntArray | None = None,
                 w: FloatArray | None = None) -> ConnectionView:
    """Build the view from corrected poses of ``node_ids`` and connections given by node ids.

    Connections to nodes missing from ``node_ids`` are dropped; with ``cov=None`` the residuals
    are NaN (drawn grey). ``w``: optional (m,) ``|w|`` per connection (quality control).
    """
    node_ids = np.asarray(node_ids, dtype=np.int64).reshape(-1)
    T = np.asarray(T_world_node, dtype=float).reshape(-1, 4, 4)
    src_id = np.asarray(src_id, dtype=np.int64).reshape(-1)
    dst_id = np.asarray(dst_id, dtype=np.int64).reshape(-1)
    status = (np.zeros(src_id.size, np.int64) if status is None
              else np.asarray(status, dtype=np.int64).reshape(-1))
    order = np.argsort(node_ids, kind='stable')
    sorted_ids = node_ids[order]

    def lookup(ids: IntArray) -> IntArray:
        if sorted_ids.size == 0:
            return np.full(ids.size, -1, np.int64)
        pos = np.clip(np.searchsorted(sorted_ids, ids), 0, sorted_ids.size - 1)
        return np.where(sorted_ids[pos] == ids, order[pos], -1)

    src, dst = lookup(src_id), lookup(dst_id)
    keep = (src >= 0) & (dst >= 0)
    src, dst = src[keep], dst[keep]
    if cov is None:
        resid = np.full(src.size, np.nan)
    else:
        cov = np.asarray(cov, dtype=float).reshape(-1, 6, 6)[keep]
        resid = misclosure_mahalanobis(T[src], T[dst], np.asarray(z, float)[keep], cov)
    w_keep = None if w is None else np.asarray(w, dtype=float).reshape(-1)[keep]
    return ConnectionView(T[:, :3, 3].copy(), src, dst, resid, status[keep], w_keep)


def connection_view(aligner) -> ConnectionView:
    """View of a :class:`ga_ros.core.window.TrackWindowAligner`: every node at its corrected
    pose and every connection it holds (with ``|w|`` when its quality control is on)."""
    cp = aligner.corrected_path()
    src_id, dst_id, z, _cross, status = aligner.connection_arrays()
    cov = aligner.connection_covariances()
    w = aligner.connection_w() if getattr(aligner.config, 'quality', False) else None
    return network_view(cp.node_ids, cp.T_world_node, src_id, dst_id, z, cov, status, w)
