"""Self-calibration of the fix sources (ga_ros.core.calibration.fix_parameters): the Jacobians
against finite differences of the measurement model, the bordered solution against a joint
least-squares solve by scipy, a known offset and a known latency recovered within 3 sigma with
a better path, the sigma's honesty over a Monte-Carlo, and an offset that one fix source
alone cannot determine: not estimated, and the result of the adjustment without it, bit for
bit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import least_squares
from solver_problems import whitener

from ga_ros.core.calibration import (
    FIX_PARAMETERS,
    CalibrationConfig,
    fix_priors,
    node_velocities,
    solve_with_calibration,
)
from ga_ros.core.calibration.fix_parameters import (
    fix_jacobians,
    fix_misclosures,
    fix_shift,
    node_velocity,
)
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.sim.biased import FixSource, biased_fixes, biased_survey

ALL = ('offset_x', 'offset_y', 'offset_z', 'time_offset')
OFFSET = np.array([2.0, -1.0, 0.5])


def _curve(t):
    return np.stack([3 * np.cos(0.2 * t), 2 * np.sin(0.3 * t), 0.1 * t], axis=-1)


def _curve_rate(t):
    return np.stack([-0.6 * np.sin(0.2 * t), 0.6 * np.cos(0.3 * t), 0.1 + 0 * t], axis=-1)


def test_velocity_is_the_derivative_of_the_path():
    t = np.arange(0.0, 20.0, 0.05)
    T = np.repeat(np.eye(4)[None], t.size, axis=0)
    T[:, :3, 3] = _curve(t)
    perm = np.random.default_rng(0).permutation(t.size)  # network order is not time order
    v = node_velocities(T[perm], t[perm])
    inner = (t[perm] > t[0]) & (t[perm] < t[-1])  # central differences
    np.testing.assert_allclose(v[inner], _curve_rate(t[perm])[inner], atol=5e-4)
    # d/dtau p(t - tau) = -p'(t): the time offset's Jacobian, by central differences
    h = 1e-5
    num = (_curve(t - h) - _curve(t + h)) / (2 * h)
    E = FIX_PARAMETERS['time_offset'].jacobian(node_velocities(T, t))
    np.testing.assert_allclose(E[1:-1, :3], num[1:-1], atol=5e-4)
    np.testing.assert_array_equal(E[:, 3:], 0.0)


def test_one_nodes_velocity_is_node_velocities_value_bit_for_bit():
    """:func:`node_velocity` (the online calibration's, one node) against
    :func:`node_velocities` (the batch's, all nodes): shuffled rows, shared stamps, the ends
    and a single node."""
    rng = np.random.default_rng(3)
    t = np.round(rng.uniform(0.0, 5.0, 40), 1)  # repeated stamps
    T = np.repeat(np.eye(4)[None], t.size, axis=0)
    T[:, :3, 3] = rng.normal(size=(t.size, 3))
    v = node_velocities(T, t)
    for row in range(t.size):
        np.testing.assert_array_equal(node_velocity(T, t, row), v[row], err_msg=str(row))
    np.testing.assert_array_equal(node_velocity(T[:1], t[:1], 0), np.zeros(3))
    # the newest node: one-sided, from the node before it in time
    np.testing.assert_array_equal(node_velocity(T[:3], np.array([0.0, 1.0, 2.0]), 2),
                                  T[2, :3, 3] - T[1, :3, 3])


@pytest.mark.parametrize('seed', [0, 1])
def test_fix_jacobians_match_finite_differences_of_the_misclosure(seed):
    """``de/dc`` against central differences of the misclosure of the corrected fixes (the
    correction :func:`fix_shift` applied to a fix with a lever arm and a pose far from it)."""
    rng = np.random.default_rng(seed)
    s = biased_survey(rng, n_nodes=40)
    stamps = np.arange(40) * 0.5
    obs = biased_fixes(rng, s.T_true, stamps, [FixSource('fix0', every=3, sigma_m=0.3)])
    T = s.T_true @ se3.exp(rng.normal(0, 0.05, (40, 6)))
    rows = obs.rows(s.network.node_ids)
    v = node_velocities(T, stamps)[rows]
    params = [FIX_PARAMETERS[k] for k in ALL]
    E = fix_jacobians(obs, params, v)
    c0 = rng.normal(0, 0.5, len(params))
    h = 1e-6
    for a in range(len(params)):
        d = np.zeros(len(params))
        d[a] = h
        ep = fix_misclosures(obs, T, rows, fix_shift(E, c0 + d))[0]
        em = fix_misclosures(obs, T, rows, fix_shift(E, c0 - d))[0]
        np.testing.assert_allclose(E[:, :, a], (ep - em) / (2 * h), atol=1e-7)
    # the model itself: e = p_pred + b - v tau - p_fix
    e = fix_misclosures(obs, T, rows, fix_shift(E, c0))[0]
    e0 = fix_misclosures(obs, T, rows, np.zeros((len(obs), 3)))[0]
    np.testing.assert_allclose(e[:, :3], e0[:, :3] + c0[:3] - v * c0[3], atol=1e-12)


def _two_sources(seed, n=200, offset=OFFSET, latency=0.0):
    rng = np.random.default_rng(seed)
    s = biased_survey(rng, n_nodes=n)
    stamps = np.arange(n) * 0.5
    obs = biased_fixes(rng, s.T_true, stamps, [
        FixSource('fix0', every=5, sigma_m=0.2),
        FixSource('fix1', every=10, first=2, sigma_m=0.5, offset_m=tuple(offset),
                  latency_s=latency)])
    return s, obs


def _rmse(T, s):
    return np.sqrt(np.mean(np.sum((T[:, :3, 3] - s.T_true[:, :3, 3]) ** 2, axis=1)))


@pytest.mark.parametrize('seed', [3, 4, 5])
def test_recovers_a_known_offset_of_the_second_source(seed):
    s, obs = _two_sources(seed)
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
                                      calibration=CalibrationConfig(fix_parameters=ALL),
                                      fixes=obs)
    est = {(p.source, p.name): p for p in rep.parameters}
    for axis, name in enumerate(('offset_x', 'offset_y', 'offset_z')):
        p = est[('fix1', name)]
        assert p.estimated, rep.lines()
        assert abs(p.value - OFFSET[axis]) < 3 * p.sigma, rep.lines()
        # the better source is the reference: only the difference is determined
        assert not est[('fix0', name)].estimated
        assert 'not separable from' in est[('fix0', name)].reason
        assert f'fix1 {name}' in est[('fix0', name)].reason
    plain = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
                                   calibration=CalibrationConfig(fix_parameters=()),
                                   fixes=obs)[0]
    assert _rmse(res.T_world_node, s) < 0.8 * _rmse(plain.T_world_node, s)
    text = '\n'.join(rep.lines())
    assert 'fix1 offset_x = ' in text and ' m (|t| ' in text
    plain_dict = rep.as_dict()
    assert any(p['source'] == 'fix1' and p['name'] == 'offset_y' and p['estimated']
               for p in plain_dict['parameters'])


@pytest.mark.parametrize('seed', [6, 7, 8])
def test_recovers_a_known_latency_of_one_source(seed):
    rng = np.random.default_rng(seed)
    s = biased_survey(rng, n_nodes=200)
    obs = biased_fixes(rng, s.T_true, np.arange(200) * 0.5,
                       [FixSource('gnss', every=4, sigma_m=0.3, latency_s=0.3)])
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
                                      calibration=CalibrationConfig(fix_parameters=ALL),
                                      fixes=obs)
    est = {p.name: p for p in rep.parameters if p.source == 'gnss'}
    assert est['time_offset'].estimated, rep.lines()
    assert abs(est['time_offset'].value - 0.3) < 3 * est['time_offset'].sigma, rep.lines()
    for name in ('offset_x', 'offset_y', 'offset_z'):
        assert not est[name].estimated
        assert est[name].reason.startswith('not determined by the network')
    plain = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
                                   calibration=CalibrationConfig(fix_parameters=()),
                                   fixes=obs)[0]
    assert _rmse(res.T_world_node, s) < 0.8 * _rmse(plain.T_world_node, s)


def test_an_offset_one_source_cannot_see_is_not_estimated_and_changes_nothing():
    """One fix source and odometry, no other absolute information: its offset is the datum's
    (the fixes define the frame), so it is not determined, the report says why, and the
    adjustment is the one without fix parameters, bit for bit."""
    rng = np.random.default_rng(21)
    s = biased_survey(rng, n_nodes=150)
    obs = biased_fixes(rng, s.T_true, np.arange(150) * 0.5,
                       [FixSource('gnss', every=5, sigma_m=0.5, offset_m=tuple(OFFSET))])
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
                                      calibration=CalibrationConfig(fix_parameters=ALL),
                                      fixes=obs)
    est = {p.name: p for p in rep.parameters if p.source == 'gnss'}
    for name in ('offset_x', 'offset_y', 'offset_z'):
        assert not est[name].estimated
        assert 'its fixes define the frame' in est[name].reason, est[name].reason
        assert est[name].information_ratio < 1e-6
    assert not est['time_offset'].estimated, rep.lines()
    # the adjustment with the fixes as plain priors (no fix parameters at all)
    ref, ref_rep = solve_with_calibration(
        s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
        priors=fix_priors(obs, s.T_dead, s.network.node_ids),
        calibration=CalibrationConfig(fix_parameters=()))
    assert np.array_equal(res.T_world_node, ref.T_world_node)
    assert [p.value for p in rep.parameters[:2]] == [p.value for p in ref_rep.parameters]


def test_a_held_node_determines_the_offset_of_a_single_source():
    """A held node is absolute information: the first node held at its true pose, one fix
    source's offset is determined and recovered."""
    rng = np.random.default_rng(22)
    s = biased_survey(rng, n_nodes=150)
    obs = biased_fixes(rng, s.T_true, np.arange(150) * 0.5,
                       [FixSource('gnss', every=5, sigma_m=0.5, offset_m=tuple(OFFSET))])
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[0],
                                      calibration=CalibrationConfig(fix_parameters=ALL),
                                      fixes=obs)
    est = {p.name: p for p in rep.parameters if p.source == 'gnss'}
    for axis, name in enumerate(('offset_x', 'offset_y', 'offset_z')):
        assert est[name].estimated, rep.lines()
        assert abs(est[name].value - OFFSET[axis]) < 3 * est[name].sigma


def test_estimate_matches_joint_least_squares():
    """The bordered Gauss-Newton with the fixes' parameters reaches the minimum of the joint
    problem over poses, fix1's offset and its latency, computed by scipy with the velocity a
    function of the poses (the bordered solution holds it at each estimate)."""
    s, obs = _two_sources(9, n=60, latency=0.2)
    cal = CalibrationConfig(parameters=(), fix_parameters=ALL, alpha=1.0 - 1e-9, noise=False,
                            tolerance=1e-6)
    res, rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
                                      calibration=cal, fixes=obs)
    est = {(p.source, p.name): p for p in rep.parameters}
    names = [('fix1', k) for k in ALL] + [('fix0', 'time_offset')]
    assert all(est[k].estimated for k in names), rep.lines()
    arr = s.network.arrays()
    Lc = np.array([whitener(np.linalg.inv(c)) for c in arr.cov])
    Lf = np.array([whitener(i[:3, :3]) for i in obs.information])
    rows = obs.rows(s.network.node_ids)
    is1 = np.array([src == 'fix1' for src in obs.sources])
    pf = np.array([t.fix.T_map_sensor[:3, 3] for t in obs.terms])
    stamps = obs.node_stamps_s
    n = s.T_dead.shape[0]

    def fun(x):
        T = s.T_dead @ se3.exp(x[:6 * n].reshape(n, 6))
        b, tau1, tau0 = x[6 * n:6 * n + 3], x[6 * n + 3], x[6 * n + 4]
        e = se3.log(se3.inverse(se3.from_translation_rotvec(arr.z[:, :3], arr.z[:, 3:]))
                    @ se3.relative(T[arr.src], T[arr.dst]))
        v = node_velocities(T, stamps)[rows]
        tau = np.where(is1, tau1, tau0)
        ef = T[rows, :3, 3] + np.where(is1[:, None], b, 0.0) - v * tau[:, None] - pf
        return np.concatenate([(Lc @ e[:, :, None]).ravel(), (Lf @ ef[:, :, None]).ravel()])

    sol = least_squares(fun, np.zeros(6 * n + 5), xtol=1e-14, ftol=1e-14, gtol=1e-14)
    got = np.array([est[k].value for k in names])
    sig = np.array([est[k].sigma for k in names])
    # the velocity's own dependence on the poses (second order) is the only difference
    assert np.all(np.abs(got - sol.x[6 * n:]) < 0.05 * sig), (got, sol.x[6 * n:], sig)
    Q = np.linalg.inv(sol.jac.T @ sol.jac)
    np.testing.assert_allclose(sig, np.sqrt(np.diag(Q)[6 * n:]), rtol=0.05)


