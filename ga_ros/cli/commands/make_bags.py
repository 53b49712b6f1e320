"""``ga-ros make-bags``: regenerate the sample bags deterministically (seeded simulators)."""

from __future__ import annotations

import argparse
from pathlib import Path

from ga_ros.cli.commands import SUMMARIES
from ga_ros.replay.samples import make_sample_bags


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        'make-bags', help=SUMMARIES['make-bags'],
        description='Write the sample bags with the seeded simulators: aerial_measurements '
                    "(the paper's aerial scenario as measurements) and stereo_sample "
                    '(compressed stereo pairs); both carry ground truth on /ga/ground_truth.',
        allow_abbrev=False)
    p.add_argument('--out', type=Path, default=Path('bags'), help='output folder (default bags)')
    p.add_argument('which', nargs='*', choices=('measurements', 'stereo'),
                   default=['measurements', 'stereo'], help='which bags (default both)')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    for kind, path in make_sample_bags(args.out, tuple(args.which)).items():
        size = sum(f.stat().st_size for f in path.iterdir()) / 1e6
        print(f'{kind:<13} {path} ({size:.1f} MB)')
    return 0
