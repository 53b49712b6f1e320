"""A stand-in for tf2_ros' ``static_transform_publisher`` (not installable here), for the launch
file tests: the same non-deprecated command line, ``--x --y --z`` (m), ``--roll --pitch --yaw``
(rad, ``R = Rz(yaw) Ry(pitch) Rx(roll)``, as tf2's ``setRPY``) or ``--qx --qy --qz --qw``,
``--frame-id``, ``--child-frame-id``, then ROS arguments. Anything else (the deprecated positional
form, or a pose handed over as one argument) is refused with exit code 2, as the real program
refuses a command line it cannot parse. Publishes the transform once on ``/tf_static``
(transient local, as tf2_ros' static broadcaster) and spins until SIGINT. Each command line is
appended to the file ``$GA_ROS_STATIC_TF_LOG`` if set, for the test to check.
"""

from __future__ import annotations

import argparse
import os
import sys

import rclpy
from geometry_msgs.msg import TransformStamped
from rclpy.node import Node
from rclpy.qos import DurabilityPolicy, QoSProfile
from rclpy.utilities import remove_ros_args
from scipy.spatial.transform import Rotation
from tf2_msgs.msg import TFMessage


def parse(argv: list[str]) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog='static_transform_publisher', allow_abbrev=False)
    for name in ('x', 'y', 'z', 'roll', 'pitch', 'yaw', 'qx', 'qy', 'qz'):
        p.add_argument(f'--{name}', type=float, default=0.0)
    p.add_argument('--qw', type=float, default=None)
    p.add_argument('--frame-id', required=True)
    p.add_argument('--child-frame-id', required=True)
    return p.parse_args(argv)


def main() -> int:
    argv = remove_ros_args(sys.argv)[1:]
    log = os.environ.get('GA_ROS_STATIC_TF_LOG')
    if log:
        with open(log, 'a') as f:
            f.write(' '.join(repr(a) for a in argv) + '\n')
    a = parse(argv)
    if a.qw is not None:
        q = [a.qx, a.qy, a.qz, a.qw]
    else:
        q = Rotation.from_euler('xyz', [a.roll, a.pitch, a.yaw]).as_quat()
    rclpy.init()
    node = Node('static_transform_publisher')
    msg = TransformStamped()
    msg.header.stamp = node.get_clock().now().to_msg()
    msg.header.frame_id, msg.child_frame_id = a.frame_id, a.child_frame_id
    msg.transform.translation.x, msg.transform.translation.y = a.x, a.y
    msg.transform.translation.z = a.z
    r = msg.transform.rotation
    r.x, r.y, r.z, r.w = (float(v) for v in q)
    pub = node.create_publisher(TFMessage, '/tf_static', QoSProfile(
        depth=1, durability=DurabilityPolicy.TRANSIENT_LOCAL))
    pub.publish(TFMessage(transforms=[msg]))
    try:
        rclpy.spin(node)
    except KeyboardInterrupt:
        pass
    finally:
        rclpy.try_shutdown()
    return 0


if __name__ == '__main__':
    sys.exit(main())
