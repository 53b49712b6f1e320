"""g2o pose-graph files: read into a :class:`ConnectionNetwork`, write back, evaluate the cost.

Supported lines (one record per line, fields separated by white space)::

    VERTEX_SE3:QUAT  id x y z qx qy qz qw
    EDGE_SE3:QUAT    i j [p] x y z qx qy qz qw  I11 I12 .. I16 I22 .. I66  (21 upper values)
    PARAMS_SE3OFFSET p x y z qx qy qz qw         (sensor offset T_robot_sensor, id p)
    VERTEX_SE2       id x y theta
    EDGE_SE2         i j [p] x y theta  I11 I12 I13 I22 I23 I33            (6 upper values)
    PARAMS_SE2OFFSET p x y theta
    VERTEX2          id x y theta                (TORO 2-D)
    EDGE2            i j x y theta  Iff Ifs Iss Irr Ifr Isr                (TORO order)
    FIX              id [id ...]

Blank lines and lines starting with ``#`` are skipped. An edge is the motion ``T_i_j`` of vertex
``j`` in the frame of vertex ``i`` with an information matrix ``Omega`` (inverse covariance); for
``EDGE_SE3:QUAT`` its order is ``[x y z qx qy qz]``, the same as ours ``[x y z rx ry rz]``. As in
GTSAM's g2o reader (and as the benchmark's reference optima assume, see
``shared/data/README.md``), the rotation block is taken as the information of the rotation vector
(rad), not of the quaternion's vector part (which would weigh rotations by 4).

Sensor offsets (what RTAB-Map and g2o itself write first): an identity ``PARAMS_*OFFSET`` is
accepted and written back. An edge that names a parameter id ``p`` measures the motion between
sensor frames, ``Z = S^-1 T_i^-1 T_j S`` with ``S = T_robot_sensor``; it is read as the robot-frame
motion ``T_meas = S Z S^-1`` with information ``Ad(S^-1)' Omega Ad(S^-1)`` (exactly the same cost,
since ``Log(S^-1 X S) = Ad(S^-1) Log(X)``), and written back in the sensor frame. A non-identity
offset that no edge names is refused: it is ambiguous whether the file's edges include it.

Files without any ``VERTEX`` line (edge-only benchmark files) are read with vertices in
increasing id order and ``has_guess = False``: see :mod:`ga_ros.core.initialization` for the
initial guess. Information matrices that are not positive definite are repaired by eigenvalue
clipping (:func:`ga_ros.core.covariance.nearest_positive_definite`) with one
:class:`InformationRepairWarning` per file listing the lines, or refused with ``strict=True``.

Cost convention (:func:`graph_cost`): ``sum_k e_k' Omega_k e_k`` with
``e_k = Log(T_meas^-1 T_i^-1 T_j)``, the full Lie-group logarithm (GTSAM's ``Pose3`` / ``Pose2``
local coordinates), ordered translation first (``[rho, phi]`` in 3-D, ``[rho_x, rho_y, theta]`` in
2-D). 2-D graphs are embedded in SE(3) (``z = 0``, rotation about ``z``); the out-of-plane
components ``z, rx, ry`` get unit information. The SE(3) logarithm of a planar motion is the SE(2)
logarithm padded with zeros, so the embedded problem has exactly the 2-D cost and optimum.

Reading is all-or-nothing and vectorised (the lines of each record type are parsed as one numpy
array): every line is validated first (field count, numbers, tags, quaternion norms, information,
known vertices), and a :class:`FormatError` names the file and line of the first problem of the
first failing check; the network is built only from a completely valid file.
"""

from __future__ import annotations

import operator
import os
import warnings
from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.covariance import (
    PD_TOLERANCE,
    nearest_positive_definite,
    not_positive_definite,
)
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.io.atomic import atomic_write

TAG_VERTEX_SE3 = 'VERTEX_SE3:QUAT'
TAG_EDGE_SE3 = 'EDGE_SE3:QUAT'
TAG_PARAMS_SE3 = 'PARAMS_SE3OFFSET'
TAG_VERTEX_SE2 = 'VERTEX_SE2'
TAG_EDGE_SE2 = 'EDGE_SE2'
TAG_PARAMS_SE2 = 'PARAMS_SE2OFFSET'
TAG_VERTEX_TORO = 'VERTEX2'
TAG_EDGE_TORO = 'EDGE2'
TAG_FIX = 'FIX'

