"""Two namespaced robots on one DDS domain (issue 14 item 2), each with its own stereo bag,
``vo_node`` and ``alignment_node`` (``ga_ros.tools.fleet``): each corrected path comes only
from that robot's own measurements."""

from __future__ import annotations

from pathlib import Path

import pytest

from ga_ros.tools import fleet

SAMPLE_STAMP_NS = 1_700_000_000 * 1_000_000_000   # ga_ros.replay.samples.BASE_STAMP_NS
OFFSET_S = 10_000.0                                # robot2's bag starts this much later


def test_every_robot_process_lives_in_its_namespace(tmp_path: Path) -> None:
    cmds = fleet.robot_commands('robot2', tmp_path / 'bag', tmp_path, 5.0, 3.0, 60.0)
    for role, argv in cmds.items():
        ros = argv[argv.index('--ros-args'):]
        assert '__ns:=/robot2' in ros, role
        if role != 'mapping':  # the simulated clock of each robot is its own
            assert '/clock:=/robot2/clock' in ros, role
    play = cmds['play']
    for topic in fleet.STEREO_TOPICS:
        assert f'{topic}:=/robot2{topic}' in play
    # the nodes' own topics are relative (config/*.yaml), the TF frames get the robot's prefix
    assert 'left_image_topic:=stereo/left/image_raw/compressed' in cmds['vo']
    assert 'map_frame:=robot2/map' in cmds['alignment']


@pytest.mark.ros
@pytest.mark.slow
def test_two_robots_each_path_from_its_own_measurements(tmp_path: Path) -> None:
    # two short surveys of different sizes and terrain (the bundled sample is 3x longer and
    # would only make the test slower)
    first = fleet.make_second_bag(tmp_path / 'robot1_bag', 0.0, positions_per_swath=10, seed=4)
    second = fleet.make_second_bag(tmp_path / 'robot2_bag', OFFSET_S)
    res = fleet.run_fleet(tmp_path / 'run', {'robot1': first, 'robot2': second}, rate=10.0,
                          timeout_s=200)
    print(fleet.format_result(res))
    assert res.ok, res.errors
    r1, r2 = res.robots
    boundary = SAMPLE_STAMP_NS + int(OFFSET_S * 1e9)
    for r in (r1, r2):
        # the path equals the in-process replay of the measurements this robot's mapping node
        # recorded (checked in run_fleet: same poses, same stamps, <= 1e-6 m)
        assert r.measurements > 30 and r.path_poses == r.replay_poses > 10, r
        assert r.max_diff_vs_replay_m <= 1e-6
    # nothing crossed: every measurement and pose of a robot has a stamp of its own bag
    assert r1.stamp_range_ns[1] < boundary and r1.path_stamp_range_ns[1] < boundary
    assert r2.stamp_range_ns[0] >= boundary and r2.path_stamp_range_ns[0] >= boundary
    assert (r1.measurements, r1.path_poses) != (r2.measurements, r2.path_poses)
