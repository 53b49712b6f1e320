"""Sensor subscriptions whose reliability adapts to the publishers' offered QoS.

A best-effort subscription connects to every publisher, but on a loaded host it loses a large
part of big messages (raw images) that a reliable publisher would have delivered; a reliable
subscription gets them all but does not connect to a best-effort publisher. As rosbag2's
recorder (``rosbag2_transport/qos.cpp``, ``adapt_request_to_offers``), ``qos_reliability:
auto`` reads the offered QoS of the topic's publishers when the subscription is created and
subscribes **reliable when every publisher offers reliable, else best effort**. Without a
publisher yet, it subscribes reliable and checks again on a steady-clock timer every
``retry_period_s`` until the first publisher appears (an incompatible best-effort publisher
meanwhile is expected, not logged as a warning); it re-subscribes best effort only if a
publisher offers best effort. So a reliable stream is never re-subscribed: its first messages,
which a player or driver sends as soon as the subscription has matched, are not lost in a
switch (a best-effort stream may lose the messages sent during its switch, as it may lose
any). The choice is logged; publishers that appear later do not change it (a best-effort one
would then not connect to a reliable subscription: force ``best_effort`` for such graphs).
``best_effort`` / ``reliable`` force the reliability.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from rclpy.clock import Clock, ClockType
from rclpy.event_handler import SubscriptionEventCallbacks
from rclpy.node import Node
from rclpy.qos import ReliabilityPolicy

from ga_ros.ros.qos import AUTO, sensor_qos

BEST_EFFORT = 'best_effort'
RELIABLE = 'reliable'


def adapt_reliability(offered: Sequence[ReliabilityPolicy]) -> str | None:
    """The subscription reliability matching every offered one: ``'reliable'`` when all
    publishers offer reliable, ``'best_effort'`` when any offers best effort (or something
    else), None without publishers."""
    if not offered:
        return None
    return RELIABLE if all(r == ReliabilityPolicy.RELIABLE for r in offered) else BEST_EFFORT


class AdaptiveSubscription:
    """One sensor subscription with ``qos_reliability`` ``auto`` | ``best_effort`` |
    ``reliable`` (module docstring).

    Attributes
    ----------
    topic : the subscribed topic.
    reliability : the reliability in use: ``'best_effort'`` or ``'reliable'``.
    decided : False while ``auto`` waits for the first publisher (reliable meanwhile).
    """

    def __init__(self, node: Node, msg_type: Any, topic: str, callback: Callable[[Any], None],
                 reliability: str, depth: int, retry_period_s: float = 0.1) -> None:
        """Subscribe ``callback`` to ``topic``; ``reliability`` is checked by
        :func:`ga_ros.ros.qos.sensor_qos` (raises :class:`ga_ros.errors.InputError`)."""
        sensor_qos(reliability, depth)
        self._node, self._type, self._callback, self._depth = node, msg_type, callback, depth
        self.topic = topic
        self._timer = None
        self.decided = reliability != AUTO
        if self.decided:
            self.reliability = reliability
        else:
            chosen = self._adapt()
            self.decided = chosen is not None
            self.reliability = chosen or RELIABLE
        # undecided: an incompatible (best-effort) publisher is expected news, not a warning
        events = (SubscriptionEventCallbacks(incompatible_qos=lambda _status: None)
                  if not self.decided else None)
        self.subscription = node.create_subscription(
            msg_type, topic, callback, sensor_qos(self.reliability, depth),
            event_callbacks=events)
        if reliability == AUTO:
            if self.decided:
                self._log()
            else:
                self._timer = node.create_timer(retry_period_s, self._retry,
                                                clock=Clock(clock_type=ClockType.STEADY_TIME))

    def _adapt(self) -> str | None:
        infos = self._node.get_publishers_info_by_topic(self.topic)
        return adapt_reliability([i.qos_profile.reliability for i in infos])

    def _log(self) -> None:
        why = ('every publisher offers reliable' if self.reliability == RELIABLE
               else 'a publisher offers best effort')
        self._node.get_logger().info(
            f'{self.topic}: subscribed {self.reliability} (qos_reliability auto: {why})')

    def _retry(self) -> None:
        chosen = self._adapt()
        if chosen is None:
            return
        self._timer.cancel()
        self._node.destroy_timer(self._timer)
        self._timer = None
        self.decided = True
        if chosen != self.reliability:
            self._node.destroy_subscription(self.subscription)
            self.reliability = chosen
            self.subscription = self._node.create_subscription(
                self._type, self.topic, self._callback, sensor_qos(chosen, self._depth))
        self._log()
