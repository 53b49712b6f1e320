"""Offline batch alignment with the aligner's interface: the whole survey re-solved per track.

:class:`BatchAligner` is the replay's ``--aligner batch``: at every track end it solves the full
mixed adjustment (:func:`ga_ros.core.solver.solve`) over every node and connection so far, from
the previous solution (new nodes: chained from their source). No sliding window and no freezing:
the reference the track-window aligner approximates, affordable offline on small surveys.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.measurement import Measurement
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.quality.variance_components import (
    SourceGroups,
    VarianceComponentConfig,
    VarianceComponents,
    solve_with_variance_components,
)
from ga_ros.core.window import UpdateResult
from ga_ros.errors import InputError, SolverError


@dataclass
class BatchPath:
    """Corrected path (fields as the track-window aligner's CorrectedPath)."""

    node_ids: IntArray
    track_ids: IntArray
    stamps_ns: IntArray
    T_world_node: FloatArray
    frozen: np.ndarray


class BatchAligner:
    """Full batch re-solve at each track end (see the module docstring).

    Parameters
    ----------
    config : :class:`ga_ros.core.solver.SolverConfig` (None = defaults).
    T_world_first : (4, 4) datum: pose of the first node, held fixed (identity default).
    """

    def __init__(self, config: object = None, T_world_first: FloatArray | None = None) -> None:
        self.config = config
        self.T_world_first = np.eye(4) if T_world_first is None else np.asarray(T_world_first)
        self.network = ConnectionNetwork()
        self.T: dict[int, FloatArray] = {}
        self.stamps: dict[int, int] = {}
        self.tracks: dict[int, int] = {}
        self.pairs: set[tuple[int, int]] = set()
        self.first: int | None = None
        self.track: int | None = None
        self._result = None
        self._cov: dict[int, FloatArray] | None = None
        #: the variance factors per source of the last refine_batch that estimated them
        self.variance_components: VarianceComponents | None = None

    def add_measurement(self, m: Measurement) -> list[UpdateResult]:
        """Add one connection; a new ``dst_track`` first ends (solves) the current track.

        Raises InputError (nothing changed) for a duplicate, or a source node never seen.
        """
        if (m.src_id, m.dst_id) in self.pairs or (m.dst_id, m.src_id) in self.pairs:
            raise InputError(f'duplicate connection {m.src_id} -> {m.dst_id}')
        if self.first is not None and m.src_id not in self.T:
            raise InputError(f'unknown source node {m.src_id} (not connected to the survey)')
        out = []
        if self.track is not None and m.dst_track != self.track:
            u = self.finish_track()
            if u is not None:
                out.append(u)
        self.track = m.dst_track
        if self.first is None:
            self.first = m.src_id
            self.network.add_node(m.src_id, m.src_track)
            self.T[m.src_id] = self.T_world_first.copy()
            self.tracks[m.src_id] = m.src_track
        if m.dst_id not in self.T:
            self.network.add_node(m.dst_id, m.dst_track)
            self.T[m.dst_id] = self.T[m.src_id] @ m.T_src_dst
            self.tracks[m.dst_id] = m.dst_track
            self.stamps[m.dst_id] = int(m.stamp_ns)
        self.network.add_connection(m.src_id, m.dst_id, m.z, m.cov)
        self.pairs.add((m.src_id, m.dst_id))
        return out

    def _solve(self, variance_groups: SourceGroups | None = None,
               variance_config: VarianceComponentConfig | None = None) -> UpdateResult | None:
        from ga_ros.core.solver import SolverConfig, solve

        if self.first is None:
            return None
        t0 = time.perf_counter()
        ids = self.network.node_ids
        T0 = np.array([self.T[int(i)] for i in ids])
        cfg = self.config or SolverConfig()
        if variance_groups is None:
            res = solve(self.network, T0, cfg, fixed=[self.first])
        else:
            conn = self.network.arrays()
            groups = variance_groups.of(ids[conn.src], ids[conn.dst], conn.z)
            res, self.variance_components = solve_with_variance_components(
                self.network, T0, groups, cfg, fixed=[self.first], config=variance_config,
                split=variance_groups.split())
        if not np.isfinite(res.T_world_node).all():
            raise SolverError('batch solve produced non-finite poses')
        for k, i in enumerate(ids):
            self.T[int(i)] = res.T_world_node[k]
        self._result = res
        self._cov = None
        return UpdateResult(int(self.track if self.track is not None else -1), res.iterations,
                            res.converged, float(res.sigma0_sq),
                            1e3 * (time.perf_counter() - t0), len(ids),
                            self.network.n_connections, len(set(self.tracks.values())), 0,
                            res.reason, 0, res.n_unknowns)

    def finish_track(self) -> UpdateResult | None:
        """Solve the whole survey so far."""
        return self._solve()

    def refine_batch(self, variance_groups: SourceGroups | None = None,
                     variance_config: VarianceComponentConfig | None = None
                     ) -> UpdateResult | None:
        """Same as :meth:`finish_track` (every update is already a full batch); with
        ``variance_groups``, the variance factor of each group is estimated with it (as
        :meth:`ga_ros.core.window.TrackWindowAligner.refine_batch` does)."""
        return self._solve(variance_groups, variance_config)

    def corrected_path(self) -> BatchPath:
        ids = np.array(sorted(self.T), dtype=np.int64)
        return BatchPath(ids, np.array([self.tracks[i] for i in ids], dtype=np.int64),
                         np.array([self.stamps.get(i, -1) for i in ids], dtype=np.int64),
                         np.array([self.T[i] for i in ids]).reshape(-1, 4, 4),
                         np.zeros(len(ids), dtype=bool))

    def covariance(self, node_id: int) -> FloatArray:
        """(6, 6) marginal covariance of a node from the last solve (all blocks computed once)."""
        if self._result is None:
            raise SolverError('no solution yet')
        if self._cov is None:
            ids = self._result.node_ids
            blocks = self._result.covariance(ids)
            self._cov = {int(i): blocks[k] for k, i in enumerate(ids)}
        if int(node_id) not in self._cov:
            raise SolverError(f'node {node_id} is not in the last solution')
        return self._cov[int(node_id)]
