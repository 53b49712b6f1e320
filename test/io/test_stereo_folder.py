"""EuRoC ASL and KITTI odometry folders replayed directly (``ga-ros replay FOLDER``).

The folders are made in the test, shaped like the datasets' own, from the stereo simulator
(``ga_ros.sim.stereo``): PNG images listed by stamp, the calibration in the datasets' formats
(EuRoC ``sensor.yaml`` with ``T_BS``, KITTI ``calib.txt`` projections), the ground truth in
their files. Checks: the pairs, stamps, calibration and ground truth read are the ones written,
and a replay of the folder runs to its end with the ground truth matched.
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from ga_ros.cli.main import main
from ga_ros.geometry import se3, so3
from ga_ros.io.folder_bag import open_recording
from ga_ros.io.stereo_folder import read_stereo_folder
from ga_ros.io.trajectory import read_tum
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene

T0_NS = 1403636579763555584  # EuRoC MH_01's first stamp
#: the left camera in the body (IMU) frame: turned and shifted, as on EuRoC's VI-Sensor
T_B_CAM0 = se3.from_rt(so3.exp(np.array([0.02, -0.01, 1.55])), np.array([-0.02, 0.07, 0.01]))


def _survey():
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=16, step_m=6.0,
                                       turn_positions=8, seed=5))
    rig = StereoRig.for_size(320, 240)
    return survey, rig, make_scene(survey, rig, seed=5)


def _yaml_matrix(T: np.ndarray) -> str:
    return ('  cols: 4\n  rows: 4\n  data: [' + ', '.join(f'{v:.17g}' for v in T.reshape(-1))
            + ']\n')


def _sensor_yaml(rig: StereoRig, T_BS: np.ndarray) -> str:
    K = rig.K
    return ('%YAML:1.0\nsensor_type: camera\ncomment: simulated\nT_BS:\n' + _yaml_matrix(T_BS)
            + f'rate_hz: 2\nresolution: [{rig.width}, {rig.height}]\ncamera_model: pinhole\n'
            f'intrinsics: [{K[0, 0]}, {K[1, 1]}, {K[0, 2]}, {K[1, 2]}]\n'
            'distortion_model: radial-tangential\ndistortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n')


def make_euroc_folder(root: Path) -> dict:
    """``root/mav0/{cam0,cam1,state_groundtruth_estimate0}`` of the simulated survey; returns
    what was written (stamps, body poses, rig)."""
    survey, rig, scene = _survey()
    rng = np.random.default_rng(5)
    stamps = survey.stamps_ns + T0_NS
    T_B_CAM1 = T_B_CAM0 @ rig.T_left_right
    mav = root / 'mav0'
    for cam, T_BS in (('cam0', T_B_CAM0), ('cam1', T_B_CAM1)):
        (mav / cam / 'data').mkdir(parents=True)
        (mav / cam / 'sensor.yaml').write_text(_sensor_yaml(rig, T_BS))
        (mav / cam / 'data.csv').write_text('#timestamp [ns],filename\n' + ''.join(
            f'{s},{s}.png\n' for s in stamps))
    for T, s in zip(survey.T_world_cam, stamps):
        left, right = scene.render_pair(T, rng)
        cv2.imwrite(str(mav / 'cam0' / 'data' / f'{s}.png'), left)
        cv2.imwrite(str(mav / 'cam1' / 'data' / f'{s}.png'), right)
    T_world_B = survey.T_world_cam @ se3.inverse(T_B_CAM0)
    gt_stamps, T_gt = stamps, T_world_B
    p, q = se3.to_pos_quat(T_gt)
    gt = mav / 'state_groundtruth_estimate0'
    gt.mkdir()
    (gt / 'data.csv').write_text(
        '#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], '
        'q_RS_z [], v_RS_R_x [m s^-1]\n' + ''.join(
            f'{s},' + ','.join(f'{v:.17g}' for v in (*a, b[3], *b[:3])) + ',0\n'
            for s, a, b in zip(gt_stamps, p, q)))
    return {'stamps': stamps, 'T_world_B': T_world_B, 'rig': rig, 'gt_stamps': gt_stamps,
            'T_gt': T_gt}


@pytest.fixture(scope='module')
def euroc(tmp_path_factory) -> tuple[Path, dict]:
    root = tmp_path_factory.mktemp('euroc') / 'MH_sim'
    return root, make_euroc_folder(root)


def test_euroc_folder_is_read_as_written(euroc):
    root, made = euroc
    f = read_stereo_folder(root)
    assert f is not None and f.kind == 'EuRoC'
    assert np.array_equal(f.stamps_ns, made['stamps'])
    assert [p.name for p in f.left_files] == [f'{s}.png' for s in made['stamps']]
    assert all(p.parent.parent.name == 'cam1' for p in f.right_files)
    assert np.allclose(f.T_base_left, T_B_CAM0, atol=1e-12)
    assert np.allclose(f.T_base_right, T_B_CAM0 @ made['rig'].T_left_right, atol=1e-12)
    # rectification of two parallel pinhole cameras: the rig's focal length and baseline
    rig = made['rig']
    P_l, P_r = f.left.projection(), f.right.projection()
    assert P_l[0, 0] == pytest.approx(rig.focal_px, rel=1e-3)
    assert -P_r[0, 3] / P_r[0, 0] == pytest.approx(rig.baseline_m, rel=1e-6)
    assert np.array_equal(f.ground_truth_stamps_ns, made['gt_stamps'])
    assert np.allclose(f.T_world_base, made['T_gt'], atol=1e-9)
    assert read_stereo_folder(root / 'mav0').stamps_ns.size == made['stamps'].size


def test_euroc_folder_as_a_bag_gives_calibration_before_images(euroc):
    root, made = euroc
    with open_recording(root) as bag:
        names = {t.name: t.count for t in bag.info.topics}
        assert names['/cam0/image_raw'] == names['/cam1/image_raw'] == made['stamps'].size
        first = [bm.topic for _, bm in zip(range(5), bag.messages())]
    assert set(first[:3]) == {'/cam0/camera_info', '/cam1/camera_info', '/tf_static'}
    assert first[3:5] == ['/cam0/image_raw', '/cam1/image_raw']


def test_replay_of_a_euroc_folder(euroc, tmp_path, capsys):
    root, made = euroc
    assert main(['replay', str(root), '--info']) == 0
    info = capsys.readouterr().out
    assert 'source: stereo images /cam0/image_raw + /cam1/image_raw' in info
    out = tmp_path / 'out'
    rc = main(['replay', str(root), '--out', str(out), '--no-plot', '--no-progress'])
    text = capsys.readouterr().out
    assert rc == 0, text
    summary = json.loads((out / 'summary.json').read_text())
    assert summary['source'] == 'stereo'
    assert summary['n_inputs'] == made['stamps'].size  # every pair read
    assert summary['n_nodes'] >= 5
    assert 'error vs ground truth' in text
    # the ground truth written is the body's (base_link) poses at the keyframe stamps
    gt = read_tum(out / 'trajectory_gt.tum')
    idx = np.searchsorted(made['gt_stamps'], gt.stamps_ns)
    assert np.array_equal(made['gt_stamps'][idx], gt.stamps_ns)
    assert np.allclose(gt.T_world_node[:, :3, 3], made['T_gt'][idx, :3, 3], atol=1e-6)
    # the VO's motion, in base_link through T_BS, follows the body: a few % of the path
    ga = read_tum(out / 'trajectory_ga.tum')
    k = np.searchsorted(made['stamps'], ga.stamps_ns)
    assert np.array_equal(made['stamps'][k], ga.stamps_ns)  # keyframes at image stamps
    travel = np.linalg.norm(np.diff(made['T_world_B'][:, :3, 3], axis=0), axis=1).sum()
    err = np.linalg.norm(ga.T_world_node[:, :3, 3] - made['T_world_B'][k, :3, 3], axis=1)
    assert err.max() < 0.05 * travel, (err.max(), travel)
    assert err.max() > 0  # estimated, not copied from the ground truth


def make_kitti_sequence(root: Path) -> dict:
    """``root/sequences/00`` (image_0, image_1, calib.txt, times.txt) and ``root/poses/00.txt``
    of the simulated survey; returns what was written."""
    survey, rig, scene = _survey()
    rng = np.random.default_rng(6)
    seq = root / 'sequences' / '00'
    for d in ('image_0', 'image_1'):
        (seq / d).mkdir(parents=True)
    t = survey.stamps_ns * 1e-9 + 0.05
    for k, T in enumerate(survey.T_world_cam):
        left, right = scene.render_pair(T, rng)
        cv2.imwrite(str(seq / 'image_0' / f'{k:06d}.png'), left)
        cv2.imwrite(str(seq / 'image_1' / f'{k:06d}.png'), right)
    (seq / 'times.txt').write_text(''.join(f'{x:e}\n' for x in t))
    P0 = np.hstack([rig.K, np.zeros((3, 1))])
    P1 = P0.copy()
    P1[0, 3] = -rig.focal_px * rig.baseline_m

    def row(M):
        return ' '.join(f'{v:.12e}' for v in M.reshape(-1))

    (seq / 'calib.txt').write_text(f'P0: {row(P0)}\nP1: {row(P1)}\nP2: {row(P0)}\n'
                                   f'P3: {row(P1)}\nTr: {row(np.eye(4)[:3])}\n')
    T_first = se3.inverse(survey.T_world_cam[0]) @ survey.T_world_cam  # KITTI: cam0(0) frame
    (root / 'poses').mkdir()
    (root / 'poses' / '00.txt').write_text(''.join(f'{row(T[:3])}\n' for T in T_first))
    return {'stamps': np.round(t * 1e9).astype(np.int64), 'T': T_first, 'rig': rig}


def test_kitti_sequence_is_read_and_replayed(tmp_path, capsys):
    made = make_kitti_sequence(tmp_path / 'kitti')
    seq = tmp_path / 'kitti' / 'sequences' / '00'
    f = read_stereo_folder(seq)
    assert f is not None and f.kind == 'KITTI'
    assert np.array_equal(f.stamps_ns, made['stamps'])
    assert [p.name for p in f.right_files][:2] == ['000000.png', '000001.png']
    assert -f.right.projection()[0, 3] / f.right.projection()[0, 0] == pytest.approx(
        made['rig'].baseline_m)
    assert np.allclose(f.T_base_left, np.eye(4))
    assert np.array_equal(f.ground_truth_stamps_ns, made['stamps'])
    assert np.allclose(f.T_world_base, made['T'], atol=1e-9)
    out = tmp_path / 'out'
    rc = main(['replay', str(seq), '--out', str(out), '--no-plot', '--no-progress'])
    text = capsys.readouterr().out
    assert rc == 0, text
    ga = read_tum(out / 'trajectory_ga.tum')
    k = np.searchsorted(made['stamps'], ga.stamps_ns)
    assert np.array_equal(made['stamps'][k], ga.stamps_ns)
    travel = np.linalg.norm(np.diff(made['T'][:, :3, 3], axis=0), axis=1).sum()
    err = np.linalg.norm(ga.T_world_node[:, :3, 3] - made['T'][k, :3, 3], axis=1)
    assert 0 < err.max() < 0.05 * travel, (err.max(), travel)


def test_a_folder_of_neither_kind_says_what_is_read(tmp_path, capsys):
    (tmp_path / 'x' / 'mav0' / 'cam0').mkdir(parents=True)
    assert read_stereo_folder(tmp_path / 'x') is None
    assert main(['replay', str(tmp_path / 'x'), '--info']) == 1
    err = capsys.readouterr().err
    assert 'EuRoC ASL folder' in err and 'KITTI' in err
