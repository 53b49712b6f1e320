"""QoS profiles of the ga_ros topics."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy


def latched_qos(depth: int = 1) -> QoSProfile:
    """Reliable, transient-local: a late subscriber gets the last ``depth`` messages at once
    (used for the corrected path and the network markers)."""
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      durability=DurabilityPolicy.TRANSIENT_LOCAL,
                      reliability=ReliabilityPolicy.RELIABLE)


def measurement_qos(depth: int = 100000, transient_local: bool = False) -> QoSProfile:
    """Reliable, deep queue: bursts of measurements during a window update are queued rather
    than dropped (publishers should use the same profile). Volatile by default;
    ``transient_local``: a restarted subscriber gets the publisher's history again."""
    durability = (DurabilityPolicy.TRANSIENT_LOCAL if transient_local
                  else DurabilityPolicy.VOLATILE)
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST, durability=durability,
                      reliability=ReliabilityPolicy.RELIABLE)


def stream_qos(depth: int = 10) -> QoSProfile:
    """Reliable, volatile, shallow: the pose / odometry / diagnostics streams."""
    return QoSProfile(depth=depth, history=HistoryPolicy.KEEP_LAST,
                      durability=DurabilityPolicy.VOLATILE,
                      reliability=ReliabilityPolicy.RELIABLE)
