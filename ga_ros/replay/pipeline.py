"""The offline replay: bag -> [stereo VO] -> track-window alignment -> output bag, TUM, PNG, JSON.

Runs as fast as the CPU allows (no real-time pacing) and without ROS. The aligner sees exactly
what the alignment node would see, in bag order, so a replay reproduces the live pipeline's
numbers.

Outputs (in ``out_dir``)
------------------------
``replay_bag/`` (mcap rosbag2: corrected path after every track update, corrected poses with
covariance, the measurements, markers, the F2F path and the ground truth when the input has it),
``trajectory_ga.tum``, ``trajectory_f2f.tum``, ``trajectory_gt.tum`` (when ground truth is
present), ``trajectory.png`` and ``summary.json``. Log times of the output bag follow the input's
(:mod:`ga_ros.replay.outputs`).

Ground truth comes from a file or a topic (:mod:`ga_ros.io.groundtruth`), matched to the
keyframes by node id when both have them, else by stamp with interpolation.

A bag cut short (a truncated mcap) is replayed up to the damage: the result then carries a
warning, not an error.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field, is_dataclass, replace
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.integration import F2FIntegrator
from ga_ros.core.measurement import Measurement
from ga_ros.errors import FormatError, GaError, InputError, SolverError
from ga_ros.eval.metrics import TrajectoryError, trajectory_error
from ga_ros.inputs.absolute import T_earth_enu
from ga_ros.inputs.messages import INPUT_TYPES
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import ODOMETRY, measurement_to_odometry
from ga_ros.io.groundtruth import (
    DEFAULT_TOLERANCE_S,
    GroundTruth,
    GroundTruthMatch,
    match_nodes,
    match_stamps,
    read_ground_truth_file,
    read_ground_truth_topic,
)
from ga_ros.io.topic_plan import TopicConfig, TopicPlan, plan_topics
from ga_ros.io.trajectory import Trajectory
from ga_ros.pipeline.absolute import FixFeeder
from ga_ros.pipeline.inputs import InputFrontEnd
from ga_ros.pipeline.map_to_odom import (
    TRANSFORM_PERIOD_S,
    MapToOdom,
    PeriodicSchedule,
    without_odom_parent,
)
from ga_ros.pipeline.session import AlignmentSession
from ga_ros.replay.inputs import InputSource, InputTopics, plan_inputs
from ga_ros.replay.outputs import OutputConfig, ReplayOutputs, misclosure
from ga_ros.replay.source import SourceItem, bag_measurements


class Aligner(Protocol):
    """What the replay needs of :class:`ga_ros.core.window.TrackWindowAligner`."""

    def add_measurement(self, m: Measurement) -> list[Any]: ...

    def finish_track(self) -> Any: ...

    def refine_batch(self) -> Any: ...

    def corrected_path(self) -> Any: ...

    def covariance(self, node_id: int) -> FloatArray: ...


AlignerFactory = Callable[[FloatArray | None], Aligner]


@dataclass(frozen=True)
class ReplayConfig:
    """Settings of one replay.

    Attributes
    ----------
    topics : input topic names (and the source: measurements or stereo images).
    outputs : output topic names, map frame, bag name.
    aligner : :class:`ga_ros.core.window.AlignerConfig` (None = its defaults), or a
        :class:`ga_ros.core.solver.SolverConfig` with ``aligner_kind='batch'``.
    aligner_kind : ``'window'`` (the live node's track-window aligner) or ``'batch'``.
    vo : configuration object of the stereo VO (None = its defaults); used for image bags.
    refine_batch : run a final full batch refinement after the last track.
    pose_covariance : write each corrected pose's marginal covariance (else zeros).
    anchor_to_ground_truth : start the F2F and corrected paths at the ground-truth pose of the
        first node (the datum) when the bag has ground truth; else at the identity.
    plot : write the PNG plot.
    progress : show a progress bar on stderr.
    inputs : standard inputs (odometry / pose topics, constraints, track boundaries); when it
        has inputs they are the source (:mod:`ga_ros.replay.inputs`).
    ground_truth_file : TUM, EuRoC or KITTI ground truth (:mod:`ga_ros.io.groundtruth`),
        matched by stamp; replaces the bag's ground truth.
    ground_truth_format : ``'auto'``, ``'tum'``, ``'euroc'`` or ``'kitti'``.
    ground_truth_times, ground_truth_rate_hz, ground_truth_start_s : stamps of a KITTI file
        (its ``times.txt``, or a rate in Hz; plus a start time in s).
    ground_truth_tolerance_s : largest gap between ground-truth samples to interpolate across,
        and largest distance to hold the first / last sample (s).
    tf : write ``map -> odom`` on ``/tf`` every ``transform_publish_period_sec`` of the bag's
        log time, from the first measurement to the end, with the latest correction (and copy
        the input bag's ``/tf``, ``/tf_static`` without the transforms that would give ``odom``
        a second parent, counted in the summary's ``frames``).
    transform_publish_period_sec : period of ``map -> odom`` in the output bag, s (as the
        node's parameter of the same name).
    covariance_policy : a measurement covariance that is not positive definite: ``'reject'``
        (as the live node by default) or ``'repair'`` (eigenvalue clipping).
    """

    topics: TopicConfig = TopicConfig()
    outputs: OutputConfig = OutputConfig()
    aligner: Any = None
    aligner_kind: str = 'window'
    vo: Any = None
    refine_batch: bool = False
    pose_covariance: bool = True
    anchor_to_ground_truth: bool = True
    plot: bool = True
    progress: bool = False
    inputs: InputTopics = InputTopics()
    ground_truth_file: str = ''
    ground_truth_format: str = 'auto'
    ground_truth_times: str = ''
    ground_truth_rate_hz: float = 0.0
    ground_truth_start_s: float = 0.0
    ground_truth_tolerance_s: float = DEFAULT_TOLERANCE_S
    tf: bool = True
    covariance_policy: str = 'reject'
    transform_publish_period_sec: float = TRANSFORM_PERIOD_S


@dataclass
class ReplayResult:
    """What a replay did (also written to ``summary.json``).

    ``errors`` maps ``'f2f'`` and ``'ga'`` to :class:`TrajectoryError` against ground truth
    (empty without ground truth). ``error`` is the message of the failure that cut the replay
    short (the outputs then hold everything up to it), else None. ``quality`` (aligner
    ``quality`` on): ``per_track``, the :class:`ga_ros.core.quality.QualitySummary` of every
    update with its ``track_id``, and ``final``, that of the last adjustment. ``notes``: what
    the user should know about an unusual but valid run (e.g. a robot that did not move).
    ``ground_truth`` says what ground truth was used and how much of it matched; ``warnings``
    what the replay went on despite (e.g. a bag cut short).
    """

    bag: str
    source: str
    out_dir: str
    n_inputs: int = 0
    n_measurements: int = 0
    rejected: dict[str, int] = field(default_factory=dict)
    rejected_examples: list[str] = field(default_factory=list)
    n_nodes: int = 0
    n_tracks: int = 0
    updates: list[dict[str, Any]] = field(default_factory=list)
    seconds: float = 0.0
    errors: dict[str, TrajectoryError] = field(default_factory=dict)
    files: dict[str, str] = field(default_factory=dict)
    output_counts: dict[str, int] = field(default_factory=dict)
    error: str | None = None
    source_stats: dict[str, Any] = field(default_factory=dict)
    corrected: Trajectory | None = None
    quality: dict[str, Any] = field(default_factory=dict)
    frames: dict[str, Any] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    ground_truth: str = ''
    warnings: list[str] = field(default_factory=list)
    gaps: dict[str, Any] = field(default_factory=dict)

    @property
    def rate(self) -> float:
        """Inputs (measurements or stereo pairs) processed per second."""
        return self.n_inputs / self.seconds if self.seconds > 0 else float('nan')

    def as_dict(self) -> dict[str, Any]:
        return {
            'bag': self.bag, 'source': self.source, 'out_dir': self.out_dir,
            'n_inputs': self.n_inputs, 'n_measurements': self.n_measurements,
            'rejected': self.rejected, 'rejected_examples': self.rejected_examples,
            'n_nodes': self.n_nodes, 'n_tracks': self.n_tracks, 'updates': self.updates,
            'seconds': self.seconds, 'inputs_per_s': self.rate,
            'errors_vs_ground_truth': {k: v.as_dict() for k, v in self.errors.items()},
            'files': self.files, 'output_counts': self.output_counts, 'error': self.error,
            'source_stats': self.source_stats, 'quality': self.quality, 'frames': self.frames,
            'notes': self.notes, 'ground_truth': self.ground_truth, 'warnings': self.warnings,
            'gaps': self.gaps}


def default_aligner_factory(config: Any = None, kind: str = 'window') -> AlignerFactory:
    """A factory of the aligner used by the replay.

    Parameters
    ----------
    config : :class:`ga_ros.core.window.AlignerConfig` (``kind='window'``) or
        :class:`ga_ros.core.solver.SolverConfig` (``kind='batch'``); None = defaults.
    kind : ``'window'`` (:class:`ga_ros.core.window.TrackWindowAligner`, the live node's) or
        ``'batch'`` (:class:`ga_ros.replay.batch.BatchAligner`, full re-solve per track).
    """
    if kind == 'batch':
        from ga_ros.replay.batch import BatchAligner

        return lambda T_world_first: BatchAligner(config, T_world_first=T_world_first)
    if kind != 'window':
        raise InputError(f"aligner must be 'window' or 'batch', got {kind!r}")
    try:
        from ga_ros.core.window import AlignerConfig, TrackWindowAligner
    except ImportError as exc:
        raise InputError(f'the track-window aligner is not available ({exc}); '
                         'use the batch aligner instead') from exc
    cfg = config if config is not None else AlignerConfig()

    def make(T_world_first: FloatArray | None) -> Aligner:
        return TrackWindowAligner(cfg, T_world_first=T_world_first)

    return make


def _as_dict(obj: Any) -> dict[str, Any]:
    if obj is None:
        return {}
    if isinstance(obj, dict):
        d = dict(obj)
    elif is_dataclass(obj):
        d = asdict(obj)
    else:
        d = {k: v for k, v in vars(obj).items() if not k.startswith('_')}
    return {k: (v.item() if isinstance(v, np.generic) else v) for k, v in d.items()
            if isinstance(v, (int, float, str, bool, np.generic, type(None), dict))}


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


class _Connections:
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


class _Run:
    """State of one replay (kept out of the public function for readability)."""

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
        self.conn = _Connections()
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
        self.earth_written = False  # earth -> map on /tf_static (NavSatFix inputs)

    def _first_pose(self, m: Measurement) -> FloatArray | None:
        if self.gt is None or not self.config.anchor_to_ground_truth:
            return None
        s = self.stamps.get(m.src_id)
        hit = self._match(np.array([m.src_id]), np.array([s if s is not None else -1]))
        return hit.T_world_gt[0].copy() if hit.n_matched else None

    def _match(self, node_ids: IntArray, stamps_ns: IntArray) -> GroundTruthMatch:
        assert self.gt is not None
        return match_ground_truth(self.gt, node_ids, stamps_ns, self.match_by,
                                  self.config.ground_truth_tolerance_s)

    def step(self, item: SourceItem) -> None:
        self._advance(item.log_ns)
        self._step(item)

    def _advance(self, log_ns: int) -> None:
        """Move the output clock to ``log_ns`` (never back) and write the periodic
        ``map -> odom`` due until then, before anything logged at the new time: one time base,
        log times non-decreasing in file order."""
        self.last_ns = max(self.last_ns, int(log_ns))
        self._tf_tick(self.last_ns)

    def _tf_tick(self, log_ns: int) -> None:
        """``map -> odom`` at the due times of the fixed period, with the latest correction."""
        if not self.config.tf or self.odom is None or self.odom.T_map_odom is None:
            return
        for t in self.tf_schedule.due(log_ns):
            self.out.map_to_odom(self.odom.T_map_odom, t + self.stamp_offset_ns, t)

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
            self.fixes.add(item.fixes)
            self._add_fixes()
            self._earth_to_map(item)
        if m is None:
            if item.error:
                self._reject(item.error)
            return
        self.first_id = m.src_id if self.first_id is None else self.first_id
        if self.session is None:
            T0 = self._first_pose(m)
            self.aligner = self.factory(T0)
            self.session = AlignmentSession(aligner=self.aligner)
            self.f2f = F2FIntegrator(T0)
            front = getattr(self.source, 'front', None)
            self.odom = MapToOdom(front if isinstance(front, InputFrontEnd) else None, self.f2f)
        out = self.session.step(m)
        if out.solver_failed:  # a failed update: the aligner keeps its previous estimate
            self._reject(f'solver: {out.error}')
            return
        if not out.accepted:
            self._reject(f'aligner: {out.error}')
            return
        assert self.odom is not None
        self.stamp_offset_ns = int(m.stamp_ns) - int(item.log_ns)
        self.result.n_measurements += 1
        self.stamps.setdefault(m.dst_id, int(m.stamp_ns))
        self.tracks.setdefault(m.src_id, m.src_track)
        self.tracks.setdefault(m.dst_id, m.dst_track)
        self._admitted(out)
        if item.data is not None:
            self.out.measurement(ODOMETRY, item.data, None, self.last_ns)
        else:
            self.out.measurement(ODOMETRY, None, measurement_to_odometry(m), self.last_ns)
        if self.fixes.waiting:
            self._add_fixes()
        for u in out.updates:
            self._update(u)
        if self.odom.T_map_odom is None:  # the correction before the first update
            traj = self.corrected()
            self.odom.update(traj.node_ids, traj.T_world_node)

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

    def _admitted(self, out: Any) -> None:
        """The measurements the aligner took in a session step (held ones whose gap was filled,
        reversed ones, bridges) go into the frame-to-frame integration and the network."""
        assert self.odom is not None
        for a in out.admitted:
            self.odom.add(a)  # its F2F integration (without standard inputs)
            self.conn.append(a)
        for text in out.notes:
            if text.startswith('held measurement rejected: '):
                self._reject('aligner: ' + text[len('held measurement rejected: '):])

    def _add_fixes(self) -> None:
        """Give the aligner the fixes whose node it has (a fix on a keyframe that the next
        measurement brings waits for it); refused ones are counted as rejections."""
        for error in self.fixes.flush(
                self.aligner, self.session.gaps.anchor if self.session is not None else None):
            self._reject(f'absolute: {error}')

    def _reject(self, reason: str) -> None:
        key = reason.split(':', 1)[0]
        self.result.rejected[key] = self.result.rejected.get(key, 0) + 1
        if len(self.result.rejected_examples) < 10:
            self.result.rejected_examples.append(reason)

    def _update(self, u: Any) -> None:
        if u is None:
            return
        self.result.updates.append(_as_dict(u))
        qc = getattr(u, 'quality', None)
        if qc is not None:
            entry = {'track_id': int(u.track_id), **qc.as_dict()}
            self.result.quality.setdefault('per_track', []).append(entry)
            self.result.quality['final'] = entry
        traj = self.corrected()
        self.out.path(traj, self.last_ns)
        self._markers(traj)
        if self.odom is not None:
            self.odom.update(traj.node_ids, traj.T_world_node)
        feedback = getattr(self.source, 'on_corrected', None)
        if feedback is not None:
            feedback(traj.node_ids, traj.T_world_node)

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

    def corrected(self) -> Trajectory:
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

    def _markers(self, traj: Trajectory, everything: bool = False) -> None:
        """Markers of the connections that can still move (a non-frozen end; all at the end)."""
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
                         int(traj.stamps_ns.max()))

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

    def finish_stationary(self) -> None:
        """Outputs of a robot that did not move: its first keyframe at the datum, and a note.
        Used when keyframes were made but no motion between two of them reached the aligner."""
        node, stamp = min(self.stamps.items(), key=lambda kv: kv[1])
        T0 = np.eye(4)
        if self.gt is not None and self.config.anchor_to_ground_truth:
            hit = self._match(np.array([node]), np.array([stamp]))
            if hit.n_matched:
                T0 = hit.T_world_gt[0].copy()
        traj = Trajectory(np.array([stamp], dtype=np.int64), T0[None],
                          np.array([node], dtype=np.int64), np.zeros(1, dtype=np.int64),
                          self.config.outputs.map_frame)
        res = self.result
        res.corrected = traj
        res.n_nodes, res.n_tracks = 1, 1
        n = len(self.stamps)
        res.notes.append(f'the robot did not move: {n} keyframe{"s" if n > 1 else ""}, '
                         'stationary trajectory written')
        self.out.path(traj, self.last_ns)
        self.out.poses(traj, np.zeros((1, 6, 6)), self.last_ns)
        self.out.odometry(traj, np.zeros((1, 6, 6)), self.last_ns)
        self.out.path(traj, self.last_ns, topic=self.config.outputs.f2f_topic)
        self.out.tum('trajectory_ga.tum', traj)
        self.out.tum('trajectory_f2f.tum', traj)
        front = getattr(self.source, 'front', None)
        odom = MapToOdom(front if isinstance(front, InputFrontEnd) else None)
        T_map_odom = odom.update(traj.node_ids, traj.T_world_node)
        if self.config.tf and T_map_odom is not None:
            self.out.map_to_odom(T_map_odom, stamp, self.last_ns)
        if self.gt is not None and len(self.gt):
            self.out.ground_truth(self.gt, self.last_ns)
            self.out.tum('trajectory_gt.tum', self.gt)

    def finish(self) -> None:
        res = self.result
        if self.aligner is None:
            return
        try:
            assert self.session is not None
            flushed = self.session.flush_gaps()  # held measurements: in, bridged if need be
            self._admitted(flushed)
            for u in flushed.updates:
                self._update(u)
            self._update(self.aligner.finish_track())
            if self.config.refine_batch:
                self._update(self.aligner.refine_batch())
        except GaError as exc:
            res.error = (res.error + '; ' if res.error else '') + f'final update failed: {exc}'
        traj = self.corrected()
        res.corrected = traj
        counts = self.session.counts
        res.gaps = {'bridges': counts.bridges, 'reversed_measurements': counts.reversed,
                    'unjoined_nodes': traj.node_ids[self.session.unjoined(traj.node_ids)].tolist()}
        if self.config.tf and self.odom is not None and self.odom.T_map_odom is not None:
            self.out.map_to_odom(self.odom.T_map_odom, self.last_ns + self.stamp_offset_ns,
                                 self.last_ns)   # the final correction, at the end
        self._markers(traj, everything=True)
        res.n_nodes = len(traj)
        res.n_tracks = int(np.unique(traj.track_ids).size)
        covs = np.zeros((len(traj), 6, 6))
        if self.config.pose_covariance:
            batch = getattr(self.aligner, 'covariances', None)  # all blocks at once, if offered
            try:
                if batch is None:
                    raise SolverError('no batch covariances')
                covs[:] = np.asarray(batch(traj.node_ids), dtype=float).reshape(-1, 6, 6)
            except GaError:
                for k, n in enumerate(traj.node_ids):
                    try:
                        covs[k] = self.aligner.covariance(int(n))
                    except GaError:  # unknown: zero, as ROS does for an unknown covariance
                        pass
        self.out.poses(traj, covs, self.last_ns)
        self.out.odometry(traj, covs, self.last_ns)
        # F2F path over the nodes it reached, in node order of the corrected path
        assert self.f2f is not None
        f_ids = [int(n) for n in traj.node_ids if int(n) in self.f2f.poses]
        f2f = Trajectory(np.array([self.stamps.get(n, traj.stamps_ns[0]) for n in f_ids],
                                  dtype=np.int64),
                         np.array([self.f2f.poses[n] for n in f_ids]).reshape(-1, 4, 4),
                         np.array(f_ids, dtype=np.int64),
                         np.array([self.f2f.tracks.get(n, -1) for n in f_ids], dtype=np.int64),
                         self.config.outputs.map_frame)
        self.out.path(f2f, self.last_ns, topic=self.config.outputs.f2f_topic)
        self.out.tum('trajectory_ga.tum', traj)
        self.out.tum('trajectory_f2f.tum', f2f)
        gt_xyz = f2f_xyz = None
        if self.gt is not None and len(self.gt):
            self.out.ground_truth(self.gt, self.last_ns)
            self.out.tum('trajectory_gt.tum', self.gt)
            hit = self._match(traj.node_ids, traj.stamps_ns)
            res.ground_truth = hit.describe(self.gt_source, 'nodes', self.match_by == 'node')
            i_est = hit.i_est
            if len(i_est) >= 3:
                gt_xyz = hit.T_world_gt[:, :3, 3]
                res.errors['ga'] = trajectory_error(traj.T_world_node[i_est, :3, 3], gt_xyz)
                f_index = {n: k for k, n in enumerate(f_ids)}
                ok = [j for j, i in enumerate(i_est) if int(traj.node_ids[i]) in f_index]
                if len(ok) >= 3:
                    f_rows = [f_index[int(traj.node_ids[i_est[j]])] for j in ok]
                    res.errors['f2f'] = trajectory_error(f2f.T_world_node[f_rows, :3, 3],
                                                         gt_xyz[ok])
            gt_xyz = self.gt.T_world_node[:, :3, 3]
        f2f_xyz = f2f.T_world_node[:, :3, 3]
        if self.config.plot:
            title = f'{Path(res.bag).name}: {res.n_nodes} nodes, {res.n_tracks} tracks'
            if 'ga' in res.errors and 'f2f' in res.errors:
                title += (f'\nATE vs ground truth: F2F {res.errors["f2f"].ate_raw:.3g} m, '
                          f'GA {res.errors["ga"].ate_raw:.3g} m')
            self.out.plot('trajectory.png', traj.T_world_node[:, :3, 3], f2f_xyz, gt_xyz, title)


def _frames_summary(config: ReplayConfig, source: Any, run: _Run) -> dict[str, Any]:
    """What the replay did about frames (``summary.json``'s ``frames``)."""
    out: dict[str, Any] = {
        'map_frame': config.outputs.map_frame, 'odom_frame': config.outputs.odom_frame,
        'base_frame': config.outputs.sensor_frame,
        'transform_publish_period_sec': config.transform_publish_period_sec,
        'input_tf_to_odom_not_copied': run.tf_removed}
    front = getattr(source, 'front', None)
    ext = getattr(front, 'extrinsic', None)
    if ext is not None:
        out['camera_extrinsic'] = {'source': ext.source, 'camera_frame': ext.camera_frame,
                                   'T_base_camera': np.round(ext.T_base_cam, 9).tolist()}
    warnings = list(getattr(source, 'warnings', []) or [])
    if run.tf_removed:
        warnings.append(f'{run.tf_removed} input transforms to {config.outputs.odom_frame!r} '
                        f"not copied (another localiser's; ours is the one "
                        f'{config.outputs.map_frame} -> {config.outputs.odom_frame})')
    out['warnings'] = [w for w in warnings if 'DEFAULT covariance' not in w]
    return out


def _plan_or_hint(info: Any, topics: Any) -> TopicPlan:
    """:func:`plan_topics`; when the bag has no usable input but odometry or pose streams, the
    error names them and the option that reads them."""
    try:
        return plan_topics(info, topics)
    except FormatError as exc:
        streams = [t.name for t in info.topics if t.msgtype in INPUT_TYPES]
        if 'no usable input' not in str(exc) or not streams:
            raise
        raise FormatError(f'{exc}; odometry / pose streams found: {", ".join(streams)}: '
                          f'replay them with --odom-topic {streams[0]}') from None


def replay(bag_path: str | Path, out_dir: str | Path, config: ReplayConfig = ReplayConfig(),
           aligner_factory: AlignerFactory | None = None,
           on_plan: Callable[[TopicPlan], None] | None = None) -> ReplayResult:
    """Replay a bag through the alignment pipeline and write the outputs.

    Parameters
    ----------
    bag_path : rosbag2 directory or ``.mcap`` / ``.db3`` file.
    out_dir : output directory (created; files in it are replaced).
    config : see :class:`ReplayConfig`.
    aligner_factory : builds the aligner from the datum ``T_world_first`` (default:
        :class:`ga_ros.core.window.TrackWindowAligner` with ``config.aligner``).
    on_plan : called with the topic plan before processing starts (e.g. to print it).

    Returns
    -------
    ReplayResult

    Raises
    ------
    FormatError
        If the bag cannot be opened, lacks the needed topics (nothing is written then), or turns
        out truncated or corrupt half-way: then every output is still written, valid, with what
        was read before the failure, and the error (with ``.result`` attached) is raised at the
        end.
    """
    t0 = time.perf_counter()
    bag_path = Path(bag_path)
    with BagReader(bag_path) as bag:
        assert bag.info is not None
        specs: tuple[Any, ...] = ()
        if config.inputs.inputs:
            plan, specs = plan_inputs(bag.info, config.inputs, config.topics.ground_truth)
        else:
            plan = _plan_or_hint(bag.info, config.topics)
        factory = aligner_factory or default_aligner_factory(config.aligner,
                                                             config.aligner_kind)
        if config.ground_truth_file:  # the file replaces the topic
            plan = replace(plan, ground_truth='', notes=tuple(
                n for n in plan.notes if not n.startswith('ground truth:')) + (
                f'ground truth: {config.ground_truth_file} (file)',))
        if on_plan is not None:
            on_plan(plan)
        gt = read_ground_truth_topic(bag, plan.ground_truth) if plan.ground_truth else None
        if config.ground_truth_file:
            gt = read_ground_truth_file(config.ground_truth_file, config.ground_truth_format,
                                        config.ground_truth_times, config.ground_truth_rate_hz,
                                        config.ground_truth_start_s)
        source: Any
        if specs:
            counter = [0]
            total = sum(bag.info.topic(t).count for t in config.inputs.topics)
            source = InputSource(bag, specs, config.inputs, counter)
            unit = 'msg'
        elif plan.source == 'stereo':
            from ga_ros.replay.stereo import StereoSource

            counter = [0]
            total = bag.info.topic(plan.left_image).count
            source = StereoSource(bag, plan, config.vo, counter)
            unit = 'pair'
        else:
            counter = [0]
            total = bag.info.topic(plan.measurements).count
            source = bag_measurements(bag, plan.measurements, counter,
                                      config.covariance_policy)
            unit = 'msg'
        match_by = 'stamp'
        if plan.source == 'measurements' and gt is not None and len(gt.trajectory) and (
                gt.trajectory.node_ids >= 0).all():
            match_by = 'node'
        result = ReplayResult(str(bag_path), plan.source, str(out_dir))
        outputs = ReplayOutputs(out_dir, config.outputs)
        run = _Run(config, factory, outputs, result, gt, match_by)
        run.source = source
        if specs and config.tf:
            source.passthrough = run.copy_tf
        bar = None
        if config.progress:
            from tqdm import tqdm

            bar = tqdm(total=total, unit=unit, file=sys.stderr, mininterval=0.5,
                       desc=f'replay {bag_path.name}')
        try:
            try:
                last = 0
                for item in source:
                    run.step(item)
                    if bar is not None and counter[0] != last:
                        bar.update(counter[0] - last)
                        last = counter[0]
            except FormatError as exc:
                if bag.truncated is None and 'truncated' not in str(exc):
                    result.error = str(exc)
                else:  # a bag cut short: everything before the damage is used
                    result.warnings.append(f'{exc}; replayed the {counter[0]} {unit}s before '
                                           'the damage')
            finally:
                if bar is not None:
                    bar.update(counter[0] - last)  # what was read after the last item
                    bar.close()
            result.n_inputs = counter[0]
            result.frames = _frames_summary(config, source, run)
            stats = getattr(source, 'stats', None)
            if stats is not None:
                result.source_stats = _as_dict(stats)
            if run.aligner is None and result.error is None and run.stamps:
                run.finish_stationary()  # keyframes but no motion: the robot stood still
                if stats is not None and hasattr(stats, 'summary'):  # stereo: every reason
                    result.notes.append(f'stereo: {stats.summary()}; if the camera did move, '
                                        'lower the VO keyframe thresholds')
            elif run.aligner is None and result.error is None:
                examples = '; '.join(result.rejected_examples[:3])
                if stats is not None and hasattr(stats, 'summary'):  # stereo: every reason
                    examples = f'stereo: {stats.summary()}'
                result.error = (f'{bag_path}: no valid measurements in {counter[0]} '
                                f'{unit}s' + (f' ({examples})' if examples else ''))
            run.finish()
            fix_stats = getattr(run.aligner, 'fix_stats', None)
            if fix_stats is not None and 'absolute' in result.source_stats:
                result.source_stats['absolute']['aligner'] = _as_dict(fix_stats)
        finally:
            outputs.close()
            result.seconds = time.perf_counter() - t0
            result.files = {k: str(v) for k, v in outputs.files.items()}
            result.output_counts = dict(outputs.bag.counts)
            outputs.summary(result.as_dict())
    if result.error is not None:
        exc = FormatError(f'{result.error} (partial outputs written to {out_dir})')
        exc.result = result  # type: ignore[attr-defined]
        raise exc
    return result
