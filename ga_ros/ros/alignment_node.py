"""ROS 2 alignment node: relative-motion measurements in, corrected trajectory out.

An adapter around :class:`ga_ros.core.window.TrackWindowAligner` (STYLE habit 2): parameters ->
:class:`~ga_ros.core.window.AlignerConfig` + :class:`NodeSettings`; ``nav_msgs/Odometry``
measurement (encoding in :mod:`ga_ros.ros.conversions`) -> :class:`~ga_ros.core.measurement.
Measurement` -> ``aligner.add_measurement`` -> publish. Bad input is counted and warned about
(throttled); the node never dies on a message.

Run it with ``alignment_node --ros-args --params-file config/alignment.yaml`` or
``python -m ga_ros.ros.alignment_node ...``.

Topics (defaults; all names are parameters)
-------------------------------------------
* in  ``/ga/measurements`` (``nav_msgs/Odometry``): one connection per message.
* out ``/ga/corrected_path`` (``nav_msgs/Path``, transient local): every node, in ``map_frame``.
* out ``/ga/corrected_pose`` (``geometry_msgs/PoseWithCovarianceStamped``): newest node.
* out ``/ga/corrected_odom`` (``nav_msgs/Odometry``): newest node, ``map_frame`` ->
  ``sensor_frame``.
* out ``/ga/network_markers`` (``visualization_msgs/MarkerArray``, transient local).
* out ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``): per update and at 1 Hz.

Services (``std_srvs/Trigger``): ``~/finish_track``, ``~/reset``, ``~/save_state``,
``~/load_state``.
"""

from __future__ import annotations

import os
import sys
import time
from collections import Counter
from dataclasses import dataclass, fields
from pathlib import Path as FilePath

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.node import Node
from std_srvs.srv import Trigger
from visualization_msgs.msg import MarkerArray

from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import GaError, InputError, SolverError
from ga_ros.ros import conversions as conv
from ga_ros.ros.journal import (
    MeasurementJournal,
    journal_path,
    read_journal,
    read_snapshot_info,
    snapshot_info_path,
    write_snapshot_info,
)
from ga_ros.ros.qos import latched_qos, measurement_qos, stream_qos
from ga_ros.ros.runner import run_node
from ga_ros.ros.view import ABSORBED, OUTLIER, connection_view

NODE_NAME = 'alignment_node'
#: At most this many queued measurements, or this many seconds, per subscription callback.
DRAIN_MAX = 1000
DRAIN_SECONDS = 0.05


@dataclass(frozen=True)
class NodeSettings:
    """ROS-side parameters of the alignment node (the aligner's are in ``AlignerConfig``).

    Attributes
    ----------
    map_frame : frame of the corrected path / poses (REP 105 ``map``).
    sensor_frame : ``child_frame_id`` of the corrected odometry stream.
    measurements_topic, path_topic, pose_topic, odom_topic, markers_topic, diagnostics_topic :
        topic names.
    measurement_queue_depth : depth of the (reliable) measurement subscription queue, messages.
    state_file : ``.npz`` file for ``~/save_state`` / ``~/load_state`` and resume on start
        (``''``: none).
    autosave : save the state to ``state_file`` after every window update.
    warn_throttle_sec : minimum interval between two warnings about rejected input, s.
    publish_markers : publish the connection network as a MarkerArray.
    residual_color_scale : Mahalanobis residual drawn fully red (unitless).
    diagnostics_period_sec : period of the diagnostics timer, s (0 disables; diagnostics are
        also published after every update).
    odom_max_rate_hz : between updates, publish the newest node's pose (its frame-to-frame
        continuation from the last adjusted node, covariance unknown) on ``odom_topic`` at most
        this often, Hz (0: only after updates).
    """

    map_frame: str = 'map'
    sensor_frame: str = 'sensor'
    measurements_topic: str = '/ga/measurements'
    path_topic: str = '/ga/corrected_path'
    pose_topic: str = '/ga/corrected_pose'
    odom_topic: str = '/ga/corrected_odom'
    markers_topic: str = '/ga/network_markers'
    diagnostics_topic: str = '/diagnostics'
    measurement_queue_depth: int = 100000
    state_file: str = ''
    autosave: bool = True
    warn_throttle_sec: float = 2.0
    publish_markers: bool = True
    residual_color_scale: float = 3.0
    diagnostics_period_sec: float = 1.0
    odom_max_rate_hz: float = 10.0


