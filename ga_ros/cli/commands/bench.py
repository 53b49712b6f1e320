"""``ga-ros bench``: the benchmarks, one entry point.

``ga-ros bench solve`` (batch solve of the aerial survey), ``ga-ros bench window`` (online
track-by-track alignment), ``ga-ros bench compare`` (ga-ros against GTSAM in the same run: the
aerial survey at 10 % noise and the shared pose graphs, batch and track by track; GTSAM from
``pip install -r requirements-bench.txt``), ``ga-ros bench linalg`` (sparse Cholesky back ends
and orderings on the same normal matrices: GFlop, GFlop/s).
``ga-ros bench vo|g2o|node|replay [options]`` are aliases of the ``bench-vo``, ``bench-g2o``,
``bench-node`` and ``bench-replay`` commands (see ``main.py``).
"""

from __future__ import annotations

import argparse
import json


def register(sub) -> None:
    p = sub.add_parser('bench', help='run a benchmark and print its figures',
                       description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument('target', choices=('solve', 'window', 'compare', 'linalg'),
                   help='solve | window | compare | linalg (also: vo, g2o, node, replay, see '
                   'bench-*)')
    p.add_argument('--json', action='store_true', help='print one JSON object')
    p.add_argument('--tracks', type=int, default=25, help='double tracks in the survey (25)')
    p.add_argument('--noise', type=float, default=5.0, help='noise, %% of the true motion (5)')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--policy', choices=('weighted', 'marginal'), default='weighted')
    p.add_argument('--window', type=int, default=5, help='tracks in the window (5)')
    p.add_argument('--no-batch', action='store_true',
                   help='window: skip the batch solution (and the ATE gap) for long surveys')
    p.add_argument('--refine-every', type=int, default=None,
                   help='window: background refinement every N tracks (0: the plain window; '
                   'default: the aligner default)')
    p.add_argument('--no-gtsam', action='store_true',
                   help='window: skip the GTSAM IncrementalFixedLagSmoother comparison')
    p.add_argument('--data', type=str, default=None,
                   help='compare: directory of pose graphs (default ../shared/data/pose-graphs)')
    p.add_argument('--no-tracks', action='store_true', help='compare: batch rows only')
    p.add_argument('--repeat', type=int, default=None,
                   help='compare: each graph N times, each time column its minimum (1); '
                   'linalg: factorisations per matrix and back end (5)')
    p.set_defaults(func=run)


def run(args) -> int:
    if args.target == 'compare':
        from ga_ros.bench import compare
        return compare.main(['--window', str(args.window)] + (['--json'] if args.json else [])
                            + (['--no-tracks'] if args.no_tracks else [])
                            + ['--repeat', str(args.repeat or 1)]
                            + (['--data', args.data] if args.data else []))
    if args.target == 'linalg':
        from ga_ros.bench import linalg
        return linalg.main((['--json'] if args.json else [])
                           + (['--repeat', str(args.repeat)] if args.repeat else []))
    from ga_ros.bench import core
    if args.target == 'solve':
        fig = core.bench_batch(args.tracks, args.noise, args.seed)
        lines = [f'batch solve of the aerial survey: {fig.nodes} poses, {fig.connections} '
                 f'connections',
                 f'  equations {fig.equations}, observations {fig.observations}, unknowns '
                 f'{fig.unknowns}',
                 f'  iterations {fig.iterations} (converged: {fig.converged}, max step < '
                 f'{fig.tolerance:g} m/rad, cost {fig.cost:.4f}), '
                 f'time {fig.seconds:.2f} s, peak memory {fig.peak_rss_mb:.0f} MiB',
                 f'  ATE (first pose anchored): F2F {fig.f2f_ate_m:.2f} m, GA '
                 f'{fig.ga_ate_m:.2f} m']
    else:
        fig = core.bench_window(args.tracks, args.policy, args.window, args.noise, args.seed,
                                compare_batch=not args.no_batch, with_gtsam=not args.no_gtsam,
                                refine_every_tracks=args.refine_every)
        lines = [f'online alignment, {fig.tracks} tracks ({fig.nodes} poses, {fig.connections} '
                 f'connections), window {fig.window_tracks}, policy {fig.policy}',
                 f'  whole run {fig.total_seconds:.2f} s; per-track update p50 '
                 f'{fig.per_track_ms_p50:.0f} ms, p95 {fig.per_track_ms_p95:.0f} ms, max '
                 f'{fig.per_track_ms_max:.0f} ms (CPU p50 {fig.per_track_cpu_ms_p50:.0f} ms, p95 '
                 f'{fig.per_track_cpu_ms_p95:.0f} ms); peak memory {fig.peak_rss_mb:.0f} MiB',
                 f'  ATE rigid-aligned: window {fig.ate_rigid_window_m:.3f} m, batch '
                 f'{fig.ate_rigid_batch_m:.3f} m (gap {fig.gap_rigid_pct:+.1f} %)',
                 f'  ATE raw (first pose anchored): window {fig.ate_raw_window_m:.3f} m, batch '
                 f'{fig.ate_raw_batch_m:.3f} m (gap {fig.gap_raw_pct:+.1f} %)',
                 f'  refinement every {fig.refine_every_tracks} tracks (0: off); update CPU '
                 'ms p50 by part: ' + ', '.join(f'{k} {v:.0f}' for k, v in
                                                (fig.breakdown_cpu_ms_p50 or {}).items())
                 + f'; a measurement that ends no track: {fig.measurement_cpu_us:.0f} us CPU']
        if fig.gtsam_ms_p50 == fig.gtsam_ms_p50:  # not NaN: GTSAM ran
            lines += [f'  GTSAM IncrementalFixedLagSmoother (same survey, lag '
                      f'{fig.window_tracks} tracks): update p50 {fig.gtsam_ms_p50:.0f} ms, p95 '
                      f'{fig.gtsam_ms_p95:.0f} ms (CPU p50 {fig.gtsam_cpu_ms_p50:.0f} ms, p95 '
                      f'{fig.gtsam_cpu_ms_p95:.0f} ms), ATE rigid-aligned '
                      f'{fig.gtsam_ate_rigid_m:.3f} m',
                      f'  ga-ros / GTSAM update p50: wall '
                      f'{fig.per_track_ms_p50 / fig.gtsam_ms_p50:.2f}, CPU '
                      f'{fig.per_track_cpu_ms_p50 / fig.gtsam_cpu_ms_p50:.2f}']
        elif not args.no_gtsam:
            lines.append('  (GTSAM not installed: pip install -r requirements-bench.txt for the '
                         'IncrementalFixedLagSmoother comparison)')
    if args.json:
        print(json.dumps(core.as_dict(fig)))
    else:
        print('\n'.join(lines))
    return 0
