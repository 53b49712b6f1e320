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
