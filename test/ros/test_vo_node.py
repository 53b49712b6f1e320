"""vo_node: message conversions in-process, and a two-process test that feeds simulated stereo
images to ``python -m ga_ros.ros.vo_node`` and receives its measurements."""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, fields
from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml

pytest.importorskip('rclpy')

import rclpy  # noqa: E402
from nav_msgs.msg import Odometry  # noqa: E402
from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.node import Node  # noqa: E402
from sensor_msgs.msg import CameraInfo, CompressedImage, Image  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from ga_ros.core.extrinsic import FROM_TF, ExtrinsicConfig  # noqa: E402
from ga_ros.errors import InputError  # noqa: E402
from ga_ros.geometry import se3  # noqa: E402
from ga_ros.pipeline.stereo import NO_EXTRINSIC  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import domain_id  # noqa: E402
from ga_ros.ros.qos import measurement_qos, stream_qos  # noqa: E402
from ga_ros.ros.vo_node import EXTRINSIC_REFUSED, VoNodeSettings, array_to_image  # noqa: E402
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene  # noqa: E402
from ga_ros.vo.crosstrack import CrossTrackConfig  # noqa: E402
from ga_ros.vo.dense import DenseStereoConfig  # noqa: E402
from ga_ros.vo.evaluate import motion_errors  # noqa: E402
from ga_ros.vo.messages import camera_info_to_model  # noqa: E402
from ga_ros.vo.messages import image_to_grey as image_to_array  # noqa: E402
from ga_ros.vo.odometry import VoConfig  # noqa: E402

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'vo.yaml'


def camera_info(rig: StereoRig, right: bool, stamp_ns: int) -> CameraInfo:
    msg = CameraInfo()
    msg.header.stamp = conv.ns_to_stamp(stamp_ns)
    msg.header.frame_id = 'right' if right else 'left'
    msg.width, msg.height = rig.width, rig.height
    msg.distortion_model = 'plumb_bob'
    msg.d = [0.0] * 5
    msg.k = rig.K.ravel().tolist()
    msg.r = np.eye(3).ravel().tolist()
    P = np.hstack([rig.K, [[-rig.focal_px * rig.baseline_m if right else 0.0], [0.0], [0.0]]])
    msg.p = P.ravel().tolist()
    return msg


def test_yaml_mirrors_config_defaults():
    params = yaml.safe_load(CONFIG.read_text())['vo_node']['ros__parameters']
    expected = {f.name: getattr(VoNodeSettings(), f.name) for f in fields(VoNodeSettings)}
    expected.update(asdict(VoConfig()))  # the nested track rules as a mapping
    expected.update({f.name: getattr(ExtrinsicConfig(), f.name) for f in fields(ExtrinsicConfig)})
    expected.update({'cross_' + f.name: getattr(CrossTrackConfig(), f.name)
                     for f in fields(CrossTrackConfig)})
    expected.update({'cloud_' + f.name: getattr(DenseStereoConfig(), f.name)
                     for f in fields(DenseStereoConfig)})
    assert set(params) == set(expected)
    for key, value in expected.items():
        assert params[key] == value, key


