"""``qos_reliability: auto`` (:mod:`ga_ros.ros.adaptive_qos`): a subscription takes reliable only
when every publisher of its topic offers reliable, waits (reliable) for the first publisher,
and ``best_effort`` / ``reliable`` force the choice; checked against the QoS the middleware
reports for the subscription (``get_subscriptions_info_by_topic``), not against our own field."""

from __future__ import annotations

import time

import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.qos import QoSProfile, ReliabilityPolicy  # noqa: E402
from std_msgs.msg import String  # noqa: E402

from ga_ros.errors import InputError  # noqa: E402
from ga_ros.ros.adaptive_qos import AdaptiveSubscription  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import domain_id  # noqa: E402


def _qos(reliability: ReliabilityPolicy) -> QoSProfile:
    return QoSProfile(depth=10, reliability=reliability)


def _subscribed(node, topic: str) -> ReliabilityPolicy:
    infos = [i for i in node.get_subscriptions_info_by_topic(topic)
             if i.node_name == node.get_name()]
    assert len(infos) == 1, infos
    return infos[0].qos_profile.reliability


@pytest.mark.ros
def test_auto_follows_the_publishers_and_waits_for_the_first() -> None:
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(91))
    node = rclpy.create_node('adaptive_qos_sub', context=ctx)
    pubs = rclpy.create_node('adaptive_qos_pub', context=ctx)
    executor = rclpy.executors.SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    got: list[str] = []
    try:
        # publishers first: all reliable -> reliable; one best effort among them -> best effort
        pubs.create_publisher(String, 'rel', _qos(ReliabilityPolicy.RELIABLE))
        pubs.create_publisher(String, 'rel', _qos(ReliabilityPolicy.RELIABLE))
        pubs.create_publisher(String, 'mixed', _qos(ReliabilityPolicy.RELIABLE))
        pubs.create_publisher(String, 'mixed', _qos(ReliabilityPolicy.BEST_EFFORT))
        rel = AdaptiveSubscription(node, String, 'rel', got.append, 'auto', 5)
        mixed = AdaptiveSubscription(node, String, 'mixed', got.append, 'auto', 5)
        assert _subscribed(node, 'rel') == ReliabilityPolicy.RELIABLE and rel.decided
        assert _subscribed(node, 'mixed') == ReliabilityPolicy.BEST_EFFORT and mixed.decided
        # forced: reliable although the publisher is best effort, and the other way round
        pubs.create_publisher(String, 'be', _qos(ReliabilityPolicy.BEST_EFFORT))
        AdaptiveSubscription(node, String, 'be', got.append, 'reliable', 5)
        AdaptiveSubscription(node, String, 'rel', got.append, 'best_effort', 5)
        assert _subscribed(node, 'be') == ReliabilityPolicy.RELIABLE
        # no publisher yet: reliable, kept (the same subscription) when a reliable publisher
        # appears, so nothing it sends after matching is lost in a switch
        late = AdaptiveSubscription(node, String, 'late', got.append, 'auto', 5,
                                    retry_period_s=0.05)
        assert not late.decided and _subscribed(node, 'late') == ReliabilityPolicy.RELIABLE
        first = late.subscription
        pub = pubs.create_publisher(String, 'late', _qos(ReliabilityPolicy.RELIABLE))
        end = time.monotonic() + patience(10.0)
        while not late.decided and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        assert late.decided and _subscribed(node, 'late') == ReliabilityPolicy.RELIABLE
        assert late.subscription is first
        end = time.monotonic() + patience(10.0)
        while not got and time.monotonic() < end:
            pub.publish(String(data='x'))
            executor.spin_once(timeout_sec=0.05)
        assert got and got[0].data == 'x'
        # no publisher yet, then a best-effort one: re-subscribed best effort, and it receives
        # (into its own list: 'x's published above may still be arriving on 'late')
        got_be: list[String] = []
        late_be = AdaptiveSubscription(node, String, 'late_be', got_be.append, 'auto', 5,
                                       retry_period_s=0.05)
        pub_be = pubs.create_publisher(String, 'late_be', _qos(ReliabilityPolicy.BEST_EFFORT))
        end = time.monotonic() + patience(10.0)
        while not late_be.decided and time.monotonic() < end:
            executor.spin_once(timeout_sec=0.05)
        assert late_be.decided and _subscribed(node, 'late_be') == ReliabilityPolicy.BEST_EFFORT
        end = time.monotonic() + patience(10.0)
        while not got_be and time.monotonic() < end:
            pub_be.publish(String(data='y'))
            executor.spin_once(timeout_sec=0.05)
        assert got_be and got_be[0].data == 'y'
        with pytest.raises(InputError, match='qos_reliability'):
            AdaptiveSubscription(node, String, 'bad', got.append, 'sometimes', 5)
    finally:
        executor.shutdown()
        pubs.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
