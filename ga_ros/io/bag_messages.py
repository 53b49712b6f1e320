"""Bag messages as rosbags objects: the type store, the message type names, and conversions
between messages and core types (stamps, poses, measurements, paths) done once, at this edge.

ROS-free (:mod:`rosbags`, never ``rclpy``); the decoders share the rules of the live node
(:mod:`ga_ros.core.encoding`).
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core import encoding
from ga_ros.core.frames import parse_node_frame
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.io.trajectory import Trajectory

#: Message types used by the replay (ROS 2 names).
ODOMETRY = 'nav_msgs/msg/Odometry'
PATH = 'nav_msgs/msg/Path'
IMAGE = 'sensor_msgs/msg/Image'
COMPRESSED_IMAGE = 'sensor_msgs/msg/CompressedImage'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
POSE_WITH_COVARIANCE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
#: Message types a ground-truth topic may have (:mod:`ga_ros.io.groundtruth` reads them).
GROUND_TRUTH_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE, ODOMETRY, PATH)
TF_TOPICS = ('/tf', '/tf_static')

#: ``twist.twist.linear.x`` values of the two measurement kinds.
KIND_FLAG = encoding.KIND_FLAG


@functools.lru_cache(maxsize=1)
def typestore() -> Any:
    """The rosbags type store of ROS 2 Jazzy (standard messages; built once, read-only)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


# --------------------------------------------------------------------------- stamps
def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (rosbags object) -> integer nanoseconds."""
    return encoding.stamp_to_ns(stamp)


def ns_to_stamp(stamp_ns: int) -> Any:
    """Integer nanoseconds (>= 0) -> ``builtin_interfaces/Time`` (rosbags object)."""
    t = encoding.split_stamp(stamp_ns)
    return typestore().types['builtin_interfaces/msg/Time'](sec=t.sec, nanosec=t.nanosec)


# --------------------------------------------------------------------------- poses
def pose_msg_to_matrix(pose: Any) -> FloatArray:
    """``geometry_msgs/Pose`` (rosbags) -> 4x4; InputError on NaN or a non-unit quaternion
    (:func:`ga_ros.core.encoding.pose_to_matrix`)."""
    return encoding.pose_to_matrix(pose)


def matrix_to_pose_msg(T: FloatArray) -> Any:
    """4x4 pose -> ``geometry_msgs/Pose`` (rosbags object)."""
    p, q = se3.to_pos_quat(np.asarray(T, dtype=float))
    return pose_msg(p.tolist(), q.tolist())


def pose_msg(p: list[float], q: list[float]) -> Any:
    types = typestore().types
    return types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
        orientation=types['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3]))


# --------------------------------------------------------------------------- measurements
def odometry_to_measurement(msg: Any) -> Measurement:
    """Decode a rosbags ``nav_msgs/Odometry`` in the measurement encoding, with exactly the
    rules of the alignment node (:func:`ga_ros.core.encoding.decode_measurement`)."""
    return encoding.decode_measurement(msg)


def measurement_to_odometry(m: Measurement) -> Any:
    """Encode a :class:`Measurement` as a rosbags ``nav_msgs/Odometry`` (the fixed encoding)."""
    from ga_ros.core.frames import node_frame

    if m.kind not in KIND_FLAG:
        raise InputError(f"measurement kind must be 'consecutive' or 'cross', got {m.kind!r}")
    types = typestore().types
    cov = np.asarray(m.cov, dtype=float)
    if cov.shape != (6, 6):
        raise InputError(f'covariance must be 6x6, got {cov.shape}')
    vec = types['geometry_msgs/msg/Vector3']
    return types[ODOMETRY](
        header=header(node_frame(m.src_track, m.src_id), m.stamp_ns),
        child_frame_id=node_frame(m.dst_track, m.dst_id),
        pose=types['geometry_msgs/msg/PoseWithCovariance'](
            pose=matrix_to_pose_msg(m.T_src_dst), covariance=cov.reshape(36).copy()),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](
            twist=types['geometry_msgs/msg/Twist'](
                linear=vec(x=KIND_FLAG[m.kind], y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=np.array(encoding.source_to_values(m.source))))


def header(frame_id: str, stamp_ns: int) -> Any:
    """``std_msgs/Header`` (rosbags object)."""
    return typestore().types['std_msgs/msg/Header'](stamp=ns_to_stamp(stamp_ns),
                                                    frame_id=str(frame_id))


# --------------------------------------------------------------------------- paths, ground truth
def path_msg_to_trajectory(msg: Any) -> Trajectory:
    """rosbags ``nav_msgs/Path`` -> :class:`Trajectory` (node ids from node frame ids, if any)."""
    n = len(msg.poses)
    stamps = np.empty(n, dtype=np.int64)
    nodes = np.full(n, -1, dtype=np.int64)
    tracks = np.full(n, -1, dtype=np.int64)
    T = np.empty((n, 4, 4))
    for k, ps in enumerate(msg.poses):
        stamps[k] = stamp_to_ns(ps.header.stamp)
        T[k] = pose_msg_to_matrix(ps.pose)
        try:
            tracks[k], nodes[k] = parse_node_frame(ps.header.frame_id)
        except InputError:
            pass
    return Trajectory(stamps, T, nodes, tracks, msg.header.frame_id or 'map')


def trajectory_to_path_msg(traj: Trajectory, frame_id: str | None = None,
                           stamp_ns: int | None = None, node_frames: bool = False) -> Any:
    """:class:`Trajectory` -> rosbags ``nav_msgs/Path``.

    Parameters
    ----------
    frame_id : the path's frame (default: ``traj.frame_id``).
    stamp_ns : the path header's stamp (default: the last pose's stamp).
    node_frames : if True, each pose's ``header.frame_id`` is its node frame
        ``'ga/<track>/<node>'`` (the ground-truth convention); else ``frame_id``.
    """
    from ga_ros.core.frames import node_frame

    types = typestore().types
    frame = frame_id or traj.frame_id
    n = len(traj)
    if stamp_ns is None:
        stamp_ns = int(traj.stamps_ns[-1]) if n else 0
    poses = []
    if n:
        p_all, q_all = se3.to_pos_quat(np.asarray(traj.T_world_node, float).reshape(-1, 4, 4))
        p_all, q_all = p_all.tolist(), q_all.tolist()
    PoseStamped = types['geometry_msgs/msg/PoseStamped']
    for k in range(n):
        f = node_frame(int(traj.track_ids[k]), int(traj.node_ids[k])) if node_frames else frame
        poses.append(PoseStamped(header=header(f, int(traj.stamps_ns[k])),
                                 pose=pose_msg(p_all[k], q_all[k])))
    return types[PATH](header=header(frame, stamp_ns), poses=poses)
