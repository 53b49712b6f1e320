"""``ga-ros play``: a bag published into a live ROS graph, received by a real subscriber."""

from __future__ import annotations

import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import write_unknown_type_bag

from ga_ros.domains import domain_id
from ga_ros.replay.samples import aerial_sample, write_measurement_bag
from ga_ros.ros.deadlines import patience

pytestmark = pytest.mark.ros

DOMAIN = domain_id('test_play')


def _env() -> dict[str, str]:
    return {**os.environ, 'ROS_DOMAIN_ID': str(DOMAIN)}


@pytest.fixture(scope='module')
def sample() -> object:
    return aerial_sample(n_tracks=2, positions_per_swath=10, seed=5)


@pytest.fixture
def ros():
    """An rclpy context and node of our own (domain id of this test run)."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.node import Node

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=DOMAIN)
    node = Node('test_play_listener', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    try:
        yield node, ex
    finally:
        ex.shutdown()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _play(bag: Path, *args: str) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.play', str(bag), *args],
                            env=_env(), stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)


def _receive(ros, proc: subprocess.Popen, want: int, timeout: float = 40.0):
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from rosgraph_msgs.msg import Clock

    node, ex = ros
    got, clock = [], []
    qos = QoSProfile(depth=2000, reliability=ReliabilityPolicy.RELIABLE)
    node.create_subscription(Odometry, '/ga/measurements', got.append, qos)
    node.create_subscription(Clock, '/clock', clock.append, 100)
    end = time.monotonic() + patience(timeout)
    try:
        while time.monotonic() < end and (len(got) < want or proc.poll() is None):
            ex.spin_once(timeout_sec=0.05)
        for _ in range(20):  # drain what is in flight
            ex.spin_once(timeout_sec=0.01)
    finally:
        if proc.poll() is None:
            proc.kill()
        out, err = proc.communicate(timeout=patience(10))
    return got, clock, out, err


def test_play_as_fast_as_subscribers_keep_up(tmp_path: Path, sample: object, ros) -> None:
    from ga_ros.ros.conversions import odometry_to_measurement

    bag = write_measurement_bag(tmp_path / 'b', sample.measurements, sample.ground_truth)
    proc = _play(bag, '--rate', '0', '--delay', '0', '--wait-for-subscribers', '20',
                 '--topics', '/ga/measurements')
    got, clock, out, err = _receive(ros, proc, len(sample.measurements) + 1)
    assert proc.returncode == 0, err
    assert f'published {len(sample.measurements)} messages' in out
    assert '1 end-of-input messages' in out
    assert got[-1].child_frame_id == 'ga/track_end'        # the last track ends
    got = got[:-1]
    assert len(got) == len(sample.measurements)
    for msg, m in zip(got, sample.measurements):
        d = odometry_to_measurement(msg)
        assert (d.src_id, d.dst_id, d.kind, d.stamp_ns) == (m.src_id, m.dst_id, m.kind,
                                                           m.stamp_ns)
        np.testing.assert_allclose(d.z, m.z, atol=1e-12)
    stamps = [c.clock.sec * 10**9 + c.clock.nanosec for c in clock]
    assert stamps and stamps == sorted(stamps)
    assert stamps[-1] == sample.measurements[-1].stamp_ns


def test_play_at_a_rate_publishes_clock_in_bag_time(tmp_path: Path, sample: object, ros) -> None:
    ms = sample.measurements[:30]
    bag = write_measurement_bag(tmp_path / 'b', ms, None)
    span_s = (ms[-1].stamp_ns - ms[0].stamp_ns) * 1e-9
    proc = _play(bag, '--rate', str(span_s / 1.0), '--delay', '0', '--wait-for-subscribers',
                 '20')
    got, clock, out, err = _receive(ros, proc, len(ms) + 1)
    assert proc.returncode == 0, err
    assert len(got) == len(ms) + 1 and got[-1].child_frame_id == 'ga/track_end'
    stamps = np.array([c.clock.sec * 10**9 + c.clock.nanosec for c in clock])
    assert (np.diff(stamps) >= 0).all()
    assert stamps[0] >= ms[0].stamp_ns and stamps[-1] == ms[-1].stamp_ns
    assert len(stamps) > 5  # /clock keeps ticking between messages


def test_play_rejects_bad_bags(tmp_path: Path) -> None:
    path = write_unknown_type_bag(tmp_path / 'u')
    for bag, expect in ((path, "unknown message type 'my_pkg/msg/Thing'"),
                        (tmp_path / 'missing', 'bag not found')):
        res = subprocess.run([sys.executable, '-m', 'ga_ros.ros.play', str(bag), '--delay', '0'],
                             env=_env(), capture_output=True, text=True, timeout=patience(60))
        assert res.returncode == 1
        assert expect in res.stderr


def test_play_drives_the_alignment_node(tmp_path: Path, sample: object, ros) -> None:
    """`ga-ros play` into a running alignment_node (sim time): the path the node publishes at
    the first track end equals TrackWindowAligner fed the same measurements in-process."""
    window = pytest.importorskip('ga_ros.core.window')
    harness = pytest.importorskip('ga_ros.ros.harness')
    from nav_msgs.msg import Path as PathMsg

    from ga_ros.ros.qos import latched_qos

    aligner = window.TrackWindowAligner(window.AlignerConfig())
    for m in sample.measurements:
        if aligner.add_measurement(m):
            break
    want = aligner.corrected_path()
    bag = write_measurement_bag(tmp_path / 'b', sample.measurements, sample.ground_truth)
    node, ex = ros
    paths = []
    # a deep reader queue: the first update's path must not be replaced by a later one (the
    # node keeps publishing the open track's path) before this process has taken it
    sub = node.create_subscription(PathMsg, '/ga/corrected_path', paths.append,
                                   latched_qos(100))
    proc = harness.start_node_process(DOMAIN, {'use_sim_time': True, 'autosave': False},
                                      log_path=tmp_path / 'node.log')
    player = None
    try:
        # the node's path publisher keeps only its last path for a late subscriber: match it
        # before the node has anything to publish, or the first update's path may be missed
        end = time.monotonic() + patience(40)
        while sub.get_publisher_count() == 0 and time.monotonic() < end:
            ex.spin_once(timeout_sec=0.1)
        assert sub.get_publisher_count() > 0, (tmp_path / 'node.log').read_text()[-2000:]
        player = _play(bag, '--rate', '0', '--delay', '0', '--wait-for-subscribers', '20')
        end = time.monotonic() + patience(40)
        def first_update():  # paths between updates hold the open track dead-reckoned
            return next((p for p in paths if len(p.poses) == len(want.node_ids)), None)

        while time.monotonic() < end and first_update() is None:
            ex.spin_once(timeout_sec=0.1)
        player.wait(timeout=patience(30))
        assert player.returncode == 0, player.stderr.read()
    finally:
        if player is not None and player.poll() is None:
            player.kill()
        harness.stop_process(proc)
    assert first_update() is not None, (tmp_path / 'node.log').read_text()[-2000:]
    got = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                    for p in first_update().poses])
    np.testing.assert_allclose(got, np.asarray(want.T_world_node)[:, :3, 3], atol=1e-6)


def test_play_says_what_was_not_delivered(tmp_path: Path, sample: object) -> None:
    """Nobody subscribes: the history is kept for the delivery timeout, then play exits with
    code 3 naming the measurement topic (a node that never got the data is not a success)."""
    from ga_ros.ros.play import EXIT_NOT_DELIVERED

    bag = write_measurement_bag(tmp_path / 'b', sample.measurements[:10], None)
    t0 = time.monotonic()
    res = subprocess.run([sys.executable, '-m', 'ga_ros.ros.play', str(bag), '--rate', '0',
                          '--wait-for-subscribers', '0', '--delivery-timeout', '2'],
                         env={**_env(), 'ROS_DOMAIN_ID': str(domain_id('test_play nobody'))},
                         capture_output=True, text=True, timeout=patience(120))
    assert res.returncode == EXIT_NOT_DELIVERED, res.stderr
    assert 'not delivered' in res.stderr and '/ga/measurements: no subscriber' in res.stderr
    assert time.monotonic() - t0 >= 2.0


@pytest.mark.parametrize('confirm', ['never', 'all', 'part'])
def test_play_waits_for_a_subscriber_asking_for_the_history(tmp_path: Path, sample: object, ros,
                                                           confirm: str) -> None:
    """A transient-local subscriber of the measurements is there to process them: play expects
    its input-done confirmation (its node name and how many measurements it received) from
    the subscription alone (whenever its done publisher is discovered), exits 0 once it
    confirmed all it was sent, and with code 3 naming it when it never confirms or confirms
    fewer than were sent (no success without delivery)."""
    from diagnostic_msgs.msg import KeyValue
    from nav_msgs.msg import Odometry

    from ga_ros.ros.play import EXIT_NOT_DELIVERED
    from ga_ros.ros.qos import latched_qos, measurement_qos

    node, ex = ros
    got = []
    # a node with a done publisher counts as at work: the one that never confirms has none
    done = (node.create_publisher(KeyValue, '/ga/measurements_done', latched_qos())
            if confirm != 'never' else None)

    def on_measurement(msg: Odometry) -> None:
        if msg.child_frame_id != 'ga/track_end':
            got.append(msg)
        elif done is not None:
            n = len(got) if confirm == 'all' else len(got) // 2
            done.publish(KeyValue(key=node.get_fully_qualified_name(), value=str(n)))

    node.create_subscription(Odometry, '/ga/measurements', on_measurement,
                             measurement_qos(transient_local=True))
    bag = write_measurement_bag(tmp_path / 'b', sample.measurements[:20], None)
    proc = _play(bag, '--rate', '0', '--delay', '0', '--wait-for-subscribers', '20',
                 '--delivery-timeout', '3')
    end = time.monotonic() + patience(120)
    while proc.poll() is None and time.monotonic() < end:
        ex.spin_once(timeout_sec=0.05)
    if proc.poll() is None:
        proc.kill()
    _, err = proc.communicate(timeout=patience(10))
    assert len(got) == 20, err
    if confirm == 'all':
        assert proc.returncode == 0, err
    else:
        assert proc.returncode == EXIT_NOT_DELIVERED, err
        assert node.get_fully_qualified_name() in err, err
        if confirm == 'never':
            assert 'did not confirm' in err and '/ga/measurements_done' in err
        else:
            assert 'confirmed only 10 of the 20 measurements sent' in err


def test_an_endpoint_without_a_node_name_is_not_waited_for() -> None:
    """rclpy names an endpoint ``_NODE_NAME_UNKNOWN_`` while DDS does not know its node (a
    killed node's stale endpoint): play must not wait for it to confirm."""
    from types import SimpleNamespace

    from ga_ros.ros.play import BagPlayer

    def info(name: str, durability: int) -> SimpleNamespace:
        return SimpleNamespace(node_name=name, node_namespace='/',
                               qos_profile=SimpleNamespace(durability=durability))

    from rclpy.qos import DurabilityPolicy
    tl = DurabilityPolicy.TRANSIENT_LOCAL
    node = SimpleNamespace(
        get_subscriptions_info_by_topic=lambda t: [info('alignment_node', tl),
                                                   info('_NODE_NAME_UNKNOWN_', tl)],
        get_publishers_info_by_topic=lambda t: [info('_NODE_NAME_UNKNOWN_', 0)])
    player = SimpleNamespace(node=node)
    assert BagPlayer.confirmers(player, '/ga/measurements') == {'/alignment_node'}
