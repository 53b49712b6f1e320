"""``vo_node``: stereo visual odometry feeding the alignment node.

An adapter of :class:`ga_ros.pipeline.stereo.StereoFrontEnd` (the replay drives the same
object): subscribes to a left/right image pair (``sensor_msgs/Image`` or, with
``compressed: true``, ``sensor_msgs/CompressedImage``) and their ``sensor_msgs/CameraInfo``,
hands each message to the front end (pairing within ``max_pair_dt_sec``, decoding, calibration,
:class:`ga_ros.vo.odometry.StereoOdometry`, :class:`ga_ros.vo.crosstrack.CrossTrackMatcher`)
and publishes what it returns.

Publishes
---------
* ``ga/measurements`` (``nav_msgs/Odometry``, the measurement encoding of
  :mod:`ga_ros.ros.conversions`): one message per keyframe-to-keyframe motion and per accepted
  cross-track connection;
* ``ga/vo/odometry`` (``nav_msgs/Odometry``): the raw integrated VO pose of every frame,
  ``odom_frame -> base_frame`` (``odom`` = the robot's first base frame), with the covariance of
  the motion from its keyframe; and, when ``publish_odom_tf``, the same pose as the TF
  ``odom_frame -> base_frame`` (as an odometry source does: turn it off when another node
  publishes ``odom -> base_link``);
* ``ga/vo/debug_image`` (``sensor_msgs/Image``, when ``publish_debug_image``): the rectified
  left image with the state written on it;
* ``ga/keyframe_cloud`` (``sensor_msgs/PointCloud2``, when ``publish_keyframe_cloud``, and
  computed only while the topic has a subscriber: dense stereo costs CPU): for each new
  keyframe, the dense stereo points of its rectified pair
  (:meth:`ga_ros.pipeline.stereo.StereoFrontEnd.keyframe_cloud`, parameters ``cloud_*``),
  fields ``x y z intensity`` (float32), in the left camera's optical frame (``header.frame_id``
  the camera frame of the extrinsic, i.e. ``camera_frame`` or the left image's frame;
  ``header.stamp`` the keyframe's stamp), :func:`ga_ros.ros.conversions.cloud_to_pointcloud2`;
* ``ga/keyframe_image`` (``sensor_msgs/Image`` mono8) and ``ga/keyframe_camera_info``
  (``sensor_msgs/CameraInfo``: ``k`` and ``p = [k | 0]`` of the rectified camera, no
  distortion), when ``publish_keyframe_image``, while the image topic has a subscriber: each new
  keyframe's rectified left image, same stamp and frame as its cloud (what ``map_node``'s
  mosaic warps; one image per keyframe, no extra computation beyond rectifying it).

Frames (REP 103/105): the VO measures the left camera's optical frame; every measurement and
pose leaves as the robot's ``base_frame``, converted with the camera's extrinsic
(:mod:`ga_ros.core.extrinsic`), resolved at the first stereo pair from ``/tf_static``
(``base_frame -> camera_frame``, the left image's frame by default), else the parameter
``T_base_camera``, else the identity when said so (``assume_identity_extrinsic: true``). Without
any of them the node refuses the pairs (counted as ``no_measurement/no camera extrinsic yet``,
diagnostics ERROR, an error naming the three ways, throttled) and keeps waiting: the first pair
after the transform arrived on ``/tf_static`` resolves it and the VO starts there.

Loss detection: each image stream has a :class:`ga_ros.pipeline.stream_rate.StreamMonitor`
(rate from the stamps, gaps counted as lost messages) and the pairs a
:class:`ga_ros.pipeline.stream_rate.FrameMonitor` (a frame of which one image arrived and the
other not is a lost pair; frames of which nothing arrived are counted from the stamp gaps); the
diagnostics report received / expected / lost and turn WARN when the lost
fraction exceeds ``loss_warn_fraction``. The image and camera-info subscriptions use the
``qos_reliability`` of the parameters with ``image_queue`` messages of depth: ``auto`` (default,
:mod:`ga_ros.ros.adaptive_qos`) subscribes reliable when every publisher offers reliable (no
loss in transport), else best effort; ``best_effort`` / ``reliable`` force it. The choice is
in the diagnostics (``qos/<stream>``).

Live end of input: when no image has arrived for ``idle_end_track_s`` (wall clock) after the
last measurement, the node publishes the end-of-input message on the measurements topic
(``nav_msgs/Odometry`` with ``child_frame_id`` :data:`ga_ros.topics.TRACK_END_FRAME`, as
``ga-ros play`` does at the end of a bag): the alignment node ends and adjusts the open track at
once; the VO's next keyframe starts a new track. A robot standing still keeps its track (its
camera still streams images).

Subscribes also to the corrected path (``nav_msgs/Path``, transient local; poses matched to
keyframes by stamp) to predict overlaps, and to ``track_boundary_topic`` (``std_msgs/Empty``)
to start a new track on request, and publishes ``diagnostics`` (``diagnostic_msgs/
DiagnosticArray``, every ``diagnostics_period_sec``): pairs received / processed / dropped,
measurements, and the count of every reason a pair gave no measurement.

Frames are never dropped silently. The image callbacks only pair messages (no decoding) and put
the pair in a bounded queue of ``pair_queue`` pairs; one worker thread runs the VO on the queue.
Policy when the VO is slower than the camera: **skip oldest** -- a new pair arriving at a full
queue drops the oldest waiting pair, so the VO always works on the newest images (the KLT
tracker bridges the gap; a gap too large loses the track, counted as ``lost``). Every drop is
counted (``dropped (queue full)``) and warned about (throttled). Parameters:
``config/vo.yaml``; the VO fields mirror
:class:`~ga_ros.vo.odometry.VoConfig`, the ``cross_*`` fields
:class:`~ga_ros.vo.crosstrack.CrossTrackConfig`. Bad input (mismatched sizes or encodings,
missing CameraInfo, textureless frames, a lost track) is warned about (throttled) and produces
no measurement; the node never dies on a message.
"""

