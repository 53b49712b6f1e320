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
* out ``ga/corrected_pose`` (``geometry_msgs/PoseWithCovarianceStamped``): newest node.
* out ``ga/corrected_odom`` (``nav_msgs/Odometry``): newest node, ``map_frame`` ->
  ``base_frame``.
* out ``/tf``: ``map_frame -> odom_frame`` every ``transform_publish_period_sec`` with the latest
  correction (:mod:`ga_ros.pipeline.map_to_odom`); when another node publishes a transform to
  ``odom_frame`` the node warns, reports it in the diagnostics (WARN) and stops publishing it
  unless ``publish_tf_when_contested``.
* out ``ga/network_markers`` (``visualization_msgs/MarkerArray``, transient local).
* out ``/diagnostics`` (``diagnostic_msgs/DiagnosticArray``): per update and at 1 Hz; with
  standard inputs, each input's received / expected / lost messages (from its stamps,
  :mod:`ga_ros.pipeline.stream_rate`; WARN above ``loss_warn_fraction``).
* out ``ga/measurements_done`` (``std_msgs/Empty``): an end-of-input message was processed
  (``ga-ros play`` keeps its history until then).

Services (``std_srvs/Trigger``): ``~/finish_track``, ``~/reset``, ``~/save_state``,
``~/load_state``.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass, replace
from functools import partial
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from geometry_msgs.msg import PoseStamped, PoseWithCovarianceStamped
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import ParameterDescriptor, SetParametersResult
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, NavSatFix
from std_msgs.msg import Empty
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage
from visualization_msgs.msg import MarkerArray

from ga_ros import topics
from ga_ros.core.config_ranges import check_ranges, ranged
from ga_ros.core.extrinsic import (
    ExtrinsicConfig,
    renamed_parameter_error,
    unknown_extrinsic_error,
)
from ga_ros.core.gaps import GapConfig
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import GaError, InputError, SolverError
from ga_ros.geometry import se3
from ga_ros.inputs.absolute import ABSOLUTE_TYPES, NAVSAT, AbsoluteInputConfig, T_earth_enu
from ga_ros.inputs.absolute import ODOMETRY as ABS_ODOMETRY
from ga_ros.inputs.absolute import POSE_COV as ABS_POSE_COV
from ga_ros.inputs.messages import INPUT_TYPES, ODOMETRY, POSE, POSE_COV
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.io.cdr import path_cdr
from ga_ros.pipeline.absolute import AbsoluteFrontEnd, AbsoluteSpec, FixFeeder
from ga_ros.pipeline.inputs import (
    COVARIANCE_POLICIES,
    InputFrontEnd,
    InputSpec,
    InputStep,
    decode_measurement,
)
from ga_ros.pipeline.keyframe_camera import KeyframeCamera, KeyframeCameraConfig
from ga_ros.pipeline.map_to_odom import MapToOdom, foreign_odom_parents
from ga_ros.pipeline.params import parameter_names
from ga_ros.pipeline.session import AlignmentSession, SessionConfig, bounded
from ga_ros.pipeline.stream_rate import StreamMonitor
from ga_ros.ros import conversions as conv
from ga_ros.ros.adaptive_qos import AdaptiveSubscription
from ga_ros.ros.params import declare_config, updated_config
from ga_ros.ros.qos import (
    AUTO,
    RELIABILITIES,
    latched_qos,
    measurement_qos,
    sensor_qos,
    stream_qos,
)
from ga_ros.ros.runner import node_usage, run_node
from ga_ros.ros.view import connection_view

NODE_NAME = 'alignment_node'
#: At most this many queued measurements, or this many seconds, per subscription callback.
DRAIN_MAX = 1000
DRAIN_SECONDS = 0.05
#: Another node's ``-> odom`` transform keeps ours off the air this long after it was heard, s.
TF_CONTEST_HOLD_SEC = 5.0


#: A dataclass field with a default and its parameter range ``[lo, hi]``.
field_ = ranged


