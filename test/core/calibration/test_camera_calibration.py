"""A camera extrinsic's rotation as additional parameters (ga_ros.core.calibration.
camera_parameters): the generators against central differences of the corrected motion's
misclosure, the recovery of a known rotation error on a swath survey with cross-track
connections, and a straight-line camera survey, where the poses absorb it: not estimated,
the result the uncalibrated one bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.core.calibration import (
    CAMERA_PARAMETERS,
    PARAMETERS,
    CalibrationConfig,
    camera_sources,
    misclosure_jacobian,
    solve_with_calibration,
)
from ga_ros.core.calibration.parameters import MotionCorrections
from ga_ros.core.solver import solve
from ga_ros.errors import InputError
from ga_ros.geometry import se3, so3
from ga_ros.sim.camera_survey import line_survey, swath_survey

PHI = np.array([0.02, -0.01, 0.03])  # the extrinsic's rotation error (rad, body frame)


def _corrected(z, dt, k, om, phi):
    """``X S(T) X^-1`` written out independently of the module (matrices, no generators)."""
    T = se3.from_translation_rotvec(z[:3], z[3:])
    c, s = np.cos(om * dt), np.sin(om * dt)
    S = T.copy()
    S[:3, :3] = T[:3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    S[:3, 3] = (1.0 + k) * T[:3, 3]
    X = np.eye(4)
    X[:3, :3] = so3.exp(phi)
    return X @ S @ np.linalg.inv(X)


def _misclosure(x, z, dt, Tij):
    return se3.log(np.linalg.inv(_corrected(z, dt, x[0], x[1], x[2:])) @ Tij)


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_generators_match_finite_differences(seed):
    """Every parameter's Jacobian ``-J_l(e)^-1 G`` of the misclosure of a corrected motion
    (scale, yaw rate and the extrinsic's three axes together, at non-zero values, a turn of
    up to 180 deg) against central differences of the misclosure computed from matrices."""
    rng = np.random.default_rng(seed)
    z = np.concatenate([rng.normal(0, 3.0, 3), rng.normal(0, 1.0, 3)])
    if seed == 2:
        z[3:] = [0.0, 0.0, np.pi - 0.01]   # a cross-track connection between swaths
    dt = 0.7
    x = np.concatenate([rng.normal(0, 0.05, 2), rng.normal(0, 0.05, 3)])
    corr = MotionCorrections(np.array([x[0]]), np.array([x[1]]), x[None, 2:])
    motions = corr.apply(z[None], np.array([dt]))
    np.testing.assert_allclose(motions.T[0], _corrected(z, dt, x[0], x[1], x[2:]), atol=1e-12)
    Tij = motions.T[0] @ se3.exp(rng.normal(0, 0.2, 6))  # a misclosure far from zero
    e = _misclosure(x, z, dt, Tij)
    h = 1e-6
    params = [PARAMETERS['scale'], PARAMETERS['yaw_rate']] + [
        CAMERA_PARAMETERS[f'extrinsic_r{a}'] for a in 'xyz']
    for i, par in enumerate(params):
        d = np.zeros(5)
        d[i] = h
        num = (_misclosure(x + d, z, dt, Tij) - _misclosure(x - d, z, dt, Tij)) / (2 * h)
        ana = misclosure_jacobian(e[None], par.generator_of(motions))[0]
        np.testing.assert_allclose(ana, num, atol=1e-7, rtol=1e-6, err_msg=par.name)


def _rmse(T, T_true):
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_extrinsic_rotation_recovered_on_a_swath_survey(seed):
    """Swaths flown in alternating directions, a body-frame odometry and the camera's
    cross-track connections conjugated by a known extrinsic rotation error: each axis
    estimated within 3 sigma of the truth, the path closer to the truth than without."""
    s = swath_survey(np.random.default_rng(seed), PHI)
    res, rep = solve_with_calibration(s.network, s.T_init, s.sources, s.dt_s, fixed=s.fixed,
                                      calibration=CalibrationConfig(cameras=('cam0',)),
                                      groups=s.groups)
    cam = [p for p in rep.parameters if p.source == 'cam0' and p.name.startswith('extrinsic')]
    assert [p.name for p in cam] == ['extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz']
    for p, truth in zip(cam, PHI):
        assert p.estimated, p.line()
        assert abs(p.value - truth) < 3.0 * p.sigma, p.line()
        assert p.unit == 'rad' and f'cam0 {p.name} = ' in p.line()
    # the odometry has no systematic error: its parameters are candidates, not estimated
    assert not any(p.estimated for p in rep.parameters if p.source == 'odom0')
    d = rep.as_dict()
    assert {q['name'] for q in d['parameters'] if q['source'] == 'cam0'} == {
        'extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz'}
    plain = solve(s.network, s.T_init, fixed=s.fixed)
    assert _rmse(res.T_world_node, s.T_true) < 0.5 * _rmse(plain.T_world_node, s.T_true)


def test_no_camera_named_changes_nothing():
    """The default configuration names no camera: no camera candidate, and the result is the
    one of a configuration without camera parameters, bit for bit."""
    s = swath_survey(np.random.default_rng(3), PHI)
    res, rep = solve_with_calibration(s.network, s.T_init, s.sources, s.dt_s, fixed=s.fixed,
                                      groups=s.groups)
    res0, rep0 = solve_with_calibration(s.network, s.T_init, s.sources, s.dt_s, fixed=s.fixed,
                                        calibration=CalibrationConfig(camera_parameters=()))
    assert not any(p.source == 'cam0' for p in rep.parameters)
    assert np.array_equal(res.T_world_node, res0.T_world_node)
    assert rep.lines() == rep0.lines()


@pytest.mark.parametrize('seed', [0, 1, 2])
def test_a_straight_camera_survey_does_not_determine_it(seed):
    """The camera alone on a straight line with position fixes: the poses absorb the
    conjugation (every axis not determined, with the reason), and the result is the
    uncalibrated one bit for bit."""
    s = line_survey(np.random.default_rng(seed), PHI)
    res, rep = solve_with_calibration(s.network, s.T_init, s.sources, s.dt_s,
                                      priors=s.priors, groups=s.groups,
                                      calibration=CalibrationConfig(cameras=('cam0',)))
    res0, rep0 = solve_with_calibration(s.network, s.T_init, s.sources, s.dt_s,
                                        priors=s.priors, groups=s.groups)
    cam = [p for p in rep.parameters if p.name.startswith('extrinsic')]
    assert len(cam) == 3
    for p in cam:
        assert not p.estimated and p.reason.startswith('not determined'), p.line()
    assert np.array_equal(res.T_world_node, res0.T_world_node)
    assert [p.line() for p in rep.parameters if not p.name.startswith('extrinsic')] == \
        rep0.lines()[:len(rep0.parameters)]


def test_camera_sources_and_config():
    assert camera_sources(['odom0', 'cam0', 'cross', 'cam0'], ('cam0',)) == [
        None, 'cam0', None, 'cam0']
    with pytest.raises(InputError, match='extrinsic_rx'):
        CalibrationConfig(camera_parameters=('extrinsic_roll',))


def _whitener(info):
    w, V = np.linalg.eigh(0.5 * (info + info.T))
    return np.sqrt(w)[:, None] * V.T


def test_estimate_matches_joint_least_squares():
    """The bordered Gauss-Newton with the camera's parameters reaches the minimum of the joint
    problem computed independently by scipy over the poses and the three axes together (the
    corrected motions written out with matrices), and its sigmas are those of the joint
    normal matrix."""
    from scipy.optimize import least_squares

    s = swath_survey(np.random.default_rng(7), PHI, n_swaths=3, per_swath=10)
    res, rep = solve_with_calibration(
        s.network, s.T_init, s.sources, s.dt_s, fixed=s.fixed, groups=s.groups,
        calibration=CalibrationConfig(parameters=(), cameras=('cam0',), alpha=1.0 - 1e-9,
                                      noise=False))
    est = [p for p in rep.parameters if p.source == 'cam0']
    assert all(p.estimated for p in est), rep.lines()
    arr = s.network.arrays()
    Lc = np.array([_whitener(np.linalg.inv(c)) for c in arr.cov])
    cam = np.array(s.groups) == 'cam0'
    n = s.T_init.shape[0]

    def fun(x):
        T = s.T_init.copy()
        T[1:] = T[1:] @ se3.exp(x[:6 * (n - 1)].reshape(n - 1, 6))
        phi = x[6 * (n - 1):]
        Tc = np.array([_corrected(z, 0.0, 0.0, 0.0, phi if c else np.zeros(3))
                       for z, c in zip(arr.z, cam)])
        e = se3.log(se3.inverse(Tc) @ se3.relative(T[arr.src], T[arr.dst]))
        return (Lc @ e[:, :, None]).ravel()

    sol = least_squares(fun, np.zeros(6 * (n - 1) + 3), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    phi = sol.x[6 * (n - 1):]
    Q = np.linalg.inv(sol.jac.T @ sol.jac)[-3:, -3:]
    for a, p in enumerate(est):
        assert abs(p.value - phi[a]) < 1e-3 * p.sigma, (p.line(), phi)
        assert p.sigma == pytest.approx(np.sqrt(Q[a, a]), rel=1e-3)
    T = s.T_init.copy()
    T[1:] = T[1:] @ se3.exp(sol.x[:6 * (n - 1)].reshape(n - 1, 6))
    np.testing.assert_allclose(res.T_world_node[:, :3, 3], T[:, :3, 3], atol=1e-3)


@pytest.mark.slow
def test_the_extrinsics_nees_over_seeds():
    """The published sigmas are honest: per axis, the mean of ``((phi - truth) / sigma)^2``
    over 16 seeds of the swath survey inside the 99 % band of ``chi2(16) / 16``."""
    from scipy.stats import chi2

    z = []
    for seed in range(100, 116):
        s = swath_survey(np.random.default_rng(seed), PHI)
        _, rep = solve_with_calibration(s.network, s.T_init, s.sources, s.dt_s,
                                        fixed=s.fixed, groups=s.groups,
                                        calibration=CalibrationConfig(cameras=('cam0',)))
        cam = [p for p in rep.parameters if p.source == 'cam0']
        assert all(p.estimated for p in cam), rep.lines()
        z.append([(p.value - t) / p.sigma for p, t in zip(cam, PHI)])
    nees = np.mean(np.square(z), axis=0)
    lo, hi = chi2.ppf([0.005, 0.995], 16) / 16
    assert np.all((nees > lo) & (nees < hi)), (nees, lo, hi)


def test_the_cameras_consecutive_motions_carry_it_too():
    """With the camera's visual odometry beside the body-frame odometry on every consecutive
    motion, its consecutive connections see the extrinsic as well (a translation measured by
    both turns by ``phi``): every axis within 3 sigma, with smaller sigmas than from the
    cross-track connections alone (the same survey otherwise)."""
    kw = dict(n_swaths=4)
    s = swath_survey(np.random.default_rng(8), PHI, camera_consecutive=True, **kw)
    cal = CalibrationConfig(cameras=('cam0',))
    _, rep = solve_with_calibration(s.network, s.T_init, s.sources, s.dt_s, fixed=s.fixed,
                                    calibration=cal, groups=s.groups)
    cam = [p for p in rep.parameters if p.source == 'cam0' and p.name.startswith('extr')]
    s1 = swath_survey(np.random.default_rng(8), PHI, **kw)
    _, rep1 = solve_with_calibration(s1.network, s1.T_init, s1.sources, s1.dt_s,
                                     fixed=s1.fixed, calibration=cal, groups=s1.groups)
    alone = [p for p in rep1.parameters if p.source == 'cam0']
    for p, q, truth in zip(cam, alone, PHI):
        assert p.estimated and abs(p.value - truth) < 3 * p.sigma, rep.lines()
        assert p.sigma < q.sigma, (p.line(), q.line())
    # cam0's consecutive motions also carry its odometry parameters (not estimated: no error)
    assert {p.name for p in rep.parameters if p.source == 'cam0'} == {
        'scale', 'yaw_rate', 'extrinsic_rx', 'extrinsic_ry', 'extrinsic_rz'}


@pytest.mark.parametrize('seed', [0, 1])
def test_the_corrected_motions_covariance_is_monte_carlo_s(seed):
    """``conjugated_covariances``: the covariance of ``X T X^-1`` (``[t, rotvec]``) for motions
    ``T`` drawn with a full covariance ``C`` is the sample covariance of the corrected motions
    (20,000 draws, within 5 % of each standard deviation and 0.03 in correlation); undone
    (``inverse``) it is ``C`` again to 1e-15."""
    from ga_ros.core.calibration.camera_parameters import conjugated_covariances

    rng = np.random.default_rng(seed)
    z0 = np.concatenate([rng.normal(0, 3, 3), rng.normal(0, 0.4, 3)])
    L = rng.normal(size=(6, 6)) * np.array([0.2] * 3 + [0.01] * 3)[:, None]
    C = L @ L.T + np.diag([0.01] * 3 + [1e-5] * 3)
    phi = rng.normal(0, 0.3, 3)
    z = rng.multivariate_normal(z0, C, size=20_000)
    X = np.eye(4)
    X[:3, :3] = so3.exp(phi)
    T = X @ se3.from_translation_rotvec(z[:, :3], z[:, 3:]) @ np.linalg.inv(X)
    sample = np.cov(se3.to_translation_rotvec(T).T)
    got = conjugated_covariances(C, phi)[0]
    sd, sd_s = np.sqrt(np.diag(got)), np.sqrt(np.diag(sample))
    np.testing.assert_allclose(sd, sd_s, rtol=0.05)
    np.testing.assert_allclose(got / np.outer(sd, sd), sample / np.outer(sd_s, sd_s), atol=0.03)
    # the stated covariance is not the corrected one's (the check can fail)
    assert np.abs(C / np.outer(sd_s, sd_s) - sample / np.outer(sd_s, sd_s)).max() > 0.1
    np.testing.assert_allclose(conjugated_covariances(got, phi, inverse=True)[0], C,
                               atol=1e-15 * np.abs(C).max() * 10)