def test_image_conversions(rng):
    img = rng.integers(0, 256, (24, 32), dtype=np.uint8)
    np.testing.assert_array_equal(image_to_array(array_to_image(img, 5, 'cam')), img)
    msg = array_to_image(img, 5, 'cam')
    msg.encoding = 'bgr8'
    msg.step = 32 * 3
    bgr = np.repeat(img[:, :, None], 3, axis=2)
    msg.data = bgr.tobytes()
    np.testing.assert_array_equal(image_to_array(msg), img)
    msg.encoding = '8UC3'  # the same bytes as bgr8 (one decoder for the node and the replay)
    np.testing.assert_array_equal(image_to_array(msg), img)
    msg.encoding = 'mono16'  # high byte of little-endian 16-bit grey
    msg.step = 32 * 2
    msg.data = (img.astype('<u2') << 8 | 7).tobytes()
    np.testing.assert_array_equal(image_to_array(msg), img)
    msg.encoding = '32FC1'
    with pytest.raises(InputError):
        image_to_array(msg)
    msg = array_to_image(img, 5, 'cam')
    msg.data = msg.data[:100]
    with pytest.raises(InputError):
        image_to_array(msg)
    ok, buf = cv2.imencode('.png', img)
    cmsg = CompressedImage(format='png', data=buf.tobytes())
    np.testing.assert_array_equal(image_to_array(cmsg), img)
    with pytest.raises(InputError):
        image_to_array(CompressedImage(format='jpeg', data=b'not an image'))
    info = camera_info(StereoRig(), True, 0)
    model = camera_info_to_model(info)
    assert model.is_rectified() and model.projection()[0, 3] < 0
    info.k = [0.0] * 9
    with pytest.raises(InputError):
        camera_info_to_model(info)


@pytest.mark.ros
def test_two_processes_images_in_measurements_out(tmp_path):
    rig = StereoRig()
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=14, seed=8))
    scene = make_scene(survey, rig, seed=8)
    rng = np.random.default_rng(8)
    n = 14
    frames = [scene.render_pair(T, rng) for T in survey.T_world_cam[:n]]
    dom = domain_id(21)
    env = dict(os.environ, ROS_DOMAIN_ID=str(dom), PYTHONUNBUFFERED='1')
    log = open(tmp_path / 'vo_node.log', 'wb')  # noqa: SIM115
    proc = subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.vo_node', '--ros-args',
                             '--params-file', str(CONFIG), '-p', 'warn_throttle_sec:=0.0',
                             '-p', 'assume_identity_extrinsic:=true'],
                            env=env, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=dom)
    node = Node(f'vo_test_{os.getpid()}', context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    received: list[Odometry] = []
    odoms: list[Odometry] = []
    node.create_subscription(Odometry, '/ga/measurements', received.append, measurement_qos())
    node.create_subscription(Odometry, '/ga/vo/odometry', odoms.append, stream_qos(100))
    s = VoNodeSettings()
    pub_l = node.create_publisher(Image, s.left_image_topic, 20)
    pub_r = node.create_publisher(Image, s.right_image_topic, 20)
    pub_il = node.create_publisher(CameraInfo, s.left_info_topic, 20)
    pub_ir = node.create_publisher(CameraInfo, s.right_info_topic, 20)

    def log_text() -> str:
        return (tmp_path / 'vo_node.log').read_text()

    def spin_until(done, seconds: float, what: str, every=None) -> None:
        """Spin until ``done()``; ``every()`` (if given) is called about every 0.5 s while
        waiting (a resend). Fails, with the node's log, if the node exits or after
        ``seconds``."""
        deadline = time.monotonic() + patience(seconds)
        next_call = time.monotonic() + 0.5
        while not done():
            assert proc.poll() is None, log_text()
            assert time.monotonic() < deadline, f'{what}; node log:\n{log_text()}'
            ex.spin_once(timeout_sec=0.02)
            if every is not None and time.monotonic() >= next_call:
                every()
                next_call = time.monotonic() + 0.5

    def send(left, right, stamp, info=True):
        if info:
            pub_il.publish(camera_info(rig, False, stamp))
            pub_ir.publish(camera_info(rig, True, stamp))
        pub_l.publish(array_to_image(left, stamp, 'left'))
        pub_r.publish(array_to_image(right, stamp, 'right'))

    odom_stamps: set[int] = set()
    node.create_subscription(Odometry, '/ga/vo/odometry',
                             lambda m: odom_stamps.add(conv.stamp_to_ns(m.header.stamp)),
                             stream_qos(100))

    try:
        spin_until(lambda: (min(p.get_subscription_count() for p in (pub_l, pub_r, pub_il, pub_ir))
                            > 0 and node.count_publishers('/ga/measurements') > 0),
                   30, 'vo_node not discovered')
        # Images before any CameraInfo: they wait for it, with a warning (no crash).
        send(*frames[0], 1, info=False)
        spin_until(lambda: 'no CameraInfo' in log_text(), 10,
                   'images without CameraInfo not reported',
                   every=lambda: send(*frames[0], 1, info=False))
        pub_il.publish(camera_info(rig, False, 2))
        pub_ir.publish(camera_info(rig, True, 2))
        spin_until(lambda: 'stereo calibration' in log_text(), 10, 'CameraInfo not taken')
        # each frame once the node has published the odometry of the one before (the queue
        # of config/vo.yaml holds 2 pairs: faster, the VO would skip frames)
        for i in range(n):
            stamp = int(survey.stamps_ns[i]) + 10
            send(*frames[i], stamp)
            spin_until(lambda s=stamp: s in odom_stamps, 20, f'no odometry of frame {i}')
            if i == 5:  # bad input in the middle: mismatched sizes, unknown encoding
                send(frames[i][0][:, :300].copy(), frames[i][1], stamp + 1, info=False)
                bad = array_to_image(frames[i][0], stamp + 2, 'left')
                bad.encoding = '16UC1'
                pub_l.publish(bad)
                pub_r.publish(array_to_image(frames[i][1], stamp + 2, 'right'))
                spin_until(lambda: log_text().count('stereo pair dropped') >= 2, 20,
                           'bad pairs not reported')
        assert proc.poll() is None, (tmp_path / 'vo_node.log').read_text()
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
            try:
                proc.wait(timeout=patience(10))
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=patience(10))
        log.close()
    text = (tmp_path / 'vo_node.log').read_text()
    assert 'no CameraInfo' in text and 'dropped' in text
    assert proc.returncode in (0, -signal.SIGINT), text
    # Every frame gave a raw odometry message (each waited for above); keyframes gave
    # consecutive measurements.
    assert len(odoms) >= n and all(int(survey.stamps_ns[i]) + 10 in odom_stamps
                                   for i in range(n))
    meas = [conv.odometry_to_measurement(m) for m in received]
    assert len(meas) >= 4
    frame_of_stamp = {int(survey.stamps_ns[i]) + 10: i for i in range(n)}
    frame_of_node = {meas[0].src_id: 0}
    for m in meas:
        assert m.kind == 'consecutive'
        frame_of_node[m.dst_id] = frame_of_stamp[m.stamp_ns]
        T_true = se3.relative(survey.T_world_cam[frame_of_node[m.src_id]],
                              survey.T_world_cam[frame_of_node[m.dst_id]])
        dt, dr, _ = motion_errors(T_true, m)
        assert dt < 0.02 * np.linalg.norm(T_true[:3, 3]) and dr < 0.2


