"""Standard inputs in the replay: bags written here with rosbags, as other robots record them.

A robot drives a 20 m x 10 m rectangle twice at 1 m/s (odometry at 10 Hz with a heading drift);
the bag holds only that stream (+ ``/tf``), as a Nav2 TurtleBot recording does.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    ODOMETRY,
    POSE_COV_STAMPED,
    POSE_STAMPED,
    RECTANGLE_LAP_S,
    Drive,
    odometry_msg,
    pose_cov_stamped_msg,
    pose_stamped_msg,
    rectangle_drive,
    ros1_odometry_msg,
    write_ros1_bag,
    write_tf,
    write_tf_static,
)

from ga_ros.core.tracks import TrackRules
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.inputs.messages import constraint_frames
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import ns_to_stamp
from ga_ros.io.bag_writer import BagWriter
from ga_ros.io.groundtruth import read_ground_truth_file
from ga_ros.io.trajectory import read_tum, write_tum
from ga_ros.pipeline.inputs import InputSpec
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.inputs import InputTopics
from ga_ros.replay.pipeline import replay

RATE_HZ = 10.0
T0_NS = 1_700_000_000_000_000_000


def _scenario(laps: float = 2.0) -> Drive:
    return rectangle_drive(laps, RATE_HZ, T0_NS)


def write_odom_bag(path: Path, kind: str = 'odom', constraints: bool = False) -> np.ndarray:
    """The robot's bag: ``/odom`` (all-zero covariance) or a pose stream, ``/tf``; optionally
    loop closures on ``/loops`` between the two laps. Returns the ground truth."""
    stamps, gt, odom = _scenario()
    with BagWriter(path) as bag:
        write_tf_static(bag, [('base_link', 'laser', np.eye(4))], int(stamps[0]))
        for s, T in zip(stamps, odom):
            s = int(s)
            if kind == 'odom':
                bag.write('/odom', ODOMETRY, odometry_msg(T, s), s)
            elif kind == 'pose_cov':
                cov = np.diag([0.05] * 3 + [0.01] * 3) ** 2
                bag.write('/pose', POSE_COV_STAMPED, pose_cov_stamped_msg(T, s, cov), s)
            else:
                bag.write('/pose', POSE_STAMPED, pose_stamped_msg(T, s), s)
            write_tf(bag, 'odom', 'base_link', T, s)
        if constraints:
            n_lap = int(RECTANGLE_LAP_S * RATE_HZ)
            cov = np.diag([0.02] * 3 + [0.002] * 3) ** 2
            for i in range(0, n_lap, 50):
                j = i + n_lap
                a, b = int(stamps[i]), int(stamps[j])
                fa, fb = constraint_frames('stamp', a, b)
                msg = odometry_msg(se3.relative(gt[i], gt[j]), b, frame=fa, child=fb,
                                   pose_cov=cov)
                bag.write('/loops', ODOMETRY, msg, int(stamps[-1]) + 1 + i)
    return gt


def _config(topic: str, constraints: str = '', track_mode: str = 'distance') -> ReplayConfig:
    from ga_ros.inputs.odometry import OdometryInputConfig

    spec = InputSpec(topic, 'odometry', OdometryInputConfig(
        'odom0', keyframe_travel_m=1.0, track=TrackRules(track_mode, length_m=20.0)))
    return ReplayConfig(inputs=InputTopics((spec,), constraints), plot=False)


def _ate(T_est: np.ndarray, T_gt: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((T_est[:, :3, 3] - T_gt[:, :3, 3]) ** 2, axis=1))))


def _read(bag_dir: Path, topic: str) -> list:
    with BagReader(bag_dir) as bag:
        return [m for m in bag.messages([topic])]


def test_odometry_with_zero_covariance_gives_path_tf_and_evo_streams(tmp_path: Path) -> None:
    write_odom_bag(tmp_path / 'in')
    res = replay(tmp_path / 'in', tmp_path / 'out', _config('/odom'))
    assert res.source == 'inputs'
    n_keyframes = res.source_stats['odom0']['keyframes']
    assert res.n_nodes == n_keyframes > 100  # ~120 m of travel, one keyframe per metre
    assert res.source_stats['odom0']['default_covariances'] == res.n_measurements
    assert 'DEFAULT covariance' in res.source_stats['warnings']['first']
    out = Path(res.files['bag'])
    tf = _read(out, '/tf')
    frames = {(t.header.frame_id, t.child_frame_id) for m in tf for t in m.msg.transforms}
    assert {('map', 'odom'), ('odom', 'base_link')} <= frames
    assert len(_read(out, '/tf_static')) == 1
    odom_out = _read(out, '/ga/corrected_odom')
    poses = _read(out, '/ga/corrected_pose')
    assert len(odom_out) == len(poses) == res.n_nodes
    assert odom_out[0].msg.child_frame_id == 'base_link'
    # map -> odom is the correction: map->odom * odom->base of the last keyframe = corrected
    corrected = read_tum(res.files['trajectory_ga'])
    last_map_odom = [t for m in tf for t in m.msg.transforms
                     if t.child_frame_id == 'odom'][-1].transform
    T_map_odom = se3.from_pos_quat(
        np.array([last_map_odom.translation.x, last_map_odom.translation.y,
                  last_map_odom.translation.z]),
        np.array([last_map_odom.rotation.x, last_map_odom.rotation.y, last_map_odom.rotation.z,
                  last_map_odom.rotation.w]))
    assert T_map_odom.shape == (4, 4)
    assert len(corrected) == res.n_nodes
    # TUM stamps: one per keyframe, strictly increasing, the first at the bag's first sample
    assert corrected.stamps_ns[0] == T0_NS
    assert np.all(np.diff(corrected.stamps_ns) > 0)


@pytest.mark.parametrize('kind', ['pose_cov', 'pose'])
def test_pose_streams(tmp_path: Path, kind: str) -> None:
    write_odom_bag(tmp_path / 'in', kind=kind)
    res = replay(tmp_path / 'in', tmp_path / 'out', _config('/pose'))
    st = res.source_stats['odom0']
    assert res.n_nodes == st['keyframes'] > 100
    if kind == 'pose':  # no covariance at all: every measurement gets the default
        assert st['default_covariances'] == res.n_measurements
    else:  # a localiser's independent pose covariances are not a random walk: default too,
        # unless pose_independent is chosen; the stream itself must have been read
        assert st['samples'] == 1200


def test_external_loop_closures_by_stamp_correct_the_drift(tmp_path: Path) -> None:
    gt = write_odom_bag(tmp_path / 'in', constraints=True)
    stamps, _, odom = _scenario()
    write_tum(tmp_path / 'gt.tum', stamps, gt)
    base = _config('/odom', '/loops', track_mode='none')
    cfg = ReplayConfig(inputs=base.inputs, plot=False, ground_truth_file=str(tmp_path / 'gt.tum'))
    res = replay(tmp_path / 'in', tmp_path / 'out', cfg)
    assert res.source_stats['odom0']['constraints'] == 12
    assert res.rejected == {}
    ga = read_tum(res.files['trajectory_ga'])
    idx = np.searchsorted(stamps, ga.stamps_ns)
    assert np.array_equal(stamps[idx], ga.stamps_ns)  # TUM stamps are the samples' stamps
    T_odom = gt[0] @ se3.inverse(odom[0]) @ odom[idx]
    # a heading bias: 3.1 m ATE of the odometry, 0.74 m corrected (one closure per 5 m)
    assert _ate(ga.T_world_node, gt[idx]) < 0.35 * _ate(T_odom, gt[idx])
    assert res.errors['ga'].ate_raw < 0.35 * _ate(T_odom, gt[idx])
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert summary['source'] == 'inputs'


def test_ros1_bag(tmp_path: Path) -> None:
    stamps, _, odom = _scenario(laps=0.5)
    path = write_ros1_bag(tmp_path / 'robot.bag', [
        (int(s), '/odom', ODOMETRY, ros1_odometry_msg(T, int(s))) for s, T in zip(stamps, odom)])
    res = replay(path, tmp_path / 'out', _config('/odom'))
    assert res.n_nodes == res.source_stats['odom0']['keyframes'] >= 29


def test_odometry_bag_without_options_names_the_option(tmp_path: Path) -> None:
    write_odom_bag(tmp_path / 'in')
    with pytest.raises(FormatError, match='ga-ros replay .* --odom-topic /odom'):
        replay(tmp_path / 'in', tmp_path / 'out', ReplayConfig(plot=False))


def test_unsupported_storage_says_what_to_give(tmp_path: Path) -> None:
    p = tmp_path / 'data.txt'
    p.write_text('x')
    with pytest.raises(FormatError, match='ROS 1 .bag'):
        replay(p, tmp_path / 'out', _config('/odom'))


def test_missing_input_topic_lists_the_bag(tmp_path: Path) -> None:
    write_odom_bag(tmp_path / 'in')
    with pytest.raises(FormatError, match=r'missing topic /wheel_odom.*/odom \['):
        replay(tmp_path / 'in', tmp_path / 'out', _config('/wheel_odom'))


def test_euroc_and_tum_ground_truth_files(tmp_path: Path) -> None:
    stamps, gt, _ = _scenario(laps=0.1)
    p, q = se3.to_pos_quat(gt)
    lines = ['#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], '
             'q_RS_y [], q_RS_z [], v_RS_R_x [m s^-1]']
    lines += [f'{s},{a[0]},{a[1]},{a[2]},{b[3]},{b[0]},{b[1]},{b[2]},0.0'
              for s, a, b in zip(stamps, p, q)]
    (tmp_path / 'data.csv').write_text('\n'.join(lines) + '\n')
    write_tum(tmp_path / 'gt.tum', stamps, gt)
    for name in ('data.csv', 'gt.tum'):
        traj = read_ground_truth_file(tmp_path / name).trajectory
        assert np.array_equal(traj.stamps_ns, stamps)
        assert np.allclose(traj.T_world_node, gt, atol=1e-9)
    (tmp_path / 'bad.csv').write_text('1403636579758555392,1,2,3,2,0,0,0\n')
    with pytest.raises(FormatError, match='not unit length'):
        read_ground_truth_file(tmp_path / 'bad.csv')


def test_stamp_helpers_round_trip() -> None:
    assert ns_to_stamp(T0_NS + 5).nanosec == 5


def test_first_node_stamp_without_ground_truth(tmp_path: Path) -> None:
    """Measurement encoding without ground truth: node 0's stamp is one node interval before
    node 1's (not node 1's, which made evo pair it with the wrong pose)."""
    from ga_ros.replay.samples import aerial_sample, write_measurement_bag

    s = aerial_sample(n_tracks=2)
    write_measurement_bag(tmp_path / 'm', s.measurements, None)
    res = replay(tmp_path / 'm', tmp_path / 'out', ReplayConfig(plot=False))
    tum = read_tum(res.files['trajectory_ga'])
    gt = s.ground_truth.stamps_ns
    assert np.all(np.diff(tum.stamps_ns) > 0)
    assert tum.stamps_ns[0] == gt[1] - np.median(np.diff(gt[1:]))


def test_cli_one_command_for_an_odometry_bag(tmp_path: Path, capsys) -> None:
    from ga_ros.cli.main import main

    write_odom_bag(tmp_path / 'in')
    (tmp_path / 'inputs.yaml').write_text('odom0:\n  keyframe_travel_m: 2.0\n'
                                          '  track:\n    mode: distance\n    length_m: 20.0\n')
    rc = main(['replay', str(tmp_path / 'in'), '--odom-topic', '/odom', '--input-config',
               str(tmp_path / 'inputs.yaml'), '--out', str(tmp_path / 'out'), '--no-plot'])
    text = capsys.readouterr().out
    assert rc == 0, text
    assert 'odom0: 1200 samples, 60 keyframes' in text and 'DEFAULT covariance' in text
    assert len(read_tum(tmp_path / 'out' / 'trajectory_ga.tum')) == 60
    assert main(['replay', str(tmp_path / 'in'), '--odom-topic', '/odom', '--info']) == 0
    assert 'source: odom0 /odom (nav_msgs/msg/Odometry)' in capsys.readouterr().out
    assert main(['replay', str(tmp_path / 'in'), '--info']) == 2  # no input named: says so
    assert 'no usable input' in capsys.readouterr().out


def test_covariance_policy_reject_or_repair(tmp_path: Path) -> None:
    """One measurement with an indefinite covariance: rejected by default, repaired on request
    (eigenvalue clipping: same eigenvectors, the negative eigenvalue raised to the floor)."""
    from ga_ros.core.measurement import Measurement
    from ga_ros.io.bag_messages import measurement_to_odometry
    from ga_ros.pipeline.inputs import decode_measurement
    from ga_ros.replay.samples import aerial_sample, write_measurement_bag

    s = aerial_sample(n_tracks=2)
    ms = list(s.measurements)
    k = 5
    bad = ms[k].cov.copy()
    w, V = np.linalg.eigh(bad)
    w[0] = -w[0]                                   # one negative eigenvalue
    bad = V @ np.diag(w) @ V.T
    m = ms[k]
    ms[k] = Measurement(m.src_id, m.dst_id, m.src_track, m.dst_track, m.z, bad, m.stamp_ns,
                        m.kind)
    msg = measurement_to_odometry(ms[k])
    with pytest.raises(InputError, match='positive definite'):
        decode_measurement(msg, 'reject')
    fixed = decode_measurement(msg, 'repair').cov
    w2, V2 = np.linalg.eigh(fixed)
    assert w2.min() > 0 and np.allclose(np.sort(w2)[1:], np.sort(w)[1:], rtol=1e-9)
    write_measurement_bag(tmp_path / 'm', ms, s.ground_truth)
    res = replay(tmp_path / 'm', tmp_path / 'a', ReplayConfig(plot=False))
    assert res.rejected == {'decode': 1}
    res = replay(tmp_path / 'm', tmp_path / 'b', ReplayConfig(plot=False,
                                                             covariance_policy='repair'))
    assert res.rejected == {} and res.n_measurements == len(ms)
