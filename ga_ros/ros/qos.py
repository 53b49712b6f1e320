"""QoS profiles of the ga_ros topics."""

from __future__ import annotations

from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy

from ga_ros.errors import InputError


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


#: ``qos_reliability``: adapt to the publishers' offered QoS (:mod:`ga_ros.ros.adaptive_qos`).
AUTO = 'auto'
#: Accepted values of the ``qos_reliability`` parameters (``auto`` first: the default).
RELIABILITIES = (AUTO, 'best_effort', 'reliable')


def sensor_qos(reliability: str = 'best_effort', depth: int = 10) -> QoSProfile:
    """Subscription QoS of a sensor input (images, camera info, odometry): keep last ``depth``,
    volatile; ``best_effort`` (the ROS sensor-data convention) connects to best-effort and
    reliable publishers alike, ``reliable`` only to reliable ones (then nothing is lost in
    transport while the queue keeps up). ``auto`` is resolved to one of the two by
    :class:`ga_ros.ros.adaptive_qos.AdaptiveSubscription`; here it gives best effort.

    Raises
    ------
    InputError
        ``reliability`` is not one of :data:`RELIABILITIES` or ``depth`` < 1.
    """
    if reliability not in RELIABILITIES:
        raise InputError(f'qos_reliability must be one of {RELIABILITIES}, got {reliability!r}')
    if depth < 1:
        raise InputError(f'QoS depth must be at least 1, got {depth}')
    return QoSProfile(depth=int(depth), history=HistoryPolicy.KEEP_LAST,
                      durability=DurabilityPolicy.VOLATILE,
                      reliability=(ReliabilityPolicy.BEST_EFFORT if reliability == 'best_effort'
                                   else ReliabilityPolicy.RELIABLE))


def tf_static_qos() -> QoSProfile:
    """``/tf_static``'s QoS (reliable, transient local, depth 1 as tf2's static listener)."""
    return latched_qos(1)
