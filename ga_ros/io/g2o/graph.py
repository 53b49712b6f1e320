"""The :class:`PoseGraph` read from (or written to) a g2o file."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import InputError
from ga_ros.geometry import se3


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """A pose graph read from (or to be written to) a g2o file.

    Attributes
    ----------
    network : the connection network; node ids are the g2o vertex ids (track 0), connection ``k``
        is edge ``k`` of the file, its covariance the inverse of the edge's information.
    T_init : (n, 4, 4) initial guess ``T_world_node`` of every vertex, in network index order
        (identity for every vertex if ``has_guess`` is false).
    vertex_ids : (n,) vertex ids, in network index order (the file's order; increasing for an
        edge-only file).
    dim : 2 (``VERTEX_SE2`` / ``EDGE_SE2`` / TORO) or 3 (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``).
    fixed : ids of the vertices named on ``FIX`` lines (held fixed as the datum).
    edge_src, edge_dst : (m,) vertex *indices* of each edge's two ends.
    T_meas : (m, 4, 4) measured motions ``T_i_j`` of the robot frames (offsets applied).
    information : (m, d, d) information of each edge in its native order, ``d = 6``
        (``[x y z rx ry rz]``) or ``d = 3`` (``[x y theta]``), robot frame, repaired if needed.
    path : file the graph was read from, if any.
    has_guess : whether the file gave vertex poses (false for an edge-only file).
    offsets : parameter id -> (4, 4) sensor offset ``T_robot_sensor`` of ``PARAMS_*OFFSET``.
    edge_param : (m,) parameter id each edge names, -1 for none (``None``: no edge names one).
    repaired_lines : file lines of the edges whose information was repaired.
    flavour : ``'g2o'`` or ``'toro'`` (``VERTEX2`` / ``EDGE2``), kept for writing back.
    edge_lines : the edge records as read, one line each in file order (fields joined by one
        space), which :func:`write_g2o` writes back as they are instead of formatting the
        edges' ~30 numbers again (most of a write's time); ``None`` for a graph not read from
        a file, or whose information was repaired (those edges are written from the arrays).
        They are written only while the graph's vertex ids and edge arrays are the very arrays
        they were read with (:meth:`edges_as_read`): a graph made with other ones (e.g.
        ``dataclasses.replace(graph, information=...)``) is written from its arrays. The id
        and edge arrays of a read graph are read-only; an edit of its ``information`` in place
        is caught by a checksum.
    """

    network: ConnectionNetwork
    T_init: FloatArray
    vertex_ids: IntArray
    dim: int
    fixed: tuple[int, ...]
    edge_src: IntArray
    edge_dst: IntArray
    T_meas: FloatArray
    information: FloatArray
    path: str | None = field(default=None, compare=False)
    has_guess: bool = True
    offsets: dict[int, FloatArray] = field(default_factory=dict)
    edge_param: IntArray | None = None
    repaired_lines: tuple[int, ...] = ()
    flavour: str = 'g2o'
    edge_lines: str | None = field(default=None, repr=False)
    #: what edge_lines was read with: (vertex_ids, edge_src, edge_dst, T_meas, edge_param,
    #: information, offsets) and the checksum of the information (information_checksum)
    _read_with: tuple = field(default=(), repr=False)

    @property
    def n_vertices(self) -> int:
        return int(self.vertex_ids.shape[0])

    @property
    def n_edges(self) -> int:
        return int(self.edge_src.shape[0])

    def edges_as_read(self) -> bool:
        """Whether :attr:`edge_lines` still describes this graph's edges: they were kept at
        reading and the graph holds the very arrays (and offsets) read with them, its
        information unchanged."""
        if self.edge_lines is None or not self._read_with:
            return False
        *arrays, checksum = self._read_with
        now = (self.vertex_ids, self.edge_src, self.edge_dst, self.T_meas, self.edge_param,
               self.information, self.offsets)
        return (all(a is b for a, b in zip(arrays, now))
                and information_checksum(self.information) == checksum)

    @staticmethod
    def from_network(network: ConnectionNetwork, T_world_node: FloatArray,
                     fixed: tuple[int, ...] = ()) -> PoseGraph:
        """Wrap a connection network and poses for export as a 3-D g2o graph.

        Parameters
        ----------
        network : connections with covariances (``[x y z rx ry rz]``); information = inverse.
        T_world_node : (n, 4, 4) poses in network index order.
        fixed : vertex ids to write on a ``FIX`` line.
        """
        T = np.asarray(T_world_node, dtype=float)
        if T.shape != (network.n_nodes, 4, 4):
            raise InputError(f'T_world_node must have shape ({network.n_nodes}, 4, 4), '
                             f'got {T.shape}')
        c = network.arrays()
        info = np.linalg.inv(c.cov)
        info = 0.5 * (info + np.swapaxes(info, 1, 2))
        return PoseGraph(network=network, T_init=T.copy(), vertex_ids=network.node_ids,
                         dim=3, fixed=tuple(int(i) for i in fixed), edge_src=c.src.copy(),
                         edge_dst=c.dst.copy(),
                         T_meas=se3.from_translation_rotvec(c.z[:, :3], c.z[:, 3:]),
                         information=info)

    def with_initial_guess(self, T_world_node: FloatArray) -> PoseGraph:
        """The same graph with another initial guess (``has_guess`` becomes true).

        Parameters
        ----------
        T_world_node : (n, 4, 4) vertex poses in the graph's vertex order.
        """
        T = np.asarray(T_world_node, dtype=float)
        if T.shape != (self.n_vertices, 4, 4) or not np.isfinite(T).all():
            raise InputError(f'initial guess must be finite with shape ({self.n_vertices}, 4, 4),'
                             f' got {T.shape}')
        return replace(self, T_init=T.copy(), has_guess=True)


def information_checksum(information: FloatArray) -> tuple[float, float]:
    """Sum of squares and lag-one sum of products of the entries (two BLAS dot products, ~0.1
    ms for 6,000 edges): an edit in place of a read graph's information (a changed value, two
    values swapped) changes them (:meth:`PoseGraph.edges_as_read`)."""
    flat = information.reshape(-1)
    return float(flat @ flat), float(flat[1:] @ flat[:-1])
