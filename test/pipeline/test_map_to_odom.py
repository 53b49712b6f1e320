"""One owner of ``map -> odom`` (ga_ros.pipeline.map_to_odom): the replay writes it at a fixed
period over the whole bag and does not copy another localiser's; the alignment node stops
publishing it when it hears another publisher (unless told) and says so in /diagnostics."""

from __future__ import annotations

import json
import os
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import ODOMETRY, odometry_msg
from test_replay_inputs import _config, _scenario

from ga_ros.core.integration import F2FIntegrator
from ga_ros.core.measurement import Measurement
from ga_ros.domains import domain_id
from ga_ros.geometry import se3
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_writer import BagWriter, tf_message, transform_msg
from ga_ros.pipeline.map_to_odom import (
    MapToOdom,
    PeriodicSchedule,
    foreign_odom_parents,
    without_odom_parent,
)

AMCL = se3.from_translation_rotvec(np.array([7.4, 7.5, 0.0]), np.array([0, 0, 0.3]))


def test_schedule_gives_every_period_once_and_caps_a_jump():
    sched = PeriodicSchedule(0.05, max_burst=4)
    assert sched.due(1_000) == [1_000]
    assert sched.due(1_000 + 49_999_999) == []
    assert sched.due(1_000 + 120_000_000) == [1_000 + 50_000_000, 1_000 + 100_000_000]
    late = sched.due(1_000 + 10**9)          # 18 due, only the newest 4 sent
    assert len(late) == 4 and late[-1] == 1_000 + 10**9
    assert np.all(np.diff(late) == 50_000_000)


def test_map_to_odom_composes_with_the_chain_to_the_corrected_pose(rng):
    m2o = MapToOdom(f2f=F2FIntegrator())
    ids, T_map = [0], [np.eye(4)]
    for k in range(5):
        motion = se3.exp(rng.normal(size=6) * 0.2)
        m2o.add(Measurement.from_pose(k, k + 1, 0, 0, motion, np.eye(6), 10 * (k + 1)))
        ids.append(k + 1)
        T_map.append(se3.exp(rng.normal(size=6)))    # any correction of the nodes
    T = m2o.update(np.array(ids), np.array(T_map))
    T_odom_5, stamp = m2o.latest()
    assert stamp == 50
    np.testing.assert_allclose(T @ T_odom_5, T_map[-1], atol=1e-12)


def test_own_and_foreign_transforms_are_told_apart():
    ours = np.eye(4)
    ours[0, 3] = 2.9
    stamp = 1_700_000_000_000_000_000
    msg = tf_message([transform_msg('map', 'odom', ours, stamp),
                      transform_msg('odom', 'base_link', np.eye(4), stamp)])
    assert foreign_odom_parents(msg, 'odom', {stamp: ours}, 'map') == []
    other = tf_message([transform_msg('map', 'odom', AMCL, stamp + 1)])
    assert foreign_odom_parents(other, 'odom', {stamp: ours}, 'map') == ['map']
    assert foreign_odom_parents(tf_message([transform_msg('world', '/odom', ours, stamp)]),
                                'odom', {stamp: ours}, 'map') == ['world']
    kept, removed = without_odom_parent(msg, 'odom')
    assert removed == 1 and [t.child_frame_id for t in kept.transforms] == ['base_link']


def _nav2_bag(path: Path) -> int:
    """A Nav2-like bag: /odom at 10 Hz, /tf with odom -> base_link and AMCL's map -> odom
    (at 5 Hz, in the same messages as odom -> base_link half of the time)."""
    stamps, _, odom = _scenario(laps=0.5)
    n_amcl = 0
    with BagWriter(path) as bag:
        for k, (s, T) in enumerate(zip(stamps, odom)):
            s = int(s)
            bag.write('/odom', ODOMETRY, odometry_msg(T, s), s)
            tfs = [transform_msg('odom', 'base_link', T, s)]
            if k % 2 == 0:
                tfs.append(transform_msg('map', 'odom', AMCL, s))
                n_amcl += 1
            bag.write('/tf', 'tf2_msgs/msg/TFMessage', tf_message(tfs), s)
            if k % 4 == 1:   # a message of AMCL alone
                bag.write('/tf', 'tf2_msgs/msg/TFMessage',
                          tf_message([transform_msg('map', 'odom', AMCL, s)]), s)
                n_amcl += 1
    return n_amcl


def test_replay_writes_one_map_to_odom_at_a_fixed_period_and_drops_amcls(tmp_path: Path):
    from ga_ros.replay.pipeline import replay

    n_amcl = _nav2_bag(tmp_path / 'in')
    r = replay(tmp_path / 'in', tmp_path / 'out', _config('/odom'))
    assert r.error is None and r.n_tracks >= 1
    with BagReader(tmp_path / 'in') as bag:
        odom_logs = [m.log_ns for m in bag.messages(['/odom'])]
    with BagReader(tmp_path / 'out' / 'replay_bag') as bag:
        tf = [(m.log_ns, t) for m in bag.messages(['/tf']) for t in m.msg.transforms]
    to_odom = [(log, t) for log, t in tf if t.child_frame_id == 'odom']
    assert to_odom and all(t.header.frame_id == 'map' for _, t in to_odom)
    p = np.array([[t.transform.translation.x, t.transform.translation.y] for _, t in to_odom])
    assert not np.any(np.all(np.isclose(p, AMCL[:2, 3]), axis=1))   # none of AMCL's
    logs = np.array([log for log, _ in to_odom])
    # every 50 ms of the bag from the first odometry message (the identity until the first
    # measurement places the map at the first keyframe) to the last sample, and one at the end
    assert np.all(np.diff(logs[:-1]) == 50_000_000)
    assert logs[0] == odom_logs[0] and odom_logs[-1] - logs[-2] < 50_000_000
    assert len(logs) - 1 == (logs[-2] - logs[0]) // 50_000_000 + 1
    # odom -> base_link is copied, every one
    assert sum(t.child_frame_id == 'base_link' for _, t in tf) == len(odom_logs)
    frames = json.loads((tmp_path / 'out' / 'summary.json').read_text())['frames']
    assert frames['input_tf_to_odom_not_copied'] == n_amcl
    assert any('not copied' in w for w in frames['warnings'])
    # the last one is the final correction: with the odometry pose of the newest keyframe it
    # gives that keyframe's corrected pose
    assert r.corrected is not None