# name -> (description, additional constraints, numeric range (lo, hi) or None)
_DESCRIPTIONS: dict[str, tuple[str, str, tuple[float, float] | None]] = {
    'window_tracks': ('number of tracks (double swaths) in the sliding window', '', (1, 1000)),
    'freeze_policy': ('how tracks leaving the window enter the next solves', "'weighted' "
                      "(weighted parameters, paper Sec. III-E) | 'marginal'", None),
    'model': ('constraint model of the live aligner', "'se3' (the only one for sensor-frame "
              'motions)', None),
    'max_iterations': ('Gauss-Newton iterations per window update', '', (1, 10000)),
    'damping': ('solver damping', "'none' (Gauss-Helmert as in the paper) | 'lm' "
                '(Levenberg-Marquardt)', None),
    'keep_all_connections': ('keep every measurement for a final batch refinement (memory '
                             'grows ~340 bytes per measurement)', '', None),
    'tolerance': ('convergence: max |correction| (m / rad)', '', (0.0, 1e3)),
    'cost_tolerance': ('convergence: relative cost decrease of a Gauss-Newton step', '',
                       (0.0, 1.0)),
    'robust_loss': ("robust loss on each connection's Mahalanobis misclosure",
                    "'none' | 'huber' | 'cauchy'", None),
    'robust_scale': ('Mahalanobis distance where the robust loss departs from least squares',
                     '', (0.0, 1e6)),
    'outlier_chi2_prob': ('chi-square probability of the misclosure gate for cross-track '
                          'connections (0 disables)', '', (0.0, 1.0)),
    'map_frame': ('frame of the corrected path and poses (REP 105)', '', None),
    'sensor_frame': ('child_frame_id of the corrected odometry', '', None),
    'measurements_topic': ('input: nav_msgs/Odometry measurement encoding (README)', '', None),
    'path_topic': ('output: nav_msgs/Path, transient local', '', None),
    'pose_topic': ('output: PoseWithCovarianceStamped of the newest node', '', None),
    'odom_topic': ('output: nav_msgs/Odometry of the newest node', '', None),
    'markers_topic': ('output: MarkerArray of nodes and connections', '', None),
    'diagnostics_topic': ('output: DiagnosticArray', '', None),
    'measurement_queue_depth': ('reliable queue depth of the measurement subscription', '',
                                (1, 1000000)),
    'state_file': (".npz state file: save/load services and resume on start ('' = none)", '',
                   None),
    'autosave': ('save the state after every window update', '', None),
    'warn_throttle_sec': ('minimum seconds between warnings on rejected input', '', (0.0, 3600)),
    'publish_markers': ('publish the connection network as markers', '', None),
    'residual_color_scale': ('Mahalanobis residual drawn red', '', (1e-6, 1e6)),
    'odom_max_rate_hz': ('max rate of the corrected odometry between updates, Hz (0 = only '
                         'after updates)', '', (0.0, 1000.0)),
    'diagnostics_period_sec': ('diagnostics timer period, s (0 = only on updates)', '',
                               (0.0, 3600)),
}


def _descriptor(name: str, default: object) -> ParameterDescriptor:
    text, constraints, rng = _DESCRIPTIONS.get(name, (name.replace('_', ' '), '', None))
    d = ParameterDescriptor(name=name, description=text, additional_constraints=constraints,
                            read_only=True)
    if rng is not None and isinstance(default, bool):
        rng = None
    if rng is not None and isinstance(default, int):
        d.integer_range = [IntegerRange(from_value=int(rng[0]), to_value=int(rng[1]), step=1)]
    elif isinstance(default, float):
        # accept '-p tolerance:=1' as well as 1.0 (dynamic typing; coerced and range-checked
        # in _declare_dataclass)
        d.dynamic_typing = True
        if rng is not None:
            d.floating_point_range = [FloatingPointRange(from_value=float(rng[0]),
                                                         to_value=float(rng[1]), step=0.0)]
    return d


