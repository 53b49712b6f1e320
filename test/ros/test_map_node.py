"""``map_node`` in-process: keyframe clouds (PointCloud2 in a camera frame) and corrections
(the alignment node's own bytes) in, ``ga/map`` out as RViz and Foxglove read it, equal to a
map computed independently from the final poses; bad messages dropped, the node going on;
``~/save_map`` and the shutdown write the PLY."""

from __future__ import annotations

import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from nav_msgs.msg import Path as PathMsg  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message  # noqa: E402
from sensor_msgs.msg import PointCloud2, PointField  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402

from ga_ros.geometry import se3  # noqa: E402
from ga_ros.pipeline import corrections as corr  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import domain_id  # noqa: E402
from ga_ros.ros.map_node import MapNode  # noqa: E402
from ga_ros.ros.qos import latched_qos, stream_qos  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / 'mapping'))
from test_cloud_map import VOXEL, assert_same_map, read_ply, reference_map  # noqa: E402
from test_cloud_map import Path as KeyPath  # noqa: E402

#: T_base_camera of the test: 0.2 m ahead, 0.5 m up, optical axes (rpy -pi/2 0 -pi/2)
T_BASE_CAM_TEXT = '0.2 0 0.5 -1.5707963267948966 0 -1.5707963267948966'


class Cloud:
    """What assert_same_map reads."""

    def __init__(self, points, intensity):
        self.points, self.intensity = points, intensity


def read_as_viewers_do(msg: PointCloud2) -> Cloud:
    """RViz's / Foxglove's reading: the fields named x, y, z (FLOAT32) and intensity, at their
    offsets, point_step apart, little-endian."""
    f = {p.name: p for p in msg.fields}
    assert [(f[n].offset, f[n].datatype, f[n].count) for n in ('x', 'y', 'z', 'intensity')] == [
        (0, PointField.FLOAT32, 1), (4, PointField.FLOAT32, 1), (8, PointField.FLOAT32, 1),
        (12, PointField.FLOAT32, 1)]
    assert msg.point_step == 16 and msg.row_step == 16 * msg.width and msg.height == 1
    assert not msg.is_bigendian and msg.is_dense
    raw = np.frombuffer(bytes(msg.data), np.uint8).reshape(msg.width, msg.point_step)
    col = lambda n: raw[:, f[n].offset:f[n].offset + 4].copy().view('<f4').reshape(-1)
    return Cloud(np.c_[col('x'), col('y'), col('z')], col('intensity'))