@dataclass(frozen=True)
class NodeSettings:
    """ROS-side parameters of the alignment node (the aligner's are in ``AlignerConfig``).

    Attributes
    ----------
    map_frame : frame of the corrected path / poses (REP 105 ``map``).
    measurements_topic : input: nav_msgs/Odometry measurement encoding (README).
    path_topic : output: nav_msgs/Path of every node, transient local.
    pose_topic : output: PoseWithCovarianceStamped of the newest adjusted node.
    odom_topic : output: nav_msgs/Odometry of the newest node.
    markers_topic : output: MarkerArray of nodes and connections.
    diagnostics_topic : output: DiagnosticArray.
    measurement_queue_depth : depth of the (reliable) measurement subscription queue, messages.
    state_file : ``.npz`` file for ``~/save_state`` / ``~/load_state`` and resume on start
        (``''``: none).
    autosave : journal every measurement and save the state to ``state_file`` after every
        window update.
    warn_throttle_sec : minimum interval between two warnings about rejected input, s.
    publish_markers : publish the connection network as a MarkerArray.
    residual_color_scale : Mahalanobis residual drawn fully red (unitless); with the aligner's
        ``quality`` on, the ``|w|`` drawn fully red (e.g. the w-test's critical value).
    diagnostics_period_sec : period of the diagnostics timer, s (0 disables; diagnostics are
        also published after every update).
    odom_max_rate_hz : between updates, publish the newest node's pose (its frame-to-frame
        continuation from the last adjusted node, covariance unknown) on ``odom_topic`` at most
        this often, Hz (0: only after updates).
    inputs : comma-separated names of standard inputs (``odom0,pose0``); each has parameters
        ``<name>.topic``, ``<name>.type`` and the OdometryInputConfig fields ``<name>.<field>``
        (config/inputs.yaml).
    constraints_topic : input: external constraints (nav_msgs/Odometry, ``stamp/<ns>`` or
        ``node/<id>`` ends) on the first standard input's keyframes.
    absolutes : comma-separated names of absolute inputs (``fix0,amcl0``: GNSS, AMCL, USBL,
        motion capture; :mod:`ga_ros.pipeline.absolute`), tied to the first standard input's
        keyframes; each has parameters ``<name>.topic``, ``<name>.type`` and the
        AbsoluteInputConfig fields ``<name>.<field>``. With any, set ``datum: fixes`` (the map
        frame is then the fixes' frame).
    track_boundary_topic : input: std_msgs/Empty, a new track of the standard inputs.
    covariance_policy : measurement covariance that is not positive definite: ``reject`` or
        ``repair`` (eigenvalue clipping).
    input_warn_throttle_sec : minimum interval between two default-covariance warnings, s.
    odom_frame : REP 105 odometry frame of the first standard input (``map -> odom`` on TF).
    base_frame : the robot's base frame: ``child_frame_id`` of the corrected odometry (and
        child of ``map`` when ``publish_map_to_base``).
    publish_tf : publish ``map_frame -> odom_frame`` on ``tf_topic`` (odom: the first standard
        input's frame, or without standard inputs the frame-to-frame integration of the
        consecutive measurements).
    publish_map_to_base : also publish ``map_frame -> base_frame`` (only when nothing else
        publishes ``odom -> base``: a frame has one parent).
    tf_topic : TF topic (``/tf``; remap it to ``tf`` for namespaced robots); static transforms
        go on it with ``_static`` appended (``/tf_static``).
    publish_earth_transform : with a NavSatFix input and ``datum: fixes`` (the map frame is then
        the ENU frame at the inputs' origin), publish REP 105 ``earth_frame -> map_frame`` (ECEF
        to ENU at that origin) once on the static TF topic, latched, as soon as the origin is
        known (the ``datum`` parameter, or the first fix).
    earth_frame : REP 105 Earth-centred, Earth-fixed frame (``earth``).
    transform_publish_period_sec : period of the TF timer, s (0: after updates only).
    publish_tf_when_contested : keep publishing ``map_frame -> odom_frame`` when another node
        publishes a transform to ``odom_frame`` on ``tf_topic`` (a frame has one parent: TF
        consumers would jump between the two); off: ours stops until the other has been
        silent for :data:`TF_CONTEST_HOLD_SEC`.
    loss_warn_fraction : diagnostics WARN when a standard input's lost / expected messages
        exceed this.
    window_path_topic : output: nav_msgs/Path of the nodes the window can still move.
    full_path_min_period_sec : publish the full path at most this often, s (0: after every
        update; big surveys: e.g. 10, the window path carries the updates).
    measurement_durability : ``transient_local`` (default: the publisher's history is delivered
        again after a restart, so nothing published while the node was down or still queued
        when it was killed is lost; the publisher must be transient local too, as ``ga-ros
        play`` and the VO node are; a volatile publisher is not matched and named in an error
        line; re-delivered measurements are counted as ``rejected/duplicate``) or ``volatile``
        (any publisher; what is published while the node is down is lost).
    fsync_period_sec : journal durability: every record reaches the OS at once (``kill -9``
        loses nothing); it is also fsync-ed (power cut) after every measurement if 0, else at
        most every this many seconds.
    track_idle_timeout_sec : end the open track when no measurement has arrived for this long,
        wall-clock s (0: never; a track end then comes from the next track's first measurement,
        the end-of-input message or ``~/finish_track``). Measurements of a track that arrive
        after its end are rejected (``out_of_order``): keep it well above any pause of the VO.
    path_period_sec : publish the path, when nodes were added since the last one, at most this
        often, s; the open track's nodes are then in it at their dead-reckoned poses
        (diagnostics ``dead_reckoned_nodes``: how many at the end of the path) (0: only after
        updates).
    allow_reset : whether ``~/reset`` may clear the state (and empty the state files); off by
        default, since any peer on the ROS graph can call it.
    allow_finish_track : whether ``~/finish_track`` may end the open track; off by default:
        a call mid-track turns the rest of the track into ``out_of_order`` rejections and the
        later tracks into ``unknown_source`` ones (tracks end by the next track's first
        measurement, the end-of-input message or ``track_idle_timeout_sec``).
    allow_load_state : whether ``~/load_state`` may replace the state by the state file's;
        off by default (with ``autosave: false`` it reverts to an older save).
    state_required : refuse to start when ``state_file`` cannot be used (its directory is a
        file or read-only, ...) instead of running without persistence (one error line and
        ``persistence: off`` in the diagnostics).
    gaps : measurements whose source node is unknown (a gap in the stream): how long they are
        held for the missing measurements, and the bridges that join what is still apart
        (:class:`~ga_ros.core.gaps.GapConfig`; parameters ``gaps.<name>``).
    """

    map_frame: str = 'map'
    measurements_topic: str = topics.MEASUREMENTS
    path_topic: str = topics.CORRECTED_PATH
    pose_topic: str = topics.CORRECTED_POSE
    odom_topic: str = topics.CORRECTED_ODOM
    markers_topic: str = topics.NETWORK_MARKERS
    diagnostics_topic: str = topics.DIAGNOSTICS
    measurement_queue_depth: int = field_(100000, 1, 1000000)
    state_file: str = ''
    autosave: bool = True
    warn_throttle_sec: float = field_(2.0, 0.0, 3600.0)
    publish_markers: bool = True
    residual_color_scale: float = field_(3.0, 1e-6, 1e6)
    diagnostics_period_sec: float = field_(1.0, 0.0, 3600.0)
    odom_max_rate_hz: float = field_(10.0, 0.0, 1000.0)
    inputs: str = ''
    absolutes: str = ''
    constraints_topic: str = topics.CONSTRAINTS
    track_boundary_topic: str = topics.TRACK_BOUNDARY
    covariance_policy: str = 'reject'
    input_warn_throttle_sec: float = field_(10.0, 0.0, 3600.0)
    odom_frame: str = 'odom'
    base_frame: str = 'base_link'
    publish_tf: bool = True
    publish_map_to_base: bool = False
    tf_topic: str = '/tf'
    publish_earth_transform: bool = True
    earth_frame: str = 'earth'
    transform_publish_period_sec: float = field_(0.05, 0.0, 3600.0)
    publish_tf_when_contested: bool = False
    loss_warn_fraction: float = field_(0.01, 0.0, 1.0)
    window_path_topic: str = topics.WINDOW_PATH
    full_path_min_period_sec: float = field_(0.0, 0.0, 86400.0)

    measurement_durability: str = 'transient_local'
    fsync_period_sec: float = field_(1.0, 0.0, 3600.0)
    track_idle_timeout_sec: float = field_(0.0, 0.0, 86400.0)
    path_period_sec: float = field_(1.0, 0.0, 3600.0)
    allow_reset: bool = False
    allow_finish_track: bool = False
    allow_load_state: bool = False
    state_required: bool = False
    gaps: GapConfig = GapConfig()

    def __post_init__(self) -> None:
        check_ranges(self)


