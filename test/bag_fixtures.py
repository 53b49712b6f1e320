"""Bags shaped like other people's data, written with rosbags inside the tests.

Small builders of rosbags message objects (odometry, poses, ``NavSatFix``, images, ROS 1
messages), writers of whole bags from ``(log time, topic, type, message)`` rows, and the ground
truth most replay tests drive: a 20 x 10 m rectangle and odometry that drifts off it.

Conventions: stamps and log times are integer nanoseconds (a header stamp is the sensor's time,
a log time the recorder's clock); poses are 4x4 ``T_frame_child`` (``T_odom_base`` for odometry);
covariances are 6x6 in ROS order ``[x y z rx ry rz]`` (m^2, rad^2), or flat ``(36,)`` arrays.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.encoding import network_index
from ga_ros.geometry import se3
from ga_ros.inputs.absolute import NAVSAT as NAV_SAT_FIX
from ga_ros.io.bag_messages import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    ODOMETRY,
    POSE_STAMPED,
    header,
    matrix_to_pose_msg,
    typestore,
)
from ga_ros.io.bag_messages import POSE_WITH_COVARIANCE as POSE_COV_STAMPED
from ga_ros.io.bag_writer import (
    LINE_WIDTH,
    NAMESPACE,
    NODE_SCALE,
    BagWriter,
    residual_color,
    tf_message,
    transform_msg,
)
from ga_ros.replay import samples

#: A row of a bag: log time (ns), topic, message type, rosbags message.
Row = tuple[int, str, str, Any]

TF = 'tf2_msgs/msg/TFMessage'
#: The sample bags' stereo topics (:mod:`ga_ros.replay.samples`): left info, right info, left
#: image, right image, in the order of :func:`stereo_rows`.
SAMPLE_STEREO_TOPICS = (samples.LEFT_INFO_TOPIC, samples.RIGHT_INFO_TOPIC,
                        samples.LEFT_IMAGE_TOPIC, samples.RIGHT_IMAGE_TOPIC)
#: Seconds of one lap of :func:`rectangle`.
RECTANGLE_LAP_S = 60.0


# --------------------------------------------------------------------------- trajectories
def rectangle(t_s: FloatArray) -> FloatArray:
    """``(n, 4, 4)`` poses ``T_world_base`` at ``t_s`` (s since start): a 20 x 10 m rectangle
    driven at 1 m/s counter-clockwise from the origin, heading along the motion (positions
    piecewise linear in time, one lap every :data:`RECTANGLE_LAP_S`)."""
    d = np.mod(np.asarray(t_s, dtype=float), RECTANGLE_LAP_S)
    out = np.empty((len(d), 4, 4))
    for k, s in enumerate(d):
        if s < 20:
            x, y, yaw = s, 0.0, 0.0
        elif s < 30:
            x, y, yaw = 20.0, s - 20, np.pi / 2
        elif s < 50:
            x, y, yaw = 20 - (s - 30), 10.0, np.pi
        else:
            x, y, yaw = 0.0, 10 - (s - 50), -np.pi / 2
        out[k] = se3.from_translation_rotvec(np.array([x, y, 0.0]), np.array([0, 0, yaw]))
    return out


def drifting_odometry(T_true: FloatArray, yaw_per_step: float) -> FloatArray:
    """``(n, 4, 4)`` odometry poses from the true first pose: the true increments, each followed
    by a constant heading error ``yaw_per_step`` (rad) about z."""
    odom = [T_true[0].copy()]
    err = se3.from_translation_rotvec(np.zeros(3), np.array([0, 0, yaw_per_step]))
    for k in range(1, len(T_true)):
        odom.append(odom[-1] @ se3.relative(T_true[k - 1], T_true[k]) @ err)
    return np.array(odom)


class Drive(NamedTuple):
    """A drive around :func:`rectangle`: stamps (ns), true poses and drifting odometry poses."""

    stamps_ns: np.ndarray
    T_true: FloatArray
    T_odom: FloatArray


def rectangle_drive(laps: float, rate_hz: float, t0_ns: int,
                    yaw_per_step: float = 5e-4) -> Drive:
    """``laps`` laps of :func:`rectangle` sampled at ``rate_hz`` from ``t0_ns``, with the
    odometry of :func:`drifting_odometry`."""
    t = np.arange(0.0, laps * RECTANGLE_LAP_S, 1.0 / rate_hz)
    T_true = rectangle(t)
    return Drive(t0_ns + np.round(t * 1e9).astype(np.int64), T_true,
                 drifting_odometry(T_true, yaw_per_step))


# --------------------------------------------------------------------------- ROS 2 messages
def pose_with_covariance(T: FloatArray, cov: FloatArray | None = None) -> Any:
    """``geometry_msgs/PoseWithCovariance`` of a pose and a 6x6 (or flat) covariance (default
    all zeros: unknown)."""
    c = np.zeros(36) if cov is None else np.asarray(cov, dtype=float).reshape(36).copy()
    return typestore().types['geometry_msgs/msg/PoseWithCovariance'](
        pose=matrix_to_pose_msg(T), covariance=c)


def odometry_msg(T: FloatArray, stamp_ns: int, *, frame: str = 'odom', child: str = 'base_link',
                 pose_cov: FloatArray | None = None, twist_cov: FloatArray | None = None,
                 linear_x: float = 0.0) -> Any:
    """``nav_msgs/Odometry`` as a robot driver publishes it: pose ``T_frame_child``, its
    covariance, a twist of ``linear_x`` m/s forward and the twist covariance (both default all
    zeros, as Nav2's odometry)."""
    types = typestore().types
    vec = types['geometry_msgs/msg/Vector3']
    tc = np.zeros(36) if twist_cov is None else np.asarray(twist_cov, float).reshape(36).copy()
    return types[ODOMETRY](
        header=header(frame, int(stamp_ns)), child_frame_id=child,
        pose=pose_with_covariance(T, pose_cov),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](
            twist=types['geometry_msgs/msg/Twist'](linear=vec(x=linear_x, y=0.0, z=0.0),
                                                   angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=tc))


def pose_stamped_msg(T: FloatArray, stamp_ns: int, frame: str = 'odom') -> Any:
    """``geometry_msgs/PoseStamped`` of ``T_frame_base``."""
    return typestore().types[POSE_STAMPED](header=header(frame, int(stamp_ns)),
                                           pose=matrix_to_pose_msg(T))


def pose_cov_stamped_msg(T: FloatArray, stamp_ns: int, cov: FloatArray,
                         frame: str = 'odom') -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped`` (what AMCL publishes) of ``T_frame_base``."""
    return typestore().types[POSE_COV_STAMPED](header=header(frame, int(stamp_ns)),
                                               pose=pose_with_covariance(T, cov))


def nav_sat_fix_msg(lla: Sequence[float], stamp_ns: int, position_cov: FloatArray | None,
                    frame: str = 'gps', status: int = 0) -> Any:
    """``sensor_msgs/NavSatFix`` at latitude, longitude (deg) and altitude (m) with a 3x3 ENU
    position covariance (m^2; type DIAGONAL_KNOWN), or without one (``None``: zeros, type
    UNKNOWN); ``status`` -1 is "no fix"."""
    types = typestore().types
    cov = np.zeros(9) if position_cov is None else np.asarray(position_cov, float).reshape(9)
    return types[NAV_SAT_FIX](
        header=header(frame, int(stamp_ns)),
        status=types['sensor_msgs/msg/NavSatStatus'](status=status, service=1),
        latitude=float(lla[0]), longitude=float(lla[1]), altitude=float(lla[2]),
        position_covariance=cov, position_covariance_type=0 if position_cov is None else 2)


def mono8_image_msg(img: np.ndarray, frame: str, stamp_ns: int) -> Any:
    """Raw ``sensor_msgs/Image`` (``mono8``) of a ``uint8`` image, as a camera driver records
    it."""
    return typestore().types['sensor_msgs/msg/Image'](
        header=header(frame, int(stamp_ns)), height=img.shape[0], width=img.shape[1],
        encoding='mono8', is_bigendian=0, step=img.shape[1],
        data=np.ascontiguousarray(img).reshape(-1))


def stereo_rows(rig: Any, left: np.ndarray, right: np.ndarray, stamp_ns: int, *,
                topics: Sequence[str], frames: Sequence[str] = ('left', 'right'),
                log_ns: int | None = None, quality: int | None = None) -> list[Row]:
    """The four messages of one stereo pair: left and right ``CameraInfo`` (the right one with
    ``Tx = -f b``) then left and right JPEG ``CompressedImage``.

    Parameters
    ----------
    rig : a :class:`ga_ros.sim.stereo.StereoRig` (intrinsics, size, baseline).
    topics : left info, right info, left image, right image topic names.
    frames : the left and right camera frame ids.
    log_ns : the recorder's time (default: the stamp).
    quality : JPEG quality (default: the sample bags').
    """
    s = int(stamp_ns)
    log = s if log_ns is None else int(log_ns)
    jpeg = {} if quality is None else {'quality': quality}
    info = [samples.camera_info_msg(rig.K, rig.width, rig.height, frames[0], s),
            samples.camera_info_msg(rig.K, rig.width, rig.height, frames[1], s,
                                    -rig.focal_px * rig.baseline_m)]
    images = [samples.compressed_image_msg(left, frames[0], s, **jpeg),
              samples.compressed_image_msg(right, frames[1], s, **jpeg)]
    return [(log, topics[0], CAMERA_INFO, info[0]), (log, topics[1], CAMERA_INFO, info[1]),
            (log, topics[2], COMPRESSED_IMAGE, images[0]),
            (log, topics[3], COMPRESSED_IMAGE, images[1])]


# --------------------------------------------------------------------------- writing bags
def write_tf_static(bag: BagWriter, transforms: Iterable[tuple[str, str, FloatArray]],
                    stamp_ns: int, log_ns: int | None = None) -> None:
    """One ``/tf_static`` message of ``(parent, child, T_parent_child)`` transforms, as
    robot_state_publisher latches it."""
    msgs = [transform_msg(p, c, T, int(stamp_ns)) for p, c, T in transforms]
    bag.write('/tf_static', TF, tf_message(msgs), int(stamp_ns if log_ns is None else log_ns))


def write_tf(bag: BagWriter, parent: str, child: str, T: FloatArray, stamp_ns: int,
             log_ns: int | None = None) -> None:
    """One ``/tf`` message with the transform ``T_parent_child``."""
    bag.write('/tf', TF, tf_message([transform_msg(parent, child, T, int(stamp_ns))]),
              int(stamp_ns if log_ns is None else log_ns))


def write_rows(bag: BagWriter, rows: Iterable[Row]) -> None:
    """Write ``(log time, topic, type, message)`` rows in log-time order (stable: rows of one
    time keep their order)."""
    for log_ns, topic, msgtype, msg in sorted(rows, key=lambda r: r[0]):
        bag.write(topic, msgtype, msg, int(log_ns))


def write_bag(path: Path, rows: Iterable[Row]) -> Path:
    """An mcap rosbag2 bag at ``path`` of the rows (:func:`write_rows`)."""
    with BagWriter(path) as bag:
        write_rows(bag, rows)
    return path


def write_unknown_type_bag(path: Path) -> Path:
    """A bag with one message of a type outside the standard set (``my_pkg/msg/Thing``)."""
    from rosbags.rosbag2 import StoragePlugin, Writer

    w = Writer(path, version=9, storage_plugin=StoragePlugin.MCAP)
    w.open()
    c = w.add_connection('/custom', 'my_pkg/msg/Thing', msgdef='int32 a',
                         rihs01='RIHS01_' + '0' * 64)
    w.write(c, 5, b'\x00\x01\x00\x00\x07\x00\x00\x00')
    w.close()
    return path


# --------------------------------------------------------------------------- ROS 1
@functools.lru_cache(maxsize=1)
def ros1_typestore() -> Any:
    """The rosbags type store of ROS 1 Noetic (messages with ``header.seq``)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS1_NOETIC)


def _ros1_header(frame: str, stamp_ns: int) -> Any:
    types = ros1_typestore().types
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    return types['std_msgs/msg/Header'](
        seq=0, stamp=types['builtin_interfaces/msg/Time'](sec=sec, nanosec=nsec), frame_id=frame)


def _ros1_pose(T: FloatArray) -> Any:
    types = ros1_typestore().types
    p, q = se3.to_pos_quat(T)
    return types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
        orientation=types['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3]))


def ros1_pose_stamped_msg(T: FloatArray, stamp_ns: int, frame: str = 'map') -> Any:
    """ROS 1 ``geometry_msgs/PoseStamped`` of ``T_frame_base``."""
    return ros1_typestore().types[POSE_STAMPED](header=_ros1_header(frame, stamp_ns),
                                                pose=_ros1_pose(T))


def ros1_odometry_msg(T: FloatArray, stamp_ns: int, frame: str = 'odom',
                      child: str = 'base_link') -> Any:
    """ROS 1 ``nav_msgs/Odometry`` of ``T_frame_child`` with all-zero covariances and twist."""
    types = ros1_typestore().types
    vec = types['geometry_msgs/msg/Vector3']
    return types[ODOMETRY](
        header=_ros1_header(frame, stamp_ns), child_frame_id=child,
        pose=types['geometry_msgs/msg/PoseWithCovariance'](pose=_ros1_pose(T),
                                                           covariance=np.zeros(36)),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](
            twist=types['geometry_msgs/msg/Twist'](linear=vec(x=0.0, y=0.0, z=0.0),
                                                   angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=np.zeros(36)))


def write_ros1_bag(path: Path, rows: Iterable[Row]) -> Path:
    """A ROS 1 ``.bag`` of ROS 1 message rows, in log-time order (connections in order of first
    appearance)."""
    from rosbags.rosbag1 import Writer

    store = ros1_typestore()
    with Writer(path) as w:
        conns: dict[str, Any] = {}
        for log_ns, topic, msgtype, msg in sorted(rows, key=lambda r: r[0]):
            if topic not in conns:
                conns[topic] = w.add_connection(topic, msgtype, typestore=store)
            w.write(conns[topic], int(log_ns), store.serialize_ros1(msg, msgtype))
    return path


def reference_network_markers(p_world_node: FloatArray, src_index: IntArray, dst_index: IntArray,
                    normalized_residual: FloatArray, frame_id: str, stamp_ns: int,
                    node_scale: float = NODE_SCALE, line_width: float = LINE_WIDTH,
                    residual_scale: float = 3.0, namespace: str = NAMESPACE) -> Any:
    """The connection network as a rosbags ``visualization_msgs/MarkerArray``, built message
    object by message object: the reference that :func:`ga_ros.io.cdr.network_markers_cdr`
    (what the replay writes) must serialize to the same bytes as.

    Same layout as the alignment node's markers: a ``DELETEALL`` marker, a ``SPHERE_LIST`` of
    nodes (id 0) and a ``LINE_LIST`` of connections (id 1) coloured by
    :func:`ga_ros.io.bag_writer.residual_color` of their Mahalanobis misclosure.

    Parameters
    ----------
    p_world_node : (n, 3) node positions in ``frame_id`` (m).
    src_index, dst_index : (m,) node indices of the connections' ends.
    normalized_residual : (m,) Mahalanobis norm of each connection's misclosure (unitless).
    node_scale, line_width : marker sizes (m).
    """
    types = typestore().types
    Marker = types['visualization_msgs/msg/Marker']
    Point = types['geometry_msgs/msg/Point']
    Color = types['std_msgs/msg/ColorRGBA']
    net = network_index(p_world_node, src_index, dst_index)
    p, src, dst = net.p, net.src, net.dst

    def marker(kind: int, action: int, mid: int, ns: str, scale: float, points: list[Any],
               color: Any, colors: list[Any]) -> Any:
        return Marker(
            header=header(frame_id, stamp_ns), ns=ns, id=mid, type=kind, action=action,
            pose=matrix_to_pose_msg(np.eye(4)),
            scale=types['geometry_msgs/msg/Vector3'](x=scale, y=scale, z=scale),
            color=color, lifetime=types['builtin_interfaces/msg/Duration'](sec=0, nanosec=0),
            frame_locked=False, points=points, colors=colors, texture_resource='',
            texture=types['sensor_msgs/msg/CompressedImage'](
                header=header('', 0), format='', data=np.zeros(0, dtype=np.uint8)),
            uv_coordinates=[], text='', mesh_resource='',
            mesh_file=types['visualization_msgs/msg/MeshFile'](
                filename='', data=np.zeros(0, dtype=np.uint8)),
            mesh_use_embedded_materials=False)

    white = Color(r=1.0, g=1.0, b=1.0, a=1.0)
    clear = marker(Marker.ARROW, Marker.DELETEALL, 0, namespace, 1.0, [], white, [])
    nodes = marker(Marker.SPHERE_LIST, Marker.ADD, 0, namespace + '/nodes', float(node_scale),
                   [Point(x=x, y=y, z=z) for x, y, z in p.tolist()],
                   Color(r=0.2, g=0.4, b=1.0, a=1.0), [])
    ends = np.empty((2 * src.size, 3))
    ends[0::2] = p[src]
    ends[1::2] = p[dst]
    rgba = np.repeat(residual_color(normalized_residual, residual_scale), 2, axis=0)
    lines = marker(Marker.LINE_LIST, Marker.ADD, 1, namespace + '/connections', float(line_width),
                   [Point(x=x, y=y, z=z) for x, y, z in ends.tolist()], white,
                   [Color(r=r, g=g, b=b, a=a) for r, g, b, a in rgba.tolist()])
    return types['visualization_msgs/msg/MarkerArray'](markers=[clear, nodes, lines])