from __future__ import annotations

import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from functools import partial
from typing import Any

import cv2
import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry, Path
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, CompressedImage, Image, PointCloud2
from std_msgs.msg import Empty
from tf2_msgs.msg import TFMessage

from ga_ros import topics
from ga_ros.core.extrinsic import ExtrinsicConfig, TransformTree
from ga_ros.core.measurement import Measurement
from ga_ros.errors import GaError, UnknownExtrinsicError
from ga_ros.geometry import se3
from ga_ros.inputs.names import CAMERA_SOURCE
from ga_ros.pipeline.params import parameter_names
from ga_ros.pipeline.stereo import (
    NO_EXTRINSIC,
    FrameOutput,
    FrontEndConfig,
    ImagePair,
    StereoFrontEnd,
)
from ga_ros.pipeline.stream_rate import FrameMonitor, StreamMonitor
from ga_ros.ros import conversions as conv
from ga_ros.ros.adaptive_qos import AdaptiveSubscription
from ga_ros.ros.bounded_log import BoundedLogging
from ga_ros.ros.params import declare_config
from ga_ros.ros.qos import latched_qos, measurement_qos, stream_qos, tf_static_qos
from ga_ros.ros.runner import node_usage, run_node
from ga_ros.vo.crosstrack import CrossTrackConfig
from ga_ros.vo.dense import DenseStereoConfig
from ga_ros.vo.odometry import VoConfig

NODE_NAME = 'vo_node'


