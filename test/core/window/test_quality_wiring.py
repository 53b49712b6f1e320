"""Quality control wired into the results: SolveResult, window updates, the w-test gate, the
replay's summary.json, the markers' colours, the node's diagnostics and ``ga-ros solve``.

The window's figures are checked against the dense reference of test_quality (full ``A``,
``B``, ``S``, ``N^-1`` with numpy) on a window that holds the whole survey, and against
:func:`quality_control` on the same window problem when frozen tracks enter as priors.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from test_quality import correlated_problem, dense_reference

from ga_ros import domains
from ga_ros.core.measurement import Measurement
from ga_ros.core.quality import (
    QualityConfig,
    checked_solve,
    quality_control,
    summarise,
)
from ga_ros.core.solver import SolverConfig, initial_guess_f2f, solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.replay.samples import aerial_sample


@pytest.fixture(scope='module')
def sample() -> object:
    return aerial_sample(n_tracks=3, positions_per_swath=8, noise_pct=5.0, seed=3)


def cross_track(ms: list[Measurement]) -> list[int]:
    return [i for i, m in enumerate(ms) if m.src_track != m.dst_track]


def corrupt(ms: list[Measurement], k: int, metres: float = 8.0) -> list[Measurement]:
    """The measurements with the ``k``-th cross-track connection moved by ``metres`` along x."""
    cross = cross_track(ms)
    i = cross[k]
    out = list(ms)
    z = ms[i].z.copy()
    T = se3.from_translation_rotvec(z[None, :3], z[None, 3:])[0]
    T[:3, 3] += T[:3, :3] @ np.array([metres, 0.0, 0.0])
    out[i] = replace(ms[i], z=se3.to_translation_rotvec(T[None])[0])
    return out


def run(ms: list[Measurement], cfg: AlignerConfig, T_first: np.ndarray) -> tuple:
    al = TrackWindowAligner(cfg, T_world_first=T_first)
    ups = []
    for m in ms:
        ups += al.add_measurement(m)
    ups.append(al.finish_track())
    return al, [u for u in ups if u is not None]


def test_summary_of_a_report_by_hand(rng):
    net, _ = correlated_problem(rng, 'se3')
    res = checked_solve(net, initial_guess_f2f(net), SolverConfig(model='se3'))
    rep = res.quality
    again = quality_control(net, res)
    np.testing.assert_allclose(rep.w, again.w)
    s = summarise(rep, net)
    w = np.abs(rep.w).max(axis=1)
    k = int(np.argmax(w))
    c = net.arrays()
    assert s.w_max == pytest.approx(w[k])
    assert (s.w_max_src_id, s.w_max_dst_id) == (int(net.node_ids[c.src[k]]),
                                                int(net.node_ids[c.dst[k]]))
    assert s.n_w_rejected == int((w > rep.w_critical).sum())
    assert s.redundancy_number_min == pytest.approx(rep.redundancy_numbers.min())
    assert s.mdb_median_m == pytest.approx(np.median(rep.mdb[:, :3]))
    assert s.sigma0_sq == pytest.approx(res.sigma0_sq)
    # a subset: the per-connection figures over it only, the global test unchanged
    sub = np.zeros(len(c), dtype=bool)
    sub[::3] = True
    s3 = summarise(rep, net, sub)
    assert s3.n_tested == sub.sum() and s3.w_max == pytest.approx(w[sub].max())
    assert s3.sigma0_sq == s.sigma0_sq
    assert json.loads(json.dumps(s.as_dict()))['n_tested'] == len(c)
    with pytest.raises(InputError):
        summarise(rep, net, sub[:-1])


def test_update_quality_equals_the_dense_computation(sample):
    """Window of all tracks (no frozen nodes): the update's QC summary equals the figures of a
    dense computation of the same adjustment (the whole survey, first node fixed)."""
    ms = sample.measurements
    T0 = sample.ground_truth.T_world_node[0]
    cfg = AlignerConfig(window_tracks=10, quality=True, quality_alpha0=1e-3,
                        outlier_chi2_prob=0.0)
    al, ups = run(ms, cfg, T0)
    q = ups[-1].quality
    assert q is not None and q.n_tested == ups[-1].n_window_connections
    # independent: the survey as one network, solved in batch, QC by dense matrices
    from ga_ros.core.network import ConnectionNetwork
    net = ConnectionNetwork()
    cp = al.corrected_path()
    for i, t in zip(cp.node_ids, cp.track_ids):
        net.add_node(int(i), int(t))
    net.add_connections([m.src_id for m in ms], [m.dst_id for m in ms],
                        np.array([m.z for m in ms]), np.array([m.cov for m in ms]))
    res = solve(net, cp.T_world_node, SolverConfig(tolerance=1e-10), fixed=[int(cp.node_ids[0])])
    ref = dense_reference(net, res, res.free_node_ids, QualityConfig(alpha0=1e-3).lambda0)
    w = np.abs(ref['w']).max(axis=1)
    k = int(np.argmax(w))
    c = net.arrays()
    assert q.sigma0_sq == pytest.approx(ref['cost'] / ref['redundancy'], rel=1e-4)
    assert q.redundancy == ref['redundancy']
    assert q.w_max == pytest.approx(w[k], rel=1e-3)
    assert (q.w_max_src_id, q.w_max_dst_id) == (int(net.node_ids[c.src[k]]),
                                                int(net.node_ids[c.dst[k]]))
    assert q.n_w_rejected == int((w > 3.2905).sum())
    rn = np.trace(ref['R_blocks'], axis1=1, axis2=2)
    assert q.redundancy_number_min == pytest.approx(rn.min(), abs=1e-6)
    assert q.mdb_median_m == pytest.approx(np.median(ref['mdb'][:, :3]), rel=1e-4)
    # the per-connection |w| kept for the markers, in connection order
    src, dst, *_ = al.connection_arrays()
    w_al = al.connection_w()
    pair = {(int(a), int(b)): x for a, b, x in zip(src, dst, w_al)}
    np.testing.assert_allclose([pair[(int(net.node_ids[a]), int(net.node_ids[b]))]
                                for a, b in zip(c.src, c.dst)], w, rtol=1e-3, atol=1e-6)


def test_update_quality_with_frozen_tracks_equals_quality_control(sample):
    """Window of 1 track (frozen neighbours enter as weighted parameters): the update's QC is
    quality_control of that window problem, priors included, at the update's own result (its
    covariances come from its last factorisation, ``solve(factor_at_solution=False)``)."""
    cfg = AlignerConfig(window_tracks=1, quality=True, outlier_chi2_prob=0.0)
    al, ups = run(sample.measurements, cfg, sample.ground_truth.T_world_node[0])
    q = ups[-1].quality
    net, nodes, _, conns, fixed, priors = al.updater.window_problem(al.stats.tracks_in_window)
    assert priors, 'the window must hold a prior for this test'
    res = al.last_adjustment
    assert res.n_unknowns == ups[-1].n_unknowns
    rep = quality_control(net, res, priors, cfg.quality_config())
    ref = summarise(rep, net)
    for name in ('global_passed', 'redundancy', 'n_w_rejected', 'w_max_src_id', 'w_max_dst_id'):
        assert getattr(q, name) == getattr(ref, name)
    for name in ('sigma0_sq', 'w_max', 'redundancy_number_min', 'mdb_median_m'):
        assert getattr(q, name) == pytest.approx(getattr(ref, name), rel=1e-4)
    np.testing.assert_allclose(rep.redundancy_numbers.sum() + rep.prior_redundancy,
                               rep.redundancy, atol=1e-6)


@pytest.mark.parametrize('gate', ['chi2', 'w-test'])
def test_gate_excludes_a_wrong_connection(sample, gate):
    ms = corrupt(sample.measurements, 5)
    bad = ms[cross_track(ms)[5]]
    cfg = AlignerConfig(window_tracks=2, gate=gate, quality=True)
    al, ups = run(ms, cfg, sample.ground_truth.T_world_node[0])
    src, dst, _, cross, status = al.connection_arrays()
    excluded = {(int(a), int(b)) for a, b, s in zip(src, dst, status) if s == 2}
    assert excluded == {(bad.src_id, bad.dst_id)}
    for u in ups:  # what is left after the gate looks like the clean survey (max |w| ~ 4)
        assert u.quality.w_max < 1.5 * u.quality.w_critical
        assert (u.quality.w_max_src_id, u.quality.w_max_dst_id) != (bad.src_id, bad.dst_id)


def test_wrong_connection_shows_in_replay_summary_and_markers(tmp_path: Path, sample):
    """Gate off, QC on: the wrong connection is the worst w of summary.json's quality block and
    its marker line is red; the other lines are not."""
    from ga_ros.io.bag import BagReader
    from ga_ros.replay.config import ReplayConfig
    from ga_ros.replay.pipeline import replay
    from ga_ros.replay.samples import write_measurement_bag

    ms = corrupt(sample.measurements, 5)
    bad = ms[cross_track(ms)[5]]
    bag = write_measurement_bag(tmp_path / 'in', ms, sample.ground_truth)
    cfg = AlignerConfig(window_tracks=5, quality=True, outlier_chi2_prob=0.0)
    r = replay(bag, tmp_path / 'out', ReplayConfig(aligner=cfg, plot=False))
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    block = summary['quality']
    assert len(block['per_track']) == len(r.updates) == 3
    final = block['final']
    assert (final['w_max_src_id'], final['w_max_dst_id']) == (bad.src_id, bad.dst_id)
    assert final['w_max'] > 1.5 * final['w_critical'] and final['n_w_rejected'] >= 1
    # the markers of the end: the line of the wrong connection red, most others not
    with BagReader(r.files['bag']) as reader:
        arr = [m.msg for m in reader.messages(topics=['/ga/network_markers'])][-1]
    lines = [m for m in arr.markers if m.type == 5][0]  # LINE_LIST
    pts = np.array([[p.x, p.y, p.z] for p in lines.points]).reshape(-1, 2, 3)
    rgba = np.array([[c.r, c.g, c.b, c.a] for c in lines.colors])[::2]
    traj = r.corrected
    pos = {int(i): traj.T_world_node[k, :3, 3] for k, i in enumerate(traj.node_ids)}
    k = int(np.argmin(np.linalg.norm(pts[:, 0] - pos[bad.src_id], axis=1)
                      + np.linalg.norm(pts[:, 1] - pos[bad.dst_id], axis=1)))
    assert rgba[k, 0] == 1.0 and rgba[k, 1] == 0.0  # red: |w| beyond the scale
    assert (rgba[:, 1] > 0).mean() > 0.9            # the others green to yellow


def test_connection_colours_and_diagnostic_values():
    conv = pytest.importorskip('ga_ros.ros.conversions')
    rgba = conv.connection_rgba(np.array([0.0, 9.0, 1.0]), np.array([0, 0, 2]), 3.0,
                                w=np.array([0.0, -4.0, np.nan]))
    np.testing.assert_allclose(rgba[0], [0, 1, 0, 1])
    np.testing.assert_allclose(rgba[1], [1, 0, 0, 1])   # |w| = 4 > 3: red
    np.testing.assert_allclose(rgba[2], conv.OUTLIER_RGBA)
    rgba = conv.connection_rgba(np.array([1.5]), np.array([1]), 3.0)
    np.testing.assert_allclose(rgba[0], [1, 1, 0, conv.ABSORBED_ALPHA])
    assert conv.quality_values(None) == {}
    from ga_ros.core.quality import QualitySummary
    s = QualitySummary(False, 2.5, 100, 5.0, 3, 9, 2, 3.29, 0.4, 1.1, 0.02, 50, 0.012)
    v = conv.quality_values(s)
    assert v['quality/global_test'] == 'fail' and v['quality/w_max_connection'] == '3->9'
    assert v['quality/n_w_rejected'] == 2 and v['quality/ms'] == pytest.approx(12.0)
    assert v['quality/mdb_median_deg'] == pytest.approx(np.degrees(0.02))


def test_aligner_config_checks_the_new_fields():
    with pytest.raises(InputError):
        AlignerConfig(gate='huber')
    with pytest.raises(InputError):
        AlignerConfig(quality_alpha0=0.0)
    cfg = AlignerConfig(gate='w-test', quality=True, quality_alpha0=1e-3)
    assert cfg.quality_config().w_critical == pytest.approx(3.2905, abs=1e-3)
    assert AlignerConfig.from_dict({'gate': 'w-test', 'quality': True}).gate == 'w-test'


def test_solve_cli_quality_json(pose_graph_dir: Path, capsys):
    """``ga-ros solve --quality --json``: the QC block beside the variance factor, equal to
    quality_control of a solve of the written graph."""
    from ga_ros.cli.main import main as cli_main
    from ga_ros.io.g2o import read_g2o

    path = pose_graph_dir / 'smallGrid3D.g2o'
    assert cli_main(['solve', str(path), '--quality', '--json']) == 0
    out = json.loads(capsys.readouterr().out)
    q = out['quality']
    assert 'sigma0_sq' not in q and out['variance_factor'] > 0  # not repeated
    graph = read_g2o(path)
    res = solve(graph.network, graph.T_init, SolverConfig(damping='dogleg', max_iterations=100,
                                                          tolerance=1e-10))
    rep = quality_control(graph.network, res, config=QualityConfig(alpha0=1e-3))
    w = rep.w_max
    assert q['w_max'] == pytest.approx(w.max(), rel=1e-3)
    assert q['n_w_rejected'] == int((w > rep.w_critical).sum())
    assert q['n_tested'] == graph.n_edges


def test_quality_every_second_update(sample):
    ms = sample.measurements
    T0 = sample.ground_truth.T_world_node[0]
    _, ups = run(ms, AlignerConfig(window_tracks=2, quality=True, quality_every=2), T0)
    assert [u.quality is not None for u in ups] == [False, True, False]
    _, ups = run(ms, AlignerConfig(window_tracks=2, quality=True, quality_every=2,
                                   gate='w-test'), T0)
    assert all(u.quality is not None for u in ups)  # the gate computed it anyway


def test_node_diagnostics_and_markers_carry_the_quality(sample):
    """The alignment node with ``quality`` and the w-test gate: /diagnostics key/values hold the
    last update's QC figures, the markers' view the per-connection |w|."""
    pytest.importorskip('rclpy')

    import rclpy
    from rclpy.parameter import Parameter

    from ga_ros.ros import conversions as conv
    from ga_ros.ros.alignment_node import AlignmentNode
    from ga_ros.ros.view import connection_view

    ms = corrupt(sample.measurements, 5)
    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domains.domain_id('quality_wiring'))
    node = AlignmentNode(context=ctx, parameter_overrides=[
        Parameter('window_tracks', value=2), Parameter('quality', value=True),
        Parameter('gate', value='w-test'), Parameter('diagnostics_period_sec', value=0.0)])
    try:
        for m in ms:
            node._on_measurement(conv.measurement_to_odometry(m))
        node._finish_track()
        values = node.diagnostic_values()
        q = node.session.last_update.quality
        assert values['quality/global_test'] == ('pass' if q.global_passed else 'fail')
        assert values['quality/w_max'] == pytest.approx(q.w_max)
        assert values['quality/n_w_rejected'] == q.n_w_rejected
        assert values['outliers_excluded'] >= 1
        view = connection_view(node.aligner)
        assert view.w is not None and np.isfinite(view.w).sum() > 0.5 * view.w.size
        rgba = conv.connection_rgba(view.normalized_residual, view.status, 3.0, view.w)
        assert (rgba[view.status == 2] == conv.OUTLIER_RGBA).all()
        node._publish_markers(force=True)  # builds the message without error
    finally:
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)
