"""A survey aligned online track by track against batch GA and F2F (Figs. 7-9, Sec. IV, V-B).

:func:`survey_window` runs F2F, the batch GA (with its quality control) and the online track
window (every policy of ``ReproduceConfig.policies``) on any survey's measured motions;
:func:`aerial_window` feeds it the aerial survey with synthetic noise, and experiment 2
(:mod:`ga_ros.report.experiments.experiment2`) the motions of our VO.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.quality import QualityReport, quality_control
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.errors import GaError
from ga_ros.eval.metrics import ate, improvement_pct, per_track_mean, position_errors
from ga_ros.geometry import se3, so3
from ga_ros.report.config import ReproduceConfig
from ga_ros.report.experiments.seeds import EXP_AERIAL, run_rng
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb
from ga_ros.sim.scenario import Scenario


@dataclass
class AerialResult:
    """Fig. 7/8, window-versus-batch gap and timings on the aerial survey."""

    summary: dict
    errors: dict[str, FloatArray]
    fig8: dict[int, dict[str, FloatArray]]
    track_ids: IntArray
    paths: dict[str, FloatArray] = field(default_factory=dict)
    T_true: FloatArray | None = None
    quality: QualityReport | None = None
    consecutive: BoolArray | None = None


def window_available() -> bool:
    """True when :mod:`ga_ros.core.window` (the track-window aligner) can be imported."""
    try:
        from ga_ros.core.window import AlignerConfig, TrackWindowAligner  # noqa: F401
    except ImportError:
        return False
    return True


def aligner_config(policy: str, window: int):
    """The :class:`~ga_ros.core.window.AlignerConfig` of a policy name of
    ``ReproduceConfig.policies``: ``'<freeze policy>'`` (the plain window, no background
    refinement), ``'<freeze policy>+refine'`` (with the background refinement at its default
    settings) or ``'<freeze policy>+<executor>'`` (with it run by that ``refine_executor``).
    Every policy of the list gets its rows in the gap tables and its curve in Figs. 7 and 9."""
    from ga_ros.core.window import AlignerConfig

    base, _, executor = policy.partition('+')
    if not executor:  # the plain window: no background refinement
        extra = {'refine_every_tracks': 0}
    elif executor == 'refine':  # the refinement with its default settings
        extra = {}
    else:
        extra = {'refine_executor': executor}
    return AlignerConfig(window_tracks=window, freeze_policy=base, **extra)


def run_aligner(sc: Scenario, z: FloatArray, cov: FloatArray, policy: str, window: int,
                snapshot_tracks: set[int], f2f: FloatArray, final_refine: bool = True) -> dict:
    """Feed a survey's measurements track by track into a TrackWindowAligner; then, when
    ``final_refine``, its final batch refinement (``refined``; else ``refined`` is the path)."""
    from ga_ros.core.window import TrackWindowAligner

    aligner = TrackWindowAligner(aligner_config(policy, window), T_world_first=sc.T_world_node[0])
    meas = sc.measurements(z, cov)
    dst_track = np.array([m.dst_track for m in meas])
    bounds = np.searchsorted(dst_track, np.unique(sc.track_ids), side='right')
    updates, wall_ms, snapshots = [], [], {}
    rejected = 0
    start = 0
    chain_f2f = f2f
    t_run = time.perf_counter()
    for k, stop in enumerate(bounds):
        before = None
        if k in snapshot_tracks:
            before = _before_update(aligner, sc, k, chain_f2f)
        for m in meas[start:stop]:
            try:
                updates.extend(aligner.add_measurement(m))
            except GaError:  # counted by the aligner (stats.n_rejected); the run goes on
                rejected += 1
        t0 = time.perf_counter()
        u = aligner.finish_track()
        wall_ms.append(1e3 * (time.perf_counter() - t0))
        if u is not None:
            updates.append(u)
        if k in snapshot_tracks:
            after = aligner.corrected_path().T_world_node
            snapshots[k] = {'before': before, 'after': after.copy()}
        start = stop
    run_s = time.perf_counter() - t_run
    if hasattr(aligner, 'close'):  # stop the background refinement's worker
        aligner.close()
    path = aligner.corrected_path().T_world_node.copy()
    refined, refine_s = path, 0.0
    if final_refine:
        t0 = time.perf_counter()
        aligner.refine_batch()
        refine_s = time.perf_counter() - t0
        refined = aligner.corrected_path().T_world_node.copy()
    return {'updates': updates, 'wall_ms': wall_ms, 'run_s': run_s, 'path': path,
            'refined': refined, 'refine_s': refine_s, 'snapshots': snapshots,
            'rejected': rejected}


def _before_update(aligner, sc: Scenario, k: int, f2f: FloatArray) -> FloatArray:
    """Estimate before the update at the end of track ``k``: the corrected path so far, with
    track ``k`` chained by F2F from the last corrected node (what the paper's Fig. 8 calls
    "before GA")."""
    n_end = int(np.searchsorted(sc.track_ids, k, side='right'))
    if k == 0:
        return f2f[:n_end].copy()
    T_prev = aligner.corrected_path().T_world_node
    n0 = T_prev.shape[0]
    out = np.empty((n_end, 4, 4))
    out[:n0] = T_prev
    out[n0:] = T_prev[-1] @ se3.inverse(f2f[n0 - 1]) @ f2f[n0:n_end]
    return out


def aerial_window(cfg: ReproduceConfig) -> AerialResult:
    """The aerial survey with synthetic noise: :func:`survey_window` at ``aerial_noise``."""
    sc = aerial_scenario(cfg.aerial_tracks, cfg.aerial_positions_per_swath)
    nm = perturb(sc.true_motions(), NoiseModel(cfg.aerial_noise, sc.depth_m),
                 run_rng(cfg.seed, EXP_AERIAL, 0))
    res = survey_window(cfg, sc, nm.z, nm.cov)
    res.summary['noise_pct'] = cfg.aerial_noise
    return res


def survey_window(cfg: ReproduceConfig, sc: Scenario, z: FloatArray, cov: FloatArray,
                  quality: bool = True) -> AerialResult:
    """A survey's measured motions ``z`` (m, 6) with covariances ``cov`` (m, 6, 6): F2F, batch
    GA (with its quality control when ``quality``), the online window (each policy of
    ``cfg.policies``) and its final batch refinement; ATE raw (first pose anchored) and
    rigidly aligned; per-track update times. The poses of every estimate are kept in
    ``AerialResult.paths`` (Fig. 9: altitude and heading errors)."""
    T_true = sc.T_world_node
    f2f = sc.f2f(z)
    net = sc.network(z, cov)
    t0 = time.perf_counter()
    batch = batch_solve(net, f2f)
    batch_s = time.perf_counter() - t0
    summary: dict = {
        'nodes': sc.n_nodes, 'connections': sc.n_connections,
        'cross_connections': int((~sc.consecutive).sum()), 'tracks': sc.n_tracks,
        'se3': {'equations': batch.n_equations, 'observations': batch.n_observations,
                'unknowns': batch.n_unknowns},
        'paper_model_counts': {'equations': 3 * sc.n_connections,
                               'observations': 6 * sc.n_connections,
                               'unknowns': 3 * (sc.n_nodes - 1)},
        'f2f': ates(f2f, T_true), 'batch': {**ates(batch.T_world_node, T_true),
                                            'seconds': batch_s, 'iterations': batch.iterations,
                                            'sigma0_sq': float(batch.sigma0_sq)},
        'window_available': window_available(), 'policies': {},
    }
    summary['improvement_pct'] = {'batch': improvement_pct(summary['f2f']['mean_error_m'],
                                                           summary['batch']['mean_error_m'])}
    errors = {'f2f': position_errors(f2f, T_true), 'batch': position_errors(batch.T_world_node,
                                                                          T_true)}
    paths = {'f2f': f2f, 'batch': batch.T_world_node}
    qrep = None
    if quality:
        t0 = time.perf_counter()
        qrep = quality_control(net, batch)
        summary['quality'] = quality_summary(qrep, sc.consecutive)
        summary['quality']['seconds'] = time.perf_counter() - t0
    fig8: dict[int, dict[str, FloatArray]] = {}
    if summary['window_available']:
        fig8 = _window_policies(cfg, sc, z, cov, f2f, summary, errors, paths)
    return AerialResult(summary, errors, fig8, sc.track_ids, paths, T_true, qrep,
                        sc.consecutive)


def _window_policies(cfg: ReproduceConfig, sc: Scenario, z: FloatArray, cov: FloatArray,
                     f2f: FloatArray, summary: dict, errors: dict[str, FloatArray],
                     paths: dict[str, FloatArray]) -> dict[int, dict[str, FloatArray]]:
    """Run the online window with every policy of ``cfg.policies`` and add its figures to
    :func:`survey_window`'s ``summary`` (per policy, per-track means, improvement over F2F),
    ``errors`` and ``paths``; return Fig. 8's before/after errors (the first policy's)."""
    T_true = sc.T_world_node
    wanted = {t - 1 for t in cfg.fig8_tracks if 1 <= t <= sc.n_tracks}
    fig8: dict[int, dict[str, FloatArray]] = {}
    for policy in cfg.policies:
        out = run_aligner(sc, z, cov, policy, cfg.window_tracks,
                          wanted if policy == cfg.policies[0] else set(), f2f)
        summary['policies'][policy] = _policy_figures(out, T_true, summary['batch'])
        errors[f'window_{policy}'] = position_errors(out['path'], T_true)
        paths[f'window_{policy}'] = out['path']
        errors[f'refined_{policy}'] = position_errors(out['refined'], T_true)
        for k, snap in out['snapshots'].items():
            n_end = snap['after'].shape[0]
            lo = int(np.searchsorted(sc.track_ids, max(0, k - cfg.window_tracks + 1)))
            fig8[k + 1] = {
                'nodes': np.arange(lo, n_end),
                'before': position_errors(snap['before'][lo:n_end], T_true[lo:n_end]),
                'after': position_errors(snap['after'][lo:n_end], T_true[lo:n_end])}
    summary['per_track_f2f_mean_m'] = per_track_mean(errors['f2f'], sc.track_ids)
    for policy in cfg.policies:
        summary['improvement_pct'][policy] = improvement_pct(
            summary['f2f']['mean_error_m'],
            summary['policies'][policy]['window']['mean_error_m'])
    first = f'window_{cfg.policies[0]}'
    summary['per_track_window_mean_m'] = per_track_mean(errors[first], sc.track_ids)
    return fig8


def _policy_figures(out: dict, T_true: FloatArray, batch: dict[str, float]) -> dict:
    """JSON-ready figures of one policy's run (:func:`run_aligner`'s dict): ATEs of the window
    and of its final refinement, gaps to ``batch`` (:func:`ates` of the batch GA), update
    times and counts."""
    ms = np.array([u.update_ms for u in out['updates']])
    w = ates(out['path'], T_true)
    return {
        'window': w, 'refined': ates(out['refined'], T_true), **gaps_pct(w, batch),
        'update_ms': {'p50': float(np.percentile(ms, 50)),
                      'p95': float(np.percentile(ms, 95)), 'max': float(ms.max())},
        'finish_track_wall_ms_max': float(max(out['wall_ms'])),
        'updates': len(out['updates']), 'run_s': out['run_s'],
        'refine_s': out['refine_s'],
        'converged_updates': int(sum(bool(u.converged) for u in out['updates'])),
        'outliers': int(sum(int(u.n_outliers) for u in out['updates'])),
        'rejected_measurements': out['rejected'],
    }


def batch_solve(net, f2f: FloatArray):
    """The batch GA of a survey's network from its F2F path (the reference of every gap)."""
    return solve(net, f2f, SolverConfig(tolerance=1e-7))


