"""Writing a :class:`~ga_ros.io.g2o.graph.PoseGraph` as a g2o (or TORO) file."""

from __future__ import annotations

import os
from itertools import chain
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.io.g2o.graph import PoseGraph
from ga_ros.io.g2o.offsets import apply_offsets
from ga_ros.io.g2o.planar import se3_to_se2
from ga_ros.io.g2o.records import (
    TAG_EDGE_SE2,
    TAG_EDGE_SE3,
    TAG_EDGE_TORO,
    TAG_FIX,
    TAG_PARAMS_SE2,
    TAG_PARAMS_SE3,
    TAG_VERTEX_SE2,
    TAG_VERTEX_SE3,
    TAG_VERTEX_TORO,
    TORO_FROM_G2O,
)
from ga_ros.safe_write import atomic_write


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
        Z, info = apply_offsets(graph.T_meas, graph.information, param, graph.offsets,
                                 graph.dim, inverse=True)
        d = 6 if graph.dim == 3 else 3
        upper = info[:, np.triu_indices(d)[0], np.triu_indices(d)[1]]
        if toro:
            upper = upper[:, np.argsort(TORO_FROM_G2O)]
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