#: tag -> (dimension, kind, allowed field counts including the tag)
_SPEC: dict[str, tuple[int, str, tuple[int, ...]]] = {
    TAG_VERTEX_SE3: (3, 'vertex', (9,)), TAG_EDGE_SE3: (3, 'edge', (31, 32)),
    TAG_PARAMS_SE3: (3, 'param', (9,)),
    TAG_VERTEX_SE2: (2, 'vertex', (5,)), TAG_EDGE_SE2: (2, 'edge', (12, 13)),
    TAG_PARAMS_SE2: (2, 'param', (5,)),
    TAG_VERTEX_TORO: (2, 'vertex', (5,)), TAG_EDGE_TORO: (2, 'edge', (12,)),
}
#: index of the 2-D components [x y theta] inside our 6-vector [x y z rx ry rz]
_SE2_AXES = np.array([0, 1, 5])
#: TORO's EDGE2 information order (ff fs ss rr fr sr) as positions of the g2o upper triangle
#: (11 12 13 22 23 33): g2o value k is TORO value _TORO_FROM_G2O[k]
_TORO_FROM_G2O = np.array([0, 1, 4, 2, 5, 3])
#: a quaternion whose norm is further than this from 1 is rejected rather than normalised
_QUAT_NORM_TOL = 1e-2
#: an offset this close to the identity (max |entry| of S - I) is treated as the identity
_IDENTITY_TOL = 1e-12


class InformationRepairWarning(UserWarning):
    """Some information matrices of a file were not positive definite and were repaired."""


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
    #: information, offsets) and the checksum of the information (_checksum)
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
        return all(a is b for a, b in zip(arrays, now)) and _checksum(self.information) == checksum

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
        fields = {k: getattr(self, k) for k in self.__dataclass_fields__}
        fields.update(T_init=T.copy(), has_guess=True)
        return PoseGraph(**fields)


# ---------------------------------------------------------------------------------- reading
def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _floats(F: np.ndarray, lines: IntArray, path: str) -> FloatArray:
    """``(k, c)`` numbers of a ``(k, c)`` array of strings, or the first bad line's error."""
    try:
        values = np.fromiter(map(float, F.ravel()), dtype=float, count=F.size).reshape(F.shape)
    except ValueError:
        for row, line in zip(F.tolist(), lines.tolist()):  # error path only
            bad = [f for f in row if not _is_float(f)]
            if bad:
                raise FormatError(f'non-numeric value {bad[0]!r}', path, line) from None
        raise
    finite = np.isfinite(values).reshape(len(values), -1).all(axis=1)
    if not finite.all():
        raise FormatError('NaN or infinite value', path, int(lines[np.argmin(finite)]))
    return values


def _ids(F: np.ndarray, lines: IntArray, path: str, what: str = 'vertex id') -> IntArray:
    """``(k,)`` non-negative integer ids of a ``(k,)`` array of strings, or the first bad line's
    error."""
    try:
        values = np.fromiter(map(int, F), dtype=np.int64, count=F.size)
        ok = values >= 0
    except (ValueError, OverflowError):
        # error path only; 19 digits bound int() (Python refuses > 4300 digits with an error)
        ok = np.array([f.isdigit() and len(f) <= 19 and int(f) < 2**63 for f in F.tolist()])
        values = None
    if not ok.all():
        k = int(np.argmin(ok))
        text = str(F[k])
        shown = repr(text) if len(text) <= 40 else f'{text[:20]!r}... ({len(text)} characters)'
        raise FormatError(f'{what} must be a non-negative integer below 2^63, got {shown}', path,
                          int(lines[k]))
    return values


def _upper_to_full(upper: FloatArray, d: int) -> FloatArray:
    """Symmetric ``(d, d)`` matrices from their row-major upper triangles ``(..., d(d+1)/2)``."""
    iu = np.triu_indices(d)
    out = np.zeros(upper.shape[:-1] + (d, d))
    out[..., iu[0], iu[1]] = upper
    out[..., iu[1], iu[0]] = upper
    return out