def ates(T: FloatArray, T_true: FloatArray) -> dict[str, float]:
    """ATE (m) raw (first pose anchored), rigidly aligned, and the mean position error."""
    return {'raw_rmse_m': ate(T, T_true, 'first').rmse,
            'aligned_rmse_m': ate(T, T_true, 'rigid').rmse,
            'mean_error_m': float(position_errors(T, T_true).mean())}


def gaps_pct(window: dict[str, float], batch: dict[str, float]) -> dict[str, float]:
    """Gap to batch (%) of an estimate's ATEs (from :func:`ates`): ``100 (window / batch -
    1)``, raw and rigidly aligned."""
    return {'gap_aligned_pct': 100.0 * (window['aligned_rmse_m'] / batch['aligned_rmse_m'] - 1),
            'gap_raw_pct': 100.0 * (window['raw_rmse_m'] / batch['raw_rmse_m'] - 1.0)}


def quality_summary(q: QualityReport, consecutive: BoolArray) -> dict:
    """JSON-ready figures of a batch adjustment's quality control (Baarda): the global test,
    redundancy numbers, w-test and MDB, the last two also per kind of connection."""
    out = q.summary()
    w_crit = float(q.w_critical)
    for name, sel in (('consecutive', consecutive), ('cross', ~consecutive)):
        if not sel.any():
            continue
        mdb = q.mdb[sel]
        out[name] = {
            'connections': int(sel.sum()),
            'redundancy_number_median': float(np.median(q.redundancy_numbers[sel])),
            'w_abs_max': float(np.nanmax(np.abs(q.w[sel]))),
            'w_rejected_components': int((np.abs(q.w[sel]) > w_crit).sum()),
            'mdb_translation_median_m': float(np.nanmedian(mdb[:, :3])),
            'mdb_rotation_median_deg': float(np.degrees(np.nanmedian(mdb[:, 3:]))),
        }
    w = q.w[np.isfinite(q.w)]
    out['w_mean'] = float(w.mean()) if w.size else float('nan')
    out['w_std'] = float(w.std()) if w.size else float('nan')
    return out


def pose_error_profiles(T_est: FloatArray, T_true: FloatArray) -> dict[str, FloatArray]:
    """Errors along the trajectory (the paper's Fig. 9): ``position`` ``|p_est - p_true|`` (m),
    ``altitude`` ``z_est - z_true`` (m, world ``z`` up) and ``heading`` (rad), the world-``z``
    component of ``log(R_est R_true')`` (the rotation error about the vertical)."""
    R_err = T_est[:, :3, :3] @ np.swapaxes(T_true[:, :3, :3], 1, 2)
    return {'position': position_errors(T_est, T_true),
            'altitude': T_est[:, 2, 3] - T_true[:, 2, 3],
            'heading': so3.log(R_err)[:, 2]}