@pytest.mark.ros
def test_bad_parameter_exits_with_one_line_error(tmp_path):
    env = dict(os.environ, ROS_DOMAIN_ID=str(domain_id(23)))
    proc = subprocess.run([sys.executable, '-m', 'ga_ros.ros.vo_node', '--ros-args',
                           '--params-file', str(CONFIG), '-p', 'track.mode:=sometimes'],
                          env=env, capture_output=True, text=True, timeout=patience(60))
    assert proc.returncode == 1
    assert 'track.mode' in proc.stderr and 'Traceback' not in proc.stderr


@pytest.mark.ros
def test_node_in_process_adapter(rng):
    """The callbacks without spinning: pairing, measurements, debug image, corrected path."""
    from rclpy.parameter import Parameter

    from ga_ros.ros.vo_node import VoNode

    rig = StereoRig()
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=10, seed=9))
    scene = make_scene(survey, rig, seed=9)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(31))
    node = VoNode(context=ctx, parameter_overrides=[
        Parameter('publish_debug_image', value=True), Parameter('warn_throttle_sec', value=0.0),
        Parameter('pair_queue', value=100), Parameter('source', value='down_cam')])
    sent = []
    node.pub_meas.publish = sent.append
    debug = []
    node.pub_debug.publish = debug.append
    try:
        for side in ('left', 'right'):
            node._on_info(camera_info(rig, side == 'right', 0), side)
        assert node.odometry is not None and not node.calibration.needs_rectification
        # no /tf_static, no T_base_camera, no assume_identity_extrinsic: the pairs are refused
        # (counted, an ERROR status naming the three ways) and the node waits
        errors: list[str] = []
        logger = node.get_logger()
        original_error = logger.error
        logger.error = lambda text, **kw: errors.append(text) or original_error(text)
        for i in range(2):
            left, right = scene.render_pair(survey.T_world_cam[0], rng)
            node._on_image(array_to_image(left, 1000 + i, 'l'), 'left')
            node._on_image(array_to_image(right, 1000 + i, 'r'), 'right')
        assert node.wait_idle()
        assert not sent and node.counts['processed'] == 0 and not debug
        level, message = node.health()
        values = node.diagnostic_values()
        assert level == 2 and values['camera_extrinsic'] == EXTRINSIC_REFUSED
        assert values[f'no_measurement/{NO_EXTRINSIC}'] == 2
        for text in (message, errors[-1]):
            assert all(w in text for w in ('base_link -> l on /tf_static', 'T_base_camera',
                                           'assume_identity_extrinsic: true'))
        # the transform arrives: the next pair resolves it and the VO starts there
        T_base_l = se3.from_rt(np.eye(3), np.array([0.2, 0.0, -0.1]))
        node._on_tf_static(TFMessage(transforms=[
            conv.transform_msg('base_link', 'l', T_base_l, 0)]))
        for i in range(10):
            left, right = scene.render_pair(survey.T_world_cam[i], rng)
            stamp = int(survey.stamps_ns[i]) + 10**9   # after the refused ones
            # right first, then an unpaired stale left, then the left: pairing by stamp.
            node._on_image(array_to_image(right, stamp, 'r'), 'right')
            node._on_image(array_to_image(left, stamp, 'l'), 'left')
        assert node.wait_idle()
        assert node.counts['pairs'] == 10 and len(debug) == 10
        assert node.diagnostic_values()['camera_extrinsic'] == FROM_TF
        np.testing.assert_array_equal(node.front.extrinsic.T_base_cam, T_base_l)
        assert node.health()[0] != 2 and node.front.stats.pairs == 12
        for name in ('max_features', 'cross_min_inliers', 'left_image_topic'):
            d = node.describe_parameter(name)
            assert d.read_only and len(d.description) > len(name) + 10
        meas = [conv.odometry_to_measurement(m) for m in sent]
        assert len(meas) >= 2 and all(m.kind == 'consecutive' for m in meas)
        # every measurement names the camera (parameter source), carried by the encoding
        assert {m.source for m in meas} == {'down_cam'}
        # A corrected path of the keyframes (by stamp) reaches the matcher.
        ids = sorted(node.front._stamp_to_node.values())
        stamps = sorted(node.front._stamp_to_node)
        T = np.repeat(np.eye(4)[None], len(ids), axis=0)
        node._on_path(conv.path_to_msg(T, stamps, 'map'))
        np.testing.assert_allclose(node.matcher.predicted_pose(ids[-1]), np.eye(4))
        # Inconsistent right CameraInfo (no baseline): rejected with a warning, state kept.
        odo = node.odometry
        node._on_info(camera_info(rig, False, 1), 'right')
        node._on_info(camera_info(rig, True, 2), 'right')
        assert node.odometry is odo
        # A changed calibration re-initialises the VO but keeps the node ids increasing.
        rig2 = StereoRig(baseline_m=12.0)
        node._on_info(camera_info(rig2, True, 3), 'right')
        assert node.odometry is not odo and node.calibration.baseline_m == 12.0
        assert node.odometry.next_node_id == odo.next_node_id
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def _upscaled_pairs(n: int, seed: int) -> tuple[StereoRig, list]:
    """``n`` 752x480 pairs at 20 Hz (rendered at 376x240 and upscaled) and their rig."""
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=n, step_m=1.6,
                                       turn_positions=0, frame_period_s=0.05, seed=seed))
    small = StereoRig(376, 240, 229.0, 2.2)
    scene = make_scene(survey, small, seed=seed)
    rng = np.random.default_rng(seed)
    rig = StereoRig(752, 480, 458.0, 2.2)
    pairs = []
    for i in range(n):
        left, right = scene.render_pair(survey.T_world_cam[i], rng)
        pairs.append((int(survey.stamps_ns[i]) + 1,
                      cv2.resize(left, (752, 480)), cv2.resize(right, (752, 480))))
    return rig, pairs


