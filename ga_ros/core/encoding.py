"""Decoding the ROS measurement encoding, for any message object with the ROS field names.

The encoding (README, "The measurement encoding") is a ``nav_msgs/Odometry`` per connection.
rclpy messages (the nodes, :mod:`ga_ros.ros.conversions`) and rosbags messages (the ROS-free
replay, :mod:`ga_ros.io.bag_messages`) have the same field names, so both decode here and cannot
drift apart. Nothing here imports ROS.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.frames import parse_node_frame
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3

#: ``twist.twist.linear.x`` values of the two measurement kinds.
KIND_FLAG = {'consecutive': 0.0, 'cross': 1.0}
#: Largest accepted deviation of a quaternion's norm from 1 (it is then normalised).
QUAT_NORM_TOL = 1e-3
#: ``twist.covariance`` carries the measurement's source (``Measurement.source``): its UTF-8
#: bytes, one per element (value 0-255), zero-padded; all zero: no source. At most this many
#: bytes.
SOURCE_BYTES = 36


def source_to_values(source: str) -> list[float]:
    """The 36 ``twist.covariance`` values carrying ``source`` (see :data:`SOURCE_BYTES`).

    Raises
    ------
    InputError
        The name is longer than :data:`SOURCE_BYTES` bytes in UTF-8 (use a shorter input name).
    """
    raw = str(source).encode('utf-8')
    if len(raw) > SOURCE_BYTES:
        raise InputError(f'source name {source!r} is longer than {SOURCE_BYTES} bytes in '
                         'UTF-8: use a shorter input name')
    return [float(b) for b in raw] + [0.0] * (SOURCE_BYTES - len(raw))


def source_from_values(values: Sequence[float]) -> str:
    """The source carried by ``twist.covariance`` (:func:`source_to_values`); '' when the
    values are all zero or are not byte values (a publisher that fills the twist's covariance
    with something else: the source is then unknown, the measurement is kept)."""
    v = np.asarray(values, dtype=float).reshape(-1)
    if v.size != SOURCE_BYTES or not np.isfinite(v).all() or not v.any():
        return ''
    if (v < 0).any() or (v > 255).any() or (v != np.round(v)).any():
        return ''
    raw = bytes(int(b) for b in v).rstrip(b'\0')
    if b'\0' in raw:
        return ''
    return raw.decode('utf-8', 'replace')


def rejected(reason: str, text: str) -> InputError:
    """An :class:`InputError` with a short ``reason`` key (the keys counted by the node's
    diagnostics and by :class:`ga_ros.core.window.TrackWindowAligner`)."""
    return InputError(text, reason=reason)


@dataclass(frozen=True)
class StampParts:
    """A stamp split as ``builtin_interfaces/Time`` stores it: ``sec`` and ``nanosec``."""

    sec: int
    nanosec: int


def split_stamp(stamp_ns: int) -> StampParts:
    """Integer nanoseconds (>= 0) -> ``sec``, ``nanosec``; InputError if negative."""
    stamp_ns = int(stamp_ns)
    if stamp_ns < 0:
        raise InputError(f'stamp must be >= 0 ns, got {stamp_ns}', reason='bad_stamp')
    sec, nanosec = divmod(stamp_ns, 1_000_000_000)
    return StampParts(int(sec), int(nanosec))


@dataclass(frozen=True)
class NetworkIndex:
    """Checked inputs of the network markers: node positions ``p`` (n, 3), m, and the
    connections' end indices ``src``, ``dst`` (m,)."""

    p: FloatArray
    src: IntArray
    dst: IntArray


def network_index(p_world_node: FloatArray, src_index: IntArray,
                  dst_index: IntArray) -> NetworkIndex:
    """Validate the inputs of a network marker message (InputError on mismatched lengths or
    an index out of range)."""
    p = np.asarray(p_world_node, dtype=float).reshape(-1, 3)
    src = np.asarray(src_index, dtype=np.int64).reshape(-1)
    dst = np.asarray(dst_index, dtype=np.int64).reshape(-1)
    if src.shape != dst.shape:
        raise InputError('src_index and dst_index must have the same length')
    if src.size and (min(src.min(), dst.min()) < 0 or max(src.max(), dst.max()) >= p.shape[0]):
        raise InputError('connection index out of range')
    return NetworkIndex(p, src, dst)