def _declare_dataclass(node: Node, cls: type) -> object:
    """Declare one parameter per field of the frozen dataclass ``cls`` (default: the field's
    default) and build an instance from the values (the ROS params mirror the config 1:1)."""
    values = {}
    defaults = cls()
    for f in fields(cls):
        default = getattr(defaults, f.name)
        if isinstance(default, np.generic):
            default = default.item()
        descriptor = _descriptor(f.name, default)
        value = node.declare_parameter(f.name, default, descriptor).value
        if isinstance(default, float):
            if isinstance(value, bool) or not isinstance(value, int | float):
                raise InputError(f'parameter {f.name} must be a number, got {value!r}')
            value = float(value)
            for r in descriptor.floating_point_range:
                if not r.from_value <= value <= r.to_value:
                    raise InputError(f'parameter {f.name} = {value} is outside '
                                     f'[{r.from_value}, {r.to_value}]')
        values[f.name] = value
    return cls(**values)


def classify_rejection(exc: Exception) -> str:
    """Short reason key for a rejected measurement (diagnostics counts ``rejected/<reason>``)."""
    reason = getattr(exc, 'reason', None)
    if isinstance(reason, str) and reason:
        return reason
    text = str(exc).lower()
    for key, words in (('self_loop', ('self-loop', 'itself')),
                       ('frozen', ('frozen',)),
                       ('duplicate', ('duplicate', 'already', 'repeat')),
                       ('out_of_order', ('order', 'older', 'earlier track', 'past')),
                       ('bad_covariance', ('covariance', 'positive definite', 'symmetric')),
                       ('non_finite', ('nan', 'inf')),
                       ('bad_id', ('frame id', 'id out of range', 'id must', 'ids must')),
                       ('bad_quaternion', ('quaternion',))):
        if any(w in text for w in words):
            return key
    return 'invalid'


