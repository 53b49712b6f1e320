"""Issue 12 at node level: nothing lost to races, kills, corrupt or foreign files, bad ids.

In-process tests call the node's callbacks directly (the measurements queued in its
subscription are real DDS messages); the process tests run ``alignment_node`` and
``ga-ros play`` as separate processes on their own ``ROS_DOMAIN_ID``.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.duration import Duration  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from std_srvs.srv import Trigger  # noqa: E402
from test_alignment_node import direct, survey  # noqa: E402

from ga_ros import domains, topics  # noqa: E402
from ga_ros.core.measurement import Measurement  # noqa: E402
from ga_ros.core.window import AlignerConfig, TrackWindowAligner  # noqa: E402
from ga_ros.pipeline.journal import journal_path  # noqa: E402
from ga_ros.replay.samples import aerial_sample, write_measurement_bag  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.alignment_node import AlignmentNode  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import NodeClient, start_node_process, stop_process  # noqa: E402
from ga_ros.ros.qos import measurement_qos  # noqa: E402

CONFIG2 = AlignerConfig(window_tracks=2)


def domain_id(offset: int) -> int:
    """This module's domain id for ``offset`` (claimed machine-wide, apart from the other
    test modules' ids)."""
    return domains.domain_id(('test_reliability', offset))


def end_message() -> Odometry:
    msg = Odometry()
    msg.child_frame_id = topics.TRACK_END_FRAME
    return msg


class InProcess:
    """An alignment node and a publisher node in one context (nothing spins them: the node's
    callbacks are called by the test, the publisher's messages wait in the node's queue)."""

    def __init__(self, offset: int, params: list[Parameter]) -> None:
        self.ctx = rclpy.Context()
        rclpy.init(context=self.ctx, domain_id=domain_id(offset))
        self.nodes: list = []
        self.params = [Parameter('window_tracks', value=2),
                       Parameter('allow_finish_track', value=True),
                       Parameter('diagnostics_period_sec', value=0.0), *params]
        self.client = rclpy.create_node('reliab_pub', context=self.ctx)
        self.pub = self.client.create_publisher(Odometry, '/' + topics.MEASUREMENTS,
                                                measurement_qos(transient_local=True))

    def node(self) -> AlignmentNode:
        node = AlignmentNode(context=self.ctx, parameter_overrides=self.params)
        self.nodes.append(node)
        return node

    def publish_and_wait_acked(self, node: AlignmentNode, msgs: list[Odometry]) -> None:
        deadline = time.monotonic() + patience(10)
        while self.pub.get_subscription_count() < 1:
            assert time.monotonic() < deadline, 'the node did not match the publisher'
            time.sleep(0.01)
        for msg in msgs:
            self.pub.publish(msg)
        assert self.pub.wait_for_all_acked(Duration(seconds=patience(10)))

    def close(self) -> None:
        for node in self.nodes:
            node.destroy_node()
        self.client.destroy_node()
        rclpy.try_shutdown(context=self.ctx)


@pytest.fixture
def ros_pair(request):
    made: list[InProcess] = []

    def make(params: list[Parameter], offset: int = 21) -> InProcess:
        made.append(InProcess(offset, params))
        return made[-1]

    yield make
    for p in made:
        p.close()


def feed(node: AlignmentNode, ms: list[Measurement]) -> None:
    """Hand measurements to the node's callback, in order."""
    for m in ms:
        node._on_measurement(conv.measurement_to_odometry(m))


def feed_with_bad(node: AlignmentNode, ms: list[Measurement], bad: list[Measurement]) -> None:
    """The survey with ``bad`` inserted inside track 1, then the end-of-input message."""
    k = next(k for k, m in enumerate(ms) if m.dst_track == 1) + 3
    feed(node, ms[:k])
    feed(node, bad)
    feed(node, ms[k:])
    node._on_measurement(end_message())


def last_of_track_1(ms: list[Measurement]) -> Measurement:
    """The measurement after which :func:`feed_with_bad` inserts its bad ones."""
    return ms[next(k for k, m in enumerate(ms) if m.dst_track == 1) + 2]


def assert_same_path(got: TrackWindowAligner, ref: TrackWindowAligner, atol: float = 1e-9):
    a, b = got.corrected_path(), ref.corrected_path()
    np.testing.assert_array_equal(a.node_ids, b.node_ids)
    np.testing.assert_allclose(a.T_world_node, b.T_world_node, atol=atol)


