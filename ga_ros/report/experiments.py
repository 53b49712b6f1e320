"""The paper's experiments, each returning JSON-ready numbers plus the arrays its plots need.

* :func:`table1`: Table I and Fig. 5 (Sec. V-A): F2F vs GA mean position error of the four
  synthetic trajectories at each noise level, ``runs`` Monte-Carlo runs each.
* :func:`future_tracks`: Fig. 2/3 (Sec. IV): how much each new track moves the track-1 positions.
* :func:`aerial_window`: Fig. 7/8 and the window-versus-batch gap (Sec. IV, V-B): the aerial
  survey aligned online track by track with :class:`~ga_ros.core.window.TrackWindowAligner`,
  against the full batch solution and F2F, with per-track update times.
* :func:`memory_profile`: peak memory of one track update for two survey sizes.
* :func:`survey_window`: F2F / window (every policy) / batch on any survey's measured motions,
  with the batch adjustment's quality control (:func:`quality_summary`); the aerial survey with
  synthetic noise and experiment 2 both go through it.
* :func:`stereo_experiment`: experiment 2 (Sec. V-B) from rendered stereo and our VO, with the
  VO's NEES and Fig. 12's registration of neighbouring swaths.
* :func:`wrong_connections`: the wrong-connection table (:mod:`ga_ros.bench.outliers`).
* :func:`policy_seeds`: the freeze policies on several noise draws of the aerial survey, with
  the paired difference of each policy's gap to batch against weighted (mean, sd, t interval).

Every random draw comes from :func:`run_rng` so any single number can be recomputed alone.
"""

from __future__ import annotations

import time
import tracemalloc
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.quality import QualityReport, quality_control
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.errors import GaError, InputError
from ga_ros.eval.metrics import ate, improvement_pct, per_track_mean, position_errors
from ga_ros.geometry import se3, so3
from ga_ros.report.config import ReproduceConfig
from ga_ros.report.stereo_survey import (
    CACHE_NAME,
    Registration,
    StereoSurveyConfig,
    VoSurvey,
    ground_homography,
    register_pair,
    render_vo_survey,
)
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb
from ga_ros.sim.scenario import Scenario
from ga_ros.sim.trajectories import synthetic_scenario

#: Path families of the synthetic trajectories (the first key of a Table I run).
FAMILIES = ('lawnmower', 'looping')

#: Experiment keys of :func:`run_rng`.
EXP_TABLE1, EXP_PAPER_MODEL, EXP_FUTURE, EXP_AERIAL, EXP_MEMORY = 1, 2, 3, 4, 5
EXP_OUTLIERS = 6


def run_rng(seed: int, experiment: int, *keys: int) -> np.random.Generator:
    """The generator of one run: ``default_rng(SeedSequence([seed, experiment, *keys]))``.

    Table I uses ``keys = (family, noise index, run)`` with ``family`` the index of the path's
    family in :data:`FAMILIES`. The open path's nodes and connections are a prefix of the closed
    one's, and a standard normal draw of the first ``m`` rows equals the first ``m`` rows of a
    longer draw, so open and closed share the noise of their common connections (common random
    numbers): their difference is the effect of closing the path, not of the draw.
    """
    return np.random.default_rng(np.random.SeedSequence([int(seed), int(experiment),
                                                         *map(int, keys)]))


@dataclass
class SyntheticRun:
    """Per-node position errors (m) of one Monte-Carlo run."""

    f2f: FloatArray
    ga: FloatArray
    converged: bool
    iterations: int
    n_equations: int
    n_observations: int
    n_unknowns: int


