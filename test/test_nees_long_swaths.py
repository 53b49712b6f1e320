"""Honest covariances on long swaths (issue #15 item 2): where the window's priors stop being
valid, and a position NEES checked against an independent computation.

At 10 % noise on 400-pose swaths the window's published covariances are overconfident (mean
position NEES 50-200 in ``scripts/bench_nees.py``) while the batch solve of the same data is
honest (NEES ~3). The cause is the linearisation point of the frozen tracks' joint prior: it is
the exact second-order model of the absorbed connections at the estimate the track was frozen
at, and the next track moves the boundary so far (100 m, 3 deg on a 4 km swath) that the model
no longer holds; the window then moves the boundary along a direction the quadratic prior finds
cheap and the real absorbed terms do not. The same survey made small enough for a unit test:
2 double tracks, 200 poses per swath, 20 % noise, window 1 track.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
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
        al._T[:sc.n_nodes] = batch.T_world_node[np.asarray(al._ids)]
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


def test_the_frozen_prior_holds_near_its_linearisation_point_only(survey, first_estimate):
    """The prior of the frozen first track against the true cost of the connections it absorbed
    (its eliminated nodes re-adjusted with the prior nodes held): from the freeze estimate to
    the batch solution both rise alike; to the window's own solution the true cost rises many
    times more than the prior says. This is the documented limit behind the overconfident
    window on long swaths (README, covariance section); a prior re-linearised at the batch
    solution removes it (next test)."""
    sc, nm, batch = survey
    al = first_estimate
    (idx, mean, H), = al._priors
    H = H.toarray() if sp.issparse(H) else H
    ids = np.asarray(al._ids)[idx]
    wn, wT = al._T_weighted
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
        e = se3.log(se3.inverse(mean) @ T_S).ravel()
        return float(e @ H @ e)

    T_lin = al._T[idx]  # frozen nodes are not written back: the freeze estimate
    rise = {k: (true_cost(T) - true_cost(T_lin), prior_cost(T) - prior_cost(T_lin))
            for k, T in (('batch', batch.T_world_node[ids]), ('window', T_window))}
    true_b, prior_b = rise['batch']
    true_w, prior_w = rise['window']
    assert abs(prior_b - true_b) < 0.02 * true_b, rise
    # the window's boundary costs the absorbed connections some 70 (chi-square units) more
    # than the prior says: the window optimises the wrong function there
    assert true_w - prior_w > max(30.0, 10 * abs(true_b - prior_b)), rise


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


@pytest.mark.xfail(strict=True, reason='known limit (README, "Honest covariances on long '
                   'swaths"): the frozen prior stays linearised at the freeze estimate; the '
                   'window ends several batch sd off with covariances ~0.6-0.7 of the batch')
def test_frozen_at_its_first_estimate_the_window_agrees_with_the_batch(survey, first_estimate):
    """What the window should do on its own run (track 0 frozen at its first estimate): its
    second track within one batch standard deviation of the batch estimate (mean squared, in
    batch sd^2) and covariances within 20 % of the batch ones. Strict xfail: it fails (XPASS)
    once the limit is fixed, and then becomes a plain test."""
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
    """``scripts/bench_nees.py`` on a tiny survey: its JSON line carries the same NEES as a
    direct batch solve of the same seeded noise, and the window reproduces it (3 tracks fit
    in the window: no freeze)."""
    import importlib.util
    import json
    import sys
    from pathlib import Path

    script = Path(__file__).resolve().parents[1] / 'scripts' / 'bench_nees.py'
    spec = importlib.util.spec_from_file_location('bench_nees', script)
    mod = importlib.util.module_from_spec(spec)
    sys.modules.setdefault('bench_nees', mod)  # dataclasses look their module up
    spec.loader.exec_module(mod)
    assert mod.main(['--tracks', '2', '--per-swath', '6', '--noise', '3', '--runs', '1',
                     '--window', '3', '--policies', 'weighted', '--json', '--seed', '5']) == 0
    row = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    sc = aerial_scenario(n_tracks=2, positions_per_swath=6)
    nm = perturb(sc.true_motions(), NoiseModel(3.0, sc.depth_m), np.random.default_rng(5))
    b = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z), SolverConfig(tolerance=1e-8))
    ids = sc.node_ids[1:]
    want = position_nees(b.T_world_node[1:], b.covariance(ids), sc.T_world_node[1:]).mean()
    assert row['batch']['nees'] == pytest.approx(want, rel=1e-6)
    assert row['weighted']['nees'] == pytest.approx(want, rel=1e-3)
    assert row['weighted']['diff'] < 1e-3
