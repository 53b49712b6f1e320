"""Background refinement: batch equality, rebuilt priors, hand-off determinism."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import scipy.linalg as sla
from solver_problems import noisy_aerial_survey

from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior, SolverConfig, normal_matrix_at, solve
from ga_ros.core.window import ALIGNER_SOLVER, AlignerConfig, TrackWindowAligner
from ga_ros.core.window.freeze import prior_nodes, tangent_prior
from ga_ros.core.window.handoff import RefinementHandoff
from ga_ros.core.window.refinement import absorbed_priors, refine_snapshot
from ga_ros.core.window.storage import unpack_sym6
from ga_ros.errors import InputError
from ga_ros.geometry import se3


def _survey(n_tracks=5, per_swath=8, pct=5.0, seed=4):
    return noisy_aerial_survey(n_tracks, per_swath, pct, seed)


def _run(cfg, sc, ms):
    al = TrackWindowAligner(cfg, sc.T_world_node[0])
    ups = al.add_measurements(ms).updates + [al.finish_track()]
    return al, ups


def _refining(policy='weighted', executor='inline', lag=1, **solver):
    return AlignerConfig(window_tracks=2, freeze_policy=policy, refine_every_tracks=1,
                         refine_lag_tracks=lag, refine_executor=executor,
                         refine_relinearize_sigma=0.0,
                         solver=replace(ALIGNER_SOLVER, **solver))


def test_config_refuses_bad_refinement_settings():
    for bad in ({'refine_every_tracks': -1}, {'refine_lag_tracks': 0},
                {'refine_executor': 'gpu'}):
        with pytest.raises(InputError):
            AlignerConfig(**bad)


def test_refinement_equals_a_batch_solve_of_the_snapshot():
    sc, nm, ms = _survey()
    al, _ = _run(AlignerConfig(window_tracks=2, refine_relinearize_sigma=0.0), sc, ms)
    snap = al.handoff.snapshot()
    res = refine_snapshot(snap)
    assert res.ok and snap.frozen.any()
    ref = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z), SolverConfig(tolerance=1e-10))
    np.testing.assert_allclose(res.T_world_node, ref.T_world_node, atol=1e-6)
    frozen = np.nonzero(snap.frozen)[0]
    cov_ref = ref.covariance(sc.node_ids[frozen])
    np.testing.assert_allclose(res.frozen_cov, cov_ref, rtol=1e-4,
                               atol=1e-8 * np.abs(cov_ref).max())


def test_refinement_covariances_by_selected_inversion_equal_the_solver_s_own(monkeypatch):
    """The frozen nodes' covariances come from selected inversion on the batch factor whatever
    the horizon's size; they equal those of ``SolveResult.covariance`` (here its banded
    selected inversion, below 12,000 unknowns) of the same solve to rounding."""
    import ga_ros.core.window.freeze as freeze_mod
    import ga_ros.core.window.refinement as refinement_mod

    sc, nm, ms = _survey()
    al, _ = _run(AlignerConfig(window_tracks=2, refine_relinearize_sigma=0.0), sc, ms)
    snap = al.handoff.snapshot()
    assert snap.frozen.sum() > freeze_mod.TRAILING_MIN_NODES  # not the few-nodes path
    used = []
    selected = freeze_mod._selected_marginals
    monkeypatch.setattr(freeze_mod, '_selected_marginals',
                        lambda sysm, cols: used.append(cols.size) or selected(sysm, cols))
    res = refine_snapshot(snap)
    assert res.ok and used == [int(snap.frozen[1:].sum())]  # every frozen node but the datum
    monkeypatch.setattr(refinement_mod, 'marginal_covariances',
                        lambda r, ids, banded=False: r.covariance(ids))
    ref = refine_snapshot(snap)
    np.testing.assert_array_equal(res.T_world_node, ref.T_world_node)
    scale = np.abs(ref.frozen_cov).max()
    np.testing.assert_allclose(res.frozen_cov, ref.frozen_cov, rtol=1e-9, atol=1e-12 * scale)


def test_tangent_prior_has_the_requested_gradient_and_normal_matrix():
    """The solver's own linearisation of the prior (``models.prior_residual``: position and
    rotation apart) at ``T_lin`` must give back ``u = g`` and ``N = H``, also for shifts of
    0.2 rad, where the plain shift mean ``T_lin exp(-H^-1 g)`` is off by ~10 %."""
    rng = np.random.default_rng(5)
    k = 3
    T_lin = se3.exp(rng.normal(0.0, 1.0, (k, 6)))
    A = rng.normal(size=(6 * k, 6 * k))
    H = A @ A.T + 6 * k * np.eye(6 * k)
    g = H @ rng.normal(0.0, 0.2, 6 * k)
    ids = np.arange(1, k + 1)
    net = ConnectionNetwork()
    for i in ids:
        net.add_node(int(i))
    mean, info = tangent_prior(T_lin, H, g)
    N, _, u = normal_matrix_at(net, T_lin, 'se3', (), [GaussianPrior(ids, mean, info)])
    np.testing.assert_allclose(u, g, rtol=1e-7, atol=1e-7 * np.abs(g).max())
    np.testing.assert_allclose(N.toarray(), H, rtol=1e-7, atol=1e-7 * np.abs(H).max())
    plain = T_lin @ se3.exp(-sla.solve(H, g).reshape(k, 6))
    _, _, u_plain = normal_matrix_at(net, T_lin, 'se3', (), [GaussianPrior(ids, plain, H)])
    assert np.abs(u_plain - g).max() > 1e-2 * np.abs(g).max()


@pytest.mark.parametrize('policy', ['weighted', 'marginal'])
def test_rebuilt_priors_equal_one_dense_schur_complement(policy):
    """The track-by-track elimination of :func:`absorbed_priors` against one dense Schur
    complement of every absorbed connection onto the prior nodes."""
    sc, nm, ms = _survey(n_tracks=5, per_swath=6)
    al, _ = _run(AlignerConfig(window_tracks=2, freeze_policy=policy), sc, ms)
    snap = al.handoff.snapshot()
    T = snap.T_world_node
    priors = absorbed_priors(snap, T)
    assert len(priors) == 1
    keep = np.nonzero(prior_nodes(snap.frozen, snap.src, snap.dst, snap.status,
                                  policy))[0]
    np.testing.assert_array_equal(np.sort(priors[0].nodes), keep)
    absorbed = np.nonzero(snap.status == 1)[0]
    nodes = np.unique(np.concatenate([[0], snap.src[absorbed], snap.dst[absorbed]]))
    local = np.full(snap.node_ids.size, -1)
    local[nodes] = np.arange(nodes.size)
    net = ConnectionNetwork.from_arrays(snap.node_ids[nodes], snap.track_ids[nodes],
                                        local[snap.src[absorbed]], local[snap.dst[absorbed]],
                                        snap.z[absorbed], unpack_sym6(snap.cov21[absorbed]))
    N, free_ids, u = normal_matrix_at(net, T[nodes], 'se3', [int(snap.node_ids[0])])
    N = N.toarray()
    pos = {int(i): k for k, i in enumerate(free_ids)}
    S = [pos[int(snap.node_ids[i])] for i in priors[0].nodes]
    L = [k for k in range(len(free_ids)) if k not in set(S)]
    cS = (6 * np.array(S)[:, None] + np.arange(6)).ravel()
    cL = (6 * np.array(L)[:, None] + np.arange(6)).ravel()
    NLS = N[np.ix_(cL, cS)]
    H = N[np.ix_(cS, cS)] - NLS.T @ np.linalg.solve(N[np.ix_(cL, cL)], NLS)
    g = u[cS] - NLS.T @ np.linalg.solve(N[np.ix_(cL, cL)], u[cL])
    mean, info = tangent_prior(T[priors[0].nodes], 0.5 * (H + H.T), g)
    np.testing.assert_allclose(priors[0].information, info, rtol=1e-6,
                               atol=1e-9 * np.abs(info).max())
    np.testing.assert_allclose(priors[0].T_world_node, mean, atol=1e-8)


def test_after_refine_batch_the_next_window_adjustment_stays_at_the_batch_optimum():
    """``refine_batch`` rebuilds the priors at the refined estimate, so the window problem it
    leaves is at its optimum there: adjusting it again moves nothing. With the priors kept at
    their old means (the bug), the same adjustment moved the estimate back (0.5 mm here)."""
    sc, nm, ms = _survey(n_tracks=5, per_swath=8, pct=5.0)
    al, _ = _run(AlignerConfig(window_tracks=2, refine_relinearize_sigma=0.0,
                               solver=replace(ALIGNER_SOLVER, tolerance=1e-10)), sc, ms)
    old_priors = list(al.state.priors)
    al.refine_batch()
    window = [t for t in al.state.tracks if t in al.state.finished][-2:]
    moves = []
    for priors in (al.state.priors, old_priors):
        al.state.priors = priors
        net, nodes, _, _, fixed, gp = al.updater.window_problem(window)
        res = solve(net, al.state.T[nodes], SolverConfig(tolerance=1e-10), fixed=fixed, priors=gp)
        moves.append(np.abs(res.T_world_node[:, :3, 3] - al.state.T[nodes][:, :3, 3]).max())
    assert moves[0] < 1e-5, moves
    assert moves[1] > 100 * moves[0] and moves[1] > 1e-4, moves


@pytest.mark.parametrize('lag', [1, 2])
@pytest.mark.parametrize('policy', ['weighted', 'marginal'])
def test_refining_window_is_exact_in_the_linear_limit(policy, lag):
    """At tiny noise every installed refinement (the frozen poses, covariances and priors it
    hands back for the state after the hand-off's freezes) keeps the window exact, and the
    smoothing carries the window's correction back: at every update that installs one, every
    node, frozen ones included, equals the batch solution of the data received so far."""
    sc, nm, ms = _survey(n_tracks=6, per_swath=6, pct=0.01)
    cfg = replace(_refining(policy, lag=lag, tolerance=1e-12, max_iterations=30),
                  window_tracks=lag + 1)
    al = TrackWindowAligner(cfg, sc.T_world_node[0])
    sd = 0.0005  # smallest position standard deviation of this survey's batch solution (m)
    np.testing.assert_array_equal(sc.node_ids, np.arange(sc.node_ids.size))
    checked = []
    for m in ms + [None]:
        ups = al.add_measurement(m) if m is not None else [al.finish_track()]
        for up in ups:
            if up.refined_after_tracks < 0:
                continue
            assert 'converged' in up.refine_reason, up.refine_reason
            assert up.track_id == up.refined_after_tracks + lag - 1
            path = al.corrected_path()
            n = path.node_ids.size
            src, dst, z, _, _ = al.connection_arrays()  # node ids are indices here
            net = ConnectionNetwork.from_arrays(sc.node_ids[:n], sc.track_ids[:n], src, dst, z,
                                                al.connection_covariances())
            batch = solve(net, sc.f2f(nm.z)[:n], SolverConfig(tolerance=1e-12),
                          fixed=[int(sc.node_ids[0])])
            gap = np.abs(path.T_world_node[:, :3, 3] - batch.T_world_node[:, :3, 3]).max()
            assert gap < 1e-3 * sd, (up.track_id, gap)
            frozen = sc.node_ids[:n][path.frozen & (sc.node_ids[:n] != 0)]
            cov_ref = solve(net, batch.T_world_node, SolverConfig(tolerance=1e-12),
                            fixed=[0]).covariance(frozen)
            assert np.all(np.diagonal(al.covariances(frozen), axis1=1, axis2=2)
                          >= np.diagonal(cov_ref, axis1=1, axis2=2) * (1 - 1e-3))
            checked.append(up.track_id)
    assert checked, 'no refinement was installed'


@pytest.mark.parametrize('policy', ['weighted', 'marginal'])
@pytest.mark.parametrize('installs', [True, False])
def test_a_freeze_leaves_its_prior_to_the_refinement_installed_with_it(monkeypatch, installs,
                                                                      policy):
    """A freeze at an update that installs a refinement does not compute its joint prior (the
    refinement replaces every prior); if the hand-off does not install, the prior is computed
    then, so the state is bit for bit that of freezes that always compute it."""
    import ga_ros.core.window.aligner as aligner_mod
    import ga_ros.core.window.freeze as freeze_mod

    sc, nm, ms = _survey(n_tracks=6, per_swath=8)
    if not installs:
        def refuse(self, snap, res):
            raise InputError('the frozen nodes or absorbed connections changed (test)')
        monkeypatch.setattr(RefinementHandoff, 'install', refuse)
    computed, late = [], []
    new_prior = freeze_mod.new_prior
    monkeypatch.setattr(freeze_mod, 'new_prior',
                        lambda *a: computed.append(1) or new_prior(*a))
    deferred_priors = aligner_mod.TrackWindowAligner._deferred_priors

    def count_late(self, plans, installed):
        before = len(computed)
        deferred_priors(self, plans, installed)
        late.append(len(computed) - before)

    monkeypatch.setattr(aligner_mod.TrackWindowAligner, '_deferred_priors', count_late)
    states = []
    for always in (False, True):
        if always:  # freezes that never leave anything to the refinement
            monkeypatch.setattr(aligner_mod.TrackWindowAligner, '_refinement_due',
                                lambda self, n: False)
        computed.clear()
        late.clear()
        al, ups = _run(_refining(policy), sc, ms)
        al.close()  # the freeze ahead after the last update (never installed) done
        refined = [u for u in ups if u.refined_after_tracks >= 0]
        assert refined and all(u.refine_reason.startswith('not installed') != installs
                               for u in refined), [u.refine_reason for u in refined]
        st = al.state
        n = len(st.ids)
        states.append((len(computed) - sum(late), st.T[:n].copy(), st.cov[:n].copy(),
                       st.status.a.copy(),
                       [(p[0].copy(), p[1].copy(), p[2].toarray() if hasattr(p[2], 'toarray')
                         else np.array(p[2])) for p in st.priors], sum(late)))
    (n_deferred, *deferred, n_late), (n_always, *always_, n_late_always) = states
    assert n_late_always == 0
    if installs:  # the installing updates' freezes computed none, not even later
        assert n_late == 0 and n_deferred < n_always
    else:  # computed when the hand-off did not install
        assert n_late > 0
    for a, b in zip(deferred[:3], always_[:3]):
        np.testing.assert_array_equal(a, b)
    assert len(deferred[3]) == len(always_[3])
    for pa, pb in zip(deferred[3], always_[3]):
        for x, y in zip(pa, pb):
            np.testing.assert_array_equal(x, y)


def test_refinement_closes_most_of_the_gap_to_batch():
    """5 % noise, window of 2: the frozen tracks of the refining window are nearer to the batch
    solution than those of the plain window (they are the batch estimate one track behind)."""
    sc, nm, ms = _survey(n_tracks=6, per_swath=10, pct=5.0)
    batch = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z), SolverConfig(tolerance=1e-10))
    gaps = []
    for cfg in (AlignerConfig(window_tracks=2, refine_every_tracks=0), _refining()):
        al, _ = _run(cfg, sc, ms)
        path = al.corrected_path()
        d = path.T_world_node[:, :3, 3] - batch.T_world_node[:, :3, 3]
        gaps.append(np.sqrt(np.mean(np.sum(d[path.frozen] ** 2, axis=1))))
    assert gaps[1] < 0.5 * gaps[0], gaps


def test_replay_gives_the_identical_path_whatever_the_executor():
    """The hand-off is at a fixed track, so two runs with the background process, and a run
    with the inline refinement, give bit-identical paths and covariances. A worker thread
    shares the process's BLAS thread setting (the worker narrows it while it solves), so its
    run may differ in the last bits only."""
    sc, _, ms = _survey(n_tracks=4, per_swath=6)
    paths, covs = [], []
    for executor in ('process', 'process', 'inline', 'thread'):
        al, ups = _run(_refining(executor=executor), sc, ms)
        al.close()
        assert any(u.refined_after_tracks >= 0 for u in ups)
        paths.append(al.corrected_path().T_world_node)
        covs.append(al.covariances(sc.node_ids[1:]))
    for p, c in zip(paths[1:3], covs[1:3]):
        np.testing.assert_array_equal(p, paths[0])
        np.testing.assert_array_equal(c, covs[0])
    np.testing.assert_allclose(paths[3], paths[0], rtol=0, atol=1e-9)
    np.testing.assert_allclose(covs[3], covs[0], rtol=1e-9, atol=0)


def test_pattern_eliminations_equal_one_dense_conditional():
    """:class:`~ga_ros.core.window.elimination.Marginal` eliminates in parts (interior nodes first,
    each gain over the coupled nodes only): its Schur complement and its back substitution
    (:func:`~ga_ros.core.window.elimination.smoothed`) against the dense ones of a chain of
    nodes with
    a dense block over its first ones (a carried prior), written out here."""
    from ga_ros.core.window.elimination import Marginal as _Marginal
    from ga_ros.core.window.elimination import smoothed

    rng = np.random.default_rng(7)
    k = 12
    H = np.zeros((6 * k, 6 * k))
    for a, b in [(i, i + 1) for i in range(k - 1)] + [(0, 5), (2, 9)]:
        J = np.hstack([rng.normal(size=(6, 6)), rng.normal(size=(6, 6))])
        at = np.r_[6 * a:6 * a + 6, 6 * b:6 * b + 6]
        H[np.ix_(at, at)] += J.T @ J
    A = rng.normal(size=(18, 18))
    H[:18, :18] += A @ A.T  # dense over nodes 0-2
    H += 1e-3 * np.eye(6 * k)
    g = rng.normal(size=6 * k)
    work = _Marginal()
    order = rng.permutation(k)  # block positions need not follow node indices
    perm = (6 * order[:, None] + np.arange(6)).ravel()
    import scipy.sparse as sp

    work.add(order, sp.csc_matrix(H[np.ix_(perm, perm)]), g[perm])
    gone = [0, 1, 2, 3, 4, 6, 7]  # 1 and 3 coupled to no kept node: eliminated first
    steps = work.eliminate(gone)
    assert len(steps) == 2
    np.testing.assert_array_equal(np.sort(steps[0].eliminated), [1, 3])
    keep = [i for i in range(k) if i not in gone]
    cS = (6 * np.array(keep)[:, None] + np.arange(6)).ravel()
    cL = (6 * np.array(gone)[:, None] + np.arange(6)).ravel()
    HLS = H[np.ix_(cL, cS)]
    Hs = H[np.ix_(cS, cS)] - HLS.T @ np.linalg.solve(H[np.ix_(cL, cL)], HLS)
    gs = g[cS] - HLS.T @ np.linalg.solve(H[np.ix_(cL, cL)], g[cL])
    at = (6 * np.array([work.cols[i] for i in keep])[:, None] + np.arange(6)).ravel()
    np.testing.assert_allclose(work.H[np.ix_(at, at)], Hs, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(work.g[at], gs, rtol=1e-9, atol=1e-9)
    dS = 1e-2 * rng.normal(size=(len(keep), 6))
    nodes, d = smoothed(steps, np.array(keep), dS)
    dL = -np.linalg.solve(H[np.ix_(cL, cL)], g[cL] + HLS @ dS.ravel())
    np.testing.assert_array_equal(nodes, np.arange(k))
    np.testing.assert_allclose(d[gone].ravel(), dL, rtol=1e-5, atol=1e-6 * np.abs(dL).max())
    np.testing.assert_array_equal(d[keep], dS)


def test_a_worker_lost_before_smoothing_leaves_the_refined_poses_unsmoothed(monkeypatch):
    """The process worker keeps the smoothing steps; if it dies between the hand-off and the
    smoothing, the update still succeeds and says so (the refined poses stand), and the next
    refinement runs in a new worker (before, a dead worker failed every later update)."""
    import os
    import signal

    sc, _, ms = _survey(n_tracks=4, per_swath=6)
    installed = []
    install = RefinementHandoff.install

    def install_then_kill(self, snap, res):
        install(self, snap, res)
        assert res.smoothing_kept and res.smoothing == ()
        if not installed:
            for pid in list(self.refiner._pool._processes):
                os.kill(pid, signal.SIGKILL)
        installed.append(res.after_tracks)

    monkeypatch.setattr(RefinementHandoff, 'install', install_then_kill)
    al, ups = _run(_refining(executor='process'), sc, ms)
    al.close()
    hit = [u for u in ups if u.refined_after_tracks >= 0]
    assert installed and hit, [(u.reason, u.refine_reason) for u in ups]
    assert not hit[0].reason.startswith('failed')
    assert 'not smoothed' in hit[0].refine_reason, hit[0].refine_reason
    # the next refinement runs in a new worker process, installed and smoothed
    assert all(not u.reason.startswith('failed') for u in ups)
    assert len(hit) >= 2 and 'not smoothed' not in hit[1].refine_reason


UNGUARDED_SCRIPT = """
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb
import numpy as np

print('script body ran', flush=True)
sc = aerial_scenario(n_tracks=4, positions_per_swath=6)
nm = perturb(sc.true_motions(), NoiseModel(5.0, sc.depth_m), np.random.default_rng(4))
al = TrackWindowAligner(AlignerConfig(window_tracks=2, refine_every_tracks=1,
                                      refine_executor='process', refine_relinearize_sigma=0.0),
                        sc.T_world_node[0])
ups = al.add_measurements(sc.measurements(nm.z, nm.cov)).updates + [al.finish_track()]
print('installed', sum(u.refined_after_tracks >= 0 and not u.refine_reason.startswith(
      ('failed', 'not installed')) and 'not smoothed' not in u.refine_reason for u in ups),
      flush=True)
al.close()
"""


def test_the_worker_process_does_not_run_an_unguarded_script_again(tmp_path):
    """A script without an ``if __name__ == '__main__':`` guard that runs the aligner with the
    process worker: the spawned worker does not import the script again (its output would be
    duplicated, and the worker would start a second survey), and the refinements install."""
    import subprocess
    import sys

    script = tmp_path / 'survey.py'
    script.write_text(UNGUARDED_SCRIPT)
    out = subprocess.run([sys.executable, str(script)], capture_output=True, text=True,
                         timeout=120, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    lines = out.stdout.splitlines()
    assert lines.count('script body ran') == 1, out.stdout
    assert lines[-1].startswith('installed ') and int(lines[-1].split()[1]) >= 1, out.stdout


@pytest.mark.parametrize('band', [-1, 2])
def test_sparse_elimination_of_long_tracks_equals_the_dense_one(monkeypatch, band):
    """Long tracks (:data:`~ga_ros.core.window.elimination.SPARSE_FROM_TRACK_NODES`) take one
    sparse
    elimination: its priors (dense, or banded with hubs) and its smoothing against the
    track-by-track dense elimination of the same snapshot (a short survey, the threshold
    lowered), and so does the retirement's past prior."""
    import ga_ros.core.window.elimination as refinement

    sc, nm, ms = _survey(n_tracks=6, per_swath=6)
    al, _ = _run(AlignerConfig(window_tracks=2, refine_every_tracks=0), sc, ms)
    snap = replace(al.handoff.snapshot(), prior_band=band, prior_hubs=1 if band >= 0 else 0)
    T = snap.T_world_node
    out = {}
    for name, limit in (('dense', 10**9), ('sparse', 0)):
        monkeypatch.setattr(refinement, 'SPARSE_FROM_TRACK_NODES', limit)
        priors, steps = refinement.eliminate_absorbed(snap, T)
        retired = refinement.retire_tracks(snap, T, 2)
        out[name] = priors, steps, retired
    assert isinstance(out['sparse'][1][0], refinement.SparseSmoothing)
    for a, b in [(out['dense'][0], out['sparse'][0]), (out['dense'][2], out['sparse'][2])]:
        assert len(a) == len(b) == 1
        np.testing.assert_array_equal(a[0].nodes, b[0].nodes)
        Ia, Ib = (np.asarray(p.information.todense() if hasattr(p.information, 'todense')
                             else p.information) for p in (a[0], b[0]))
        np.testing.assert_allclose(Ib, Ia, rtol=1e-6, atol=1e-9 * np.abs(Ia).max())
        np.testing.assert_allclose(b[0].T_world_node, a[0].T_world_node, atol=1e-9)
    S = out['dense'][0][0].nodes
    dS = 1e-3 * np.random.default_rng(3).normal(size=(S.size, 6))
    nd, d_dense = refinement.smoothed(out['dense'][1], S, dS)
    ns, d_sparse = refinement.smoothed(out['sparse'][1], S, dS)
    np.testing.assert_array_equal(nd, ns)
    np.testing.assert_allclose(d_sparse, d_dense, rtol=1e-5, atol=1e-6 * np.abs(d_dense).max())


def test_the_refinements_compiled_solve_equals_the_numpy_one_within_the_solver_tolerance(
        monkeypatch):
    """The refinement's batch solve linearises with the compiled kernels from its first
    iteration; the NumPy linearisation (without numba) rounds differently, so the two stop at
    slightly different points: apart by far less than the solver's tolerance (the largest
    correction it leaves), and so are the rebuilt priors' means."""
    from ga_ros.core import kernels

    if not kernels.AVAILABLE:
        pytest.skip('numba not installed: the refinement solves with NumPy only')
    sc, nm, ms = _survey()
    al, _ = _run(AlignerConfig(window_tracks=2, refine_relinearize_sigma=0.0), sc, ms)
    snap = al.handoff.snapshot()
    compiled = refine_snapshot(snap)
    monkeypatch.setattr(kernels, 'AVAILABLE', False)
    plain = refine_snapshot(snap)
    assert compiled.ok and plain.ok
    tol = snap.solver.tolerance
    gap = np.abs(se3.local(plain.T_world_node, compiled.T_world_node)).max()
    assert gap < 0.1 * tol
    for a, b in zip(compiled.priors, plain.priors):
        np.testing.assert_array_equal(a.nodes, b.nodes)
        assert np.abs(se3.local(b.T_world_node, a.T_world_node)).max() < 0.1 * tol


def test_block_components_are_those_of_the_block_graph():
    """:func:`~ga_ros.core.window.elimination.block_components` (``N``'s own index arrays,
    duplicates unsorted) labels the blocks as connected components of the graph of nonzero
    blocks built entry by entry: four groups of blocks, one of them two blocks linked by a
    single nonzero entry."""
    import scipy.sparse as sp
    from scipy.sparse.csgraph import connected_components

    from ga_ros.core.window.elimination import block_components

    rng = np.random.default_rng(5)
    d, k = 3, 12
    M = np.zeros((d * k, d * k))
    for a, b in [(0, 4), (4, 7), (1, 2), (2, 9), (3, 5), (5, 6), (6, 10)]:
        M[d * a:d * a + d, d * b:d * b + d] = rng.normal(size=(d, d))
    M[d * 8 + 2, d * 11] = 1.0  # one entry links blocks 8 and 11
    M = M + M.T
    M[np.diag_indices(d * k)] += 10.0
    N = sp.csr_matrix(M)
    coo = N.tocoo()
    graph = sp.csr_matrix((np.ones(coo.nnz), (coo.row // d, coo.col // d)), shape=(k, k))
    want = connected_components(graph, directed=False)[1]
    got = block_components(N, d)
    np.testing.assert_array_equal(got, want)
    assert np.unique(got).size == 4  # {0,4,7} {1,2,9} {3,5,6,10} {8,11}
