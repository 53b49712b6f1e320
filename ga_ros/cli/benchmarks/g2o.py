"""``ga-ros bench g2o``: solve every public pose graph and print a Markdown table.

For each ``*.g2o`` in the data directory (default :data:`ga_ros.bench.data.POSE_GRAPHS`):
vertices, edges, initial cost, our final cost (:func:`ga_ros.io.g2o.graph_cost` of the optimised
vertices), the GTSAM reference optimum and its time from the directory's
``README.md``, the relative gap, solver iterations and wall time (file reading excluded).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
import time
from pathlib import Path

from ga_ros.bench.data import POSE_GRAPHS
from ga_ros.errors import GaError, InputError
from ga_ros.io.g2o import read_g2o
from ga_ros.pipeline.pose_graph import GraphSolveConfig, initial_guess, solve_graph

DEFAULT_DATA = POSE_GRAPHS

#: fallback (initial cost, GTSAM optimum, GTSAM seconds) if the data README cannot be parsed
REFERENCE = {
    'tinyGrid3D': (286.64, 18.6278, 0.001),
    'smallGrid3D': (167788.67, 1035.851, 0.03),
    'parking-garage': (16727.20, 1.26838, 0.36),
    'sphere2500': (2611315.4, 1351.402, 0.48),
    'torus3D': (4801230.3, 59900.01, 36.8),
    'intel': (553.996, 45.0042, 0.05),
    'input_M3500_g2o': (2634712.5, 137.915, 0.49),
}


def read_reference(data_dir: Path) -> dict[str, tuple[float, float, float]]:
    """``{name: (initial cost, optimum, seconds)}`` from the table in ``data_dir/../README.md``
    (or ``data_dir/README.md``); rows look like ``| name [(2-D)] | 1,234.5 | 12.3 | 0.4 s |``."""
    table = dict(REFERENCE)
    for readme in (data_dir / 'README.md', data_dir.parent / 'README.md'):
        if not readme.is_file():
            continue
        for line in readme.read_text().splitlines():
            cells = [c.strip() for c in line.strip().strip('|').split('|')]
            if len(cells) != 4:
                continue
            name = re.sub(r'\s*\(.*\)$', '', cells[0])
            try:
                values = [float(re.sub(r'[,\ss]', '', c)) for c in cells[1:]]
            except ValueError:
                continue
            table[name] = (values[0], values[1], values[2])
    return table


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``ga-ros bench g2o``."""
    p = argparse.ArgumentParser(
        prog='ga-ros bench g2o',
        description='Solve each g2o file from its own initial guess and print a Markdown table '
                    'comparing the final cost with the GTSAM reference optimum.',
        allow_abbrev=False)
    p.add_argument('--data', type=Path, default=DEFAULT_DATA,
                   help=f'directory of *.g2o files (default {DEFAULT_DATA})')
    p.add_argument('--only', nargs='+', metavar='NAME', help='datasets to run (file stems)')
    p.add_argument('--skip', nargs='+', metavar='NAME', default=[], help='datasets to skip')
    p.add_argument('--max-iterations', type=int, default=100)
    p.add_argument('--polish-iterations', type=int, default=30)
    p.add_argument('--json', action='store_true', help='also print one JSON line per dataset')
    p.add_argument('--init', default='file', help="initial guess: file (default), odometry, "
                   "spanning-tree or chordal (its time is added to the solver's)")
    return p


def run(args: argparse.Namespace) -> int:
    data = Path(args.data)
    files = sorted(data.glob('*.g2o'), key=lambda f: f.stat().st_size)
    if args.only:
        files = [f for f in files if f.stem in args.only]
    files = [f for f in files if f.stem not in args.skip]
    if not files:
        raise InputError(f'no matching *.g2o files in {data}')
    reference = read_reference(data)
    cfg = GraphSolveConfig.with_solver(polish_iterations=args.polish_iterations,
                                       max_iterations=args.max_iterations)
    print('| dataset | dim | nodes | edges | initial cost | our cost | reference | gap % '
          '| iterations | seconds | GTSAM s |')
    print('|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|')
    worst = 0
    for f in files:
        ref = reference.get(f.stem)
        t0 = time.perf_counter()
        try:
            graph = read_g2o(f)
            guess = initial_guess(graph, args.init)
            res = solve_graph(graph.with_initial_guess(guess.T_world_node), cfg)
            res.seconds += guess.seconds if guess.method != 'file' else 0.0
        except GaError as exc:
            print(f'| {f.stem} | | | | | failed: {exc} | | | | {time.perf_counter() - t0:.2f} '
                  '| |')
            worst = 1
            continue
        gap = 100.0 * (res.cost - ref[1]) / ref[1] if ref else float('nan')
        cells = [f.stem, str(graph.dim), str(graph.n_vertices), str(graph.n_edges),
                 f'{res.initial_cost:,.2f}', f'{res.cost:,.7g}',
                 f'{ref[1]:,.7g}' if ref else '-', f'{gap:+.4f}' if ref else '-',
                 str(res.iterations), f'{res.seconds:.2f}', f'{ref[2]:g}' if ref else '-']
        print('| ' + ' | '.join(cells) + ' |', flush=True)
        if args.json:
            print(json.dumps({'dataset': f.stem, 'cost': res.cost, 'reference': ref and ref[1],
                              'gap_percent': gap, 'iterations': res.iterations,
                              'seconds': res.seconds, 'converged': res.converged,
                              'reason': res.reason, 'stages': res.stages}), file=sys.stderr)
    return worst


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench g2o [options]``."""
    return run(build_parser().parse_args(argv))
