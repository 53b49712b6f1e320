"""Absolute fixes as weighted parameters (ga_ros.core.fixes and the aligner's hooks)."""

from __future__ import annotations

import numpy as np
import pytest
from line_survey import feed, fixes_aligner, line_survey, wls_positions

from ga_ros.core.fixes import (
    AbsoluteFix,
    FixTerm,
    fix_information,
    node_prior,
    sensor_jacobian,
    sensor_misclosure,
)
from ga_ros.core.measurement import Measurement
from ga_ros.core.models import prior_residual
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import InputError
from ga_ros.geometry import se3, so3


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(25)


def _random_pose(rng: np.random.Generator, scale: float = 1.0) -> np.ndarray:
    return se3.from_translation_rotvec(rng.normal(0, 3.0, 3), rng.normal(0, scale, 3))


def test_rep145_unknown_rows_carry_no_information() -> None:
    C = np.diag([4.0, 9.0, -1.0, 1e12, np.nan, 0.25])
    C[0, 1] = C[1, 0] = 1.5
    L = fix_information(C)
    known = np.array([True, True, False, False, False, True])
    assert np.all(L[~known] == 0) and np.all(L[:, ~known] == 0)
    block = np.array([[4.0, 1.5, 0.0], [1.5, 9.0, 0.0], [0.0, 0.0, 0.25]])
    np.testing.assert_allclose(L[np.ix_(known, known)], np.linalg.inv(block), rtol=1e-12)
    with pytest.raises(InputError):
        fix_information(np.zeros((6, 6)))  # all zero: the caller substitutes its default
    with pytest.raises(InputError):
        fix_information(np.diag([-1.0] * 6))


def test_sensor_jacobian_against_central_differences(rng) -> None:
    T = _random_pose(rng)
    off = _random_pose(rng, 0.3)
    fix = AbsoluteFix(0, _random_pose(rng), np.eye(6))
    J = sensor_jacobian(T, off)
    h = 1e-6
    Jn = np.zeros((6, 6))
    for a in range(6):
        d = np.zeros(6)
        d[a] = h
        ep = sensor_misclosure(se3.retract(T, d), off, fix)
        em = sensor_misclosure(se3.retract(T, -d), off, fix)
        Jn[:, a] = (ep - em) / (2 * h)
    # the rotation rows are the left Jacobian's inverse at the misclosure times J: compare the
    # position rows exactly and the rotation rows at a zero rotation misclosure
    np.testing.assert_allclose(Jn[:3], J[:3], atol=1e-6)
    fix0 = AbsoluteFix(0, T @ off, np.eye(6))
    for a in range(6):
        d = np.zeros(6)
        d[a] = h
        Jn[:, a] = (sensor_misclosure(se3.retract(T, d), off, fix0)
                    - sensor_misclosure(se3.retract(T, -d), off, fix0)) / (2 * h)
    np.testing.assert_allclose(Jn, J, atol=1e-6)


