"""g2o pose-graph files: read into a :class:`ConnectionNetwork`, write back, evaluate the cost.

Supported lines (one record per line, fields separated by white space)::

    VERTEX_SE3:QUAT id x y z qx qy qz qw
    EDGE_SE3:QUAT   i j x y z qx qy qz qw  I11 I12 .. I16 I22 .. I66   (21 upper-triangle values)
    VERTEX_SE2      id x y theta
    EDGE_SE2        i j x y theta  I11 I12 I13 I22 I23 I33              (6 upper-triangle values)
    FIX             id [id ...]

Blank lines and lines starting with ``#`` are skipped. An edge is the motion ``T_i_j`` of vertex
``j`` in the frame of vertex ``i`` with an information matrix ``Omega`` (inverse covariance); for
``EDGE_SE3:QUAT`` its order is ``[x y z qx qy qz]``, the same as ours ``[x y z rx ry rz]``. As in
GTSAM's g2o reader (and as the benchmark's reference optima assume, see
``shared/data/README.md``), the rotation block is taken as the information of the rotation vector
(rad), not of the quaternion's vector part (which would weigh rotations by 4).

Cost convention (:func:`graph_cost`): ``sum_k e_k' Omega_k e_k`` with
``e_k = Log(T_meas^-1 T_i^-1 T_j)``, the full Lie-group logarithm (GTSAM's ``Pose3`` / ``Pose2``
local coordinates), ordered translation first (``[rho, phi]`` in 3-D, ``[rho_x, rho_y, theta]`` in
2-D). 2-D graphs are embedded in SE(3) (``z = 0``, rotation about ``z``); the out-of-plane
components ``z, rx, ry`` get unit information. The SE(3) logarithm of a planar motion is the SE(2)
logarithm padded with zeros, so the embedded problem has exactly the 2-D cost and optimum.

Reading is all-or-nothing: every line is parsed and validated first (field count, numbers, tags,
positive-definite information, known vertices), and a :class:`FormatError` names the file and
line of the first problem; the network is built only from a completely valid file.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from scipy.spatial.transform import Rotation

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3

TAG_VERTEX_SE3 = 'VERTEX_SE3:QUAT'
TAG_EDGE_SE3 = 'EDGE_SE3:QUAT'
TAG_VERTEX_SE2 = 'VERTEX_SE2'
TAG_EDGE_SE2 = 'EDGE_SE2'
TAG_FIX = 'FIX'

#: number of fields (including the tag) of each record type
_FIELDS = {TAG_VERTEX_SE3: 9, TAG_EDGE_SE3: 31, TAG_VERTEX_SE2: 5, TAG_EDGE_SE2: 12}
#: index of the 2-D components [x y theta] inside our 6-vector [x y z rx ry rz]
_SE2_AXES = np.array([0, 1, 5])
#: a quaternion whose norm is further than this from 1 is rejected rather than normalised
_QUAT_NORM_TOL = 1e-2


@dataclass(frozen=True, eq=False)
class PoseGraph:
    """A pose graph read from (or to be written to) a g2o file.

    Attributes
    ----------
    network : the connection network; node ids are the g2o vertex ids (track 0), connection ``k``
        is edge ``k`` of the file, its covariance the inverse of the edge's information.
    T_init : (n, 4, 4) initial guess ``T_world_node`` of every vertex, in network index order.
    vertex_ids : (n,) vertex ids, in network index order (the file's order).
    dim : 2 (``VERTEX_SE2`` / ``EDGE_SE2``) or 3 (``VERTEX_SE3:QUAT`` / ``EDGE_SE3:QUAT``).
    fixed : ids of the vertices named on ``FIX`` lines (held fixed as the datum).
    edge_src, edge_dst : (m,) vertex *indices* of each edge's two ends.
    T_meas : (m, 4, 4) measured motions ``T_i_j``.
    information : (m, d, d) information of each edge in its native order, ``d = 6``
        (``[x y z rx ry rz]``) or ``d = 3`` (``[x y theta]``).
    path : file the graph was read from, if any.
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

    @property
    def n_vertices(self) -> int:
        return int(self.vertex_ids.shape[0])

    @property
    def n_edges(self) -> int:
        return int(self.edge_src.shape[0])

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


# ---------------------------------------------------------------------------------- reading
def _numbers(fields: list[str], path: str, line: int) -> FloatArray:
    try:
        values = np.array([float(f) for f in fields])
    except ValueError:
        bad = next(f for f in fields if not _is_float(f))
        raise FormatError(f'non-numeric value {bad!r}', path, line) from None
    if not np.isfinite(values).all():
        raise FormatError('NaN or infinite value', path, line)
    return values


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _vertex_id(text: str, path: str, line: int) -> int:
    try:
        v = int(text)
    except ValueError:
        raise FormatError(f'vertex id must be a non-negative integer, got {text!r}',
                          path, line) from None
    if v < 0 or v >= 2**63:
        raise FormatError(f'vertex id must be a non-negative integer, got {text!r}', path, line)
    return v


def _upper_to_full(upper: FloatArray, d: int) -> FloatArray:
    """Symmetric ``(d, d)`` matrices from their row-major upper triangles ``(..., d(d+1)/2)``."""
    iu = np.triu_indices(d)
    out = np.zeros(upper.shape[:-1] + (d, d))
    out[..., iu[0], iu[1]] = upper
    out[..., iu[1], iu[0]] = upper
    return out


def _unit_quaternion(q: FloatArray, path: str, line: int) -> FloatArray:
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > _QUAT_NORM_TOL:
        raise FormatError(f'quaternion [qx qy qz qw] has norm {norm:.6g}, not 1', path, line)
    return q / norm


def read_g2o(path: str | os.PathLike) -> PoseGraph:
    """Read a g2o pose graph (3-D ``SE3:QUAT`` or 2-D ``SE2``; not both in one file).

    Parameters
    ----------
    path : g2o file.

    Returns
    -------
    The :class:`PoseGraph`; vertices in file order, edges in file order.

    Raises
    ------
    FormatError
        Naming ``file:line`` for: an unknown tag, a wrong field count, a non-numeric / NaN value,
        a negative or duplicate vertex id, a quaternion far from unit norm, an information matrix
        that is not symmetric positive definite, a self-loop, an edge or ``FIX`` naming a vertex
        the file does not define, a mix of 2-D and 3-D records, or a file with no vertices.
        Nothing is built unless the whole file is valid.
    """
    spath = str(path)
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f'cannot read: {exc}', spath) from None

    vertex_ids: list[int] = []
    vertex_line: dict[int, int] = {}
    vertex_pose: list[FloatArray] = []   # (7,) [x y z qx qy qz qw] or (3,) [x y theta]
    edges: list[tuple[int, int, int, FloatArray, FloatArray]] = []  # line, i, j, meas, info
    fix: list[tuple[int, int]] = []      # line, id
    dim: int | None = None
    dim_line = 0

    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.split()
        if not fields or fields[0].startswith('#'):
            continue
        tag = fields[0]
        if tag == TAG_FIX:
            if len(fields) < 2:
                raise FormatError('FIX needs at least one vertex id', spath, lineno)
            fix.extend((lineno, _vertex_id(f, spath, lineno)) for f in fields[1:])
            continue
        if tag not in _FIELDS:
            raise FormatError(f'unknown tag {tag!r} (supported: {", ".join(_FIELDS)}, FIX)',
                              spath, lineno)
        if len(fields) != _FIELDS[tag]:
            raise FormatError(f'{tag} needs {_FIELDS[tag]} fields, got {len(fields)}',
                              spath, lineno)
        this_dim = 2 if tag.endswith('SE2') else 3
        if dim is None:
            dim, dim_line = this_dim, lineno
        elif this_dim != dim:
            raise FormatError(f'{tag} is a {this_dim}-D record but line {dim_line} made this a '
                              f'{dim}-D graph; mixed files are not supported', spath, lineno)
        if tag.startswith('VERTEX'):
            vid = _vertex_id(fields[1], spath, lineno)
            if vid in vertex_line:
                raise FormatError(f'vertex {vid} is already defined on line {vertex_line[vid]}',
                                  spath, lineno)
            values = _numbers(fields[2:], spath, lineno)
            if dim == 3:
                values[3:] = _unit_quaternion(values[3:], spath, lineno)
            vertex_line[vid] = lineno
            vertex_ids.append(vid)
            vertex_pose.append(values)
        else:
            i = _vertex_id(fields[1], spath, lineno)
            j = _vertex_id(fields[2], spath, lineno)
            if i == j:
                raise FormatError(f'edge from vertex {i} to itself', spath, lineno)
            values = _numbers(fields[3:], spath, lineno)
            d = 6 if dim == 3 else 3
            n_meas = 7 if dim == 3 else 3
            meas = values[:n_meas]
            if dim == 3:
                meas[3:] = _unit_quaternion(meas[3:], spath, lineno)
            info = _upper_to_full(values[n_meas:], d)
            eig = np.linalg.eigvalsh(info)
            if eig[0] <= 1e-12 * max(float(np.abs(info).max()), 1e-300):
                raise FormatError(f'information matrix is not positive definite (eigenvalues '
                                  f'{np.array2string(eig, precision=3)})', spath, lineno)
            edges.append((lineno, i, j, meas, info))

    if not vertex_ids:
        raise FormatError('no vertices (VERTEX_SE3:QUAT or VERTEX_SE2 lines) found', spath)
    for lineno, i, j, _, _ in edges:
        for v in (i, j):
            if v not in vertex_line:
                raise FormatError(f'edge refers to vertex {v}, which the file does not define',
                                  spath, lineno)
    for lineno, v in fix:
        if v not in vertex_line:
            raise FormatError(f'FIX refers to vertex {v}, which the file does not define',
                              spath, lineno)

    # ------------------------------------------------ everything is valid: build the graph
    assert dim is not None
    poses = np.array(vertex_pose)
    m = len(edges)
    d = 6 if dim == 3 else 3
    meas = np.array([e[3] for e in edges]).reshape(m, 7 if dim == 3 else 3)
    info = np.array([e[4] for e in edges]).reshape(m, d, d)
    if dim == 3:
        T_init = se3.from_pos_quat(poses[:, :3], poses[:, 3:])
        T_meas = se3.from_pos_quat(meas[:, :3], meas[:, 3:])
        info6 = info
    else:
        T_init = se2_to_se3(poses)
        T_meas = se2_to_se3(meas)
        info6 = np.broadcast_to(np.eye(6), (m, 6, 6)).copy()
        info6[:, _SE2_AXES[:, None], _SE2_AXES[None, :]] = info
    cov = np.linalg.inv(info6)
    cov = 0.5 * (cov + np.swapaxes(cov, 1, 2))

    index = {v: k for k, v in enumerate(vertex_ids)}
    src = np.array([index[e[1]] for e in edges], dtype=np.int64)
    dst = np.array([index[e[2]] for e in edges], dtype=np.int64)
    ids = np.asarray(vertex_ids, dtype=np.int64)

    network = ConnectionNetwork(duplicates='keep')
    for v in vertex_ids:
        network.add_node(v, 0)
    z = se3.to_translation_rotvec(T_meas)
    try:
        network.add_connections(ids[src], ids[dst], z, cov)
    except InputError as exc:  # e.g. a bit-identical repeated edge: name its line
        raise FormatError(f'the network rejected the edges: {exc}', spath) from None
    fixed = tuple(dict.fromkeys(v for _, v in fix))
    return PoseGraph(network=network, T_init=T_init, vertex_ids=ids, dim=dim, fixed=fixed,
                     edge_src=src, edge_dst=dst, T_meas=T_meas, information=info, path=spath)


