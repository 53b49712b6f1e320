"""``ga-ros bench solve`` and ``ga-ros bench window``: the estimator on the aerial survey.

``solve``: the batch solve of the paper's aerial survey (``--tracks`` double tracks, ``--noise``
percent of the true motion). ``window``: the same survey aligned track by track
(:class:`~ga_ros.core.window.TrackWindowAligner`), with the batch solution for the ATE gap and
GTSAM's IncrementalFixedLagSmoother in the same run when GTSAM is installed
(``pip install -r requirements-bench.txt``).
"""

from __future__ import annotations

import argparse
import json

from ga_ros.core.window import FREEZE_POLICIES


def build_parser(target: str) -> argparse.ArgumentParser:
    """The parser of ``ga-ros bench solve`` / ``ga-ros bench window``."""
    p = argparse.ArgumentParser(prog=f'ga-ros bench {target}', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument('--json', action='store_true', help='print one JSON object')
    p.add_argument('--tracks', type=int, default=25, help='double tracks in the survey (25)')
    p.add_argument('--noise', type=float, default=5.0, help='noise, %% of the true motion (5)')
    p.add_argument('--seed', type=int, default=0)
    if target == 'window':
        p.add_argument('--policy', choices=tuple(FREEZE_POLICIES), default='weighted')
        p.add_argument('--window', type=int, default=5, help='tracks in the window (5)')
        p.add_argument('--no-batch', action='store_true',
                       help='skip the batch solution (and the ATE gap) for long surveys')
        p.add_argument('--refine-every', type=int, default=None,
                       help='background refinement every N tracks (0: the plain window; '
                       'default: the aligner default)')
        p.add_argument('--no-gtsam', action='store_true',
                       help='skip the GTSAM IncrementalFixedLagSmoother comparison')
    return p


def stage_table(fig) -> list[str]:
    """The lines of ``bench window``'s stage table: CPU ms per track by stage, on the update
    call's thread and in the background, means over the tracks with a full window."""
    st = fig.stage_cpu_ms or {}
    end, bg = st.get('track end', {}), st.get('background', {})
    out = [f'  CPU ms per track by stage (mean over the {fig.full_window_tracks} tracks with a '
           'full window; track end: the update call and the outputs, on its thread; '
           'background: every other thread):',
           f'    {"stage":<18}{"track end":>10}{"background":>12}{"both":>8}']
    for k in end:
        out.append(f'    {k:<18}{end[k]:>10.1f}{bg.get(k, 0.0):>12.1f}'
                   f'{end[k] + bg.get(k, 0.0):>8.1f}')
    a, b = sum(end.values()), sum(bg.values())
    out.append(f'    {"total":<18}{a:>10.1f}{b:>12.1f}{a + b:>8.1f}')
    return out + work_table(fig)


def work_table(fig) -> list[str]:
    """The lines of ``bench window``'s work table: linearisations, gradient passes, costs and
    factorisations per track by part (:func:`ga_ros.bench.stages.counted_work`), means over
    the tracks with a full window."""
    from ga_ros.bench.stages import WORK_KINDS, WORK_PARTS

    work = fig.work_per_track or {}
    if not work:
        return []
    out = ['  work per track (the same means; linearisations: N and gradient assembled, '
           'gradients: a gradient pass without N, costs: a cost evaluated alone, '
           "factorisations: numeric sparse Cholesky; a worker process's not seen):",
           f'    {"part":<18}' + ''.join(f'{k:>16}' for k in WORK_KINDS)]
    for part in [*WORK_PARTS, 'other']:
        if any(f'{part} {k}' in work for k in WORK_KINDS):
            out.append(f'    {part:<18}' + ''.join(f'{work.get(f"{part} {k}", 0.0):>16.2f}'
                                                    for k in WORK_KINDS))
    return out


def main_solve(argv: list[str] | None = None) -> int:
    """``ga-ros bench solve [options]``."""
    return _run('solve', build_parser('solve').parse_args(argv))


def main_window(argv: list[str] | None = None) -> int:
    """``ga-ros bench window [options]``."""
    return _run('window', build_parser('window').parse_args(argv))


def _run(target: str, args: argparse.Namespace) -> int:
    from ga_ros.bench import core
    if target == 'solve':
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
                 f'  refinement every {fig.refine_every_tracks} tracks (0: off); a measurement '
                 f'that ends no track: {fig.measurement_cpu_us:.0f} us CPU',
                 f'  CPU per track, p50: update call {fig.per_track_cpu_ms_p50:.0f} ms (its '
                 f'thread), background {fig.background_cpu_ms_p50:.0f} ms (every other thread '
                 f'and process), total with the outputs {fig.total_cpu_ms_p50:.0f} ms (p95 '
                 f'{fig.total_cpu_ms_p95:.0f})',
                 *stage_table(fig)]
        if fig.gtsam_ms_p50 == fig.gtsam_ms_p50:  # not NaN: GTSAM ran
            lines += [f'  GTSAM IncrementalFixedLagSmoother (same survey, lag '
                      f'{fig.window_tracks} tracks): update p50 {fig.gtsam_ms_p50:.0f} ms, p95 '
                      f'{fig.gtsam_ms_p95:.0f} ms (CPU p50 {fig.gtsam_cpu_ms_p50:.0f} ms, p95 '
                      f'{fig.gtsam_cpu_ms_p95:.0f} ms), ATE rigid-aligned '
                      f'{fig.gtsam_ate_rigid_m:.3f} m',
                      f'  ga-ros / GTSAM, p50: update call wall '
                      f'{fig.per_track_ms_p50 / fig.gtsam_ms_p50:.2f}, CPU '
                      f'{fig.per_track_cpu_ms_p50 / fig.gtsam_cpu_ms_p50:.2f} (latency); total '
                      f'CPU per track (update call, outputs, background) '
                      f'{fig.total_cpu_ms_p50 / fig.gtsam_cpu_ms_p50:.2f}']
        elif not args.no_gtsam:
            lines.append('  (GTSAM not installed: pip install -r requirements-bench.txt for the '
                         'IncrementalFixedLagSmoother comparison)')
    if args.json:
        print(json.dumps(core.as_dict(fig)))
    else:
        print('\n'.join(lines))
    return 0