@pytest.mark.parametrize('lever', [False, True])
def test_node_prior_gradient_and_hessian_match_the_fix_cost(rng, lever: bool) -> None:
    """The prior's cost ``r' H r`` (solver residual) has the gradient and Gauss-Newton Hessian of
    the fixes' own cost ``sum e_i' L_i e_i`` at the linearisation point (central differences on
    the manifold, right perturbation)."""
    T = _random_pose(rng)
    off = _random_pose(rng, 0.2) if lever else se3.identity()
    terms, infos = [], []
    for full in (True, False, True):
        # position and rotation errors uncorrelated (as fixes are): a correlated fix moves the
        # combined mean's rotation with the position misclosures, a linearisation point away
        L = np.zeros((6, 6))
        for blk in (slice(0, 3), slice(3, 6)):
            A = rng.normal(size=(3, 3))
            L[blk, blk] = A @ A.T + 0.5 * np.eye(3)
        if not full:
            L[3:, :] = 0.0
            L[:, 3:] = 0.0
        # misclosures: 0.3 m, 2 mrad (the rotation parts agree to first order in the
        # misclosure: the left and right Jacobians of SO(3) differ by O(|e|))
        noise = np.concatenate([rng.normal(0, 0.3, 3), rng.normal(0, 2e-3, 3)])
        fix = AbsoluteFix(0, T @ off @ se3.exp(noise), L)
        terms.append(FixTerm(0, off, fix))
        infos.append(L)
    T_m, H = node_prior(T, terms, infos)

    def prior_cost(X):
        r, _ = prior_residual('se3', X[None], T_m[None])
        return float(r[0] @ H @ r[0])

    def fix_cost(X):
        return sum(float(e @ Li @ e) for e, Li in
                   ((sensor_misclosure(X, t.T_node_sensor, t.fix), Li)
                    for t, Li in zip(terms, infos)))

    h = 1e-5
    g_p, g_f = np.zeros(6), np.zeros(6)
    for a in range(6):
        d = np.zeros(6)
        d[a] = h
        g_p[a] = (prior_cost(se3.retract(T, d)) - prior_cost(se3.retract(T, -d))) / (2 * h)
        g_f[a] = (fix_cost(se3.retract(T, d)) - fix_cost(se3.retract(T, -d))) / (2 * h)
    scale = np.abs(g_f).max()
    if lever:
        # with a lever arm the prior holds R_k o at the linearisation point: the position
        # gradient agrees, the rotation gradient differs by the lever-arm term (module doc)
        np.testing.assert_allclose(g_p[:3], g_f[:3], atol=1e-5 * scale)
    else:
        np.testing.assert_allclose(g_p, g_f, atol=1e-2 * scale)
    # Gauss-Newton Hessians: prior J' H J against sum J_e' L J_e (position block always)
    _, Jr = prior_residual('se3', T[None], T_m[None])
    H_p = Jr[0].T @ H @ Jr[0]
    H_f = sum(sensor_jacobian(T, t.T_node_sensor).T @ Li @ sensor_jacobian(T, t.T_node_sensor)
              for t, Li in zip(terms, infos))
    np.testing.assert_allclose(H_p[:3, :3], H_f[:3, :3], rtol=1e-3, atol=1e-6)
    if not lever:
        np.testing.assert_allclose(H_p, H_f, rtol=0.05, atol=1e-3 * np.abs(H_f).max())


def test_batch_with_fixes_equals_weighted_least_squares(rng) -> None:
    """Rotations known (to 1e-6 rad), so the se3 adjustment is the linear positions problem
    whose weighted least-squares solution is computed by hand."""
    n_tracks, per = 4, 10
    ms, z, p_true = line_survey(rng, n_tracks, per, 0.05)
    n = n_tracks * per
    fixes = {k: (p_true[k] + rng.normal(0, 0.5, 3), 0.5) for k in range(3, n, 7)}
    al = fixes_aligner(2)
    feed(al, ms, fixes)
    al.refine_batch()
    p_hat = al.corrected_path().T_world_node[:, :3, 3]
    p_ref = wls_positions(n, z, 0.05, fixes)
    np.testing.assert_allclose(p_hat, p_ref, atol=2e-4)


def test_window_newest_node_equals_batch_and_fixes_survive_freezing(rng) -> None:
    """In the (nearly) linear case the window's estimate of the newest track equals the batch
    solution of everything so far: the fixes of frozen tracks were absorbed into the joint
    priors, not lost (without them the newest track would drift away from the fixes' frame)."""
    n_tracks, per = 6, 8
    ms, z, p_true = line_survey(rng, n_tracks, per, 0.05)
    n = n_tracks * per
    fixes = {k: (p_true[k] + rng.normal(0, 0.3, 3), 0.3) for k in range(2, n, 5)}
    al = fixes_aligner(2)
    feed(al, ms, fixes)
    al.finish_track()
    path = al.corrected_path()
    assert path.frozen[:per].all()  # the first tracks froze
    p_ref = wls_positions(n, z, 0.05, fixes)
    last = slice(n - per, n)
    np.testing.assert_allclose(path.T_world_node[last, :3, 3], p_ref[last], atol=2e-3)
    # and its covariance is the batch one (the linear problem's inverse normal matrix)
    cov = al.covariance(n - 1)[:3, :3]
    al.refine_batch()
    np.testing.assert_allclose(cov, al.covariance(n - 1)[:3, :3], rtol=0.02, atol=1e-6)


