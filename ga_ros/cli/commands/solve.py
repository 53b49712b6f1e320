"""``ga-ros solve FILE.g2o --out OUT.g2o [--json]``: optimise a g2o pose graph.

The algorithms live in :mod:`ga_ros.pipeline.pose_graph`, one solve and its report in
:mod:`ga_ros.pipeline.solve_report`; this module parses and prints.
Batch mode (default) solves the whole graph with the mixed adjustment (``se3`` model, which
minimises the g2o/GTSAM cost ``sum e' Omega e``): Levenberg-Marquardt from the file's initial
guess, then undamped Gauss-Newton (Gauss-Helmert) iterations from the LM result, kept only if
they lower the cost. Track mode (``--tracks TRACKS.csv``) replays the graph track by track
through :class:`ga_ros.core.window.TrackWindowAligner`, as the live node would, and finishes
with its batch refinement.

The cost printed is always the independent evaluation :func:`ga_ros.io.g2o.graph_cost` of the
written vertices.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
import warnings

import numpy as np

from ga_ros.core.initialization import INIT_METHODS
from ga_ros.core.solver.losses import ROBUST_LOSSES
from ga_ros.io.g2o import InformationRepairWarning, PoseGraph, read_g2o
from ga_ros.pipeline.solve_report import SolveReport, SolveRequest, solve_report, write_solution
from ga_ros.runtime import keep_freed_memory


# --------------------------------------------------------------------------------------- CLI
def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        'solve', help='optimise a g2o pose graph (batch, or track by track)',
        description='Optimise a g2o pose graph (VERTEX_SE3:QUAT/EDGE_SE3:QUAT, VERTEX_SE2/'
                    'EDGE_SE2, PARAMS_*OFFSET, TORO VERTEX2/EDGE2) from its own initial guess '
                    '(or, for an edge-only file, from a chordal initialisation) and write the '
                    "result. The printed cost is sum e' Omega e over the edges (GTSAM's "
                    'between-factor error), with the a-posteriori variance factor and its '
                    'chi-square test at 95 %.')
    p.add_argument('input', help='g2o file')
    p.add_argument('--init', choices=('auto', 'file', *INIT_METHODS), default='auto',
                   help="initial guess: the file's vertices, odometry chaining, a minimum "
                   'spanning tree of the most certain edges, or chordal rotation-first '
                   "(Carlone et al. 2015); default auto: of the file's vertices and chordal, "
                   'the start with the lower cost (the output says which)')
    p.add_argument('--check-init', action='store_true',
                   help='batch: solve again from another initialisation (chordal; spanning tree '
                   'if chordal was used) and report whether it reaches a lower cost')
    p.add_argument('--strict', action='store_true',
                   help='refuse an information matrix that is not positive definite (default: '
                   'repair it to the nearest positive-definite one by eigenvalue clipping, '
                   'with one warning listing the lines)')
    p.add_argument('--out', '-o', help='write the optimised graph (all vertices) here')
    p.add_argument('--tum', help='also write the optimised vertices as a TUM trajectory '
                   '(timestamp = vertex id in seconds)')
    p.add_argument('--kitti', help='also write the optimised vertices as KITTI poses')
    p.add_argument('--json', action='store_true',
                   help='print one JSON object (cost, iterations, seconds, ...)')
    p.add_argument('--quality', action='store_true',
                   help="batch: Baarda's quality control of the solution (largest w-test "
                   'statistic and its edge, edges the w-test rejects, smallest redundancy '
                   'number, median minimal detectable bias); in the JSON under "quality"')
    p.add_argument('--alpha0', type=float, default=1e-3,
                   help='level of the w-test of --quality (default 0.001: |w| > 3.29)')
    p.add_argument('--tracks', help='CSV "node_id,track_id" (after a header): run track by track')
    p.add_argument('--window', type=int, default=5, help='tracks in the sliding window (track '
                   'mode; default 5)')
    p.add_argument('--robust', choices=ROBUST_LOSSES, default='none',
                   help='robust loss on the Mahalanobis misclosure (default none)')
    p.add_argument('--robust-scale', type=float, default=3.0,
                   help='Mahalanobis distance where the robust loss starts (default 3)')
    p.add_argument('--damping', choices=('dogleg', 'lm', 'none'),
                   help='batch default dogleg (at most one factorisation per iteration); lm: '
                   'Levenberg-Marquardt then Gauss-Newton; none: GN only '
                   '(track mode default none, as the live node)')
    p.add_argument('--max-iterations', type=int,
                   help='iteration cap (default 100 in batch, 10 per window update)')
    p.add_argument('--polish-iterations', type=int, default=30,
                   help='Gauss-Newton iterations after LM (batch; default 30)')
    p.add_argument('--tolerance', type=float,
                   help='stop on max correction below this (default 1e-8 batch, 1e-6 tracks)')
    p.add_argument('--outlier-prob', type=float, default=0.999,
                   help='track mode: chi-square gate on cross connections (0 disables)')
    p.add_argument('--no-refine', action='store_true',
                   help='track mode: skip the final batch refinement')
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ga_ros.safe_write import check_destinations

    check_destinations(*(p for p in (args.out, args.tum, args.kitti) if p))  # before the work
    if not args.tracks:
        keep_freed_memory()  # a one-shot batch process: its temporaries reuse the heap
    t_read = time.perf_counter()
    graph = _read(args)
    read_seconds = time.perf_counter() - t_read
    report = solve_report(graph, solve_request(args), name=args.input)
    write_solution(report, args.out, args.tum, args.kitti)
    summary = report.summary(str(args.input), args.out, read_seconds)
    if args.json:
        print(json.dumps(summary))
    else:
        _print_summary(report, summary, args)
    return 0


def solve_request(args: argparse.Namespace) -> SolveRequest:
    """The :class:`SolveRequest` of the parsed options."""
    return SolveRequest(init=args.init, tracks=args.tracks or '', window=args.window,
                        robust=args.robust, robust_scale=args.robust_scale,
                        damping=args.damping, max_iterations=args.max_iterations,
                        polish_iterations=args.polish_iterations, tolerance=args.tolerance,
                        outlier_prob=args.outlier_prob, refine=not args.no_refine,
                        check_init=args.check_init, quality=args.quality, alpha0=args.alpha0)


def _read(args: argparse.Namespace) -> PoseGraph:
    """The graph of ``args.input``; each information-matrix repair warning as one line."""
    with warnings.catch_warnings(record=True) as caught:  # one line each, not a traceback
        warnings.simplefilter('always', InformationRepairWarning)
        graph = read_g2o(args.input, strict=args.strict)
    for w in caught:
        print(f'ga-ros solve: warning: {w.message}', file=sys.stderr)
    return graph


def _print_summary(report: SolveReport, summary: dict, args: argparse.Namespace) -> None:
    """The text summary of a solve on stdout."""
    graph, result, guess, evidence = report.graph, report.result, report.guess, report.evidence
    print(f'{args.input}: {graph.dim}-D, {graph.n_vertices} vertices, {graph.n_edges} edges')
    print(f'initial cost {result.initial_cost:.10g} (init: {guess.method}'
          f'{_compared(guess.compared)})')
    print(f'final cost   {result.cost:.10g}')
    print(f'variance factor {evidence.variance_factor:.4g} (dof {evidence.dof}); chi-square '
          f'95 % [{evidence.chi2_lower:.6g}, {evidence.chi2_upper:.6g}]: '
          f'{evidence.chi2_test}')
    q = report.quality
    if q is not None:
        print(f"quality      max |w| {q['w_max']:.3g} on edge {q['w_max_src_id']}->"
              f"{q['w_max_dst_id']} (critical {q['w_critical']:.3g}); "
              f"{q['n_w_rejected']} edges rejected by the w-test; min redundancy number "
              f"{q['redundancy_number_min']:.3g}; median MDB {q['mdb_median_m']:.3g} m / "
              f"{np.degrees(q['mdb_median_rad']):.3g} deg ({q['seconds']:.2f} s)")
    if graph.repaired_lines:
        print(f'repaired     {len(graph.repaired_lines)} information matrices (not positive '
              f'definite)')
    if report.check is not None:
        verdict = ('LOWER: the solution above is a local minimum' if report.check.lower
                   else 'not lower')
        print(f'check-init   {report.check.method}: cost {report.check.cost:.10g} ({verdict})')
    if args.robust != 'none':
        print(f'robust ({args.robust}) objective {result.objective:.10g}')
    print(f'iterations   {result.iterations} ({result.reason})')
    if report.hint:
        print(f'hint         {report.hint}')
    print(f'time         {result.seconds:.3f} s')
    if result.per_track_ms is not None:
        ms = np.asarray(result.per_track_ms)
        print(f'tracks       {ms.size}, update ms: mean {ms.mean():.1f}, max {ms.max():.1f}')
        if summary['rejected']:
            print(f"rejected     {summary['rejected']} (dropped as the live node would)")
    if args.out:
        print(f'wrote {args.out}')


def _compared(compared: dict[str, float]) -> str:
    """The costs at the starts ``--init auto`` compared, for the printed summary."""
    others = [f'{m} {c:.6g}' for m, c in compared.items()]
    return f'; auto, costs at the starts: {", ".join(others)}' if len(others) > 1 else ''
