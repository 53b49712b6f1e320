"""The alignment node's ``map -> odom`` from the first odometry message (in-process, the same
:class:`~ga_ros.pipeline.map_to_odom.MapToOdom` as the replay): the identity, said in
/diagnostics, until the first AMCL-like fix; then the fixes' placement, before any window
update; header stamps never back."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip('rclpy')
pytest.importorskip('tf2_msgs.msg')

from geometry_msgs.msg import PoseWithCovarianceStamped  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from test_node_inputs import INPUT_PARAMS, odom_msgs  # noqa: E402

from ga_ros.core.encoding import pose_to_matrix  # noqa: E402
from ga_ros.geometry import se3  # noqa: E402
from ga_ros.io.bag import BagReader  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.alignment_node import AlignmentNode  # noqa: E402
from ga_ros.ros.harness import domain_id, ros_context  # noqa: E402

T_MAP_ODOM = se3.from_translation_rotvec(np.array([7.4, 7.5, 0.0]), np.array([0, 0, 0.3]))


def _amcl(T_map_base: np.ndarray, stamp) -> PoseWithCovarianceStamped:
    fix = PoseWithCovarianceStamped()
    fix.header.frame_id = 'map'
    fix.header.stamp = stamp
    p = fix.pose.pose
    p.position.x, p.position.y, p.position.z = (float(v) for v in T_map_base[:3, 3])
    q = se3.quat_from_matrix(T_map_base[:3, :3])
    p.orientation.x, p.orientation.y, p.orientation.z, p.orientation.w = (float(v) for v in q)
    cov = np.zeros(36)
    cov[0] = cov[7] = 0.1 ** 2
    cov[35] = 0.02 ** 2
    fix.pose.covariance = cov.tolist()
    return fix


def _tf(msg) -> tuple[int, np.ndarray]:
    t = msg.transforms[0]
    assert (t.header.frame_id, t.child_frame_id) == ('map', 'odom')
    tr, q = t.transform.translation, t.transform.rotation
    return (conv.stamp_to_ns(t.header.stamp),
            se3.from_pos_quat(np.array([tr.x, tr.y, tr.z]), np.array([q.x, q.y, q.z, q.w])))


def test_node_publishes_identity_then_the_fixes_placement_before_any_update():
    params = {**INPUT_PARAMS, 'diagnostics_period_sec': 0.0, 'transform_publish_period_sec': 0.0,
              'absolutes': 'amcl0', 'amcl0.topic': 'amcl_pose', 'amcl0.type': 'pose_cov',
              'amcl0.track_min_interval_s': 1000.0, 'datum': 'fixes',
              'odom0.track.length_m': 1000.0}
    with ros_context(domain_id(23)) as ctx:
        node = AlignmentNode(context=ctx, parameter_overrides=[
            Parameter(k, value=v) for k, v in params.items()])
        sent, diags = [], []
        node.pub_tf.publish = sent.append
        node.pub_diag.publish = diags.append
        try:
            node._publish_tf()
            assert not sent                     # no odometry yet: nothing to send
            msgs = odom_msgs(40)
            node._on_input('odom0', msgs[0])
            node._publish_tf()
            stamp, T = _tf(sent[-1])            # from the first odometry message: identity
            assert stamp == conv.stamp_to_ns(msgs[0].header.stamp)
            np.testing.assert_allclose(T, np.eye(4))
            node._publish_diagnostics()
            values = conv.diagnostics_to_dict(diags[-1])
            assert 'identity' in values['map_to_odom/placed_by']
            for k, msg in enumerate(msgs[1:], 1):
                node._on_input('odom0', msg)
                if k % 5 == 3:
                    node._on_absolute('amcl0', _amcl(T_MAP_ODOM @ pose_to_matrix(msg.pose.pose),
                                                     msg.header.stamp))
                node._publish_tf()
            assert node.session.counts.updates == 0     # no window update yet
            _, T = _tf(sent[-1])
            T_base = pose_to_matrix(msgs[-1].pose.pose)
            np.testing.assert_allclose((T @ T_base)[:2, 3], (T_MAP_ODOM @ T_base)[:2, 3],
                                       atol=1e-6)
            stamps = [_tf(m)[0] for m in sent]
            assert np.all(np.diff(stamps) >= 0)
            node._publish_diagnostics()
            values = conv.diagnostics_to_dict(diags[-1])
            assert values['map_to_odom/placed_by'] == 'fixes'
            assert int(values['map_to_odom/fixes_used']) >= 6
            assert int(values['map_to_odom/jumps_warned']) == 0
        finally:
            node.destroy_node()


@pytest.mark.slow
def test_live_node_on_a_played_nav2_bag_places_the_map_like_the_replay(tmp_path):
    """``alignment_node`` (a process) on ``/odom`` and ``/amcl_pose`` while ``ga-ros play``
    plays the Nav2-shaped bag of the replay test (its ``/tf`` left out: AMCL is not running):
    ``map -> odom`` is the identity from the first odometry message, within the fixes'
    uncertainty of the truth once the first fix is in, stamps never back, and /diagnostics says
    what placed the map."""
    import os
    import subprocess
    import sys

    from diagnostic_msgs.msg import DiagnosticArray
    from test_map_placement_replay import SIGMA_XY, write_nav2_bag
    from tf2_msgs.msg import TFMessage

    from ga_ros.ros.harness import NodeClient, start_node_process, stop_process
    from ga_ros.ros.qos import stream_qos

    b = write_nav2_bag(tmp_path / 'nav2', 3)
    with BagReader(tmp_path / 'nav2') as bag:
        amcl_stamps = [conv.stamp_to_ns(m.msg.header.stamp) for m in bag.messages(['/amcl_pose'])]
    domain = domain_id(83)
    node = start_node_process(domain, {
        'inputs': 'odom0', 'odom0.topic': '/odom', 'absolutes': 'amcl0',
        'amcl0.topic': '/amcl_pose', 'amcl0.type': 'pose_cov', 'datum': 'fixes',
        'publish_markers': False, 'autosave': False, 'diagnostics_period_sec': 0.2},
        log_path=tmp_path / 'node.log')
    play = None
    try:
        with NodeClient(domain) as client:
            tf = client.record(TFMessage, '/tf', stream_qos(1000))
            diags = client.record(DiagnosticArray, '/diagnostics', stream_qos(1000))
            client.spin_until(lambda: bool(diags), 60.0, 'the node up')
            env = dict(os.environ, ROS_DOMAIN_ID=str(domain))
            play = subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.play',
                                     str(tmp_path / 'nav2'), '--rate', '2', '--no-clock',
                                     '--delay', '2',  # the node's inputs settle their QoS
                                     '--topics', '/odom', '/amcl_pose'],
                                    env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    text=True)
            client.spin_until(lambda: play.poll() is not None, 120.0, 'the bag played')
            log = (tmp_path / 'node.log').read_text()[-2000:]
            ours = [_tf(m) for m in tf if m.transforms[0].child_frame_id == 'odom']
            assert ours, log
            stamps = np.array([s for s, _ in ours])
            T = np.array([t for _, t in ours])
            assert np.all(np.diff(stamps) >= 0), 'a header stamp steps back'
            # from the first odometry messages it takes (the timer's first tick; on a loaded
            # machine a few may come in before it: the in-process test above checks the very
            # first), the identity until the first fix
            assert stamps[0] < b.stamps_ns[0] + 2e9, (stamps[0] - b.stamps_ns[0]) / 1e9
            np.testing.assert_allclose(T[stamps < amcl_stamps[0]], np.tile(np.eye(4), (
                int((stamps < amcl_stamps[0]).sum()), 1, 1)))
            # once the first fix is in: map -> base_link within 3 sigma of the truth until the
            # first window update (10 s of bag later; the aligner's afterwards)
            k = np.searchsorted(b.stamps_ns, stamps)
            assert np.array_equal(b.stamps_ns[k], stamps)    # stamped at an odometry message
            err = np.linalg.norm((T @ b.T_odom[k])[:, :2, 3] - b.T_map_true[k, :2, 3], axis=1)
            placed = (stamps > amcl_stamps[0] + 100_000_000) & (stamps < amcl_stamps[0] + 9e9)
            assert placed.sum() > 50 and err[placed].max() < 3 * SIGMA_XY, err[placed].max()
            assert err[stamps > amcl_stamps[0] + 100_000_000].max() < 1.0
            seen = {conv.diagnostics_to_dict(m).get('map_to_odom/placed_by') for m in diags}
            assert {'fixes', 'aligner'} <= seen, seen
    finally:
        if play is not None and play.poll() is None:
            play.kill()
        stop_process(node)
