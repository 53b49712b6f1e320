"""ROS 2 alignment node: relative-motion measurements in, corrected trajectory out.

An adapter around :class:`ga_ros.pipeline.session.AlignmentSession` (STYLE habit 2):
parameters -> :class:`~ga_ros.core.window.AlignerConfig` + :class:`NodeSettings`;
``nav_msgs/Odometry`` measurement (encoding in :mod:`ga_ros.ros.conversions`) ->
:class:`~ga_ros.core.measurement.Measurement` -> ``session.step`` -> publish. The session owns
the aligner, the rejection counters, the journal/snapshot recovery and the diagnostic values.
Bad input is counted and warned about (throttled); the node never dies on a message.

Run it with ``alignment_node --ros-args --params-file config/alignment.yaml`` or
``python -m ga_ros.ros.alignment_node ...``.

Topics (defaults, relative: they follow the node's namespace; all names are parameters)
--------------------------------------------------------------------------------------
* in  ``ga/measurements`` (``nav_msgs/Odometry``): one connection per message.
* out ``ga/corrected_path`` (``nav_msgs/Path``, transient local): every node, in ``map_frame``.
* out ``ga/corrections`` (``nav_msgs/Path``, reliable, volatile): after every update, anchor
  keyframes of what moved beyond ``corrections.translation_m`` / ``corrections.rotation_rad``
  (entries, and spans inside which a consumer interpolates the correction) and the keyframes
  added, each named by its stamp, its ``header.frame_id`` ``map_frame`` (``/span`` appended
  where a span closes); the first message after a start, reset or ``~/load_state``
  is full (opened by a ``ga/full_path`` marker pose) (:mod:`ga_ros.pipeline.corrections`).
* out ``ga/corrected_pose`` (``geometry_msgs/PoseWithCovarianceStamped``): newest node.
* out ``ga/corrected_odom`` (``nav_msgs/Odometry``): newest node, ``map_frame`` ->
  ``base_frame``.
* out ``/tf``: ``map_frame -> odom_frame`` every ``transform_publish_period_sec`` with the latest
  correction (:mod:`ga_ros.pipeline.map_to_odom`), from the first odometry message: the
  identity until the map is placed (with ``datum: fixes`` by the fixes, until the first window
  update; after a restart on a saved state that state's last correction, journaled after each
  update), said in the diagnostics (``map_to_odom/placed_by``; a jump beyond the fixes'
  uncertainty is a WARN); when another node publishes a transform to ``odom_frame`` the node
  warns, reports it in the diagnostics (WARN) and stops publishing it unless
  ``publish_tf_when_contested``.
* out ``ga/network_markers`` (``visualization_msgs/MarkerArray``, transient local).
* out ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``): per update and at 1 Hz; with
  standard inputs, each input's received / expected / lost messages (from its stamps,
  :mod:`ga_ros.pipeline.stream_rate`; WARN above ``loss_warn_fraction``).
* out ``ga/measurements_done`` (``diagnostic_msgs/KeyValue``: this node's name, the
  measurements it received): an end-of-input message was processed (``ga-ros play`` keeps its
  history until every node confirmed all it sent).

Services (``std_srvs/Trigger``): ``~/finish_track``, ``~/reset``, ``~/save_state``,
``~/load_state``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import replace
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, KeyValue
from geometry_msgs.msg import PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import SetParametersResult
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from ga_ros import topics
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import GaError, InputError, SolverError
from ga_ros.pipeline.absolute import FixFeeder
from ga_ros.pipeline.corrections import CorrectionTracker
from ga_ros.pipeline.inputs import (
    COVARIANCE_POLICIES,
    decode_measurement,
)
from ga_ros.pipeline.journal import DEFAULT_STATE_FILE, default_state_file
from ga_ros.pipeline.map_to_odom import MapToOdom
from ga_ros.pipeline.path_mirror import PathMirror
from ga_ros.pipeline.session import AlignmentSession, SessionConfig, bounded
from ga_ros.pipeline.session.outputs import UpdateBug
from ga_ros.pipeline.session.restore import continue_inputs
from ga_ros.ros.alignment_diagnostics import AlignmentDiagnostics, QueueLoss, RejectionLog
from ga_ros.ros.alignment_inputs import AlignmentInputs
from ga_ros.ros.alignment_outputs import AlignmentOutputs
from ga_ros.ros.alignment_services import AlignmentServices
from ga_ros.ros.alignment_settings import (  # noqa: F401 - public names of this module
    DYNAMIC_ALIGNER,
    DYNAMIC_SETTINGS,
    INPUT_PARAMETERS,
    NodeSettings,
    declared_parameters,
    field_,
)
from ga_ros.ros.alignment_tf import TF_CONTEST_HOLD_SEC, AlignmentTf  # noqa: F401
from ga_ros.ros.bounded_log import BoundedLogging, shown_id
from ga_ros.ros.params import declare_config, updated_config
from ga_ros.ros.qos import (
    latched_qos,
    measurement_qos,
    sensor_qos,
    stream_qos,
)
from ga_ros.ros.runner import node_usage, run_node

NODE_NAME = 'alignment_node'
#: At most this many queued measurements, or this many seconds, per subscription callback.
DRAIN_MAX = 1000
DRAIN_SECONDS = 0.05
#: Queue depth of ``ga/corrections`` (keep last): corrections a slow subscriber may lag behind.
CORRECTIONS_DEPTH = 100


class AlignmentNode(BoundedLogging, AlignmentInputs, AlignmentOutputs, AlignmentTf,
                    AlignmentDiagnostics, AlignmentServices, Node):
    """Adapter: measurements -> :class:`AlignmentSession` -> corrected path, pose, markers."""

    def __init__(self, **kwargs: Any) -> None:
        super().__init__(NODE_NAME, **kwargs)
        self.aligner_config: AlignerConfig = declare_config(
            self, AlignerConfig, dynamic=DYNAMIC_ALIGNER,
            read_only_reason='it shapes the window state; restart the node to change it')
        self.settings: NodeSettings = declare_config(
            self, NodeSettings, dynamic=DYNAMIC_SETTINGS,
            read_only_reason='topics, queues, timers and state files are set up at start')
        s = self.settings
        if s.covariance_policy not in COVARIANCE_POLICIES:
            raise InputError(f'covariance_policy must be one of {COVARIANCE_POLICIES}')
        self.front = self._declare_inputs(s)
        self.absolute = self._declare_absolutes(s)
        self._fix_feeder = FixFeeder()
        if s.measurement_durability not in ('volatile', 'transient_local'):
            raise InputError(f'parameter measurement_durability must be volatile or '
                             f'transient_local, got {s.measurement_durability!r}')
        self.settings = s = self._state_file_of(s)
        self.session = AlignmentSession(
            self.aligner_config, SessionConfig(s.state_file, s.autosave, s.fsync_period_sec,
                                               state_required=s.state_required, gaps=s.gaps,
                                               compact_records=s.journal_compact_records,
                                               lock_owner=self.get_fully_qualified_name()),
            warn=self._warn_session)
        self._next_odom_time = 0.0  # perf_counter time before which no odometry is sent
        self._last_odom_node: int | None = None
        self._markers_dirty = False
        self._last_input = time.monotonic()
        self._path_nodes = 0           # nodes in the last published path
        self.incompatible_publishers = 0  # publishers not matched (incompatible QoS)
        self._rejections = RejectionLog()
        self.queue_loss = QueueLoss()
        # subscribe first: what arrives while the state is restored waits in the queue
        self.sub = self.create_subscription(
            Odometry, s.measurements_topic, self._on_measurements,
            measurement_qos(s.measurement_queue_depth,
                            transient_local=s.measurement_durability == 'transient_local'),
            event_callbacks=SubscriptionEventCallbacks(
                incompatible_qos=self._on_incompatible_qos,
                message_lost=self._on_message_lost))

        self._create_publishers(s)
        # the odometry chain and map -> odom, as in the replay: the first standard input, or
        # without standard inputs the frame-to-frame integration of the measurements
        self.odom = MapToOdom(self.front, datum=self.aligner_config.datum)
        self._resumed = False    # a restored state: its path places the map
        self._own_tf: dict[int, np.ndarray] = {}   # stamp -> T_map_odom of what we sent
        self._foreign_tf: tuple[str, float] = ('', -np.inf)   # its parent, monotonic time
        # best effort hears reliable and best-effort TF publishers alike
        self.create_subscription(TFMessage, s.tf_topic, self._on_tf, sensor_qos('best_effort',
                                                                                100))
        self._pub_earth: Any = None  # earth -> map, latched (created once the datum is known)
        self._next_full_path = 0.0  # perf_counter time before which the full path waits
        self._path_dirty = False
        self.corrections = CorrectionTracker(s.corrections)
        #: the corrected path kept in step with the aligner (the outputs' source)
        self.paths = PathMirror(s.map_frame)
        self._create_services()

        if s.state_file:
            self.get_logger().info(f'restoring the state from {s.state_file} ...')
        how = self.session.resume()
        self._restore_datum()
        self._continue_inputs()
        if how is not None and not how.startswith('failed'):
            self._resumed = True
            self.get_logger().info(f'resumed from {s.state_file} ({how}): '
                                   f'{self.session.n_nodes()} nodes')
            self.odom.restore(self.session.map_odom)   # map -> odom as before the restart
            self._publish_all()

        wall = RosClock(clock_type=ClockType.STEADY_TIME)  # also under use_sim_time
        if s.diagnostics_period_sec > 0:  # wall clock: reports also while sim time stands
            self.create_timer(s.diagnostics_period_sec, self._publish_diagnostics, clock=wall)
        if s.warn_throttle_sec > 0:
            self.create_timer(s.warn_throttle_sec, self._log_rejections, clock=wall)
        if s.track_idle_timeout_sec > 0:
            self.create_timer(min(1.0, s.track_idle_timeout_sec / 4), self._idle_check, clock=wall)
        if s.path_period_sec > 0:
            self.create_timer(s.path_period_sec, self._path_timer, clock=wall)
        if s.publish_markers:
            self.create_timer(1.0, self._markers_timer)
        self._subscribe_inputs(s)
        if s.transform_publish_period_sec > 0:
            self.create_timer(s.transform_publish_period_sec, self._publish_tf)
        self.create_timer(1.0, self._full_path_timer)  # the period may change at run time
        self.add_on_set_parameters_callback(self._on_set_parameters)
        self.get_logger().info(
            f'listening on {self.sub.topic_name}; window {self.aligner_config.window_tracks} '
            f'tracks, model {self.aligner_config.solver.model!r}, path in {s.map_frame!r}')

    def _state_file_of(self, s: NodeSettings) -> NodeSettings:
        """The settings with the default state file resolved
        (``$ROS_HOME/ga_ros/<namespace>/<name>/state``), and one line on where the state is kept
        (or that it is not)."""
        if s.state_file == DEFAULT_STATE_FILE:
            path = default_state_file(self.get_namespace(), self.get_name())
            s = replace(s, state_file=str(path))
            self.get_logger().info(f'state kept in {path.parent}/ (parameter state_file: '
                                   f"{DEFAULT_STATE_FILE!r}; a path to keep it elsewhere, '' for "
                                   'none)')
        elif not s.state_file:
            self.get_logger().warning("state_file: '': no persistence, a crash of this node loses "
                                      'what the publishers no longer hold')
        return s

    def _create_publishers(self, s: NodeSettings) -> None:
        """The output publishers (besides the latched ``earth -> map``, made when needed)."""
        self.pub_path = self.create_publisher(Path, s.path_topic, latched_qos())
        self.pub_pose = self.create_publisher(PoseWithCovarianceStamped, s.pose_topic,
                                              stream_qos())
        self.pub_odom = self.create_publisher(Odometry, s.odom_topic, stream_qos())
        self.pub_markers = self.create_publisher(MarkerArray, s.markers_topic, latched_qos())
        self.pub_diag = self.create_publisher(DiagnosticArray, s.diagnostics_topic, stream_qos())
        self.pub_window = self.create_publisher(Path, s.window_path_topic, stream_qos())
        # reliable, volatile, deep: a delta stream (a late joiner starts from the latched
        # ga/corrected_path; one old delta would be of no use to it), none may be dropped
        self.pub_corrections = self.create_publisher(Path, s.corrections_topic,
                                                     stream_qos(CORRECTIONS_DEPTH))
        self.pub_tf = self.create_publisher(TFMessage, s.tf_topic, stream_qos(100))
        self.pub_done = self.create_publisher(   # transient local: a player matched late
            KeyValue, topics.input_done_topic(s.measurements_topic), latched_qos())  # gets it

    @property
    def aligner(self) -> TrackWindowAligner:
        """The session's aligner."""
        return self.session.aligner

    @aligner.setter
    def aligner(self, value: TrackWindowAligner) -> None:
        self.session.aligner = value

    # ------------------------------------------------------------------ callbacks
    def _on_measurements(self, msg: Odometry, info: Any) -> None:
        """Subscription callback: handle ``msg``, then take the messages already queued behind
        it straight from the subscription (up to ``DRAIN_MAX`` or ``DRAIN_SECONDS``), which
        saves the executor's per-message wait-set round trip on bursts."""
        self.queue_loss.seen(info)
        self._on_measurement(msg)
        self._drain(DRAIN_MAX, DRAIN_SECONDS)

    def _warn_session(self, text: str) -> None:
        """The session's warnings: persistence failures as errors (throttled), others once."""
        if text.startswith('a different survey'):
            self.get_logger().warning(text)
        elif 'persistence' in text or 'journal' in text or 'state file' in text:
            self.get_logger().error(text, throttle_duration_sec=self.settings.warn_throttle_sec)
        else:
            self.get_logger().warning(text)

    def _on_incompatible_qos(self, event: Any) -> None:
        """A publisher on the measurements topic that cannot be matched (e.g. volatile while
        the node asks for transient local): nothing of it is received. One error line."""
        self.incompatible_publishers = int(getattr(event, 'total_count', 0))
        self.get_logger().error(
            f'a publisher on {self.sub.topic_name} offers an incompatible QoS (policy '
            f'{getattr(event, "last_policy_kind", "?")}): NOTHING of it is received. The node '
            f'asks for {self.settings.measurement_durability} durability: publish transient '
            'local (ga_ros.ros.qos.measurement_qos(transient_local=True)) or set the parameter '
            'measurement_durability: volatile')

    def _on_message_lost(self, event: Any) -> None:
        """DDS reports measurements lost before they reached the subscription queue."""
        self.queue_loss.lost_events += int(getattr(event, 'total_count_change', 0))

    def _drain(self, max_messages: int | None = None, max_seconds: float | None = None) -> int:
        """Handle the measurements already queued in the subscription (all of them by default:
        a track end, a service call or a timer acts only after everything received before
        it). Returns how many were handled."""
        t_end = time.perf_counter() + max_seconds if max_seconds is not None else None
        n = 0
        while max_messages is None or n < max_messages:
            try:
                with self.sub.handle:
                    taken = self.sub.handle.take_message(Odometry, False)
            except Exception:  # noqa: BLE001 - e.g. the subscription was destroyed
                return n
            if taken is None:
                return n
            self.queue_loss.seen(taken[1])
            self._on_measurement(taken[0])
            n += 1
            if t_end is not None and time.perf_counter() > t_end:
                return n
        return n

    def _on_measurement(self, msg: Odometry) -> None:
        """One measurement: decode, one session step, publish if a window update ran."""
        self._last_input = time.monotonic()
        if msg.child_frame_id == topics.TRACK_END_FRAME:   # in-band: after all before it
            try:
                self._finish_track(drain=False, cause='end_of_input')  # (not what came after)
            except SolverError:
                pass                             # counted and logged by the session
            # the publisher may now let its history go: who we are and what we received
            self.pub_done.publish(KeyValue(key=self.get_fully_qualified_name(),
                                           value=str(self.session.counts.received)))
            return
        try:
            m = decode_measurement(msg, self.settings.covariance_policy)
        except GaError as exc:
            self._warn_rejected(self.session.undecodable(exc), exc, msg)
            return
        except Exception as exc:  # noqa: BLE001 - the node must never die on a message
            self.session.counts.received += 1
            self.session.internal_error(exc)
            self._warn_rejected('internal', exc, msg)
            return
        self._process(m, msg)

    def _process(self, m: Measurement, msg: Any) -> None:
        """One session step of a measurement (``msg``: its message, named in warnings)."""
        t0 = time.perf_counter()
        self._last_input = time.monotonic()
        throttle = self.settings.warn_throttle_sec
        try:
            try:
                out = self.session.step(m)
            except UpdateBug as bug:    # reported; the step was complete: go on with it
                self._update_bug(bug)
                out = bug.result
            if self.session.previous_survey is not None:
                self._new_survey()
            if self.front is None:
                for taken in out.admitted:  # held ones whose gap was filled, bridges
                    self.odom.add(taken)
        except Exception as exc:  # noqa: BLE001 - the node must never die on a message
            self.session.internal_error(exc)
            self.get_logger().error(f'internal error on measurement '
                                    f'{msg.header.frame_id!r}->'
                                    f'{getattr(msg, "child_frame_id", "")!r}: '
                                    f'{self.session.last_error}', throttle_duration_sec=1.0)
            return
        if out.solver_failed:
            self.get_logger().error(f'window update failed, keeping the previous estimate: '
                                    f'{out.error}', throttle_duration_sec=throttle)
            self._publish_diagnostics()
            return
        if not out.accepted:
            self._warn_rejected(out.reason, out.error, msg)
            return
        try:
            if out.updates:
                self._after_updates(out.notes)
            elif (self.settings.odom_max_rate_hz > 0 and t0 >= self._next_odom_time
                  and self.aligner.newest_node_id != self._last_odom_node):
                self._publish_newest_odom()
        except Exception as exc:  # noqa: BLE001 - the node must never die on a message
            self.session.last_error = f'after update: {type(exc).__name__}: {exc}'
            self.get_logger().error(self.session.last_error, throttle_duration_sec=throttle)

    def _continue_inputs(self) -> None:
        """A restored state (at start, or ``~/load_state``): the standard inputs number their
        keyframes on after its nodes and tracks, running ones on a fresh keyframe chain, and
        the fixes tied to their former keyframes are dropped
        (:func:`~ga_ros.pipeline.session.restore.continue_inputs`)."""
        if self.front is None:
            return
        dropped = self._fix_feeder.forget()
        first = continue_inputs(self.session, self.front)
        if first is not None:
            self.get_logger().info(f'standard inputs: keyframes numbered from node {first[0]}, '
                                   f'track {first[1]} (after the restored state)'
                                   + (f'; {dropped} fixes on the former keyframes dropped'
                                      if dropped else ''))

    def _new_survey_inputs(self) -> None:
        """The survey was emptied (``~/reset``): the standard inputs start a fresh keyframe
        chain at their next sample, numbered as at a start (from the first input's
        ``first_node_id``, 0 by default, on track 0)
        (:meth:`~ga_ros.pipeline.inputs.InputFrontEnd.new_survey`: nothing of theirs refers
        to the former keyframes, the camera's included), the fixes resolved on the former
        keyframes are dropped, and ``map -> odom`` is placed again as at a start
        (:meth:`~ga_ros.pipeline.map_to_odom.MapToOdom.new_map`)."""
        self._resumed = False
        dropped = self._fix_feeder.forget()
        self.odom.new_map()
        if self.front is None:
            return
        self.front.new_survey()
        first = self.front.inputs[self.front.primary].config.first_node_id
        self.get_logger().info(f'standard inputs: a new survey from node {first}, track 0 at '
                               'the next sample' + (f'; {dropped} fixes on the former '
                                                    'keyframes dropped' if dropped else ''))

    def _new_survey(self) -> None:
        """The session moved the resumed state aside (another survey's first measurement
        came, :mod:`ga_ros.pipeline.session.survey_identity`): outputs start afresh, as after
        ``~/reset``."""
        self.session.previous_survey = None
        self._resumed = False
        self._datum_saved = False   # the datum file went with the old state
        self.corrections.restart()  # consumers drop what they held: a full message next
        self.paths.restart()
        self._publish_all()

    def _warn_rejected(self, reason: object, exc: object, msg: Any) -> None:
        """Note a rejection (counted by the session); logged by a timer, not per message."""
        log = self._rejections
        log.pending += 1
        log.last = (msg.header.frame_id, getattr(msg, 'child_frame_id', ''), reason, exc)
        if self.settings.warn_throttle_sec == 0:
            self._log_rejections()

    def _log_rejections(self) -> None:
        """One warning for the rejections since the last one (timer of ``warn_throttle_sec``)."""
        log = self._rejections
        if not log.pending:
            return
        src, dst, reason, exc = log.last
        self.get_logger().warning(
            f'{log.pending} measurement(s) rejected; the last {shown_id(src)}->{shown_id(dst)} '
            f'({reason}): {bounded(str(exc))} '
            f'[{sum(self.session.counts.rejected.values())} rejected so far]')
        log.pending = 0

    def _idle_check(self) -> None:
        """End the open track after ``track_idle_timeout_sec`` without input."""
        self._drain()
        idle = time.monotonic() - self._last_input
        if idle >= self.settings.track_idle_timeout_sec and self.aligner.open_track is not None:
            self.get_logger().info(f'no measurement for {idle:.1f} s: ending track '
                                   f'{self.aligner.open_track}')
            try:
                self._finish_track(drain=False, cause='idle_timeout')   # just drained
            except SolverError:
                pass                              # counted and logged by the session

    def _path_timer(self) -> None:
        """Publish the path when nodes were added since the last one (the open track's at their
        dead-reckoned poses)."""
        if self.session.n_nodes() != self._path_nodes:
            self._publish_all()

    def _finish_track(self, drain: bool = True, cause: str = 'finish_track') -> Any:
        """End the open track (after the queued measurements if ``drain``; journaled with its
        ``cause``) and publish; returns the update (None: no open track). Raises SolverError
        (counted) if the update failed."""
        if drain:
            self._drain()
        try:
            update = self.session.finish_track(cause)
        except SolverError:
            self._publish_diagnostics()
            raise
        except UpdateBug as bug:   # reported; the track ended as without strict
            self._update_bug(bug)
            update = bug.result
        if update is not None:
            self._publish_all()
        return update

    def _update_bug(self, bug: UpdateBug) -> None:
        """Report a window update's bug that a strict aligner re-raised
        (``GA_ROS_STRICT_UPDATES``): one ERROR line and the diagnostics (``failed_updates``,
        ``last_error``; the session warned with its traceback); the node goes on."""
        self.session.last_error = bounded(str(bug))
        self.get_logger().error(str(bug), throttle_duration_sec=self.settings.warn_throttle_sec)
        self._publish_diagnostics()

    def _after_updates(self, notes: tuple[str, ...]) -> None:
        """Log what the session noted about the updates, then publish everything."""
        for note in notes:
            self.get_logger().error(note, throttle_duration_sec=self.settings.warn_throttle_sec)
        self._publish_all()

    def _on_set_parameters(self, params: list[Parameter]) -> SetParametersResult:
        """Apply run-time changes (read-only parameters are refused by rclpy itself)."""
        changes = {p.name: p.value for p in params}
        try:
            settings = updated_config(self, self.settings, changes)
            aligner = updated_config(self, self.aligner_config, changes)
            if settings.covariance_policy not in COVARIANCE_POLICIES:
                raise InputError(f'covariance_policy must be one of {COVARIANCE_POLICIES}')
        except InputError as exc:
            return SetParametersResult(successful=False, reason=str(exc))
        self.settings = settings
        if aligner != self.aligner_config:
            self.aligner_config = self.session.config = aligner
            self.aligner.config = aligner
        if self.front is not None:
            self.front.throttle.period_s = settings.input_warn_throttle_sec
        return SetParametersResult(successful=True)

    def destroy_node(self) -> None:
        self.session.close()
        super().destroy_node()


def usage() -> str:
    """The ``--help`` text of the alignment nodes."""
    return node_usage(NODE_NAME, __doc__, declared_parameters(('<input>',), ('<fix>',)))


def main(args: list[str] | None = None) -> int:
    """Console entry point ``alignment_node`` (also ``python -m ga_ros.ros.alignment_node``)."""
    return run_node(AlignmentNode, NODE_NAME, args, usage=usage)


if __name__ == '__main__':
    sys.exit(main())
