"""First contact: a bag without a usable default input gets the exact command for its topics.

Bags shaped like other people's: a Nav2 recording (``/odom`` with all-zero covariance,
AMCL's ``/amcl_pose``), a ROS 1 bag of two SLAM systems' ``PoseStamped`` outputs beside a
motion-capture ground truth, a bag with nothing the replay reads. The command printed is run
as printed, and must replay the bag.
"""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    ODOMETRY,
    POSE_COV_STAMPED,
    POSE_STAMPED,
    odometry_msg,
    pose_cov_stamped_msg,
    pose_stamped_msg,
    rectangle_drive,
    ros1_pose_stamped_msg,
    write_bag,
    write_ros1_bag,
    write_unknown_type_bag,
)

from ga_ros.cli.main import main
from ga_ros.io.bag import bag_info
from ga_ros.replay.suggest import suggest

T0_NS = 1_700_000_000_000_000_000


def _nav2_bag(path: Path) -> Path:
    """``/odom``, ``/amcl_pose`` (every 5th step), and RViz's ``/initialpose`` and Nav2's
    ``/goal_pose`` (commands, not inputs)."""
    drive = rectangle_drive(0.25, 10.0, T0_NS)
    cov = np.diag([0.05] * 3 + [0.01] * 3) ** 2
    rows = [(T0_NS - 10**9, '/initialpose', POSE_COV_STAMPED,
             pose_cov_stamped_msg(drive.T_true[0], T0_NS - 10**9, cov, frame='map'))]
    rows += [(T0_NS + k * 10**9, '/goal_pose', POSE_STAMPED,
              pose_stamped_msg(drive.T_true[-1], T0_NS + k * 10**9, frame='map'))
             for k in range(4)]
    for k, (s, T, T_odom) in enumerate(zip(drive.stamps_ns, drive.T_true, drive.T_odom)):
        rows.append((int(s), '/odom', ODOMETRY, odometry_msg(T_odom, int(s))))
        if k % 5 == 0:
            rows.append((int(s) + 1000, '/amcl_pose', POSE_COV_STAMPED,
                         pose_cov_stamped_msg(T, int(s), cov, frame='map')))
    return write_bag(path, rows)


def _slam_ros1_bag(path: Path) -> Path:
    drive = rectangle_drive(0.25, 10.0, T0_NS)
    rows = []
    for s, T, T_odom in zip(drive.stamps_ns, drive.T_true, drive.T_odom):
        s = int(s)
        rows.append((s, '/orb_slam/pose', POSE_STAMPED, ros1_pose_stamped_msg(T_odom, s)))
        rows.append((s + 1, '/vins/pose', POSE_STAMPED, ros1_pose_stamped_msg(T_odom, s)))
        rows.append((s + 2, '/vicon/base', POSE_STAMPED, ros1_pose_stamped_msg(T, s)))
    return write_ros1_bag(path, rows)


def _printed_command(text: str) -> list[str]:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip().startswith('ga-ros replay ')]
    assert len(lines) == 1, text
    return shlex.split(lines[0])


def _run_printed(argv: list[str], out: Path, capsys) -> str:
    assert argv[:2] == ['ga-ros', 'replay']
    rc = main(argv[1:] + ['--out', str(out), '--no-plot', '--no-progress'])
    text = capsys.readouterr().out
    assert rc == 0, text
    return text


def test_nav2_recording_gets_the_odometry_and_fixes_command(tmp_path, capsys):
    bag = _nav2_bag(tmp_path / 'nav2')
    assert main(['replay', str(bag), '--out', str(tmp_path / 'x')]) == 2
    err = capsys.readouterr().err
    assert 'no usable input' in err
    argv = _printed_command(err)
    assert argv == ['ga-ros', 'replay', str(bag), '--odom-topic', '/odom',
                    '--absolute-topic', '/amcl_pose']
    assert 'nav_msgs/msg/Odometry' in err
    assert 'geometry_msgs/msg/PoseWithCovarianceStamped' in err
    assert '/initialpose' not in err and '/goal_pose' not in err  # commands, not inputs
    assert not (tmp_path / 'x').exists()  # nothing written

    assert main(['replay', str(bag), '--info']) == 2
    out = capsys.readouterr().out
    assert '/amcl_pose' in out.split('cannot replay')[0]  # the listing comes first
    assert _printed_command(out.split('cannot replay')[1]) == argv

    text = _run_printed(argv, tmp_path / 'out', capsys)
    assert 'fix0' in text or 'absolute' in text
    assert (tmp_path / 'out' / 'trajectory_ga.tum').is_file()


def test_ros1_bag_of_two_slam_outputs_and_ground_truth(tmp_path, capsys):
    bag = _slam_ros1_bag(tmp_path / 'slam.bag')
    assert main(['replay', str(bag)]) == 2
    err = capsys.readouterr().err
    argv = _printed_command(err)
    assert argv == ['ga-ros', 'replay', str(bag), '--odom-topic', '/orb_slam/pose',
                    '--ground-truth-topic', '/vicon/base']
    assert '--odom-topic /vins/pose' in err  # the second stream is named with its option
    assert err.count('geometry_msgs/msg/PoseStamped') == 3
    text = _run_printed(argv, tmp_path / 'out', capsys)
    assert 'error vs ground truth' in text


def test_bag_with_nothing_readable_says_what_the_replay_reads(tmp_path, capsys):
    bag = write_unknown_type_bag(tmp_path / 'other')
    assert suggest(bag_info(bag)) is None
    assert main(['replay', str(bag)]) == 2
    err = capsys.readouterr().err
    assert 'replay it with' not in err
    assert '--odom-topic' in err and '--absolute-topic' in err and 'EuRoC' in err


def test_suggestion_prefers_odometry_named_odom_and_leaves_out_measurements(tmp_path):
    drive = rectangle_drive(0.05, 10.0, T0_NS)
    rows = []
    for s, T in zip(drive.stamps_ns, drive.T_odom):
        rows.append((int(s), '/ekf/pose', POSE_STAMPED, pose_stamped_msg(T, int(s))))
        rows.append((int(s), '/wheel/odom', ODOMETRY, odometry_msg(T, int(s))))
        rows.append((int(s), '/ga/measurements', ODOMETRY, odometry_msg(T, int(s))))
    info = bag_info(write_bag(tmp_path / 'b', rows))
    s = suggest(info, '/ga/measurements')
    assert s is not None
    assert s.odometry == '/wheel/odom'
    assert s.other_odometry == ('/ekf/pose',)
    assert s.absolutes == () and s.ground_truth == ''


def test_replay_help_describes_every_input_kind_and_recording_format(capsys):
    with pytest.raises(SystemExit):
        main(['replay', '--help'])
    text = capsys.readouterr().out
    for words in ('rosbag2', 'mcap', 'sqlite3', 'ROS 1', '.bag', 'EuRoC', 'sensor.yaml',
                  'KITTI', 'calib.txt', 'measurements', 'stereo pair', 'CameraInfo',
                  '--odom-topic', 'nav_msgs/Odometry', 'PoseStamped', '--absolute-topic',
                  'NavSatFix', 'AMCL', 'camera beside odom', '--camera-extrinsic',
                  'ground truth', 'exit code 2'):
        assert words in text, words
