"""The alignment node's outputs for big surveys (issue 14 item 3): the window's movable poses on
``ga/window_path`` after every update, the full path at most every
``full_path_min_period_sec`` (in-process node, publishers captured)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip('rclpy')

from nav_msgs.msg import Path  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from rclpy.serialization import deserialize_message, serialize_message  # noqa: E402

from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.alignment_node import AlignmentNode  # noqa: E402
from ga_ros.ros.harness import domain_id, ros_context  # noqa: E402
from ga_ros.sim.aerial import aerial_scenario  # noqa: E402
from ga_ros.sim.noise import NoiseModel, perturb  # noqa: E402


@pytest.fixture
def ctx():
    with ros_context(domain_id(61)) as c:
        yield c


def _poses(msg) -> np.ndarray:
    return np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                     for p in msg.poses])


def test_window_path_every_update_full_path_at_most_every_period(ctx) -> None:
    params = {'window_tracks': 2, 'full_path_min_period_sec': 3600.0, 'autosave': False,
              'publish_markers': False, 'diagnostics_period_sec': 0.0,
              'transform_publish_period_sec': 0.0}
    node = AlignmentNode(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                           for k, v in params.items()])
    full, window = [], []
    try:
        node.pub_path.publish = lambda data: full.append(deserialize_message(data, Path))
        node.pub_window.publish = window.append
        sc = aerial_scenario(n_tracks=4, positions_per_swath=6)
        nm = perturb(sc.true_motions(), NoiseModel(2.0, sc.depth_m), np.random.default_rng(2))
        for m in sc.measurements(nm.z, nm.cov):
            node._on_measurement(conv.measurement_to_odometry(m))
        node._finish_track(drain=False)
        n_updates = node.aligner.stats.n_updates
        assert n_updates >= 4
        # one window path per update; the full path only once within the period (the first)
        assert len(window) >= n_updates and len(full) == 1
        cp = node.aligner.corrected_path()
        movable = ~cp.frozen
        assert 0 < movable.sum() < len(cp.node_ids)      # older tracks froze
        np.testing.assert_array_equal(_poses(window[-1]), cp.T_world_node[movable, :3, 3])
        assert [p.header.stamp.sec * 10**9 + p.header.stamp.nanosec
                for p in window[-1].poses] == cp.stamps_ns[movable].tolist()
        # the period over: the timer sends the full path once, with every node
        node._next_full_path = 0.0
        node._full_path_timer()
        node._full_path_timer()
        assert len(full) == 2
        np.testing.assert_array_equal(_poses(full[-1]), cp.T_world_node[:, :3, 3])
        # message size: linear in the poses (docs/multi-robot.md, "The path at 100,000 poses")
        sizes = [len(serialize_message(conv.path_to_msg(cp.T_world_node[:k], cp.stamps_ns[:k],
                                                        'map'))) for k in (10, 20)]
        per_pose = (sizes[1] - sizes[0]) // 10
        n = len(cp.node_ids)
        assert len(serialize_message(full[-1])) == sizes[0] + (n - 10) * per_pose
        assert per_pose <= 80   # 'map' frame: ~8 MB for 100,000 poses
    finally:
        node.destroy_node()


@pytest.mark.parametrize('frame_id', ['', 'm', 'map', 'odom', 'robot1/map', 'a_long/frame_x'])
@pytest.mark.parametrize('n', [0, 1, 2, 7])
def test_path_bytes_decode_to_the_rclpy_message(frame_id: str, n: int) -> None:
    """``path_cdr`` writes what ``serialize_message(path_to_msg(...))`` does (same length; rclpy
    decodes it to an equal message; padding bytes may differ), for frame ids of every padding
    phase and stamps with nanoseconds."""
    from ga_ros.geometry import se3
    from ga_ros.io.cdr import path_cdr

    rng = np.random.default_rng(n + len(frame_id))
    T = se3.exp(rng.normal(size=(n, 6)) * [5, 5, 5, 2, 2, 2])
    stamps = rng.integers(0, 2**31 * 10**9, size=n)
    for stamp in (1_700_000_000_123_456_789, None):
        want = conv.path_to_msg(T, stamps, frame_id, stamp)
        got = path_cdr(T, stamps, frame_id, stamp)
        assert len(got) == len(serialize_message(want))
        assert deserialize_message(got, Path) == want


@pytest.mark.parametrize('frame_id', ['', 'map', 'robot1/map'])
@pytest.mark.parametrize('n', [0, 1, 2, 9])
def test_framed_path_bytes_decode_to_the_rclpy_message(frame_id: str, n: int) -> None:
    """``framed_path_cdr`` (``ga/corrections``: each pose with its own frame id, of every
    length and so every padding phase) writes what rclpy serializes for the same message (same
    length; decoded equal; padding bytes may differ)."""
    from geometry_msgs.msg import PoseStamped

    from ga_ros.geometry import se3
    from ga_ros.io.cdr import framed_path_cdr

    rng = np.random.default_rng(n + len(frame_id))
    T = se3.exp(rng.normal(size=(n, 6)) * [5, 5, 5, 2, 2, 2])
    stamps = rng.integers(0, 2**31 * 10**9, size=n)
    frames = ['ga/full_path'] + [f'ga/{k}/{"7" * (k + 1)}' for k in range(n - 1)] if n else []
    got = framed_path_cdr(T, stamps, frames, frame_id, 1_700_000_000_123_456_789)
    want = Path()
    want.header.frame_id = frame_id
    want.header.stamp = conv.ns_to_stamp(1_700_000_000_123_456_789)
    p, q = (a.tolist() for a in se3.to_pos_quat(T)) if n else ([], [])
    for k in range(n):
        ps = PoseStamped()
        ps.header.frame_id = frames[k]
        ps.header.stamp = conv.ns_to_stamp(int(stamps[k]))
        ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = p[k]
        o = ps.pose.orientation
        o.x, o.y, o.z, o.w = q[k]
        want.poses.append(ps)
    assert len(got) == len(serialize_message(want))
    assert deserialize_message(got, Path) == want
