"""``vo_node``: stereo visual odometry feeding the alignment node.

Subscribes to a left/right image pair (``sensor_msgs/Image`` or, with ``compressed: true``,
``sensor_msgs/CompressedImage``) and their ``sensor_msgs/CameraInfo``; pairs left and right by
stamp (its own approximate-time pairing, within ``max_pair_dt_sec``), rectifies when the
CameraInfo says the images are raw, and runs :class:`ga_ros.vo.odometry.StereoOdometry` and
:class:`ga_ros.vo.crosstrack.CrossTrackMatcher`.

Publishes
---------
* ``/ga/measurements`` (``nav_msgs/Odometry``, the measurement encoding of
  :mod:`ga_ros.ros.conversions`): one message per keyframe-to-keyframe motion and per accepted
  cross-track connection;
* ``/ga/vo/odometry`` (``nav_msgs/Odometry``): the raw integrated VO pose of every frame
  (``odom_frame`` = first camera frame), with the covariance of the motion from its keyframe;
* ``/ga/vo/debug_image`` (``sensor_msgs/Image``, when ``publish_debug_image``): the rectified
  left image with the state written on it.

Subscribes also to the corrected path (``nav_msgs/Path``, transient local; poses matched to
keyframes by stamp) to predict overlaps, and to ``track_boundary_topic`` (``std_msgs/Empty``)
to start a new track on request. Parameters: ``config/vo.yaml``; the VO fields mirror
:class:`~ga_ros.vo.odometry.VoConfig`, the ``cross_*`` fields
:class:`~ga_ros.vo.crosstrack.CrossTrackConfig`. Bad input (mismatched sizes or encodings,
missing CameraInfo, textureless frames, a lost track) is warned about (throttled) and produces
no measurement; the node never dies on a message.
"""

from __future__ import annotations

import re
import sys
from collections import deque
from dataclasses import dataclass, fields

import cv2
import numpy as np
from nav_msgs.msg import Odometry, Path
from rcl_interfaces.msg import ParameterDescriptor
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Empty