def test_fix_on_frozen_or_unknown_node_is_refused_and_counted(rng) -> None:
    ms, _, _ = line_survey(rng, 4, 5, 0.05)
    al = fixes_aligner(1)
    for m in ms:
        al.add_measurement(m)
    fix = AbsoluteFix.from_covariance(0, se3.identity(), np.diag([1.0] * 3 + [-1.0] * 3))
    with pytest.raises(InputError):
        al.add_fix(FixTerm(0, se3.identity(), fix))
    with pytest.raises(InputError):
        al.add_fix(FixTerm(999, se3.identity(), fix))
    assert al.fix_stats.rejected == {'fix_frozen_node': 1, 'fix_no_keyframe': 1}


def test_gate_excludes_a_gross_fix_and_keeps_the_others(rng) -> None:
    n_tracks, per = 3, 20
    ms, z, p_true = line_survey(rng, n_tracks, per, 0.02)
    al = TrackWindowAligner(AlignerConfig(window_tracks=3, datum='fixes', refine_every_tracks=0,
                                          fix_gate_prob=0.9999))
    bad = {13, 40}
    for m in ms:
        al.add_measurement(m)
        k = m.dst_id
        if k % 3 == 1:
            p = p_true[k] + rng.normal(0, 0.5, 3) + (np.array([30.0, -20.0, 0.0]) if k in bad
                                                     else 0.0)
            al.add_fix(FixTerm(k, se3.identity(), AbsoluteFix.from_covariance(
                m.stamp_ns, se3.from_translation_rotvec(p, np.zeros(3)),
                np.diag([0.25] * 3 + [-1.0] * 3), 'gnss')))
    al.finish_track()
    assert al.fix_stats.outliers == len(bad)
    err = np.linalg.norm(al.corrected_path().T_world_node[:, :3, 3] - p_true, axis=1)
    assert err.max() < 1.0


def test_fix_rotation_is_a_left_perturbation_in_the_map_frame(rng) -> None:
    """A full-pose fix with only yaw known pins the heading (rz about the map's z axis)."""
    T = se3.from_translation_rotvec(np.zeros(3), np.array([0.0, 0.0, 0.3]))
    yaw = 0.5
    fix = AbsoluteFix.from_covariance(0, se3.from_translation_rotvec(
        np.zeros(3), np.array([0.0, 0.0, yaw])), np.diag([-1.0] * 5 + [0.01]))
    e = sensor_misclosure(T, se3.identity(), fix)
    np.testing.assert_allclose(e[3:], [0.0, 0.0, 0.3 - yaw], atol=1e-12)
    np.testing.assert_allclose(so3.exp(e[3:]) @ fix.T_map_sensor[:3, :3], T[:3, :3],
                               atol=1e-12)