# ---------------------------------------------------------------------------------- writing
def _fmt(values) -> str:
    return ' '.join(repr(float(v)) for v in values)  # shortest exact repr


def write_g2o(path: str | os.PathLike, graph: PoseGraph,
              T_world_node: FloatArray | None = None) -> None:
    """Write a pose graph (all vertices, all edges, ``FIX``) in g2o format.

    The file is written to a temporary name and renamed, so a failure leaves no half file.

    Parameters
    ----------
    path : output file.
    graph : the graph; its edges and information are written as read.
    T_world_node : (n, 4, 4) vertex poses to write (default: ``graph.T_init``). For a 2-D graph
        they are projected to the plane (x, y, yaw about z).
    """
    T = graph.T_init if T_world_node is None else np.asarray(T_world_node, dtype=float)
    if T.shape != (graph.n_vertices, 4, 4):
        raise InputError(f'T_world_node must have shape ({graph.n_vertices}, 4, 4), '
                         f'got {T.shape}')
    if not np.isfinite(T).all():
        raise InputError('T_world_node has NaN or inf entries; refusing to write them')
    lines: list[str] = []
    ids = graph.vertex_ids
    if graph.dim == 3:
        p, q = se3.to_pos_quat(T)
        for k in range(graph.n_vertices):
            lines.append(f'{TAG_VERTEX_SE3} {ids[k]} {_fmt(p[k])} {_fmt(q[k])}')
        pm, qm = se3.to_pos_quat(graph.T_meas)
        iu = np.triu_indices(6)
        for k in range(graph.n_edges):
            lines.append(f'{TAG_EDGE_SE3} {ids[graph.edge_src[k]]} {ids[graph.edge_dst[k]]} '
                         f'{_fmt(pm[k])} {_fmt(qm[k])} {_fmt(graph.information[k][iu])}')
    else:
        v = se3_to_se2(T)
        for k in range(graph.n_vertices):
            lines.append(f'{TAG_VERTEX_SE2} {ids[k]} {_fmt(v[k])}')
        vm = se3_to_se2(graph.T_meas)
        iu = np.triu_indices(3)
        for k in range(graph.n_edges):
            lines.append(f'{TAG_EDGE_SE2} {ids[graph.edge_src[k]]} {ids[graph.edge_dst[k]]} '
                         f'{_fmt(vm[k])} {_fmt(graph.information[k][iu])}')
    if graph.fixed:
        lines.append(f'{TAG_FIX} ' + ' '.join(str(int(v)) for v in graph.fixed))
    out = Path(path)
    try:
        fd, tmp = tempfile.mkstemp(prefix=f'.{out.name}.', dir=out.parent or '.')
    except OSError as exc:
        raise FormatError(f'cannot write: {exc}', str(path)) from None
    try:
        with os.fdopen(fd, 'w') as fh:
            fh.write('\n'.join(lines) + '\n')
        os.replace(tmp, out)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
    :mod:`ga_ros.geometry`: ``phi`` from scipy's rotation vector, ``rho = V(phi)^-1 t`` with
    ``V^-1 = I - W/2 + (1/theta^2 - cot(theta/2) / (2 theta)) W^2`` (``W = [phi]x``), whose last
    coefficient is evaluated by its series ``1/12 + theta^2/720 + theta^4/30240`` near 0."""
    phi = Rotation.from_matrix(T[:, :3, :3]).as_rotvec()
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