def test_offset_sigma_is_honest_over_a_monte_carlo():
    """The NEES of fix1's offset per axis, ``((b - b_true) / sigma)^2`` with the published
    sigmas, summed over seeds (always estimated: no selection by the test): inside the 99 %
    band of its chi-square."""
    from scipy.stats import chi2

    nees, dof = 0.0, 0
    for seed in range(30, 38):
        s, obs = _two_sources(seed, n=120)
        rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
                                     calibration=CalibrationConfig(
                                         fix_parameters=ALL[:3], noise=False,
                                         alpha=1.0 - 1e-9),
                                     fixes=obs)[1]
        est = {(p.source, p.name): p for p in rep.parameters}
        for axis, name in enumerate(ALL[:3]):
            p = est[('fix1', name)]
            assert p.estimated
            nees += ((p.value - OFFSET[axis]) / p.sigma) ** 2
            dof += 1
    lo, hi = chi2.ppf([0.005, 0.995], dof)
    assert lo < nees < hi, (nees, dof)


def test_unknown_fix_parameter_is_refused():
    with pytest.raises(InputError, match='unknown fix calibration parameter'):
        CalibrationConfig(fix_parameters=('latency',))


def test_book_observations_give_the_books_fix_prior_bit_for_bit():
    """An aligner's fix book (a gauge prior, an excluded fix, two fixes on one node, lever
    arms, full-pose fixes) as observations: their priors are the book's, so passing them as
    ``fixes`` instead of the book's priors changes nothing while no fix parameter is
    estimated."""
    from ga_ros.core.calibration import book_observations
    from ga_ros.core.fixes import AbsoluteFix, FixBook, FixTerm, gauge_information

    rng = np.random.default_rng(3)
    n = 12
    T = se3.exp(rng.normal(0, 1.0, (n, 6)))
    ids = np.arange(100, 100 + n)
    book = FixBook()
    book.add_gauge(0, int(ids[0]), 0, T[0], gauge_information(1e3, 0.05, 3.0))
    for k, row in enumerate([1, 4, 4, 7, 9, 11]):
        off = se3.exp(rng.normal(0, 0.3, 6))
        cov = np.diag(rng.uniform(0.1, 1.0, 6))
        if k % 2:
            cov[3:, 3:] = np.eye(3) * 1e9  # position only
        fix = AbsoluteFix.from_covariance(k * 10**8, T[row] @ off @ se3.exp(rng.normal(0, .1, 6)),
                                          cov, 'gnss')
        book.add(row, FixTerm(int(ids[row]), off, fix), fix.information)
    book.status[3] = 2  # excluded
    rows = np.arange(n)
    want = book.priors(rows, T, ids)
    obs = book_observations(book, rows, np.arange(n) * 0.5)
    assert len(obs) == 5
    got = fix_priors(obs, T, ids)
    assert np.array_equal(got[0].node_ids, want[0].node_ids)
    assert np.array_equal(got[0].T_world_node, want[0].T_world_node)
    assert np.array_equal(np.asarray(got[0].information), np.asarray(want[0].information))
    assert want[1].weak and len(want) == 2