from ga_ros.errors import GaError, InputError
from ga_ros.ros import conversions as conv
from ga_ros.ros.qos import latched_qos, measurement_qos, stream_qos
from ga_ros.ros.runner import run_node
from ga_ros.vo.calibration import CameraModel, StereoCalibration
from ga_ros.vo.crosstrack import CrossTrackConfig, CrossTrackMatcher
from ga_ros.vo.odometry import StereoFrame, StereoOdometry, VoConfig, VoResult

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
    cross_track : run the cross-track matcher.
    max_pair_dt_sec : largest stamp difference of a left/right pair (s).
    odom_frame, camera_frame : frame ids of the raw VO odometry.
    image_queue : depth of the image subscriptions (best effort, sensor-data QoS).
    warn_throttle_sec : minimum seconds between repeated warnings.
    """

    left_image_topic: str = '/stereo/left/image_rect'
    right_image_topic: str = '/stereo/right/image_rect'
    left_info_topic: str = '/stereo/left/camera_info'
    right_info_topic: str = '/stereo/right/camera_info'
    compressed: bool = False
    measurements_topic: str = '/ga/measurements'
    odometry_topic: str = '/ga/vo/odometry'
    path_topic: str = '/ga/corrected_path'
    track_boundary_topic: str = '/ga/vo/track_boundary'
    debug_image_topic: str = '/ga/vo/debug_image'
    publish_debug_image: bool = False
    cross_track: bool = True
    max_pair_dt_sec: float = 0.005
    odom_frame: str = 'vo_odom'
    camera_frame: str = 'camera'
    image_queue: int = 10
    warn_throttle_sec: float = 5.0


# ----------------------------------------------------------------------------- conversions
def image_to_array(msg: Image) -> np.ndarray:
    """``sensor_msgs/Image`` (mono8, bgr8, rgb8, bgra8, rgba8) -> uint8 grey array.

    Raises
    ------
    InputError
        Unsupported encoding, or a data size that disagrees with ``height``, ``step``.
    """
    channels = {'mono8': 1, '8uc1': 1, 'bgr8': 3, 'rgb8': 3, 'bgra8': 4, 'rgba8': 4, '8uc3': 3}
    enc = msg.encoding.lower()
    if enc not in channels:
        raise InputError(f'unsupported image encoding {msg.encoding!r} (use mono8 or bgr8)')
    c = channels[enc]
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.frombuffer(bytes(msg.data) if not isinstance(msg.data, bytes) else msg.data,
                         np.uint8)
    if h <= 0 or w <= 0 or step < w * c or data.size < h * step:
        raise InputError(f'image data of {data.size} bytes does not match {w}x{h}, step {step}')
    img = data[:h * step].reshape(h, step)[:, :w * c].reshape(h, w, c)
    if c == 1:
        return np.ascontiguousarray(img[:, :, 0])
    code = {'bgr8': cv2.COLOR_BGR2GRAY, '8uc3': cv2.COLOR_BGR2GRAY, 'rgb8': cv2.COLOR_RGB2GRAY,
            'bgra8': cv2.COLOR_BGRA2GRAY, 'rgba8': cv2.COLOR_RGBA2GRAY}[enc]
    return cv2.cvtColor(np.ascontiguousarray(img), code)


def compressed_to_array(msg: CompressedImage) -> np.ndarray:
    """``sensor_msgs/CompressedImage`` (jpeg / png) -> uint8 grey array."""
    buf = np.frombuffer(bytes(msg.data), np.uint8)
    img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if buf.size else None
    if img is None:
        raise InputError(f'could not decode compressed image (format {msg.format!r})')
    return img


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


def camera_info_to_model(msg: CameraInfo) -> CameraModel:
    """``sensor_msgs/CameraInfo`` -> :class:`CameraModel` (InputError when K is empty)."""
    K = np.asarray(msg.k, float).reshape(3, 3)
    if K[0, 0] <= 0 or K[1, 1] <= 0 or msg.width <= 0 or msg.height <= 0:
        raise InputError('CameraInfo has no intrinsics (K is zero) or no image size')
    P = np.asarray(msg.p, float).reshape(3, 4)
    R = np.asarray(msg.r, float).reshape(3, 3)
    if not np.any(R):
        R = np.eye(3)
    return CameraModel(int(msg.width), int(msg.height), K, np.asarray(msg.d, float), R,
                       P if np.any(P) else None, msg.distortion_model or 'plumb_bob')


def field_docs(cls: type) -> dict[str, str]:
    """``{field: text}`` from the numpydoc ``Attributes`` section of a config dataclass."""
    docs: dict[str, str] = {}
    names: list[str] = []
    for line in (cls.__doc__ or '').splitlines():
        m = re.match(r'^    ([a-z_0-9, ]+) : (.*)$', line)
        if m:
            names = [n.strip() for n in m.group(1).split(',')]
            for n in names:
                docs[n] = m.group(2).strip()
        elif names and line.startswith('        ') and line.strip():
            for n in names:
                docs[n] += ' ' + line.strip()
        else:
            names = []
    return docs


def _declare(node: Node, cls: type, prefix: str = '') -> object:
    """Declare one parameter per dataclass field (name = prefix + field, description = the
    field's documentation) and build the config from the values."""
    defaults = cls()
    docs = field_docs(cls)
    values = {}
    for f in fields(cls):
        default = getattr(defaults, f.name)
        text = docs.get(f.name, f.name.replace('_', ' ')).replace('``', '')
        desc = ParameterDescriptor(name=prefix + f.name, read_only=True,
                                   description=f'{cls.__name__}.{f.name}: {text}')
        value = node.declare_parameter(prefix + f.name, default, desc).value
        if isinstance(default, float) and isinstance(value, int):
            value = float(value)
        values[f.name] = value
    return cls(**values)


class VoNode(Node):
    """Adapter: messages -> :class:`StereoOdometry` / :class:`CrossTrackMatcher` -> messages."""

    def __init__(self, **kwargs: object) -> None:
        """``kwargs`` go to :class:`rclpy.node.Node` (e.g. ``context``,
        ``parameter_overrides`` in tests)."""
        super().__init__(NODE_NAME, **kwargs)
        self.settings: VoNodeSettings = _declare(self, VoNodeSettings)
        self.vo_config: VoConfig = _declare(self, VoConfig)
        self.cross_config: CrossTrackConfig = _declare(self, CrossTrackConfig, 'cross_')
        s = self.settings
        self.odometry: StereoOdometry | None = None
        self.matcher: CrossTrackMatcher | None = None
        self.calibration: StereoCalibration | None = None
        self._info: dict[str, CameraModel] = {}
        self._lefts: deque = deque(maxlen=max(2, s.image_queue))
        self._rights: deque = deque(maxlen=max(2, s.image_queue))
        self._stamp_to_node: dict[int, int] = {}
        self._last_warn: dict[str, float] = {}
        self.counts = {'pairs': 0, 'measurements': 0, 'cross': 0, 'dropped': 0}
        self.pub_meas = self.create_publisher(Odometry, s.measurements_topic, measurement_qos())
        self.pub_odom = self.create_publisher(Odometry, s.odometry_topic, stream_qos())
        self.pub_debug = (self.create_publisher(Image, s.debug_image_topic, stream_qos(2))
                          if s.publish_debug_image else None)
        img_type = CompressedImage if s.compressed else Image
        # Best effort (sensor-data QoS) matches both best-effort and reliable publishers.
        qos = QoSProfile(depth=max(1, s.image_queue), history=HistoryPolicy.KEEP_LAST,
                         reliability=ReliabilityPolicy.BEST_EFFORT,
                         durability=DurabilityPolicy.VOLATILE)
        self.create_subscription(img_type, s.left_image_topic,
                                 lambda m: self._on_image(m, 'left'), qos)
        self.create_subscription(img_type, s.right_image_topic,
                                 lambda m: self._on_image(m, 'right'), qos)
        self.create_subscription(CameraInfo, s.left_info_topic,
                                 lambda m: self._on_info(m, 'left'), qos)
        self.create_subscription(CameraInfo, s.right_info_topic,
                                 lambda m: self._on_info(m, 'right'), qos)
        self.create_subscription(Path, s.path_topic, self._on_path, latched_qos())
        self.create_subscription(Empty, s.track_boundary_topic, self._on_boundary, 10)
        self.get_logger().info(
            f'listening to {s.left_image_topic} / {s.right_image_topic} '
            f'({"compressed" if s.compressed else "raw"}), publishing {s.measurements_topic}')

    # ------------------------------------------------------------------ helpers
    def _warn(self, key: str, text: str) -> None:
        now = self.get_clock().now().nanoseconds * 1e-9
        if now - self._last_warn.get(key, -1e18) >= self.settings.warn_throttle_sec:
            self._last_warn[key] = now
            self.get_logger().warning(text)

    # ------------------------------------------------------------------ callbacks
    def _on_info(self, msg: CameraInfo, side: str) -> None:
        try:
            model = camera_info_to_model(msg)
        except (GaError, ValueError) as exc:
            self._warn('info', f'{side} CameraInfo rejected: {exc}')
            return
        old = self._info.get(side)
        if old is not None and _same_model(old, model) and self.calibration is not None:
            return
        self._info[side] = model
        if 'left' in self._info and 'right' in self._info:
            try:
                cal = StereoCalibration.from_camera_models(self._info['left'],
                                                           self._info['right'])
            except GaError as exc:
                if old is not None:
                    self._info[side] = old  # keep the last good calibration
                self._warn('info', f'stereo calibration rejected: {exc}')
                return
            self.calibration = cal
            if self.odometry is None:
                self.odometry = StereoOdometry(cal, self.vo_config)
            else:  # a changed calibration: continue node and track ids, re-initialise
                self.get_logger().warning('stereo calibration changed: VO re-initialises')
                self.odometry = self.odometry.recalibrated(cal)
            self.matcher = CrossTrackMatcher(cal.K, cal.width, cal.height, self.cross_config)
            self.get_logger().info(
                f'stereo calibration {cal.width}x{cal.height}, f = {cal.K[0, 0]:.1f} px, '
                f'baseline {cal.baseline_m:.3f} m, '
                f'{"rectifying" if cal.needs_rectification else "already rectified"}')

    def _on_image(self, msg: Image | CompressedImage, side: str) -> None:
        stamp = conv.stamp_to_ns(msg.header.stamp)
        try:
            img = (compressed_to_array(msg) if isinstance(msg, CompressedImage)
                   else image_to_array(msg))
        except (GaError, ValueError) as exc:
            self.counts['dropped'] += 1
            self._warn('image', f'{side} image dropped: {exc}')
            return
        (self._lefts if side == 'left' else self._rights).append((stamp, img))
        self._pair()

    def _pair(self) -> None:
        tol = int(self.settings.max_pair_dt_sec * 1e9)
        while self._lefts and self._rights:
            tl, left = self._lefts[0]
            tr, right = self._rights[0]
            if abs(tl - tr) <= tol:
                self._lefts.popleft()
                self._rights.popleft()
                self._process(left, right, tl)
            elif tl < tr:
                self._lefts.popleft()
            else:
                self._rights.popleft()

    def _process(self, left: np.ndarray, right: np.ndarray, stamp_ns: int) -> None:
        if self.odometry is None:
            self.counts['dropped'] += 1
            self._warn('no_info', 'stereo pair dropped: no CameraInfo for both cameras yet')
            return
        self.counts['pairs'] += 1
        try:
            res = self.odometry.process(StereoFrame(left, right, stamp_ns))
        except GaError as exc:
            self.counts['dropped'] += 1
            self._warn('frame', f'stereo pair dropped: {exc}')
            return
        if res.status in ('lost', 'rejected'):
            self._warn('lost', f'VO {res.status}: {res.reason}; re-initialising')
        if res.measurement is not None:
            self.pub_meas.publish(conv.measurement_to_odometry(res.measurement))
            self.counts['measurements'] += 1
        if res.keyframe is not None:
            self._stamp_to_node[res.keyframe.stamp_ns] = res.keyframe.node_id
            while len(self._stamp_to_node) > 50000:  # bounded (oldest first)
                self._stamp_to_node.pop(next(iter(self._stamp_to_node)))
            if self.settings.cross_track and self.matcher is not None:
                self._cross(res)
        cov = res.cov if res.cov is not None else np.eye(6) * 1e-9
        self.pub_odom.publish(conv.odometry_msg(res.T_world_cam, cov, self.settings.odom_frame,
                                                self.settings.camera_frame, stamp_ns))
        if self.pub_debug is not None:
            self._publish_debug(left, right, res)

    def _cross(self, res: VoResult) -> None:
        try:
            attempts = self.matcher.add(res.keyframe)
        except GaError as exc:
            self._warn('cross', f'cross-track matching failed: {exc}')
            return
        for a in attempts:
            if a.accepted and a.measurement is not None:
                self.pub_meas.publish(conv.measurement_to_odometry(a.measurement))
                self.counts['cross'] += 1
            self.get_logger().debug(
                f'cross {a.src_id}->{a.dst_id}: overlap {a.predicted_overlap:.2f}, '
                f'{a.n_matches} matches, {a.n_inliers} inliers, ratio {a.inlier_ratio:.2f}, '
                f'spread {a.spread:.2f}, s2 {a.sigma0_sq:.2f}: '
                f'{"accepted" if a.accepted else "rejected: " + a.reason}')

    def _publish_debug(self, left: np.ndarray, right: np.ndarray, res: VoResult) -> None:
        if self.calibration is None:
            return
        rect, _ = self.calibration.rectify(left, right)
        img = rect.copy()
        cv2.putText(img, f'{res.status} kf {res.keyframe_id} trk {res.track_id} '
                    f'inl {res.n_inliers}', (5, 15), cv2.FONT_HERSHEY_SIMPLEX, 0.4, 255, 1)
        self.pub_debug.publish(array_to_image(img, res.stamp_ns, self.settings.camera_frame))

    def _on_path(self, msg: Path) -> None:
        if self.matcher is None or not msg.poses:
            return
        try:
            T = conv.path_msg_to_poses(msg)
        except (GaError, ValueError) as exc:
            self._warn('path', f'corrected path ignored: {exc}')
            return
        ids, keep = [], []
        for k, ps in enumerate(msg.poses):
            node = self._stamp_to_node.get(conv.stamp_to_ns(ps.header.stamp))
            if node is not None:
                ids.append(node)
                keep.append(k)
        if ids:
            try:
                self.matcher.set_corrected_poses(np.asarray(ids), T[keep])
            except GaError as exc:
                self._warn('path', f'corrected path ignored: {exc}')

    def _on_boundary(self, _msg: Empty) -> None:
        if self.odometry is not None:
            self.odometry.request_track_boundary()


def _same_model(a: CameraModel, b: CameraModel) -> bool:
    return ((a.width, a.height) == (b.width, b.height)
            and np.array_equal(np.asarray(a.K), np.asarray(b.K))
            and np.array_equal(np.asarray(a.D), np.asarray(b.D))
            and np.array_equal(a.projection(), b.projection()))


def main(args: list[str] | None = None) -> int:
    """Console entry point ``vo_node`` (also ``python -m ga_ros.ros.vo_node``)."""
    return run_node(VoNode, NODE_NAME, args)


if __name__ == '__main__':
    sys.exit(main())
