"""Smoke test of ``ga-ros reproduce`` on the tiny preset, with an independent recomputation of
some of the report's numbers (own noise draw, own F2F loop, own error statistics)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from ga_ros.cli.main import main
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import solve
from ga_ros.geometry import se3
from ga_ros.report import preset, run_reproduction
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.trajectories import SYNTHETIC_TRAJECTORIES, synthetic_scenario


def _noisy(T_true, src, dst, pct, depth, rng):
    """Independent implementation of the documented noise model."""
    T_rel = np.linalg.inv(T_true[src]) @ T_true[dst]
    t = np.linalg.norm(T_rel[:, :3, 3], axis=1)
    sig = np.empty((len(src), 6))
    sig[:, :3] = (pct / 100 * t)[:, None]
    sig[:, 3:] = (pct / 100 * t / depth)[:, None]  # true rotations are identity
    xi = rng.standard_normal((len(src), 6)) * sig
    T_meas = T_rel @ se3.exp(xi)
    cov = np.zeros((len(src), 6, 6))
    cov[:, range(6), range(6)] = sig**2
    return T_meas, cov


def _f2f(T_true, src, dst, T_meas):
    k_of = {(int(s), int(d)): k for k, (s, d) in enumerate(zip(src, dst))}
    out = [T_true[0]]
    for i in range(len(T_true) - 1):
        out.append(out[-1] @ T_meas[k_of[(i, i + 1)]])
    return np.array(out)


@pytest.fixture(scope='module')
def tiny_report(tmp_path_factory):
    out = tmp_path_factory.mktemp('report')
    cfg = preset('tiny')
    return cfg, out, run_reproduction(cfg, out)


def test_report_files_and_keys(tiny_report):
    cfg, out, rep = tiny_report
    for name in ('report.md', 'report.json', *rep['images']):
        assert (out / name).is_file(), name
    data = json.loads((out / 'report.json').read_text())
    assert set(data['improvement_pct']) == set(SYNTHETIC_TRAJECTORIES)
    for v in data['improvement_pct'].values():
        assert set(v) == {f'{p:g}' for p in cfg.noise_levels}
    assert data['runs'] == cfg.runs
    assert isinstance(data['window_vs_batch_gap_pct'], dict)
    if data['aerial']['window_available']:
        assert set(data['window_vs_batch_gap_pct']) == set(cfg.policies)
        assert set(data['per_track_update_ms']) == {'p50', 'p95', 'max'}
    md = (out / 'report.md').read_text()
    row = next(r for r in data['table1'] if r['trajectory'] == 'looping_closed')
    assert f'{row["ga_mean_m"]:.3f}' in md and f'{row["improvement_pct"]:.1f}' in md
    # issue 15: experiment 2 from rendered stereo, quality control, wrong connections
    e2 = data['experiment2']
    assert {'survey', 'nees', 'f2f', 'batch', 'policies', 'fig12', 'quality'} <= set(e2)
    assert e2['batch']['raw_rmse_m'] < e2['f2f']['raw_rmse_m']
    assert {'fig7_9_exp2.png', 'fig12_registration.png', 'fig_quality.png'} <= set(
        data['images'])
    q = data['quality_control']
    assert q['redundancy_numbers_sum'] == pytest.approx(q['redundancy'], rel=1e-6)
    assert data['policies'] == list(cfg.policies)
    rows = data['wrong_connections']['rows']
    assert {r['method'] for r in rows} == set(cfg.outlier_methods)
    assert 'Experiment 2 from rendered stereo' in md and 'Wrong cross-track' in md


def test_report_prints_the_policies_on_several_noise_draws(tiny_report):
    """The multi-draw table below the single-draw one: draw 0 is the single-draw run, every
    figure of report.json's ``policy_seeds`` is in the Markdown, and the target row reads the
    paired intervals."""
    cfg, out, rep = tiny_report
    ps = rep['policy_seeds']
    if not rep['aerial']['window_available']:
        pytest.skip('no track-window aligner')
    assert ps['n'] == cfg.policy_seeds == len(ps['draws']) and ps['reference'] == 'weighted'
    for p, v in rep['aerial']['policies'].items():
        assert ps['policies'][p]['raw']['values'][0] == v['gap_raw_pct']
        assert ps['policies'][p]['aligned']['values'][0] == v['gap_aligned_pct']
        assert len(set(ps['policies'][p]['raw']['values'])) == cfg.policy_seeds  # new draws
    md = (out / 'report.md').read_text()
    single = md.index('| window K=')
    multi = md.index(f'### The policies on {cfg.policy_seeds} noise draws')
    assert single < multi
    m = ps['policies']['marginal']
    d = m['vs_reference']['aligned']
    assert (f'| marginal | {m["raw"]["mean"]:+.1f} +- {m["raw"]["sd"]:.1f} | '
            f'{m["aligned"]["mean"]:+.1f} +- {m["aligned"]["sd"]:.1f} |') in md
    assert f'{d["mean"]:+.1f} [{d["ci_low"]:+.1f}, {d["ci_high"]:+.1f}]' in md
    assert 'How to read it' in md
    met = 'yes' if not ps['worse'] else '**no**'
    assert any(x.startswith('| no policy worse than weighted') and x.endswith(f'| {met} |')
               for x in md.splitlines())


def test_table1_numbers_recomputed_independently(tiny_report):
    cfg, _, rep = tiny_report
    name = 'lawnmower_open'
    j = 0  # family 'lawnmower'
    i = len(cfg.noise_levels) - 1
    pct = cfg.noise_levels[i]
    sc = synthetic_scenario(name)
    f2f_err, ga_err = [], []
    for r in range(cfg.runs):
        rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 1, j, i, r]))
        T_meas, cov = _noisy(sc.T_world_node, sc.src, sc.dst, pct, 110.0, rng)
        T0 = _f2f(sc.T_world_node, sc.src, sc.dst, T_meas)
        net = ConnectionNetwork()
        for n, t in zip(range(sc.n_nodes), sc.track_ids):
            net.add_node(n, int(t))
        net.add_connections(sc.src, sc.dst, se3.to_translation_rotvec(T_meas), cov)
        res = solve(net, T0)
        truth = sc.T_world_node[:, :3, 3]
        f2f_err.append(np.mean(np.sqrt(((T0[:, :3, 3] - truth) ** 2).sum(1))))
        ga_err.append(np.mean(np.sqrt(((res.T_world_node[:, :3, 3] - truth) ** 2).sum(1))))
    row = next(x for x in rep['table1'] if x['trajectory'] == name and x['noise_pct'] == pct)
    assert row['f2f_mean_m'] == pytest.approx(np.mean(f2f_err), rel=1e-6)
    assert row['ga_mean_m'] == pytest.approx(np.mean(ga_err), rel=1e-5)
    expect = 100 * (1 - np.mean(ga_err) / np.mean(f2f_err))
    assert rep['improvement_pct'][name][f'{pct:g}'] == pytest.approx(expect, abs=1e-3)
    assert row['equations'] == 6 * sc.n_connections
    assert row['unknowns'] == 6 * (sc.n_nodes - 1)


def test_aerial_f2f_ate_recomputed_independently(tiny_report):
    cfg, _, rep = tiny_report
    sc = aerial_scenario(cfg.aerial_tracks, cfg.aerial_positions_per_swath)
    rng = np.random.default_rng(np.random.SeedSequence([cfg.seed, 4, 0]))
    T_meas, _ = _noisy(sc.T_world_node, sc.src, sc.dst, cfg.aerial_noise, 110.0, rng)
    T0 = _f2f(sc.T_world_node, sc.src, sc.dst, T_meas)
    e = np.linalg.norm(T0[:, :3, 3] - sc.positions, axis=1)
    a = rep['aerial']
    assert a['f2f']['raw_rmse_m'] == pytest.approx(np.sqrt(np.mean(e**2)), rel=1e-6)
    assert a['nodes'] == sc.n_nodes and a['connections'] == sc.n_connections
    assert a['batch']['aligned_rmse_m'] < a['f2f']['aligned_rmse_m']


def test_reproduce_command_rejects_bad_output(tmp_path, capsys):
    f = tmp_path / 'file'
    f.write_text('x')
    assert main(['reproduce', '--preset', 'tiny', '--out', str(f)]) == 1
    assert 'not a directory' in capsys.readouterr().err


class _BatchAligner:
    """Stand-in for TrackWindowAligner with an unlimited window: every update is the batch
    solution of everything seen so far, so the report's window-vs-batch gap must be ~0."""

    def __init__(self, config=None, T_world_first=None):
        self.net = ConnectionNetwork()
        self.T_first = T_world_first
        self.T = T_world_first[None].copy()

    def add_measurement(self, m):
        self.net.add_node(m.src_id, m.src_track)
        self.net.add_node(m.dst_id, m.dst_track)
        self.net.add_connection(m.src_id, m.dst_id, m.z, m.cov)
        return []

    def finish_track(self):
        from types import SimpleNamespace

        from ga_ros.core.solver import initial_guess_f2f

        res = solve(self.net, initial_guess_f2f(self.net, self.T_first))
        self.T = res.T_world_node
        return SimpleNamespace(update_ms=1e3 * res.seconds, converged=res.converged,
                               n_outliers=0)

    def refine_batch(self):
        return self.finish_track()

    def corrected_path(self):
        from types import SimpleNamespace

        return SimpleNamespace(T_world_node=self.T.copy())

    @property
    def stats(self):
        return None


