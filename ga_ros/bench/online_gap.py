"""Per-track gap between the online (track-window) estimate and the batch one.

For each freeze policy (and the background refinement), the aerial survey of the report is fed
track by track; after every track the corrected path is compared with a batch solve of the data
received so far (same connections, warm-started from the online path): ATE raw (first pose
anchored) and rigidly aligned, both against ground truth, as gap percentages
``100 (online / batch - 1)``. Prints one table row per track and a summary per policy.
With ``--seeds N`` the same on N noise draws, then per policy the mean and sd of the end gaps
and the paired difference with ``weighted`` (same draw) with its 95 % t interval: the
statistics of the report's multi-draw table (``ReproduceConfig.policy_seeds``).

    ga-ros bench online-gap --tracks 8 --policies weighted marginal
    ga-ros bench online-gap --tracks 8 --policies weighted marginal \
        --no-per-track --seeds 5
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ga_ros.bench.survey import add_survey_arguments, survey_noise
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.eval.metrics import ate
from ga_ros.report.experiments.policies import policy_statistics
from ga_ros.report.experiments.seeds import EXP_AERIAL, run_rng
from ga_ros.report.markdown.policies import policy_seeds_table
from ga_ros.report.markdown.targets import policy_target_row
from ga_ros.sim.aerial import aerial_scenario


def _policy_config(name: str, window: int, every: int, lag: int,
                   prior: dict | None = None) -> AlignerConfig:
    base, _, refine = name.partition('+')
    extra = {'refine_every_tracks': 0}
    if refine:
        extra = {'refine_every_tracks': every, 'refine_lag_tracks': lag,
                 'refine_executor': refine}
    return AlignerConfig(window_tracks=window, freeze_policy=base, **extra, **(prior or {}))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog='ga-ros bench online-gap', description=__doc__.splitlines()[0], allow_abbrev=False)
    add_survey_arguments(ap, tracks=8)
    ap.add_argument('--seed', type=int, default=20051101, help='master seed')
    ap.add_argument('--seeds', type=int, default=1,
                    help='noise draws r = 0..N-1 (run_rng(seed, 4, r), the draws of the report); '
                         "N > 1 prints the mean and sd of each policy's end gap and its paired "
                         'difference with weighted (95 %% t interval), as the report does')
    ap.add_argument('--policies', nargs='+', default=['weighted', 'marginal'],
                    help="freeze policies; 'weighted+process' (+thread, +inline): with refinement")
    ap.add_argument('--every', type=int, default=1, help='refine_every_tracks')
    ap.add_argument('--lag', type=int, default=1, help='refine_lag_tracks')
    ap.add_argument('--prior-band', type=int, default=None,
                    help='AlignerConfig.prior_band (default: the aligner default; -1 dense)')
    ap.add_argument('--prior-hubs', type=int, default=None, help='AlignerConfig.prior_hubs')
    ap.add_argument('--horizon', type=int, default=None,
                    help='AlignerConfig.refine_horizon_tracks (default: the aligner default)')
    ap.add_argument('--relinearize-sigma', type=float, default=None,
                    help='AlignerConfig.refine_relinearize_sigma (default: the aligner default; '
                         '0: a refinement at every trigger)')
    ap.add_argument('--no-per-track', action='store_true',
                    help='compare with batch at the end only (no batch solve per track)')
    args = ap.parse_args(argv)
    if args.seeds < 1:
        ap.error('--seeds must be >= 1')
    sc = aerial_scenario(args.tracks, args.positions)
    gaps: dict[str, dict[str, list[float]]] = {p: {'raw': [], 'aligned': []}
                                               for p in args.policies}
    for r in range(args.seeds):
        if args.seeds > 1:
            print(f'#### noise draw r = {r} (run_rng({args.seed}, {EXP_AERIAL}, {r}))')
        end = run_draw(args, sc, run_rng(args.seed, EXP_AERIAL, r))
        for name, (raw, aligned) in end.items():
            gaps[name]['raw'].append(raw)
            gaps[name]['aligned'].append(aligned)
    if args.seeds > 1:
        ref = 'weighted' if 'weighted' in args.policies else args.policies[0]
        stats = policy_statistics(gaps, ref)
        print(f'\n#### {args.seeds} noise draws, gap to batch at the end of the survey')
        print('\n'.join(policy_seeds_table({**stats, 'draws': list(range(args.seeds))})))
        row = policy_target_row(stats)
        print(f'\n{row[0]}: {"met" if row[2] else "NOT met"}; {row[1]}')
    return 0


def run_draw(args: argparse.Namespace, sc, rng: np.random.Generator) -> dict:
    """One noise draw: every policy of ``args.policies`` fed track by track, its gaps to batch
    printed (per track, or at the end with ``--no-per-track``). Returns per policy the end
    gaps ``(raw %, aligned %)``."""
    nm = survey_noise(sc, args.noise, rng)
    T_true = sc.T_world_node
    meas = sc.measurements(nm.z, nm.cov)
    dst_track = np.array([m.dst_track for m in meas])
    bounds = np.searchsorted(dst_track, np.unique(sc.track_ids), side='right')
    bcfg = SolverConfig(tolerance=1e-7)
    batch_cache: dict[int, np.ndarray] = {}

    def batch_upto(al: TrackWindowAligner, n: int) -> np.ndarray:
        if n not in batch_cache:
            src, dst, z, _, status = al.connection_arrays()
            cov = al.connection_covariances()
            keep = (status != 2) & (src < n) & (dst < n)
            net = ConnectionNetwork()
            for i in range(n):
                net.add_node(int(sc.node_ids[i]), int(sc.track_ids[i]))
            net.add_connections(src[keep], dst[keep], z[keep], cov[keep])
            T0 = al.corrected_path().T_world_node[:n]
            batch_cache[n] = solve(net, T0, bcfg, fixed=[int(sc.node_ids[0])]).T_world_node
        return batch_cache[n]

    def gaps(T, Tb, n):
        wr, wa = ate(T, T_true[:n], 'first').rmse, ate(T, T_true[:n], 'rigid').rmse
        br, ba = ate(Tb, T_true[:n], 'first').rmse, ate(Tb, T_true[:n], 'rigid').rmse
        return 100 * (wr / br - 1), 100 * (wa / ba - 1), br, ba

    end = {}
    for name in args.policies:
        prior = {k: v for k, v in (('prior_band', args.prior_band),
                                   ('prior_hubs', args.prior_hubs),
                                   ('refine_horizon_tracks', args.horizon),
                                   ('refine_relinearize_sigma', args.relinearize_sigma))
                 if v is not None}
        al = TrackWindowAligner(_policy_config(name, args.window, args.every, args.lag, prior),
                                T_world_first=T_true[0])
        start, ms, rows, own, wait, cpu = 0, [], [], [], [], []
        t_run = time.perf_counter()
        for k, stop in enumerate(bounds):
            for m in meas[start:stop]:
                al.add_measurement(m)
            t0, c0 = time.perf_counter(), time.process_time()
            up = al.finish_track()
            ms.append(1e3 * (time.perf_counter() - t0))
            cpu.append(1e3 * (time.process_time() - c0))
            own.append(up.update_ms - up.refine_wait_ms)
            wait.append(up.refine_wait_ms)
            start = stop
            n = len(al.corrected_path().node_ids)
            if not args.no_per_track or k == len(bounds) - 1:
                path = al.corrected_path()
                Tb = batch_upto(al, n)
                d = np.linalg.norm(path.T_world_node[:, :3, 3] - Tb[:, :3, 3], axis=1)
                fz = path.frozen
                dif = (np.sqrt(np.mean(d[fz] ** 2)) if fz.any() else 0.0,
                       np.sqrt(np.mean(d[~fz] ** 2)))
                rows.append((k, *gaps(path.T_world_node, Tb, n), *dif))
        run_s = time.perf_counter() - t_run
        al.close()
        print(f'== {name}: window {args.window}, {args.tracks} double tracks, '
              f'{args.noise:g} % noise; finish_track ms p50 {np.percentile(ms, 50):.0f} '
              f'p95 {np.percentile(ms, 95):.0f} max {max(ms):.0f} (update without the hand-off '
              f'p50 {np.percentile(own, 50):.0f} p95 {np.percentile(own, 95):.0f}; hand-off wait '
              f'+ install p50 {np.percentile(wait, 50):.0f} max {max(wait):.0f}); '
              f'CPU of this process p50 {np.percentile(cpu, 50):.0f} p95 '
              f'{np.percentile(cpu, 95):.0f}; run {run_s:.1f} s; {al.config.prior_band=}, '
              f'{al.config.prior_hubs=}')
        print(' track  gap_raw%  gap_aligned%  batch_raw_m  batch_aligned_m  to_batch_frozen_m'
              '  to_batch_window_m')
        for k, gr, ga, br, ba, df, dw in rows:
            print(f'{k:6d} {gr:9.1f} {ga:13.1f} {br:12.3f} {ba:16.3f} {df:18.3f} {dw:18.3f}')
        g = np.array([r[1:3] for r in rows])
        print(f'   end raw {g[-1, 0]:+.1f} % aligned {g[-1, 1]:+.1f} %; mean over tracks raw '
              f'{g[:, 0].mean():+.1f} % aligned {g[:, 1].mean():+.1f} %')
        end[name] = (float(g[-1, 0]), float(g[-1, 1]))
    return end