# ------------------------------------------------------------------ ordering (point 1)
def test_finish_track_waits_for_the_queued_measurements(ros_pair, rng):
    """The race of point 1: `~/finish_track` arrives while the rest of the track is still in
    the subscription queue; it must apply after them, not cut the track short."""
    pair = ros_pair([])
    node = pair.node()
    ms = survey(rng, n_tracks=3, per_swath=5)
    k2 = next(k for k, m in enumerate(ms) if m.dst_track == 2) + 2
    for m in ms[:k2]:
        node._on_measurement(conv.measurement_to_odometry(m))
    pair.publish_and_wait_acked(node, [conv.measurement_to_odometry(m) for m in ms[k2:]])
    resp = node._srv_finish_track(Trigger.Request(), Trigger.Response())
    assert resp.success, resp.message
    assert node.session.counts.accepted == len(ms)
    assert sum(node.session.counts.rejected.values()) == 0
    assert_same_path(node.aligner, direct(ms, CONFIG2))


def test_end_of_input_message_ends_the_last_track(ros_pair, rng):
    pair = ros_pair([Parameter('path_period_sec', value=0.0)])
    node = pair.node()
    ms = survey(rng, n_tracks=2, per_swath=5)
    feed(node, ms)
    assert node.aligner.open_track == 1
    assert node.diagnostic_values()['dead_reckoned_nodes'] == 10    # open track: flagged
    node._on_measurement(end_message())
    assert node.aligner.open_track is None
    assert node.diagnostic_values()['dead_reckoned_nodes'] == 0
    assert sum(node.session.counts.rejected.values()) == 0
    assert_same_path(node.aligner, direct(ms, CONFIG2))


def test_end_of_input_message_is_ordered_in_the_queue(ros_pair, rng):
    """The in-band end message ends the track exactly where it stands in the stream: a
    measurement queued behind it is handled after the track end (here: refused, its track has
    ended), not before."""
    pair = ros_pair([])
    node = pair.node()
    ms = survey(rng, n_tracks=2, per_swath=5)
    first = next(k for k, m in enumerate(ms) if m.dst_track == 1)
    k = next(k for k, m in enumerate(ms) if k > first + 2 and m.dst_track == 1
             and m.dst_id not in {n.dst_id for n in ms[:k]} | {ms[0].src_id})   # a new node
    feed(node, ms[:k])
    pair.publish_and_wait_acked(node, [end_message(), conv.measurement_to_odometry(ms[k])])
    assert node._drain() == 2
    assert dict(node.session.counts.rejected) == {'out_of_order': 1}
    ref = TrackWindowAligner(CONFIG2)
    for m in ms[:k]:
        ref.add_measurement(m)
    ref.finish_track()
    assert_same_path(node.aligner, ref)


def test_idle_timeout_ends_the_open_track(ros_pair, rng):
    idle = patience(0.5)   # "not idle yet" holds even if this process is descheduled a while
    pair = ros_pair([Parameter('track_idle_timeout_sec', value=idle)])
    node = pair.node()
    ms = survey(rng, n_tracks=2, per_swath=4)
    feed(node, ms)
    node._idle_check()                                 # not idle yet
    assert node.aligner.open_track == 1
    time.sleep(idle + 0.01)              # the idleness itself (a sleep never ends early)
    node._idle_check()
    assert node.aligner.open_track is None
    assert_same_path(node.aligner, direct(ms, CONFIG2))


# ------------------------------------------------------------------ bad ids (point 4)
def test_far_ahead_track_id_is_rejected_and_the_survey_goes_on(ros_pair, rng):
    node = ros_pair([]).node()
    ms = survey(rng, n_tracks=3, per_swath=4)
    last = last_of_track_1(ms)
    feed_with_bad(node, ms, [
        Measurement(last.dst_id, last.dst_id + 1, last.dst_track, 1_000_000, last.z, last.cov,
                    last.stamp_ns, 'consecutive'),
        Measurement(last.dst_id, 2**53, last.dst_track, last.dst_track, last.z, last.cov,
                    last.stamp_ns, 'consecutive')])
    assert dict(node.session.counts.rejected) == {'track_jump': 1, 'id_jump': 1}
    assert_same_path(node.aligner, direct(ms, CONFIG2))


