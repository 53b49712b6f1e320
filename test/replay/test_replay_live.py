"""Replay == live: the same bag messages give the same outputs through the replay and the nodes.

The nodes run in this process and get each bag message deserialised by rclpy (as a
subscription would hand it over); the replay reads the bag with rosbags. Both drive the same
pipeline objects (:class:`ga_ros.pipeline.session.AlignmentSession`,
:class:`ga_ros.pipeline.stereo.StereoFrontEnd`), so the results must agree exactly.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from sensor_msgs.msg import CameraInfo, CompressedImage  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from ga_ros import domains  # noqa: E402
from ga_ros.io.bag import BagReader  # noqa: E402
from ga_ros.io.bag_messages import measurement_to_odometry, odometry_to_measurement  # noqa: E402
from ga_ros.io.bag_writer import BagWriter  # noqa: E402
from ga_ros.replay.config import ReplayConfig  # noqa: E402
from ga_ros.replay.pipeline import replay  # noqa: E402
from ga_ros.replay.samples import aerial_sample  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402

RCLPY_TYPES = {'nav_msgs/msg/Odometry': Odometry, 'sensor_msgs/msg/CameraInfo': CameraInfo,
               'sensor_msgs/msg/CompressedImage': CompressedImage,
               'tf2_msgs/msg/TFMessage': TFMessage}


def domain_id(offset: int) -> int:
    """This module's domain id for ``offset`` (claimed machine-wide)."""
    return domains.domain_id(('replay_live', offset))


def live_messages(bag: Path, topics: list[str] | None = None) -> list[tuple[str, object]]:
    """Every message of the bag as an rclpy message (what a subscription delivers)."""
    with BagReader(bag) as reader:
        return [(m.topic, deserialize_message(bytes(m.data), RCLPY_TYPES[m.msgtype]))
                for m in reader.messages(topics) if m.msgtype in RCLPY_TYPES]


@pytest.fixture
def context():
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(33))
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)


def test_alignment_node_equals_replay(tmp_path: Path, context) -> None:
    from ga_ros.ros.alignment_node import AlignmentNode

    s = aerial_sample(n_tracks=3, positions_per_swath=10, noise_pct=5.0, seed=5)
    ms = s.measurements
    with BagWriter(tmp_path / 'in') as bag:
        for k, m in enumerate(ms):
            msg = measurement_to_odometry(m)
            if k == 7:
                msg.header.frame_id = 'camera'    # undecodable: rejected by both
            bag.write('/ga/measurements', 'nav_msgs/msg/Odometry', msg, m.stamp_ns)
            if k == 20:                            # a repeated delivery: rejected by both
                bag.write('/ga/measurements', 'nav_msgs/msg/Odometry', msg, m.stamp_ns)
    r = replay(tmp_path / 'in', tmp_path / 'out',
               ReplayConfig(anchor_to_ground_truth=False, plot=False))
    node = AlignmentNode(context=context, parameter_overrides=[
        Parameter('diagnostics_period_sec', value=0.0),
        Parameter('allow_finish_track', value=True)])
    try:
        for _, msg in live_messages(tmp_path / 'in'):
            node._on_measurement(msg)
        assert node._srv_finish_track(Trigger.Request(), Trigger.Response()).success
        cp = node.aligner.corrected_path()
        values = node.diagnostic_values()
    finally:
        node.destroy_node()
    # the node's path at the end is the replay's online estimate (trajectory_online.tum); the
    # replay's GA is the final batch on top of it
    np.testing.assert_array_equal(cp.node_ids, r.online.node_ids)
    np.testing.assert_array_equal(cp.T_world_node, r.online.T_world_node)
    np.testing.assert_array_equal(cp.node_ids, r.corrected.node_ids)
    assert values['measurements_accepted'] == r.n_measurements == len(ms) - 1
    assert values['rejected'] == sum(r.rejected.values()) == 2
    assert values['updates'] == len(r.updates) == 3


