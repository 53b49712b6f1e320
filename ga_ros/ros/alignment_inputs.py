"""Standard, camera and absolute inputs of the alignment node: their parameters,
subscriptions and callbacks (mixin of :class:`~ga_ros.ros.alignment_node.AlignmentNode`)."""


from dataclasses import replace
from functools import partial
from typing import Any

import numpy as np
from nav_msgs.msg import Odometry
from rcl_interfaces.msg import ParameterDescriptor
from sensor_msgs.msg import CameraInfo, CompressedImage, Image
from std_msgs.msg import Empty
from tf2_msgs.msg import TFMessage

from ga_ros.core.extrinsic import (
    ExtrinsicConfig,
    renamed_parameter_error,
    unknown_extrinsic_error,
)
from ga_ros.errors import GaError, InputError
from ga_ros.geometry import se3
from ga_ros.inputs.absolute import ABSOLUTE_TYPES, AbsoluteInputConfig
from ga_ros.inputs.absolute import POSE_COV as ABS_POSE_COV
from ga_ros.inputs.messages import INPUT_TYPES, ODOMETRY
from ga_ros.inputs.names import CAMERA_SOURCE
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.pipeline.absolute import AbsoluteFrontEnd, AbsoluteSpec
from ga_ros.pipeline.inputs import (
    InputFrontEnd,
    InputSpec,
    InputStep,
)
from ga_ros.pipeline.journal import datum_path, read_datum, write_datum
from ga_ros.pipeline.keyframe_camera import KeyframeCamera, KeyframeCameraConfig
from ga_ros.pipeline.stereo import FrontEndConfig
from ga_ros.pipeline.stream_rate import StreamMonitor
from ga_ros.ros import conversions as conv
from ga_ros.ros.adaptive_qos import AdaptiveSubscription
from ga_ros.ros.alignment_settings import NodeSettings
from ga_ros.ros.message_types import message_class
from ga_ros.ros.params import declare_config
from ga_ros.ros.qos import (
    AUTO,
    RELIABILITIES,
    latched_qos,
    measurement_qos,
    sensor_qos,
)


class AlignmentInputs:
    """Inputs of :class:`~ga_ros.ros.alignment_node.AlignmentNode`."""

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
        source = declare('source', CAMERA_SOURCE, "the camera's name: the source of its "
                         'cross-track connections (variance group, calibrate_cameras)')
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
            front=FrontEndConfig(source=str(source)),
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
        self._save_datum()
        self._publish_earth()
        self._resolve_fixes()

    def _restore_datum(self) -> None:
        """The map frame's geodetic origin saved beside the state file (a restart keeps the
        frame of the restored poses and fixes; :func:`~ga_ros.pipeline.journal.read_datum`)."""
        path = self.settings.state_file
        self._datum_saved = False
        if self.absolute is None or not path:
            return
        try:
            datum, where = read_datum(path), str(datum_path(path))
        except (OSError, GaError) as exc:
            datum, where = None, f'{exc}'
        if datum is None and self.session.datum is not None:  # the journal holds it too
            datum, where = self.session.datum, f'the journal of {path}'
        if datum is None:
            if where != str(datum_path(path)):
                self.get_logger().error(f'{where}; the next NavSatFix sets the map origin anew')
            return
        for name in self.absolute.restore_datum(datum):
            self.get_logger().warning(
                f'{name}.datum differs from the origin of the saved state {list(datum)} '
                f'({where}): its fixes are in another frame than the restored poses')
        self._datum_saved = True
        self.get_logger().info(f'map origin (lat, lon, alt) {list(datum)} from {where}')

    def _save_datum(self) -> None:
        """Write the map frame's geodetic origin beside the state file once it is known."""
        path = self.settings.state_file
        if self._datum_saved or self.absolute is None or not path:
            return
        datum = self.absolute.earth_datum()
        if datum is None:
            return
        self.session.journal_datum(datum)
        try:
            write_datum(path, datum)
        except (OSError, GaError) as exc:
            self.get_logger().error(f'the map origin cannot be saved beside the state file: '
                                    f'{exc}', throttle_duration_sec=10.0)
            return
        self._datum_saved = True

    def _resolve_fixes(self) -> None:
        """Fixes the odometry now covers -> the aligner (a track boundary if one asks)."""
        if self.absolute is None or self.front is None:
            return
        step = self.absolute.resolve(self.front.inputs[self.front.primary])
        if step.end_track:
            self.front.track_boundary()
        warned = self.odom.jumps_warned
        self.odom.add_fixes(step.fixes)   # they place the map until the first update
        self._placement_changed(warned)
        self._fix_feeder.add(step.fixes)
        # the session journals the fixes with the measurements and joins their nodes' pieces
        for error in self._fix_feeder.flush(self.session):
            self.get_logger().warning(f'fix refused: {error}', throttle_duration_sec=5.0)

    def _subscribe_inputs(self, s: NodeSettings) -> None:
        #: the sensor subscriptions by input name (their reliability, :mod:`.adaptive_qos`)
        self.sensor_subscriptions: dict[str, AdaptiveSubscription] = {}
        if self.front is None:
            return
        if self.absolute is not None:
            for spec in self.absolute.specs.values():
                self.sensor_subscriptions[spec.name] = AdaptiveSubscription(
                    self, message_class(spec.msgtype), spec.topic,
                    partial(self._on_absolute, spec.name), AUTO, 100)
            # the sensors' lever arms (latched: every static broadcaster's last message)
            self.create_subscription(TFMessage, '/tf_static', self.absolute.static_transform,
                                     latched_qos(100))
        # the message classes follow the type names of inputs/messages.py and inputs/absolute.py
        for spec in self.front.specs.values():
            # auto (default): reliable when every publisher offers reliable, else best effort
            reliability, depth = self._input_qos[spec.name]
            self.sensor_subscriptions[spec.name] = AdaptiveSubscription(
                self, message_class(spec.msgtype), spec.topic, partial(self._on_input, spec.name),
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