@pytest.mark.parametrize('scale', [1e-20, 1e308, 1e9])
def test_tiny_huge_and_placeholder_covariances_are_rejected(ros_pair, rng, scale):
    """Point 3: counted as bad_covariance at the boundary; every later update still works."""
    node = ros_pair([]).node()
    ms = survey(rng, n_tracks=3, per_swath=4)
    last = last_of_track_1(ms)
    feed_with_bad(node, ms, [Measurement(last.src_id, last.dst_id + 1, last.src_track,
                                         last.dst_track, last.z, scale * np.eye(6),
                                         last.stamp_ns, 'consecutive')])
    assert dict(node.session.counts.rejected) == {'bad_covariance': 1}
    assert node.session.counts.solver_failures == 0
    assert_same_path(node.aligner, direct(ms, CONFIG2))


# ------------------------------------------------------------------ files (point 5)
def _run_first(pair: InProcess, ms: list) -> None:
    first = pair.node()
    feed(first, ms)
    first.session.journal.close()          # what the OS holds when the process is killed
    pair.nodes.remove(first)
    first.destroy_node()


@pytest.mark.parametrize('damage', ['journal_header', 'snapshot_crc', 'both_torn'])
def test_damaged_files_keep_every_intact_node(ros_pair, rng, tmp_path, damage):
    state = tmp_path / 'state.npz'
    pair = ros_pair([Parameter('state_file', value=str(state))], offset=23)
    ms = survey(rng, n_tracks=3, per_swath=5)
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 2) + 4
    _run_first(pair, ms[:cut])
    jpath = journal_path(state)
    if damage in ('journal_header', 'both_torn'):
        data = bytearray(jpath.read_bytes())
        data[:4] = b'XXXX'
        jpath.write_bytes(bytes(data) + (b'\x07' * 30 if damage == 'both_torn' else b''))
    if damage == 'snapshot_crc':
        data = bytearray(state.read_bytes())
        data[len(data) // 2] ^= 0xFF
        state.write_bytes(bytes(data))
    second = pair.node()
    ref = TrackWindowAligner(CONFIG2)
    for m in ms[:cut]:
        ref.add_measurement(m)
    assert_same_path(second.aligner, ref)
    moved = [p for p in tmp_path.iterdir() if '.corrupt-' in p.name]
    assert moved, 'the damaged file is kept aside'
    feed(second, ms[cut:])
    second._on_measurement(end_message())
    assert_same_path(second.aligner, direct(ms, CONFIG2))


@pytest.mark.parametrize('kind', ['foreign', 'symlink'])
def test_foreign_or_linked_state_file_is_never_written(ros_pair, rng, tmp_path, kind):
    victim = tmp_path / 'notes.txt'
    victim.write_text('precious\n')
    state = victim if kind == 'foreign' else tmp_path / 'state.npz'
    if kind == 'symlink':
        state.symlink_to(victim)
    pair = ros_pair([Parameter('state_file', value=str(state)),
                     Parameter('allow_reset', value=True)], offset=25)
    node = pair.node()
    ms = survey(rng, n_tracks=2, per_swath=4)
    feed(node, ms)
    node._on_measurement(end_message())
    assert not node._srv_save(Trigger.Request(), Trigger.Response()).success
    node._srv_reset(Trigger.Request(), Trigger.Response())
    assert victim.read_text() == 'precious\n'
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ['notes.txt'] + (['state.npz'] if kind == 'symlink' else []))


def test_reset_is_disabled_by_default(ros_pair, rng, tmp_path):
    state = tmp_path / 'state.npz'
    node = ros_pair([Parameter('state_file', value=str(state))], offset=27).node()
    for m in survey(rng, n_tracks=2, per_swath=4):
        node._on_measurement(conv.measurement_to_odometry(m))
    resp = node._srv_reset(Trigger.Request(), Trigger.Response())
    assert not resp.success and 'allow_reset' in resp.message
    assert node.session.n_nodes() > 0 and state.exists()


# ------------------------------------------------------------------ processes (points 2, 7)
def _play(bag: Path, dom: int, *args: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(dom))
    return subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.play', str(bag), *args],
                            env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                            text=True)