def test_vo_node_equals_replay(tmp_path: Path, context) -> None:
    """The stereo front end in vo_node and in the replay: the same measurements, bit for bit
    (corrected-path feedback off: the live node gets it asynchronously)."""
    pytest.importorskip('ga_ros.vo.odometry')
    from ga_ros.pipeline.stereo import FrontEndConfig
    from ga_ros.replay.samples import StereoSampleConfig, make_stereo_bag
    from ga_ros.ros.vo_node import VoNode

    cfg = StereoSampleConfig(n_tracks=1, positions_per_swath=10, turn_positions=12, seed=4)
    bag = make_stereo_bag(tmp_path / 'bag', cfg)
    r = replay(bag, tmp_path / 'out', ReplayConfig(vo=FrontEndConfig(feedback=False),
                                                   plot=False))
    with BagReader(tmp_path / 'out' / 'replay_bag') as out:
        want = [odometry_to_measurement(m.msg) for m in out.messages(['/ga/measurements'])]
    from rclpy.parameter import Parameter

    node = VoNode(context=context, parameter_overrides=[Parameter('pair_queue', value=1000)])
    sent: list[Odometry] = []
    node.pub_meas.publish = sent.append
    try:
        for topic, msg in live_messages(bag):
            side = 'left' if '/left/' in topic else 'right'
            if isinstance(msg, TFMessage):   # the sample's extrinsic, as tf2 would hand it
                node._on_tf_static(msg)
            elif isinstance(msg, CameraInfo):
                node._on_info(msg, side)
            else:
                node._on_image(msg, side)
                assert node.wait_idle()  # the worker thread, in bag order
    finally:
        node.destroy_node()
    got = [conv.odometry_to_measurement(m) for m in sent]
    assert len(want) > 5 and len(got) == len(want) == r.n_measurements
    for a, b in zip(got, want):
        assert (a.src_id, a.dst_id, a.kind, a.stamp_ns) == (b.src_id, b.dst_id, b.kind,
                                                           b.stamp_ns)
        np.testing.assert_array_equal(a.z, b.z)
        np.testing.assert_array_equal(a.cov, b.cov)


def test_corrections_of_the_node_equal_the_replay_bag(tmp_path: Path, context) -> None:
    """``ga/corrections``: the messages the node publishes after each update are the replay
    bag's, field for field (the replay without its final batch, which the node does not run);
    a reset publishes an empty full message."""
    from nav_msgs.msg import Path as PathMsg

    from ga_ros import topics
    from ga_ros.ros.alignment_node import AlignmentNode

    s = aerial_sample(n_tracks=7, positions_per_swath=8, noise_pct=5.0, seed=5)
    with BagWriter(tmp_path / 'in') as bag:
        for m in s.measurements:
            bag.write('/ga/measurements', 'nav_msgs/msg/Odometry', measurement_to_odometry(m),
                      m.stamp_ns)
    replay(tmp_path / 'in', tmp_path / 'out',
           ReplayConfig(anchor_to_ground_truth=False, plot=False, final_batch=False))
    with BagReader(tmp_path / 'out' / 'replay_bag') as out:
        want = [deserialize_message(bytes(m.data), PathMsg)
                for m in out.messages(['/ga/corrections'])]
    node = AlignmentNode(context=context, parameter_overrides=[
        Parameter('diagnostics_period_sec', value=0.0),
        Parameter('allow_finish_track', value=True), Parameter('allow_reset', value=True)])
    sent: list = []
    node.pub_corrections.publish = sent.append
    try:
        for _, msg in live_messages(tmp_path / 'in'):
            node._on_measurement(msg)
        assert node._srv_finish_track(Trigger.Request(), Trigger.Response()).success
        got = [deserialize_message(bytes(data), PathMsg) for data in sent]
        assert node._srv_reset(Trigger.Request(), Trigger.Response()).success
    finally:
        node.destroy_node()
    assert len(got) == 7 and got == want          # one per update
    assert got[0].poses[0].header.frame_id == topics.CORRECTIONS_FULL_FRAME
    assert all(m.header.frame_id == 'map' for m in got)
    assert not any(p.header.frame_id == topics.CORRECTIONS_FULL_FRAME for m in got[1:]
                   for p in m.poses)
    reset = deserialize_message(bytes(sent[-1]), PathMsg)   # after the reset: drop everything
    assert [p.header.frame_id for p in reset.poses] == [topics.CORRECTIONS_FULL_FRAME]
