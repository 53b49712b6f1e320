"""``~/reset`` under running standard inputs: the session starts a fresh survey
(:meth:`AlignmentSession.reset`), the inputs a fresh keyframe chain at their next sample,
numbered from 0 on track 0 (:meth:`InputFrontEnd.new_survey`), and ``map -> odom`` is placed
again as at a start (:meth:`MapToOdom.new_map`): nothing refers to the former keyframes."""

from __future__ import annotations

import numpy as np
from bag_fixtures import odometry_msg
from test_restart_bridge import _drive, _Node

from ga_ros.geometry import se3
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.pipeline.inputs import InputFrontEnd, InputSpec
from ga_ros.pipeline.keyframe_camera import KeyframeCamera


def _reset(node: _Node) -> None:
    """What the node's ``~/reset`` does (ROS-free)."""
    node.session.reset()
    node.front.new_survey()
    node.odom.new_map()


def test_a_reset_under_running_odometry_starts_a_fresh_survey_at_the_next_sample(tmp_path
                                                                                 ) -> None:
    """12 nodes driven, ``map -> odom`` placed by the aligner, then a reset while the odometry
    runs on. The fresh survey's first node is the next sample's keyframe, node 0 on track 0,
    at the map origin (``datum: first_node``); the nodes after it lie on the odometry moved by
    ``inv(T_odom_first)``, which ``map -> odom`` becomes at the first update (the identity
    until then, as at a start). Nothing is held, bridged or rejected. Before, the fresh
    survey started at the former keyframe 11 (its sample before the reset), on track 1, and
    ``map -> odom`` kept the former survey's placement. A restart on the state then saved
    continues the new survey (not taken for another one)."""
    drive = _drive(400)
    state = tmp_path / 'state'
    node = _Node(state)
    for T, stamp in drive[:120]:
        node.sample(T, stamp)
    assert node.session.n_nodes() == 12 and node.odom.placed_by == 'aligner'
    _reset(node)
    assert node.session.n_nodes() == 0 and node.odom.placed_by == 'identity'
    np.testing.assert_array_equal(node.odom.T_map_odom, np.eye(4))
    for T, stamp in drive[120:260]:
        node.sample(T, stamp)
    node.session.finish_track()
    s = node.session
    assert s.counts.rejected == {} and s.counts.bridges == 0 and s.gaps.n_unjoined == 0
    assert not s.gaps.held and not node.warnings
    cp = s.aligner.corrected_path()
    assert [int(i) for i in cp.node_ids] == list(range(14))
    assert int(cp.track_ids[0]) == 0
    assert node.front.keyframe_stamp(0) == drive[120][1]
    T_map_odom = se3.inverse(drive[120][0])   # the first new keyframe is the map origin
    for node_id, T_map in zip(cp.node_ids, cp.T_world_node):
        np.testing.assert_allclose(T_map, T_map_odom @ node.front.keyframe_pose(int(node_id)),
                                   atol=1e-6)
    node.odom.update(cp.node_ids, cp.T_world_node)
    assert node.odom.placed_by == 'aligner' and node.odom.jumps_warned == 0
    np.testing.assert_allclose(node.odom.T_map_odom, T_map_odom, atol=1e-6)
    # the state files hold the new survey: a restart continues it
    node.crash()
    again = _Node(state)
    assert again.session.n_nodes() == 14
    for T, stamp in drive[280:360]:
        again.sample(T, stamp)
    again.session.finish_track()
    assert again.session.previous_survey is None and again.session.restart_bridge == 'measured'
    cp = again.session.aligner.corrected_path()
    assert [int(i) for i in cp.node_ids] == list(range(len(cp.node_ids)))
    assert len(cp.node_ids) > 14


def test_a_front_end_started_afresh_forgets_its_former_keyframes() -> None:
    """:meth:`InputFrontEnd.new_survey` after samples: the next sample of the first input is
    keyframe ``first_node_id`` on track 0 with no motion from before; the further input's
    waiting intervals and the camera's keyframes are dropped; the further input measures the
    new chain's intervals. Before any sample it only undoes a restored state's numbering."""
    specs = [InputSpec('/a', 'odometry', OdometryInputConfig('odom0', keyframe_travel_m=1.0,
                                                             first_node_id=3)),
             InputSpec('/b', 'odometry', OdometryInputConfig('odom1'))]
    front = InputFrontEnd(specs, camera=KeyframeCamera())
    front.continue_from(30, 5)
    front.new_survey()
    assert front.inputs['odom0'].keyframe_ids == (3, 3)
    drive = _drive(120)
    for T, stamp in drive[:40]:
        front.sample('odom0', odometry_msg(T, stamp))
    assert front.inputs['odom1'].stats.pending == 3
    assert front.camera is not None and len(front.camera._waiting) == 4
    front.new_survey()
    assert front.inputs['odom1'].stats.pending == 0 and not front.camera._waiting
    out = []
    for k, (T, stamp) in enumerate(drive[40:80]):
        step = front.sample('odom0', odometry_msg(T, stamp))
        if k == 0:
            assert step.node_stamps == {3: stamp} and not step.measurements
        out += step.measurements
        out += front.sample('odom1', odometry_msg(T, stamp - 1)).measurements
    pairs = {(m.source, m.src_id, m.dst_id, m.src_track, m.dst_track) for m in out}
    assert pairs == {(name, 3 + k, 4 + k, 0, 0) for name in ('odom0', 'odom1')
                     for k in range(3)}
    assert [kf.node_id for kf in front.camera._waiting] == [3, 4, 5, 6]
