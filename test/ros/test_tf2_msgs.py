"""tf2_msgs/TFMessage built into .venv by scripts/build_tf2_msgs.sh: usable by rclpy across
processes, and byte-compatible with the independent CDR implementation of rosbags."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import time

import pytest

from ga_ros.domains import domain_id
from ga_ros.ros.deadlines import patience

pytestmark = pytest.mark.ros

DOMAIN = domain_id('test_tf2_msgs')

PUBLISHER = textwrap.dedent("""
    import os
    import time
    import rclpy
    from geometry_msgs.msg import TransformStamped
    from tf2_msgs.msg import TFMessage

    rclpy.init()
    node = rclpy.create_node('tf_talker')
    pub = node.create_publisher(TFMessage, '/tf', 10)
    t = TransformStamped()
    t.header.frame_id = 'map'
    t.header.stamp.sec = 42
    t.child_frame_id = 'odom'
    t.transform.translation.x = 1.5
    t.transform.translation.y = -2.25
    t.transform.rotation.z = 0.6
    t.transform.rotation.w = 0.8
    end = time.monotonic() + 30.0 * float(os.environ.get("GA_ROS_TEST_PATIENCE", "4"))
    while time.monotonic() < end:
        pub.publish(TFMessage(transforms=[t]))
        rclpy.spin_once(node, timeout_sec=0.1)
""")


def _tf2_msgs():
    pytest.importorskip('rclpy')
    try:
        from tf2_msgs.msg import TFMessage
    except ImportError:
        pytest.skip('tf2_msgs not built: run bash scripts/build_tf2_msgs.sh (needs gcc, g++)')
    return TFMessage


def test_tf_message_crosses_processes() -> None:
    TFMessage = _tf2_msgs()
    import rclpy
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    env = {**os.environ, 'ROS_DOMAIN_ID': str(DOMAIN)}
    proc = subprocess.Popen([sys.executable, '-c', PUBLISHER], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN)
    node = Node('tf_listener', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    got: list = []
    node.create_subscription(TFMessage, '/tf', got.append, 10)
    try:
        end = time.monotonic() + patience(40.0)
        while not got and time.monotonic() < end and proc.poll() is None:
            ex.spin_once(timeout_sec=0.1)
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        if proc.poll() is None:
            proc.kill()
        _, err = proc.communicate(timeout=patience(10))
    assert got, f'no /tf message received; publisher stderr:\n{err}'
    t = got[0].transforms[0]
    assert (t.header.frame_id, t.child_frame_id, t.header.stamp.sec) == ('map', 'odom', 42)
    assert (t.transform.translation.x, t.transform.translation.y) == (1.5, -2.25)
    assert (t.transform.rotation.z, t.transform.rotation.w) == (0.6, 0.8)


def test_tf_message_cdr_matches_rosbags() -> None:
    """rclpy's serialisation (the generated fastrtps typesupport) read by rosbags, and back."""
    TFMessage = _tf2_msgs()
    from geometry_msgs.msg import TransformStamped
    from rclpy.serialization import deserialize_message, serialize_message
    from rosbags.typesys import Stores, get_typestore

    msgs = []
    for k in range(3):
        t = TransformStamped()
        t.header.frame_id = f'frame{k}'
        t.header.stamp.nanosec = 1000 * k + 7
        t.child_frame_id = 'base_link'
        t.transform.translation.z = 0.5 * k
        t.transform.rotation.x = 1.0
        t.transform.rotation.w = 0.0
        msgs.append(t)
    raw = serialize_message(TFMessage(transforms=msgs))
    store = get_typestore(Stores.ROS2_JAZZY)
    decoded = store.deserialize_cdr(raw, 'tf2_msgs/msg/TFMessage')
    assert [t.header.frame_id for t in decoded.transforms] == ['frame0', 'frame1', 'frame2']
    assert [t.header.stamp.nanosec for t in decoded.transforms] == [7, 1007, 2007]
    assert [t.transform.translation.z for t in decoded.transforms] == [0.0, 0.5, 1.0]
    # same layout (padding bytes aside: fastcdr does not zero them)
    again = bytes(store.serialize_cdr(decoded, 'tf2_msgs/msg/TFMessage'))
    assert len(again) == len(raw)
    back = deserialize_message(again, TFMessage)
    assert back == TFMessage(transforms=msgs)
