"""Frame-to-frame (F2F, dead-reckoning) integration of consecutive motion measurements.

The one F2F integrator of ga_ros: the replay's F2F path and the ``--io-only`` stand-in aligner
(:class:`DeadReckoningAligner`) both use it. Cross-track connections are ignored; each new node
is its source's pose times the measured motion ``T_src_dst`` (``T_world_dst = T_world_src @
T_src_dst``, the chain of :func:`ga_ros.geometry.se3.integrate`).
"""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.measurement import Measurement
from ga_ros.geometry import se3
from ga_ros.io.trajectory import Trajectory


class F2FIntegrator:
    """Frame-to-frame poses of the nodes reached by consecutive motions.

    Parameters
    ----------
    T_world_first : (4, 4) pose of the first source node (default identity).

    Attributes
    ----------
    poses : node id -> (4, 4) ``T_world_node``, in the order the nodes were reached.
    stamps : node id -> acquisition stamp (ns) of the destination nodes.
    tracks : node id -> track id.
    """

    def __init__(self, T_world_first: FloatArray | None = None) -> None:
        self.T_world_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first)
        self.poses: dict[int, FloatArray] = {}
        self.stamps: dict[int, int] = {}
        self.tracks: dict[int, int] = {}

    def add(self, m: Measurement) -> bool:
        """Use ``m`` if it is a consecutive motion from a known node (or the first one).

        Returns
        -------
        bool
            True if a new node was reached.
        """
        if m.kind != 'consecutive':
            return False
        if not self.poses:
            self.poses[m.src_id] = self.T_world_first.copy()
            self.tracks[m.src_id] = m.src_track
        if m.src_id in self.poses and m.dst_id not in self.poses:
            self.poses[m.dst_id] = self.poses[m.src_id] @ m.T_src_dst
            self.stamps[m.dst_id] = int(m.stamp_ns)
            self.tracks[m.dst_id] = m.dst_track
            return True
        return False

    def map_to_odom(self, node_ids: IntArray, T_map_node: FloatArray) -> FloatArray | None:
        """REP 105 ``T_map_odom`` with this integration as the odometry frame: the correction
        ``T_map_node @ inv(T_odom_node)`` of the newest node (last in ``node_ids``) that the
        integration reached; None if it reached none.

        Parameters
        ----------
        node_ids : (n,) node ids of a corrected path, in path order.
        T_map_node : (n, 4, 4) their corrected poses in the map frame.
        """
        for k in range(len(node_ids) - 1, -1, -1):
            T_odom_node = self.poses.get(int(node_ids[k]))
            if T_odom_node is not None:
                return np.asarray(T_map_node[k]) @ se3.inverse(T_odom_node)
        return None

    def newest(self) -> tuple[FloatArray, int] | None:
        """``(T_odom_node, stamp_ns)`` of the node reached last (None before any)."""
        if not self.stamps:
            return None
        node = next(reversed(self.stamps))
        return self.poses[node], self.stamps[node]


class DeadReckoningAligner:
    """Aligner stand-in (no optimisation): F2F integration with the aligner's interface.

    Used to time bag reading, decoding and output writing alone (``ga-ros bench replay
    --io-only``). A track ends when a measurement's destination track differs from the last one.
    """

    def __init__(self, T_world_first: FloatArray | None = None) -> None:
        self.f2f = F2FIntegrator(T_world_first)
        self.track: int | None = None

    def add_measurement(self, m: Measurement) -> list[dict[str, int | None]]:
        """Integrate ``m``; returns ``[{'track_id': t}]`` when it starts a new track."""
        out = []
        if self.track is not None and m.dst_track != self.track:
            out.append(self.finish_track())
        self.track = m.dst_track
        self.f2f.add(m)
        return out

    def finish_track(self) -> dict[str, int | None]:
        """The "update" of a track end (no computation)."""
        return {'track_id': self.track}

    def refine_batch(self) -> None:
        """Nothing to refine."""
        return None

    def corrected_path(self) -> Trajectory:
        """Every reached node, sorted by id (stamp -1 for the first, whose time is unknown)."""
        f = self.f2f
        ids = np.array(sorted(f.poses), dtype=np.int64)
        return Trajectory(np.array([f.stamps.get(i, -1) for i in ids], dtype=np.int64),
                          np.array([f.poses[i] for i in ids]).reshape(-1, 4, 4), ids,
                          np.array([f.tracks[i] for i in ids], dtype=np.int64))

    def covariance(self, node_id: int) -> FloatArray:
        """Unknown: zeros (6, 6)."""
        return np.zeros((6, 6))