@pytest.mark.ros
def test_map_node_follows_the_corrections(tmp_path: Path, rng) -> None:
    T_base_cam = se3.from_rt(
        np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), np.array([0.2, 0, 0.5]))
    stamps = 1_700_000_000_000_000_000 + 500_000_000 * np.arange(6)
    clouds = {int(s): (rng.uniform(-3, 3, (300, 3)).astype(np.float32),
                       rng.uniform(0, 255, 300).astype(np.float32)) for s in stamps}
    T = np.array([se3.from_translation_rotvec(np.array([2.0 * k, 0.3 * k, 0.0]),
                                              rng.normal(0, 0.1, 3)) for k in range(6)])
    tracker = corr.CorrectionTracker(corr.CorrectionThresholds(0.0, 0.0))

    class P:  # a corrected path as CorrectionTracker reads it
        def __init__(self, n, T):
            self.node_ids = np.arange(n)
            self.track_ids = np.zeros(n, np.int64)
            self.stamps_ns = stamps[:n]
            self.T_world_node = T[:n]

    map_file = tmp_path / 'out' / 'map.ply'
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(41))
    node = MapNode(context=ctx, parameter_overrides=[
        Parameter('warn_throttle_sec', value=0.0), Parameter('publish_period_sec', value=0.05),
        Parameter('voxel_m', value=VOXEL), Parameter('keyframe_voxel_m', value=0.0),
        Parameter('max_points_per_keyframe', value=0), Parameter('max_live_keyframes', value=0),
        Parameter('T_base_camera', value=T_BASE_CAM_TEXT),
        Parameter('map_file', value=str(map_file))])
    peer = Node('map_test_peer', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    executor.add_node(peer)
    maps: list[PointCloud2] = []
    pub_cloud = peer.create_publisher(PointCloud2, '/ga/keyframe_cloud', stream_qos(50))
    pub_corr = peer.create_publisher(PathMsg, '/ga/corrections', stream_qos(100))
    peer.create_subscription(PointCloud2, '/ga/map', maps.append, latched_qos(1))
    client = peer.create_client(Trigger, '/map_node/save_map')

    def spin_until(cond, what: str, seconds: float = 30) -> None:
        deadline = time.monotonic() + patience(seconds)
        while not cond():
            assert time.monotonic() < deadline, what
            executor.spin_once(timeout_sec=0.05)

    def send_corrections(n: int, T_now: np.ndarray) -> None:
        c = tracker.compare(P(n, T_now))
        assert c is not None
        pub_corr.publish(deserialize_message(corr.corrections_cdr(c, 'map', int(stamps[n - 1])),
                                             PathMsg))

    def send_cloud(s: int) -> None:
        pub_cloud.publish(conv.cloud_to_pointcloud2(*clouds[s], 'cam_optical', s))

    def map_equals(T_now: np.ndarray, n: int) -> bool:
        if not maps:
            return False
        want = reference_map({int(stamps[k]): T_now[k] @ T_base_cam for k in range(n)}, clouds)
        try:
            assert_same_map(read_as_viewers_do(maps[-1]), want)
        except AssertionError:
            return False
        return True

    try:
        spin_until(lambda: pub_cloud.get_subscription_count() and pub_corr.get_subscription_count()
                   and node.pub_map.get_subscription_count(), 'discovery')
        for s in stamps[:3]:               # clouds before their poses
            send_cloud(int(s))
        send_corrections(4, T)             # full message: 4 keyframes (the 4th without cloud)
        spin_until(lambda: map_equals(T, 3), 'the map of the first 3 keyframes')
        assert maps[-1].header.frame_id == 'map'
        # bad input: a cloud without z, a corrections message with a NaN pose: dropped
        bad = conv.cloud_to_pointcloud2(*clouds[int(stamps[0])], 'cam_optical', 5)
        bad.fields = bad.fields[:2]
        pub_cloud.publish(bad)
        bad_path = conv.path_to_msg(T[:1], stamps[:1], 'map')
        bad_path.poses[0].pose.orientation.w = float('nan')
        pub_corr.publish(bad_path)
        spin_until(lambda: node.counts['bad_clouds'] == 1 and node.counts['bad_corrections'] == 1,
                   'the bad messages counted')
        # the survey goes on: keyframes 0 and 2 move, 4 and 5 come (5's cloud after its pose)
        T2 = T.copy()
        T2[[0, 2]] = [se3.from_translation_rotvec(np.array([0.3, -0.2, 0.1]), np.zeros(3)) @ t
                      for t in T[[0, 2]]]
        send_cloud(int(stamps[3]))
        send_cloud(int(stamps[4]))
        send_corrections(6, T2)
        send_cloud(int(stamps[5]))
        spin_until(lambda: map_equals(T2, 6), 'the map after the second update')
        values = node.diagnostic_values()
        assert values['moved'] == 2 and values['live_keyframes'] == 6
        # ~/save_map
        spin_until(client.service_is_ready, 'save_map service')
        future = client.call_async(Trigger.Request())
        spin_until(future.done, 'save_map answer')
        assert future.result().success, future.result().message
        _, rec = read_ply(map_file)
        got = Cloud(np.c_[rec['x'], rec['y'], rec['z']], rec['intensity'])
        assert_same_map(got, reference_map({int(stamps[k]): T2[k] @ T_base_cam
                                            for k in range(6)}, clouds))
        map_file.unlink()
    finally:
        executor.shutdown()
        peer.destroy_node()
        node.destroy_node()            # save_on_shutdown: writes map.ply again
        rclpy.try_shutdown(context=ctx)
    assert len(read_ply(map_file)[1]) == len(read_as_viewers_do(maps[-1]).points)


def test_config_file_holds_every_parameter_at_its_default() -> None:
    """config/map.yaml: every parameter map_node declares, each at the dataclass default."""
    from dataclasses import fields

    import yaml

    from ga_ros.core.extrinsic import ExtrinsicConfig
    from ga_ros.mapping.cloud_map import CloudMapConfig
    from ga_ros.ros.map_node import MapNodeSettings, declared_parameters

    path = Path(__file__).resolve().parents[2] / 'config' / 'map.yaml'
    params = yaml.safe_load(path.read_text())['map_node']['ros__parameters']
    assert sorted(params) == sorted(declared_parameters())
    from ga_ros.pipeline.mosaic_map import MosaicMapConfig

    for cls, prefix in ((MapNodeSettings, ''), (CloudMapConfig, ''), (ExtrinsicConfig, ''),
                        (MosaicMapConfig, 'mosaic_')):
        for f in fields(cls):
            assert params[prefix + f.name] == getattr(cls(), f.name), f.name


def test_the_node_reads_spans_as_the_tracker_holds_them() -> None:
    """A corrections message with spans, serialized as the alignment node publishes it and
    deserialized by rclpy: :func:`corrections_from_msg` reads the marker, the ``/span`` endings
    and the poses bit for bit as :meth:`Corrections.message` (what the tracker assumes), and a
    consumer applying it holds what the tracker holds."""
    from ga_ros.ros.map_node import corrections_from_msg

    n = 60
    base = np.array([se3.from_translation_rotvec(np.array([4.0 * k, 0.5 * k, 20.0]),
                                                 np.array([0.0, 0.0, 0.02 * k]))
                     for k in range(n)])
    tracker, held = corr.CorrectionTracker(), corr.HeldPoses()
    spans = 0
    for u in range(3):
        T = np.array([se3.from_translation_rotvec(np.array([0.2 * u * k / n, 0.1 * u, 0.0]),
                                                  np.array([0.0, 0.0, 0.001 * u * k / n])) @ t
                      for k, t in enumerate(base)])
        c = tracker.compare(KeyPath(10**9 * (1 + np.arange(n)), T))
        got = corrections_from_msg(deserialize_message(corr.corrections_cdr(c, 'map', 5),
                                                       PathMsg))
        want = c.message()
        assert got.full == want.full == (u == 0)
        np.testing.assert_array_equal(got.stamps_ns, want.stamps_ns)
        np.testing.assert_array_equal(got.span, want.span)
        np.testing.assert_array_equal(got.T_map_base, want.T_map_base)
        held.apply(got)
        np.testing.assert_array_equal(held.T_map_base, tracker.held())
        spans += int(got.span.sum())
    assert spans > 0
