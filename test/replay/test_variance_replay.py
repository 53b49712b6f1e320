"""Variance components in the replay's final batch: several pose streams without covariances
(each gets the default of 5 % of the motion), of different true noise, in a bag.

The streams are :mod:`ga_ros.sim.sources`'s sources integrated into ``geometry_msgs/PoseStamped``
at one sample per metre (every sample a keyframe), written with rosbags as a robot records them.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import POSE_STAMPED, pose_stamped_msg, write_bag

from ga_ros.core.tracks import TrackRules
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.io.trajectory import write_tum
from ga_ros.pipeline.inputs import InputSpec
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.inputs import InputTopics
from ga_ros.replay.pipeline import replay
from ga_ros.replay.text import result_text
from ga_ros.sim.sources import SourceSpec, multi_source_survey

T0_NS = 1_700_000_000_000_000_000
SOURCES = (SourceSpec('odom0', 2.0), SourceSpec('odom1', 4.0), SourceSpec('odom2', 1.0))
N = 240


@pytest.fixture(scope='module')
def three_stream_bag(tmp_path_factory) -> tuple[Path, Path, np.ndarray]:
    tmp = tmp_path_factory.mktemp('three_streams')
    sv = multi_source_survey(np.random.default_rng(11), SOURCES, n_nodes=N)
    stamps = T0_NS + np.arange(N, dtype=np.int64) * 10 ** 9
    rows = []
    for k, s in enumerate(SOURCES):
        T = [np.eye(4)]
        for m in sv.of(s.name):
            T.append(T[-1] @ m.T_src_dst)
        rows += [(int(st) + k * 1_000_000, f'/{s.name}/pose', POSE_STAMPED,
                  pose_stamped_msg(Tk, int(st))) for st, Tk in zip(stamps, T)]
    rows.sort(key=lambda r: r[0])
    write_bag(tmp / 'in', rows)
    write_tum(tmp / 'gt.tum', stamps, sv.T_true)
    return tmp / 'in', tmp / 'gt.tum', sv.T_true


def _step_error(res, T_true: np.ndarray) -> float:
    """RMS translation error (m) of the consecutive keyframe motions of GA against the truth
    (a sum over every interval: far less noisy than the position RMSE of one random walk)."""
    traj = res.corrected
    k = ((traj.stamps_ns - T0_NS) // 10 ** 9).astype(int)
    T = traj.T_world_node
    est = np.linalg.inv(T[:-1]) @ T[1:]
    true = np.linalg.inv(T_true[k[:-1]]) @ T_true[k[1:]]
    return float(np.sqrt(np.mean(np.sum((est[:, :3, 3] - true[:, :3, 3]) ** 2, axis=1))))


def _config(names: list[str], gt: Path, vce: str) -> ReplayConfig:
    specs = tuple(InputSpec(f'/{n}/pose', 'pose',
                            OdometryInputConfig(n, keyframe_travel_m=0.9,
                                                track=TrackRules('time', duration_s=30.0)))
                  for n in names)
    return ReplayConfig(inputs=InputTopics(specs), plot=False, ground_truth_file=str(gt),
                        variance_components=vce)


def test_factors_weight_three_streams_without_covariances(three_stream_bag,
                                                          tmp_path: Path) -> None:
    """Three streams stated alike (the default), 2 / 4 / 1 % true noise: the final batch
    weights each by its estimated factor, so GA's keyframe motions are better than the best
    stream's alone and than the fusion with the stated weights, and its position RMSE is below
    the best stream's alone; ``summary.json`` and the printout show the factors, close to the
    true ``(true / 5 %)^2``, and the too-pessimistic default is named in a warning."""
    bag, gt, T_true = three_stream_bag
    names = [s.name for s in SOURCES]
    vce = replay(bag, tmp_path / 'vce', _config(names, gt, 'apply'))
    plain = replay(bag, tmp_path / 'plain', _config(names, gt, 'off'))
    assert vce.rejected == {} and vce.final_batch
    alone = {n: replay(bag, tmp_path / n, _config([n], gt, 'apply')) for n in names}
    step = {n: _step_error(r, T_true) for n, r in alone.items()}
    assert _step_error(vce, T_true) < min(step.values()), (_step_error(vce, T_true), step)
    assert _step_error(vce, T_true) < 0.9 * _step_error(plain, T_true)
    err = vce.errors['ga'].ate_raw
    assert err < min(r.errors['ga'].ate_raw for r in alone.values())
    summary = json.loads((tmp_path / 'vce' / 'summary.json').read_text())
    vc = summary['variance_components']
    assert plain.variance_components == {}
    report = replay(bag, tmp_path / 'report', _config(names, gt, 'report'))
    np.testing.assert_array_equal(report.corrected.T_world_node, plain.corrected.T_world_node)
    for s in SOURCES:
        assert report.variance_components[s.name]['factor'] == vc[s.name]['factor']
        assert vc[s.name]['applied'] and not report.variance_components[s.name]['applied']
    for s in SOURCES:
        assert vc[s.name]['estimated']
        assert vc[s.name]['factor'] == pytest.approx(s.true_factor, rel=0.35), (s.name, vc)
    text = result_text(vce)
    assert 'variance components (final batch' in text
    assert "warning: odom2's stated covariance is" in text and 'too large' in text


def test_two_streams_each_get_their_own_factor(three_stream_bag, tmp_path: Path) -> None:
    """Two streams and nothing else (2 % and 4 % true noise, both stated 5 %): the adjustment's
    residuals show only the sum of their variances; each stream's own consistency against the
    other (Grubbs, :mod:`ga_ros.core.quality.source_consistency`) splits it. Each factor is
    close to the truth and GA's keyframe motions are better than the better stream's alone and
    than the fusion with the stated weights."""
    bag, gt, T_true = three_stream_bag
    names = ['odom0', 'odom1']
    vce = replay(bag, tmp_path / 'vce', _config(names, gt, 'apply'))
    plain = replay(bag, tmp_path / 'plain', _config(names, gt, 'off'))
    better = replay(bag, tmp_path / 'odom0', _config(['odom0'], gt, 'off'))
    vc = vce.variance_components
    for s in SOURCES[:2]:
        assert vc[s.name]['applied']
        assert vc[s.name]['factor'] == pytest.approx(s.true_factor, rel=0.2), (s.name, vc)
    assert _step_error(vce, T_true) < _step_error(better, T_true)
    assert _step_error(vce, T_true) < _step_error(plain, T_true)


def test_command_line_modes() -> None:
    """``--variance-components`` sets the mode (report by default); ``--no-variance-components``
    is ``off``; an unknown mode is refused by the parser and by the config."""
    import argparse

    from ga_ros.cli.commands.replay import add_replay_arguments, replay_config
    from ga_ros.errors import InputError

    p = argparse.ArgumentParser()
    add_replay_arguments(p)
    for argv, want in (([], 'report'), (['--variance-components', 'apply'], 'apply'),
                       (['--no-variance-components'], 'off')):
        args = p.parse_args(argv)
        assert replay_config(args, progress=False).variance_components == want
    with pytest.raises(SystemExit):
        p.parse_args(['--variance-components', 'always'])
    with pytest.raises(InputError, match='variance_components'):
        ReplayConfig(variance_components='always')


def test_online_factors_in_the_replay(three_stream_bag, tmp_path: Path) -> None:
    """``variance_components: apply`` of the aligner (``--online-variance-components apply``):
    the factors estimated after each track are in ``summary.json`` with their dof, printed,
    close to the truth, the worst-stated stream named in a warning; the command line sets
    the aligner's mode."""
    import argparse
    from dataclasses import replace

    from ga_ros.cli.commands.replay import add_replay_arguments, replay_config
    from ga_ros.core.window import AlignerConfig

    bag, gt, _ = three_stream_bag
    names = [s.name for s in SOURCES]
    cfg = replace(_config(names, gt, 'off'),
                  aligner=AlignerConfig(variance_components='apply', refine_executor='inline'))
    res = replay(bag, tmp_path / 'online', cfg)
    on = json.loads((tmp_path / 'online' / 'summary.json').read_text())[
        'online_variance_components']
    assert on['_estimation'] == {'mode': 'apply', 'online': True}
    for s in SOURCES:
        assert on[s.name]['estimated'] and on[s.name]['applied'] and on[s.name]['dof'] > 20
        # the best stream (odom2, true factor 0.04) is seen only through its differences with
        # the others: the hardest to estimate (the final batch's is within 35 %)
        assert on[s.name]['factor'] == pytest.approx(s.true_factor, rel=0.5), (s.name, on)
    text = result_text(res)
    assert 'variance components (online, after each track' in text
    assert "warning: online: odom2's stated covariance is" in text
    p = argparse.ArgumentParser()
    add_replay_arguments(p)
    args = p.parse_args(['--online-variance-components', 'apply'])
    assert replay_config(args, progress=False).aligner.variance_components == 'apply'
    assert replay_config(p.parse_args([]), progress=False).aligner is None