#: NodeSettings fields that may change at run time (read at use).
DYNAMIC_SETTINGS = frozenset({
    'map_frame', 'odom_frame', 'base_frame', 'publish_tf', 'publish_map_to_base',
    'publish_tf_when_contested', 'loss_warn_fraction',
    'warn_throttle_sec', 'publish_markers', 'residual_color_scale', 'odom_max_rate_hz',
    'covariance_policy', 'input_warn_throttle_sec', 'full_path_min_period_sec'})
#: AlignerConfig fields that may change at run time (the aligner reads them at each update).
DYNAMIC_ALIGNER = frozenset({'outlier_chi2_prob', 'solver.max_iterations', 'solver.tolerance',
                             'solver.robust_loss', 'solver.robust_scale'})


class AlignmentNode(Node):
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
        self.session = AlignmentSession(
            self.aligner_config, SessionConfig(s.state_file, s.autosave, s.fsync_period_sec,
                                               state_required=s.state_required, gaps=s.gaps),
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

        self.pub_path = self.create_publisher(Path, s.path_topic, latched_qos())
        self.pub_pose = self.create_publisher(PoseWithCovarianceStamped, s.pose_topic,
                                              stream_qos())
        self.pub_odom = self.create_publisher(Odometry, s.odom_topic, stream_qos())
        self.pub_markers = self.create_publisher(MarkerArray, s.markers_topic, latched_qos())
        self.pub_diag = self.create_publisher(DiagnosticArray, s.diagnostics_topic, stream_qos())
        self.pub_window = self.create_publisher(Path, s.window_path_topic, stream_qos())
        self.pub_tf = self.create_publisher(TFMessage, s.tf_topic, stream_qos(100))
        self.pub_done = self.create_publisher(
            Empty, topics.input_done_topic(s.measurements_topic), stream_qos())
        # the odometry chain and map -> odom, as in the replay: the first standard input, or
        # without standard inputs the frame-to-frame integration of the measurements
        self.odom = MapToOdom(self.front)
        self._own_tf: dict[int, np.ndarray] = {}   # stamp -> T_map_odom of what we sent
        self._foreign_tf: tuple[str, float] = ('', -np.inf)   # its parent, monotonic time
        # best effort hears reliable and best-effort TF publishers alike
        self.create_subscription(TFMessage, s.tf_topic, self._on_tf, sensor_qos('best_effort',
                                                                                100))
        self._pub_earth: Any = None  # earth -> map, latched (created once the datum is known)
        self._next_full_path = 0.0  # perf_counter time before which the full path waits
        self._path_dirty = False
        self.create_service(Trigger, '~/finish_track', self._srv_finish_track)
        self.create_service(Trigger, '~/reset', self._srv_reset)
        self.create_service(Trigger, '~/save_state', self._srv_save)
        self.create_service(Trigger, '~/load_state', self._srv_load)

        if s.state_file:
            self.get_logger().info(f'restoring the state from {s.state_file} ...')
        how = self.session.resume()
        if how is not None and not how.startswith('failed'):
            self.get_logger().info(f'resumed from {s.state_file} ({how}): '
                                   f'{self.session.n_nodes()} nodes')
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
        if 'persistence' in text or 'journal' in text or 'state file' in text:
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
                self._finish_track(drain=False)  # (draining would take what came after it)
            except SolverError:
                pass                             # counted and logged by the session
            self.pub_done.publish(Empty())       # the publisher may now let its history go
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
            out = self.session.step(m)
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
            f'{log.pending} measurement(s) rejected; the last {src!r}->{dst!r} ({reason}): '
            f'{exc} [{sum(self.session.counts.rejected.values())} rejected so far]')
        log.pending = 0

    def _idle_check(self) -> None:
        """End the open track after ``track_idle_timeout_sec`` without input."""
        self._drain()
        idle = time.monotonic() - self._last_input
        if idle >= self.settings.track_idle_timeout_sec and self.aligner.open_track is not None:
            self.get_logger().info(f'no measurement for {idle:.1f} s: ending track '
                                   f'{self.aligner.open_track}')
            try:
                self._finish_track(drain=False)   # just drained
            except SolverError:
                pass                              # counted and logged by the session

    def _path_timer(self) -> None:
        """Publish the path when nodes were added since the last one (the open track's at their
        dead-reckoned poses)."""
        if self.session.n_nodes() != self._path_nodes:
            self._publish_all()

    def _finish_track(self, drain: bool = True) -> Any:
        """End the open track (after the queued measurements if ``drain``) and publish; returns
        the update (None: no open track). Raises SolverError (counted) if the update failed."""
        if drain:
            self._drain()
        try:
            update = self.session.finish_track()
        except SolverError:
            self._publish_diagnostics()
            raise
        if update is not None:
            self._publish_all()
        return update

    def _after_updates(self, notes: tuple[str, ...]) -> None:
        """Log what the session noted about the updates, then publish everything."""
        for note in notes:
            self.get_logger().error(note, throttle_duration_sec=self.settings.warn_throttle_sec)
        self._publish_all()

    # ------------------------------------------------------------------ standard inputs
    def _declare_inputs(self, s: NodeSettings) -> InputFrontEnd | None:
        """Parameters ``<name>.topic``, ``<name>.type``, ``<name>.<field>`` of each input named
        in ``inputs``; the front end (None without inputs)."""
        names = [n.strip() for n in s.inputs.split(',') if n.strip()]
        #: per standard input: (QoS reliability, depth) and the stamp-gap loss monitor
        self._input_qos: dict[str, tuple[str, int]] = {}
        self.input_streams: dict[str, StreamMonitor] = {}
        if not names:
            return None
        specs = []
        for name in names:
            why = 'the input is set up at start'
            topic = self.declare_parameter(f'{name}.topic', '', ParameterDescriptor(
                description=f'{name}: input topic (read-only: {why})', read_only=True)).value
            msgtype = self.declare_parameter(f'{name}.type', ODOMETRY, ParameterDescriptor(
                description=f'{name}: {" | ".join(INPUT_TYPES)} (read-only: {why})',
                read_only=True)).value
            cfg = declare_config(self, OdometryInputConfig, prefix=f'{name}.',
                                 read_only_reason=why,
                                 defaults=OdometryInputConfig(name))
            if not topic:
                raise InputError(f'input {name}: set the parameter {name}.topic')
            reliability = str(self.declare_parameter(
                f'{name}.qos_reliability', AUTO, ParameterDescriptor(
                    description=f'{name}: subscription QoS, {" | ".join(RELIABILITIES)} '
                    f'(auto: reliable when every publisher offers reliable, else best effort; '
                    f'read-only: {why})',
                    read_only=True)).value)
            depth = int(self.declare_parameter(f'{name}.qos_depth', 100, ParameterDescriptor(
                description=f'{name}: subscription queue depth, messages (read-only: {why})',
                read_only=True)).value)
            sensor_qos(reliability, depth)      # refuse a bad value at start
            self._input_qos[name] = (reliability, depth)
            self.input_streams[name] = StreamMonitor()
            specs.append(InputSpec(str(topic), str(msgtype), replace(cfg, name=name)))
        return InputFrontEnd(specs, s.input_warn_throttle_sec, camera=self._declare_camera())

    def _declare_camera(self) -> KeyframeCamera | None:
        """Parameters ``camera.*`` of a stereo camera beside the odometry (cross-track
        connections on the first input's keyframes); None when ``camera.left_image_topic`` is
        empty."""
        why = 'the camera is set up at start'

        def declare(name: str, default: Any, text: str) -> Any:
            return self.declare_parameter(f'camera.{name}', default, ParameterDescriptor(
                description=f'{text} (read-only: {why})', read_only=True)).value

        topics_ = {side: (declare(f'{side}_image_topic', '', f'{side} image topic (empty: no '
                                  'camera)'),
                          declare(f'{side}_info_topic', '', f'{side} CameraInfo topic'))
                   for side in ('left', 'right')}
        compressed = declare('compressed', False, 'subscribe to sensor_msgs/CompressedImage')
        extrinsic = declare('T_base_camera', '', "the left optical frame's pose in the base "
                            "frame: 'x y z qx qy qz qw' (m, quaternion x y z w) or "
                            "'x y z roll pitch yaw' (rad); '' = not given")
        identity = declare('assume_identity_extrinsic', False, 'without camera.T_base_camera: '
                           'the camera frame is the base frame')
        old = self.declare_parameter('camera.base_to_camera', None, ParameterDescriptor(
            description='renamed: camera.T_base_camera', dynamic_typing=True)).value
        offset = declare('max_image_offset_s', 0.25,
                         'largest time between a keyframe and its image pair (s)')
        if old is not None:
            raise renamed_parameter_error('camera.base_to_camera', 'camera.T_base_camera')
        if not topics_['left'][0]:
            return None
        if not all(t for pair in topics_.values() for t in pair):
            raise InputError('camera: set camera.left_image_topic, camera.right_image_topic, '
                             'camera.left_info_topic and camera.right_info_topic')
        ext = ExtrinsicConfig(T_base_camera=str(extrinsic)).from_parameters()
        if ext is None and not identity:
            raise unknown_extrinsic_error('camera', 'camera.T_base_camera',
                                          'camera.assume_identity_extrinsic: true',
                                          tf_static=False)
        p, q = se3.to_pos_quat(ext.T_base_cam if ext is not None else np.eye(4))
        self._camera_topics = (topics_, bool(compressed))
        return KeyframeCamera(KeyframeCameraConfig(
            T_base_camera=tuple(float(v) for v in (*p, *q)),
            max_image_offset_s=float(offset)))

    def _declare_absolutes(self, s: NodeSettings) -> AbsoluteFrontEnd | None:
        """Parameters ``<name>.topic``, ``<name>.type``, ``<name>.<field>`` of each absolute
        input named in ``absolutes``; the front end (None without any)."""
        names = [n.strip() for n in s.absolutes.split(',') if n.strip()]
        if not names:
            return None
        if self.front is None:
            raise InputError('absolutes need a standard odometry input (parameter inputs): '
                             'fixes are tied to its keyframes')
        specs = []
        why = 'the input is set up at start'
        for name in names:
            topic = self.declare_parameter(f'{name}.topic', '', ParameterDescriptor(
                description=f'{name}: absolute input topic (read-only: {why})',
                read_only=True)).value
            msgtype = self.declare_parameter(f'{name}.type', ABS_POSE_COV, ParameterDescriptor(
                description=f'{name}: {" | ".join(ABSOLUTE_TYPES)} (read-only: {why})',
                read_only=True)).value
            cfg = declare_config(self, AbsoluteInputConfig, prefix=f'{name}.',
                                 read_only_reason=why, defaults=AbsoluteInputConfig(name))
            if self.declare_parameter(f'{name}.lever_arm_m', None, ParameterDescriptor(
                    description=f'renamed: {name}.T_base_sensor',
                    dynamic_typing=True)).value is not None:
                raise renamed_parameter_error(f'{name}.lever_arm_m', f'{name}.T_base_sensor')
            if not topic:
                raise InputError(f'absolute input {name}: set the parameter {name}.topic')
            specs.append(AbsoluteSpec(str(topic), str(msgtype), replace(cfg, name=name)))
        return AbsoluteFrontEnd(specs, s.input_warn_throttle_sec)

    def _on_absolute(self, name: str, msg: Any) -> None:
        assert self.absolute is not None
        step = self.absolute.message(name, msg)
        if step.warning:
            self.get_logger().warning(step.warning)
        if step.error:
            self.get_logger().warning(step.error, throttle_duration_sec=5.0)
        self._publish_earth()
        self._resolve_fixes()

    def _publish_earth(self) -> None:
        """REP 105 ``earth -> map`` on the static TF topic, once the NavSatFix inputs' ENU
        origin is known (``publish_earth_transform``; the map frame is that ENU frame only
        with ``datum: fixes``)."""
        s = self.settings
        if (self._pub_earth is not None or not s.publish_earth_transform
                or self.absolute is None or self.aligner_config.datum != 'fixes'):
            return
        datum = self.absolute.earth_datum()
        if datum is None:
            return
        self._pub_earth = self.create_publisher(TFMessage, s.tf_topic + '_static',
                                                latched_qos())
        stamp = int(self.get_clock().now().nanoseconds)
        self._pub_earth.publish(TFMessage(transforms=[conv.transform_msg(
            s.earth_frame, s.map_frame, T_earth_enu(datum), stamp)]))
        self.get_logger().info(f'{s.earth_frame} -> {s.map_frame}: ENU at lat {datum[0]:.7f}, '
                               f'lon {datum[1]:.7f}, alt {datum[2]:.2f} m')

    def _resolve_fixes(self) -> None:
        """Fixes the odometry now covers -> the aligner (a track boundary if one asks)."""
        if self.absolute is None or self.front is None:
            return
        step = self.absolute.resolve(self.front.inputs[self.front.primary])
        if step.end_track:
            self.front.track_boundary()
        self._fix_feeder.add(step.fixes)
        # the session journals the fixes with the measurements
        for error in self._fix_feeder.flush(self.session, self.session.gaps.anchor):
            self.get_logger().warning(f'fix refused: {error}', throttle_duration_sec=5.0)

    def _subscribe_inputs(self, s: NodeSettings) -> None:
        #: the sensor subscriptions by input name (their reliability, :mod:`.adaptive_qos`)
        self.sensor_subscriptions: dict[str, AdaptiveSubscription] = {}
        if self.front is None:
            return
        if self.absolute is not None:
            kinds_abs = {ABS_POSE_COV: PoseWithCovarianceStamped, ABS_ODOMETRY: Odometry,
                         NAVSAT: NavSatFix}
            for spec in self.absolute.specs.values():
                self.sensor_subscriptions[spec.name] = AdaptiveSubscription(
                    self, kinds_abs[spec.msgtype], spec.topic,
                    partial(self._on_absolute, spec.name), AUTO, 100)
            # the sensors' lever arms (latched: every static broadcaster's last message)
            self.create_subscription(TFMessage, '/tf_static', self.absolute.static_transform,
                                     latched_qos(100))
        kinds = {ODOMETRY: Odometry, POSE_COV: PoseWithCovarianceStamped, POSE: PoseStamped}
        for spec in self.front.specs.values():
            # auto (default): reliable when every publisher offers reliable, else best effort
            reliability, depth = self._input_qos[spec.name]
            self.sensor_subscriptions[spec.name] = AdaptiveSubscription(
                self, kinds[spec.msgtype], spec.topic, partial(self._on_input, spec.name),
                reliability, depth)
        self.create_subscription(Odometry, s.constraints_topic, self._on_constraint,
                                 measurement_qos(1000))
        self.create_subscription(Empty, s.track_boundary_topic,
                                 lambda _msg: self.front.track_boundary(), 10)
        if self.front.camera is not None:
            cam_topics, compressed = self._camera_topics
            img_type = CompressedImage if compressed else Image
            for side, (image, info) in cam_topics.items():   # as the standard inputs' default
                self.sensor_subscriptions[f'camera_{side}_image'] = AdaptiveSubscription(
                    self, img_type, image, partial(self._on_camera_image, side), AUTO, 100)
                self.sensor_subscriptions[f'camera_{side}_info'] = AdaptiveSubscription(
                    self, CameraInfo, info, partial(self._on_camera_info, side), AUTO, 100)
        self.get_logger().info('standard inputs: ' + ', '.join(
            f'{sp.name} {sp.topic} [{sp.msgtype}]' for sp in self.front.specs.values()))

    def _on_input(self, name: str, msg: Any) -> None:
        assert self.front is not None
        try:
            self.input_streams[name].add(conv.stamp_to_ns(msg.header.stamp))
        except (AttributeError, TypeError, ValueError):
            pass                                   # a malformed stamp is rejected below
        self._after_input(self.front.sample(name, msg), msg)
        if self.absolute is not None and name == self.front.primary:
            self._resolve_fixes()

    def _on_camera_image(self, side: str, msg: Any) -> None:
        assert self.front is not None
        self._after_input(self.front.image(side, msg), msg)

    def _on_camera_info(self, side: str, msg: Any) -> None:
        assert self.front is not None
        self._after_input(self.front.camera_info(side, msg), msg)

    def _on_constraint(self, msg: Odometry) -> None:
        assert self.front is not None
        self._after_input(self.front.constraint(msg), msg)

    def _after_input(self, step: InputStep, msg: Any) -> None:
        """Warn (throttled) and step the session with the input's measurements."""
        if step.warning:
            self.get_logger().warning(step.warning)
        if step.error:
            exc = InputError(step.error)
            self._warn_rejected(self.session.undecodable(exc), exc, msg)
        for m in step.measurements:
            self._process(m, msg)

    def _publish_tf(self) -> None:
        """``map -> odom`` (and optionally ``map -> base``) of the newest correction, stamped at
        the newest odometry pose; not while another node publishes ``odom``'s parent (unless
        ``publish_tf_when_contested``)."""
        s = self.settings
        T_map_odom = self.odom.T_map_odom
        if not s.publish_tf or T_map_odom is None:
            return
        if self.tf_contested_by and not s.publish_tf_when_contested:
            return
        newest = self.odom.latest()
        if newest is None:
            return
        latest, stamp = newest
        tfs = [conv.transform_msg(s.map_frame, s.odom_frame, T_map_odom, stamp)]
        if s.publish_map_to_base:
            tfs.append(conv.transform_msg(s.map_frame, s.base_frame, T_map_odom @ latest, stamp))
        self._own_tf[int(stamp)] = T_map_odom.copy()
        while len(self._own_tf) > 1000:
            self._own_tf.pop(next(iter(self._own_tf)))
        self.pub_tf.publish(TFMessage(transforms=tfs))

    @property
    def tf_contested_by(self) -> str:
        """Parent frame of another node's transform to ``odom_frame`` heard within the last
        :data:`TF_CONTEST_HOLD_SEC` ('' when none: ours is published again)."""
        parent, at = self._foreign_tf
        return parent if time.monotonic() - at < TF_CONTEST_HOLD_SEC else ''

    def _on_tf(self, msg: TFMessage) -> None:
        """Another publisher of a transform to ``odom_frame``: warn (throttled), report it in
        the diagnostics and stop publishing ours (unless ``publish_tf_when_contested``)."""
        s = self.settings
        parents = foreign_odom_parents(msg, s.odom_frame, self._own_tf, s.map_frame)
        if not parents:
            return
        first = not self.tf_contested_by
        self._foreign_tf = (parents[0], time.monotonic())
        what = ('publishing ours anyway (publish_tf_when_contested)'
                if s.publish_tf_when_contested else 'not publishing ours')
        self.get_logger().warning(
            f'another node publishes {parents[0]} -> {s.odom_frame} on {s.tf_topic}: a frame has '
            f'one parent; {what}. Stop the other localiser or remap, or set '
            f'publish_tf_when_contested', throttle_duration_sec=max(s.warn_throttle_sec, 1.0))
        if first:
            self._publish_diagnostics()

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

    def _srv_finish_track(self, request: Trigger.Request,
                          response: Trigger.Response) -> Trigger.Response:
        if not self.settings.allow_finish_track:
            response.success = False
            response.message = ('finish_track is disabled (parameter allow_finish_track: false; '
                                'tracks end by the next track, the end-of-input message or '
                                'track_idle_timeout_sec)')
            return response
        try:
            update = self._finish_track()
        except SolverError as exc:
            response.success, response.message = False, f'solver failed: {exc}'
            return response
        except Exception as exc:  # noqa: BLE001 - a service must answer
            response.success, response.message = False, f'{type(exc).__name__}: {exc}'
            return response
        if update is None:
            response.success, response.message = True, 'no open track'
            return response
        response.success = True
        response.message = (f'track {update.track_id}: {update.iterations} iterations, '
                            f'sigma0^2 {update.sigma0_sq:.4g}, {update.update_ms:.1f} ms')
        return response

    def _srv_reset(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self.settings.allow_reset:
            response.success = False
            response.message = 'reset is disabled (parameter allow_reset: false)'
            return response
        self._drain()
        try:
            self.session.reset()
        except Exception as exc:  # noqa: BLE001 - a service must answer
            response.success, response.message = False, f'reset refused: {exc}'
            return response
        self._publish_all()
        response.success, response.message = True, 'state cleared'
        return response

    def _srv_save(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        path = self.settings.state_file
        if not path:
            response.success, response.message = False, 'parameter state_file is empty'
            return response
        self._drain()
        try:
            self.session.save(path)
        except Exception as exc:  # noqa: BLE001 - a service must answer
            response.success, response.message = False, f'save failed: {exc}'
            return response
        response.success, response.message = True, f'saved to {path}'
        return response

    def _srv_load(self, request: Trigger.Request, response: Trigger.Response) -> Trigger.Response:
        if not self.settings.allow_load_state:
            response.success = False
            response.message = 'load_state is disabled (parameter allow_load_state: false)'
            return response
        self._drain()
        try:
            how = self.session.load()
        except Exception as exc:  # noqa: BLE001 - a service must answer
            path = self.settings.state_file
            response.success = False
            response.message = (f'no state file {path!r}' if 'no state file' in str(exc)
                                else f'load failed (state unchanged): {exc}')
            return response
        self._publish_all()
        response.success = True
        response.message = (f'loaded {self.session.n_nodes()} nodes from '
                            f'{self.settings.state_file} ({how})')
        return response

    # ------------------------------------------------------------------ publishing
    def diagnostic_values(self) -> dict[str, object]:
        """The session's diagnostics key/values, with the last update's quality figures."""
        values = self.session.diagnostic_values()
        values['measurements_lost_in_queue'] = self.queue_loss.total
        values.update(conv.quality_values(getattr(self.session.last_update, 'quality', None)))
        for name, sub in getattr(self, 'sensor_subscriptions', {}).items():
            values[f'qos/{name}'] = (sub.reliability if sub.decided
                                     else 'best_effort (auto: no publisher yet)')
        return values

    def _publish_all(self) -> None:
        """Publish path, newest pose, odometry, markers and diagnostics; never raises."""
        try:
            self._publish_outputs()
        except Exception as exc:  # noqa: BLE001 - publishing must not stop the node
            self.session.last_error = f'publish: {type(exc).__name__}: {exc}'
            self.get_logger().error(f'could not publish the outputs: {self.session.last_error}',
                                    throttle_duration_sec=self.settings.warn_throttle_sec)
        self._publish_diagnostics()

    def _publish_outputs(self) -> None:
        s = self.settings
        cp = self.aligner.corrected_path()
        self._path_nodes = len(cp.node_ids)
        if len(cp.node_ids):
            stamp_ns = int(cp.stamps_ns[-1])
        else:
            stamp_ns = self.get_clock().now().nanoseconds
        self._path_dirty = True
        if time.perf_counter() >= self._next_full_path:
            self._publish_full_path(cp, stamp_ns)
        movable = ~np.asarray(getattr(cp, 'frozen', np.zeros(len(cp.node_ids), bool)), bool)
        self.pub_window.publish(conv.path_to_msg(cp.T_world_node[movable],
                                                 cp.stamps_ns[movable], s.map_frame, stamp_ns))
        self.odom.update(cp.node_ids, cp.T_world_node)
        if self.front is not None:
            self.front.set_corrected(cp.node_ids, cp.T_world_node)
        self._publish_tf()
        k = self.session.newest_adjusted(cp)
        if k is not None:
            cov = self.session.covariance_or_unknown(int(cp.node_ids[k]))
            t_k = int(cp.stamps_ns[k])
            self.pub_pose.publish(conv.pose_with_covariance_msg(cp.T_world_node[k], cov,
                                                                s.map_frame, t_k))
            self.pub_odom.publish(conv.odometry_msg(cp.T_world_node[k], cov, s.map_frame,
                                                    s.base_frame, t_k))
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
            colors[self.session.unjoined(cp.node_ids)] = [1.0, 0.55, 0.0, 1.0]  # behind a bridge
            conn_rgba = conv.connection_rgba(view.normalized_residual, view.status,
                                             s.residual_color_scale, view.w)
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

    def _publish_full_path(self, cp: Any, stamp_ns: int) -> None:
        self._next_full_path = time.perf_counter() + self.settings.full_path_min_period_sec
        self._path_dirty = False
        # serialized from the arrays (ga_ros.io.cdr): 100,000 poses in ms instead of seconds
        self.pub_path.publish(path_cdr(cp.T_world_node, cp.stamps_ns, self.settings.map_frame,
                                       stamp_ns))

    def _full_path_timer(self) -> None:
        if self._path_dirty and time.perf_counter() >= self._next_full_path:
            cp = self.aligner.corrected_path()
            if len(cp.node_ids):
                self._publish_full_path(cp, int(cp.stamps_ns[-1]))

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
                                                self.settings.base_frame,
                                                int(cp.stamps_ns[-1])))

    def _publish_diagnostics(self) -> None:
        try:
            self.queue_loss.publishers = self.sub.get_publisher_count()
            values = self.diagnostic_values()
            health = self.session.health()
        except Exception as exc:  # noqa: BLE001 - diagnostics must not stop the node
            values = {'error': bounded(str(exc))}
            health = None
        problems = [health.message] if health is not None and not health.ok else []
        if self.tf_contested_by:
            s = self.settings
            values['tf_contested_by'] = self.tf_contested_by
            problems.append(f'another node publishes {self.tf_contested_by} -> {s.odom_frame}'
                            + ('' if s.publish_tf_when_contested else '; ours not published'))
        for name, mon in self.input_streams.items():
            r = mon.report()
            values.update(r.values(f'input/{name}/'))
            if r.loss_fraction > self.settings.loss_warn_fraction:
                problems.append(f'{name}: {r.lost} of {r.expected} messages lost')
        level, message = DiagnosticStatus.OK, 'ok'
        error = health is not None and health.error
        if self.queue_loss.total:
            problems.append(f'{self.queue_loss.total} measurements lost by a full subscription '
                            'queue')
        if self.incompatible_publishers:
            error = True
            problems.append('a publisher with an incompatible QoS is not received')
        if problems:
            level = DiagnosticStatus.ERROR if error else DiagnosticStatus.WARN
            message = '; '.join(problems)
        level_int = level[0] if isinstance(level, bytes) else int(level)
        self.pub_diag.publish(conv.diagnostics_msg(
            f'{self.get_fully_qualified_name()}: global alignment', 'ga_ros', values,
            self.get_clock().now().nanoseconds, level=level_int, message=message))