def _final_path(client: NodeClient, n: int, proc, timeout: float = 40.0) -> np.ndarray:
    client.spin_until(lambda: client.paths and len(client.paths[-1][1].poses) == n
                      and client.diag_int('dead_reckoned_nodes') == 0
                      and client.diag_int('nodes') == n, timeout,
                      f'a path of {n} nodes, all adjusted', proc)
    return conv.path_msg_to_poses(client.paths[-1][1])


@pytest.mark.ros
def test_play_into_a_node_started_just_before_delivers_everything(tmp_path):
    sample = aerial_sample(n_tracks=2, positions_per_swath=6, seed=3)
    bag = write_measurement_bag(tmp_path / 'b', sample.measurements, None)
    dom = domain_id(31)
    proc = start_node_process(dom, {'autosave': False, 'diagnostics_period_sec': 0.2},
                              log_path=tmp_path / 'node.log')
    time.sleep(0.1)
    player = _play(bag, dom, '--rate', '0')                  # default options
    client = NodeClient(dom)
    try:
        out, _ = player.communicate(timeout=patience(60))
        assert player.returncode == 0, out
        ref = direct(sample.measurements, AlignerConfig())
        got = _final_path(client, len(ref.corrected_path().node_ids), proc)
        assert client.diag_int('measurements_accepted') == len(sample.measurements), \
            client.diagnostics
        np.testing.assert_allclose(got, ref.corrected_path().T_world_node, atol=1e-6)
    finally:
        client.close()
        stop_process(proc)


@pytest.mark.ros
def test_kill_9_during_play_loses_nothing(tmp_path):
    """kill -9 of the node while `ga-ros play --rate 0` keeps publishing, restart: the final
    path equals an uninterrupted run (journal + snapshot, and the player's transient-local
    history re-delivers what the dead node had queued or missed)."""
    sample = aerial_sample(n_tracks=5, positions_per_swath=10, seed=4)
    bag = write_measurement_bag(tmp_path / 'b', sample.measurements, None)
    dom = domain_id(33)
    state = tmp_path / 'state.npz'
    params = {'state_file': str(state), 'measurement_durability': 'transient_local',
              'diagnostics_period_sec': 0.2}
    log = tmp_path / 'node.log'
    proc = start_node_process(dom, params, log_path=log)
    client = NodeClient(dom)
    player = None
    try:
        client.spin_until(lambda: all(c.service_is_ready() for c in client.services.values()),
                          30, 'the node', proc)
        player = _play(bag, dom, '--rate', '0', '--wait-for-subscribers', '60')
        jpath = journal_path(state)
        deadline = time.monotonic() + patience(30)
        while not (jpath.exists() and jpath.stat().st_size > 11 + 381 * 30):
            assert time.monotonic() < deadline and player.poll() is None, 'play too fast'
            time.sleep(0.001)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=patience(10))
        proc = start_node_process(dom, params, log_path=log)
        out, _ = player.communicate(timeout=patience(90))
        assert player.returncode == 0, out
        ref = direct(sample.measurements, AlignerConfig())
        got = _final_path(client, len(ref.corrected_path().node_ids), proc)
        np.testing.assert_allclose(got, ref.corrected_path().T_world_node, atol=1e-6)
    except Exception:
        print(log.read_text() if log.exists() else '(no log)', client.diagnostics,
              player.communicate()[0] if player is not None and player.poll() is not None
              else '')
        raise
    finally:
        if player is not None and player.poll() is None:
            player.kill()
        client.close()
        stop_process(proc)


def test_play_imports_only_ros_interface_packages(tmp_path, monkeypatch):
    """A bag naming a Python module as a message package cannot make the player import it."""
    from ga_ros.errors import InputError
    from ga_ros.ros.message_types import message_class

    (tmp_path / 'evil_pkg' / 'msg').mkdir(parents=True)
    (tmp_path / 'evil_pkg' / '__init__.py').write_text('')
    (tmp_path / 'evil_pkg' / 'msg' / '__init__.py').write_text(
        'import pathlib\npathlib.Path(__file__).with_name("ran").touch()\nclass Thing: pass\n')
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ('evil_pkg/msg/Thing', 'os/msg/Thing', 'nav_msgs/msg/../os', 'nav_msgs/srv/X'):
        with pytest.raises(InputError, match='message type'):
            message_class(name)
    assert not (tmp_path / 'evil_pkg' / 'msg' / 'ran').exists()
    assert message_class('nav_msgs/msg/Odometry') is Odometry
