"""``map -> odom`` from the first odometry message, replaying a bag shaped like a Nav2 TurtleBot
recording: ``/odom`` (``nav_msgs/Odometry``, all-zero covariance, drifting), ``/amcl_pose``
(``PoseWithCovarianceStamped`` in ``map``: x, y, yaw variances, zeros elsewhere, as AMCL sends)
starting before the first track ends, ``/tf`` with ``odom -> base_link`` and AMCL's own
``map -> odom``; header stamps in simulation time, log times on the wall clock.

The output's ``map -> odom`` is checked against the truth the bag was made from: present from
the first odometry message (the identity until the first fix), then ``map -> base_link`` within
the fixes' uncertainty of the true pose, no jump beyond it without a warning, header stamps
never back.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

import numpy as np
import pytest
from bag_fixtures import (
    ODOMETRY,
    POSE_COV_STAMPED,
    TF,
    odometry_msg,
    pose_cov_stamped_msg,
    rectangle_drive,
)

from ga_ros.geometry import se3
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_writer import BagWriter, tf_message, transform_msg

SIM_T0_NS = 41_300_000_000          # simulation time at the start of the recording
WALL_T0_NS = 1_765_000_000_000_000_000
RATE_HZ = 20.0
SIGMA_XY, SIGMA_YAW = 0.15, 0.03     # AMCL's stated sigmas (m, rad)
#: where AMCL's map has the odometry's origin
T_MAP_WORLD = se3.from_translation_rotvec(np.array([7.4, 7.5, 0.0]), np.array([0, 0, 0.3]))


class Nav2Bag(NamedTuple):
    stamps_ns: np.ndarray      # header stamps (sim time) of /odom
    log_ns: np.ndarray         # their log times (wall clock)
    T_odom: np.ndarray         # (n, 4, 4) odometry poses
    T_map_true: np.ndarray     # (n, 4, 4) true poses of the base in AMCL's map
    amcl_log_ns: np.ndarray    # log times of /amcl_pose


def write_nav2_bag(path: Path, seed: int = 3, yaw_known: bool = True) -> Nav2Bag:
    """One lap of a 20 x 10 m rectangle at 1 m/s (:func:`bag_fixtures.rectangle_drive`), odometry
    at 20 Hz drifting in heading, AMCL at 2 Hz from 0.7 s on (its pose and its ``map -> odom``
    on ``/tf``), log times 1-4 ms after the stamps on another clock. ``yaw_known`` False: the
    fixes are positions only (a zero yaw variance: unknown, as AMCL's other zeros)."""
    rng = np.random.default_rng(seed)
    drive = rectangle_drive(1.0, RATE_HZ, SIM_T0_NS, yaw_per_step=1e-4)
    stamps = drive.stamps_ns
    log = WALL_T0_NS + (stamps - SIM_T0_NS) + rng.integers(1_000_000, 4_000_000, len(stamps))
    log = np.maximum.accumulate(log)
    T_map_true = np.array([T_MAP_WORLD @ T for T in drive.T_true])
    amcl_log = []
    cov = np.zeros((6, 6))
    cov[0, 0] = cov[1, 1] = SIGMA_XY ** 2
    cov[5, 5] = SIGMA_YAW ** 2 if yaw_known else 0.0
    with BagWriter(path) as bag:
        for k, (s, lg, T) in enumerate(zip(stamps, log, drive.T_odom)):
            s, lg = int(s), int(lg)
            bag.write('/odom', ODOMETRY, odometry_msg(T, s), lg)
            bag.write('/tf', TF, tf_message([transform_msg('odom', 'base_link', T, s)]), lg)
            if k >= 14 and k % 10 == 4:          # AMCL: 2 Hz from 0.7 s
                T_m = T_map_true[k] @ se3.from_translation_rotvec(
                    np.zeros(3), np.array([0, 0, rng.normal(0, SIGMA_YAW)]))
                T_m[:2, 3] += rng.normal(0, SIGMA_XY, 2)
                a_log = lg + 30_000_000           # AMCL's update takes 30 ms
                bag.write('/amcl_pose', POSE_COV_STAMPED,
                          pose_cov_stamped_msg(T_m, s, cov, 'map'), a_log)
                bag.write('/tf', TF, tf_message([transform_msg(
                    'map', 'odom', T_m @ se3.inverse(T), s)]), a_log)
                amcl_log.append(a_log)
    return Nav2Bag(stamps, log, drive.T_odom, T_map_true, np.array(amcl_log))


def _map_to_odom(bag_dir: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(log times, header stamps, (n, 4, 4) values) of the output's ``map -> odom``."""
    logs, stamps, T = [], [], []
    with BagReader(bag_dir) as bag:
        for m in bag.messages(['/tf']):
            for t in m.msg.transforms:
                if t.child_frame_id == 'odom':
                    assert t.header.frame_id == 'map'
                    tr, q = t.transform.translation, t.transform.rotation
                    logs.append(m.log_ns)
                    stamps.append(t.header.stamp.sec * 10**9 + t.header.stamp.nanosec)
                    T.append(se3.from_pos_quat(np.array([tr.x, tr.y, tr.z]),
                                               np.array([q.x, q.y, q.z, q.w])))
    return np.array(logs), np.array(stamps), np.array(T)


@pytest.mark.parametrize(('seed', 'yaw_known'), [(1, True), (3, True), (3, False)])
def test_nav2_recording_has_map_to_odom_from_the_first_odometry_message(
        tmp_path: Path, capsys, seed: int, yaw_known: bool) -> None:
    from ga_ros.cli.main import main

    b = write_nav2_bag(tmp_path / 'nav2', seed, yaw_known)
    rc = main(['replay', str(tmp_path / 'nav2'), '--odom-topic', '/odom', '--absolute-topic',
               '/amcl_pose', '--out', str(tmp_path / 'out'), '--no-plot', '--no-progress'])
    text = capsys.readouterr().out
    assert rc == 0, text
    logs, stamps, T = _map_to_odom(tmp_path / 'out' / 'replay_bag')
    frames = json.loads((tmp_path / 'out' / 'summary.json').read_text())['frames']
    with BagReader(tmp_path / 'out' / 'replay_bag') as bag:   # one per window update
        first_update = next(m.log_ns for m in bag.messages(['/ga/corrected_path']))

    # from the first odometry message, every 50 ms, stamped in the bag's (simulation) time
    assert logs[0] == b.log_ns[0] and abs(int(stamps[0]) - int(b.stamps_ns[0])) < 5_000_000
    assert np.all(np.diff(logs[:-1]) == 50_000_000)
    assert np.all(np.diff(stamps) >= 0), 'a header stamp steps back'
    # none of AMCL's map -> odom is copied
    assert frames['input_tf_to_odom_not_copied'] == len(b.amcl_log_ns)

    # map -> base_link at every transform: with the odometry pose at its stamp
    k = np.clip(np.searchsorted(b.stamps_ns, stamps, side='right') - 1, 0, len(b.stamps_ns) - 1)
    T_map_base = T @ b.T_odom[k]
    err = np.linalg.norm(T_map_base[:, :2, 3] - b.T_map_true[k, :2, 3], axis=1)
    before = logs < b.amcl_log_ns[0]
    assert before.any() and np.allclose(T[before], np.eye(4)), 'identity before the first fix'
    assert np.linalg.norm(b.T_map_true[0, :2, 3]) > 9.0   # what the identity is off by
    # placed by the fixes from when they determine it (the first one with its yaw; else once
    # the odometry has moved between fixes: 1.5 m at 1 m/s, the heading sigma then below
    # 0.5 rad) to the first window update (10 s later): within their uncertainty of the true
    # pose (3 sigma)
    determined = b.amcl_log_ns[0] if yaw_known else b.amcl_log_ns[0] + 1_500_000_000
    by_fixes = (logs > determined) & (logs < first_update)
    assert (logs[by_fixes][-1] - logs[by_fixes][0]) > 9e9
    assert err[by_fixes].max() < 3 * SIGMA_XY, err[by_fixes].max()
    # then the aligner's (the odometry drifts between its updates)
    assert err[logs > b.amcl_log_ns[0]].max() < 1.0
    # every change of map -> base_link (the same odometry pose before and after) beyond
    # 3 sigma of the fixes after the first placement is warned about
    jumps = np.linalg.norm(((T[1:] - T[:-1]) @ b.T_odom[k[1:]])[:, :2, 3], axis=1)
    jumps = jumps[logs[:-1] > b.amcl_log_ns[0]]
    m2o = frames['map_to_odom']
    assert (jumps > 1.01 * 3 * SIGMA_XY).sum() <= m2o['jumps_warned']
    assert m2o['jumps_warned'] <= (jumps > 0.99 * 3 * SIGMA_XY).sum()
    assert (m2o['jumps_warned'] > 0) == any('map -> odom jumped' in w
                                            for w in frames['warnings'])
    assert (m2o['jumps_warned'] > 0) == ('warning: map -> odom jumped' in text)
    assert m2o['placed_by'] == 'aligner' and m2o['fixes_used'] >= 19
    assert m2o['fixes_heading'] == ('orientation+motion' if yaw_known else 'motion')
