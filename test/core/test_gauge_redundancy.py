"""The variance factor with the datum from the fixes (``datum='fixes'``): the weak gauge prior
is a datum, not an observation, and is left out of the redundancy
(:attr:`GaussianPrior.weak <ga_ros.core.solver.priors.GaussianPrior.weak>`).

Checked by a Monte-Carlo whose inputs are drawn from their stated covariances: the mean
a-posteriori variance factor must be 1 within its standard error, and the redundancy the count
of the observations' equations less the unknowns (the fixes determine the datum).
"""

from __future__ import annotations

import numpy as np

from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.geometry import se3


def _lawnmower(n: int, per: int) -> tuple[np.ndarray, list[np.ndarray]]:
    T_true, steps = [se3.identity()], []
    for i in range(n - 1):
        turn = np.pi / 2 if (i % per) in (per - 2, per - 1) else 0.0
        steps.append(se3.from_translation_rotvec(np.array([1.0, 0.0, 0.0]),
                                                 np.array([0.0, 0.0, turn])))
        T_true.append(T_true[-1] @ steps[-1])
    return np.array(T_true), steps


def test_variance_factor_with_fixes_averages_one_over_a_monte_carlo() -> None:
    rng = np.random.default_rng(11)
    per, n_tracks, runs, sig_fix, every = 8, 2, 120, 0.3, 3
    n = per * n_tracks
    T_true, steps = _lawnmower(n, per)
    C = np.diag([0.05 ** 2] * 3 + [0.01 ** 2] * 3)
    L = np.linalg.cholesky(C)
    fixed_nodes = [k for k in range(1, n) if k % every == 1]
    s0, red = [], []
    for _ in range(runs):
        al = TrackWindowAligner(AlignerConfig(window_tracks=2, datum='fixes',
                                              refine_every_tracks=0, fix_gate_prob=0.0,
                                              refine_executor='inline'),
                                T_world_first=T_true[0])
        for i in range(n - 1):
            T_m = steps[i] @ se3.exp(L @ rng.normal(size=6))
            al.add_measurement(Measurement.from_pose(i, i + 1, i // per, (i + 1) // per, T_m,
                                                     C, (i + 1) * 10 ** 9))
            k = i + 1
            if k in fixed_nodes:
                p = T_true[k, :3, 3] + rng.normal(0, sig_fix, 3)
                al.add_fix(FixTerm(k, se3.identity(), AbsoluteFix.from_covariance(
                    k * 10 ** 9, se3.from_translation_rotvec(p, np.zeros(3)),
                    np.diag([sig_fix ** 2] * 3 + [-1.0] * 3), 'gnss')))
        al.finish_track()
        up = al.refine_batch()
        s0.append(up.sigma0_sq)
        red.append(al.last_adjustment.redundancy)
        al.close()
    # the observations' equations less the unknowns, plus the dimensions the gauge holds
    # where the fixes determine the datum only weakly (here the tilt, 0.05 rad): tr(Q H) in [0, 6)
    n_obs_r = 6 * (n - 1) + 3 * len(fixed_nodes) - 6 * n
    red = np.asarray(red)
    assert (red > n_obs_r - 1e-6).all() and (red < n_obs_r + 6).all(), (red.min(), red.max())
    s0 = np.asarray(s0)
    mean, se = float(s0.mean()), float(s0.std(ddof=1) / np.sqrt(runs))
    assert abs(mean - 1.0) < 3 * se, (mean, se)
    # counting the gauge by its rank (6 equations) gives a factor clearly below 1
    by_rank = s0 * red / (n_obs_r + 6)
    assert by_rank.mean() < 1.0 - 3 * se, by_rank.mean()