def _unit_quaternions(q: FloatArray, lines: IntArray, path: str) -> FloatArray:
    norm = np.linalg.norm(q, axis=1)
    bad = np.abs(norm - 1.0) > _QUAT_NORM_TOL
    if bad.any():
        k = int(np.argmax(bad))
        raise FormatError(f'quaternion [qx qy qz qw] has norm {norm[k]:.6g}, not 1', path,
                          int(lines[k]))
    return q / norm[:, None]


def _first_duplicate(ids: IntArray, lines: IntArray) -> tuple[int, int, int] | None:
    """``(id, earlier line, later line)`` of the earliest repeated id (ids in line order)."""
    order = np.argsort(ids, kind='stable')
    s = ids[order]
    dup = np.flatnonzero(s[1:] == s[:-1])
    if dup.size == 0:
        return None
    later = lines[order[dup + 1]]
    k = int(np.argmin(later))
    return int(s[dup[k]]), int(lines[order[dup[k]]]), int(later[k])


@dataclass(frozen=True)
class _Group:
    """The lines of one tag with one field count, as a ``(k, c)`` object array of strings."""

    tag: str
    lines: IntArray
    F: np.ndarray


def _poses(values: FloatArray, dim: int, lines: IntArray, path: str) -> FloatArray:
    """``(k, 4, 4)`` poses of ``[x y z qx qy qz qw]`` or ``[x y theta]`` rows."""
    if dim == 3:
        return se3.from_pos_quat(values[:, :3], _unit_quaternions(values[:, 3:7], lines, path))
    return se2_to_se3(values)


def _split_lines(text: str, path: str
                 ) -> tuple[list[_Group], list[tuple[int, list[str]]], list[list[str]]]:
    """Group the records by (tag, field count); ``FIX`` lines apart. Checks tags and counts.
    Also returns every line's fields (line ``k`` at ``k - 1``)."""
    rows = [ln.split() for ln in text.splitlines()]
    tag_list = [r[0] if r else '#' for r in rows]
    tags = np.array(tag_list)
    counts = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
    lines = np.arange(1, len(rows) + 1)
    # not np.char.startswith: importing numpy.char costs a few ms of every command's start-up
    used = ~np.fromiter((t.startswith('#') for t in tag_list), dtype=bool, count=len(rows))
    known = np.isin(tags, [*_SPEC, TAG_FIX])
    if (used & ~known).any():
        k = int(np.argmax(used & ~known))
        raise FormatError(f'unknown tag {tags[k]!r} (supported: {", ".join(_SPEC)}, FIX)',
                          path, int(lines[k]))
    fix = [(int(lines[k]), rows[k][1:]) for k in np.flatnonzero(tags == TAG_FIX)]
    groups: list[_Group] = []
    for tag, (_, _, allowed) in _SPEC.items():
        mine = tags == tag
        wrong = mine & ~np.isin(counts, allowed)
        if wrong.any():
            k = int(np.argmax(wrong))
            need = ' or '.join(map(str, allowed))
            raise FormatError(f'{tag} needs {need} fields, got {counts[k]}', path, int(lines[k]))
        for c in allowed:
            idx = np.flatnonzero(mine & (counts == c))
            if idx.size:
                F = np.array(list(chain.from_iterable(operator.itemgetter(*idx)(rows)))
                             if idx.size > 1 else rows[idx[0]], dtype=object)
                groups.append(_Group(tag, lines[idx], F.reshape(idx.size, c)))
    return groups, fix, rows


def _graph_dim(groups: list[_Group], spath: str) -> int:
    """The graph's dimension, 2 or 3; refuses a mix of 2-D and 3-D records or an empty file."""
    first = {d: min((int(g.lines[0]) for g in groups if _SPEC[g.tag][0] == d), default=0)
             for d in (2, 3)}
    if first[2] and first[3]:
        later, earlier = max(first[2], first[3]), min(first[2], first[3])
        d_late = 2 if first[2] == later else 3
        raise FormatError(f'this is a {d_late}-D record but line {earlier} made this a '
                          f'{5 - d_late}-D graph; mixed files are not supported', spath, later)
    if not groups:
        raise FormatError('no vertices and no edges (VERTEX_SE3:QUAT / EDGE_SE3:QUAT or '
                          'VERTEX_SE2 / EDGE_SE2 lines) found', spath)
    return 3 if first[3] else 2


def _kind(groups: list[_Group], name: str) -> list[_Group]:
    """The groups of one record kind (``'param'``, ``'vertex'`` or ``'edge'``)."""
    return [g for g in groups if _SPEC[g.tag][1] == name]


