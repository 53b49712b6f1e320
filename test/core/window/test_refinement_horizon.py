"""Bounded background refinement (``refine_horizon_tracks``): equal to the whole-survey one
while the survey fits the horizon, exact in the linear limit beyond it (every absorbed
connection in exactly one prior), bounded snapshots, save / restore and replay determinism."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from solver_problems import noisy_aerial_survey

from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import ALIGNER_SOLVER, AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import load_state, save_state
from ga_ros.core.window.refinement import refine_snapshot


def _config(horizon, window=2, executor='inline', band=-1, **solver):
    return AlignerConfig(window_tracks=window, refine_every_tracks=1, refine_executor=executor,
                         refine_relinearize_sigma=0.0,
                         refine_horizon_tracks=horizon, prior_band=band,
                         prior_hubs=0 if band < 0 else 3,
                         solver=replace(ALIGNER_SOLVER, **solver))


def _run(cfg, sc, ms):
    al = TrackWindowAligner(cfg, sc.T_world_node[0])
    ups = al.add_measurements(ms).updates + [al.finish_track()]
    al.close()
    return al, ups


def _batch(al, sc, f2f):
    """The batch solution of every connection the aligner kept (an independent solve)."""
    path = al.corrected_path()
    n = path.node_ids.size
    src, dst, z, _, status = al.connection_arrays()   # node ids are indices here
    keep = status != 2
    net = ConnectionNetwork.from_arrays(sc.node_ids[:n], sc.track_ids[:n], src[keep], dst[keep],
                                        z[keep], al.connection_covariances()[keep])
    return solve(net, f2f[:n], SolverConfig(tolerance=1e-12), fixed=[int(sc.node_ids[0])])


def test_bounded_refinement_equals_the_whole_survey_one_while_the_survey_fits():
    """A horizon at least as long as the survey retires nothing: path, covariances and priors
    are bit for bit those of ``refine_horizon_tracks = 0`` (the whole survey each time)."""
    sc, _, ms = noisy_aerial_survey(5, 6, 5.0, 4)
    runs = [_run(_config(h, band=16), sc, ms)[0] for h in (0, 5, 40)]
    assert all(al.state.retired == 0 and not al.state.past for al in runs)
    assert all(al.handoff.n_refinements >= 2 for al in runs)
    for al in runs[1:]:
        np.testing.assert_array_equal(al.corrected_path().T_world_node,
                                      runs[0].corrected_path().T_world_node)
        np.testing.assert_array_equal(al.covariances(sc.node_ids[1:]),
                                      runs[0].covariances(sc.node_ids[1:]))
        assert len(al.state.priors) == len(runs[0].state.priors)
        for (i, m, h), (i0, m0, h0) in zip(al.state.priors, runs[0].state.priors):
            np.testing.assert_array_equal(i, i0)
            np.testing.assert_array_equal(m, m0)
            np.testing.assert_array_equal(h.toarray() if hasattr(h, 'toarray') else h,
                                          h0.toarray() if hasattr(h0, 'toarray') else h0)


def test_bounded_refinement_is_the_batch_solution_in_the_linear_limit():
    """At tiny noise marginalisation is exact, so a fixed-lag smoother's estimate of the nodes
    it still holds is the batch one: at every update that installs a refinement, after the
    window adjustment and the smoothing, every node not yet retired equals the batch solution
    of all data received (the retired ones stay put), and the published covariances of the
    horizon's frozen nodes are the batch ones. A connection absorbed twice, or lost, when its
    track retires would move both by far more than these tolerances."""
    sc, nm, ms = noisy_aerial_survey(8, 5, 0.01, 3)
    np.testing.assert_array_equal(sc.node_ids, np.arange(sc.node_ids.size))
    al = TrackWindowAligner(_config(3, tolerance=1e-12, max_iterations=30), sc.T_world_node[0])
    f2f = sc.f2f(nm.z)
    sd = 0.0005   # smallest position standard deviation of this survey's batch solution (m)
    checked = []
    for m in ms + [None]:
        ups = al.add_measurement(m) if m is not None else [al.finish_track()]
        for up in ups:
            if up.refined_after_tracks < 0 or not al.state.retired:
                continue
            assert 'converged' in up.refine_reason, up.refine_reason
            batch = _batch(al, sc, f2f)
            path = al.corrected_path()
            f = al.state.track_nodes[al.state.finished_order()[al.state.retired]][0]
            gap = np.abs(path.T_world_node[f:, :3, 3] - batch.T_world_node[f:, :3, 3]).max()
            assert gap < 1e-3 * sd, (up.track_id, gap)
            frozen = np.nonzero(path.frozen)[0]
            frozen = frozen[frozen >= f]
            cov = al.covariances(sc.node_ids[frozen])
            ref = batch.covariance(sc.node_ids[frozen])
            np.testing.assert_allclose(cov, ref, rtol=1e-3, atol=1e-3 * np.abs(ref).max())
            checked.append((up.track_id, al.state.retired))
    assert len(checked) >= 3 and checked[-1][1] >= 3, checked


def test_bounded_snapshots_do_not_grow_with_the_survey():
    """The snapshot handed to the worker holds the horizon only: about ``H + 1`` tracks of
    nodes and their connections, however many tracks were flown; a refinement of it equals a
    batch solve of those nodes with the past prior."""
    sc, _, ms = noisy_aerial_survey(10, 4, 5.0, 6)
    al = TrackWindowAligner(_config(3), sc.T_world_node[0])
    per_track = 2 * 4 + 2
    sizes = []
    for m in ms:
        for up in al.add_measurement(m):
            snap = al.handoff.snapshot()
            sizes.append((up.track_id, snap.node_ids.size, snap.src.size))
            assert snap.node_ids.size <= 5 * per_track, sizes
    al.finish_track()
    al.close()
    assert al.state.retired >= 5 and sizes[-1][1] < sc.node_ids.size / 2, sizes
    snap = al.handoff.snapshot()
    res = refine_snapshot(snap)
    assert res.ok and snap.past and snap.first_node > 0
    assert res.past and res.T_world_node.shape[0] == snap.node_ids.size
    # refine_batch re-solves everything: the next refinement covers the whole survey again
    al.refine_batch()
    assert al.state.retired == 0 and not al.state.past
    assert al.handoff.snapshot().node_ids.size == sc.node_ids.size


def test_save_restore_mid_survey_continues_the_same_path(tmp_path):
    """A state saved after tracks retired (the past prior and its count are in the file, and a
    pending refinement restarts from the same data) continues to the same path."""
    sc, _, ms = noisy_aerial_survey(8, 4, 5.0, 2)
    cfg = _config(3, executor='process')
    cut = next(k for k, m in enumerate(ms) if m.dst_track == 6) + 2
    a = TrackWindowAligner(cfg, sc.T_world_node[0])
    a.add_measurements(ms[:cut])
    assert a.state.retired and a.state.past and a.refinement_state() is not None
    save_state(a, tmp_path / 'state')
    b = load_state(tmp_path / 'state').aligner
    assert b.state.retired == a.state.retired and len(b.state.past) == len(a.state.past)
    for x in (a, b):
        x.add_measurements(ms[cut:])
        x.finish_track()
        x.close()
    assert b.state.retired == a.state.retired
    np.testing.assert_array_equal(b.corrected_path().T_world_node,
                                  a.corrected_path().T_world_node)


def test_bounded_replay_is_identical_whatever_the_executor():
    """The retirement, like the hand-off, depends on track counts only: a background process
    and the inline refinement give bit-identical paths and covariances."""
    sc, _, ms = noisy_aerial_survey(7, 4, 5.0, 9)
    runs = [_run(_config(3, executor=e, band=16), sc, ms)[0] for e in ('process', 'inline')]
    assert runs[0].state.retired == runs[1].state.retired >= 2
    np.testing.assert_array_equal(runs[0].corrected_path().T_world_node,
                                  runs[1].corrected_path().T_world_node)
    np.testing.assert_array_equal(runs[0].covariances(sc.node_ids[1:]),
                                  runs[1].covariances(sc.node_ids[1:]))


def test_a_refinement_stopped_at_max_iterations_is_installed_and_retires():
    """A batch solve that uses up its iterations (tolerances ~0 here) is installed as the
    window's own updates are kept; refusing it stalled the retirement, and the horizon grew
    with the survey (300 tracks of 20 poses: 26 tracks at track 200 instead of 11)."""
    sc, _, ms = noisy_aerial_survey(7, 4, 5.0, 3)
    al, ups = _run(_config(3, tolerance=1e-300, cost_tolerance=0.0), sc, ms)
    reasons = [u.refine_reason for u in ups if u.refined_after_tracks >= 0]
    assert reasons and all(r == 'max_iterations' for r in reasons), reasons
    assert al.state.retired == 7 - 3 - 1 and al.handoff.n_refinements == len(reasons)


def test_horizon_rows_are_every_connection_between_the_horizons_nodes(tmp_path):
    """The horizon's connections (scanned only from the first connection of the horizon's
    first track) are exactly those whose two nodes are at or after its first node, by brute
    force over every connection, for every track start and connection count, also after a
    save / restore (the tables rebuilt from the file)."""
    sc, _, ms = noisy_aerial_survey(6, 6, 5.0, 3)
    al = TrackWindowAligner(AlignerConfig(window_tracks=2, refine_every_tracks=0),
                            sc.T_world_node[0])
    al.add_measurements(ms[:-5])  # the last track still open
    save_state(al, tmp_path / 'state.npz')
    for aligner in (al, load_state(tmp_path / 'state.npz').aligner):
        src, dst = aligner.state.src.a, aligner.state.dst.a
        starts = [int(aligner.state.track_nodes[t][0]) for t in aligner.state.tracks]
        assert len(starts) == 6 and src.size > 100
        for f in starts[1:]:
            for m in (src.size, src.size - 7, src.size // 2):
                want = np.flatnonzero((src[:m] >= f) & (dst[:m] >= f))
                got = aligner.state.horizon_rows(f, m)
                assert got.dtype == np.int64
                np.testing.assert_array_equal(got, want)