def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (fields ``sec``, ``nanosec``) -> integer nanoseconds."""
    return int(stamp.sec) * 1_000_000_000 + int(stamp.nanosec)


def covariance_from_values(values: Sequence[float]) -> FloatArray:
    """36 row-major values -> 6x6 covariance; InputError unless finite, symmetric (to 1e-6
    relative) and positive definite (smallest eigenvalue above 1e-12 of the largest entry, the
    rule of :func:`ga_ros.core.network.check_covariances`)."""
    cov = np.asarray(values, dtype=float).reshape(6, 6)
    if not np.isfinite(cov).all():
        raise InputError('covariance has NaN or inf entries')
    scale = max(float(np.abs(cov).max()), 1e-300)
    if float(np.abs(0.5 * cov - 0.5 * cov.T).max()) > 0.5e-6 * scale:  # no overflow at 1e308
        raise InputError('covariance is not symmetric')
    cov = 0.5 * cov + 0.5 * cov.T
    try:
        smallest = float(np.linalg.eigvalsh(cov / scale)[0])
    except np.linalg.LinAlgError:
        smallest = -1.0
    if not smallest > 1e-12:
        raise InputError('covariance is not positive definite')
    return cov


def pose_to_matrix(pose: Any) -> FloatArray:
    """``geometry_msgs/Pose`` -> 4x4; InputError on NaN/inf or a non-unit quaternion."""
    p = np.array([pose.position.x, pose.position.y, pose.position.z], dtype=float)
    o = pose.orientation
    q = np.array([o.x, o.y, o.z, o.w], dtype=float)
    if not (np.isfinite(p).all() and np.isfinite(q).all()):
        raise InputError('pose has NaN or inf entries')
    norm = float(np.sqrt(q @ q))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise InputError(f'quaternion is not unit length (norm {norm:.6g})')
    return se3.from_pos_quat(p, q / norm)


def quat_to_rotvec(x: float, y: float, z: float, w: float) -> list[float]:
    """Unit quaternion ``x y z w`` -> rotation vector (rad), angle in [0, pi]; scalar code, as
    this runs once per received message."""
    if w < 0.0:
        x, y, z, w = -x, -y, -z, -w
    s = math.sqrt(x * x + y * y + z * z)
    if s < 1e-8:
        k = 2.0 / w  # angle = 2 atan2(s, w) ~ 2 s / w: rotvec ~ 2 v / w (error O(s^3))
    else:
        k = 2.0 * math.atan2(s, w) / s
    return [k * x, k * y, k * z]


def decode_measurement(msg: Any) -> Measurement:
    """Decode a ``nav_msgs/Odometry`` of the measurement encoding into a :class:`Measurement`.

    Raises
    ------
    InputError
        On malformed frame ids, a self-loop, NaN/inf in the pose, a non-unit quaternion, a
        covariance that is not symmetric positive definite, or a kind flag other than 0 or 1.
        Its ``reason`` attribute is one of ``'bad_id'``, ``'self_loop'``, ``'bad_kind'``,
        ``'non_finite'``, ``'bad_quaternion'``, ``'bad_covariance'``.
    """
    try:
        src_track, src_id = parse_node_frame(msg.header.frame_id)
        dst_track, dst_id = parse_node_frame(msg.child_frame_id)
    except InputError as exc:
        raise rejected('bad_id', str(exc)) from None
    if src_id == dst_id:
        raise rejected('self_loop', f'self-loop: measurement from node {src_id} to itself')
    flag = float(msg.twist.twist.linear.x)
    if flag == 1.0:
        kind = 'cross'
    elif flag == 0.0:
        kind = 'consecutive'
    else:
        raise rejected('bad_kind', 'twist.linear.x must be 0 (consecutive) or 1 (cross), '
                       f'got {flag!r}')
    p, q = msg.pose.pose.position, msg.pose.pose.orientation
    z = [float(p.x), float(p.y), float(p.z)]
    quat = [float(q.x), float(q.y), float(q.z), float(q.w)]
    if not all(math.isfinite(v) for v in z + quat):
        raise rejected('non_finite', 'pose has NaN or inf entries')
    norm = math.sqrt(sum(v * v for v in quat))
    if abs(norm - 1.0) > QUAT_NORM_TOL:
        raise rejected('bad_quaternion', f'quaternion is not unit length (norm {norm:.6g})')
    z += quat_to_rotvec(*(v / norm for v in quat))
    try:
        cov = covariance_from_values(msg.pose.covariance)
    except InputError as exc:
        raise rejected('bad_covariance', str(exc)) from None
    return Measurement(src_id, dst_id, src_track, dst_track, np.array(z), cov,
                       stamp_to_ns(msg.header.stamp), kind,
                       source_from_values(msg.twist.covariance))