def test_published_covariances_with_fixes_are_honest() -> None:
    """Monte-Carlo NEES: odometry drawn from its covariance, position fixes from theirs; the
    window aligner's published position covariances (newest node after the last update, and
    every node) against the actual errors: mean NEES within the chi-square band."""
    rng = np.random.default_rng(3)
    n_tracks, per, runs = 4, 30, 30
    n = n_tracks * per
    # a lawnmower: 30 m swaths, 1 m steps, turning at the swath ends
    T_true = [se3.identity()]
    steps = []
    for i in range(n - 1):
        turn = np.pi / 2 if (i % per) in (per - 2, per - 1) else 0.0
        steps.append(se3.from_translation_rotvec(np.array([1.0, 0.0, 0.0]),
                                                 np.array([0.0, 0.0, turn])))
        T_true.append(T_true[-1] @ steps[-1])
    T_true = np.array(T_true)
    C = np.diag([0.02 ** 2] * 3 + [0.003 ** 2] * 3)
    L = np.linalg.cholesky(C)
    sig_fix = 0.5
    nees_last, nees_all = [], []
    for _ in range(runs):
        al = TrackWindowAligner(AlignerConfig(window_tracks=2, datum='fixes',
                                              refine_every_tracks=0, fix_gate_prob=0.0),
                                T_world_first=T_true[0])
        for i in range(n - 1):
            T_m = steps[i] @ se3.exp(L @ rng.normal(size=6))
            al.add_measurement(Measurement.from_pose(i, i + 1, i // per, (i + 1) // per, T_m,
                                                     C, (i + 1) * 10 ** 9))
            k = i + 1
            if k % 10 == 5:
                p = T_true[k, :3, 3] + rng.normal(0, sig_fix, 3)
                al.add_fix(FixTerm(k, se3.identity(), AbsoluteFix.from_covariance(
                    k * 10 ** 9, se3.from_translation_rotvec(p, np.zeros(3)),
                    np.diag([sig_fix ** 2] * 3 + [-1.0] * 3))))
        al.finish_track()
        T = al.corrected_path().T_world_node
        cov = al.covariances(np.arange(n))
        # position error in the node frame (the covariance's right perturbation)
        e = np.einsum('kji,kj->ki', T[:, :3, :3], T_true[:, :3, 3] - T[:, :3, 3])
        nees = np.einsum('ki,ki->k', e, np.linalg.solve(cov[:, :3, :3], e[:, :, None])[:, :, 0])
        nees_last.append(nees[-1])
        nees_all.append(nees[1:].mean())
    from scipy.stats import chi2
    lo, hi = chi2.ppf([0.005, 0.995], 3 * runs) / runs
    assert lo < np.mean(nees_last) < hi, np.mean(nees_last)
    # over every node (frozen ones with the covariance they froze with): correlated along a
    # run, so a looser band
    assert 2.0 < np.mean(nees_all) < 4.5, np.mean(nees_all)


def test_fixes_survive_a_snapshot(rng, tmp_path) -> None:
    """A state file keeps the fixes (and the gauge prior): the restored aligner continues as
    the original does."""
    from ga_ros.core.window.persistence import load_state, save_state

    ms, _, p_true = line_survey(rng, 4, 10, 0.05)
    cfg = dict(window_tracks=2, datum='fixes', refine_every_tracks=0, freeze_ahead=False)
    a = TrackWindowAligner(AlignerConfig(**cfg))
    head, tail = ms[:25], ms[25:]
    for m in head:
        a.add_measurement(m)
        if m.dst_id % 4 == 0:
            a.add_fix(FixTerm(m.dst_id, se3.identity(), AbsoluteFix.from_covariance(
                m.stamp_ns, se3.from_translation_rotvec(p_true[m.dst_id] + [0.3, 0, 0],
                                                        np.zeros(3)),
                np.diag([0.04] * 3 + [-1.0] * 3), 'gnss')))
    save_state(a, tmp_path / 'state.ga')
    b = load_state(tmp_path / 'state.ga').aligner
    assert len(b.state.fixes) == len(a.state.fixes) and b.fix_stats == a.fix_stats
    for al in (a, b):
        for m in tail:
            al.add_measurement(m)
        al.finish_track()
    np.testing.assert_allclose(b.corrected_path().T_world_node, a.corrected_path().T_world_node,
                               atol=1e-9)
    # and the fixes moved the path (a 0.3 m shift of every fix along x)
    assert np.mean(a.corrected_path().T_world_node[:, 0, 3] - p_true[:, 0]) > 0.2
