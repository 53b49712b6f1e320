"""The replay's figures mean what they say, each checked against a computation made here.

Fixture (written with rosbags): a robot driving a 20 x 10 m rectangle, ``/odom``
(``nav_msgs/Odometry``, all-zero covariance, 10 Hz) with a heading drift, recorded in an odom
frame that is neither the map nor the start pose (offset 5 m and 40 deg, as a robot's odometry
that was running before the recording); AMCL-like fixes ``/amcl_pose`` in ``map`` at 1 Hz;
ground truth as a TUM file at 30 Hz, 7 ms off the odometry's stamps (interpolated).

* F2F is the recorded odometry, anchored exactly as GA: its first keyframe where GA's first
  keyframe is (the ground truth's first pose without fixes, where the fixes put it with them);
* "% lower" / "% higher" is the sign of the change; ``--no-anchor`` compares RMSEs after rigid
  alignment;
* ``trajectory_gt.tum`` holds the ground truth at the keyframe stamps (evo pairs every line),
  the raw stream is ``trajectory_gt_raw.tum``;
* ``trajectory_ga.tum`` is the final batch, ``trajectory_online.tum`` the online estimate, both
  in ``summary.json`` with their RMSEs, and the final batch is no worse on a run with fixes.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    ODOMETRY,
    POSE_COV_STAMPED,
    odometry_msg,
    pose_cov_stamped_msg,
    rectangle,
    rectangle_drive,
)

from ga_ros.core.tracks import TrackRules
from ga_ros.eval.metrics import TrajectoryError, relative_change_text
from ga_ros.geometry import se3
from ga_ros.inputs.absolute import AbsoluteInputConfig
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.io.bag_writer import BagWriter
from ga_ros.io.trajectory import read_tum, write_tum
from ga_ros.pipeline.absolute import AbsoluteSpec
from ga_ros.pipeline.inputs import InputSpec
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.inputs import InputTopics
from ga_ros.replay.pipeline import replay
from ga_ros.replay.result import ReplayResult
from ga_ros.replay.text import result_text

T0_NS = 1_700_000_000_000_000_000
#: the odom frame in the map frame: where the odometry's origin is
T_MAP_ODOM0 = se3.from_translation_rotvec(np.array([5.0, -3.0, 0.0]),
                                          np.array([0.0, 0.0, np.deg2rad(40.0)]))


@pytest.fixture(scope='module')
def robot(tmp_path_factory) -> dict:
    tmp = tmp_path_factory.mktemp('figures')
    rng = np.random.default_rng(5)
    drive = rectangle_drive(1.5, 10.0, T0_NS, yaw_per_step=1e-3)
    # recorded odometry: in an odom frame placed anywhere (T_odom_base)
    T_odom = se3.inverse(T_MAP_ODOM0) @ drive.T_odom
    fixes = []
    with BagWriter(tmp / 'in') as bag:
        for k, (s, T) in enumerate(zip(drive.stamps_ns, T_odom)):
            s = int(s)
            bag.write('/odom', ODOMETRY, odometry_msg(T, s), s)
            if k % 10 == 5:
                T_m = drive.T_true[k].copy()
                T_m[:2, 3] += rng.normal(0, 0.2, 2)
                cov = np.zeros((6, 6))
                cov[0, 0] = cov[1, 1] = 0.2 ** 2
                cov[5, 5] = 0.05 ** 2
                fixes.append(T_m[:3, 3])
                bag.write('/amcl_pose', POSE_COV_STAMPED,
                          pose_cov_stamped_msg(T_m, s, cov, 'map'), s)
    t_gt = np.arange(0.0, 90.0, 1.0 / 30.0) + 0.007
    write_tum(tmp / 'gt.tum', T0_NS + np.round(t_gt * 1e9).astype(np.int64), rectangle(t_gt))
    return dict(dir=tmp, stamps=drive.stamps_ns, T_odom=T_odom, n_gt=len(t_gt))


def _config(robot: dict, fixes: bool, aligner_kw: dict | None = None, **kw) -> ReplayConfig:
    from ga_ros.core.window import AlignerConfig

    spec = InputSpec('/odom', 'odometry', OdometryInputConfig(
        'odom0', keyframe_travel_m=1.0, track=TrackRules('distance', length_m=15.0)))
    amcl = (AbsoluteSpec('/amcl_pose', 'pose_cov', AbsoluteInputConfig('amcl0', frame_id='map')),)
    aligner = AlignerConfig(datum='fixes' if fixes else 'first_node', refine_executor='inline',
                            **(aligner_kw or {}))
    return ReplayConfig(inputs=InputTopics((spec,), absolutes=amcl if fixes else ()),
                        aligner=aligner, ground_truth_file=str(robot['dir'] / 'gt.tum'), **kw)


def _rmse(p: np.ndarray, q: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((p - q) ** 2, axis=1))))


def _recorded_f2f(robot: dict, ga: object) -> tuple[np.ndarray, np.ndarray]:
    """(F2F positions, true positions) at GA's keyframes, computed here: the recorded odometry
    at each keyframe stamp, moved rigidly so its first keyframe is GA's first keyframe; the
    truth from the rectangle itself (not the TUM file)."""
    idx = np.searchsorted(robot['stamps'], ga.stamps_ns)
    assert np.array_equal(robot['stamps'][idx], ga.stamps_ns)
    T_odom = robot['T_odom'][idx]
    f2f = ga.T_world_node[0] @ np.linalg.inv(T_odom[0]) @ T_odom
    truth = rectangle((ga.stamps_ns - T0_NS) * 1e-9)
    return f2f[:, :3, 3], truth[:, :3, 3]


@pytest.mark.parametrize('fixes', [False, True], ids=['odometry', 'with_fixes'])
def test_f2f_is_the_recorded_odometry_anchored_as_ga(robot: dict, tmp_path: Path,
                                                     fixes: bool) -> None:
    res = replay(robot['dir'] / 'in', tmp_path / 'out', _config(robot, fixes))
    assert res.rejected == {}, res.rejected_examples
    ga = read_tum(res.files['trajectory_ga'])
    if not fixes:  # the datum: GA's first keyframe at the ground truth's first pose
        gt0 = read_tum(res.files['trajectory_gt']).T_world_node[0]
        np.testing.assert_allclose(ga.T_world_node[0], gt0, atol=1e-6)
        truth0 = rectangle(np.array([(ga.stamps_ns[0] - T0_NS) * 1e-9]))[0]
        np.testing.assert_allclose(gt0, truth0, atol=0.01)
    f2f_xyz, true_xyz = _recorded_f2f(robot, ga)
    f2f_file = read_tum(res.files['trajectory_f2f'])
    np.testing.assert_array_equal(f2f_file.stamps_ns, ga.stamps_ns)
    np.testing.assert_allclose(f2f_file.T_world_node[:, :3, 3], f2f_xyz, atol=1e-6)
    # the printed RMSEs, by hand (the TUM ground truth is linear between corners: 1 cm)
    e = res.errors
    assert e['f2f'].n == e['ga'].n == len(ga)
    assert e['f2f'].ate_raw == pytest.approx(_rmse(f2f_xyz, true_xyz), abs=0.01)
    assert e['ga'].ate_raw == pytest.approx(_rmse(ga.T_world_node[:, :3, 3], true_xyz), abs=0.01)
    assert e['f2f'].ate_raw > 1.0  # the drift is real
    if fixes:
        assert e['ga'].ate_raw < 0.3 * e['f2f'].ate_raw


def test_final_batch_online_and_ground_truth_files(robot: dict, tmp_path: Path) -> None:
    """A live node that keeps one track and never refines the past (the online estimate then
    cannot use a fix for the tracks before it): the final batch, which uses every fix for every
    keyframe, is no worse. (With the default window and background refinement the two are
    within a few per cent of each other, either way: the heading drift is a bias the noise
    model does not describe, so the least-squares optimum need not have the lower RMSE.)"""
    res = replay(robot['dir'] / 'in', tmp_path / 'out',
                 _config(robot, True, dict(window_tracks=1, refine_every_tracks=0)))
    ga = read_tum(res.files['trajectory_ga'])
    online = read_tum(res.files['trajectory_online'])
    np.testing.assert_array_equal(online.stamps_ns, ga.stamps_ns)
    assert not np.allclose(online.T_world_node, ga.T_world_node, atol=1e-6)  # not a copy
    truth = rectangle((ga.stamps_ns - T0_NS) * 1e-9)[:, :3, 3]
    rmse_ga, rmse_online = (_rmse(t.T_world_node[:, :3, 3], truth) for t in (ga, online))
    assert rmse_ga <= rmse_online + 1e-3, (rmse_ga, rmse_online)
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    err = summary['errors_vs_ground_truth']
    assert err['ga']['ate_raw_m'] == pytest.approx(rmse_ga, abs=0.01)
    assert err['online']['ate_raw_m'] == pytest.approx(rmse_online, abs=0.01)
    assert summary['trajectories']['ga'] == 'final batch' and summary['final_batch']
    assert len(summary['updates']) == res.n_tracks  # the online updates; the batch apart
    # ground truth at the keyframe stamps: one line per keyframe, evo's association (nearest
    # stamp within 10 ms) pairs every one; the raw stream in its own file
    gt = read_tum(res.files['trajectory_gt'])
    assert len(gt) == len(ga)
    j = np.abs(gt.stamps_ns[None, :] - ga.stamps_ns[:, None]).argmin(axis=1)
    assert np.all(np.abs(gt.stamps_ns[j] - ga.stamps_ns) <= 10_000_000)
    assert len(np.unique(j)) == len(ga)
    np.testing.assert_allclose(gt.T_world_node[:, :3, 3], truth, atol=0.01)
    assert len(read_tum(res.files['trajectory_gt_raw'])) == robot['n_gt']
    text = result_text(res)
    assert 'final batch of everything read, trajectory_ga.tum' in text
    assert 'what the live node publishes at the end, trajectory_online.tum' in text
    assert 'odometry anchored as GA, trajectory_f2f.tum' in text
    assert (tmp_path / 'out' / 'trajectory.png').stat().st_size > 10_000


def test_no_final_batch_writes_the_online_estimate(robot: dict, tmp_path: Path) -> None:
    res = replay(robot['dir'] / 'in', tmp_path / 'out', _config(robot, True, plot=False,
                                                                 final_batch=False))
    ga = read_tum(res.files['trajectory_ga'])
    online = read_tum(res.files['trajectory_online'])
    np.testing.assert_array_equal(online.T_world_node, ga.T_world_node)
    assert 'online, no final batch, trajectory_ga.tum' in result_text(res)


def test_no_anchor_compares_after_rigid_alignment(robot: dict, tmp_path: Path) -> None:
    res = replay(robot['dir'] / 'in', tmp_path / 'out',
                 _config(robot, False, plot=False, anchor_to_ground_truth=False))
    ga = read_tum(res.files['trajectory_ga'])
    f2f = read_tum(res.files['trajectory_f2f'])
    np.testing.assert_allclose(ga.T_world_node[0], np.eye(4), atol=1e-9)  # the datum
    truth = rectangle((ga.stamps_ns - T0_NS) * 1e-9)[:, :3, 3]

    def kabsch_rmse(p: np.ndarray, q: np.ndarray) -> float:
        pc, qc = p - p.mean(0), q - q.mean(0)
        U, _, Vt = np.linalg.svd(qc.T @ pc)
        R = U @ np.diag([1, 1, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        return _rmse(pc @ R.T, qc)

    want = {k: kabsch_rmse(t.T_world_node[:, :3, 3], truth) for k, t in (('ga', ga), ('f2f', f2f))}
    assert res.errors_compared == 'aligned'
    for k in want:
        assert res.errors[k].ate_aligned == pytest.approx(want[k], abs=0.01)
    text = result_text(res)
    assert 'after rigid alignment (each its own; --no-anchor)' in text
    line = next(x for x in text.splitlines() if x.strip().startswith('GA'))
    assert f"{res.errors['ga'].ate_aligned:10.3f} m" in line
    change = relative_change_text(res.errors['ga'].ate_aligned, res.errors['f2f'].ate_aligned,
                                  'F2F')
    assert change in line


def test_lower_and_higher_in_words() -> None:
    assert relative_change_text(0.93, 1.0, 'F2F') == '7.0 % lower than F2F'
    assert relative_change_text(1.07, 1.0, 'F2F') == '7.0 % higher than F2F'
    assert relative_change_text(200.148, 200.176, 'F2F') == 'equal to F2F'
    assert relative_change_text(1.0, 0.0, 'F2F') == ''
    # a worse GA in the printout: "higher", never a negative "lower"
    r = ReplayResult('b', 'inputs', 'o', final_batch=True)
    r.errors = {'f2f': TrajectoryError(1.0, 0.5, 2.0, 10),
                'online': TrajectoryError(1.10, 0.4, 2.0, 10),
                'ga': TrajectoryError(1.07, 0.4, 2.0, 10)}
    text = result_text(r)
    assert '7.0 % higher than F2F' in text and '10.0 % higher than F2F' in text
    assert 'lower' not in text and '-' not in text.split('error vs ground truth')[1]


def test_batch_aligner_counts_the_fixes_it_cannot_take(robot: dict, tmp_path: Path) -> None:
    """``--aligner batch`` has no fixes: each one read is a counted rejection, none is lost
    silently."""
    import dataclasses

    cfg = dataclasses.replace(_config(robot, True, plot=False), aligner=None,
                              aligner_kind='batch')
    res = replay(robot['dir'] / 'in', tmp_path / 'out', cfg)
    n_fixes = res.source_stats['absolute']['amcl0']['fixes']
    assert n_fixes == 90
    assert res.rejected == {'absolute': n_fixes}, res.rejected
    assert 'takes no fixes' in res.rejected_examples[0]


def test_plot_draws_ga_f2f_fixes_and_ground_truth_in_the_map_frame(robot: dict, tmp_path: Path,
                                                                    monkeypatch) -> None:
    """What the PNG is drawn from: GA, online, F2F and the ground truth as in their files, and
    every fix read at its position in the map frame."""
    import ga_ros.replay.outputs as outputs

    drawn: dict = {}

    def capture(path, ga, f2f, gt, title, online=None, fixes=None, frame='map'):
        drawn.update(ga=ga, f2f=f2f, gt=gt, online=online, fixes=fixes, frame=frame,
                     title=title)

    monkeypatch.setattr(outputs, 'plot_trajectories', capture)
    res = replay(robot['dir'] / 'in', tmp_path / 'out', _config(robot, True))
    for key, name in (('ga', 'trajectory_ga'), ('f2f', 'trajectory_f2f'),
                      ('online', 'trajectory_online'), ('gt', 'trajectory_gt')):
        np.testing.assert_allclose(drawn[key], read_tum(res.files[name]).T_world_node[:, :3, 3],
                                   atol=1e-6)
    assert drawn['frame'] == 'map' and len(drawn['fixes']) == 90
    # the fixes were drawn where they were measured: within 1 m (5 sigma) of the true path
    path = rectangle(np.arange(0.0, 90.0, 0.01))[:, :2, 3]
    d = np.linalg.norm(drawn['fixes'][:, None, :2] - path[None], axis=2).min(1)
    assert d.max() < 1.0
    assert f"F2F {res.errors['f2f'].ate_raw:.3g} m" in drawn['title']


def test_a_failed_final_batch_leaves_the_online_estimate_with_a_warning(
        robot: dict, tmp_path: Path, monkeypatch) -> None:
    from ga_ros.core.window import TrackWindowAligner
    from ga_ros.errors import SolverError

    def fail(self, **kwargs):
        raise SolverError('not positive definite')

    monkeypatch.setattr(TrackWindowAligner, 'refine_batch', fail)
    res = replay(robot['dir'] / 'in', tmp_path / 'out', _config(robot, False, plot=False))
    assert res.error is None and not res.final_batch
    assert res.warnings == ['final batch failed (not positive definite): trajectory_ga.tum is '
                            'the online estimate']
    np.testing.assert_array_equal(read_tum(res.files['trajectory_ga']).T_world_node,
                                  read_tum(res.files['trajectory_online']).T_world_node)
    assert 'online, no final batch' in result_text(res)
