"""REP 103/105 frames: the camera extrinsic (ga_ros.core.extrinsic) and a forward-looking
optical camera whose extrinsic is in ``/tf_static``, in the replay and in ``vo_node``."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from ga_ros.core.extrinsic import (
    FROM_PARAMETERS,
    FROM_TF,
    IDENTITY_ASSUMED,
    R_BODY_OPTICAL,
    ExtrinsicConfig,
    TransformTree,
    extrinsic_from_parameters,
    motion_to_base,
    pose_to_base,
)
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError, UnknownExtrinsicError
from ga_ros.geometry import se3, so3

#: The camera 0.4 m ahead of and 1.2 m above base_link, looking forward (optical frame).
CAM_XYZ = np.array([0.4, 0.0, 1.2])
T_BASE_CAM = se3.from_rt(R_BODY_OPTICAL, CAM_XYZ)


def _random_cov(rng: np.random.Generator) -> np.ndarray:
    A = rng.normal(size=(6, 6)) * np.array([0.05, 0.05, 0.05, 0.01, 0.01, 0.01])
    return A @ A.T + np.eye(6) * 1e-6


# --------------------------------------------------------------------------- extrinsic
def test_motion_to_base_moves_the_base_as_the_rigidly_attached_camera(rng):
    T_w_b1 = se3.exp(rng.normal(size=6))
    T_b1_b2 = se3.exp(rng.normal(size=6) * 0.5)
    # the camera poses of two base poses, then the camera's motion between them
    T_w_c1, T_w_c2 = T_w_b1 @ T_BASE_CAM, T_w_b1 @ T_b1_b2 @ T_BASE_CAM
    m = Measurement.from_pose(3, 4, 0, 0, se3.inverse(T_w_c1) @ T_w_c2, _random_cov(rng), 7)
    mb = motion_to_base(m, T_BASE_CAM)
    np.testing.assert_allclose(mb.T_src_dst, T_b1_b2, atol=1e-10)
    assert (mb.src_id, mb.dst_id, mb.stamp_ns, mb.kind) == (3, 4, 7, 'consecutive')


def test_base_covariance_matches_monte_carlo_of_the_camera_perturbation(rng):
    """Perturb the camera motion on the right, map each sample to the base motion, measure
    the base perturbation with log: its sample covariance is the converted covariance."""
    T_c = se3.exp(rng.normal(size=6) * 0.3)
    cov_c = _random_cov(rng)
    m = Measurement.from_pose(0, 1, 0, 0, T_c, cov_c)
    mb = motion_to_base(m, T_BASE_CAM)
    xi = rng.multivariate_normal(np.zeros(6), cov_c, size=20000)
    T_b_samples = T_BASE_CAM @ (T_c @ se3.exp(xi)) @ se3.inverse(T_BASE_CAM)
    xi_b = se3.log(se3.inverse(mb.T_src_dst) @ T_b_samples)
    emp = np.cov(xi_b.T)
    # NEES of the base perturbations against the converted covariance: 6 on average
    nees = np.einsum('ni,ij,nj->n', xi_b, np.linalg.inv(mb.cov), xi_b)
    assert nees.mean() == pytest.approx(6.0, rel=0.05)
    np.testing.assert_allclose(emp, mb.cov, atol=0.05 * np.abs(mb.cov).max())
    np.testing.assert_allclose(mb.cov, mb.cov.T)
    assert np.linalg.eigvalsh(mb.cov).min() > 0


def test_pose_to_base_of_a_forward_camera_is_rep_103():
    """The optical camera moving 5 m along its z: the base moves 5 m along x."""
    T_w_c = se3.from_rt(np.eye(3), np.array([0.0, 0.0, 5.0]))
    T_odom_base = pose_to_base(T_w_c, T_BASE_CAM)
    np.testing.assert_allclose(T_odom_base, se3.from_rt(np.eye(3), [5.0, 0.0, 0.0]),
                               atol=1e-12)


def test_parameters_rpy_and_quaternion_agree_with_tf2_conventions():
    # REP 103 camera_link -> optical frame: rpy (-pi/2, 0, -pi/2)
    T = extrinsic_from_parameters(CAM_XYZ, rpy=(-np.pi / 2, 0.0, -np.pi / 2))
    np.testing.assert_allclose(T, T_BASE_CAM, atol=1e-12)
    q = se3.quat_from_matrix(R_BODY_OPTICAL)
    np.testing.assert_allclose(extrinsic_from_parameters(CAM_XYZ, quat_xyzw=q), T_BASE_CAM,
                               atol=1e-12)
    # yaw alone turns x into y (right-handed, about z)
    Ty = extrinsic_from_parameters((0, 0, 0), rpy=(0, 0, np.pi / 2))
    np.testing.assert_allclose(Ty[:3, :3] @ [1, 0, 0], [0, 1, 0], atol=1e-12)
    with pytest.raises(InputError):
        extrinsic_from_parameters((0, 0), rpy=(0, 0, 0))
    with pytest.raises(InputError):
        extrinsic_from_parameters((0, 0, 0))


def test_transform_tree_composes_a_chain_and_the_config_resolves_in_order(rng):
    tree = TransformTree()
    T_base_link = se3.exp(rng.normal(size=6))
    tree.add('base_link', 'camera_link', T_base_link)
    tree.add('/camera_link', 'camera_optical', se3.from_rt(R_BODY_OPTICAL, np.zeros(3)))
    tree.add('odom', 'base_link', se3.exp(rng.normal(size=6)))
    T = tree.lookup('base_link', 'camera_optical')
    np.testing.assert_allclose(T, T_base_link @ se3.from_rt(R_BODY_OPTICAL, np.zeros(3)),
                               atol=1e-12)
    np.testing.assert_allclose(tree.lookup('camera_optical', 'base_link'), se3.inverse(T),
                               atol=1e-12)
    assert tree.lookup('base_link', 'elsewhere') is None
    cfg = ExtrinsicConfig(T_base_camera='0.4 0 1.2 -1.5707963267948966 0 -1.5707963267948966')
    assert cfg.resolve(T, 'camera_optical').source == FROM_TF
    from_params = cfg.resolve(None, 'camera_optical')
    assert from_params.source == FROM_PARAMETERS
    np.testing.assert_allclose(from_params.T_base_cam, T_BASE_CAM, atol=1e-12)
    assert ExtrinsicConfig(assume_identity_extrinsic=True).resolve(None).source == (
        IDENTITY_ASSUMED)
    with pytest.raises(UnknownExtrinsicError) as refused:   # identity only when said so
        ExtrinsicConfig().resolve(None, 'cam')
    assert all(w in str(refused.value) for w in ('publish base_link -> cam on /tf_static',
                                                  'set T_base_camera',
                                                  'assume_identity_extrinsic: true'))
    with pytest.raises(InputError):
        ExtrinsicConfig(T_base_camera='1 2 3').resolve(None)


# --------------------------------------------------------------------------- forward camera
def _forward_drive(n: int = 61, step_m: float = 1.0):
    """A camera looking along its z and moving along it ``step_m`` per frame (the simulator's
    nadir camera descending over its terrain; the robot frames are ours)."""
    from ga_ros.sim.stereo import StereoRig, Survey, make_scene, nadir_rotation

    T = np.array([se3.from_rt(nadir_rotation(0.0), np.array([0.0, 0.0, 200.0 - k * step_m]))
                  for k in range(n)])
    survey = Survey(T, (np.arange(n) * 50_000_000).astype(np.int64), np.zeros(n, int),
                    np.zeros(n, int), np.zeros(n, bool))
    rig = StereoRig.for_size(320, 240)
    return survey, rig, make_scene(survey, rig, seed=1)


def _write_forward_bag(path: Path, with_tf_static: bool) -> Path:
    from bag_fixtures import SAMPLE_STEREO_TOPICS, stereo_rows, write_rows, write_tf_static

    from ga_ros.io.bag_writer import BagWriter
    from ga_ros.replay.samples import BASE_STAMP_NS

    survey, rig, scene = _forward_drive()
    rng = np.random.default_rng(5)
    with BagWriter(path) as bag:
        t0 = int(BASE_STAMP_NS)
        if with_tf_static:   # as robot_state_publisher: base_link -> camera_link -> optical
            write_tf_static(bag, [
                ('base_link', 'camera_link', se3.from_rt(np.eye(3), CAM_XYZ)),
                ('camera_link', 'camera_optical', se3.from_rt(R_BODY_OPTICAL, np.zeros(3)))], t0)
        for T, s in zip(survey.T_world_cam, survey.stamps_ns):
            s = int(s) + t0 + 1
            left, right = scene.render_pair(T, rng)
            write_rows(bag, stereo_rows(rig, left, right, s, topics=SAMPLE_STEREO_TOPICS,
                                        frames=('camera_optical', 'camera_right'), quality=90))
    return path


@pytest.mark.slow
def test_replay_of_a_forward_camera_with_tf_static_drives_along_map_x(tmp_path, capsys):
    from ga_ros.pipeline.stereo import FrontEndConfig
    from ga_ros.replay.config import ReplayConfig
    from ga_ros.replay.pipeline import replay

    bag = _write_forward_bag(tmp_path / 'fwd', with_tf_static=True)
    r = replay(bag, tmp_path / 'out', ReplayConfig(plot=False))
    p = r.corrected.T_world_node[:, :3, 3]
    assert len(p) >= 3
    # 60 m forward: along +x of map, z ~ 0 (the camera's optical z is the robot's x); each
    # keyframe where the drive was at its stamp (1 m per 50 ms frame)
    from ga_ros.replay.samples import BASE_STAMP_NS

    travelled = (r.corrected.stamps_ns - BASE_STAMP_NS - 1) / 50_000_000 * 1.0
    assert travelled[-1] > 50.0
    np.testing.assert_allclose(p[:, 0], travelled, atol=0.03 * 60.0)
    assert np.abs(p[:, 1]).max() < 1.5 and np.abs(p[:, 2]).max() < 1.5
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    ext = summary['frames']['camera_extrinsic']
    assert ext['source'] == FROM_TF and ext['camera_frame'] == 'camera_optical'
    np.testing.assert_allclose(ext['T_base_camera'], T_BASE_CAM, atol=1e-9)
    assert summary['frames']['warnings'] == []

    # without /tf_static: refused before any work (exit 1 with the ways to give it) ...
    from ga_ros.cli.main import main

    bag2 = _write_forward_bag(tmp_path / 'fwd2', with_tf_static=False)
    args = ['replay', str(bag2), '--no-plot', '--no-progress']
    assert main([*args, '--out', str(tmp_path / 'refused')]) == 1
    err = capsys.readouterr().err
    assert 'camera extrinsic unknown' in err and 'base_link -> camera_optical' in err
    assert '--vo T_base_camera' in err and '--vo assume_identity_extrinsic=true' in err
    assert not (tmp_path / 'refused').exists()
    # ... and when said so, the identity: the same numbers in the camera's frame
    assert main([*args, '--out', str(tmp_path / 'out2'), '--vo',
                 'assume_identity_extrinsic=true']) == 0
    frames = json.loads((tmp_path / 'out2' / 'summary.json').read_text())['frames']
    assert frames['camera_extrinsic']['source'] == IDENTITY_ASSUMED
    r2 = replay(bag2, tmp_path / 'out3', ReplayConfig(plot=False, vo=FrontEndConfig(
        extrinsic=ExtrinsicConfig(assume_identity_extrinsic=True))))
    assert r2.corrected.T_world_node[-1, 2, 3] > 50.0   # optical z
    np.testing.assert_allclose(r2.corrected.T_world_node[:, [2, 0, 1], 3] * [1, -1, -1],
                               p, atol=0.05)   # the same motion, seen from base_link


@pytest.mark.ros
@pytest.mark.slow
def test_vo_node_with_tf_static_publishes_base_link_motion_and_odometry():
    rclpy = pytest.importorskip('rclpy')
    from rclpy.parameter import Parameter
    from tf2_msgs.msg import TFMessage

    from ga_ros.ros import conversions as conv
    from ga_ros.ros.harness import domain_id
    from ga_ros.ros.vo_node import VoNode, array_to_image

    survey, rig, scene = _forward_drive()
    rng = np.random.default_rng(5)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(57))
    node = VoNode(context=ctx, parameter_overrides=[Parameter('pair_queue', value=1000),
                                                    Parameter('cross_track', value=False)])
    sent, odom, tf = [], [], []
    node.pub_meas.publish = sent.append
    node.pub_odom.publish = odom.append
    node.pub_tf.publish = tf.append
    try:
        node._on_tf_static(TFMessage(transforms=[
            conv.transform_msg('base_link', 'camera_optical', T_BASE_CAM, 0)]))
        info = conv.ns_to_stamp(0)
        for side, Tx in (('left', 0.0), ('right', -rig.focal_px * rig.baseline_m)):
            from sensor_msgs.msg import CameraInfo

            msg = CameraInfo(width=rig.width, height=rig.height, distortion_model='plumb_bob')
            msg.header.stamp = info
            msg.d = [0.0] * 5
            msg.k = rig.K.ravel().tolist()
            msg.r = np.eye(3).ravel().tolist()
            msg.p = np.hstack([rig.K, [[Tx], [0.0], [0.0]]]).ravel().tolist()
            node._on_info(msg, side)
        for T, s in zip(survey.T_world_cam, survey.stamps_ns):
            left, right = scene.render_pair(T, rng)
            node._on_image(array_to_image(left, int(s) + 1, 'camera_optical'), 'left')
            node._on_image(array_to_image(right, int(s) + 1, 'camera_right'), 'right')
        assert node.wait_idle(120.0)
        meas = [conv.odometry_to_measurement(m) for m in sent]
        assert len(meas) >= 2
        T_end = se3.integrate(np.eye(4), np.array([m.T_src_dst for m in meas]))[-1]
        assert T_end[0, 3] > 50.0
        assert abs(T_end[1, 3]) < 1.5 and abs(T_end[2, 3]) < 1.5
        last = odom[-1]
        assert (last.header.frame_id, last.child_frame_id) == ('odom', 'base_link')
        assert last.pose.pose.position.x == pytest.approx(60.0, rel=0.05)
        t = tf[-1].transforms[0]
        assert (t.header.frame_id, t.child_frame_id) == ('odom', 'base_link')
        assert node.diagnostic_values()['camera_extrinsic'] == FROM_TF
        assert node.diagnostic_values()['pairs/lost'] == 0
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def test_so3_hat_is_used_consistently():
    """The optical rotation is proper (det +1) and maps optical z to base x."""
    assert np.linalg.det(R_BODY_OPTICAL) == pytest.approx(1.0)
    np.testing.assert_allclose(R_BODY_OPTICAL @ [0, 0, 1], [1, 0, 0])
    np.testing.assert_allclose(so3.log(R_BODY_OPTICAL @ R_BODY_OPTICAL.T), np.zeros(3),
                               atol=1e-12)


def test_transform_tree_reads_tf_messages_and_skips_broken_transforms(rng):
    """``add_message`` (the one ``/tf_static`` reader): a chain read from messages composes as
    the matrices do; a zero quaternion or a NaN is skipped, not recorded."""
    from types import SimpleNamespace as NS

    def tf(parent: str, child: str, p, q):
        return NS(header=NS(frame_id=parent), child_frame_id=child, transform=NS(
            translation=NS(x=p[0], y=p[1], z=p[2]), rotation=NS(x=q[0], y=q[1], z=q[2],
                                                                 w=q[3])))

    T1, T2 = se3.exp(rng.normal(size=6)), se3.exp(rng.normal(size=6))
    (p1, q1), (p2, q2) = se3.to_pos_quat(T1), se3.to_pos_quat(T2)
    tree = TransformTree()
    n = tree.add_message(NS(transforms=[
        tf('base_link', 'gps_mount', p1, 2.0 * q1), tf('gps_mount', 'gps', p2, q2),
        tf('base_link', 'broken', p1, [0.0, 0.0, 0.0, 0.0]),
        tf('base_link', 'nan', [np.nan, 0.0, 0.0], q1)]))
    assert n == 2 and len(tree) == 2
    np.testing.assert_allclose(tree.lookup('base_link', 'gps'), T1 @ T2, atol=1e-12)
    assert tree.lookup('base_link', 'broken') is None