def test_aerial_window_plumbing_with_a_batch_stand_in(monkeypatch):
    import sys
    import types
    from dataclasses import replace

    from ga_ros.report.experiments.memory import memory_profile
    from ga_ros.report.experiments.seeds import EXP_AERIAL, run_rng
    from ga_ros.report.experiments.survey import aerial_window

    fake = types.ModuleType('ga_ros.core.window')
    fake.AlignerConfig = lambda **kw: None
    fake.TrackWindowAligner = _BatchAligner
    monkeypatch.setitem(sys.modules, 'ga_ros.core.window', fake)
    cfg = replace(preset('tiny'), aerial_tracks=4, fig8_tracks=(1, 3))
    res = aerial_window(cfg)
    for policy in cfg.policies:
        p = res.summary['policies'][policy]
        assert abs(p['gap_aligned_pct']) < 1e-3 and abs(p['gap_raw_pct']) < 1e-3
        assert p['updates'] == 4
    assert sorted(res.fig8) == [1, 3]
    # before the update at the end of track 3: tracks 1-2 as estimated, track 3 chained by F2F
    sc = aerial_scenario(4, cfg.aerial_positions_per_swath)
    n2 = int(np.searchsorted(sc.track_ids, 1, side='right'))
    n3 = int(np.searchsorted(sc.track_ids, 2, side='right'))
    d = res.fig8[3]
    assert d['nodes'][0] == 0 and d['nodes'][-1] == n3 - 1
    assert d['before'][n2:n3].mean() > d['after'][n2:n3].mean()  # F2F-chained track 3 improves
    # tracks 1-2 "before" = the batch solution of tracks 1-2, recomputed here
    from ga_ros.core.solver import initial_guess_f2f
    from ga_ros.sim.noise import NoiseModel, perturb

    nm = perturb(sc.true_motions(), NoiseModel(cfg.aerial_noise, 110.0),
                 run_rng(cfg.seed, EXP_AERIAL, 0))
    sub = sc.first_tracks(2)
    net = sub.network(nm.z[:sub.n_connections], nm.cov[:sub.n_connections])
    T12 = solve(net, initial_guess_f2f(net, sc.T_world_node[0])).T_world_node
    e12 = np.linalg.norm(T12[:, :3, 3] - sub.positions, axis=1)
    np.testing.assert_allclose(d['before'][:n2], e12, rtol=1e-6, atol=1e-6)
    mem = memory_profile(replace(cfg, memory_tracks=(2, 3)))
    assert set(mem['sizes']) == {'2', '3'}