def synthetic_run(sc: Scenario, percent: float, rng: np.random.Generator,
                  model: str = 'se3') -> SyntheticRun:
    """One run: noisy motions, F2F from the known first pose, GA (batch, first node fixed)."""
    noise = NoiseModel(percent, sc.depth_m)
    nm = perturb(sc.true_motions(model), noise, rng, model='se3' if model == 'se3' else 'paper')
    if model == 'se3':
        T0 = sc.f2f(nm.z)
    else:
        T0 = se3.identity(sc.n_nodes)
        T0[:, :3, 3] = sc.f2f_positions(nm.z, model)
    # the paper model's rotation acts on world coordinates (hundreds of m), so its corrections
    # converge linearly near the end: a looser tolerance (1e-6 m) and more iterations
    scfg = SolverConfig() if model == 'se3' else SolverConfig(model=model, max_iterations=50,
                                                                tolerance=1e-6)
    res = solve(sc.network(nm.z, nm.cov), T0, scfg)
    return SyntheticRun(position_errors(T0, sc.T_world_node),
                        position_errors(res.T_world_node, sc.T_world_node), res.converged,
                        res.iterations, res.n_equations, res.n_observations, res.n_unknowns)


@dataclass
class Table1Result:
    rows: list[dict]
    improvement_pct: dict[str, dict[str, float]]
    profiles: dict[str, dict[str, FloatArray]] = field(default_factory=dict)
    paper_model: list[dict] = field(default_factory=list)


def noise_key(percent: float) -> str:
    """JSON key of a noise level: ``'10'`` for 10.0, ``'2.5'`` for 2.5."""
    return f'{percent:g}'


def table1(cfg: ReproduceConfig) -> Table1Result:
    """Table I and Fig. 5: mean position error of F2F and GA per trajectory and noise level."""
    rows: list[dict] = []
    improvement: dict[str, dict[str, float]] = {}
    profiles: dict[str, dict[str, FloatArray]] = {}
    paper_rows: list[dict] = []
    for name in cfg.trajectories:
        j = FAMILIES.index(name.split('_')[0])
        sc = synthetic_scenario(name)
        improvement[name] = {}
        for i, pct in enumerate(cfg.noise_levels):
            runs = [synthetic_run(sc, pct, run_rng(cfg.seed, EXP_TABLE1, j, i, r))
                    for r in range(cfg.runs)]
            f2f = np.array([r.f2f.mean() for r in runs])
            ga = np.array([r.ga.mean() for r in runs])
            imp = improvement_pct(float(f2f.mean()), float(ga.mean()))
            improvement[name][noise_key(pct)] = imp
            rows.append({
                'trajectory': name, 'noise_pct': pct, 'runs': cfg.runs,
                'nodes': sc.n_nodes, 'connections': sc.n_connections,
                'equations': runs[0].n_equations, 'observations': runs[0].n_observations,
                'unknowns': runs[0].n_unknowns,
                'paper_equations': 3 * sc.n_connections,
                'paper_observations': 6 * sc.n_connections,
                'paper_unknowns': 3 * (sc.n_nodes - 1),
                'f2f_mean_m': float(f2f.mean()), 'ga_mean_m': float(ga.mean()),
                'ga_std_m': float(ga.std()),
                'f2f_mse_m2': float(np.mean([np.mean(r.f2f ** 2) for r in runs])),
                'ga_mse_m2': float(np.mean([np.mean(r.ga ** 2) for r in runs])),
                'improvement_pct': imp,
                'converged': int(sum(r.converged for r in runs)),
                'mean_iterations': float(np.mean([r.iterations for r in runs])),
            })
            if pct == cfg.profile_noise:
                profiles[name] = {'f2f': np.mean([r.f2f for r in runs], axis=0),
                                  'ga': np.mean([r.ga for r in runs], axis=0)}
            if cfg.paper_model_runs:
                pr = [synthetic_run(sc, pct, run_rng(cfg.seed, EXP_PAPER_MODEL, j, i, r),
                                    model='paper') for r in range(cfg.paper_model_runs)]
                pf = float(np.mean([r.f2f.mean() for r in pr]))
                pg = float(np.mean([r.ga.mean() for r in pr]))
                paper_rows.append({
                    'trajectory': name, 'noise_pct': pct, 'runs': cfg.paper_model_runs,
                    'equations': pr[0].n_equations, 'observations': pr[0].n_observations,
                    'unknowns': pr[0].n_unknowns, 'f2f_mean_m': pf, 'ga_mean_m': pg,
                    'improvement_pct': improvement_pct(pf, pg),
                    'converged': int(sum(r.converged for r in pr)),
                })
    return Table1Result(rows, improvement, profiles, paper_rows)


