"""Honest covariances on long swaths (issue #15 item 2): the frozen prior holds where the window
moves the boundary, and a position NEES checked against an independent computation.

At 10 % noise on 400-pose swaths the window's published covariances were overconfident (mean
position NEES 50-200 in ``ga-ros bench nees``) while the batch solve of the same data was
honest (NEES ~3). The cause was the residual of the frozen tracks' joint prior: the exact
second-order model of the absorbed connections at the freeze estimate, in the SE(3) tangent
``log(T_mean^-1 T)``, whose translation mixes the rotation with the absolute displacement of the
boundary; the next track moves that boundary far (100-300 m, several degrees on a 2-4 km swath)
and there the model was 70 chi-square units too cheap. The prior now takes position and
rotation apart (:func:`ga_ros.core.models.prior_residual`, :func:`ga_ros.core.window.freeze.
tangent_prior`): the same quadratic at the linearisation point (a change of variables), but it
holds where the window goes. The survey made small enough for a unit test: 2 double tracks, 200
poses per swath, 20 % noise, window 1 track.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from ga_ros.core import models
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.freeze import tangent_prior
from ga_ros.eval import position_nees
from ga_ros.geometry import se3
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb

PER_SWATH = 200


@pytest.fixture(scope='module')
def survey():
    sc = aerial_scenario(n_tracks=2, positions_per_swath=PER_SWATH)
    nm = perturb(sc.true_motions(), NoiseModel(20.0, sc.depth_m), np.random.default_rng(0))
    batch = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z),
                  SolverConfig(tolerance=1e-9, max_iterations=50))
    return sc, nm, batch


@pytest.fixture(scope='module')
def first_estimate(survey):
    """The window's own run: track 0 frozen at its first estimate."""
    return _aligner(*survey[:2])


def _aligner(sc, nm, batch=None) -> TrackWindowAligner:
    """Window of one track, refinement off; ``batch``: the estimate is set to the batch
    solution just before the second track's update (so track 0 freezes there: the prior is
    linearised at the batch estimate)."""
    al = TrackWindowAligner(AlignerConfig(window_tracks=1, refine_every_tracks=0),
                            sc.T_world_node[0])
    al.add_measurements(sc.measurements(nm.z, nm.cov))
    if batch is not None:
        al.state.T[:sc.n_nodes] = batch.T_world_node[np.asarray(al.state.ids)]
    al.finish_track()
    return al


def test_position_nees_equals_a_direct_computation():
    """``e' C_pp^-1 e`` with ``T_est = T_true exp(-d)`` (so ``e = d`` exactly), against an
    explicit inverse of each position block."""
    rng = np.random.default_rng(4)
    n = 7
    T_true = se3.exp(rng.normal(scale=[5, 5, 5, 0.3, 0.3, 0.3], size=(n, 6)))
    d = rng.normal(scale=[2, 1, 0.5, 0.05, 0.05, 0.05], size=(n, 6))
    A = rng.normal(size=(n, 6, 6))
    cov = A @ np.swapaxes(A, 1, 2) + 0.1 * np.eye(6)
    got = position_nees(T_true @ se3.exp(-d), cov, T_true)
    want = [d[i, :3] @ np.linalg.inv(cov[i, :3, :3]) @ d[i, :3] for i in range(n)]
    np.testing.assert_allclose(got, want, rtol=1e-9)