class _ScaledAligner(_BatchAligner):
    """The batch stand-in, except that the policy ``'worse'`` publishes its path stretched by
    3 % about the first pose: a policy made worse on purpose, on every noise draw."""

    def __init__(self, config=None, T_world_first=None):
        super().__init__(config, T_world_first)
        self.scale = 1.03 if config['freeze_policy'] == 'worse' else 1.0

    def corrected_path(self):
        path = super().corrected_path()
        p = path.T_world_node[:, :3, 3]
        path.T_world_node[:, :3, 3] = p[0] + self.scale * (p - p[0])
        return path


def test_policy_draws_flag_a_policy_made_worse_on_purpose(monkeypatch):
    """Through the report's own plumbing (noise draws, batch reference, pairing): a copy of
    the reference policy differs from it by exactly 0 on every draw, a stretched one is
    significantly worse and fails the target row."""
    import sys
    import types
    from dataclasses import replace

    from ga_ros.report.experiments.policies import policy_seeds
    from ga_ros.report.markdown.targets import policy_target_row

    fake = types.ModuleType('ga_ros.core.window')
    fake.AlignerConfig = lambda **kw: kw
    fake.TrackWindowAligner = _ScaledAligner
    monkeypatch.setitem(sys.modules, 'ga_ros.core.window', fake)
    # the gap is relative to the batch ATE, which changes from draw to draw: 8 draws
    cfg = replace(preset('tiny'), aerial_tracks=2, policies=('weighted', 'same', 'worse'),
                  policy_seeds=8)
    ps = policy_seeds(cfg)
    assert ps['available'] and ps['draws'] == list(range(8)) and ps['worse'] == ['worse']
    same = ps['policies']['same']['vs_reference']
    for metric in ('raw', 'aligned'):
        assert same[metric]['mean'] == 0.0 and same[metric]['sd'] == 0.0
        w = ps['policies']['weighted'][metric]['values']
        assert all(abs(g) < 1e-3 for g in w)  # the stand-in is the batch solution
    assert ps['policies']['worse']['vs_reference']['aligned']['ci_low'] > 0
    assert policy_target_row(ps)[2] is False
    # different noise draws: the stretched path's gap changes from draw to draw
    assert len(set(ps['policies']['worse']['aligned']['values'])) == 8