@dataclass(frozen=True)
class _Params:
    """The parameter (sensor offset) records: offsets by id, and their lines and ids."""

    offsets: dict[int, FloatArray]
    lines: IntArray
    ids: IntArray


def _read_params(groups: list[_Group], dim: int, spath: str) -> _Params:
    """Parse the parameter records; refuses a duplicate parameter id."""
    p_groups = _kind(groups, 'param')
    if not p_groups:
        return _Params({}, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    p_lines = np.concatenate([g.lines for g in p_groups])
    p_ids = np.concatenate([_ids(g.F[:, 1], g.lines, spath, 'parameter id')
                            for g in p_groups])
    S = np.concatenate([_poses(_floats(g.F[:, 2:], g.lines, spath), dim, g.lines, spath)
                        for g in p_groups])
    dup = _first_duplicate(p_ids, p_lines)
    if dup is not None:
        raise FormatError(f'parameter {dup[0]} is already defined on line {dup[1]}',
                          spath, dup[2])
    return _Params({int(p): S[k] for k, p in enumerate(p_ids.tolist())}, p_lines, p_ids)


def _read_vertices(groups: list[_Group], dim: int, spath: str
                   ) -> tuple[IntArray, FloatArray] | None:
    """Vertex ids and poses in file order (``None`` without vertices); refuses duplicates."""
    v_groups = sorted(_kind(groups, 'vertex'), key=lambda g: int(g.lines[0]))
    if not v_groups:
        return None
    v_lines = np.concatenate([g.lines for g in v_groups])
    v_order = np.argsort(v_lines, kind='stable')
    v_lines = v_lines[v_order]
    v_ids = np.concatenate([_ids(g.F[:, 1], g.lines, spath) for g in v_groups])[v_order]
    T_init = np.concatenate([_poses(_floats(g.F[:, 2:], g.lines, spath), dim, g.lines,
                                    spath) for g in v_groups])[v_order]
    dup = _first_duplicate(v_ids, v_lines)
    if dup is not None:
        raise FormatError(f'vertex {dup[0]} is already defined on line {dup[1]}',
                          spath, dup[2])
    return v_ids, T_init


@dataclass(frozen=True)
class _Edges:
    """The edge records in file order: lines, end ids, parameter ids (-1: none), measured
    poses and the information matrices' upper triangles (g2o order)."""

    lines: IntArray
    i: IntArray
    j: IntArray
    param: IntArray
    Z: FloatArray
    upper: FloatArray


def _read_edges(groups: list[_Group], dim: int, spath: str) -> _Edges:
    """Parse the edge records into file order; refuses a self-loop."""
    d = 6 if dim == 3 else 3
    n_meas = 7 if dim == 3 else 3
    parts = []
    for g in _kind(groups, 'edge'):
        with_param = g.F.shape[1] in (13, 32)
        c = 4 if with_param else 3
        i = _ids(g.F[:, 1], g.lines, spath)
        j = _ids(g.F[:, 2], g.lines, spath)
        p = (_ids(g.F[:, 3], g.lines, spath, 'parameter id') if with_param
             else np.full(len(i), -1, dtype=np.int64))
        values = _floats(g.F[:, c:], g.lines, spath)
        meas = values[:, :n_meas]
        upper = values[:, n_meas:]
        if g.tag == TAG_EDGE_TORO:
            upper = upper[:, _TORO_FROM_G2O]
        parts.append((g.lines, i, j, p, _poses(meas, dim, g.lines, spath), upper))
    if sum(len(q[0]) for q in parts):
        e_lines, ei, ej, ep, Z, upper = (np.concatenate(x) for x in zip(*parts))
        order = np.argsort(e_lines, kind='stable')
        e_lines, ei, ej, ep, Z, upper = (x[order] for x in (e_lines, ei, ej, ep, Z, upper))
    else:
        e_lines = ei = ej = ep = np.zeros(0, dtype=np.int64)
        Z, upper = np.zeros((0, 4, 4)), np.zeros((0, d * (d + 1) // 2))
    loop = ei == ej
    if loop.any():
        k = int(np.argmax(loop))
        raise FormatError(f'edge from vertex {ei[k]} to itself', spath, int(e_lines[k]))
    return _Edges(e_lines, ei, ej, ep, Z, upper)


def _vertices_or_edge_ends(vertices: tuple[IntArray, FloatArray] | None, edges: _Edges,
                           spath: str) -> tuple[IntArray, FloatArray]:
    """The vertex ids and initial poses: the file's, else the edges' ends (increasing) at the
    identity; refuses a file with neither."""
    if vertices is not None:
        return vertices
    if len(edges.lines):
        ids = np.unique(np.concatenate([edges.i, edges.j]))
        return ids, np.broadcast_to(np.eye(4), (ids.size, 4, 4)).copy()
    raise FormatError('no vertices (VERTEX_SE3:QUAT or VERTEX_SE2 lines) found', spath)


def _check_references(ids: IntArray, edges: _Edges, fix: list[tuple[int, list[str]]],
                      params: _Params, dim: int, spath: str) -> None:
    """Refuse an edge or ``FIX`` naming an unknown vertex, an edge naming an unknown
    parameter, or a non-identity offset no edge names."""
    for what, ends in (('edge', edges.i), ('edge', edges.j)):
        known = np.isin(ends, ids)
        if not known.all():
            k = int(np.argmin(known))
            raise FormatError(f'{what} refers to vertex {ends[k]}, which the file does not '
                              f'define', spath, int(edges.lines[k]))
    for line, fields in fix:
        if not fields:
            raise FormatError('FIX needs at least one vertex id', spath, line)
        for v in _ids(np.array(fields, dtype=object), np.full(len(fields), line),
                      spath).tolist():
            if v not in set(ids.tolist()):
                raise FormatError(f'FIX refers to vertex {v}, which the file does not define',
                                  spath, line)
    ep = edges.param
    named = ep >= 0
    known = np.isin(ep, list(params.offsets)) | ~named
    if not known.all():
        k = int(np.argmin(known))
        tag = TAG_PARAMS_SE3 if dim == 3 else TAG_PARAMS_SE2
        raise FormatError(f'edge names parameter {ep[k]}, which no {tag} line defines', spath,
                          int(edges.lines[k]))
    for pid, S in params.offsets.items():
        if not (ep == pid).any() and np.abs(S - np.eye(4)).max() > _IDENTITY_TOL:
            line = int(params.lines[np.flatnonzero(params.ids == pid)[0]])
            raise FormatError(f'sensor offset {pid} is not the identity but no edge names it, '
                              'so it is unclear whether the edges include it: name it on the '
                              'edges (EDGE_... i j {pid} ...) or make it the identity', spath,
                              line)


def _checked_information(upper: FloatArray, d: int, e_lines: IntArray, strict: bool,
                         spath: str) -> tuple[FloatArray, FloatArray, tuple[int, ...]]:
    """Full information matrices, their eigenvalues and the lines repaired; refuses (strict)
    or repairs (with one warning) a matrix that is not positive definite."""
    info = _upper_to_full(upper, d)
    eig = np.linalg.eigvalsh(info)  # once, for both checks (here and the covariance's)
    bad = not_positive_definite(info, eigenvalues=eig)
    repaired: tuple[int, ...] = ()
    if bad.any():
        k = int(np.argmax(bad))
        if strict:
            raise FormatError(f'information matrix is not positive definite (eigenvalues '
                              f'{np.array2string(eig[k], precision=3)}); drop strict to repair '
                              f'it to the nearest positive-definite matrix', spath,
                              int(e_lines[k]))
        info[bad] = nearest_positive_definite(info[bad])
        eig[bad] = np.linalg.eigvalsh(info[bad])
        repaired = tuple(int(v) for v in e_lines[bad].tolist())
        shown = ', '.join(map(str, repaired[:20])) + (', ...' if len(repaired) > 20 else '')
        # stacklevel 3: read_g2o's caller, as before this was a helper of read_g2o
        warnings.warn(f'{spath}: {len(repaired)} information matrices were not positive '
                      f'definite and were repaired by eigenvalue clipping (lines {shown}); '
                      f'read strictly to refuse them instead', InformationRepairWarning,
                      stacklevel=3)
    return info, eig, repaired


def _covariances(info: FloatArray, eig: FloatArray, dim: int, e_lines: IntArray,
                 spath: str) -> FloatArray:
    """The edges' 6x6 covariances; refuses an information too ill-conditioned to invert."""
    if dim == 3:
        info6 = info
    else:
        info6 = np.broadcast_to(np.eye(6), (len(info), 6, 6)).copy()
        info6[:, _SE2_AXES[:, None], _SE2_AXES[None, :]] = info
    cov = np.linalg.inv(info6)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))
    # the network's rule for a covariance (ga_ros.core.network.check_covariances: smallest
    # eigenvalue above PD_TOLERANCE of its largest |entry|), from the information's eigenvalues
    # (those of the covariance are their inverses; a 2-D edge's padding adds eigenvalue 1)
    cov_min = 1.0 / eig[:, -1] if dim == 3 else np.minimum(1.0 / eig[:, -1], 1.0)
    singular = ~(cov_min > PD_TOLERANCE * np.abs(cov).max(axis=(1, 2)))
    if singular.any():
        k = int(np.argmax(singular))
        raise FormatError(f'information matrix is too ill-conditioned to invert (eigenvalues '
                          f'{np.array2string(eig[k], precision=3)}): its covariance would not '
                          'be positive definite; fix the matrix', spath, int(e_lines[k]))
    return cov


def read_g2o(path: str | os.PathLike, strict: bool = False) -> PoseGraph:
    """Read a g2o (or TORO 2-D) pose graph: 3-D ``SE3:QUAT`` or 2-D ``SE2``, not both.

    Parameters
    ----------
    path : g2o file.
    strict : refuse an information matrix that is not positive definite (default: repair it by
        eigenvalue clipping, with one :class:`InformationRepairWarning` listing the lines).

    Returns
    -------
    The :class:`PoseGraph`; vertices in file order (increasing ids for an edge-only file,
    ``has_guess`` false), edges in file order.

    Raises
    ------
    FormatError
        Naming ``file:line`` for: an unknown tag, a wrong field count, a non-numeric / NaN value,
        a negative or duplicate vertex or parameter id, a quaternion far from unit norm, an
        information matrix that is not symmetric positive definite (``strict`` only), a
        self-loop, an edge naming a vertex the file does not define (when it defines some) or
        a parameter it does not define, a non-identity offset no edge names, a ``FIX`` naming an
        unknown vertex, a mix of 2-D and 3-D records, or a file with no vertices and no edges.
        Nothing is built unless the whole file is valid.
    """
    spath = str(path)
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f'cannot read: {exc}', spath) from None
    groups, fix, rows = _split_lines(text, spath)
    dim = _graph_dim(groups, spath)
    params = _read_params(groups, dim, spath)
    offsets = params.offsets
    vertices = _read_vertices(groups, dim, spath)
    has_guess = vertices is not None
    edges = _read_edges(groups, dim, spath)
    e_lines, ep = edges.lines, edges.param
    ids, T_init = _vertices_or_edge_ends(vertices, edges, spath)
    _check_references(ids, edges, fix, params, dim, spath)
    info, eig, repaired = _checked_information(edges.upper, 6 if dim == 3 else 3, e_lines,
                                               strict, spath)
    # sensor offsets into the robot frame
    named = ep >= 0
    T_meas, info = _apply_offsets(edges.Z, info, ep, offsets, dim, inverse=False)
    if named.any():  # A' Omega A has other eigenvalues
        eig[named] = np.linalg.eigvalsh(info[named])
    cov = _covariances(info, eig, dim, e_lines, spath)

    # everything is valid: build the graph
    sorter = np.argsort(ids)
    src = sorter[np.searchsorted(ids, edges.i, sorter=sorter)]
    dst = sorter[np.searchsorted(ids, edges.j, sorter=sorter)]
    z = se3.to_translation_rotvec(T_meas)
    # everything was validated above (ids, ends, no self-loops, finite values, covariances):
    # no per-edge Python loop of ConnectionNetwork.add_connections; repeated edges are kept
    network = ConnectionNetwork.from_arrays(ids, np.zeros(ids.size, dtype=np.int64), src, dst,
                                            z, cov)
    fixed = tuple(dict.fromkeys(int(v) for _, fields in fix for v in fields))
    # the edge records as read, for write_g2o (not when an information was repaired)
    edge_lines = None if repaired else ''.join(
        ' '.join(rows[k - 1]) + '\n' for k in e_lines.tolist())
    toro = any(g.tag in (TAG_VERTEX_TORO, TAG_EDGE_TORO) for g in groups)
    g2o2 = any(g.tag in (TAG_VERTEX_SE2, TAG_EDGE_SE2) for g in groups)
    arrays = (ids.astype(np.int64), src.astype(np.int64), dst.astype(np.int64), T_meas,
              ep if named.any() else None)
    for a in arrays:  # the edge records stand for them: no edits in place
        if a is not None:
            a.flags.writeable = False
    read_with = (*arrays, info, offsets, _checksum(info)) if edge_lines is not None else ()
    return PoseGraph(network=network, T_init=T_init, vertex_ids=arrays[0], dim=dim,
                     fixed=fixed, edge_src=arrays[1], edge_dst=arrays[2], T_meas=T_meas,
                     information=info, path=spath, has_guess=has_guess, offsets=offsets,
                     edge_param=arrays[4], repaired_lines=repaired,
                     flavour='toro' if toro and not g2o2 else 'g2o', edge_lines=edge_lines,
                     _read_with=read_with)