@dataclass(frozen=True)
class VoNodeSettings:
    """ROS-side settings of :class:`VoNode` (``config/vo.yaml``).

    Attributes
    ----------
    left_image_topic, right_image_topic : image topics (``Image``, or ``CompressedImage``).
    left_info_topic, right_info_topic : ``CameraInfo`` topics.
    compressed : subscribe to ``sensor_msgs/CompressedImage`` instead of ``Image``.
    measurements_topic : output measurement encoding.
    odometry_topic : output raw VO odometry.
    path_topic : input corrected path (transient local) for overlap prediction.
    track_boundary_topic : input ``std_msgs/Empty``: start a new track.
    debug_image_topic : output debug image.
    publish_debug_image : publish the debug image.
    keyframe_cloud_topic : output dense stereo points of each keyframe (``PointCloud2``).
    publish_keyframe_cloud : publish the keyframe clouds (computed only while the topic has a
        subscriber).
    keyframe_image_topic : output rectified left image of each keyframe (``Image``).
    keyframe_info_topic : output ``CameraInfo`` of the rectified camera, per keyframe image.
    publish_keyframe_image : publish the keyframe images (while the image topic has a
        subscriber).
    cross_track : run the cross-track matcher.
    max_pair_dt_sec : largest stamp difference of a left/right pair (s).
    source : the camera's name, carried by every measurement it publishes (the measurement
        encoding's ``twist.covariance``, :mod:`ga_ros.ros.conversions`): the alignment node's
        variance group and ``calibrate_cameras`` name (default ``cam0``).
    odom_frame : REP 105 odometry frame of the VO odometry (parent of ``base_frame``).
    publish_odom_tf : publish ``odom_frame -> base_frame`` on ``tf_topic`` for every frame.
    tf_topic : TF topic (``/tf``).
    tf_static_topic : static TF topic read for the camera's extrinsic (``/tf_static``).
    qos_reliability : the image and camera-info subscriptions: ``auto`` (reliable when every
        publisher offers reliable, else best effort), ``best_effort`` (connects to best-effort
        and reliable publishers) or ``reliable``.
    image_queue : depth of the image and camera-info subscriptions (messages).
    loss_warn_fraction : diagnostics WARN when a stream's lost / expected exceeds this.
    pair_queue : stereo pairs waiting for the VO; when full, a new pair drops the oldest
        waiting one (policy: skip oldest, process the newest), counted and warned about.
    diagnostics_topic : output ``diagnostic_msgs/DiagnosticArray`` with the counts.
    diagnostics_period_sec : period of the diagnostics (s; 0 disables).
    warn_throttle_sec : minimum seconds between repeated warnings.
    idle_end_track_s : end the open track (end-of-input message on ``measurements_topic``)
        when no image has arrived for this long, wall-clock s (0: never).
    """

    left_image_topic: str = topics.LEFT_IMAGE
    right_image_topic: str = topics.RIGHT_IMAGE
    left_info_topic: str = topics.LEFT_INFO
    right_info_topic: str = topics.RIGHT_INFO
    compressed: bool = False
    measurements_topic: str = topics.MEASUREMENTS
    odometry_topic: str = topics.VO_ODOMETRY
    path_topic: str = topics.CORRECTED_PATH
    track_boundary_topic: str = topics.VO_TRACK_BOUNDARY
    debug_image_topic: str = topics.VO_DEBUG_IMAGE
    publish_debug_image: bool = False
    keyframe_cloud_topic: str = topics.KEYFRAME_CLOUD
    publish_keyframe_cloud: bool = True
    keyframe_image_topic: str = topics.KEYFRAME_IMAGE
    keyframe_info_topic: str = topics.KEYFRAME_CAMERA_INFO
    publish_keyframe_image: bool = True
    cross_track: bool = True
    max_pair_dt_sec: float = 0.005
    source: str = CAMERA_SOURCE
    odom_frame: str = 'odom'
    publish_odom_tf: bool = True
    tf_topic: str = '/tf'
    tf_static_topic: str = '/tf_static'
    qos_reliability: str = 'auto'
    image_queue: int = 10
    loss_warn_fraction: float = 0.01
    pair_queue: int = 2
    diagnostics_topic: str = topics.DIAGNOSTICS
    diagnostics_period_sec: float = 1.0
    warn_throttle_sec: float = 5.0
    idle_end_track_s: float = 2.0


def array_to_image(img: np.ndarray, stamp_ns: int, frame_id: str) -> Image:
    """uint8 grey array -> ``sensor_msgs/Image`` (mono8)."""
    msg = Image()
    msg.header.stamp = conv.ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width = int(img.shape[0]), int(img.shape[1])
    msg.encoding = 'mono8'
    msg.step = msg.width
    msg.data = np.ascontiguousarray(img, np.uint8).tobytes()
    return msg


#: ``camera_extrinsic`` of the diagnostics while pairs are refused for want of the extrinsic.
EXTRINSIC_REFUSED = 'unknown (pairs refused)'


