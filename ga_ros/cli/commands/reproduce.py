"""``ga-ros reproduce``: run the paper's experiments and write a Markdown/PNG/JSON report."""

from __future__ import annotations

import argparse
import sys
from dataclasses import replace

from ga_ros.cli.commands import SUMMARIES


def register(subparsers) -> None:
    p = subparsers.add_parser(
        'reproduce', help=SUMMARIES['reproduce'],
        description="Run the paper's experiments (Table I, Fig. 2/3, 5, 7, 8, window vs batch, "
                    'quality control, experiment 2 from rendered stereo with Figs. 7-9 and 12, '
                    'wrong connections, timings, memory) and write DIR/report.md, '
                    'DIR/report.json and PNG plots.', allow_abbrev=False)
    p.add_argument('--out', required=True, help='output directory')
    p.add_argument('--quick', action='store_true',
                   help='reduced run (fewer runs, smaller surveys, same experiments)')
    p.add_argument('--preset', choices=('full', 'quick', 'tiny'), default=None,
                   help='full (default; 100 runs), quick (= --quick) or tiny (smoke test)')
    p.add_argument('--runs', type=int, default=None, help='Monte-Carlo runs per Table I cell')
    p.add_argument('--seed', type=int, default=None, help='master seed')
    p.add_argument('--aerial-tracks', type=int, default=None,
                   help='double tracks of the aerial survey (default 25)')
    p.add_argument('--stereo-tracks', type=int, default=None,
                   help='tracks of experiment 2 from rendered stereo (full: 25; 0 skips it)')
    p.add_argument('--policy-seeds', type=int, default=None,
                   help='noise draws on which the freeze policies are compared (full 10, quick 5)')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ga_ros.errors import InputError
    from ga_ros.report import preset, run_reproduction

    if args.quick and args.preset not in (None, 'quick'):
        raise InputError('--quick and --preset disagree')
    cfg = preset('quick' if args.quick else (args.preset or 'full'))
    changes = {}
    if args.runs is not None:
        changes['runs'] = args.runs
    if args.seed is not None:
        changes['seed'] = args.seed
    if args.aerial_tracks is not None:
        changes['aerial_tracks'] = args.aerial_tracks
    if args.stereo_tracks is not None:
        changes['stereo_tracks'] = args.stereo_tracks
    if args.policy_seeds is not None:
        changes['policy_seeds'] = args.policy_seeds
    if changes:
        cfg = replace(cfg, **changes)
    report = run_reproduction(cfg, args.out, log=lambda s: print(s, file=sys.stderr))
    print(f'wrote {args.out}/report.md, report.json and {len(report["images"])} PNGs '
          f'in {report["timings_s"]["total_s"]:.1f} s')
    return 0
