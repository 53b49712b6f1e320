"""Two SLAM systems' ``geometry_msgs/PoseStamped`` outputs without covariances in a ROS 1 bag,
with a ground-truth stream, replayed as a new user would (``--odom-topic A --odom-topic B``):
both get the default covariance (5 % of the motion), though A (20 Hz, 2 % white noise per
sample motion) is far better than B (10 Hz, 6 %).

With the stated weights the fusion is 3x worse than A alone; with variance components each
stream's own consistency against the other splits what the residuals cannot
(:mod:`ga_ros.core.quality.source_consistency`), in the final batch and online, and the fusion
is as good as A alone, whichever stream defines the keyframes: within 1.1x on this draw, better
on the mean of six draws (B, of ~18x A's variance, has ~5 % to give; one draw varies by ~10 %).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import POSE_STAMPED, ros1_pose_stamped_msg, write_ros1_bag

from ga_ros.cli.main import main
from ga_ros.geometry import se3

T0_NS = 1_700_000_000_000_000_000
DURATION_S = 120.0


def ellipse(t: np.ndarray) -> np.ndarray:
    """``(n, 4, 4)`` a 30 x 15 m ellipse at about 1 m/s, heading along the motion."""
    w = 2 * np.pi / 75.0
    yaw = np.arctan2(7.5 * w * np.sin(w * t), 15 * w * np.cos(w * t))
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, 0, 0], T[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    T[:, 1, 0], T[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    T[:, 0, 3], T[:, 1, 3] = 15 * np.sin(w * t), 7.5 * (1 - np.cos(w * t))
    return T


def noisy(T: np.ndarray, percent: float, rng: np.random.Generator) -> np.ndarray:
    """The poses integrated from the true sample motions, each with white noise of
    ``percent`` of its length (rotation: per 10 m)."""
    rel = se3.inverse(T[:-1]) @ T[1:]
    length = np.linalg.norm(se3.to_translation_rotvec(rel)[:, :3], axis=1)
    sig = np.repeat((percent / 100 * length)[:, None], 6, axis=1)
    sig[:, 3:] /= 10.0
    out = [T[0]]
    for k in range(len(rel)):
        out.append(out[-1] @ rel[k] @ se3.exp(rng.standard_normal(6) * sig[k]))
    return np.array(out)


def write_slam_bag(path: Path, seed: int, duration_s: float = DURATION_S) -> Path:
    """The two streams and the ground truth of the module doc, drawn with ``seed``."""
    rng = np.random.default_rng(seed)
    ta = np.arange(0.0, duration_s, 1 / 20)
    tb = np.arange(0.0, duration_s, 1 / 10) + 0.03
    tg = np.arange(0.0, duration_s, 1 / 50)
    rows = []
    for topic, t, T, lag in (('/slam_a/pose', ta, noisy(ellipse(ta), 2.0, rng), 0),
                             ('/slam_b/pose', tb, noisy(ellipse(tb), 6.0, rng), 1),
                             ('/vicon/base', tg, ellipse(tg), 2)):
        stamps = T0_NS + np.round(t * 1e9).astype(np.int64)
        rows += [(int(s) + lag * 1_000_000, topic, POSE_STAMPED,
                  ros1_pose_stamped_msg(Tk, int(s))) for s, Tk in zip(stamps, T)]
    rows.sort(key=lambda r: r[0])
    return write_ros1_bag(path, rows)


@pytest.fixture(scope='module')
def slam_bag(tmp_path_factory) -> Path:
    return write_slam_bag(tmp_path_factory.mktemp('two_slam') / 'slam.bag', 2)


def _replay(bag: Path, out: Path, *args: str) -> dict:
    assert main(['replay', str(bag), '--ground-truth-topic', '/vicon/base', '--no-plot',
                 '--out', str(out), *args]) == 0
    return json.loads((out / 'summary.json').read_text())


def _ate(summary: dict, path: str = 'ga') -> float:
    return summary['errors_vs_ground_truth'][path]['ate_aligned_m']


@pytest.mark.parametrize('order', [('a', 'b'), ('b', 'a')])
def test_fused_as_good_as_the_better_stream(slam_bag, tmp_path: Path, order) -> None:
    topics = [arg for k in order for arg in ('--odom-topic', f'/slam_{k}/pose')]
    alone = _replay(slam_bag, tmp_path / 'a', '--odom-topic', '/slam_a/pose',
                    '--no-variance-components')
    stated = _replay(slam_bag, tmp_path / 'stated', *topics, '--no-variance-components')
    batch = _replay(slam_bag, tmp_path / 'batch', *topics, '--variance-components', 'apply')
    online = _replay(slam_bag, tmp_path / 'online', *topics, '--no-variance-components',
                     '--online-variance-components', 'apply')
    a, b = ('odom0', 'odom1') if order == ('a', 'b') else ('odom1', 'odom0')
    for vc in (batch['variance_components'], online['online_variance_components']):
        assert vc[a]['applied'] and vc[b]['applied']
        assert vc[b]['factor'] > 5 * vc[a]['factor'], vc   # B is the worse, by far
    assert _ate(stated) > 2 * _ate(alone)  # the stated weights: A spoilt by B
    assert _ate(batch) < 1.1 * _ate(alone), (_ate(batch), _ate(alone))
    assert _ate(online, 'online') < 1.1 * _ate(alone), (_ate(online, 'online'), _ate(alone))


def _raw(summary: dict) -> float:
    return summary['errors_vs_ground_truth']['ga']['ate_raw_m']


@pytest.mark.slow
def test_over_seeds_the_fusion_beats_the_better_stream(tmp_path: Path) -> None:
    """Six draws of the bag (180 s): the fused path (``--variance-components apply``) against
    A alone, raw and after rigid alignment. Fusing a stream of ~18x the variance can gain
    only ~3 % in expectation, and one draw's RMSE (a drift, of few degrees of freedom) varies
    by ~10 % around it: with the true weights the fusion is worse than A alone in about a third
    of the draws (docs/benchmarks.md). So the mean ratio is tested, and each draw within
    1.15x; A's factor (true 0.0074: 2 % per sample over 20 samples, against the default 5 %;
    its spread over draws ~22 %) within 50 % in every draw."""
    ratios, factors = [], []
    for seed in range(6):
        bag = write_slam_bag(tmp_path / f'{seed}.bag', seed, 180.0)
        alone = _replay(bag, tmp_path / f'a{seed}', '--odom-topic', '/slam_a/pose',
                        '--no-variance-components')
        fused = _replay(bag, tmp_path / f'f{seed}', '--odom-topic', '/slam_a/pose',
                        '--odom-topic', '/slam_b/pose', '--variance-components', 'apply')
        ratios.append((_raw(fused) / _raw(alone), _ate(fused) / _ate(alone)))
        factors.append(fused['variance_components']['odom0']['factor'])
    r = np.asarray(ratios)
    assert np.all(r.mean(axis=0) < 1.0) and np.all(r < 1.15), r
    assert np.all(np.abs(np.asarray(factors) / 0.0074 - 1) < 0.5), factors