def test_the_frozen_prior_holds_where_the_window_moves_the_boundary(survey, first_estimate):
    """The prior of the frozen first track against the true cost of the connections it absorbed
    (its eliminated nodes re-adjusted with the prior nodes held): from the freeze estimate to
    the batch solution and to the window's own solution both rise alike (within 2 %; a rise of
    ~225 chi-square units). With the SE(3)-tangent residual the window's boundary ended 330 m
    and 13 deg from the freeze estimate, where the prior said 232 and the truth was 303
    (docs/window-design.md, "The frozen prior's residual: position and rotation apart")."""
    sc, nm, batch = survey
    al = first_estimate
    (idx, mean, H), = al.state.priors
    H = H.toarray() if sp.issparse(H) else H
    ids = np.asarray(al.state.ids)[idx]
    wn, wT = al.state.T_weighted
    where = {int(i): k for k, i in enumerate(wn)}
    T_window = wT[[where[int(i)] for i in ids]]
    n0 = 2 * PER_SWATH  # the first double track; the datum is node 0
    keep = (sc.src < n0) & (sc.dst < n0)
    absorbed = sc.first_tracks(1).network(nm.z[keep], nm.cov[keep])

    def true_cost(T_S):
        T = batch.T_world_node[:n0].copy()
        T[ids] = T_S
        return solve(absorbed, T, SolverConfig(tolerance=1e-10, max_iterations=50),
                     fixed=[0] + ids.tolist()).cost

    def prior_cost(T_S):
        e, _ = models.prior_residual('se3', T_S, mean)
        return float(e.ravel() @ H @ e.ravel())

    T_lin = al.state.T[idx]  # frozen nodes are not written back: the freeze estimate
    for T in (batch.T_world_node[ids], T_window):
        true_rise = true_cost(T) - true_cost(T_lin)
        prior_rise = prior_cost(T) - prior_cost(T_lin)
        assert true_rise > 100.0 and abs(prior_rise - true_rise) < 0.02 * true_rise, \
            (true_rise, prior_rise)


def test_the_split_residual_is_a_change_of_variables_of_the_tangent_one():
    """In the linear limit nothing changes: the split prior residual and the SE(3) tangent
    ``log(T_mean^-1 T)`` agree to first order at the mean, so with the same information their
    costs differ by O(|d|^3) (halving the step divides the difference by ~8); the residual's
    Jacobian matches central differences on the manifold (perturb with exp, near the mean and
    20 deg / 300 m away)."""
    rng = np.random.default_rng(7)
    k = 4
    mean = se3.exp(rng.normal(scale=[300, 300, 50, 1, 1, 1], size=(k, 6)))
    A = rng.normal(size=(6 * k, 6 * k))
    H = A @ A.T + np.eye(6 * k)
    v = rng.normal(scale=[100, 100, 100, 0.2, 0.2, 0.2], size=(k, 6))

    def costs(t):
        T = mean @ se3.exp(t * v)
        e_split = models.prior_residual('se3', T, mean)[0].ravel()
        e_tan = se3.local(mean, T).ravel()
        return e_split @ H @ e_split, e_tan @ H @ e_tan

    (s1, t1), (s2, t2) = costs(1e-3), costs(5e-4)
    assert 7.0 < abs(s1 - t1) / abs(s2 - t2) < 9.0
    assert abs(s1 - t1) < 1e-3 * t1
    for scale in (1e-3, 1.0):
        T = mean @ se3.exp(scale * v)
        _, J = models.prior_residual('se3', T, mean)
        h = 1e-6
        for c in range(6):
            d = np.zeros((k, 6))
            d[:, c] = h
            num = (models.prior_residual('se3', T @ se3.exp(d), mean)[0]
                   - models.prior_residual('se3', T @ se3.exp(-d), mean)[0]) / (2 * h)
            np.testing.assert_allclose(num, J[:, :, c], atol=1e-6)


