"""A robot that does not move: one keyframe, a stationary trajectory, exit 0 and a note.

Two recordings written here with rosbags: a ground robot's ``/odom`` standing still for 10 s
(with the encoder jitter of a real driver), and a short stereo recording of a hovering drone
(rendered by :mod:`ga_ros.sim.stereo`, the camera wobbling by a centimetre).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    ODOMETRY,
    POSE_STAMPED,
    SAMPLE_STEREO_TOPICS,
    odometry_msg,
    pose_stamped_msg,
    stereo_rows,
    write_rows,
)

from ga_ros.cli.main import main
from ga_ros.geometry import se3
from ga_ros.io.bag_writer import BagWriter, tf_message, transform_msg
from ga_ros.io.trajectory import read_tum

T0_NS = 1_700_000_000_000_000_000


def write_still_odometry(path: Path, seconds: float = 10.0, rate_hz: float = 20.0) -> None:
    rng = np.random.default_rng(1)
    T_still = se3.from_translation_rotvec(np.array([2.0, 1.0, 0.0]), np.array([0, 0, 0.3]))
    with BagWriter(path) as bag:
        for k in range(int(seconds * rate_hz)):
            s = T0_NS + int(k * 1e9 / rate_hz)
            jitter = se3.exp(np.concatenate([rng.normal(0, 1e-4, 3), rng.normal(0, 1e-5, 3)]))
            bag.write('/odom', ODOMETRY, odometry_msg(T_still @ jitter, s), s)


def write_hovering_stereo(path: Path, frames: int = 8) -> None:
    from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene

    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=4, seed=2))
    rig = StereoRig.for_size(320, 240)
    scene = make_scene(survey, rig, seed=2)
    rng = np.random.default_rng(2)
    T_hover = survey.T_world_cam[1]
    with BagWriter(path) as bag:
        bag.write('/tf_static', 'tf2_msgs/msg/TFMessage',   # the camera is the base frame
                  tf_message([transform_msg('base_link', 'left', np.eye(4), T0_NS)]), T0_NS)
        for k in range(frames):
            s = T0_NS + k * 200_000_000
            T = T_hover @ se3.exp(np.concatenate([rng.normal(0, 0.01, 3),
                                                  rng.normal(0, 1e-4, 3)]))
            left, right = scene.render_pair(T, rng)
            write_rows(bag, stereo_rows(rig, left, right, s, topics=SAMPLE_STEREO_TOPICS))


def _replay(args: list[str], capsys) -> tuple[int, str]:
    rc = main(['replay', *args, '--no-plot', '--no-progress'])
    out = capsys.readouterr()
    return rc, out.out + out.err


def test_standing_odometry_robot_gives_a_stationary_trajectory(tmp_path: Path, capsys) -> None:
    write_still_odometry(tmp_path / 'in')
    rc, text = _replay([str(tmp_path / 'in'), '--odom-topic', '/odom', '--out',
                        str(tmp_path / 'out')], capsys)
    assert rc == 0, text
    assert 'the robot did not move: 1 keyframe, stationary trajectory written' in text
    tum = read_tum(tmp_path / 'out' / 'trajectory_ga.tum')
    assert len(tum) == 1 and tum.stamps_ns[0] == T0_NS
    np.testing.assert_allclose(tum.T_world_node[0], np.eye(4), atol=1e-9)  # the datum
    assert (tmp_path / 'out' / 'summary.json').exists()


def test_hovering_drone_stereo_gives_a_stationary_trajectory(tmp_path: Path, capsys) -> None:
    pytest.importorskip('cv2')
    write_hovering_stereo(tmp_path / 'in')
    rc, text = _replay([str(tmp_path / 'in'), '--out', str(tmp_path / 'out')], capsys)
    assert rc == 0, text
    assert 'the robot did not move: 1 keyframe, stationary trajectory written' in text
    assert 'not a keyframe' in (tmp_path / 'out' / 'summary.json').read_text()
    assert len(read_tum(tmp_path / 'out' / 'trajectory_ga.tum')) == 1


def test_a_bag_whose_measurements_are_all_rejected_still_fails(tmp_path: Path, capsys) -> None:
    """Only a still robot is a valid empty run: no keyframe at all (every sample malformed)
    still exits 1 with the reasons."""
    with BagWriter(tmp_path / 'in') as bag:
        for k in range(5):
            s = T0_NS + k * 100_000_000
            msg = pose_stamped_msg(np.eye(4), s)
            msg.pose.orientation.w = 0.0  # not a rotation
            bag.write('/pose', POSE_STAMPED, msg, s)
    rc, text = _replay([str(tmp_path / 'in'), '--odom-topic', '/pose', '--out',
                        str(tmp_path / 'out')], capsys)
    assert rc == 1, text
    assert 'no valid measurements' in text and 'did not move' not in text
