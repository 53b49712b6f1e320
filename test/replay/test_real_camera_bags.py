"""Real-camera stereo bags in the replay: EuRoC topic names (``/cam0/image_raw``), 752x480 raw
images with radial-tangential distortion at 20 Hz, CameraInfo or a calibration file, VO
parameters from ``config/vo.yaml`` and ``--vo`` overrides, and every reason a pair gave no
measurement named and counted."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
import yaml
from bag_fixtures import mono8_image_msg

from ga_ros.errors import FormatError, InputError
from ga_ros.io.bag import BagReader, bag_info
from ga_ros.io.bag_messages import CAMERA_INFO, IMAGE, header, typestore
from ga_ros.io.bag_writer import BagWriter, tf_message, transform_msg
from ga_ros.io.topic_plan import plan_topics
from ga_ros.pipeline.params import parse_override, read_params_file
from ga_ros.pipeline.stereo import (
    NODE_ONLY_PARAMS,
    NOT_KEYFRAME,
    FrontEndConfig,
    StereoFrontEnd,
    front_end_config_from_params,
)
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.pipeline import replay
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene
from ga_ros.vo.calibration import read_stereo_calibration

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'vo.yaml'
# EuRoC MAV V1_01 cam0 / cam1 (sensor.yaml): intrinsics, distortion, T_BS.
EUROC_CAM0 = {
    'intrinsics': [458.654, 457.296, 367.215, 248.375], 'resolution': [752, 480],
    'distortion_coefficients': [-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05],
    'T_BS': {'rows': 4, 'cols': 4, 'data': [
        0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975,
        0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768,
        -0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949,
        0.0, 0.0, 0.0, 1.0]}}
EUROC_CAM1 = {
    'intrinsics': [457.587, 456.134, 379.999, 255.238], 'resolution': [752, 480],
    'distortion_coefficients': [-0.28368365, 0.07451284, -0.00010473, -3.55590700e-05],
    'T_BS': {'rows': 4, 'cols': 4, 'data': [
        0.0125552670891, -0.999755099723, 0.0182237714554, -0.0198435579556,
        0.999598781151, 0.0130119051815, 0.0251588363115, 0.0453689425024,
        -0.0253898008918, 0.0179005838253, 0.999517347078, 0.00786212447038,
        0.0, 0.0, 0.0, 1.0]}}
K_RAW = np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])
D_RAW = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])
SCALE = 0.05  # the aerial scene (45-105 m deep) seen as a 2-5 m deep room
BASELINE = 0.11
N_PAIRS = 64


def _raw_maps(K_rect: np.ndarray, R: np.ndarray) -> tuple:
    """Remap tables making a raw (distorted, unrectified) image from a rectified one."""
    u, v = np.meshgrid(np.arange(752, dtype=np.float64), np.arange(480, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    rect = cv2.undistortPoints(pts, K_RAW, D_RAW, R=R, P=K_rect).reshape(480, 752, 2)
    return rect[..., 0].astype(np.float32), rect[..., 1].astype(np.float32)


def _info_fields(rig: StereoRig, R: np.ndarray, right: bool) -> dict:
    P = np.hstack([rig.K, [[-rig.K[0, 0] * BASELINE if right else 0.0], [0.0], [0.0]]])
    return {'width': 752, 'height': 480, 'distortion_model': 'plumb_bob',
            'k': K_RAW.ravel().tolist(), 'd': D_RAW.tolist(), 'r': R.ravel().tolist(),
            'p': P.ravel().tolist()}


def _info_msg(fields: dict, frame: str, stamp_ns: int):
    types = typestore().types
    return types[CAMERA_INFO](
        header=header(frame, stamp_ns), height=480, width=752, distortion_model='plumb_bob',
        d=np.asarray(fields['d'], float), k=np.asarray(fields['k'], float),
        r=np.asarray(fields['r'], float), p=np.asarray(fields['p'], float), binning_x=0,
        binning_y=0, roi=types['sensor_msgs/msg/RegionOfInterest'](
            x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


@pytest.fixture(scope='module')
def euroc_bag(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    """A EuRoC-shaped bag: /cam0/image_raw, /cam1/image_raw (mono8 752x480, distorted, 20 Hz)
    and /cam0/camera_info, /cam1/camera_info; rendered at 376x240 and upscaled (speed)."""
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=N_PAIRS, step_m=1.6,
                                       turn_positions=0, frame_period_s=0.05, seed=6))
    small = StereoRig(376, 240, 229.0, BASELINE / SCALE)
    rig = StereoRig(752, 480, 458.0, BASELINE / SCALE)
    scene = make_scene(survey, small, seed=6)
    rng = np.random.default_rng(6)
    R_l = cv2.Rodrigues(np.array([0.004, -0.006, 0.002]))[0]
    R_r = cv2.Rodrigues(np.array([-0.003, 0.005, -0.001]))[0]
    K_up = rig.K.copy()
    K_up[:2, 2] = (np.array([small.K[0, 2], small.K[1, 2]]) + 0.5) * 2 - 0.5
    maps = (_raw_maps(K_up, R_l), _raw_maps(K_up, R_r))
    cal = {'left': _info_fields(rig, R_l, False), 'right': _info_fields(rig, R_r, True)}
    for side in cal.values():  # the rectified camera is the upscaled render's
        P = np.asarray(side['p']).reshape(3, 4)
        P[:3, :3] = K_up
        P[0, 3] = -K_up[0, 0] * BASELINE if P[0, 3] else 0.0
        side['p'] = P.ravel().tolist()
    path = tmp_path_factory.mktemp('euroc') / 'bag'
    t0 = 1_403_636_579_763_555_584
    with BagWriter(path, compress=False) as bag:
        # the body frame is the left camera's (identity extrinsic, said so on /tf_static)
        bag.write('/tf_static', 'tf2_msgs/msg/TFMessage',
                  tf_message([transform_msg('base_link', 'cam0', np.eye(4), t0)]), t0)
        for i, T in enumerate(survey.T_world_cam[:N_PAIRS]):
            s = t0 + int(survey.stamps_ns[i])
            pair = scene.render_pair(T, rng)
            for k, (cam, side) in enumerate((('cam0', 'left'), ('cam1', 'right'))):
                img = cv2.resize(pair[k], (752, 480), interpolation=cv2.INTER_LINEAR)
                raw = cv2.remap(img, *maps[k], cv2.INTER_LINEAR)
                bag.write(f'/{cam}/camera_info', CAMERA_INFO, _info_msg(cal[side], cam, s), s)
                bag.write(f'/{cam}/image_raw', IMAGE, mono8_image_msg(raw, cam, s), s)
    return path, cal


def test_euroc_topics_detected_and_default_replay_gives_a_corrected_path(
        tmp_path: Path, euroc_bag: tuple[Path, dict]) -> None:
    bag, _ = euroc_bag
    plan = plan_topics(bag_info(bag))
    assert (plan.left_image, plan.right_image) == ('/cam0/image_raw', '/cam1/image_raw')
    assert (plan.left_info, plan.right_info) == ('/cam0/camera_info', '/cam1/camera_info')
    r = replay(bag, tmp_path / 'out', ReplayConfig(plot=False))  # default settings
    st = r.source_stats
    assert r.n_inputs == st['pairs'] == N_PAIRS
    assert st['pairs'] == st['measurements'] + sum(st['reasons'].values())
    assert r.n_measurements >= 5 and r.n_nodes == r.n_measurements + 1
    with BagReader(tmp_path / 'out' / 'replay_bag') as out:
        paths = [m.msg for m in out.messages(['/ga/corrected_path'])]
    assert paths and len(paths[-1].poses) == r.n_nodes
    xyz = np.array([[p.pose.position.x, p.pose.position.y, p.pose.position.z]
                    for p in paths[-1].poses])
    # 63 frames at 1.6 m/s * SCALE per frame: about 5 m of travel in the scaled world
    travel = np.linalg.norm(xyz[-1] - xyz[0])
    assert 0.7 * 63 * 1.6 * SCALE < travel < 1.3 * 63 * 1.6 * SCALE


def test_calibration_file_replaces_missing_camera_info(tmp_path: Path,
                                                       euroc_bag: tuple[Path, dict]) -> None:
    bag, cal = euroc_bag
    # A bag without CameraInfo (EuRoC-converted): the plan says what to do.
    images_only = tmp_path / 'images_only'
    with BagReader(bag) as src, BagWriter(images_only, compress=False) as dst:
        for k, m in enumerate(src.messages(['/cam0/image_raw', '/cam1/image_raw'])):
            dst.write(m.topic, IMAGE, m.msg, m.log_ns)
            if k > 8:
                break
    with pytest.raises(FormatError, match='--calibration'):
        plan_topics(bag_info(images_only))
    # The CameraInfo fields as a YAML: the same measurements as with the bag's CameraInfo.
    f = tmp_path / 'stereo.yaml'
    f.write_text(yaml.safe_dump(cal))
    from ga_ros.io.topic_plan import TopicConfig

    with_file = replay(bag, tmp_path / 'a', ReplayConfig(
        topics=TopicConfig(calibration=(str(f),)), plot=False))
    with_info = replay(bag, tmp_path / 'b', ReplayConfig(plot=False))
    assert with_file.n_measurements == with_info.n_measurements > 0
    assert with_file.source_stats['reasons'] == with_info.source_stats['reasons']


def test_euroc_sensor_yaml_rectification(tmp_path: Path) -> None:
    """EuRoC's two sensor.yaml: baseline = distance of the camera centres (from T_BS), rectified
    rays of a 3-D point agree in row and give its depth back from the disparity."""
    files = []
    for name, d in (('cam0', EUROC_CAM0), ('cam1', EUROC_CAM1)):
        p = tmp_path / f'{name}.yaml'
        p.write_text('%YAML:1.0\n' + yaml.safe_dump(dict(d, camera_model='pinhole',
                                                         distortion_model='radial-tangential')))
        files.append(str(p))
    models = read_stereo_calibration(files)
    front = StereoFrontEnd()
    cal = front.set_camera_models(models.left, models.right)
    T0 = np.reshape(EUROC_CAM0['T_BS']['data'], (4, 4))
    T1 = np.reshape(EUROC_CAM1['T_BS']['data'], (4, 4))
    assert cal.baseline_m == pytest.approx(np.linalg.norm(T0[:3, 3] - T1[:3, 3]), rel=1e-6)
    assert cal.needs_rectification and front.odometry is not None
    # A point 3 m in front of cam0, projected into each raw camera, then rectified.
    X0 = np.array([0.2, -0.1, 3.0])
    X1 = (np.linalg.inv(T1) @ T0 @ np.append(X0, 1))[:3]
    uv = []
    for X, m in ((X0, models.left), (X1, models.right)):
        raw, _ = cv2.projectPoints(X.reshape(1, 3), np.zeros(3), np.zeros(3), m.K, m.D)
        uv.append(cv2.undistortPoints(raw, m.K, m.D, R=m.R, P=m.P).ravel())
    assert uv[0][1] == pytest.approx(uv[1][1], abs=1e-3)
    depth = cal.K[0, 0] * cal.baseline_m / (uv[0][0] - uv[1][0])
    z_rect = (models.left.R @ X0)[2]
    assert depth == pytest.approx(z_rect, rel=1e-4)
    with pytest.raises(InputError, match='left of the first'):
        read_stereo_calibration(files[::-1])


def test_vo_params_file_and_overrides_reach_the_config() -> None:
    params = read_params_file(CONFIG, 'vo_node')
    assert front_end_config_from_params(params) == FrontEndConfig()  # the file = the defaults
    params.update(parse_override(t) for t in ('keyframe_max_travel_ratio=0.1',
                                              'cross_min_inliers=12', 'cross_track=false',
                                              'max_pair_dt_sec=1'))
    c = front_end_config_from_params(params)
    assert c.vo.keyframe_max_travel_ratio == 0.1 and c.cross.min_inliers == 12
    assert c.cross_track is False and c.max_pair_dt_sec == 1.0
    with pytest.raises(InputError, match='unknown VO parameter'):
        front_end_config_from_params({'keyframe_max_travel': 0.1})
    with pytest.raises(InputError, match='min_inliers'):
        front_end_config_from_params({'min_inliers': 'many'})
    with pytest.raises(InputError):
        front_end_config_from_params({'track.mode': 'sometimes'})


@pytest.mark.ros
def test_node_only_params_are_the_node_settings() -> None:
    from dataclasses import fields

    from ga_ros.ros.vo_node import VoNodeSettings

    names = {f.name for f in fields(VoNodeSettings)} - {'cross_track', 'max_pair_dt_sec', 'source'}
    assert names == NODE_ONLY_PARAMS


def test_no_keyframe_is_named_not_a_missing_camera_info(tmp_path: Path,
                                                        euroc_bag: tuple[Path, dict],
                                                        capsys: pytest.CaptureFixture) -> None:
    """The case that used to say 'image pair before its CameraInfo': keyframe rules that never
    fire (as the 110 m defaults did at 2-5 m) -> the replay names 'not a keyframe' (as a still
    camera: one keyframe, a stationary trajectory, exit 0 and the reasons)."""
    from ga_ros.cli.main import main

    bag, _ = euroc_bag
    params = tmp_path / 'vo.yaml'
    text = CONFIG.read_text().replace('keyframe_min_inliers: 60', 'keyframe_min_inliers: 6')
    params.write_text(text)
    code = main(['replay', str(bag), '--out', str(tmp_path / 'out'), '--no-plot',
                 '--no-progress', '--vo-params', str(params),
                 '--vo', 'keyframe_max_travel_ratio=100', '--vo', 'keyframe_max_rotation_deg=180',
                 '--vo', 'keyframe_min_tracked_fraction=0'])
    out = capsys.readouterr().out
    assert code == 0, out
    assert 'the robot did not move' in out and 'lower the VO keyframe thresholds' in out
    assert 'CameraInfo' not in out and f' {NOT_KEYFRAME}' in out, out
    assert f'{N_PAIRS} pairs: 0 measurements' in out and 'first keyframe (no motion yet)' in out


def test_replay_skips_a_nan_camera_info_and_uses_the_next(tmp_path: Path,
                                                         euroc_bag: tuple[Path, dict]) -> None:
    bag, _ = euroc_bag
    nan_first = tmp_path / 'nan_first'
    with BagReader(bag) as src, BagWriter(nan_first, compress=False) as dst:
        first = True
        for m in src.messages():
            if first and m.msgtype == CAMERA_INFO:
                k = m.msg.k.copy()
                k[0] = float('nan')
                m.msg.k = k
                first = False
            dst.write(m.topic, m.msgtype, m.msg, m.log_ns)
    r = replay(nan_first, tmp_path / 'out', ReplayConfig(plot=False))
    # the NaN left CameraInfo only: the first pair waits for the next left CameraInfo
    assert r.rejected == {'stereo': 1} and 'NaN' in r.rejected_examples[0]
    st = r.source_stats
    assert st['camera_info_rejected'] == 1 and 'no CameraInfo yet' not in st['reasons']
    assert r.n_inputs == st['pairs']  # every pair went through the VO
    assert r.n_measurements >= 5