@dataclass
class FutureTracksResult:
    """Fig. 2/3: mean change of the track-1 positions when track ``k`` is added."""

    tracks: list[int]
    absolute_m: dict[str, list[float]]
    normalised: dict[str, list[float]]
    n_nodes: int
    n_connections: int
    model: str = 'se3'


def future_tracks(cfg: ReproduceConfig, model: str = 'se3') -> FutureTracksResult:
    """Fig. 2/3 (Sec. IV and the Appendix, eq. Avii): how much adding track ``k`` moves the
    estimated track-1 positions.

    As in the paper's Appendix, the adjustment is linearised at the true poses, where the GA
    correction is a linear function of the observation noise: ``d = N^-1 A' P xi`` (se3 model,
    ``A`` the Jacobian of ``log(T_ij^-1 T_i^-1 T_j)`` w.r.t. the nodes, ``P`` the inverse noise
    covariance, first node fixed). For ``fig3_runs`` noise draws ``xi`` per level, the same draw
    is used for tracks ``1..k-1`` and ``1..k`` and the value at ``k`` is the mean over draws and
    track-1 nodes of ``|p_i(1..k) - p_i(1..k-1)|``; normalised by the largest (track 2).

    ``model='linear'`` does the same with positions only (``p_j - p_i = t``, translation noise
    only): no heading unknowns, hence no lever arm through which a new track's rotation noise
    moves distant nodes.
    """
    from scipy.sparse import coo_matrix

    sc_all = aerial_scenario(cfg.fig3_tracks, cfg.aerial_positions_per_swath)
    z_true = sc_all.true_motions()
    T_rel = se3.from_translation_rotvec(z_true[:, :3], z_true[:, 3:])
    if model == 'se3':
        dof = 6
        A_src = -se3.adjoint(se3.inverse(T_rel))
    elif model == 'linear':
        dof = 3
        A_src = -np.broadcast_to(np.eye(3), (len(z_true), 3, 3))
    else:
        raise ValueError(f'model must be se3 or linear, got {model!r}')
    sub = [sc_all.first_tracks(k) for k in range(1, cfg.fig3_tracks + 1)]
    track1 = sub[0].n_nodes
    levels = cfg.fig3_noise_levels
    runs = cfg.fig3_runs
    # d = N^-1 A' P xi does not change when P is scaled, so one factorisation per k serves every
    # noise level: P from the 1 % sigmas, xi drawn with each level's sigmas.
    sig1 = NoiseModel(1.0, sc_all.depth_m).sigmas(z_true)[:, :dof]
    xi = np.concatenate([run_rng(cfg.seed, EXP_FUTURE, i).standard_normal((runs,) + sig1.shape)
                         * sig1 * pct for i, pct in enumerate(levels)])  # (L runs, m, 6)
    prev = None
    changes = []
    for sc in sub:
        m, n = sc.n_connections, sc.n_nodes
        rows = np.arange(dof * m).reshape(m, dof)
        keep_s, keep_d = sc.src > 0, sc.dst > 0  # node 0 is fixed: it has no columns
        cols_s = dof * (sc.src - 1)[:, None] + np.arange(dof)
        cols_d = dof * (sc.dst - 1)[:, None] + np.arange(dof)
        r_idx = np.concatenate([np.repeat(rows[keep_s], dof, axis=1).ravel(),
                                rows[keep_d].ravel()])
        c_idx = np.concatenate([np.tile(cols_s[keep_s], (1, dof)).ravel(),
                                cols_d[keep_d].ravel()])
        vals = np.concatenate([A_src[:m][keep_s].ravel(), np.ones(dof * int(keep_d.sum()))])
        A = coo_matrix((vals, (r_idx, c_idx)), shape=(dof * m, dof * (n - 1))).tocsr()
        PA = A.multiply((1.0 / sig1[:m] ** 2).reshape(-1, 1)).tocsr()
        N = (A.T @ PA).tocsc()
        rhs = np.asarray(PA.T @ xi[:, :m].reshape(xi.shape[0], -1).T)  # (dof (n-1), L runs)
        d = _spd_solve(N, rhs)
        # track-1 positions (node 0 fixed): p_i moves by R_i rho_i, and |R_i rho_i| = |rho_i|
        rho = d.reshape(n - 1, dof, -1)[:track1 - 1, :3, :]
        if prev is not None:
            changes.append(np.linalg.norm(rho - prev, axis=1).sum(axis=0) / track1)
        prev = rho
    ch = np.array(changes).reshape(len(sub) - 1, len(levels), runs).mean(axis=2)
    absolute: dict[str, list[float]] = {}
    normalised: dict[str, list[float]] = {}
    for i, pct in enumerate(levels):
        absolute[noise_key(pct)] = ch[:, i].tolist()
        normalised[noise_key(pct)] = (ch[:, i] / ch[:, i].max()).tolist()
    return FutureTracksResult(list(range(2, cfg.fig3_tracks + 1)), absolute, normalised,
                              sc_all.n_nodes, sc_all.n_connections, model)


