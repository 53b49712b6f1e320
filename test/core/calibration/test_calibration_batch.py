"""Self-calibration in the batch (ga_ros.core.calibration): the parameters' Jacobians against
finite differences, the bordered solution against a joint least-squares solve by scipy, the
recovery of a known scale and yaw-rate bias, the tests that switch parameters off, and the
false-alarm rate of the significance test."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from solver_problems import whitener

from ga_ros.core.calibration import (
    PARAMETERS,
    CalibrationConfig,
    corrected_motions,
    misclosure_jacobian,
    solve_with_calibration,
)
from ga_ros.core.network import ConnectionNetwork
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.sim.biased import biased_survey


def _misclosure(z, dt, k, om, Tij):
    Tc = corrected_motions(z[None], np.array([dt]), np.array([k]), np.array([om]))[0]
    return se3.log(se3.inverse(Tc) @ Tij)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_parameter_jacobians_match_finite_differences(seed):
    rng = np.random.default_rng(seed)
    z = np.concatenate([rng.normal(0, 1.0, 3), rng.normal(0, 0.3, 3)])
    dt, k, om = 0.7, rng.normal(0, 0.05), rng.normal(0, 0.05)
    Tc = corrected_motions(z[None], np.array([dt]), np.array([k]), np.array([om]))[0]
    Tij = Tc @ se3.exp(rng.normal(0, 0.2, 6))  # a misclosure far from zero
    e = _misclosure(z, dt, k, om, Tij)
    h = 1e-6
    for name, d in (('scale', (h, 0.0)), ('yaw_rate', (0.0, h))):
        num = (_misclosure(z, dt, k + d[0], om + d[1], Tij)
               - _misclosure(z, dt, k - d[0], om - d[1], Tij)) / (2 * h)
        G = PARAMETERS[name].generator(Tc[None, :3, :3], z[None, :3], np.array([dt]))
        ana = misclosure_jacobian(e[None], G)[0]
        np.testing.assert_allclose(ana, num, atol=1e-7, rtol=1e-6)


def test_estimate_matches_joint_least_squares():
    """The bordered Gauss-Newton (poses eliminated with the solver's factor) reaches the
    minimum of the joint problem, computed independently by scipy over poses and
    parameters together."""
    rng = np.random.default_rng(5)
    s = biased_survey(rng, n_nodes=40, scale=0.05, yaw_rate=0.01, fix_every=8)
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                      calibration=CalibrationConfig(alpha=1.0 - 1e-9, noise=False))
    assert [p.estimated for p in rep.parameters] == [True, True]
    arr = s.network.arrays()
    Lc = np.array([whitener(np.linalg.inv(c)) for c in arr.cov])
    pri = []
    for p in s.priors:
        info = p.information.toarray() if hasattr(p.information, 'toarray') else p.information
        pri.append((p.node_ids, p.T_world_node, whitener(np.asarray(info))))
    n = s.T_dead.shape[0]

    def fun(x):
        T = s.T_dead @ se3.exp(x[:6 * n].reshape(n, 6))
        k, om = x[6 * n:]
        Tc = corrected_motions(arr.z, s.dt_s, np.full(len(arr), k), np.full(len(arr), om))
        e = se3.log(se3.inverse(Tc) @ se3.relative(T[arr.src], T[arr.dst]))
        out = [(Lc @ e[:, :, None]).ravel()]
        for ids, means, L in pri:
            r = np.concatenate([np.concatenate(
                [Tm[:3, :3].T @ (T[i, :3, 3] - Tm[:3, 3]),
                 se3.log(se3.from_rt(Tm[:3, :3].T @ T[i, :3, :3], np.zeros(3)))[3:]])
                for i, Tm in zip(ids, means)])
            out.append(L @ r)
        return np.concatenate(out)

    sol = least_squares(fun, np.zeros(6 * n + 2), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    k, om = sol.x[6 * n:]
    est = {p.name: p for p in rep.parameters}
    assert abs(est['scale'].value - k) < 1e-3 * est['scale'].sigma
    assert abs(est['yaw_rate'].value - om) < 1e-3 * est['yaw_rate'].sigma
    T = s.T_dead @ se3.exp(sol.x[:6 * n].reshape(n, 6))
    # to the solver's own stopping tolerance
    np.testing.assert_allclose(res.T_world_node[:, :3, 3], T[:, :3, 3], atol=1e-3)
    # the parameters' covariance: the inverse of the joint normal matrix (J' J at the minimum)
    Jt = sol.jac
    Q = np.linalg.inv(Jt.T @ Jt)
    assert est['scale'].sigma == pytest.approx(np.sqrt(Q[-2, -2]), rel=1e-3)
    assert est['yaw_rate'].sigma == pytest.approx(np.sqrt(Q[-1, -1]), rel=1e-3)


@pytest.mark.parametrize('seed', [11, 12, 13])
def test_recovers_known_scale_and_yaw_rate(seed):
    s = biased_survey(np.random.default_rng(seed), scale=0.03, yaw_rate=0.004)
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, priors=s.priors)
    est = {p.name: p for p in rep.parameters}
    assert est['scale'].estimated and est['yaw_rate'].estimated, rep.lines()
    assert abs(est['scale'].value - 0.03) < 4 * est['scale'].sigma
    assert abs(est['yaw_rate'].value - 0.004) < 4 * est['yaw_rate'].sigma
    plain = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                   calibration=CalibrationConfig(parameters=()))[0]

    def rmse(T):
        return np.sqrt(np.mean(np.sum((T[:, :2, 3] - s.T_true[:, :2, 3]) ** 2, axis=1)))

    assert rmse(res.T_world_node) < 0.7 * rmse(plain.T_world_node)


@pytest.mark.parametrize('name', ['scale', 'yaw_rate'])
def test_false_alarm_rate_near_alpha(name):
    """No systematic error: the parameter is switched on in about alpha of the runs, and its
    test statistic is Student-t distributed (mean square near 1; the gauge prior's 4
    equations without residuals make it ~10 % larger here)."""
    cal = CalibrationConfig(parameters=(name,), alpha=0.1)
    runs, on, t2 = 60, 0, []
    for seed in range(runs):
        s = biased_survey(np.random.default_rng(2000 + seed), n_nodes=150, fix_every=10)
        _, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s,
                                        priors=s.priors, calibration=cal)
        p = rep.parameters[0]
        on += p.estimated
        t2.append(p.test ** 2)
    # binomial(60, 0.1): mean 6, P(on > 14) < 3e-3; chi2(60)/60: P(outside [0.5, 1.7]) < 1e-3
    assert on <= 14
    assert 0.5 < np.mean(t2) < 1.7


def test_not_determined_without_fixes():
    s = biased_survey(np.random.default_rng(3), scale=0.03, yaw_rate=0.004)
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s,
                                      priors=s.priors[:1])
    assert not any(p.estimated for p in rep.parameters)
    assert all('not determined' in p.reason for p in rep.parameters)
    assert all(p.value == 0.0 for p in rep.parameters)


def test_no_durations_no_yaw_rate_and_cross_connections_excluded():
    s = biased_survey(np.random.default_rng(4), scale=0.03, yaw_rate=0.004)
    sources = list(s.sources)
    sources[10] = None  # e.g. a cross-track connection: no additional parameters
    _, rep = solve_with_calibration(s.network, s.T_dead, sources, np.zeros_like(s.dt_s),
                                    priors=s.priors)
    est = {p.name: p for p in rep.parameters}
    assert 'no motion it acts on' in est['yaw_rate'].reason
    assert est['scale'].information_ratio > 0
    with pytest.raises(InputError):
        solve_with_calibration(s.network, s.T_dead, sources[:-1], s.dt_s, priors=s.priors)
    with pytest.raises(InputError):
        CalibrationConfig(parameters=('offset',))


@pytest.mark.parametrize('seed', [21, 22, 23])
def test_calibrated_source_noise_reestimated(seed):
    """A yaw-rate bias on odometry whose stated yaw sigma is 4x the true one (the stated
    covariance allowed for the bias as white noise): after calibration the rotation's stated
    covariance fails its chi-square test and its variance factor comes out within 3 of its
    sigmas of the truth 1/16, clearly below 1; the translation's (stated truly) is within 3 of
    its sigmas of 1; the re-estimated weights give a better path than the stated ones."""
    s = biased_survey(np.random.default_rng(seed), n_nodes=300, yaw_rate=0.004, fix_every=3,
                      fix_sigma_m=0.05, sigma_yaw_rad=0.002, stated_sigma_yaw_rad=0.008)
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                      calibration=CalibrationConfig(noise=True))
    est = {p.name: p for p in rep.parameters}
    assert est['yaw_rate'].estimated, rep.lines()
    assert abs(est['yaw_rate'].value - 0.004) < 4 * est['yaw_rate'].sigma
    noise = {f.part: f for f in rep.noise}
    assert set(noise) == {'translation', 'rotation'}, rep.lines()
    rot, tra = noise['rotation'], noise['translation']
    assert rot.applied and abs(rot.factor / rot.estimate - 1) < 0.02, rep.lines()
    assert abs(rot.factor - 1 / 16) < 3 * rot.sigma, rep.lines()
    assert rot.factor + 3 * rot.sigma < 1, rep.lines()  # determined, not just consistent
    assert rot.stated_ratio < rot.quantiles[0]
    assert tra.applied and abs(tra.factor - 1.0) < 3 * tra.sigma, rep.lines()
    assert tra.quantiles[0] <= tra.stated_ratio <= tra.quantiles[1]
    stated = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                    calibration=CalibrationConfig(noise=False))[0]

    def rmse(T):
        return np.sqrt(np.mean(np.sum((T[:, :2, 3] - s.T_true[:, :2, 3]) ** 2, axis=1)))

    assert rmse(res.T_world_node) < rmse(stated.T_world_node)
    assert rep.as_dict()['noise'][0]['part'] in ('translation', 'rotation')


def _perturbed(network, eps, seed=0):
    """``network`` with every measured motion moved by ``eps`` (m and rad, random signs)."""
    a = network.arrays()
    z = a.z + eps * np.sign(np.random.default_rng(seed).standard_normal(a.z.shape))
    return ConnectionNetwork.from_arrays(network.node_ids, network.track_ids, a.src, a.dst, z,
                                         a.cov)


def test_little_redundancy_does_not_collapse_and_rounding_cannot_flip_it():
    """A fix every 10 keyframes at 0.3 m: the yaw of the odometry is seen only through the
    fixes' positions, so the rotation part has little redundancy (about 8) and loses it as its
    weight grows. The undamped iteration ``s <- s v'Pv / r`` collapses there (checked: the
    rotation factor runs to its bound 0.001 at a redundancy of 0.2, the translation's to 9);
    the damped one stops at a factor that keeps the part determined, and an input moved by
    1e-8 gives the same factors (to 1e-5 relative) and poses (to 0.1 mm, the solver's
    convergence; the flip it replaces changed the path by centimetres)."""
    s = biased_survey(np.random.default_rng(21), n_nodes=300, yaw_rate=0.004, fix_every=10,
                      fix_sigma_m=0.3, sigma_yaw_rad=0.002, stated_sigma_yaw_rad=0.008)
    cal = CalibrationConfig(noise=True)
    runs = [solve_with_calibration(net, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                   calibration=cal)
            for net in (s.network, _perturbed(s.network, 1e-8))]
    (res, rep), (res2, rep2) = runs
    noise = {f.part: f for f in rep.noise}
    rot = noise['rotation']
    assert rot.applied and not rot.held, rep.lines()
    assert rot.redundancy >= cal.noise_min_redundancy, rep.lines()
    assert 0.05 < rot.factor < 1.0, rep.lines()   # re-weighted, far from the bound
    assert abs(rot.factor / rot.estimate - 1) < 2 * cal.noise_tolerance, rep.lines()
    assert abs(noise['translation'].factor - 1.0) < 3 * noise['translation'].sigma, rep.lines()
    assert [p.estimated for p in rep.parameters] == [p.estimated for p in rep2.parameters]
    np.testing.assert_allclose([f.factor for f in rep2.noise], [f.factor for f in rep.noise],
                               rtol=1e-5)
    np.testing.assert_allclose([p.value for p in rep2.parameters],
                               [p.value for p in rep.parameters], rtol=1e-5, atol=1e-9)
    np.testing.assert_allclose(res2.T_world_node[:, :3, 3], res.T_world_node[:, :3, 3],
                               rtol=0, atol=1e-4)


def test_a_part_losing_its_redundancy_keeps_its_last_factor():
    """Without the damping (``noise_prior_dof=0``) the same survey's rotation part has a
    redundancy of about 8 at its stated covariance and about 5.4 at the factor it runs to:
    with a minimum of 6 it is held at the factor at which it was last determined (its
    redundancy there at least the minimum) and reported as held."""
    s = biased_survey(np.random.default_rng(21), n_nodes=300, yaw_rate=0.004, fix_every=10,
                      fix_sigma_m=0.3, sigma_yaw_rad=0.002, stated_sigma_yaw_rad=0.008)
    cal = CalibrationConfig(noise=True, noise_prior_dof=0.0, noise_min_redundancy=6.0)
    _, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                    calibration=cal)
    rot = {f.part: f for f in rep.noise}['rotation']
    assert rot.held and 'held' in rot.line(), rep.lines()
    assert rot.redundancy >= cal.noise_min_redundancy, rep.lines()
    assert rot.factor < 1.0, rep.lines()


@pytest.mark.slow
def test_noise_factor_within_10_percent_with_enough_redundancy():
    """A fix (3 mm) at every keyframe gives the odometry hundreds of degrees of freedom; its
    stated covariance is 4x too small (all of it) and correlates x with yaw a little, so the
    source has one part (``motion``): its factor is determined to better than 7 % (its sigma)
    and within 10 % and 3 sigmas of the truth 4 (the prior's pull, ``4^(R / (R + 4))``, is
    under 1 % here)."""
    s = biased_survey(np.random.default_rng(5), n_nodes=300, yaw_rate=0.004, fix_every=1,
                      fix_sigma_m=0.003)
    a = s.network.arrays()
    cov = a.cov / 4.0
    cov[:, 0, 5] = cov[:, 5, 0] = 1e-3 * np.sqrt(cov[:, 0, 0] * cov[:, 5, 5])
    net = ConnectionNetwork.from_arrays(s.network.node_ids, s.network.track_ids, a.src, a.dst,
                                        a.z, cov)
    _, rep = solve_with_calibration(net, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                    calibration=CalibrationConfig())
    (f,) = rep.noise
    assert f.part == 'motion' and f.applied and not f.held, rep.lines()
    assert f.sigma / f.factor < 0.07, rep.lines()
    assert abs(f.factor / 4.0 - 1.0) < 0.1 and abs(f.factor - 4.0) < 3 * f.sigma, rep.lines()


def test_no_parameter_no_noise_reestimation():
    """Without a significant parameter the stated covariances stand: the result is the plain
    adjustment's (to its convergence; the selection re-solves from its last estimate) and no
    noise factor is reported."""
    s = biased_survey(np.random.default_rng(31), n_nodes=150, fix_every=10,
                      sigma_yaw_rad=0.002, stated_sigma_yaw_rad=0.008)
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                      calibration=CalibrationConfig(noise=True))
    assert not rep.estimated() and rep.noise == []
    plain = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, priors=s.priors,
                                   calibration=CalibrationConfig(parameters=()))[0]
    np.testing.assert_allclose(res.T_world_node, plain.T_world_node, rtol=0, atol=1e-6)