@pytest.mark.parametrize('family', ['lawnmower', 'looping'])
def test_open_and_closed_share_the_noise_of_common_connections(family):
    from ga_ros.report.experiments.seeds import run_rng
    from ga_ros.sim.noise import NoiseModel, perturb

    o, c = synthetic_scenario(f'{family}_open'), synthetic_scenario(f'{family}_closed')
    m = o.n_connections
    np.testing.assert_array_equal(o.src, c.src[:m])
    np.testing.assert_array_equal(o.dst, c.dst[:m])
    zo = perturb(o.true_motions(), NoiseModel(10), run_rng(1, 1, 0, 2, 3)).z
    zc = perturb(c.true_motions(), NoiseModel(10), run_rng(1, 1, 0, 2, 3)).z
    np.testing.assert_allclose(zo, zc[:m], rtol=0, atol=1e-12)


def test_future_tracks_linearisation_matches_nonlinear_solves():
    """Fig. 2/3 is computed on the linearised adjustment; at small noise it must agree with the
    actual solver run on tracks 1..k with the same noise draws."""
    from dataclasses import replace

    from ga_ros.core.solver import SolverConfig
    from ga_ros.report.experiments.future_tracks import future_tracks
    from ga_ros.report.experiments.seeds import EXP_FUTURE, run_rng
    from ga_ros.sim.noise import NoiseModel

    pct = 0.1
    cfg = replace(preset('tiny'), fig3_tracks=3, fig3_runs=3, fig3_noise_levels=(pct,),
                  aerial_positions_per_swath=12)
    ft = future_tracks(cfg)
    sc_all = aerial_scenario(3, 12)
    z_true = sc_all.true_motions()
    sig1 = NoiseModel(1.0, 110.0).sigmas(z_true)
    xi = run_rng(cfg.seed, EXP_FUTURE, 0).standard_normal((3,) + sig1.shape) * sig1 * pct
    T_true = se3.from_translation_rotvec(z_true[:, :3], z_true[:, 3:])
    cov = NoiseModel(pct, 110.0).covariances(z_true)
    track1 = sc_all.first_tracks(1).n_nodes
    changes = np.zeros((3, 2))
    for r in range(3):
        z = se3.to_translation_rotvec(T_true @ se3.exp(xi[r]))
        prev = None
        for k in (1, 2, 3):
            sc = sc_all.first_tracks(k)
            m = sc.n_connections
            res = solve(sc.network(z[:m], cov[:m]), sc.T_world_node.copy(),
                        SolverConfig(tolerance=1e-12, max_iterations=30))
            p1 = res.T_world_node[:track1, :3, 3]
            if prev is not None:
                changes[r, k - 2] = np.linalg.norm(p1 - prev, axis=1).mean()
            prev = p1
    np.testing.assert_allclose(ft.absolute_m['0.1'], changes.mean(axis=0), rtol=0.02)