class VoNode(BoundedLogging, Node):
    """Adapter: messages -> :class:`StereoFrontEnd` -> messages."""

    def __init__(self, **kwargs: Any) -> None:
        """``kwargs`` go to :class:`rclpy.node.Node` (e.g. ``context``,
        ``parameter_overrides`` in tests)."""
        super().__init__(NODE_NAME, **kwargs)
        self.settings: VoNodeSettings = declare_config(self, VoNodeSettings)
        self.vo_config: VoConfig = declare_config(self, VoConfig)
        self.cross_config: CrossTrackConfig = declare_config(self, CrossTrackConfig, 'cross_')
        self.extrinsic_config: ExtrinsicConfig = declare_config(self, ExtrinsicConfig)
        self.cloud_config: DenseStereoConfig = declare_config(self, DenseStereoConfig, 'cloud_')
        s = self.settings
        self.front = StereoFrontEnd(FrontEndConfig(
            vo=self.vo_config, cross=self.cross_config, cross_track=s.cross_track,
            max_pair_dt_sec=s.max_pair_dt_sec, max_pending=max(2, s.image_queue),
            source=s.source,
            extrinsic=self.extrinsic_config, cloud=self.cloud_config))
        self.extrinsic_config.from_parameters()  # a malformed T_base_camera fails at start
        self.tf_static = TransformTree()
        self.streams: dict[str, StreamMonitor | FrameMonitor] = {
            'left_image': StreamMonitor(), 'right_image': StreamMonitor(),
            'pairs': FrameMonitor(int(round(s.max_pair_dt_sec * 1e9)))}
        self._last_warn: dict[str, float] = {}
        #: why the pairs are refused while the camera's extrinsic is unknown ('' otherwise)
        self.extrinsic_error = ''
        self.counts = {'pairs': 0, 'measurements': 0, 'cross': 0, 'dropped': 0,
                       'processed': 0, 'queue_dropped': 0, 'idle_track_ends': 0,
                       'keyframe_clouds': 0, 'keyframe_images': 0}
        self._last_image = time.monotonic()
        self._measured_since_end = False
        self._queue: deque[ImagePair] = deque()
        self._lock = threading.Lock()  # the front end: worker thread vs. other callbacks
        self._wake = threading.Condition()
        self._busy = False
        self._stop = False
        self.pub_diag = self.create_publisher(DiagnosticArray, s.diagnostics_topic,
                                              stream_qos())
        if s.diagnostics_period_sec > 0:  # wall clock: reports also while sim time stands
            self.create_timer(s.diagnostics_period_sec, self.publish_diagnostics,
                              clock=RosClock(clock_type=ClockType.STEADY_TIME))
        # transient local: an alignment node that matches late (discovery across hosts, a
        # restart) still gets every measurement; volatile subscribers match it as well
        self.pub_meas = self.create_publisher(Odometry, s.measurements_topic,
                                              measurement_qos(transient_local=True))
        self.pub_odom = self.create_publisher(Odometry, s.odometry_topic, stream_qos())
        self.pub_tf = (self.create_publisher(TFMessage, s.tf_topic, stream_qos(100))
                       if s.publish_odom_tf else None)
        self.create_subscription(TFMessage, s.tf_static_topic, self._on_tf_static,
                                 tf_static_qos())
        self.pub_debug = (self.create_publisher(Image, s.debug_image_topic, stream_qos(2))
                          if s.publish_debug_image else None)
        self.pub_cloud = (self.create_publisher(PointCloud2, s.keyframe_cloud_topic,
                                                stream_qos(10))
                          if s.publish_keyframe_cloud else None)
        self.pub_kf_image = self.pub_kf_info = None
        if s.publish_keyframe_image:
            self.pub_kf_image = self.create_publisher(Image, s.keyframe_image_topic,
                                                      stream_qos(10))
            self.pub_kf_info = self.create_publisher(CameraInfo, s.keyframe_info_topic,
                                                     stream_qos(10))
        img_type = CompressedImage if s.compressed else Image
        # OpenCV now, not in the worker at the first pair: importing it there holds the GIL
        # long enough for a loaded host's executor to fall behind the camera (keep-last loss)
        import cv2  # noqa: F401, PLC0415
        # auto: reliable when every publisher offers reliable, else best effort
        depth = max(1, s.image_queue)
        self.sensor_subscriptions: dict[str, AdaptiveSubscription] = {
            f'{side}_image': AdaptiveSubscription(
                self, img_type, topic, partial(self._on_image, side=side), s.qos_reliability,
                depth)
            for side, topic in (('left', s.left_image_topic), ('right', s.right_image_topic))}
        self.sensor_subscriptions.update({
            f'{side}_info': AdaptiveSubscription(
                self, CameraInfo, topic, partial(self._on_info, side=side), s.qos_reliability,
                depth)
            for side, topic in (('left', s.left_info_topic), ('right', s.right_info_topic))})
        self.create_subscription(Path, s.path_topic, self._on_path, latched_qos())
        if s.idle_end_track_s > 0:
            self.create_timer(min(0.5, s.idle_end_track_s / 4), self._idle_check,
                              clock=RosClock(clock_type=ClockType.STEADY_TIME))
        self.create_subscription(Empty, s.track_boundary_topic, self._on_boundary, 10)
        self._worker = threading.Thread(target=self._work, name='vo_worker', daemon=True)
        self._worker.start()
        self.get_logger().info(
            f'listening to {s.left_image_topic} / {s.right_image_topic} '
            f'({"compressed" if s.compressed else "raw"}), publishing {s.measurements_topic}; '
            f'queue of {s.pair_queue} pairs (skip oldest when full)')

    @property
    def calibration(self) -> Any:
        """The front end's stereo calibration (None before both CameraInfo)."""
        return self.front.calibration

    @property
    def odometry(self) -> Any:
        """The front end's stereo VO (None before both CameraInfo)."""
        return self.front.odometry

    @property
    def matcher(self) -> Any:
        """The front end's cross-track matcher (None before both CameraInfo)."""
        return self.front.matcher

    # ------------------------------------------------------------------ helpers
    def _warn(self, key: str, text: str, error: bool = False) -> None:
        """Log ``text`` (a warning, or an error), at most once per ``warn_throttle_sec`` per
        ``key``."""
        now = self.get_clock().now().nanoseconds * 1e-9
        if now - self._last_warn.get(key, -1e18) >= self.settings.warn_throttle_sec:
            self._last_warn[key] = now
            # one call site per severity: rclpy refuses a call site whose severity changes
            # ("Logger severity cannot be changed between calls")
            if error:
                self.get_logger().error(text)
            else:
                self.get_logger().warning(text)

    def _publish_measurement(self, m: Measurement) -> None:
        self.pub_meas.publish(conv.measurement_to_odometry(m))
        self._measured_since_end = True

    def _idle_check(self) -> None:
        """End the open track when the images stopped ``idle_end_track_s`` ago (timer)."""
        if not self._measured_since_end:
            return
        idle = time.monotonic() - self._last_image
        if idle < self.settings.idle_end_track_s:
            return
        with self._wake:
            if self._queue or self._busy:
                return
        with self._lock:
            end = Odometry()
            end.child_frame_id = topics.TRACK_END_FRAME
            self.pub_meas.publish(end)
            self.front.request_track_boundary()
            self._measured_since_end = False
            self.counts['idle_track_ends'] += 1
        self.get_logger().info(f'no image for {idle:.1f} s: track ended (end-of-input message '
                               f'on {self.settings.measurements_topic}); the next keyframe '
                               'starts a new track')

    # ------------------------------------------------------------------ callbacks
    def _on_info(self, msg: CameraInfo, side: str) -> None:
        recalibrating = self.front.odometry is not None
        try:
            with self._lock:
                cal = self.front.set_camera_info(side, msg)
        except (GaError, ValueError) as exc:
            self._warn('info', f'{side} CameraInfo rejected: {exc}')
            return
        if cal is None:
            return
        with self._wake:  # pairs whose images came before this CameraInfo
            held = self.front.release_held()
        for pair in held:
            self._enqueue(pair)
        if recalibrating:
            self.get_logger().warning('stereo calibration changed: VO re-initialises')
        self.get_logger().info(
            f'stereo calibration {cal.width}x{cal.height}, f = {cal.K[0, 0]:.1f} px, '
            f'baseline {cal.baseline_m:.3f} m, '
            f'{"rectifying" if cal.needs_rectification else "already rectified"}')

    def _on_tf_static(self, msg: TFMessage) -> None:
        with self._lock:
            self.tf_static.add_message(msg)

    def _resolve_extrinsic(self, pair: ImagePair) -> bool:
        """The camera's extrinsic at a pair (``/tf_static``, parameters, identity when said
        so); False, with the refusal counted and logged (throttled), while it is unknown."""
        cfg = self.extrinsic_config
        camera = cfg.camera_frame or str(pair.left.header.frame_id)
        try:
            ext = cfg.resolve(self.tf_static.lookup(cfg.base_frame, camera), camera)
        except UnknownExtrinsicError as exc:
            self.front.count_dropped(pair, NO_EXTRINSIC)
            self.extrinsic_error = str(exc)
            refused = self.front.stats.reasons.get(NO_EXTRINSIC, 0)
            self._warn('extrinsic', f'stereo pair refused ({refused} so far): {exc}',
                       error=True)
            return False
        self.front.set_extrinsic(ext)
        self.extrinsic_error = ''
        self.get_logger().info(f'camera {camera!r} in {cfg.base_frame!r} from {ext.source}')
        return True

    def _on_image(self, msg: Image | CompressedImage, side: str) -> None:
        self._last_image = time.monotonic()
        stamp = conv.stamp_to_ns(msg.header.stamp)
        self.streams[f'{side}_image'].add(stamp)
        self.streams['pairs'].announce(stamp)
        pair = self.front.pair_image(side, msg)  # cheap: no decoding
        if pair is None:
            return
        self.streams['pairs'].completed(pair.stamp_ns)
        with self._wake:  # before the calibration: wait for it (_on_info releases the pair)
            held = self.front.hold_until_calibrated(pair)
            waiting = self.front.n_held
        if held:
            self._warn('info_wait', f'no CameraInfo yet for both cameras: {waiting} stereo '
                       f'pairs wait for it (at most {self.front.config.max_pending}, older ones '
                       f'are dropped); check {self.settings.left_info_topic} and '
                       f'{self.settings.right_info_topic}')
            return
        self._enqueue(pair)

    def _enqueue(self, pair: ImagePair) -> None:
        """Queue a pair for the worker; a full queue drops its oldest pair (counted)."""
        dropped = None
        with self._wake:
            if len(self._queue) >= max(1, self.settings.pair_queue):
                dropped = self._queue.popleft()  # policy: skip oldest
            self._queue.append(pair)
            self._wake.notify()
        if dropped is not None:
            self.front.count_dropped(dropped)
            self.counts['queue_dropped'] += 1
            self._warn('queue', f'{self.counts["queue_dropped"]} stereo pairs dropped so far: '
                       'the VO is slower than the camera (queue of '
                       f'{self.settings.pair_queue} pairs full, oldest skipped)')

    def _work(self) -> None:
        """Worker thread: run the VO on queued pairs until the node is destroyed."""
        while True:
            with self._wake:
                while not self._queue and not self._stop:
                    self._wake.wait()
                if self._stop:
                    return
                pair = self._queue.popleft()
                self._busy = True
            try:
                self.process(pair)
            except Exception as exc:  # noqa: BLE001 - the worker must survive any pair
                self._warn('worker', f'stereo pair failed: {type(exc).__name__}: {exc}')
            finally:
                with self._wake:
                    self._busy = False
                    self._wake.notify_all()

    def wait_idle(self, timeout_sec: float = 30.0) -> bool:
        """Block until the queue is empty and no pair is in work (tests, shutdown)."""
        with self._wake:
            return self._wake.wait_for(lambda: not self._queue and not self._busy,
                                       timeout_sec)

    def process(self, pair: ImagePair) -> None:
        """Run the front end on one pair and publish what it gives (worker thread)."""
        with self._lock:
            if self.front.extrinsic is None and not self._resolve_extrinsic(pair):
                return
            frame = self.front.process_pair(pair)
            self.counts['processed'] += 1
            self._publish_frame(frame)

    def diagnostic_values(self) -> dict[str, object]:
        """Counts of the node: pairs received, processed, dropped, and every reason."""
        st = self.front.stats
        values: dict[str, object] = {
            'pairs_received': st.pairs, 'pairs_processed': self.counts['processed'],
            'pairs_dropped_queue_full': self.counts['queue_dropped'],
            'queue_length': len(self._queue), 'measurements': st.measurements,
            'cross_connections': self.counts['cross'], 'keyframes': st.keyframes,
            'unpaired_images': st.unpaired, 'camera_info_rejected': st.camera_info_rejected,
            'tracks_ended_idle': self.counts['idle_track_ends'],
            'keyframe_clouds': self.counts['keyframe_clouds'],
            'keyframe_images': self.counts['keyframe_images']}
        for key, n in st.reasons.items():
            values['no_measurement/' + key] = n
        if time.monotonic() - self._last_image > 1.0:   # input idle: settle every frame
            self.streams['pairs'].flush()
        for name, mon in self.streams.items():
            values.update(mon.report().values(f'{name}/'))
        ext = self.front.extrinsic
        values['camera_extrinsic'] = (ext.source if ext is not None else
                                      EXTRINSIC_REFUSED if self.extrinsic_error
                                      else 'not resolved yet')
        for name, sub in self.sensor_subscriptions.items():
            values[f'qos/{name}'] = (sub.reliability if sub.decided
                                     else 'best_effort (auto: no publisher yet)')
        return values

    def health(self) -> tuple[int, str]:
        """Diagnostic level (0 OK, 1 WARN, 2 ERROR) and message: queue drops, streams losing
        more than ``loss_warn_fraction`` (WARN), an unknown camera extrinsic (ERROR: the pairs
        are refused until it is known; identity only when said so)."""
        problems = []
        level = 1
        dropped = self.counts['queue_dropped']
        if dropped:
            problems.append(f'{dropped} pairs dropped (queue full)')
        for name, mon in self.streams.items():
            r = mon.report()
            if r.loss_fraction > self.settings.loss_warn_fraction:
                problems.append(f'{name}: {r.lost} of {r.expected} lost '
                                f'({100 * r.loss_fraction:.1f} %)')
        if self.front.extrinsic is None and self.extrinsic_error:
            refused = self.front.stats.reasons.get(NO_EXTRINSIC, 0)
            problems.insert(0, f'{refused} pairs refused: {self.extrinsic_error}')
            level = 2
        return (level, '; '.join(problems)) if problems else (0, 'ok')

    def publish_diagnostics(self) -> None:
        """Publish the counts on ``diagnostics_topic``."""
        values = self.diagnostic_values()
        level, message = self.health()
        self.pub_diag.publish(conv.diagnostics_msg(
            f'{self.get_name()}: stereo VO', self.extrinsic_config.base_frame, values,
            self.get_clock().now().nanoseconds, level=level, message=message))

    def destroy_node(self) -> None:
        """Stop the worker thread, then destroy the node."""
        with self._wake:
            self._stop = True
            self._wake.notify_all()
        self._worker.join(timeout=5.0)
        super().destroy_node()

    def _publish_frame(self, frame: FrameOutput) -> None:
        res = frame.result
        if res is None:
            self.counts['dropped'] += 1
            self._warn('frame', f'stereo pair dropped: {frame.error}')
            return
        self.counts['pairs'] += 1
        if res.status in ('lost', 'rejected'):
            self._warn('lost', f'VO {res.status}: {res.reason}; re-initialising')
        if res.measurement is not None:
            self._publish_measurement(res.measurement)
            self.counts['measurements'] += 1
        try:
            attempts = self.front.match(frame)
        except GaError as exc:
            self._warn('cross', f'cross-track matching failed: {exc}')
            attempts = []
        for a in attempts:
            if a.accepted and a.measurement is not None:
                self._publish_measurement(a.measurement)
                self.counts['cross'] += 1
            self.get_logger().debug(
                f'cross {a.src_id}->{a.dst_id}: overlap {a.predicted_overlap:.2f}, '
                f'{a.n_matches} matches, {a.n_inliers} inliers, ratio {a.inlier_ratio:.2f}, '
                f'spread {a.spread:.2f}, s2 {a.sigma0_sq:.2f}: '
                f'{"accepted" if a.accepted else "rejected: " + a.reason}')
        cov = res.cov if res.cov is not None else np.eye(6) * 1e-9
        ext = self.front.extrinsic
        if ext is not None and not ext.is_identity:
            Ad = se3.adjoint(ext.T_base_cam)
            cov = Ad @ cov @ Ad.T
        T_odom_base = self.front.base_pose(res.T_world_cam)
        s, base = self.settings, self.extrinsic_config.base_frame
        self.pub_odom.publish(conv.odometry_msg(T_odom_base, cov, s.odom_frame, base,
                                                frame.stamp_ns))
        if self.pub_tf is not None:
            self.pub_tf.publish(TFMessage(transforms=[
                conv.transform_msg(s.odom_frame, base, T_odom_base, frame.stamp_ns)]))
        if self.pub_debug is not None and frame.left is not None:
            self._publish_debug(frame)
        if res.keyframe is not None:
            self._publish_keyframe(frame)

    def _camera_frame(self) -> str:
        """The left camera's optical frame id (of the extrinsic; ``'camera'`` when none)."""
        ext = self.front.extrinsic
        return ext.camera_frame if ext is not None and ext.camera_frame else 'camera'

    def _publish_keyframe(self, frame: FrameOutput) -> None:
        """The frame's new keyframe: its rectified left image (+ CameraInfo) on
        ``keyframe_image_topic`` and its dense stereo points on ``keyframe_cloud_topic``, each
        only while subscribed (the pair is rectified once for both)."""
        want_cloud = (self.pub_cloud is not None
                      and self.pub_cloud.get_subscription_count() > 0)
        want_image = (self.pub_kf_image is not None
                      and self.pub_kf_image.get_subscription_count() > 0)
        if not (want_cloud or want_image) or frame.result is None:
            return
        kf = frame.result.keyframe
        try:
            pair = self.front.keyframe_pair(frame)
            cloud = self.front.keyframe_cloud(frame, pair) if want_cloud else None
        except GaError as exc:
            self._warn('cloud', f'keyframe cloud failed: {exc}')
            return
        if pair is None or kf is None:
            return
        frame_id = self._camera_frame()
        if want_image:
            self.pub_kf_image.publish(array_to_image(pair[0], kf.stamp_ns, frame_id))
            self.pub_kf_info.publish(self._rectified_info(pair[0].shape, kf.stamp_ns, frame_id))
            self.counts['keyframe_images'] += 1
        if cloud is not None:
            self.pub_cloud.publish(conv.cloud_to_pointcloud2(
                cloud.points, cloud.intensity, frame_id, kf.stamp_ns))
            self.counts['keyframe_clouds'] += 1

    def _rectified_info(self, shape: tuple[int, ...], stamp_ns: int, frame_id: str
                        ) -> CameraInfo:
        """``CameraInfo`` of the rectified left camera (``k``, ``p = [k | 0]``, no
        distortion, ``r`` the identity)."""
        K = np.asarray(self.front.calibration.K, float).reshape(3, 3)
        msg = CameraInfo()
        msg.header.stamp = conv.ns_to_stamp(stamp_ns)
        msg.header.frame_id = frame_id
        msg.height, msg.width = int(shape[0]), int(shape[1])
        msg.distortion_model = 'plumb_bob'
        msg.d = [0.0] * 5
        msg.k = K.reshape(-1).tolist()
        msg.r = np.eye(3).reshape(-1).tolist()
        msg.p = np.hstack([K, np.zeros((3, 1))]).reshape(-1).tolist()
        return msg

    def _publish_debug(self, frame: FrameOutput) -> None:
        cal, res = self.front.calibration, frame.result
        if cal is None or res is None:
            return
        rect, _ = cal.rectify(frame.left, frame.right)
        img = rect.copy()
        cv2.putText(img, f'{res.status} kf {res.keyframe_id} trk {res.track_id} '
                    f'inl {res.n_inliers}', (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 255, 1)
        self.pub_debug.publish(array_to_image(img, res.stamp_ns, self._camera_frame()))

    def _on_path(self, msg: Path) -> None:
        if self.front.matcher is None or not msg.poses:
            return
        try:
            T = conv.path_msg_to_poses(msg)
            stamps = np.array([conv.stamp_to_ns(ps.header.stamp) for ps in msg.poses],
                              dtype=np.int64)
            with self._lock:
                self.front.set_corrected_by_stamp(stamps, T)
        except (GaError, ValueError) as exc:
            self._warn('path', f'corrected path ignored: {exc}')

    def _on_boundary(self, _msg: Empty) -> None:
        with self._lock:
            self.front.request_track_boundary()


def declared_parameters() -> list[str]:
    """Every parameter ``vo_node`` declares (built from its config dataclasses, no rclpy)."""
    return (parameter_names(VoNodeSettings) + parameter_names(VoConfig)
            + parameter_names(CrossTrackConfig, 'cross_') + parameter_names(ExtrinsicConfig)
            + parameter_names(DenseStereoConfig, 'cloud_'))


def main(args: list[str] | None = None) -> int:
    """Console entry point ``vo_node`` (also ``python -m ga_ros.ros.vo_node``)."""
    return run_node(VoNode, NODE_NAME, args,
                    usage=lambda: node_usage(NODE_NAME, __doc__, declared_parameters()))


if __name__ == '__main__':
    sys.exit(main())
