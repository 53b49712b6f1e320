"""A simulated survey: ground-truth poses, node and track ids, and the connection network.

Connection rule (paper Sec. IV, item 5): two nodes are connected when their ground footprints
overlap by at least ``min_overlap`` (70 %) of the footprint area; consecutive nodes are always
connected. The camera looks straight down (nadir) with a fixed orientation, as in the paper's
aerial experiment ("the camera moves in a horizontal plane with no rotation", Sec. V-B), so every
footprint is the same axis-aligned square of side ``L`` and the overlap of two footprints whose
centres differ by ``(dx, dy)`` is ``max(0, 1 - |dx|/L) * max(0, 1 - |dy|/L)``. (A down swath and
a back swath flown with opposite headings would give the same squares, rotated by 180 deg.)
Candidate pairs come from a KD-tree over the footprint centres (``max(|dx|, |dy|) <= (1 -
min_overlap) L``), so building the network is ``O(n log n)``, never ``O(n^2)``.

Every connection points from the earlier node to the later one (``src < dst`` in flight order) and
its true value is ``T_src_dst`` in the ``src`` frame (the SE(3) convention of
:mod:`ga_ros.core.network`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.measurement import Measurement
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import InputError
from ga_ros.geometry import se3, so3

#: Nominal time between frames in the simulated surveys (ns): one frame per second.
FRAME_PERIOD_NS = 1_000_000_000


def footprint_overlap(d_xy: FloatArray, footprint_m: float) -> FloatArray:
    """Overlap fraction of two axis-aligned square footprints of side ``footprint_m``.

    Parameters
    ----------
    d_xy : (..., 2) offset between the footprint centres (m).
    footprint_m : footprint side length (m).

    Returns
    -------
    (...,) intersection area / footprint area, in [0, 1].
    """
    a = np.clip(1.0 - np.abs(np.asarray(d_xy, dtype=float)) / footprint_m, 0.0, None)
    return a[..., 0] * a[..., 1]


def overlap_pairs(xy: FloatArray, footprint_m: float, min_overlap: float = 0.7) -> IntArray:
    """Pairs ``(i, j)``, ``i < j``, whose footprints overlap by ``>= min_overlap``, plus every
    consecutive pair ``(k, k + 1)``.

    Parameters
    ----------
    xy : (n, 2) footprint centres (m), in flight order.
    footprint_m : footprint side (m).
    min_overlap : overlap threshold in (0, 1] (the paper: 0.7).

    Returns
    -------
    (m, 2) int64 pairs sorted by ``(j, i)`` (the order in which a survey acquires them).
    """
    xy = np.asarray(xy, dtype=float)
    if xy.ndim != 2 or xy.shape[1] != 2 or xy.shape[0] < 2:
        raise InputError(f'footprint centres must have shape (n >= 2, 2), got {xy.shape}')
    if not 0 < min_overlap <= 1:
        raise InputError(f'min_overlap must be in (0, 1], got {min_overlap}')
    n = xy.shape[0]
    radius = (1.0 - min_overlap) * footprint_m * (1 + 1e-9)
    cand = cKDTree(xy).query_pairs(radius, p=np.inf, output_type='ndarray').astype(np.int64)
    cand = np.sort(cand.reshape(-1, 2), axis=1)
    ov = footprint_overlap(xy[cand[:, 1]] - xy[cand[:, 0]], footprint_m)
    keep = cand[ov >= min_overlap - 1e-9]
    consecutive = np.stack([np.arange(n - 1), np.arange(1, n)], axis=1)
    pairs = np.unique(np.concatenate([keep, consecutive]), axis=0)
    order = np.lexsort((pairs[:, 0], pairs[:, 1]))
    return pairs[order]


@dataclass(frozen=True)
class Scenario:
    """A simulated survey with ground truth.

    Attributes
    ----------
    name : scenario name (e.g. ``'aerial'``, ``'lawnmower_open'``).
    T_world_node : (n, 4, 4) true poses, in flight order (node id = index).
    track_ids : (n,) track id of each node (a double swath for a lawnmower; a loop for looping).
    src, dst : (m,) node indices of each connection, ``src < dst``.
    footprint_m : footprint side (m) used by the connection rule.
    depth_m : scene depth (m) below the camera, used by the noise model.
    """

    name: str
    T_world_node: FloatArray
    track_ids: IntArray
    src: IntArray
    dst: IntArray
    footprint_m: float
    depth_m: float

    @property
    def n_nodes(self) -> int:
        return int(self.T_world_node.shape[0])

    @property
    def n_connections(self) -> int:
        return int(self.src.shape[0])

    @property
    def n_tracks(self) -> int:
        return int(np.unique(self.track_ids).size)

    @property
    def node_ids(self) -> IntArray:
        """(n,) node ids: ``0 .. n-1`` in flight order."""
        return np.arange(self.n_nodes, dtype=np.int64)

    @property
    def stamps_ns(self) -> IntArray:
        """(n,) acquisition times (ns), one frame per :data:`FRAME_PERIOD_NS`."""
        return np.arange(self.n_nodes, dtype=np.int64) * FRAME_PERIOD_NS

    @property
    def consecutive(self) -> BoolArray:
        """(m,) True for the frame-to-frame connections ``(k, k + 1)``."""
        return self.dst == self.src + 1

    @property
    def chain(self) -> IntArray:
        """(n - 1,) index of the connection ``(k, k + 1)`` for each ``k`` (the F2F chain)."""
        idx = np.nonzero(self.consecutive)[0]
        return idx[np.argsort(self.src[idx])]

    @property
    def positions(self) -> FloatArray:
        """(n, 3) true positions (m)."""
        return self.T_world_node[:, :3, 3]

    def true_motions(self, model: str = 'se3') -> FloatArray:
        """True observations ``(m, 6)`` ``[t, w]`` of every connection for a constraint model.

        ``se3``: ``T_src_dst = T_world_src^-1 T_world_dst`` (motion in the ``src`` frame).
        ``paper`` (eq. 1, ``p_j = R(w) p_i + t`` in world coordinates): ``R = R_j R_i^T`` and
        ``t = p_j - R p_i`` (equal to the se3 values when the camera does not rotate).
        ``linear``: ``t = p_j - p_i``, ``w = 0``.
        """
        T_i, T_j = self.T_world_node[self.src], self.T_world_node[self.dst]
        if model == 'se3':
            return se3.to_translation_rotvec(se3.relative(T_i, T_j))
        p_i, p_j = T_i[:, :3, 3], T_j[:, :3, 3]
        if model == 'paper':
            R = T_j[:, :3, :3] @ np.swapaxes(T_i[:, :3, :3], 1, 2)
            t = p_j - (R @ p_i[:, :, None])[:, :, 0]
            return np.concatenate([t, so3.log(R)], axis=1)
        if model == 'linear':
            return np.concatenate([p_j - p_i, np.zeros_like(p_i)], axis=1)
        raise InputError(f"model must be 'se3', 'paper' or 'linear', got {model!r}")

    def network(self, z: FloatArray, cov: FloatArray) -> ConnectionNetwork:
        """The connection network with measured motions ``z`` (m, 6) and covariances (m, 6, 6)."""
        net = ConnectionNetwork()
        for node_id, track_id in zip(self.node_ids.tolist(), self.track_ids.tolist()):
            net.add_node(node_id, track_id)
        net.add_connections(self.src, self.dst, z, cov)
        return net

    def f2f(self, z: FloatArray) -> FloatArray:
        """Frame-to-frame integration of the measured consecutive motions (se3 convention)
        from the known first pose: ``(n, 4, 4)`` poses ``T_world_node``."""
        zc = np.asarray(z, dtype=float)[self.chain]
        return se3.integrate(self.T_world_node[0], se3.from_translation_rotvec(zc[:, :3],
                                                                                zc[:, 3:]))

    def f2f_positions(self, z: FloatArray, model: str = 'se3') -> FloatArray:
        """F2F positions ``(n, 3)`` for observations of a constraint model (``paper``:
        ``p_{k+1} = R(w) p_k + t``; ``linear``: ``p_{k+1} = p_k + t``)."""
        if model == 'se3':
            return self.f2f(z)[:, :3, 3]
        zc = np.asarray(z, dtype=float)[self.chain]
        R = so3.exp(zc[:, 3:]) if model == 'paper' else np.broadcast_to(np.eye(3), (len(zc), 3, 3))
        p = np.empty((self.n_nodes, 3))
        p[0] = self.positions[0]
        for k in range(len(zc)):  # sequential scan
            p[k + 1] = R[k] @ p[k] + zc[k, :3]
        return p

    def measurements(self, z: FloatArray, cov: FloatArray) -> list[Measurement]:
        """The connections as :class:`Measurement` objects in acquisition order (sorted by the
        ``dst`` node, then ``src``), as a live survey would deliver them."""
        z = np.asarray(z, dtype=float)
        cov = np.asarray(cov, dtype=float)
        order = np.lexsort((self.src, self.dst))
        tr, st = self.track_ids, self.stamps_ns
        cons = self.consecutive
        return [Measurement(int(self.src[k]), int(self.dst[k]), int(tr[self.src[k]]),
                            int(tr[self.dst[k]]), z[k], cov[k], int(st[self.dst[k]]),
                            'consecutive' if cons[k] else 'cross') for k in order]

    def first_tracks(self, k: int) -> Scenario:
        """The sub-survey made of the nodes of the first ``k`` tracks (by track id order)."""
        tracks = np.unique(self.track_ids)
        if not 1 <= k <= tracks.size:
            raise InputError(f'k must be in [1, {tracks.size}], got {k}')
        keep = np.isin(self.track_ids, tracks[:k])
        n = int(np.argmin(keep)) if not keep.all() else self.n_nodes
        if not keep[:n].all() or keep[n:].any():
            raise InputError('tracks are not contiguous in flight order')
        conn = (self.src < n) & (self.dst < n)
        return Scenario(self.name, self.T_world_node[:n].copy(), self.track_ids[:n].copy(),
                        self.src[conn].copy(), self.dst[conn].copy(), self.footprint_m,
                        self.depth_m)


def scenario_from_path(name: str, positions: FloatArray, track_ids: IntArray,
                       footprint_m: float, depth_m: float,
                       min_overlap: float = 0.7) -> Scenario:
    """Build a :class:`Scenario` for a nadir camera with fixed orientation along ``positions``.

    Parameters
    ----------
    positions : (n, 3) camera positions (m) in flight order.
    track_ids : (n,) non-decreasing track ids.
    footprint_m : side of the square ground footprint (m).
    depth_m : camera height above the ground (m), for the noise model.
    min_overlap : the connection threshold (paper: 0.7).
    """
    positions = np.asarray(positions, dtype=float)
    track_ids = np.asarray(track_ids, dtype=np.int64)
    if positions.ndim != 2 or positions.shape[1] != 3 or track_ids.shape != positions.shape[:1]:
        raise InputError('positions must be (n, 3) and track_ids (n,)')
    if np.any(np.diff(track_ids) < 0):
        raise InputError('track ids must be non-decreasing in flight order')
    pairs = overlap_pairs(positions[:, :2], footprint_m, min_overlap)
    T = se3.from_rt(np.broadcast_to(np.eye(3), (positions.shape[0], 3, 3)), positions)
    return Scenario(name, T, track_ids, pairs[:, 0].copy(), pairs[:, 1].copy(),
                    float(footprint_m), float(depth_m))