def _checksum(information: FloatArray) -> tuple[float, float]:
    """Sum of squares and lag-one sum of products of the entries (two BLAS dot products, ~0.1
    ms for 6,000 edges): an edit in place of a read graph's information (a changed value, two
    values swapped) changes them (:meth:`PoseGraph.edges_as_read`)."""
    flat = information.reshape(-1)
    return float(flat @ flat), float(flat[1:] @ flat[:-1])


def _apply_offsets(T: FloatArray, info: FloatArray, param: IntArray,
                   offsets: dict[int, FloatArray], dim: int,
                   inverse: bool) -> tuple[FloatArray, FloatArray]:
    """Sensor-frame edges ``(Z, Omega)`` to robot-frame ``(S Z S^-1, Ad(S^-1)' Omega Ad(S^-1))``
    for the edges that name an offset ``S`` (``inverse``: the other way)."""
    named = np.flatnonzero(param >= 0)
    if named.size == 0:
        return T, info
    keys = np.array(sorted(offsets), dtype=np.int64)
    S = np.stack([offsets[k] for k in keys.tolist()])[np.searchsorted(keys, param[named])]
    Sinv = se3.inverse(S)
    T, info = T.copy(), info.copy()
    A = se3.adjoint(S if inverse else Sinv)   # Omega_new = A' Omega A
    if dim == 2:
        A = A[:, _SE2_AXES[:, None], _SE2_AXES[None, :]]
    if inverse:
        T[named] = Sinv @ T[named] @ S
    else:
        T[named] = S @ T[named] @ Sinv
    info[named] = np.swapaxes(A, 1, 2) @ info[named] @ A
    info[named] = 0.5 * (info[named] + np.swapaxes(info[named], 1, 2))
    return T, info