class AlignmentNode(Node):
    """Adapter: measurements -> :class:`TrackWindowAligner` -> corrected path, pose, markers."""

    def __init__(self, **kwargs) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.aligner_config: AlignerConfig = _declare_dataclass(self, AlignerConfig)
        self.settings: NodeSettings = _declare_dataclass(self, NodeSettings)
        s = self.settings
        self.aligner = TrackWindowAligner(self.aligner_config)
        self.rejected: Counter[str] = Counter()
        self.n_received = 0
        self.n_accepted = 0
        self.n_updates = 0
        self.n_solver_failures = 0
        self.n_not_converged = 0
        self.last_update = None
        self.last_error = ''
        self._cb_seconds = 0.0      # time in measurement callbacks that did not update
        self._cb_count = 0
        self._next_odom_time = 0.0  # perf_counter time before which no odometry is sent
        self._last_odom_node = None
        self._markers_dirty = False
        self.journal = (MeasurementJournal(journal_path(s.state_file))
                        if s.state_file and s.autosave else None)

        self.pub_path = self.create_publisher(Path, s.path_topic, latched_qos())
        self.pub_pose = self.create_publisher(PoseWithCovarianceStamped, s.pose_topic,
                                              stream_qos())
        self.pub_odom = self.create_publisher(Odometry, s.odom_topic, stream_qos())
        self.pub_markers = self.create_publisher(MarkerArray, s.markers_topic, latched_qos())
        self.pub_diag = self.create_publisher(DiagnosticArray, s.diagnostics_topic, stream_qos())
        self.create_service(Trigger, '~/finish_track', self._srv_finish_track)
        self.create_service(Trigger, '~/reset', self._srv_reset)
        self.create_service(Trigger, '~/save_state', self._srv_save)
        self.create_service(Trigger, '~/load_state', self._srv_load)

        if s.state_file:
            self._resume(s.state_file)

        self.sub = self.create_subscription(Odometry, s.measurements_topic, self._on_measurements,
                                            measurement_qos(s.measurement_queue_depth))
        if s.diagnostics_period_sec > 0:
            self.create_timer(s.diagnostics_period_sec, self._publish_diagnostics)
        if s.publish_markers:
            self.create_timer(1.0, self._markers_timer)
        self.get_logger().info(
            f'listening on {s.measurements_topic}; window {self.aligner_config.window_tracks} '
            f'tracks, model {self.aligner_config.model!r}, path in {s.map_frame!r}')

    # ------------------------------------------------------------------ callbacks
    def _on_measurements(self, msg: Odometry) -> None:
        """Subscription callback: handle ``msg``, then take the messages already queued behind
        it straight from the subscription (up to ``DRAIN_MAX`` or ``DRAIN_SECONDS``), which
        saves the executor's per-message wait-set round trip on bursts."""
        self._on_measurement(msg)
        t_end = time.perf_counter() + DRAIN_SECONDS
        for _ in range(DRAIN_MAX):
            try:
                with self.sub.handle:
                    taken = self.sub.handle.take_message(Odometry, False)
            except Exception:  # noqa: BLE001 - e.g. the subscription was destroyed
                return
            if taken is None:
                return
            self._on_measurement(taken[0])
            if time.perf_counter() > t_end:
                return

    def _on_measurement(self, msg: Odometry) -> None:
        """One measurement: decode, add to the aligner, publish if a window update ran."""
        t0 = time.perf_counter()
        self.n_received += 1
        try:
            m = conv.odometry_to_measurement(msg)
            updates = self.aligner.add_measurement(m)
        except SolverError as exc:
            self._solver_failed(exc)
            return
        except GaError as exc:
            self._reject(classify_rejection(exc), exc, msg)
            return
        except Exception as exc:  # noqa: BLE001 - the node must never die on a message
            self.rejected['internal'] += 1
            self.last_error = f'{type(exc).__name__}: {exc}'
            self.get_logger().error(f'internal error on measurement '
                                    f'{msg.header.frame_id!r}->{msg.child_frame_id!r}: '
                                    f'{self.last_error}', throttle_duration_sec=1.0)
            return
        self.n_accepted += 1
        try:
            if self.journal is not None:
                self.journal.append(m)
            if updates:
                self._after_updates(updates)
            else:
                if (self.settings.odom_max_rate_hz > 0
                        and t0 >= self._next_odom_time
                        and self.aligner.newest_node_id != self._last_odom_node):
                    self._publish_newest_odom()
                self._cb_seconds += time.perf_counter() - t0
                self._cb_count += 1
        except Exception as exc:  # noqa: BLE001 - the node must never die on a message
            self.last_error = f'after update: {type(exc).__name__}: {exc}'
            self.get_logger().error(self.last_error,
                                    throttle_duration_sec=self.settings.warn_throttle_sec)

    def _reject(self, reason: str, exc: Exception, msg: Odometry) -> None:
        self.rejected[reason] += 1
        self.last_error = f'{reason}: {exc}'
        self.get_logger().warning(
            f'rejected measurement {msg.header.frame_id!r}->{msg.child_frame_id!r} ({reason}): '
            f'{exc} [{sum(self.rejected.values())} rejected so far]',
            throttle_duration_sec=self.settings.warn_throttle_sec)

    def _solver_failed(self, exc: Exception) -> None:
        self.n_solver_failures += 1
        self.last_error = f'solver: {exc}'
        self.get_logger().error(f'window update failed, keeping the previous estimate: {exc}',
                                throttle_duration_sec=self.settings.warn_throttle_sec)
        self._publish_diagnostics()

    def _after_updates(self, updates) -> None:
        updates = [u for u in updates if u is not None]
        if not updates:
            return
        self.n_updates += len(updates)
        self.last_update = updates[-1]
        for u in updates:
            reason = str(getattr(u, 'reason', ''))
            if reason.startswith('failed'):
                # the aligner kept the previous estimate
                self.n_solver_failures += 1
                self.last_error = f'solver: {reason}'
                self.get_logger().error(f'window update of track {u.track_id} failed, previous '
                                        f'estimate kept: {reason}')
            elif not getattr(u, 'converged', True):
                self.n_not_converged += 1
                self.get_logger().warning(f'window update of track {u.track_id} did not converge '
                                          f'({reason})')
        self._publish_all()
        if self.settings.autosave and self.settings.state_file:
            try:
                self._save(self.settings.state_file)
            except Exception as exc:  # noqa: BLE001
                self.get_logger().error(f'autosave to {self.settings.state_file} failed: {exc}',
                                        throttle_duration_sec=self.settings.warn_throttle_sec)

    def destroy_node(self) -> None:
        if self.journal is not None:
            self.journal.close()
        super().destroy_node()

    def _srv_finish_track(self, request, response):
        try:
            update = self.aligner.finish_track()
        except SolverError as exc:
            self._solver_failed(exc)
            response.success, response.message = False, f'solver failed: {exc}'
            return response
        except Exception as exc:  # noqa: BLE001
            response.success, response.message = False, f'{type(exc).__name__}: {exc}'
            return response
        if update is None:
            response.success, response.message = True, 'no open track'
            return response
        self._after_updates([update])
        response.success = True
        response.message = (f'track {update.track_id}: {update.iterations} iterations, '
                            f'sigma0^2 {update.sigma0_sq:.4g}, {update.update_ms:.1f} ms')
        return response

    def _srv_reset(self, request, response):
        self.aligner = TrackWindowAligner(self.aligner_config)
        if self.journal is not None:      # autosave: the files mirror the live state
            self.journal.clear()
            for f in (self.settings.state_file, snapshot_info_path(self.settings.state_file)):
                FilePath(f).unlink(missing_ok=True)
        self.rejected.clear()
        self.n_received = self.n_accepted = self.n_updates = self.n_solver_failures = 0
        self.n_not_converged = 0
        self.last_update, self.last_error = None, ''
        self._publish_all()
        response.success, response.message = True, 'state cleared'
        return response

    def _srv_save(self, request, response):
        path = self.settings.state_file
        if not path:
            response.success, response.message = False, 'parameter state_file is empty'
            return response
        try:
            self._save(path)
        except Exception as exc:  # noqa: BLE001
            response.success, response.message = False, f'save failed: {exc}'
            return response
        response.success, response.message = True, f'saved to {path}'
        return response

    def _srv_load(self, request, response):
        path = self.settings.state_file
        if not path or not os.path.exists(path):
            response.success, response.message = False, f'no state file {path!r}'
            return response
        try:
            n_records = read_snapshot_info(path) if self.journal is not None else 0
            self.aligner, how = self._restore(path, n_records)
            if self.journal is not None:
                self.journal.truncate(n_records)   # the journal mirrors the restored state
        except Exception as exc:  # noqa: BLE001
            response.success, response.message = False, f'load failed (state unchanged): {exc}'
            return response
        self._publish_all()
        response.success = True
        response.message = f'loaded {self._stats_value("n_nodes", 0)} nodes from {path} ({how})'
        return response

    # ------------------------------------------------------------------ state files
    def _save(self, path: str) -> None:
        """Write the aligner snapshot atomically (temporary file, then rename), and how many
        journal records it holds."""
        target = FilePath(path)
        target.parent.mkdir(parents=True, exist_ok=True)
        tmp = target.with_name(f'.{target.stem}.tmp{os.getpid()}.npz')
        self.aligner.save(str(tmp))
        os.replace(tmp, target)
        write_snapshot_info(target, self.journal.count if self.journal is not None else 0)

    def _restore(self, path: str, n_records: int | None = None) -> tuple[TrackWindowAligner, str]:
        """A new aligner holding the snapshot ``path`` plus the journal records after it (up to
        ``n_records`` in all; default: every record). Falls back to replaying the journal into a
        fresh aligner if the snapshot cannot be loaded. Raises if neither works; ``self`` is
        not changed."""
        records = read_journal(journal_path(path)) if self.journal is not None else []
        if n_records is not None:
            records = records[:n_records]
        aligner, start, how = None, 0, 'journal replay'
        snapshot_error = None
        if os.path.exists(path):
            try:
                aligner = TrackWindowAligner.load(path)
                start = min(read_snapshot_info(path), len(records))
                how = 'snapshot'
            except Exception as exc:  # noqa: BLE001 - fall back to the journal
                snapshot_error = exc
        if aligner is None:
            if not records:
                raise snapshot_error or InputError(f'no state in {path}')
            why = f'not usable ({snapshot_error})' if snapshot_error else 'missing'
            self.get_logger().warning(f'snapshot {path} {why}; replaying {len(records)} '
                                      'journal records')
            aligner = TrackWindowAligner(self.aligner_config)
        n = 0
        for m in records[start:]:
            try:
                aligner.add_measurement(m)
                n += 1
            except GaError:
                pass  # already in the snapshot (a crash between snapshot and sidecar)
        how = (f'snapshot + {n} journal records' if how == 'snapshot'
               else f'replay of {n} journal records')
        return aligner, how

    def _resume(self, path: str) -> None:
        """On start: restore the state from ``path`` and its journal if they exist; a bad file is
        reported and the node starts empty."""
        if not os.path.exists(path) and not journal_path(path).exists():
            return
        try:
            self.aligner, how = self._restore(path)
        except Exception as exc:  # noqa: BLE001 - a bad state file must not stop the node
            self.get_logger().error(f'could not resume from {path}: {exc}; starting empty')
            self.aligner = TrackWindowAligner(self.aligner_config)
            if self.journal is not None:
                self.journal.clear()
            return
        self.get_logger().info(
            f'resumed from {path} ({how}): {self._stats_value("n_nodes", 0)} nodes')
        self._publish_all()

    # ------------------------------------------------------------------ publishing
    def _stats_value(self, name: str, default):
        try:
            return getattr(self.aligner.stats, name)
        except Exception:  # noqa: BLE001
            return default

    def _publish_all(self) -> None:
        """Publish path, newest pose, odometry, markers and diagnostics; never raises."""
        try:
            self._publish_outputs()
        except Exception as exc:  # noqa: BLE001 - publishing must not stop the node
            self.last_error = f'publish: {type(exc).__name__}: {exc}'
            self.get_logger().error(f'could not publish the outputs: {self.last_error}',
                                    throttle_duration_sec=self.settings.warn_throttle_sec)
        self._publish_diagnostics()

    def _publish_outputs(self) -> None:
        s = self.settings
        cp = self.aligner.corrected_path()
        if len(cp.node_ids):
            stamp_ns = int(cp.stamps_ns[-1])
        else:
            stamp_ns = self.get_clock().now().nanoseconds
        self.pub_path.publish(conv.path_to_msg(cp.T_world_node, cp.stamps_ns, s.map_frame,
                                               stamp_ns))
        k = self._newest_adjusted(cp)
        if k is not None:
            try:
                cov = np.asarray(self.aligner.covariance(int(cp.node_ids[k])),
                                 dtype=float).reshape(6, 6)
            except Exception:  # noqa: BLE001 - unknown covariance: ROS convention, -1 first
                cov = np.zeros((6, 6))
                cov[0, 0] = -1.0
            t_k = int(cp.stamps_ns[k])
            self.pub_pose.publish(conv.pose_with_covariance_msg(cp.T_world_node[k], cov,
                                                                s.map_frame, t_k))
            self.pub_odom.publish(conv.odometry_msg(cp.T_world_node[k], cov, s.map_frame,
                                                    s.sensor_frame, t_k))
        if s.publish_markers:
            self._markers_dirty = True
            if self.pub_markers.get_subscription_count() > 0:
                self._publish_markers()

    def _publish_markers(self, force: bool = False) -> None:
        """The network as markers. Built only when someone listens (RViz, Foxglove): otherwise
        marked dirty and sent by the 1 Hz timer once a subscriber appears. Never raises."""
        if not (self._markers_dirty or force):
            return
        s = self.settings
        try:
            cp = self.aligner.corrected_path()
            view = connection_view(self.aligner)
            colors = np.where(np.asarray(cp.frozen, dtype=bool)[:, None],
                              [[0.5, 0.5, 0.5, 1.0]], [[0.2, 0.4, 1.0, 1.0]])
            conn_rgba = conv.residual_color(view.normalized_residual, s.residual_color_scale)
            conn_rgba[view.status == OUTLIER] = (1.0, 0.0, 1.0, 1.0)    # magenta
            conn_rgba[view.status == ABSORBED, 3] = 0.3                # faded
            stamp_ns = int(cp.stamps_ns[-1]) if len(cp.node_ids) else 0
            self.pub_markers.publish(conv.network_markers(
                view.p_world_node, view.src_index, view.dst_index,
                view.normalized_residual, s.map_frame, stamp_ns, node_colors=colors,
                residual_scale=s.residual_color_scale, connection_colors=conn_rgba))
            self._markers_dirty = False
        except Exception as exc:  # noqa: BLE001 - visualisation must not stop the node
            self._markers_dirty = False
            self.get_logger().warning(f'markers not published: {exc}',
                                      throttle_duration_sec=10.0)

    def _markers_timer(self) -> None:
        if self._markers_dirty and self.pub_markers.get_subscription_count() > 0:
            self._publish_markers()

    def _publish_newest_odom(self) -> None:
        """Odometry of the newest node (open track: not adjusted yet, covariance unknown, i.e.
        ``covariance[0] = -1`` as ROS messages mark it)."""
        self._next_odom_time = time.perf_counter() + 1.0 / self.settings.odom_max_rate_hz
        cp = self.aligner.corrected_path()
        if not len(cp.node_ids):
            return
        self._last_odom_node = int(cp.node_ids[-1])
        cov = np.zeros((6, 6))
        cov[0, 0] = -1.0
        self.pub_odom.publish(conv.odometry_msg(cp.T_world_node[-1], cov, self.settings.map_frame,
                                                self.settings.sensor_frame,
                                                int(cp.stamps_ns[-1])))

    def _newest_adjusted(self, cp) -> int | None:
        """Path index of the newest node that a window update has adjusted (the open track's
        nodes are only frame-to-frame continuations without a covariance yet)."""
        open_track = getattr(self.aligner, 'open_track', None)
        tracks = np.asarray(cp.track_ids)
        done = np.nonzero(tracks != open_track)[0] if open_track is not None else \
            np.arange(tracks.size)
        return int(done[-1]) if done.size else None

    def diagnostic_values(self) -> dict[str, object]:
        """Current counters and last-update figures (the diagnostics key/values)."""
        st = self.aligner.stats
        u = self.last_update
        values: dict[str, object] = {
            'tracks_in_window': _len_or_value(getattr(st, 'tracks_in_window', 0)),
            'nodes': int(getattr(st, 'n_nodes', 0)),
            'connections': int(getattr(st, 'n_connections', 0)),
            'iterations': int(u.iterations) if u is not None else 0,
            'variance_factor': float(u.sigma0_sq) if u is not None else float('nan'),
            'update_ms': float(u.update_ms) if u is not None else float('nan'),
            'converged': bool(u.converged) if u is not None else True,
            'last_track': int(u.track_id) if u is not None else -1,
            'outliers_excluded': int(getattr(st, 'n_outliers', 0)),
            'last_update_outliers': int(getattr(u, 'n_outliers', 0)) if u is not None else 0,
            'updates': self.n_updates,
            'solver_failures': self.n_solver_failures,
            'not_converged': self.n_not_converged,
            'measurements_received': self.n_received,
            'measurements_accepted': self.n_accepted,
            'measurement_callback_us': (1e6 * self._cb_seconds / self._cb_count
                                        if self._cb_count else float('nan')),
        }
        values['rejected'] = sum(self.rejected.values())
        for key in sorted(self.rejected):
            values[f'rejected/{key}'] = self.rejected[key]
        values['last_error'] = self.last_error
        return values

    def _publish_diagnostics(self) -> None:
        try:
            values = self.diagnostic_values()
        except Exception as exc:  # noqa: BLE001
            values = {'error': str(exc)}
        level = DiagnosticStatus.OK
        message = 'ok'
        if self.n_solver_failures:
            level, message = DiagnosticStatus.WARN, 'solver failures (previous estimate kept)'
        elif self.rejected:
            level, message = DiagnosticStatus.WARN, 'rejected measurements'
        level_int = level[0] if isinstance(level, bytes) else int(level)
        self.pub_diag.publish(conv.diagnostics_msg(
            f'{self.get_name()}: global alignment', 'ga_ros', values,
            self.get_clock().now().nanoseconds, level=level_int, message=message))


def _len_or_value(x) -> int:
    try:
        return len(x)
    except TypeError:
        return int(x)


def main(args: list[str] | None = None) -> int:
    """Console entry point ``alignment_node`` (also ``python -m ga_ros.ros.alignment_node``)."""
    return run_node(AlignmentNode, NODE_NAME, args)


if __name__ == '__main__':
    sys.exit(main())