@contextlib.contextmanager
def _vo_node(offset: int, pair_queue: int):
    """An in-process VoNode (throttling off) with its measurements captured: (node, sent)."""
    from rclpy.parameter import Parameter

    from ga_ros.ros.vo_node import VoNode

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(offset))
    node = VoNode(context=ctx, parameter_overrides=[
        Parameter('warn_throttle_sec', value=0.0), Parameter('pair_queue', value=pair_queue),
        Parameter('assume_identity_extrinsic', value=True)])
    sent: list = []
    node.pub_meas.publish = sent.append
    try:
        yield node, sent
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


@pytest.mark.ros
def test_pairs_at_20_hz_are_all_processed_or_counted_as_dropped() -> None:
    """752x480 pairs handed to the callbacks at 20 Hz: received = processed + dropped (queue
    full, oldest skipped), the same counts in the diagnostics, and a warning for the drops."""
    rig, pairs = _upscaled_pairs(40, seed=11)
    with _vo_node(33, pair_queue=1) as (node, sent):
        diags: list = []
        node.pub_diag.publish = diags.append
        warnings: list[str] = []
        logger = node.get_logger()
        original_warning = logger.warning
        logger.warning = lambda text, **kw: warnings.append(text) or original_warning(text)
        for side in ('left', 'right'):
            node._on_info(camera_info(rig, side == 'right', 0), side)
        t_next = time.monotonic()
        for k, (stamp, left, right) in enumerate(pairs):
            node._on_image(array_to_image(left, stamp, 'l'), 'left')
            node._on_image(array_to_image(right, stamp, 'r'), 'right')
            if k == 20:  # a burst: three pairs at once overflow the queue of one pair
                for j in (1, 2, 3):
                    node._on_image(array_to_image(left, stamp + j * 1000, 'l'), 'left')
                    node._on_image(array_to_image(right, stamp + j * 1000, 'r'), 'right')
            t_next += 0.05
            time.sleep(max(0.0, t_next - time.monotonic()))
        assert node.wait_idle()
        node.publish_diagnostics()
        received = len(pairs) + 3
        c = node.counts
        assert node.front.stats.pairs == received
        assert c['processed'] + c['queue_dropped'] == received
        assert c['queue_dropped'] >= 2  # at least the burst
        st = node.front.stats
        assert st.pairs == st.measurements + sum(st.reasons.values())
        assert st.reasons['dropped (queue full)'] == c['queue_dropped']
        d = conv.diagnostics_to_dict(diags[-1])
        assert int(d['pairs_received']) == received
        assert int(d['pairs_processed']) + int(d['pairs_dropped_queue_full']) == received
        assert int(d['measurements']) == len(sent) > 0
        assert any('dropped so far' in w for w in warnings)


