"""Reading a g2o (or TORO 2-D) file into a :class:`~ga_ros.io.g2o.graph.PoseGraph`.

All-or-nothing: every record is validated before the network is built (see :mod:`ga_ros.io.g2o`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import FormatError
from ga_ros.geometry import se3
from ga_ros.io.g2o.graph import PoseGraph, information_checksum
from ga_ros.io.g2o.information import checked_information, edge_covariances
from ga_ros.io.g2o.offsets import apply_offsets
from ga_ros.io.g2o.records import (
    TAG_EDGE_SE2,
    TAG_EDGE_TORO,
    TAG_PARAMS_SE2,
    TAG_PARAMS_SE3,
    TAG_VERTEX_SE2,
    TAG_VERTEX_TORO,
    TORO_FROM_G2O,
    RecordGroup,
    first_duplicate,
    graph_dim,
    groups_of_kind,
    parse_floats,
    parse_ids,
    parse_poses,
    split_lines,
)

#: an offset this close to the identity (max |entry| of S - I) is treated as the identity
_IDENTITY_TOL = 1e-12


@dataclass(frozen=True)
class _Params:
    """The parameter (sensor offset) records: offsets by id, and their lines and ids."""

    offsets: dict[int, FloatArray]
    lines: IntArray
    ids: IntArray


def _read_params(groups: list[RecordGroup], dim: int, spath: str) -> _Params:
    """Parse the parameter records; refuses a duplicate parameter id."""
    p_groups = groups_of_kind(groups, 'param')
    if not p_groups:
        return _Params({}, np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64))
    p_lines = np.concatenate([g.lines for g in p_groups])
    p_ids = np.concatenate([parse_ids(g.F[:, 1], g.lines, spath, 'parameter id')
                            for g in p_groups])
    S = np.concatenate([parse_poses(parse_floats(g.F[:, 2:], g.lines, spath), dim, g.lines, spath)
                        for g in p_groups])
    dup = first_duplicate(p_ids, p_lines)
    if dup is not None:
        raise FormatError(f'parameter {dup[0]} is already defined on line {dup[1]}',
                          spath, dup[2])
    return _Params({int(p): S[k] for k, p in enumerate(p_ids.tolist())}, p_lines, p_ids)


def _read_vertices(groups: list[RecordGroup], dim: int, spath: str
                   ) -> tuple[IntArray, FloatArray] | None:
    """Vertex ids and poses in file order (``None`` without vertices); refuses duplicates."""
    v_groups = sorted(groups_of_kind(groups, 'vertex'), key=lambda g: int(g.lines[0]))
    if not v_groups:
        return None
    v_lines = np.concatenate([g.lines for g in v_groups])
    v_order = np.argsort(v_lines, kind='stable')
    v_lines = v_lines[v_order]
    v_ids = np.concatenate([parse_ids(g.F[:, 1], g.lines, spath) for g in v_groups])[v_order]
    T_init = np.concatenate([parse_poses(parse_floats(g.F[:, 2:], g.lines, spath), dim, g.lines,
                                    spath) for g in v_groups])[v_order]
    dup = first_duplicate(v_ids, v_lines)
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


def _read_edges(groups: list[RecordGroup], dim: int, spath: str) -> _Edges:
    """Parse the edge records into file order; refuses a self-loop."""
    d = 6 if dim == 3 else 3
    n_meas = 7 if dim == 3 else 3
    parts = []
    for g in groups_of_kind(groups, 'edge'):
        with_param = g.F.shape[1] in (13, 32)
        c = 4 if with_param else 3
        i = parse_ids(g.F[:, 1], g.lines, spath)
        j = parse_ids(g.F[:, 2], g.lines, spath)
        p = (parse_ids(g.F[:, 3], g.lines, spath, 'parameter id') if with_param
             else np.full(len(i), -1, dtype=np.int64))
        values = parse_floats(g.F[:, c:], g.lines, spath)
        meas = values[:, :n_meas]
        upper = values[:, n_meas:]
        if g.tag == TAG_EDGE_TORO:
            upper = upper[:, TORO_FROM_G2O]
        parts.append((g.lines, i, j, p, parse_poses(meas, dim, g.lines, spath), upper))
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
        for v in parse_ids(np.array(fields, dtype=object), np.full(len(fields), line),
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
    groups, fix, rows = split_lines(text, spath)
    dim = graph_dim(groups, spath)
    params = _read_params(groups, dim, spath)
    offsets = params.offsets
    vertices = _read_vertices(groups, dim, spath)
    has_guess = vertices is not None
    edges = _read_edges(groups, dim, spath)
    e_lines, ep = edges.lines, edges.param
    ids, T_init = _vertices_or_edge_ends(vertices, edges, spath)
    _check_references(ids, edges, fix, params, dim, spath)
    info, eig, repaired = checked_information(edges.upper, 6 if dim == 3 else 3, e_lines,
                                               strict, spath)
    # sensor offsets into the robot frame
    named = ep >= 0
    T_meas, info = apply_offsets(edges.Z, info, ep, offsets, dim, inverse=False)
    if named.any():  # A' Omega A has other eigenvalues
        eig[named] = np.linalg.eigvalsh(info[named])
    cov = edge_covariances(info, eig, dim, e_lines, spath)

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
    read_with = ((*arrays, info, offsets, information_checksum(info))
                 if edge_lines is not None else ())
    return PoseGraph(network=network, T_init=T_init, vertex_ids=arrays[0], dim=dim,
                     fixed=fixed, edge_src=arrays[1], edge_dst=arrays[2], T_meas=T_meas,
                     information=info, path=spath, has_guess=has_guess, offsets=offsets,
                     edge_param=arrays[4], repaired_lines=repaired,
                     flavour='toro' if toro and not g2o2 else 'g2o', edge_lines=edge_lines,
                     _read_with=read_with)