# ---------------------------------------------------------------------------------- writing
def _text_rows(prefix: list[str], values: FloatArray) -> str:
    """Lines ``prefix[r] v0 v1 ...`` of a ``(k, c)`` float table, without a Python loop per row.

    Floats are written as their shortest exact ``repr``, so reading them back gives the same
    bits.
    """
    k, c = values.shape
    if k == 0:
        return ''
    tokens = list(map(repr, values.ravel().tolist()))
    seps = [' '] * (k * c)
    seps[::c] = map('\n{} '.format, prefix)
    seps[0] = seps[0][1:]
    return ''.join(chain.from_iterable(zip(seps, tokens))) + '\n'


def write_g2o(path: str | os.PathLike, graph: PoseGraph,
              T_world_node: FloatArray | None = None) -> None:
    """Write a pose graph (offsets, vertices, edges, ``FIX``) in the format it was read in.

    What was read is written back: ``PARAMS_*OFFSET`` lines, edges that named a parameter (in
    the sensor frame, with their parameter id), TORO ``VERTEX2``/``EDGE2`` for a TORO file. An
    edge-only graph is written without vertices unless ``T_world_node`` is given. The file is
    written to a temporary name and renamed, so a failure leaves no half file.

    Parameters
    ----------
    path : output file.
    graph : the graph; its edges and information are written as read (its
        :attr:`PoseGraph.edge_lines` when it has them, else formatted from its arrays).
    T_world_node : (n, 4, 4) vertex poses to write (default: ``graph.T_init``). For a 2-D graph
        they are projected to the plane (x, y, yaw about z).
    """
    T = graph.T_init if T_world_node is None else np.asarray(T_world_node, dtype=float)
    if T.shape != (graph.n_vertices, 4, 4):
        raise InputError(f'T_world_node must have shape ({graph.n_vertices}, 4, 4), '
                         f'got {T.shape}')
    if not np.isfinite(T).all():
        raise InputError('T_world_node has NaN or inf entries; refusing to write them')
    ids = graph.vertex_ids
    m = graph.n_edges
    toro = graph.flavour == 'toro' and graph.dim == 2
    if graph.dim == 3:
        tags = (TAG_PARAMS_SE3, TAG_VERTEX_SE3, TAG_EDGE_SE3)

        def values(X: FloatArray) -> FloatArray:
            p, q = se3.to_pos_quat(X)
            return np.concatenate([p.reshape(-1, 3), q.reshape(-1, 4)], axis=1)
    else:
        tags = (TAG_PARAMS_SE2, TAG_VERTEX_TORO if toro else TAG_VERTEX_SE2,
                TAG_EDGE_TORO if toro else TAG_EDGE_SE2)
        values = se3_to_se2
    blocks = []
    if graph.offsets:
        keys = np.array(sorted(graph.offsets), dtype=np.int64)
        S = np.stack([graph.offsets[k] for k in keys.tolist()])
        blocks.append(_text_rows(list(map(f'{tags[0]} {{}}'.format, keys.tolist())),
                                 values(S)))
    if graph.has_guess or T_world_node is not None:
        blocks.append(_text_rows(list(map(f'{tags[1]} {{}}'.format, ids.tolist())),
                                 values(T)))
    if m and graph.edges_as_read():  # the edges as read (the same values exactly)
        blocks.append(graph.edge_lines)
    elif m:
        param = graph.edge_param if graph.edge_param is not None else np.full(m, -1, np.int64)
        Z, info = _apply_offsets(graph.T_meas, graph.information, param, graph.offsets,
                                 graph.dim, inverse=True)
        d = 6 if graph.dim == 3 else 3
        upper = info[:, np.triu_indices(d)[0], np.triu_indices(d)[1]]
        if toro:
            upper = upper[:, np.argsort(_TORO_FROM_G2O)]
        pid = np.where(param >= 0, np.char.add(' ', param.astype(str)), '').tolist()
        head = list(map(f'{tags[2]} {{}} {{}}{{}}'.format, ids[graph.edge_src].tolist(),
                        ids[graph.edge_dst].tolist(), pid))
        blocks.append(_text_rows(head, np.concatenate([values(Z), upper], axis=1)))
    if graph.fixed:
        blocks.append(f'{TAG_FIX} ' + ' '.join(str(int(v)) for v in graph.fixed) + '\n')
    if not Path(path).parent.is_dir():
        raise FormatError(f'cannot write: no directory {Path(path).parent}', str(path))
    try:
        atomic_write(path, ''.join(blocks).encode())
    except OSError as exc:
        raise FormatError(f'cannot write: {exc}', str(path)) from None


# ------------------------------------------------------------------------------ SE(2) helpers
def se2_to_se3(xyt: FloatArray) -> FloatArray:
    """Planar poses ``[x, y, theta]`` (m, rad) ``(..., 3)`` as ``(..., 4, 4)`` with ``z = 0``."""
    xyt = np.asarray(xyt, dtype=float)
    c, s = np.cos(xyt[..., 2]), np.sin(xyt[..., 2])
    T = np.zeros(xyt.shape[:-1] + (4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 1, 0], T[..., 1, 1] = c, -s, s, c
    T[..., 2, 2] = T[..., 3, 3] = 1.0
    T[..., 0, 3], T[..., 1, 3] = xyt[..., 0], xyt[..., 1]
    return T


def se3_to_se2(T: FloatArray) -> FloatArray:
    """``[x, y, yaw]`` ``(..., 3)`` of poses ``(..., 4, 4)`` (yaw = atan2(R10, R00), in
    ``(-pi, pi]``); ``z`` and tilt are dropped."""
    T = np.asarray(T, dtype=float)
    return np.stack([T[..., 0, 3], T[..., 1, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])],
                    axis=-1)


# ---------------------------------------------------------------------------- cost evaluation
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
