"""Live end of input: when the images stop, ``vo_node`` ends the track and the alignment node
adjusts it without a service call (both nodes in-process, messages handed over directly)."""

from __future__ import annotations

import time

import pytest

rclpy = pytest.importorskip('rclpy')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from test_vo_node import camera_info  # noqa: E402

from ga_ros import topics  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import domain_id  # noqa: E402
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene  # noqa: E402


@pytest.mark.ros
@pytest.mark.slow
def test_images_stop_then_the_last_track_is_adjusted(rng):
    from ga_ros.ros.alignment_node import AlignmentNode
    from ga_ros.ros.vo_node import VoNode, array_to_image

    rig = StereoRig()
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=12, seed=9))
    scene = make_scene(survey, rig, seed=9)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(63))
    vo = VoNode(context=ctx, parameter_overrides=[
        Parameter('idle_end_track_s', value=0.5), Parameter('pair_queue', value=100),
        Parameter('cross_track', value=False), Parameter('assume_identity_extrinsic',
                                                         value=True)])
    align = AlignmentNode(context=ctx, parameter_overrides=[
        Parameter('publish_markers', value=False), Parameter('autosave', value=False)])
    sent = []

    def forward(msg):   # vo_node -> alignment_node, in order
        sent.append(msg)
        align._on_measurement(msg)

    vo.pub_meas.publish = forward
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(vo)
    try:
        vo._on_info(camera_info(rig, False, 0), 'left')
        vo._on_info(camera_info(rig, True, 0), 'right')
        for i in range(12):
            left, right = scene.render_pair(survey.T_world_cam[i], rng)
            stamp = int(survey.stamps_ns[i])
            vo._on_image(array_to_image(left, stamp, 'l'), 'left')
            vo._on_image(array_to_image(right, stamp, 'r'), 'right')
        assert vo.wait_idle(60.0)
        n_meas = len(sent)
        assert n_meas >= 2 and align.aligner.open_track is not None
        assert align.session.n_nodes() == n_meas + 1
        # silence: the timer of vo_node ends the track
        t_end = time.monotonic() + patience(10.0)
        while time.monotonic() < t_end and vo.counts['idle_track_ends'] == 0:
            executor.spin_once(timeout_sec=0.1)
        assert vo.counts['idle_track_ends'] == 1
        assert len(sent) == n_meas + 1 and sent[-1].child_frame_id == topics.TRACK_END_FRAME
        # the alignment node adjusted the last track at once
        assert align.aligner.open_track is None
        assert align.session.last_update is not None
        cp = align.aligner.corrected_path()
        assert len(cp.node_ids) == n_meas + 1
        # no second end while nothing new came
        for _ in range(10):
            executor.spin_once(timeout_sec=0.1)
        assert vo.counts['idle_track_ends'] == 1
        # images again: a new track, accepted by the alignment node
        track0 = conv.odometry_to_measurement(sent[0]).dst_track
        for i in range(12):
            left, right = scene.render_pair(survey.T_world_cam[11 - i], rng)
            stamp = int(survey.stamps_ns[-1]) + (i + 1) * 10**8
            vo._on_image(array_to_image(left, stamp, 'l'), 'left')
            vo._on_image(array_to_image(right, stamp, 'r'), 'right')
        assert vo.wait_idle(60.0)
        later = [conv.odometry_to_measurement(m) for m in sent[n_meas + 1:]]
        assert later and all(m.dst_track > track0 for m in later)
        assert sum(align.session.counts.rejected.values()) == 0
    finally:
        executor.remove_node(vo)
        vo.destroy_node()
        align.destroy_node()
        rclpy.try_shutdown(context=ctx)
