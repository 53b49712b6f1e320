"""A camera's measurements carry its name (``Measurement.source``, default ``cam0``) and
``ga-ros replay --calibrate-camera NAME`` estimates its extrinsic's rotation in the final batch.

The camera beside the odometry of :mod:`test_camera_beside_odometry` (an aerial lawnmower, a
drifting body-frame odometry, a nadir stereo camera) replayed with its extrinsic's rotation
given wrong by a known ``phi``: the camera's cross-track connections, told apart from the
odometry's motions by their source, give ``phi`` back within 3 sigma; with the right extrinsic
nothing is significant. Naming the sources changes no variance group's partition (a camera's
consecutive motions and cross-track connections stay two groups), an unknown name is refused
with the known sources listed.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from ga_ros.core.measurement import Measurement, source_or_group, variance_group
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3, so3

pytest.importorskip('cv2')

from test_camera_beside_odometry import T_BASE_CAM, write_robot_bag  # noqa: E402

#: the extrinsic's rotation error given to the replay (body frame, rad)
PHI = np.array([0.02, -0.01, 0.03])


@pytest.fixture(scope='module')
def robot_bag(tmp_path_factory) -> tuple[Path, Path]:
    tmp = tmp_path_factory.mktemp('camera_source')
    write_robot_bag(tmp / 'in', tmp / 'gt.tum')
    (tmp / 'inputs.yaml').write_text(
        'odom0:\n  keyframe_travel_m: 11.0\n  track:\n    mode: heading\n    swaths: 2\n'
        '  default_noise_percent: 1.0\n  default_depth_m: 110.0\n')
    return tmp / 'in', tmp / 'gt.tum'


def _replay(bag: tuple[Path, Path], out: Path, T_base_cam: np.ndarray, *extra: str) -> int:
    from ga_ros.cli.main import main

    p, q = se3.to_pos_quat(T_base_cam)
    return main(['replay', str(bag[0]), '--odom-topic', '/odom', '--input-config',
                 str(bag[0].parent / 'inputs.yaml'),
                 '--left-image', '/cam/left/image/compressed',
                 '--right-image', '/cam/right/image/compressed',
                 '--left-info', '/cam/left/camera_info', '--right-info', '/cam/right/camera_info',
                 '--camera-extrinsic', *map(str, [*p, *q]), '--ground-truth', str(bag[1]),
                 '--out', str(out), '--no-plot', '--no-progress', *extra])


def test_calibrate_camera_recovers_the_extrinsic_rotation(robot_bag, tmp_path: Path,
                                                          capsys) -> None:
    """The extrinsic given as ``exp(-phi) R_true``: each axis of the camera's parameters
    within 3 sigma of ``phi``, printed and in ``summary.json``; the right extrinsic: none
    significant. Without the switch no calibration runs and the camera's connections are their
    own variance group, ``cam0.cross``."""
    T_off = T_BASE_CAM.copy()
    T_off[:3, :3] = so3.exp(-PHI) @ T_BASE_CAM[:3, :3]
    assert _replay(robot_bag, tmp_path / 'off', T_off, '--calibrate-camera', 'cam0') == 0
    text = capsys.readouterr().out
    summary = json.loads((tmp_path / 'off' / 'summary.json').read_text())
    cam = [p for p in summary['calibration']['parameters'] if p['source'] == 'cam0']
    assert [p['name'] for p in cam] == ['extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz']
    for p, truth in zip(cam, PHI):
        assert p['estimated'] and abs(p['value'] - truth) < 3 * p['sigma'], cam
        assert p['sigma'] < 0.005, cam
        assert f"cam0         {p['name']} {p['value']:.6g} +- " in text, text

    assert _replay(robot_bag, tmp_path / 'true', T_BASE_CAM, '--calibrate-camera', 'cam0') == 0
    capsys.readouterr()
    summary = json.loads((tmp_path / 'true' / 'summary.json').read_text())
    cam = [p for p in summary['calibration']['parameters'] if p['source'] == 'cam0']
    assert len(cam) == 3 and not any(p['estimated'] for p in cam), cam

    assert _replay(robot_bag, tmp_path / 'plain', T_off) == 0
    capsys.readouterr()
    summary = json.loads((tmp_path / 'plain' / 'summary.json').read_text())
    assert not summary.get('calibration')
    groups = set(summary['variance_components']) - {'_estimation'}
    assert groups == {'odom0', 'cam0.cross'}, groups


def test_with_calibrate_the_camera_is_estimated_online_too(robot_bag, tmp_path: Path,
                                                          capsys) -> None:
    """``--calibrate --calibrate-camera cam0``: the last online estimate has the camera's
    rotation within 3 sigma (published, not applied), the final batch too."""
    T_off = T_BASE_CAM.copy()
    T_off[:3, :3] = so3.exp(-PHI) @ T_BASE_CAM[:3, :3]
    assert _replay(robot_bag, tmp_path / 'on', T_off, '--calibrate', '--calibrate-camera',
                   'cam0') == 0
    capsys.readouterr()
    summary = json.loads((tmp_path / 'on' / 'summary.json').read_text())
    for block in ('online_calibration', 'calibration'):
        cam = [p for p in summary[block]['parameters'] if p['source'] == 'cam0']
        assert len(cam) == 3, summary[block]
        for p, truth in zip(cam, PHI):
            assert p['estimated'] and abs(p['value'] - truth) < 3 * p['sigma'], (block, p)


def test_an_unknown_camera_is_refused_before_reading(robot_bag, tmp_path: Path,
                                                     capsys) -> None:
    """The inputs name their sources: an unknown name stops the replay at once, listing them."""
    assert _replay(robot_bag, tmp_path / 'x', T_BASE_CAM, '--calibrate-camera', 'cam1') == 1
    err = capsys.readouterr().err
    assert "'cam1': no such source" in err and 'cam0, odom0' in err, err
    assert not (tmp_path / 'x' / 'summary.json').exists()


def _sample(n_tracks: int = 3) -> tuple[list[Measurement], object]:
    from ga_ros.replay.samples import aerial_sample

    s = aerial_sample(n_tracks=n_tracks, positions_per_swath=30, seed=3)
    return s.measurements, s.ground_truth


def test_naming_a_source_keeps_the_variance_groups(tmp_path: Path) -> None:
    """A stereo VO's motions and cross-track connections with the source ``cam0`` (carried by
    the measurement encoding) or none: the same final batch with the variance components
    applied, bit for bit, under the groups ``cam0`` / ``cam0.cross`` instead of ``motion`` /
    ``cross``."""
    from ga_ros.replay.config import ReplayConfig
    from ga_ros.replay.pipeline import replay
    from ga_ros.replay.samples import write_measurement_bag

    ms, gt = _sample()
    assert not any(m.source for m in ms) and any(m.kind == 'cross' for m in ms)
    out = {}
    for name in ('', 'cam0'):
        bag = write_measurement_bag(tmp_path / f'in{name}', [replace(m, source=name)
                                                             for m in ms], gt)
        res = replay(bag, tmp_path / f'out{name}', ReplayConfig(plot=False,
                                                                variance_components='apply'))
        out[name] = ((tmp_path / f'out{name}' / 'trajectory_ga.tum').read_bytes(),
                     res.variance_components)
    assert out[''][0] == out['cam0'][0]
    plain, named = out[''][1], out['cam0'][1]
    assert set(plain) - {'_estimation'} == {'motion', 'cross'}, plain
    assert set(named) - {'_estimation'} == {'cam0', 'cam0.cross'}, named
    for a, b in (('motion', 'cam0'), ('cross', 'cam0.cross')):
        assert plain[a]['factor'] == named[b]['factor'], (plain[a], named[b])


def test_an_unknown_camera_in_a_measurements_bag_is_refused_at_the_final_batch(
        tmp_path: Path) -> None:
    """A measurements bag names its sources in its data: an unknown name is the replay's
    error at the final batch (outputs written, the online estimate), listing them."""
    from ga_ros.replay.config import ReplayConfig
    from ga_ros.replay.pipeline import replay
    from ga_ros.replay.samples import write_measurement_bag

    ms, gt = _sample(2)
    bag = write_measurement_bag(tmp_path / 'in', [replace(m, source='cam0') for m in ms], gt)
    with pytest.raises(FormatError, match=r"'camX': no such source; the sources of the "
                                          r'measurements are: cam0 '):
        replay(bag, tmp_path / 'out', ReplayConfig(plot=False, calibrate_cameras=('camX',)))
    assert (tmp_path / 'out' / 'trajectory_ga.tum').exists()


def test_variance_group_and_source() -> None:
    """A named source's cross-track connections: group ``<source>.cross``, source their
    own; unnamed ones as before."""
    z, cov = np.zeros(6), np.eye(6)
    m = Measurement(0, 1, 0, 0, z, cov, 0, 'cross', 'cam0')
    assert variance_group(m) == 'cam0.cross' and source_or_group(m) == 'cam0'
    m = replace(m, source='')
    assert variance_group(m) == 'cross' == source_or_group(m)
    m = replace(m, kind='consecutive')
    assert variance_group(m) == 'motion' == source_or_group(m)
    assert variance_group(replace(m, source='cam0')) == 'cam0'


def test_the_stereo_front_end_names_its_measurements() -> None:
    """Every measurement the stereo front end lets out carries the camera's ``source`` (with
    or without an extrinsic); ``--vo source=NAME`` / ``vo_node``'s ``source`` set it, a name
    the encoding cannot carry is refused."""
    from ga_ros.core.extrinsic import Extrinsic
    from ga_ros.pipeline.stereo import FrontEndConfig, StereoFrontEnd, front_end_config_from_params

    m = Measurement.from_pose(0, 1, 0, 0, se3.exp(np.array([1.0, 0, 0, 0, 0, 0.1])),
                              np.eye(6) * 1e-4)
    front = StereoFrontEnd()
    assert front._to_base(m).source == 'cam0'
    front = StereoFrontEnd(front_end_config_from_params({'source': 'down_cam'}))
    assert front._to_base(m).source == 'down_cam'
    front.set_extrinsic(Extrinsic(T_BASE_CAM))
    based = front._to_base(m)
    assert based.source == 'down_cam'
    np.testing.assert_allclose(based.T_src_dst,
                               T_BASE_CAM @ m.T_src_dst @ se3.inverse(T_BASE_CAM), atol=1e-12)
    with pytest.raises(InputError, match='camera source'):
        FrontEndConfig(source='x' * 37)
    with pytest.raises(InputError, match='camera source'):
        FrontEndConfig(source='')


def test_command_line_calibrate_camera() -> None:
    """``--calibrate-camera`` (repeatable) sets ``ReplayConfig.calibrate_cameras``."""
    import argparse

    from ga_ros.cli.commands.replay import add_replay_arguments, replay_config

    p = argparse.ArgumentParser()
    add_replay_arguments(p)
    assert replay_config(p.parse_args([]), progress=False).calibrate_cameras == ()
    cfg = replay_config(p.parse_args(['--calibrate-camera', 'cam0', '--calibrate-camera',
                                      'cam1']), progress=False)
    assert cfg.calibrate_cameras == ('cam0', 'cam1') and not cfg.calibrate
