"""Covariance queries of the track-window aligner (:meth:`TrackWindowAligner.covariance
<ga_ros.core.window.TrackWindowAligner.covariance>`, ``covariances``).

Frozen nodes: the marginal block stored when they froze (or refined since). Window nodes: from
the last window adjustment (selected inversion on its factor, guarded by the lock it shares with
a freeze computed ahead). Nodes of the open track have not been adjusted yet:
:class:`~ga_ros.errors.InputError`.
"""

from __future__ import annotations

import threading
from collections.abc import Callable

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.solver import SolveResult
from ga_ros.core.window.state import WindowState
from ga_ros.errors import InputError


def covariance(state: WindowState, last: Callable[[], SolveResult | None], node_id: int,
               lock: threading.Lock) -> FloatArray:
    """6x6 covariance ``[x y z rx ry rz]`` (right perturbation) of a node's pose; ``last``
    returns the last window adjustment (computed on first use after a restore)."""
    try:
        k = state.index[int(node_id)]
    except (KeyError, TypeError, ValueError):
        raise InputError(f'unknown node {node_id}') from None
    if state.frozen[k]:
        return state.cov[k].copy()
    res = last()
    if res is not None and k in set(state.last_window.tolist()):
        if k == 0 and not state.fixes.has_gauge:  # the datum, held fixed
            return np.zeros((6, 6))
        with lock:  # after a freeze being computed ahead, which shares it
            return res.covariance([state.ids[k]])[0]
    raise InputError(f'node {node_id} has not been adjusted yet (its track is still open)')


def covariances(state: WindowState, last: Callable[[], SolveResult | None], node_ids,
                lock: threading.Lock) -> FloatArray:
    """``(k, 6, 6)`` covariances of many nodes at once (see :func:`covariance`); window nodes
    are computed together from the last adjustment (selected inversion rather than one solve
    per node)."""
    ids = np.atleast_1d(np.asarray(node_ids, dtype=np.int64))
    out = np.zeros((ids.size, 6, 6))
    in_window = set(state.last_window.tolist())
    from_window = []
    for k, node in enumerate(ids.tolist()):
        i = state.index.get(int(node))
        if i is None:
            raise InputError(f'unknown node {node}')
        if state.frozen[i]:
            out[k] = state.cov[i]
        elif i in in_window:
            if i != 0 or state.fixes.has_gauge:
                from_window.append(k)
        else:
            raise InputError(f'node {node} has not been adjusted yet (its track is still '
                             'open)')
    if from_window:
        res = last()
        with lock:  # after a freeze being computed ahead, which shares it
            out[from_window] = res.covariance(ids[from_window])  # in blas_threads()
    return out
