"""The wrong-connection table (issue 15 item 5) on a reduced aerial survey."""

from __future__ import annotations

from ga_ros.report.config import ReproduceConfig
from ga_ros.report.experiments.seeds import EXP_OUTLIERS, run_rng
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb


def wrong_connections(cfg: ReproduceConfig) -> dict:
    """The wrong-connection table (issue 15 item 5) on a reduced aerial survey: the clean run,
    then each fraction of ``outlier_fractions`` of the cross-track connections replaced by
    gross errors (:func:`ga_ros.bench.outliers.inject`), each defence of ``outlier_methods``
    run by :func:`ga_ros.bench.outliers.run_method`. Per row: recall and precision of the
    rejection, share of good connections rejected (%), rigidly aligned ATE (m) and its change
    against the clean run of the same family (the online gates against themselves, the batch
    methods against batch LS)."""
    from ga_ros.bench.outliers import inject, run_method

    sc = aerial_scenario(cfg.outlier_tracks, cfg.outlier_positions_per_swath)
    nm = perturb(sc.true_motions(), NoiseModel(cfg.outlier_noise, sc.depth_m),
                 run_rng(cfg.seed, EXP_OUTLIERS, 0))
    gross, alpha0 = (5.0, 15.0), 1e-4
    rows, clean = [], {}
    for i, fraction in enumerate((0.0, *cfg.outlier_fractions)):
        z, bad = inject(sc, nm.z, fraction, gross, gross, run_rng(cfg.seed, EXP_OUTLIERS, 1, i))
        for method in cfg.outlier_methods:
            out = run_method(method, sc, z, nm.cov, bad, alpha0, 20)
            if fraction == 0.0:
                clean[method] = out.ate_m
            ref = clean.get(method if method.startswith('gate') else 'ls', out.ate_m)
            hit, n_rej = int((out.rejected & bad).sum()), int(out.rejected.sum())
            rows.append({
                'wrong_pct': 100.0 * fraction, 'method': method, 'wrong': int(bad.sum()),
                'recall_pct': 100.0 * hit / bad.sum() if bad.any() else float('nan'),
                'precision_pct': 100.0 * hit / n_rej if n_rej else float('nan'),
                'good_rejected_pct': 100.0 * (out.rejected & ~bad).sum() / (~bad).sum(),
                'ate_m': out.ate_m, 'd_ate_pct': 100.0 * (out.ate_m / ref - 1.0),
                'seconds': out.seconds})
    return {'tracks': cfg.outlier_tracks, 'nodes': sc.n_nodes,
            'connections': sc.n_connections, 'cross_connections': int((~sc.consecutive).sum()),
            'noise_pct': cfg.outlier_noise, 'gross_m': list(gross), 'gross_deg': list(gross),
            'alpha0': alpha0, 'rows': rows}