@pytest.mark.ros
def test_nan_camera_info_first_then_valid_ones_give_measurements() -> None:
    """A CameraInfo with a NaN focal length is rejected with its reason and never stored:
    the valid ones that follow calibrate the VO and the pairs give measurements."""
    rig, pairs = _upscaled_pairs(30, seed=12)
    with _vo_node(35, pair_queue=100) as (node, sent):
        for side in ('left', 'right'):
            bad = camera_info(rig, side == 'right', 0)
            k = list(bad.k)
            k[0] = float('nan')
            bad.k = k
            node._on_info(bad, side)
        assert node.calibration is None and node.front.stats.camera_info_rejected == 2
        with pytest.raises(InputError, match='NaN'):
            camera_info_to_model(bad)
        for stamp, left, right in pairs:
            for side in ('left', 'right'):
                node._on_info(camera_info(rig, side == 'right', stamp), side)
            node._on_image(array_to_image(left, stamp, 'l'), 'left')
            node._on_image(array_to_image(right, stamp, 'r'), 'right')
        assert node.wait_idle()
        assert node.calibration is not None and node.calibration.baseline_m == 2.2
        assert len(sent) >= 2 and node.front.stats.measurements == len(sent)


@pytest.mark.ros
def test_camera_info_just_after_the_images_loses_no_pair() -> None:
    """Each pair's CameraInfo (same stamp) arrives just after its images: the first pair waits
    for the calibration instead of being dropped ("no CameraInfo yet"), and the node gives the
    same measurements as with the CameraInfo first."""
    from ga_ros.pipeline.stereo import NO_CAMERA_INFO

    rig, pairs = _upscaled_pairs(30, seed=12)
    runs = []
    for offset, info_first in ((37, True), (39, False)):
        with _vo_node(offset, pair_queue=100) as (node, sent):
            for stamp, left, right in pairs:
                infos = [(camera_info(rig, side == 'right', stamp), side)
                         for side in ('left', 'right')]
                if info_first:
                    for msg, side in infos:
                        node._on_info(msg, side)
                node._on_image(array_to_image(left, stamp, 'l'), 'left')
                node._on_image(array_to_image(right, stamp, 'r'), 'right')
                if not info_first:
                    for msg, side in infos:
                        node._on_info(msg, side)
            assert node.wait_idle()
            st = node.front.stats
            assert NO_CAMERA_INFO not in st.reasons, st.reasons
            assert node.counts['processed'] == st.pairs == len(pairs)
            runs.append([conv.odometry_to_measurement(m) for m in sent])
    first, after = runs
    assert len(first) == len(after) >= 2
    for a, b in zip(first, after):
        assert (a.src_id, a.dst_id) == (b.src_id, b.dst_id)
        np.testing.assert_allclose(a.z, b.z, atol=1e-12)