def test_a_reference_source_gets_no_offset_and_the_other_is_estimated_against_it():
    """``fix_reference``: the worse source named the reference keeps the frame (no offset
    candidate), so the better source's offset is estimated against it: minus the worse one's
    true offset."""
    s, obs = _two_sources(3)
    res, rep = solve_with_calibration(
        s.network, s.T_dead, s.sources, s.dt_s, fixed=[], fixes=obs,
        calibration=CalibrationConfig(fix_parameters=ALL, fix_reference=('fix1',)))
    names = [(p.source, p.name) for p in rep.parameters]
    assert ('fix1', 'offset_x') not in names and ('fix1', 'time_offset') in names
    est = {(p.source, p.name): p for p in rep.parameters}
    for axis, name in enumerate(('offset_x', 'offset_y', 'offset_z')):
        p = est[('fix0', name)]
        assert p.estimated, rep.lines()
        assert abs(p.value + OFFSET[axis]) < 3 * p.sigma


def test_no_stamps_no_time_offset():
    """Nodes without stamps (all 0): no velocity, so the time offset acts on nothing and is
    not a candidate, with the reason; the offsets are still tested."""
    s, obs = _two_sources(3, n=80)
    flat = type(obs)(obs.terms, obs.information, np.zeros_like(obs.node_stamps_s))
    rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[], fixes=flat,
                                 calibration=CalibrationConfig(fix_parameters=ALL))[1]
    est = {(p.source, p.name): p for p in rep.parameters}
    for src in ('fix0', 'fix1'):
        assert not est[(src, 'time_offset')].estimated
        assert 'no fix taken while moving' in est[(src, 'time_offset')].reason
    assert est[('fix1', 'offset_x')].estimated, rep.lines()


def test_time_offset_sigma_is_honest_over_a_monte_carlo():
    """The NEES of one source's latency over seeds (always estimated): inside the 99 % band
    of its chi-square."""
    from scipy.stats import chi2

    z = []
    for seed in range(100, 116):
        rng = np.random.default_rng(seed)
        s = biased_survey(rng, n_nodes=120)
        obs = biased_fixes(rng, s.T_true, np.arange(120) * 0.5,
                           [FixSource('gnss', every=4, sigma_m=0.3, latency_s=0.3)])
        rep = solve_with_calibration(s.network, s.T_dead, s.sources, s.dt_s, fixed=[],
                                     fixes=obs, calibration=CalibrationConfig(
                                         alpha=1.0 - 1e-9, noise=False))[1]
        p = next(p for p in rep.parameters if p.name == 'time_offset')
        assert p.estimated
        z.append((p.value - 0.3) / p.sigma)
    lo, hi = chi2.ppf([0.005, 0.995], len(z))
    assert lo < float(np.sum(np.square(z))) < hi, z