def test_the_split_prior_keeps_the_requested_gradient_and_normal_matrix_far_from_its_mean():
    """``tangent_prior`` for a shift ``H^-1 g`` of 100 m and 0.3 rad: the split residual's
    gradient ``B' H' e`` and Gauss-Newton matrix ``B' H' B`` at ``T_lin`` (computed here from
    the residual's own Jacobian, dense and sparse information) are ``g`` and ``H``."""
    rng = np.random.default_rng(8)
    k = 3
    T_lin = se3.exp(rng.normal(scale=[500, 500, 50, 1, 1, 1], size=(k, 6)))
    A = rng.normal(size=(6 * k, 6 * k))
    H = A @ A.T + np.eye(6 * k)
    g = H @ rng.normal(scale=[100, 100, 100, 0.3, 0.3, 0.3], size=(k, 6)).ravel()
    for info_in in (H, sp.csr_matrix(H)):
        mean, info = tangent_prior(T_lin, info_in, g)
        info = info.toarray() if sp.issparse(info) else info
        e, B = models.prior_residual('se3', T_lin, mean)
        Bd = np.zeros((6 * k, 6 * k))
        for a in range(k):
            Bd[6 * a:6 * a + 6, 6 * a:6 * a + 6] = B[a]
        np.testing.assert_allclose(Bd.T @ info @ e.ravel(), g, rtol=1e-8,
                                   atol=1e-8 * np.abs(g).max())
        np.testing.assert_allclose(Bd.T @ info @ Bd, H, rtol=1e-8, atol=1e-8 * np.abs(H).max())


def _distance_to_batch(al, sc, batch) -> tuple[float, float]:
    """Mean squared distance of the second track to the batch estimate (batch sd^2) and the
    median ratio of its position covariance traces to the batch ones."""
    new = np.nonzero(sc.track_ids == 1)[0]
    cov_b = batch.covariance(new)
    T = al.corrected_path().T_world_node[new]
    diff = position_nees(T, cov_b, batch.T_world_node[new]).mean()
    ratio = np.median(np.trace(al.covariances(new)[:, :3, :3], axis1=1, axis2=2)
                      / np.trace(cov_b[:, :3, :3], axis1=1, axis2=2))
    return float(diff), float(ratio)


def test_frozen_at_its_first_estimate_the_window_agrees_with_the_batch(survey, first_estimate):
    """The window on its own run (track 0 frozen at its first estimate): its second track
    within one batch standard deviation of the batch estimate (mean squared, in batch sd^2)
    and covariances within 20 % of the batch ones (measured: 0.08 sd^2, 0.92; with the SE(3)
    tangent prior residual 12 sd^2, 0.67: a strict xfail until then)."""
    sc, _, batch = survey
    diff, ratio = _distance_to_batch(first_estimate, sc, batch)
    assert diff < 1.0 and abs(ratio - 1.0) < 0.2, (diff, ratio)


def test_a_prior_linearised_at_the_batch_solution_gives_the_batch_solution(survey):
    """With track 0 frozen at the batch estimate (the prior linearised there), the window
    reproduces the batch estimate and covariances of the second track: the linearisation point
    of the prior is the whole difference."""
    sc, nm, batch = survey
    diff, ratio = _distance_to_batch(_aligner(sc, nm, batch), sc, batch)
    assert diff < 0.01 and abs(ratio - 1.0) < 0.01, (diff, ratio)


def test_bench_nees_prints_what_it_measured(capsys):
    """``ga-ros bench nees`` on a tiny survey: its JSON line carries the same NEES as a
    direct batch solve of the same seeded noise, and the window reproduces it (3 tracks fit
    in the window: no freeze)."""
    import json

    from ga_ros.cli.main import main

    assert main(['bench', 'nees', '--tracks', '2', '--per-swath', '6', '--noise', '3',
                 '--runs', '1', '--window', '3', '--policies', 'weighted', '--json',
                 '--seed', '5']) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    sc = aerial_scenario(n_tracks=2, positions_per_swath=6)
    nm = perturb(sc.true_motions(), NoiseModel(3.0, sc.depth_m), np.random.default_rng(5))
    b = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z), SolverConfig(tolerance=1e-8))
    ids = sc.node_ids[1:]
    want = position_nees(b.T_world_node[1:], b.covariance(ids), sc.T_world_node[1:]).mean()
    assert row['batch']['nees'] == pytest.approx(want, rel=1e-6)
    assert row['weighted']['nees'] == pytest.approx(want, rel=1e-3)
    assert row['weighted']['diff'] < 1e-3
