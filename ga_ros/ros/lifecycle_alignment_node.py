"""Managed (lifecycle) variant of the alignment node: ``lifecycle_alignment_node``.

The same node as :mod:`ga_ros.ros.alignment_node` (parameters, topics, services), driven by
the ROS 2 lifecycle (``rclpy.lifecycle``, REP 2008 style states) so that a launch system or
nav2's lifecycle manager can bring it up and down with the rest of the robot:

* ``unconfigured`` -> ``configure``: parameters are read and topics, services and timers
  created at construction (rclpy creates them with the node), so configuring only checks that
  the node is ready; ``inactive``: every input message is dropped and counted
  (:attr:`LifecycleAlignmentNode.dropped_inactive`), no TF is sent;
* ``activate``: measurements and standard inputs are processed, TF published;
* ``deactivate``: back to dropping (the state is kept);
* ``cleanup``: the state is forgotten (as ``~/reset``), and the standard inputs restart (their
  counters too; a camera beside the odometry stays configured, without its keyframes);
* ``shutdown``: nothing more is processed.

Run it with ``python -m ga_ros.ros.lifecycle_alignment_node --ros-args --params-file
config/alignment.yaml`` and drive it with the ``~/change_state`` service
(``lifecycle_msgs/srv/ChangeState``) or ``ros2 lifecycle set``.
"""

from __future__ import annotations

import sys
from typing import Any

from rclpy.lifecycle import LifecycleNode, State, TransitionCallbackReturn

from ga_ros.core.measurement import Measurement
from ga_ros.pipeline.inputs import InputFrontEnd
from ga_ros.pipeline.map_to_odom import MapToOdom
from ga_ros.pipeline.stream_rate import StreamMonitor
from ga_ros.ros.alignment_node import NODE_NAME, AlignmentNode, usage
from ga_ros.ros.runner import run_node


class LifecycleAlignmentNode(AlignmentNode, LifecycleNode):
    """:class:`AlignmentNode` as a lifecycle node (module doc)."""

    def __init__(self, **kwargs: Any) -> None:
        self.active = False
        self.dropped_inactive = 0
        super().__init__(**kwargs)

    # ------------------------------------------------------------------ gates
    def _process(self, m: Measurement, msg: Any) -> None:
        if not self.active:
            self.dropped_inactive += 1
            return
        super()._process(m, msg)

    def _on_input(self, name: str, msg: Any) -> None:
        if not self.active:
            self.dropped_inactive += 1
            return
        super()._on_input(name, msg)

    def _on_constraint(self, msg: Any) -> None:
        if not self.active:
            self.dropped_inactive += 1
            return
        super()._on_constraint(msg)

    def _publish_tf(self) -> None:
        if self.active:
            super()._publish_tf()

    # ------------------------------------------------------------------ transitions
    def on_configure(self, state: State) -> TransitionCallbackReturn:
        self.get_logger().info('configured (topics and services were created at start)')
        return TransitionCallbackReturn.SUCCESS

    def on_activate(self, state: State) -> TransitionCallbackReturn:
        self.active = True
        return TransitionCallbackReturn.SUCCESS

    def on_deactivate(self, state: State) -> TransitionCallbackReturn:
        self.active = False
        return TransitionCallbackReturn.SUCCESS

    def on_cleanup(self, state: State) -> TransitionCallbackReturn:
        self.active = False
        self.session.reset()
        self._datum_saved = False   # the datum file went with the state
        self._fix_feeder.forget()   # tied to the former keyframes
        self.corrections.restart()  # consumers drop what they held: a full message next
        self.paths.restart()
        if self.front is not None:
            # the camera beside the odometry stays (its calibration and subscriptions), without
            # the former keyframes
            camera = self.front.camera
            if camera is not None:
                camera.forget_keyframes()
            self.front = InputFrontEnd(list(self.front.specs.values()),
                                       self.settings.input_warn_throttle_sec, camera=camera)
        # a new odometry chain, the map not placed yet
        self.odom = MapToOdom(self.front, datum=self.aligner_config.datum)
        self._resumed = False
        for name in self.input_streams:
            self.input_streams[name] = StreamMonitor()
        return TransitionCallbackReturn.SUCCESS

    def on_shutdown(self, state: State) -> TransitionCallbackReturn:
        self.active = False
        return TransitionCallbackReturn.SUCCESS


def main(args: list[str] | None = None) -> int:
    """Console entry point ``lifecycle_alignment_node``."""
    return run_node(LifecycleAlignmentNode, NODE_NAME, args, usage=usage)


if __name__ == '__main__':
    sys.exit(main())
