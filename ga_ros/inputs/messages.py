"""Standard ROS messages -> input samples and external constraints (ROS-free, duck-typed).

The decoders read attributes only (``msg.header.stamp.sec``, ``msg.pose.pose.position.x``,
...), so the same code takes rclpy messages (live node) and rosbags messages (replay).

Input types (:data:`INPUT_TYPES`)
    ``nav_msgs/msg/Odometry``: pose, pose covariance and twist covariance;
    ``geometry_msgs/msg/PoseWithCovarianceStamped``: pose and pose covariance;
    ``geometry_msgs/msg/PoseStamped``: pose only (the default covariance is used).

External constraint encoding (``nav_msgs/msg/Odometry`` on ``ga/constraints``)
    A relative pose ``T_a_b`` (the pose of ``b`` in the frame of ``a``) with its covariance
    (right perturbation ``T_a_b exp(xi)``, ``[x y z rx ry rz]``, m^2 / rad^2; zeros or ``-1``
    in the first element: unknown, the input's default is used):

    * ``header.frame_id`` = ``'stamp/<ns>'`` and ``child_frame_id`` = ``'stamp/<ns>'``: between
      the robot base at two times (integer nanoseconds), e.g. a loop closure found by place
      recognition; each stamp is mapped onto the nearest keyframe of the odometry input;
    * ``header.frame_id`` = ``'node/<id>'`` and ``child_frame_id`` = ``'node/<id>'``: between
      two keyframes (node ids as published on the corrected path);
    * ``pose.pose`` = ``T_a_b``, ``pose.covariance`` = its covariance; ``header.stamp`` and the
      twist are not read.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.encoding import pose_to_matrix, stamp_to_ns
from ga_ros.errors import InputError

ODOMETRY = 'nav_msgs/msg/Odometry'
POSE_COV = 'geometry_msgs/msg/PoseWithCovarianceStamped'
POSE = 'geometry_msgs/msg/PoseStamped'
#: Message types an odometry / pose input accepts.
INPUT_TYPES = (ODOMETRY, POSE_COV, POSE)
#: Short names accepted in parameters and on the command line.
TYPE_ALIASES = {'odometry': ODOMETRY, 'odom': ODOMETRY, 'pose_with_covariance': POSE_COV,
                'pose_cov': POSE_COV, 'pose': POSE, 'nav_msgs/Odometry': ODOMETRY,
                'geometry_msgs/PoseWithCovarianceStamped': POSE_COV,
                'geometry_msgs/PoseStamped': POSE}

_END = re.compile(r'^(stamp|node)/(\d{1,19})$')


def input_type(name: str) -> str:
    """The full message type of an input type name (full name or alias, see the module doc).

    Raises
    ------
    InputError
        An unknown type.
    """
    return resolve_type(name, INPUT_TYPES, TYPE_ALIASES, 'input')


def resolve_type(name: str, types, aliases: dict[str, str], what: str) -> str:
    """The full message type that ``name`` (a full name or an alias of ``aliases``) names among
    ``types``; ``what`` names the kind of input in the error.

    Raises
    ------
    InputError
        An unknown type.
    """
    full = aliases.get(name, name)
    if full not in types:
        raise InputError(f'unknown {what} type {name!r}; use one of {types} '
                         f'or {sorted(aliases)}')
    return full


@dataclass(frozen=True)
class PoseSample:
    """One decoded odometry / pose message.

    Attributes
    ----------
    stamp_ns : ``header.stamp`` (ns).
    frame_id : ``header.frame_id`` (the odometry frame, e.g. ``odom``).
    child_frame_id : ``child_frame_id`` of an Odometry (the base frame), else ''.
    T_odom_base : (4, 4) pose of the base in ``frame_id``.
    pose_cov : (6, 6) pose covariance ``[x y z rx ry rz]`` as sent (None for PoseStamped).
    twist_cov : (6, 6) twist covariance as sent (Odometry only, else None).
    """

    stamp_ns: int
    frame_id: str
    child_frame_id: str
    T_odom_base: FloatArray
    pose_cov: FloatArray | None
    twist_cov: FloatArray | None


def decode_sample(msg: Any, msgtype: str) -> PoseSample:
    """Decode an Odometry, PoseWithCovarianceStamped or PoseStamped message.

    Parameters
    ----------
    msg : rclpy or rosbags message.
    msgtype : its full type name (one of :data:`INPUT_TYPES`).

    Raises
    ------
    InputError
        NaN/inf in the pose, a non-unit quaternion or an unsupported type.
    """
    msgtype = input_type(msgtype)
    stamp = stamp_to_ns(msg.header.stamp)
    frame = str(msg.header.frame_id)
    if msgtype == POSE:
        return PoseSample(stamp, frame, '', pose_to_matrix(msg.pose), None, None)
    T = pose_to_matrix(msg.pose.pose)
    pose_cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
    if msgtype == POSE_COV:
        return PoseSample(stamp, frame, '', T, pose_cov, None)
    twist_cov = np.asarray(msg.twist.covariance, dtype=float).reshape(6, 6)
    return PoseSample(stamp, frame, str(msg.child_frame_id), T, pose_cov, twist_cov)


@dataclass(frozen=True)
class Constraint:
    """A decoded external constraint (see the module doc).

    Attributes
    ----------
    by : ``'stamp'`` or ``'node'``.
    a, b : the two ends: stamps (ns) or node ids.
    T_a_b : (4, 4) pose of ``b`` in the frame of ``a``.
    cov : (6, 6) covariance as sent (may be unusable: the input then uses its default).
    """

    by: str
    a: int
    b: int
    T_a_b: FloatArray
    cov: FloatArray


def decode_constraint(msg: Any) -> Constraint:
    """Decode an external constraint (``nav_msgs/Odometry``, encoding in the module doc).

    Raises
    ------
    InputError
        Frame ids not ``stamp/<ns>`` or ``node/<id>``, the two ends of different kinds, or a
        malformed pose.
    """
    ends = [_END.match(str(f).lstrip('/')) for f in (msg.header.frame_id, msg.child_frame_id)]
    if ends[0] is None or ends[1] is None or ends[0].group(1) != ends[1].group(1):
        raise InputError(
            f'constraint frame ids {msg.header.frame_id!r} -> {msg.child_frame_id!r}: use '
            "'stamp/<ns>' -> 'stamp/<ns>' or 'node/<id>' -> 'node/<id>'")
    T = pose_to_matrix(msg.pose.pose)
    cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6)
    return Constraint(ends[0].group(1), int(ends[0].group(2)), int(ends[1].group(2)), T, cov)


def constraint_frames(by: str, a: int, b: int) -> tuple[str, str]:
    """``(header.frame_id, child_frame_id)`` of a constraint between stamps or node ids."""
    if by not in ('stamp', 'node'):
        raise InputError(f"constraint ends must be 'stamp' or 'node', got {by!r}")
    return f'{by}/{int(a)}', f'{by}/{int(b)}'
