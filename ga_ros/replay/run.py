"""The run loop of a replay: one :class:`ReplayRun` takes the source's items in bag order.

Each measurement goes through the same :class:`ga_ros.pipeline.session.AlignmentSession` call
as in the live node; every window update writes the corrected path, the corrections, the
markers and ``map -> odom`` into the output bag and feeds the corrected path back to the
source. The final outputs are :mod:`ga_ros.replay.finish`'s.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.integration import F2FIntegrator
from ga_ros.core.measurement import Measurement
from ga_ros.core.quality.variance_components import SourceGroups
from ga_ros.inputs.absolute import T_earth_enu
from ga_ros.io.bag_messages import ODOMETRY, measurement_to_odometry
from ga_ros.io.groundtruth import (
    DEFAULT_TOLERANCE_S,
    GroundTruth,
    GroundTruthMatch,
    match_nodes,
    match_stamps,
)
from ga_ros.io.trajectory import Trajectory
from ga_ros.pipeline.absolute import FixFeeder
from ga_ros.pipeline.corrections import Corrections, CorrectionTracker
from ga_ros.pipeline.inputs import InputFrontEnd
from ga_ros.pipeline.map_to_odom import MapToOdom, PeriodicSchedule, without_odom_parent
from ga_ros.pipeline.session import AlignmentSession
from ga_ros.replay.aligner import Aligner, AlignerFactory
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.outputs import ReplayOutputs, misclosure
from ga_ros.replay.result import ReplayResult, plain_fields
from ga_ros.replay.source import SourceItem
from ga_ros.replay.stamped_path import StampedPath


def match_ground_truth(gt: Trajectory, node_ids: IntArray, stamps_ns: IntArray, by: str,
                       tolerance_s: float = DEFAULT_TOLERANCE_S) -> GroundTruthMatch:
    """Ground-truth poses of the estimated nodes.

    Parameters
    ----------
    by : ``'node'`` (same node id, :func:`ga_ros.io.groundtruth.match_nodes`) or ``'stamp'``
        (:func:`ga_ros.io.groundtruth.match_stamps`: at the sample, interpolated, or held).
    tolerance_s : see :func:`ga_ros.io.groundtruth.match_stamps`.
    """
    if by == 'node':
        return match_nodes(gt, node_ids)
    return match_stamps(gt, stamps_ns, tolerance_s)


class Connections:
    """Accepted connections in growing arrays: node ids, ``z`` (m, 6), ``cov`` (m, 6, 6)."""

    def __init__(self) -> None:
        self.n = 0
        self.src = np.zeros(1024, dtype=np.int64)
        self.dst = np.zeros(1024, dtype=np.int64)
        self.z = np.zeros((1024, 6))
        self.cov = np.zeros((1024, 6, 6))

    def append(self, m: Measurement) -> None:
        if self.n == len(self.src):
            grow = len(self.src)
            self.src = np.concatenate([self.src, np.zeros(grow, dtype=np.int64)])
            self.dst = np.concatenate([self.dst, np.zeros(grow, dtype=np.int64)])
            self.z = np.concatenate([self.z, np.zeros((grow, 6))])
            self.cov = np.concatenate([self.cov, np.zeros((grow, 6, 6))])
        k = self.n
        self.src[k], self.dst[k] = m.src_id, m.dst_id
        self.z[k] = m.z
        self.cov[k] = m.cov
        self.n += 1

    def view(self) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
        n = self.n
        return self.src[:n], self.dst[:n], self.z[:n], self.cov[:n]


class ReplayRun:
    """State of one replay between its items: the aligner and its session, the F2F
    integration, node stamps and tracks, the accepted connections, ``map -> odom``.

    Parameters
    ----------
    config : the replay's settings (:class:`ga_ros.replay.config.ReplayConfig`).
    factory : builds the aligner from the datum ``T_world_first`` at the first measurement.
    outputs : where the outputs go.
    result : filled in as the replay goes (counts, rejections, updates).
    gt : the ground truth, or None.
    match_by : ``'node'`` or ``'stamp'`` (:func:`match_ground_truth`).
    """

    def __init__(self, config: ReplayConfig, factory: AlignerFactory, outputs: ReplayOutputs,
                 result: ReplayResult, gt: GroundTruth | None, match_by: str) -> None:
        self.config = config
        self.factory = factory
        self.out = outputs
        self.result = result
        self.gt = None if gt is None else gt.trajectory
        self.gt_source = '' if gt is None else gt.describe()
        self.match_by = match_by
        self.aligner: Aligner | None = None
        self.session: AlignmentSession | None = None
        self.f2f: F2FIntegrator | None = None
        self.stamps: dict[int, int] = {}
        self.tracks: dict[int, int] = {}
        self.conn = Connections()
        self.frozen: np.ndarray | None = None
        self.last_ns = 0
        self.source: Any = None
        self.first_id: int | None = None
        self.odom: MapToOdom | None = None
        self.tf_schedule = PeriodicSchedule(config.transform_publish_period_sec)
        #: header stamp minus log time of the newest measurement (stamps of map -> odom)
        self.stamp_offset_ns = 0
        self.tf_removed = 0
        self.fixes = FixFeeder()  # absolute fixes waiting for their node
        #: the variance group (source) of every connection the aligner took
        self.groups = SourceGroups()
        #: positions (m, map frame) of the fixes read, for the plot
        self.fix_xyz: list[FloatArray] = []
        self.earth_written = False  # earth -> map on /tf_static (NavSatFix inputs)
        #: the keyframes moved or added since the last corrections message (as the node's)
        self.corrections = CorrectionTracker(config.outputs.corrections)
        #: called with each corrections message's content (e.g. the map of ``--map``)
        self.on_corrections: Callable[[Corrections], None] | None = None
        self.odom_tf_stamp = -1  # stamp of the last odom -> base_link written
        #: the corrected path with the replay's stamps and its message, kept in step with the
        #: aligner (the rows an update can change are read, not the whole path)
        self.path = StampedPath(config.outputs.map_frame, self.stamps, self.first_stamp,
                                self.first_stamp_of_ground_truth)

    def _first_pose(self, m: Measurement) -> FloatArray | None:
        if self.gt is None or not self.config.anchor_to_ground_truth:
            return None
        s = self.stamps.get(m.src_id)
        hit = self.match(np.array([m.src_id]), np.array([s if s is not None else -1]))
        return hit.T_world_gt[0].copy() if hit.n_matched else None

    def match(self, node_ids: IntArray, stamps_ns: IntArray) -> GroundTruthMatch:
        """Ground-truth poses of the nodes (ground truth required)."""
        assert self.gt is not None
        return match_ground_truth(self.gt, node_ids, stamps_ns, self.match_by,
                                  self.config.ground_truth_tolerance_s)

    def step(self, item: SourceItem) -> None:
        """Take one item of the source: its fixes, its measurement or its rejection."""
        self._stamp_offset(item)
        self._advance(item.log_ns)
        self._step(item)

    def _stamp_offset(self, item: SourceItem) -> None:
        """Header stamp minus log time of the newest odometry keyframe or measurement (the
        stamps of ``map -> odom``: the input's time base, sim time included)."""
        if item.measurement is not None:
            self.stamp_offset_ns = int(item.measurement.stamp_ns) - int(item.log_ns)
        elif item.node_stamps:
            self.stamp_offset_ns = max(int(v) for v in item.node_stamps.values()) - int(
                item.log_ns)

    def _map_to_odom(self) -> MapToOdom | None:
        """The ``map -> odom`` state, made at the first item when the source has standard
        inputs (``odom`` exists from the first odometry message; the map is then the identity
        until something places it), else at the first measurement."""
        if self.odom is None:
            front = getattr(self.source, 'front', None)
            if isinstance(front, InputFrontEnd):
                self.odom = MapToOdom(front, datum=self._datum())
        return self.odom

    def _datum(self) -> str:
        return str(getattr(self.config.aligner, 'datum', 'first_node'))

    def _advance(self, log_ns: int) -> None:
        """Move the output clock to ``log_ns`` (never back) and write the periodic
        ``map -> odom`` due until then, before anything logged at the new time: one time base,
        log times non-decreasing in file order."""
        self.last_ns = max(self.last_ns, int(log_ns))
        self._tf_tick(self.last_ns)

    def _tf_tick(self, log_ns: int) -> None:
        """``map -> odom`` at the due times of the fixed period, with the latest correction,
        from the first odometry message on (header stamps never step back)."""
        odom = self._map_to_odom()
        if not self.config.tf or odom is None or odom.latest() is None:
            return
        for t in self.tf_schedule.due(log_ns):
            self.out.map_to_odom(odom.T_map_odom, odom.stamp(t + self.stamp_offset_ns), t)

    def copy_tf(self, topic: str, msgtype: str, data: bytes | None, msg: Any,
                log_ns: int) -> None:
        """Copy an input ``/tf`` or ``/tf_static`` message without the transforms that would
        give ``odom`` a second parent (ours is the one ``map -> odom``), at its log time on the
        output clock (the final outputs come after it)."""
        self._advance(log_ns)
        log_ns = self.last_ns
        if msgtype == 'tf2_msgs/msg/TFMessage' and msg is not None:
            kept, removed = without_odom_parent(msg, self.config.outputs.odom_frame)
            if removed:
                self.tf_removed += removed
                if kept.transforms:
                    self.out.copy(topic, msgtype, None, kept, log_ns)
                return
        self.out.copy(topic, msgtype, data, msg, log_ns)

    def _step(self, item: SourceItem) -> None:
        self.last_ns = max(self.last_ns, int(item.log_ns))
        if item.node_stamps:
            for k, v in item.node_stamps.items():
                self.stamps.setdefault(int(k), int(v))
        m = item.measurement
        if item.fixes:
            self.fix_xyz += [np.asarray(f.term.fix.T_map_sensor, float)[:3, 3]
                             for f in item.fixes]
            odom = self._map_to_odom()
            if odom is not None:
                odom.add_fixes(item.fixes)   # they place the map until the first update
            self.fixes.add(item.fixes)
            self._add_fixes()
            self._earth_to_map(item)
        if m is None:
            if item.error:
                self.reject(item.error)
            return
        self.first_id = m.src_id if self.first_id is None else self.first_id
        if self.session is None:
            T0 = self._first_pose(m)
            self.aligner = self.factory(T0)
            self.session = AlignmentSession(aligner=self.aligner)
            self.f2f = F2FIntegrator(T0)
            if self._map_to_odom() is None:
                self.odom = MapToOdom(None, self.f2f, datum=self._datum())
            else:
                self.odom.f2f = self.f2f   # the F2F path's integration (odom.add)
        out = self.session.step(m)
        if out.solver_failed:  # a failed update: the aligner keeps its previous estimate
            self.reject(f'solver: {out.error}')
            return
        if not out.accepted:
            self.reject(f'aligner: {out.error}')
            return
        assert self.odom is not None
        self.result.n_measurements += 1
        self.stamps.setdefault(m.dst_id, int(m.stamp_ns))
        self.tracks.setdefault(m.src_id, m.src_track)
        self.tracks.setdefault(m.dst_id, m.dst_track)
        self.admitted(out)
        self._odom_to_base()
        if item.data is not None:
            self.out.measurement(ODOMETRY, item.data, None, self.last_ns)
        else:
            self.out.measurement(ODOMETRY, None, measurement_to_odometry(m), self.last_ns)
        if self.fixes.waiting:
            self._add_fixes()
        for u in out.updates:
            self.update(u)
        if self.odom.placed_by == 'identity':  # the provisional path before any update
            traj = self.corrected()
            self.odom.update(traj.node_ids, traj.T_world_node, adjusted=False)

    def _odom_to_base(self) -> None:
        """REP 105 ``odom -> base_link`` at each new keyframe of the odometry chain when it
        is the measurements' own (stereo VO, measurement bags: the frame-to-frame integration
        that ``map -> odom`` refers to); standard inputs bring theirs on the copied ``/tf``."""
        if not self.config.tf or self.odom is None or self.odom.front is not None:
            return
        latest = self.odom.latest()
        if latest is None or int(latest[1]) <= self.odom_tf_stamp:
            return
        self.odom_tf_stamp = int(latest[1])
        self.out.odom_to_base(latest[0], self.odom_tf_stamp, self.last_ns)

    def _earth_to_map(self, item: SourceItem) -> None:
        """REP 105 ``earth -> map`` on ``/tf_static``, once the NavSatFix inputs' ENU origin is
        known, when the map frame is the fixes' frame (``datum: fixes``)."""
        datum = getattr(self.source, 'earth_datum', lambda: None)()
        if (self.earth_written or datum is None or not self.config.tf
                or getattr(self.config.aligner, 'datum', None) != 'fixes'):
            return
        self.earth_written = True
        stamp = min(int(f.term.fix.stamp_ns) for f in item.fixes)
        self.out.earth_to_map(T_earth_enu(datum), stamp, item.log_ns)

    def admitted(self, out: Any) -> None:
        """The measurements the aligner took in a session step (held ones whose gap was filled,
        reversed ones, bridges) go into the frame-to-frame integration and the network."""
        assert self.odom is not None
        for a in out.admitted:
            self.odom.add(a)  # its F2F integration (without standard inputs)
            self.conn.append(a)
            if self.config.variance_components != 'off' or self.config.calibrate:
                self.groups.add(a)
        for text in out.notes:
            if text.startswith('held measurement rejected: '):
                self.reject('aligner: ' + text[len('held measurement rejected: '):])

    def _add_fixes(self) -> None:
        """Give the session the fixes whose node its aligner has (a fix on a keyframe that the
        next measurement brings waits for it), as the node does; refused ones are counted as
        rejections. An aligner without fixes (``--aligner batch``) rejects them, counted."""
        if self.session is None:
            return
        if not hasattr(self.aligner, 'add_fix'):
            for _ in self.fixes.waiting:
                self.reject('absolute: this aligner takes no fixes (--aligner batch); use the '
                            'track-window aligner (--aligner window, the default)')
            self.fixes.waiting = []
            return
        for error in self.fixes.flush(self.session):
            self.reject(f'absolute: {error}')

    def reject(self, reason: str) -> None:
        """Count a rejection (:meth:`ReplayResult.reject`)."""
        self.result.reject(reason)

    def update(self, u: Any, per_track: bool = True) -> None:
        """Outputs of an aligner update (None: none): path, markers, ``map -> odom`` and the
        corrected path fed back to the source; counted among the result's ``updates`` (and its
        quality among ``per_track``) unless ``per_track`` is False (the final batch)."""
        if u is None:
            return
        qc = getattr(u, 'quality', None)
        entry = None if qc is None else {'track_id': int(u.track_id), **qc.as_dict()}
        if per_track:
            self.result.updates.append(plain_fields(u))
            reason = str(getattr(u, 'reason', ''))
            if reason.startswith('failed'):
                self.result.failed_updates += 1
                if len(self.result.failed_update_examples) < 10:
                    self.result.failed_update_examples.append(f'track {u.track_id}: {reason}')
            if entry is not None:
                self.result.quality.setdefault('per_track', []).append(entry)
        if entry is not None:
            self.result.quality['final'] = entry
        t0 = time.thread_time()
        self._outputs(per_track)
        if per_track:   # what the outputs of this update cost (this thread's CPU)
            self.result.updates[-1]['outputs_cpu_ms'] = 1e3 * (time.thread_time() - t0)

    def _outputs(self, per_track: bool) -> None:
        """Everything written after an update (``update``): path, corrections, markers,
        ``map -> odom`` and the feedback to the source."""
        traj, corr_stamps, top = self._synced(every_row=not per_track)
        self.out.path_bytes(self.path.message(top), self.last_ns)
        self._corrections(traj, corr_stamps, every_row=not per_track)
        self.markers(traj, stamp_ns=top)
        if self.odom is not None:
            self.odom.update(traj.node_ids, traj.T_world_node, adjusted=True)
        feedback = getattr(self.source, 'on_corrected', None)
        if feedback is not None:
            feedback(traj.node_ids, traj.T_world_node)

    def _corrections(self, traj: Trajectory, stamps: IntArray, every_row: bool) -> None:
        """The corrections message of an update, as the node publishes it: the aligner's node
        stamps (the replay's own only where the aligner has none: ``stamps``) and its newest
        stamp in the header; ``every_row`` after the final batch."""
        path = Trajectory(stamps, traj.T_world_node, traj.node_ids, traj.track_ids,
                          traj.frame_id)
        c = self.corrections.after_update(self.aligner, path, every_row=every_row)
        if c is not None:
            self.out.corrections(c, int(stamps[-1]) if len(stamps) else 0, self.last_ns)
            if self.on_corrections is not None:
                self.on_corrections(c)

    def first_stamp_of_ground_truth(self) -> int | None:
        """The ground truth's stamp of the first node (None: no ground truth matched by node,
        or none for that node)."""
        if self.gt is not None and self.first_id is not None and self.match_by == 'node':
            hit = np.flatnonzero(self.gt.node_ids == self.first_id)
            if hit.size:
                return int(self.gt.stamps_ns[hit[0]])
        return None

    def first_stamp(self, stamps: IntArray, node_ids: IntArray) -> int:
        """Acquisition time of the first node when no message carried it (the measurement
        encoding stamps a connection at its destination): the ground truth's stamp of that node
        id when known, else one median node interval before the second node."""
        if self.gt is not None and self.first_id is not None and self.match_by == 'node':
            hit = np.flatnonzero(self.gt.node_ids == self.first_id)
            if hit.size:
                return int(self.gt.stamps_ns[hit[0]])
        known = np.sort(stamps[stamps >= 0])
        if known.size >= 2:
            return int(known[0] - np.median(np.diff(known)))
        return int(known[0]) if known.size else 0

    def _synced(self, every_row: bool = False) -> tuple[Trajectory, IntArray, int]:
        """The corrected path kept in step with the aligner (:class:`StampedPath`, views valid
        until the next call), the corrections' stamps and the newest stamp."""
        assert self.aligner is not None
        cp, stamps, corr, top = self.path.sync(self.aligner, self.first_id, every_row)
        self.frozen = cp.frozen if self.path.mirror.has_frozen else None
        return (Trajectory(stamps, cp.T_world_node, cp.node_ids, cp.track_ids,
                           self.config.outputs.map_frame), corr, top)

    def corrected(self) -> Trajectory:
        """The aligner's corrected path with node stamps and tracks, in ``map_frame`` (a
        copy)."""
        traj, _, _ = self._synced()
        self.frozen = None if self.frozen is None else self.frozen.copy()
        return Trajectory(traj.stamps_ns.copy(), traj.T_world_node.copy(),
                          traj.node_ids.copy(), traj.track_ids.copy(), traj.frame_id)

    def corrected_from_scratch(self) -> Trajectory:
        """:meth:`corrected` from the whole path, the rules applied to every row (what
        :class:`StampedPath` keeps up to date; the tests' reference)."""
        assert self.aligner is not None
        cp = self.aligner.corrected_path()
        node_ids = np.asarray(cp.node_ids, dtype=np.int64)
        frozen = getattr(cp, 'frozen', None)
        self.frozen = None if frozen is None else np.asarray(frozen, dtype=bool).reshape(-1)
        T = np.asarray(cp.T_world_node, dtype=float).reshape(-1, 4, 4)
        tracks = np.asarray(getattr(cp, 'track_ids', [self.tracks.get(int(n), -1)
                                                      for n in node_ids]), dtype=np.int64)
        cp_stamps = getattr(cp, 'stamps_ns', None)
        stamps = np.array([self.stamps.get(int(n), -1) for n in node_ids], dtype=np.int64)
        first = node_ids == self.first_id
        if first.any() and stamps[first][0] < 0:  # the aligner gives it node 1's stamp
            stamps[first] = self.first_stamp(stamps, node_ids)
        if cp_stamps is not None:
            cp_stamps = np.asarray(cp_stamps, dtype=np.int64)
            stamps = np.where(stamps < 0, cp_stamps, stamps)
        if (stamps < 0).any():  # only the very first node can be unknown
            stamps = np.where(stamps < 0, self.first_stamp(stamps, node_ids), stamps)
        return Trajectory(stamps, T, node_ids, tracks, self.config.outputs.map_frame)

    def markers(self, traj: Trajectory, everything: bool = False,
                stamp_ns: int | None = None) -> None:
        """Markers of the connections that can still move (a non-frozen end; all at the end),
        header stamped ``stamp_ns`` (default: the newest of the path's stamps)."""
        n = len(traj)
        if n == 0 or self.conn.n == 0:
            return
        src, dst, z, cov = self.conn.view()
        order = np.argsort(traj.node_ids)
        ids_sorted = traj.node_ids[order]
        pos_s = np.clip(np.searchsorted(ids_sorted, src), 0, n - 1)
        pos_d = np.clip(np.searchsorted(ids_sorted, dst), 0, n - 1)
        ok = (ids_sorted[pos_s] == src) & (ids_sorted[pos_d] == dst)
        i_src, i_dst = order[pos_s], order[pos_d]
        if not everything:
            movable = self._movable(traj)
            ok &= movable[i_src] | movable[i_dst]
        if not ok.any():
            return
        d = misclosure(traj.T_world_node, i_src[ok], i_dst[ok], z[ok], cov[ok])
        w = self._connection_w(src, dst)
        if w is not None:  # quality control on: colour by |w| (ga_ros.ros.conversions)
            d = w[ok]
        self.out.markers(traj.T_world_node[:, :3, 3], i_src[ok], i_dst[ok], d, self.last_ns,
                         int(traj.stamps_ns.max()) if stamp_ns is None else stamp_ns)

    def _connection_w(self, src: IntArray, dst: IntArray) -> FloatArray | None:
        """(m,) ``|w|`` of the connections ``src -> dst`` (node ids) at their last adjustment
        (NaN: not tested), or None when the aligner has no quality control."""
        if not getattr(getattr(self.aligner, 'config', None), 'quality', False):
            return None
        a_src, a_dst, _, _, _ = self.aligner.connection_arrays()
        w_of = dict(zip(zip(a_src.tolist(), a_dst.tolist()), self.aligner.connection_w().tolist()))
        return np.array([w_of.get(pair, np.nan) for pair in zip(src.tolist(), dst.tolist())])

    def _movable(self, traj: Trajectory) -> np.ndarray:
        """(n,) True for nodes the aligner may still move (not frozen; else the last tracks)."""
        if self.frozen is not None and len(self.frozen) == len(traj):
            return ~self.frozen
        tracks = np.unique(traj.track_ids)
        window = getattr(self.config.aligner, 'window_tracks', 5)
        return np.isin(traj.track_ids, tracks[-window:])

