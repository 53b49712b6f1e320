"""Self-calibration with noisy fixes (docs/calibration.md, *Noisy fixes: one draw against the
mean*): the yaw rate's error comes from the fixes' noise, as large as its published sigma says,
so one draw of the fix noise can leave the calibrated batch worse than the uncalibrated one
while over the draws it is better.

The reference figures are computed here from the truth of the simulation (the test only: the
estimator never sees it)."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.calibration import CalibrationConfig, solve_with_calibration
from ga_ros.core.solver import solve
from ga_ros.sim.biased import biased_survey

#: The CMU Plaza set-up in small: a yaw-rate bias, the odometry's yaw stated 10x too loose
#: (its stated sigma also covers the bias), noisy fixes (3 m) every 20 keyframes (10 s).
_SURVEY = dict(n_nodes=400, yaw_rate=0.004, sigma_yaw_rad=0.0005, stated_sigma_yaw_rad=0.005,
               fix_every=20, fix_sigma_m=3.0)


def _rmse(T, T_true):
    return float(np.sqrt(np.mean(np.sum((T[:, :2, 3] - T_true[:, :2, 3]) ** 2, axis=1))))


@pytest.mark.slow
def test_calibrated_beats_uncalibrated_over_the_draws_of_the_fix_noise():
    """Over 12 draws of the fix noise the calibrated batch (stated noise and re-estimated
    noise; the rotation's redundancy is too low here to re-weight it) has a mean RMSE 0.61x
    the plain adjustment's; the yaw rate is significant in every draw. In two draws (2 and
    11) the calibrated batch is worse than the plain one: the failure seen on the Plaza run
    with the fix noise's seed 0, reproduced where the estimator is known to be right."""
    plain, stated, noise = [], [], []
    for seed in range(12):
        s = biased_survey(np.random.default_rng(700 + seed), **_SURVEY)
        plain.append(_rmse(solve(s.network, s.T_dead, priors=s.priors).T_world_node, s.T_true))
        for cal, out in ((CalibrationConfig(noise=False), stated), (CalibrationConfig(), noise)):
            res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s,
                                              priors=s.priors, calibration=cal)
            assert {p.name for p in rep.estimated()} >= {'yaw_rate'}, rep.lines()
            out.append(_rmse(res.T_world_node, s.T_true))
    worse = [k for k, (a, b) in enumerate(zip(stated, plain)) if a > b]
    assert worse == [2, 11], (plain, stated)
    assert np.mean(stated) < 0.7 * np.mean(plain), (plain, stated)
    assert np.mean(noise) < 0.7 * np.mean(plain), (plain, noise)


@pytest.mark.slow
def test_yaw_rate_error_is_as_large_as_its_sigma():
    """The stated covariances true (odometry and fixes): over 20 draws the yaw rate's error
    against the truth has the spread its published sigma ``sqrt(Q_cc)`` gives (the fixes'
    noise it absorbs is accounted for), and no bias: the mean square of ``error / sigma`` is
    within chi2(20)/20's 99.8 % range, its mean within 3.1 / sqrt(20)."""
    z = []
    for seed in range(20):
        s = biased_survey(np.random.default_rng(900 + seed), n_nodes=400, yaw_rate=0.004,
                          sigma_yaw_rad=0.002, fix_every=20, fix_sigma_m=3.0)
        _, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s,
                                        priors=s.priors,
                                        calibration=CalibrationConfig(noise=False))
        p = next(p for p in rep.parameters if p.name == 'yaw_rate')
        assert p.estimated, rep.lines()
        z.append((p.value - 0.004) / p.sigma)
    z = np.asarray(z)
    assert 0.33 < np.mean(z ** 2) < 2.1, z
    assert abs(np.mean(z)) < 3.1 / np.sqrt(z.size), z