@pytest.mark.ros
def test_alignment_node_stops_publishing_when_another_node_owns_odom():
    rclpy = pytest.importorskip('rclpy')
    pytest.importorskip('tf2_msgs.msg')
    from rclpy.parameter import Parameter
    from std_srvs.srv import Trigger
    from test_node_inputs import INPUT_PARAMS, odom_msgs
    from tf2_msgs.msg import TFMessage

    from ga_ros.ros import conversions as conv
    from ga_ros.ros.alignment_node import TF_CONTEST_HOLD_SEC, AlignmentNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(67))
    params = {**INPUT_PARAMS, 'diagnostics_period_sec': 0.0, 'transform_publish_period_sec': 0.0,
              'allow_finish_track': True}  # the test ends the track by the service
    node = AlignmentNode(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                           for k, v in params.items()])
    sent, diags = [], []
    node.pub_tf.publish = sent.append
    node.pub_diag.publish = diags.append
    try:
        for msg in odom_msgs(60):
            node._on_input('odom0', msg)
        node._srv_finish_track(Trigger.Request(), Trigger.Response())
        node._publish_tf()
        assert sent, 'map -> odom published'
        ours = sent[-1]
        node._on_tf(ours)                       # our own message heard back: not foreign
        assert node.tf_contested_by == ''
        n = len(sent)
        amcl = TFMessage(transforms=[conv.transform_msg('map', 'odom', AMCL, 10**9)])
        node._on_tf(amcl)
        assert node.tf_contested_by == 'map'
        node._publish_tf()
        assert len(sent) == n                   # ours not published any more
        d = conv.diagnostics_to_dict(diags[-1])
        assert d['tf_contested_by'] == 'map'
        assert diags[-1].status[0].level in (b'\x01', 1)           # WARN
        assert 'another node publishes map -> odom' in diags[-1].status[0].message
        # publish anyway when told
        node.settings = replace(node.settings, publish_tf_when_contested=True)
        node._publish_tf()
        assert len(sent) == n + 1
        # without: ours again once the other has been silent for TF_CONTEST_HOLD_SEC
        node.settings = replace(node.settings, publish_tf_when_contested=False)
        node._foreign_tf = ('map', time.monotonic() - TF_CONTEST_HOLD_SEC - 0.1)
        assert node.tf_contested_by == ''
        node._publish_tf()
        assert len(sent) == n + 2
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


@pytest.mark.ros
@pytest.mark.slow
def test_live_node_beside_a_played_nav2_bag_does_not_fight_amcl(tmp_path: Path):
    """``alignment_node`` on ``/odom`` while ``ga-ros play`` plays a Nav2-like bag whose ``/tf``
    carries AMCL's ``map -> odom``: the node warns in /diagnostics and stops sending its own."""
    pytest.importorskip('rclpy')
    pytest.importorskip('tf2_msgs.msg')
    import subprocess
    import sys

    from diagnostic_msgs.msg import DiagnosticArray
    from tf2_msgs.msg import TFMessage

    from ga_ros.ros.harness import NodeClient, start_node_process, stop_process
    from ga_ros.ros.qos import stream_qos

    _nav2_bag(tmp_path / 'nav2')
    domain = domain_id(79)
    node = start_node_process(domain, {
        'inputs': 'odom0', 'odom0.topic': '/odom', 'odom0.track.mode': 'distance',
        'odom0.track.length_m': 5.0, 'publish_markers': False, 'autosave': False,
        'diagnostics_period_sec': 0.2}, log_path=tmp_path / 'node.log')
    play = None
    try:
        with NodeClient(domain) as client:
            tf = client.record(TFMessage, '/tf', stream_qos(1000))
            diags = client.record(DiagnosticArray, '/diagnostics', stream_qos(1000))
            client.spin_until(lambda: bool(diags), 60.0, 'the node up')
            env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
            play = subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.play',
                                     str(tmp_path / 'nav2'), '--rate', '2', '--no-clock'],
                                    env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    text=True)
            client.spin_until(lambda: play.poll() is not None, 120.0, 'the bag played')
            warned = [st for m in diags for st in m.status
                      if any(kv.key == 'tf_contested_by' for kv in st.values)]
            assert warned, (tmp_path / 'node.log').read_text()[-2000:]
            assert warned[-1].level in (b'\x01', 1) and 'map -> odom' in warned[-1].message
            to_odom = [t for m in tf for t in m.transforms if t.child_frame_id == 'odom']
            amcl = [t for t in to_odom if abs(t.transform.translation.x - 7.4) < 1e-9]
            ours = [t for t in to_odom if abs(t.transform.translation.x - 7.4) >= 1e-9]
            assert amcl
            # 15 s of bag at 20 Hz would be 300 of ours; at most those before AMCL was heard
            assert len(ours) < 40, len(ours)
    finally:
        if play is not None and play.poll() is None:
            play.kill()
        stop_process(node)