def _spd_solve(N, rhs: FloatArray) -> FloatArray:
    """Solve ``N X = rhs`` for a sparse SPD ``N`` (CHOLMOD via cvxopt, else SuperLU)."""
    try:
        import cvxopt
        from cvxopt import cholmod
    except ImportError:  # pragma: no cover
        from scipy.sparse.linalg import splu

        return splu(N.tocsc(), permc_spec='MMD_AT_PLUS_A').solve(rhs)
    from scipy.sparse import tril

    L = tril(N, format='coo')
    M = cvxopt.spmatrix(L.data, L.row.astype(int).tolist(), L.col.astype(int).tolist(), N.shape)
    F = cholmod.symbolic(M, uplo='L')
    cholmod.numeric(M, F)
    B = cvxopt.matrix(np.asfortranarray(rhs, dtype=float))
    cholmod.solve(F, B)
    return np.array(B)


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


def _run_aligner(sc: Scenario, z: FloatArray, cov: FloatArray, policy: str, window: int,
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
    batch = _batch_solve(net, f2f)
    batch_s = time.perf_counter() - t0

    def ates(T):
        return _ates(T, T_true)

    summary: dict = {
        'nodes': sc.n_nodes, 'connections': sc.n_connections,
        'cross_connections': int((~sc.consecutive).sum()), 'tracks': sc.n_tracks,
        'se3': {'equations': batch.n_equations, 'observations': batch.n_observations,
                'unknowns': batch.n_unknowns},
        'paper_model_counts': {'equations': 3 * sc.n_connections,
                               'observations': 6 * sc.n_connections,
                               'unknowns': 3 * (sc.n_nodes - 1)},
        'f2f': ates(f2f), 'batch': {**ates(batch.T_world_node), 'seconds': batch_s,
                                    'iterations': batch.iterations,
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
        wanted = {t - 1 for t in cfg.fig8_tracks if 1 <= t <= sc.n_tracks}
        for policy in cfg.policies:
            out = _run_aligner(sc, z, cov, policy, cfg.window_tracks,
                               wanted if policy == cfg.policies[0] else set(), f2f)
            ms = np.array([u.update_ms for u in out['updates']])
            w = ates(out['path'])
            summary['policies'][policy] = {
                'window': w, 'refined': ates(out['refined']), **_gaps_pct(w, summary['batch']),
                'update_ms': {'p50': float(np.percentile(ms, 50)),
                              'p95': float(np.percentile(ms, 95)), 'max': float(ms.max())},
                'finish_track_wall_ms_max': float(max(out['wall_ms'])),
                'updates': len(out['updates']), 'run_s': out['run_s'],
                'refine_s': out['refine_s'],
                'converged_updates': int(sum(bool(u.converged) for u in out['updates'])),
                'outliers': int(sum(int(u.n_outliers) for u in out['updates'])),
                'rejected_measurements': out['rejected'],
            }
            errors[f'window_{policy}'] = position_errors(out['path'], T_true)
            paths[f'window_{policy}'] = out['path']
            errors[f'refined_{policy}'] = position_errors(out['refined'], T_true)
            if out['snapshots']:
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
    return AerialResult(summary, errors, fig8, sc.track_ids, paths, T_true, qrep,
                        sc.consecutive)


def _batch_solve(net, f2f: FloatArray):
    """The batch GA of a survey's network from its F2F path (the reference of every gap)."""
    return solve(net, f2f, SolverConfig(tolerance=1e-7))


def _ates(T: FloatArray, T_true: FloatArray) -> dict[str, float]:
    """ATE (m) raw (first pose anchored), rigidly aligned, and the mean position error."""
    return {'raw_rmse_m': ate(T, T_true, 'first').rmse,
            'aligned_rmse_m': ate(T, T_true, 'rigid').rmse,
            'mean_error_m': float(position_errors(T, T_true).mean())}


def _gaps_pct(window: dict[str, float], batch: dict[str, float]) -> dict[str, float]:
    """Gap to batch (%) of an estimate's ATEs (from :func:`_ates`): ``100 (window / batch - 1)``,
    raw and rigidly aligned."""
    return {'gap_aligned_pct': 100.0 * (window['aligned_rmse_m'] / batch['aligned_rmse_m'] - 1),
            'gap_raw_pct': 100.0 * (window['raw_rmse_m'] / batch['raw_rmse_m'] - 1.0)}


def policy_gaps(cfg: ReproduceConfig, sc: Scenario, z: FloatArray,
                cov: FloatArray) -> dict[str, dict[str, float]]:
    """Gap to batch (%) at the end of the survey of every policy of ``cfg.policies`` on one
    noise draw: the measured motions ``z`` (m, 6) with covariances ``cov`` (m, 6, 6) fed track by
    track into the window (no snapshots, no final refinement), against the batch GA of the same
    motions. The same numbers as :func:`survey_window`'s ``gap_raw_pct`` / ``gap_aligned_pct``,
    without the rest of its figures. A policy with the background refinement runs it inline
    (``'<policy>+inline'``): the same path bit for bit as the other executors (the hand-off
    depends on track counts only), without a worker process started per draw. Keys per
    policy: ``raw``, ``aligned`` (%)."""
    f2f = sc.f2f(z)
    b = _ates(_batch_solve(sc.network(z, cov), f2f).T_world_node, sc.T_world_node)
    out = {}
    for policy in cfg.policies:
        base, _, executor = policy.partition('+')
        run_as = f'{base}+inline' if executor else base
        path = _run_aligner(sc, z, cov, run_as, cfg.window_tracks, set(), f2f,
                            final_refine=False)['path']
        g = _gaps_pct(_ates(path, sc.T_world_node), b)
        out[policy] = {'raw': g['gap_raw_pct'], 'aligned': g['gap_aligned_pct']}
    return out


@dataclass(frozen=True)
class PairedDifference:
    """Paired difference ``d_r = x_r - ref_r`` of two methods on the same ``n`` draws.

    Attributes
    ----------
    n : number of draws.
    mean, sd : mean and sample standard deviation (``ddof=1``; NaN for ``n = 1``) of ``d``,
        in the unit of ``x`` (here percentage points of gap to batch).
    ci_low, ci_high : two-sided Student-t confidence interval of the mean difference,
        ``mean -+ t(1/2 + confidence/2, n - 1) sd / sqrt(n)`` (NaN for ``n = 1``).
    confidence : level of the interval (0.95: 95 %).
    """

    n: int
    mean: float
    sd: float
    ci_low: float
    ci_high: float
    confidence: float

    @property
    def worse(self) -> bool:
        """``x`` is significantly larger than ``ref`` (the whole interval above 0)."""
        return bool(self.ci_low > 0.0)

    @property
    def better(self) -> bool:
        """``x`` is significantly smaller than ``ref`` (the whole interval below 0)."""
        return bool(self.ci_high < 0.0)


def paired_difference(x: FloatArray, ref: FloatArray,
                      confidence: float = 0.95) -> PairedDifference:
    """Mean, sd and t confidence interval of ``x - ref`` over paired draws (same noise draw in
    ``x[r]`` and ``ref[r]``): the draw's own difficulty, shared by both, cancels.

    Parameters
    ----------
    x, ref : (n,) finite values of the two methods, draw by draw.
    confidence : two-sided level of the interval, in (0, 1).

    Raises
    ------
    InputError : shapes differ, no draw, a non-finite value, or ``confidence`` outside (0, 1).
    """
    from scipy.stats import t as student_t

    x, ref = np.asarray(x, dtype=float), np.asarray(ref, dtype=float)
    if x.shape != ref.shape or x.ndim != 1 or x.size == 0:
        raise InputError(f'paired values must be two (n,) arrays, n >= 1; got {x.shape} and '
                         f'{ref.shape}')
    if not (np.isfinite(x).all() and np.isfinite(ref).all()):
        raise InputError('paired values must be finite; drop the failed draws first')
    if not 0.0 < confidence < 1.0:
        raise InputError(f'confidence must be in (0, 1), got {confidence}')
    d = x - ref
    n = d.size
    if n < 2:
        nan = float('nan')
        return PairedDifference(1, float(d[0]), nan, nan, nan, confidence)
    sd = float(d.std(ddof=1))
    half = float(student_t.ppf(0.5 + confidence / 2, n - 1)) * sd / np.sqrt(n)
    mean = float(d.mean())
    return PairedDifference(n, mean, sd, mean - half, mean + half, confidence)


def policy_statistics(gaps: dict[str, dict[str, list[float]]], reference: str,
                      confidence: float = 0.95) -> dict:
    """Multi-draw comparison of freeze policies (issue 15: "no policy worse than weighted").

    Parameters
    ----------
    gaps : per policy, ``{'raw': [...], 'aligned': [...]}``: the gap to batch (%) on each noise
        draw, the draws in the same order for every policy.
    reference : the policy the others are compared with (a key of ``gaps``).
    confidence : level of the paired intervals.

    Returns
    -------
    JSON-ready dict: ``reference``, ``confidence``, ``n`` (draws), ``policies`` (per policy:
    ``raw`` / ``aligned`` with the per-draw ``values``, their ``mean`` and ``sd``; and for every
    policy but the reference ``vs_reference``: per metric the :class:`PairedDifference` fields,
    ``worse`` and ``better``; ``worse``: either metric significantly worse) and ``worse`` (the
    policies significantly worse than the reference on either metric).
    """
    if reference not in gaps:
        raise InputError(f'reference policy {reference!r} is not among {sorted(gaps)}')
    ref = gaps[reference]
    out: dict = {'reference': reference, 'confidence': confidence,
                 'n': len(ref['raw']), 'policies': {}, 'worse': []}
    for policy, g in gaps.items():
        row: dict = {}
        for metric in ('raw', 'aligned'):
            v = np.asarray(g[metric], dtype=float)
            row[metric] = {'values': v.tolist(), 'mean': float(v.mean()),
                           'sd': float(v.std(ddof=1)) if v.size > 1 else float('nan')}
        if policy != reference:
            vs = {}
            for metric in ('raw', 'aligned'):
                d = paired_difference(g[metric], ref[metric], confidence)
                vs[metric] = {**asdict(d), 'worse': d.worse, 'better': d.better}
            vs['worse'] = vs['raw']['worse'] or vs['aligned']['worse']
            row['vs_reference'] = vs
            if vs['worse']:
                out['worse'].append(policy)
        out['policies'][policy] = row
    return out


def policy_seeds(cfg: ReproduceConfig, first: AerialResult | None = None, log=None) -> dict:
    """The freeze policies on ``cfg.policy_seeds`` independent noise draws of the aerial survey
    (draw ``r`` from ``run_rng(cfg.seed, EXP_AERIAL, r)``; draw 0 is the one of
    :func:`aerial_window`, whose gaps are taken from ``first`` when given), with
    :func:`policy_statistics` against ``'weighted'`` (else the first policy).

    Returns
    -------
    JSON-ready dict: ``available`` (False without the window aligner or policies), ``draws``
    (the ``r`` keys), ``tracks``, ``noise_pct``, ``seconds`` and the keys of
    :func:`policy_statistics`.
    """
    if not window_available() or not cfg.policies:
        return {'available': False}
    say = log or (lambda s: None)
    t0 = time.perf_counter()
    sc = aerial_scenario(cfg.aerial_tracks, cfg.aerial_positions_per_swath)
    gaps: dict[str, dict[str, list[float]]] = {p: {'raw': [], 'aligned': []}
                                               for p in cfg.policies}
    for r in range(cfg.policy_seeds):
        if r == 0 and first is not None:
            pol = {p: {'raw': v['gap_raw_pct'], 'aligned': v['gap_aligned_pct']}
                   for p, v in first.summary['policies'].items()}
        else:
            say(f'  policy comparison: noise draw {r + 1}/{cfg.policy_seeds}')
            nm = perturb(sc.true_motions(), NoiseModel(cfg.aerial_noise, sc.depth_m),
                         run_rng(cfg.seed, EXP_AERIAL, r))
            pol = policy_gaps(cfg, sc, nm.z, nm.cov)
        for p in cfg.policies:
            gaps[p]['raw'].append(pol[p]['raw'])
            gaps[p]['aligned'].append(pol[p]['aligned'])
    reference = 'weighted' if 'weighted' in cfg.policies else cfg.policies[0]
    stats = policy_statistics(gaps, reference)
    return {'available': True, 'draws': list(range(cfg.policy_seeds)),
            'tracks': cfg.aerial_tracks, 'noise_pct': cfg.aerial_noise,
            'seconds': time.perf_counter() - t0, **stats}


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


def memory_profile(cfg: ReproduceConfig) -> dict:
    """Peak traced memory (tracemalloc) of each track update for two survey sizes, and the
    memory retained by the aligner at the end (which holds the whole path, so it grows)."""
    if not window_available():
        return {'available': False}
    from ga_ros.core.window import AlignerConfig, TrackWindowAligner

    out: dict = {'available': True, 'sizes': {}}
    for n_tracks in cfg.memory_tracks:
        sc = aerial_scenario(n_tracks, cfg.aerial_positions_per_swath)
        nm = perturb(sc.true_motions(), NoiseModel(cfg.aerial_noise, sc.depth_m),
                     run_rng(cfg.seed, EXP_MEMORY, n_tracks))
        meas = sc.measurements(nm.z, nm.cov)
        tracemalloc.start()
        try:
            base = tracemalloc.get_traced_memory()[0]
            # the window update's own memory: without the background refinement (a batch of
            # the whole survey, whose memory grows with it by design)
            aligner = TrackWindowAligner(AlignerConfig(window_tracks=cfg.window_tracks,
                                                       refine_every_tracks=0),
                                         T_world_first=sc.T_world_node[0])
            peaks = []
            dst_track = np.array([m.dst_track for m in meas])
            bounds = np.searchsorted(dst_track, np.arange(n_tracks), side='right')
            start = 0
            for stop in bounds:
                for m in meas[start:stop]:
                    try:
                        aligner.add_measurement(m)
                    except GaError:
                        pass  # counted in the aligner's stats; memory is what is measured
                current = tracemalloc.get_traced_memory()[0]
                tracemalloc.reset_peak()
                aligner.finish_track()
                peaks.append(tracemalloc.get_traced_memory()[1] - current)
                start = stop
            retained = tracemalloc.get_traced_memory()[0] - base
        finally:
            tracemalloc.stop()
        full = peaks[min(cfg.window_tracks, len(peaks)) - 1:]  # updates with a full window
        out['sizes'][str(n_tracks)] = {
            'nodes': sc.n_nodes, 'connections': sc.n_connections,
            'full_window_updates': len(full),
            'update_peak_mib_full_window_mean': float(np.mean(full)) / 2**20,
            'update_peak_mib_max': float(max(peaks)) / 2**20,
            'retained_mib': float(retained) / 2**20}
    return out


def pose_error_profiles(T_est: FloatArray, T_true: FloatArray) -> dict[str, FloatArray]:
    """Errors along the trajectory (the paper's Fig. 9): ``position`` ``|p_est - p_true|`` (m),
    ``altitude`` ``z_est - z_true`` (m, world ``z`` up) and ``heading`` (rad), the world-``z``
    component of ``log(R_est R_true')`` (the rotation error about the vertical)."""
    R_err = T_est[:, :3, :3] @ np.swapaxes(T_true[:, :3, :3], 1, 2)
    return {'position': position_errors(T_est, T_true),
            'altitude': T_est[:, 2, 3] - T_true[:, 2, 3],
            'heading': so3.log(R_err)[:, 2]}


@dataclass
class StereoExperiment:
    """Experiment 2 from rendered stereo: the VO survey, its window / batch results and the
    Fig. 12 registrations."""

    survey: VoSurvey
    result: AerialResult
    summary: dict
    registrations: list[dict[str, Registration]]


def stereo_experiment(cfg: ReproduceConfig, out_dir: Path | None = None,
                      log=None) -> StereoExperiment:
    """The paper's experiment 2 as the paper ran it: motions (consecutive and cross-track) from
    rendered 320x240 stereo by our VO with its own covariances (:func:`render_vo_survey`,
    cached in ``out_dir``), then F2F, the track window (every policy of ``cfg.policies``) and
    batch GA (:func:`survey_window`), the VO's covariance consistency (NEES of the motions),
    and Fig. 12: images of neighbouring swaths registered with the relative motion of F2F, of
    the VO's own cross-track measurement, of the window, of the batch and of the truth."""
    scfg = StereoSurveyConfig(n_tracks=cfg.stereo_tracks,
                              positions_per_swath=cfg.stereo_positions_per_swath)
    cache = None if out_dir is None else Path(out_dir) / CACHE_NAME
    t0 = time.perf_counter()
    vs = render_vo_survey(scfg, cache, log)
    vo_s = time.perf_counter() - t0
    sc = vs.scenario()
    sub = replace(cfg, fig8_tracks=cfg.stereo_fig8_tracks)
    res = survey_window(sub, sc, vs.z, vs.cov)
    nees = vs.nees()
    summary = {
        'survey': {'tracks': scfg.n_tracks, 'positions_per_swath': scfg.positions_per_swath,
                   'step_m': scfg.step_m, 'image_size': f'{scfg.width}x{scfg.height}',
                   'median_depth_m': vs.depth_m, **vs.stats},
        'seconds_this_run': vo_s, 'cached': bool(cache is not None and vo_s < 0.5 * vs.stats[
            'seconds']['total']),
        'nees': nees, **res.summary}
    regs: list[dict[str, Registration]] = []
    f = vs.fig12
    first = f'window_{cfg.policies[0]}' if cfg.policies else 'batch'
    est = {'f2f': res.paths['f2f'], 'window': res.paths.get(first, res.paths['batch']),
           'batch': res.paths['batch'], 'truth': vs.T_true}
    rows = []
    for j, (a, b) in enumerate(zip(f.get('a', []), f.get('b', []))):
        a, b = int(a), int(b)
        h = f['plane'][j]
        reg: dict[str, Registration] = {}
        for name, T in est.items():
            H = ground_homography(vs.K, T[a], T[b], h)
            reg[name] = register_pair(f['img_a'][j], f['img_b'][j], H)
        k = int(np.nonzero((vs.src == a) & (vs.dst == b))[0][0])
        T_a = est['window'][a]
        T_b = T_a @ se3.from_translation_rotvec(vs.z[k, :3], vs.z[k, 3:])
        reg['measured'] = register_pair(f['img_a'][j], f['img_b'][j],
                                        ground_homography(vs.K, T_a, T_b, h))
        regs.append(reg)
        rows.append({'node_a': a, 'node_b': b, 'swath_a': int(vs.swath[a]),
                     'swath_b': int(vs.swath[b]),
                     'plane_height_m': float(f['plane_height_m'][j]),
                     'plane_slope_deg': float(np.degrees(np.arccos(np.clip(h[2], -1, 1)))),
                     **{f'{n}_{m}': getattr(r, m) for n, r in reg.items()
                        for m in ('overlap', 'mean_abs_diff', 'ncc')}})
    summary['fig12'] = rows
    return StereoExperiment(vs, res, summary, regs)


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
