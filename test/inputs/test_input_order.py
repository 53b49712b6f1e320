"""Inputs in a stable order: the first ``--odom-topic`` (or ``odom0``) defines the keyframes,
whatever sections an ``--input-config`` file has; a section for an input that is not given is
an error naming it (exit 2).

Fixture: a ROS 1 bag with two SLAM systems' ``geometry_msgs/PoseStamped`` outputs, A at 20 Hz
(drifting) and B at 10 Hz (on the true path), as :mod:`bag_fixtures` writes them.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from bag_fixtures import POSE_STAMPED, rectangle_drive, ros1_pose_stamped_msg, write_ros1_bag

from ga_ros.cli.main import main
from ga_ros.errors import UsageError
from ga_ros.pipeline.inputs import specs_from_mapping

T0_NS = 1_700_000_000_000_000_000


@pytest.fixture(scope='module')
def slam_bag(tmp_path_factory) -> tuple[Path, int, int]:
    """(bag, samples of A, samples of B)."""
    tmp = tmp_path_factory.mktemp('two_slam')
    a = rectangle_drive(0.5, 20.0, T0_NS)
    b = rectangle_drive(0.5, 10.0, T0_NS + 30_000_000)
    rows = [(int(s), '/slam_a/pose', POSE_STAMPED, ros1_pose_stamped_msg(T, int(s)))
            for s, T in zip(a.stamps_ns, a.T_odom)]
    rows += [(int(s) + 1_000_000, '/slam_b/pose', POSE_STAMPED, ros1_pose_stamped_msg(T, int(s)))
             for s, T in zip(b.stamps_ns, b.T_true)]
    return write_ros1_bag(tmp / 'slam.bag', rows), len(a.stamps_ns), len(b.stamps_ns)


def _sources(text: str) -> list[str]:
    return [line.strip() for line in text.splitlines() if line.strip().startswith('source: ')]


def test_first_odom_topic_defines_the_keyframes_whatever_the_config_has(
        slam_bag, tmp_path: Path, capsys) -> None:
    bag, n_a, n_b = slam_bag
    cfg = tmp_path / 'c.yaml'
    cfg.write_text('odom1:\n  keyframe_travel_m: 2.0\n')
    args = ['replay', str(bag), '--odom-topic', '/slam_a/pose', '--odom-topic', '/slam_b/pose',
            '--input-config', str(cfg)]
    assert main(args + ['--info']) == 0
    sources = _sources(capsys.readouterr().out)
    assert sources[0].startswith('source: odom0 /slam_a/pose'), sources
    # the section's settings reach the input it names
    assert sources[1].startswith('source: odom1 /slam_b/pose') and 'every 2 m' in sources[1]
    rc = main(args + ['--out', str(tmp_path / 'out'), '--no-plot', '--json'])
    out = capsys.readouterr().out
    assert rc == 0, out
    import json

    stats = json.loads(out)['source_stats']
    assert stats['odom0']['samples'] == n_a and 'keyframes' in stats['odom0']  # keyframe source
    assert stats['odom1']['samples'] == n_b and 'not_covered' in stats['odom1']  # measured on A's


def test_config_sections_with_topics_odom0_first(slam_bag, tmp_path: Path, capsys) -> None:
    """Without --odom-topic, sections that give their own topic: odom0 first, whatever the
    file order."""
    bag, _, _ = slam_bag
    cfg = tmp_path / 'c.yaml'
    cfg.write_text('odom1:\n  topic: /slam_b/pose\nodom0:\n  topic: /slam_a/pose\n')
    assert main(['replay', str(bag), '--input-config', str(cfg), '--info']) == 0
    sources = _sources(capsys.readouterr().out)
    assert [s.split()[1:3] for s in sources] == [['odom0', '/slam_a/pose'],
                                                 ['odom1', '/slam_b/pose']]


def test_section_for_an_input_not_given_is_an_error_naming_it(slam_bag, tmp_path: Path,
                                                              capsys) -> None:
    bag, _, _ = slam_bag
    cfg = tmp_path / 'c.yaml'
    cfg.write_text('odom0:\n  keyframe_travel_m: 2.0\nodom2:\n  keyframe_travel_m: 3.0\n')
    rc = main(['replay', str(bag), '--odom-topic', '/slam_a/pose', '--odom-topic',
               '/slam_b/pose', '--input-config', str(cfg), '--out', str(tmp_path / 'out')])
    err = capsys.readouterr().err
    assert rc == 2
    assert "'odom2'" in err and 'odom0 = /slam_a/pose' in err and 'odom1' in err, err
    assert not (tmp_path / 'out').exists()  # refused before anything was written
    with pytest.raises(UsageError, match="'odom1'"):
        specs_from_mapping({'odom1': {'keyframe_travel_m': 2.0}})
