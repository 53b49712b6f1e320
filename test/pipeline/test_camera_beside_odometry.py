"""A stereo camera beside a drifting odometry (:mod:`ga_ros.pipeline.keyframe_camera`).

An aerial robot flies a lawnmower (two double swaths, :mod:`ga_ros.sim.stereo`) with its own
odometry at 10 Hz (a heading drift and a 1 % scale error) and a nadir stereo camera at 2 Hz
mounted off the base (a rotation and a lever arm). The bag holds ``/odom``, the compressed
images and their ``CameraInfo``, as a robot records them; the ground truth (base poses) is a
TUM file. The odometry defines the keyframes; the images give cross-track connections
between swaths, which must correct the drift.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import ODOMETRY, odometry_msg, stereo_rows, write_bag

from ga_ros import domains
from ga_ros.geometry import se3
from ga_ros.inputs.odometry import interpolate_pose
from ga_ros.io.trajectory import write_tum

pytest.importorskip('cv2')

#: the left camera's optical frame in the base frame (x forward, z up): looking down, image
#: x to the base's right, 0.4 m ahead of and 0.2 m below the base origin
R_BASE_CAM = np.array([[0.0, -1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])
T_BASE_CAM = se3.from_rt(R_BASE_CAM, np.array([0.4, 0.0, -0.2]))
ODOM_HZ = 10
#: left info, right info, left image, right image
CAMERA_TOPICS = ('/cam/left/camera_info', '/cam/right/camera_info', '/cam/left/image/compressed',
                 '/cam/right/image/compressed')


def write_robot_bag(path: Path, gt_file: Path) -> None:
    from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene

    survey = lawnmower(LawnmowerConfig(n_tracks=2, positions_per_swath=12, turn_positions=8,
                                       seed=5))
    rig = StereoRig.for_size(320, 240)
    scene = make_scene(survey, rig, seed=5)
    rng = np.random.default_rng(5)
    t0 = 1_700_000_000_000_000_000
    T_world_base = survey.T_world_cam @ se3.inverse(T_BASE_CAM)
    # base poses at the odometry rate, interpolated between the frames
    period = int(1e9 / ODOM_HZ)
    stamps = np.arange(0, int(survey.stamps_ns[-1]) + 1, period)
    k = np.clip(np.searchsorted(survey.stamps_ns, stamps, side='right') - 1, 0,
                len(survey.stamps_ns) - 2)
    alpha = (stamps - survey.stamps_ns[k]) / np.diff(survey.stamps_ns)[k]
    gt = np.array([interpolate_pose(T_world_base[i], T_world_base[i + 1], a)
                   for i, a in zip(k, alpha)])
    odom = [np.eye(4)]
    for a, b in zip(gt[:-1], gt[1:]):
        D = se3.relative(a, b)
        D[:3, 3] *= 1.01
        drift = se3.exp(np.array([0, 0, 0, 0, 0, 0.004 / ODOM_HZ]))
        odom.append(odom[-1] @ D @ drift)
    write_tum(gt_file, stamps + t0, gt)
    rows = [(int(s), '/odom', ODOMETRY, odometry_msg(T, int(s)))
            for s, T in zip(stamps + t0, odom)]
    for s, T in zip(survey.stamps_ns + t0, survey.T_world_cam):
        left, right = scene.render_pair(T, rng)
        # the images arrive after the odometry of their time
        rows += stereo_rows(rig, left, right, int(s), topics=CAMERA_TOPICS,
                            frames=('cam_left', 'cam_right'), log_ns=int(s) + 30_000_000)
    write_bag(path, rows)


@pytest.fixture(scope='module')
def robot_bag(tmp_path_factory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp('camera_beside')
    write_robot_bag(tmp / 'in', tmp / 'gt.tum')
    return tmp / 'in', tmp / 'gt.tum'


def test_camera_beside_odometry_makes_cross_track_connections(robot_bag, tmp_path: Path,
                                                             capsys) -> None:
    from ga_ros.cli.main import main

    bag, gt_file = robot_bag
    (tmp_path / 'inputs.yaml').write_text(
        'odom0:\n  keyframe_travel_m: 11.0\n  track:\n    mode: heading\n    swaths: 2\n'
        '  default_noise_percent: 1.0\n  default_depth_m: 110.0\n')
    p, q = se3.to_pos_quat(T_BASE_CAM)
    rc = main(['replay', str(bag), '--odom-topic', '/odom', '--input-config',
               str(tmp_path / 'inputs.yaml'),
               '--left-image', '/cam/left/image/compressed',
               '--right-image', '/cam/right/image/compressed',
               '--left-info', '/cam/left/camera_info', '--right-info', '/cam/right/camera_info',
               '--camera-extrinsic', *map(str, [*p, *q]), '--ground-truth', str(gt_file),
               '--out', str(tmp_path / 'out'), '--no-plot', '--no-progress', '--json'])
    out = capsys.readouterr().out
    assert rc == 0, out
    import json

    res = json.loads(out)
    cam = res['source_stats']['camera']
    assert cam['keyframes_with_image'] >= 0.8 * res['source_stats']['odom0']['keyframes']
    assert cam['cross_accepted'] > 5 and cam['rejected'] == 0, cam
    assert res['rejected'] == {}, res['rejected_examples']
    err = res['errors_vs_ground_truth']
    assert err['ga']['ate_raw_m'] < 0.5 * err['f2f']['ate_raw_m'], (err, cam)


def test_change_frame_against_composition() -> None:
    """The base motion and covariance from a camera motion, against composing sampled
    perturbations (Monte-Carlo of the right perturbation through the extrinsic)."""
    rng = np.random.default_rng(0)
    T_ca_cb = se3.exp(np.array([1.0, -2.0, 0.5, 0.1, -0.2, 0.3]))
    L = rng.normal(0, 0.02, (6, 6))
    C = L @ L.T + 1e-4 * np.eye(6)
    T_b, C_b = se3.change_frame(T_ca_cb, C, T_BASE_CAM)
    np.testing.assert_allclose(T_b, T_BASE_CAM @ T_ca_cb @ se3.inverse(T_BASE_CAM), atol=1e-12)
    d = rng.multivariate_normal(np.zeros(6), C, 20000)
    samples = T_BASE_CAM @ (T_ca_cb @ se3.exp(d)) @ se3.inverse(T_BASE_CAM)
    e = se3.log(se3.inverse(T_b) @ samples)
    np.testing.assert_allclose(np.cov(e.T), C_b, atol=3e-5 + 0.05 * np.abs(C_b).max())


def test_alignment_node_with_a_camera_beside_its_odometry(robot_bag) -> None:
    """The node with ``inputs: odom0`` and ``camera.*`` topics, fed the bag's messages by its
    callbacks (in-process): cross-track connections are made and accepted."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.parameter import Parameter

    from ga_ros.io.bag import BagReader
    from ga_ros.ros.alignment_node import AlignmentNode

    bag, _ = robot_bag
    p, q = se3.to_pos_quat(T_BASE_CAM)
    params = {'inputs': 'odom0', 'odom0.topic': 'odom', 'odom0.keyframe_travel_m': 11.0,
              'odom0.track.mode': 'heading', 'odom0.default_noise_percent': 1.0,
              'odom0.default_depth_m': 110.0,
              'camera.left_image_topic': 'cam/left/image/compressed',
              'camera.right_image_topic': 'cam/right/image/compressed',
              'camera.left_info_topic': 'cam/left/camera_info',
              'camera.right_info_topic': 'cam/right/camera_info', 'camera.compressed': True,
              'camera.T_base_camera': ' '.join(str(float(v)) for v in (*p, *q)),
              'camera.source': 'down_cam',
              'publish_markers': False, 'diagnostics_period_sec': 0.0,
              'transform_publish_period_sec': 0.0}
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domains.domain_id('camera_beside_odometry'))
    node = AlignmentNode(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                           for k, v in params.items()])
    try:
        subs = {s.topic_name for s in node.subscriptions}
        assert {'/cam/left/image/compressed', '/cam/right/camera_info'} <= subs
        processed: list = []   # the measurements the node steps (kind, source)
        step = node._process
        node._process = lambda m, msg: processed.append((m.kind, m.source)) or step(m, msg)
        with BagReader(bag) as reader:
            for bm in reader.messages(None):
                side = 'left' if '/left/' in bm.topic else 'right'
                if bm.topic == '/odom':
                    node._on_input('odom0', bm.msg)
                elif bm.topic.endswith('camera_info'):
                    node._on_camera_info(side, bm.msg)
                else:
                    node._on_camera_image(side, bm.msg)
        cam = node.front.stats()['camera']
        assert cam['cross_accepted'] > 5 and cam['rejected'] == 0, cam
        assert sum(node.session.counts.rejected.values()) == 0
        assert node.session.counts.accepted == (node.front.inputs['odom0'].stats.measurements
                                                + cam['cross_accepted'])
        # the camera's connections carry its name (parameter camera.source)
        assert set(processed) == {('consecutive', 'odom0'), ('cross', 'down_cam')}, processed
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_camera_extrinsic_is_identity_only_when_said_so() -> None:
    """Without ``camera.T_base_camera`` / ``--camera-extrinsic`` the node and the replay refuse
    with one line naming the ways to give it; the old parameter name says the new one; the node
    takes the parameter as the same pose the replay takes from its seven numbers."""
    rclpy = pytest.importorskip('rclpy')
    from rclpy.parameter import Parameter

    from ga_ros.cli.commands.replay import camera_extrinsic
    from ga_ros.errors import InputError
    from ga_ros.ros.alignment_node import AlignmentNode

    with pytest.raises(InputError, match='--camera-extrinsic identity'):
        camera_extrinsic(None)
    assert camera_extrinsic(['identity']) == (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    with pytest.raises(InputError, match='X Y Z QX QY QZ QW'):
        camera_extrinsic(['1', '2', '3'])
    p, q = se3.to_pos_quat(T_BASE_CAM)
    text = ' '.join(str(float(v)) for v in (*p, *q))
    base = {'inputs': 'odom0', 'odom0.topic': 'odom', 'publish_markers': False,
            'diagnostics_period_sec': 0.0, 'transform_publish_period_sec': 0.0,
            **{f'camera.{side}_{kind}_topic': f'cam/{side}/{kind}'
               for side in ('left', 'right') for kind in ('image', 'info')}}
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domains.domain_id('camera_beside_odometry 7'))
    try:
        for extra, match in (({}, 'camera.T_base_camera'),
                             ({'camera.base_to_camera': [0.0] * 6 + [1.0]},
                              'camera.base_to_camera is now camera.T_base_camera')):
            with pytest.raises(InputError, match=match) as err:
                AlignmentNode(context=ctx, parameter_overrides=[
                    Parameter(k, value=v) for k, v in {**base, **extra}.items()])
            assert '\n' not in str(err.value)
        for extra, T in (({'camera.T_base_camera': text}, T_BASE_CAM),
                         ({'camera.assume_identity_extrinsic': True}, np.eye(4))):
            node = AlignmentNode(context=ctx, parameter_overrides=[
                Parameter(k, value=v) for k, v in {**base, **extra}.items()])
            try:
                np.testing.assert_allclose(node.front.camera.config.T_base_cam, T, atol=1e-9)
            finally:
                node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)
