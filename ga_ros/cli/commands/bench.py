"""``ga-ros bench NAME [options]``: run a benchmark and print its figures.

Speed and memory targets are measured here, never in tests. Every benchmark has its own options
(``ga-ros bench NAME --help``); the list is :data:`ga_ros.cli.benchmarks.BENCHMARKS`.
"""

from __future__ import annotations

import argparse
import importlib

from ga_ros.cli.benchmarks import BENCHMARKS
from ga_ros.cli.commands import SUMMARIES


def register(sub) -> None:
    listing = '\n'.join(f'  {name:18s} {b.summary}' for name, b in BENCHMARKS.items())
    p = sub.add_parser('bench', help=SUMMARIES['bench'],
                       description=f'{__doc__}\nbenchmarks:\n{listing}',
                       formatter_class=argparse.RawDescriptionHelpFormatter, allow_abbrev=False)
    p.add_argument('target', choices=sorted(BENCHMARKS), metavar='NAME',
                   help='the benchmark (see the list above)')
    p.add_argument('options', nargs=argparse.REMAINDER,
                   help="the benchmark's own options (ga-ros bench NAME --help)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Import the benchmark named by ``args.target`` and call its ``main(options)``."""
    module, function = BENCHMARKS[args.target].entry.split(':')
    return int(getattr(importlib.import_module(module), function)(args.options) or 0)