@dataclass
class QueueLoss:
    """Measurements lost before the node took them: DDS's message-lost events, plus gaps in
    the publisher's sequence numbers (a full ``KEEP_LAST`` subscription queue drops the oldest
    message silently; the numbers are per publisher, so gaps are counted only while exactly one
    publisher is matched).

    Attributes
    ----------
    lost_events : messages DDS reported lost.
    gaps : messages missing between two consecutive sequence numbers taken.
    publishers : matched publishers (refreshed by the diagnostics timer).
    """

    lost_events: int = 0
    gaps: int = 0
    publishers: int = 1
    _last: int | None = None

    @property
    def total(self) -> int:
        """Messages known to be lost."""
        return self.lost_events + self.gaps

    def seen(self, info: Any) -> None:
        """Note the message info (``publication_sequence_number``) of a message taken."""
        try:
            seq = int(info['publication_sequence_number'])
        except (KeyError, TypeError, ValueError):
            return
        if seq <= 0 or seq >= 2**63 or self.publishers != 1:  # unsupported, or several
            self._last = None
            return
        if self._last is not None and seq > self._last + 1:
            self.gaps += seq - self._last - 1
        self._last = seq


@dataclass
class RejectionLog:
    """Rejections not logged yet: how many, and the last one (source and target frame, reason,
    error)."""

    pending: int = 0
    last: tuple[Any, ...] = ()


#: Parameters of each standard input ``<name>.``: besides the OdometryInputConfig fields.
INPUT_PARAMETERS = ('topic', 'type', 'qos_reliability', 'qos_depth')


def declared_parameters(inputs: tuple[str, ...] = ()) -> list[str]:
    """Every parameter the alignment node declares (built from its config dataclasses, no
    rclpy), with those of the standard inputs named in ``inputs``."""
    names = parameter_names(AlignerConfig) + parameter_names(NodeSettings)
    for name in inputs:
        names += [f'{name}.{p}' for p in INPUT_PARAMETERS]
        names += parameter_names(OdometryInputConfig, f'{name}.')
    return names


def usage() -> str:
    """The ``--help`` text of the alignment nodes."""
    return node_usage(NODE_NAME, __doc__, declared_parameters(('<input>',)))


def main(args: list[str] | None = None) -> int:
    """Console entry point ``alignment_node`` (also ``python -m ga_ros.ros.alignment_node``)."""
    return run_node(AlignmentNode, NODE_NAME, args, usage=usage)


if __name__ == '__main__':
    sys.exit(main())
