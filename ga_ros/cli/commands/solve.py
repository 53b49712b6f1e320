"""``ga-ros solve FILE.g2o --out OUT.g2o [--json]``: optimise a g2o pose graph.

The algorithms live in :mod:`ga_ros.pipeline.pose_graph`; this module parses and prints.
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
import dataclasses
import json
import sys
import time
import warnings

import numpy as np

from ga_ros.core.initialization import INIT_METHODS
from ga_ros.core.solver.losses import ROBUST_LOSSES
from ga_ros.errors import InputError
from ga_ros.io.g2o import InformationRepairWarning, PoseGraph, read_g2o, write_g2o
from ga_ros.pipeline.pose_graph import (
    GraphSolveConfig,
    GraphSolveResult,
    check_initialization,
    initial_guess,
    optimum_evidence,
    read_tracks,
    solve_graph,
    solve_tracks,
)
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
    from ga_ros.io.atomic import check_destinations

    check_destinations(*(p for p in (args.out, args.tum, args.kitti) if p))  # before the work
    if not args.tracks:
        keep_freed_memory()  # a one-shot batch process: its temporaries reuse the heap
    t_read = time.perf_counter()
    with warnings.catch_warnings(record=True) as caught:  # one line each, not a traceback
        warnings.simplefilter('always', InformationRepairWarning)
        graph = read_g2o(args.input, strict=args.strict)
    for w in caught:
        print(f'ga-ros solve: warning: {w.message}', file=sys.stderr)
    read_seconds = time.perf_counter() - t_read
    guess = initial_guess(graph, args.init)
    graph = graph.with_initial_guess(guess.T_world_node)
    initial = guess.cost  # graph_cost at the guess
    if not np.isfinite(initial):
        raise InputError(f'{args.input}: no final cost can be reached, the initial cost is '
                         f'{initial}: a vertex or edge holds an absurd value (e.g. 1e308); '
                         'fix the file. Nothing was written')
    if args.tracks:
        result = _run_tracks(graph, args)
    else:
        overrides = dict(damping=args.damping, max_iterations=args.max_iterations,
                         tolerance=args.tolerance)
        cfg = GraphSolveConfig.with_solver(
            polish_iterations=args.polish_iterations, robust_loss=args.robust,
            robust_scale=args.robust_scale, **{k: v for k, v in overrides.items() if v})
        result = solve_graph(graph, cfg, initial_cost=initial)
    if not np.isfinite(result.cost):
        raise InputError(f'{args.input}: the final cost is {result.cost} (initial '
                         f'{result.initial_cost}): a vertex or edge holds an absurd value (e.g. '
                         '1e308); fix the file. Nothing was written')
    evidence = optimum_evidence(graph, result.T_world_node, result.cost)
    check = None
    if args.check_init and not args.tracks:
        check = check_initialization(graph, result.cost, guess.method, cfg)
    if args.out:
        write_g2o(args.out, graph, result.T_world_node)
    if args.tum or args.kitti:  # imported here: start-up of a plain solve
        from ga_ros.io.trajectory import write_kitti, write_tum
    if args.tum:
        write_tum(args.tum, graph.vertex_ids * 1_000_000_000, result.T_world_node)
    if args.kitti:
        write_kitti(args.kitti, result.T_world_node)
    summary = {
        'file': str(args.input), 'mode': 'tracks' if args.tracks else 'batch',
        'dim': graph.dim, 'vertices': graph.n_vertices, 'edges': graph.n_edges,
        'initial_cost': result.initial_cost, 'cost': result.cost, 'objective': result.objective,
        'iterations': result.iterations, 'seconds': result.seconds,
        'read_seconds': read_seconds, 'converged': result.converged, 'reason': result.reason,
        'robust': args.robust, 'stages': result.stages, 'out': args.out,
        'init': guess.method, 'init_seconds': guess.seconds, 'init_compared': guess.compared,
        'termination': result.reason,
        'hint': _hint(result.reason, guess.method) if not args.tracks else None,
        'repaired_edges': len(graph.repaired_lines), 'repaired_lines': list(graph.repaired_lines),
        'dof': evidence.dof, 'variance_factor': evidence.variance_factor,
        'chi2_95': [evidence.chi2_lower, evidence.chi2_upper], 'chi2_test': evidence.chi2_test,
        'check_init': dataclasses.asdict(check) if check is not None else None,
    }
    if args.quality and not args.tracks:
        summary['quality'] = _quality(graph, result.T_world_node, args.alpha0)
    if result.per_track_ms is not None:
        summary['per_track_ms'] = result.per_track_ms
        summary['rejected'] = result.stages[0].get('rejected', {})
    if args.json:
        print(json.dumps(summary))
    else:
        out = sys.stdout
        print(f'{args.input}: {graph.dim}-D, {graph.n_vertices} vertices, {graph.n_edges} edges',
              file=out)
        print(f'initial cost {result.initial_cost:.10g} (init: {guess.method}'
              f'{_compared(guess.compared)})', file=out)
        print(f'final cost   {result.cost:.10g}', file=out)
        print(f'variance factor {evidence.variance_factor:.4g} (dof {evidence.dof}); chi-square '
              f'95 % [{evidence.chi2_lower:.6g}, {evidence.chi2_upper:.6g}]: '
              f'{evidence.chi2_test}', file=out)
        q = summary.get('quality')
        if q is not None:
            print(f"quality      max |w| {q['w_max']:.3g} on edge {q['w_max_src_id']}->"
                  f"{q['w_max_dst_id']} (critical {q['w_critical']:.3g}); "
                  f"{q['n_w_rejected']} edges rejected by the w-test; min redundancy number "
                  f"{q['redundancy_number_min']:.3g}; median MDB {q['mdb_median_m']:.3g} m / "
                  f"{np.degrees(q['mdb_median_rad']):.3g} deg ({q['seconds']:.2f} s)", file=out)
        if graph.repaired_lines:
            print(f'repaired     {len(graph.repaired_lines)} information matrices (not positive '
                  f'definite)', file=out)
        if check is not None:
            verdict = ('LOWER: the solution above is a local minimum' if check.lower
                       else 'not lower')
            print(f'check-init   {check.method}: cost {check.cost:.10g} ({verdict})', file=out)
        if args.robust != 'none':
            print(f'robust ({args.robust}) objective {result.objective:.10g}', file=out)
        print(f'iterations   {result.iterations} ({result.reason})', file=out)
        if summary['hint']:
            print(f"hint         {summary['hint']}", file=out)
        print(f'time         {result.seconds:.3f} s', file=out)
        if result.per_track_ms is not None:
            ms = np.asarray(result.per_track_ms)
            print(f'tracks       {ms.size}, update ms: mean {ms.mean():.1f}, max {ms.max():.1f}',
                  file=out)
            if summary['rejected']:
                print(f"rejected     {summary['rejected']} (dropped as the live node would)",
                      file=out)
        if args.out:
            print(f'wrote {args.out}', file=out)
    return 0


def _compared(compared: dict[str, float]) -> str:
    """The costs at the starts ``--init auto`` compared, for the printed summary."""
    others = [f'{m} {c:.6g}' for m, c in compared.items()]
    return f'; auto, costs at the starts: {", ".join(others)}' if len(others) > 1 else ''


def _hint(reason: str, init: str) -> str | None:
    """What to try when the solve stopped at the iteration cap (``None`` otherwise)."""
    if reason != 'max_iterations':
        return None
    also = '' if init == 'chordal' else ' or start elsewhere (--init chordal)'
    return ('stopped at the iteration cap before converging: the result may be short of the '
            f'optimum; raise --max-iterations{also}')


def _quality(graph: PoseGraph, T_world_node: np.ndarray, alpha0: float) -> dict:
    """Quality figures of the solution (:mod:`ga_ros.core.quality`), without those the summary
    already has (the variance factor and its chi-square test: ``variance_factor``, ``dof``)."""
    from ga_ros.core.quality import QualityConfig, checked_solve, summarise
    from ga_ros.pipeline.pose_graph import GRAPH_SOLVER

    t0 = time.perf_counter()
    # one Gauss-Newton step at the solution gives the residuals and N the tests need
    res = checked_solve(graph.network, T_world_node,
                        dataclasses.replace(GRAPH_SOLVER, damping='none', max_iterations=1),
                        fixed=list(graph.fixed) or None, config=QualityConfig(alpha0=alpha0))
    out = summarise(res.quality, graph.network, seconds=time.perf_counter() - t0).as_dict()
    for duplicate in ('sigma0_sq', 'redundancy', 'global_passed'):
        out.pop(duplicate)
    return out


def _run_tracks(graph: PoseGraph, args: argparse.Namespace) -> GraphSolveResult:
    tracks = read_tracks(args.tracks, graph.vertex_ids)
    return solve_tracks(graph, tracks, window=args.window, damping=args.damping or 'none',
                        robust_loss=args.robust, robust_scale=args.robust_scale,
                        outlier_chi2_prob=args.outlier_prob, refine=not args.no_refine,
                        max_iterations=args.max_iterations or 10,
                        tolerance=args.tolerance or 1e-6)