@pytest.mark.ros
def test_keyframe_clouds_published_while_subscribed() -> None:
    """``ga/keyframe_cloud``: nothing computed without a subscriber; with one, a PointCloud2
    per new keyframe, stamped with the keyframe's stamp, in the left image's frame, its points
    in front of the camera at the simulated terrain's depths. ``ga/keyframe_image`` (+
    ``ga/keyframe_camera_info``): the same keyframes' rectified left images and intrinsics."""
    from rclpy.parameter import Parameter
    from sensor_msgs.msg import CameraInfo, Image, PointCloud2

    from ga_ros.ros.vo_node import VoNode
    from ga_ros.vo.messages import image_to_grey

    rig = StereoRig()
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=12, seed=4))
    scene = make_scene(survey, rig, seed=4)
    rng = np.random.default_rng(4)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id(37))
    node = VoNode(context=ctx, parameter_overrides=[
        Parameter('warn_throttle_sec', value=0.0), Parameter('pair_queue', value=100),
        Parameter('assume_identity_extrinsic', value=True), Parameter('cross_track', value=False),
        Parameter('cloud_pixel_stride', value=4)])
    listener = Node('cloud_listener', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(listener)
    received: list[PointCloud2] = []
    kf_images: list[Image] = []
    kf_infos: list[CameraInfo] = []
    lefts: dict[int, np.ndarray] = {}
    try:
        for side in ('left', 'right'):
            node._on_info(camera_info(rig, side == 'right', 0), side)

        def feed(indices: range) -> None:
            for i in indices:
                left, right = scene.render_pair(survey.T_world_cam[i], rng)
                stamp = int(survey.stamps_ns[i])
                lefts[stamp] = left
                node._on_image(array_to_image(left, stamp, 'l_optical'), 'left')
                node._on_image(array_to_image(right, stamp, 'r_optical'), 'right')
            assert node.wait_idle()

        feed(range(0, 4))  # no subscriber: no cloud computed
        assert node.front.stats.keyframes >= 1 and node.counts['keyframe_clouds'] == 0
        assert node.front._dense is None
        listener.create_subscription(PointCloud2, '/ga/keyframe_cloud', received.append,
                                     stream_qos(100))
        listener.create_subscription(Image, '/ga/keyframe_image', kf_images.append,
                                     stream_qos(100))
        listener.create_subscription(CameraInfo, '/ga/keyframe_camera_info', kf_infos.append,
                                     stream_qos(100))
        deadline = time.monotonic() + patience(30)
        while (node.pub_cloud.get_subscription_count() == 0
               or node.pub_kf_image.get_subscription_count() == 0):
            assert time.monotonic() < deadline, 'cloud subscriber not discovered'
            executor.spin_once(timeout_sec=0.05)
        kf_before = node.front.stats.keyframes
        feed(range(4, 12))
        new_kf = node.front.stats.keyframes - kf_before
        assert new_kf >= 2 and node.counts['keyframe_clouds'] == new_kf
        deadline = time.monotonic() + patience(30)
        while len(received) < new_kf or len(kf_images) < new_kf or len(kf_infos) < new_kf:
            assert time.monotonic() < deadline, f'{len(received)} of {new_kf} clouds received'
            executor.spin_once(timeout_sec=0.05)
        assert [m.header.stamp for m in kf_images] == [m.header.stamp for m in received]
        K = np.asarray(node.front.calibration.K, float)
        for img, info in zip(kf_images, kf_infos):
            assert img.header == info.header and img.header.frame_id == 'l_optical'
            # the sample's images are rectified already: the keyframe's own left image
            assert np.array_equal(image_to_grey(img), lefts[conv.stamp_to_ns(img.header.stamp)])
            assert np.allclose(np.reshape(info.k, (3, 3)), K) and not any(info.d)
            assert (info.width, info.height) == (img.width, img.height)
        kf_stamps = set(node.front._stamp_to_node)
        depths = [scene.render(T, with_depth=True)[1] for T in survey.T_world_cam[4:12]]
        z_lo, z_hi = min(d.min() for d in depths), max(d.max() for d in depths)
        for msg in received:
            assert conv.stamp_to_ns(msg.header.stamp) in kf_stamps
            assert msg.header.frame_id == 'l_optical'
            assert [f.name for f in msg.fields] == ['x', 'y', 'z', 'intensity']
            assert msg.point_step == 16 and msg.is_dense and msg.height == 1
            xyzi = np.frombuffer(bytes(msg.data), '<f4').reshape(-1, 4)
            assert len(xyzi) == msg.width > 0.5 * (rig.width - 64) * rig.height / 16
            z = xyzi[:, 2]
            assert np.median(z) > z_lo and np.median(z) < z_hi
            assert np.mean((z > 0.9 * z_lo) & (z < 1.1 * z_hi)) > 0.98
        assert node.diagnostic_values()['keyframe_clouds'] == new_kf
        assert node.diagnostic_values()['keyframe_images'] == new_kf
    finally:
        executor.shutdown()
        listener.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


@pytest.mark.ros
def test_a_warning_then_an_error_from_the_throttled_log_both_reach_the_log() -> None:
    """The node's throttled log writes warnings and errors (an unknown extrinsic is an
    error after a 'no CameraInfo yet' warning): rclpy refuses a call site whose severity
    changes, which made the worker drop the pair with 'Logger severity cannot be changed'."""
    with _vo_node(34, pair_queue=1) as (node, _):
        node._warn('camera_info', 'a warning first')
        node._warn('extrinsic', 'then an error', error=True)
        node._warn('queue', 'and a warning again')
