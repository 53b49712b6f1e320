"""One ``ga-ros solve`` of a g2o pose graph and its report, ROS-free.

:func:`solve_report` chains the steps of :mod:`ga_ros.pipeline.pose_graph`: the initial guess
(``--init auto`` compares the file's vertices with chordal and keeps the start of lower cost),
the batch or track-by-track solve, the evidence of an optimum (variance factor and its
chi-square test), the optional second start (``--check-init``) and Baarda's quality figures;
:meth:`SolveReport.summary` is the command's JSON object. The command line only parses and
prints.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError
from ga_ros.io.g2o import PoseGraph, write_g2o
from ga_ros.pipeline.pose_graph import (
    GRAPH_SOLVER,
    GraphSolveConfig,
    GraphSolveResult,
    InitCheck,
    InitialGuess,
    OptimumEvidence,
    check_initialization,
    initial_guess,
    optimum_evidence,
    read_tracks,
    solve_graph,
    solve_tracks,
)


@dataclass(frozen=True)
class SolveRequest:
    """What to do with a graph (the options of ``ga-ros solve``).

    Attributes
    ----------
    init : initial guess: ``'auto'``, ``'file'`` or a method of
        :data:`ga_ros.core.initialization.INIT_METHODS`.
    tracks : CSV ``node_id,track_id`` (after a header): solve track by track; ``''``: batch.
    window : tracks in the sliding window (track mode).
    robust : robust loss on the Mahalanobis misclosure (``'none'``: least squares).
    robust_scale : Mahalanobis distance where the robust loss starts.
    damping : ``'dogleg'``, ``'lm'``, ``'none'`` or None (batch dogleg, track mode none).
    max_iterations : iteration cap, None = 100 in batch, 10 per window update.
    polish_iterations : Gauss-Newton iterations after LM (batch).
    tolerance : stop on max correction below this, None = 1e-8 batch, 1e-6 tracks.
    outlier_prob : track mode: chi-square gate quantile on cross connections (0 disables).
    refine : track mode: the final batch refinement.
    check_init : batch: solve again from another start and compare the costs.
    quality : batch: Baarda's quality control of the solution.
    alpha0 : level of the w-test of ``quality``.
    """

    init: str = 'auto'
    tracks: str = ''
    window: int = 5
    robust: str = 'none'
    robust_scale: float = 3.0
    damping: str | None = None
    max_iterations: int | None = None
    polish_iterations: int = 30
    tolerance: float | None = None
    outlier_prob: float = 0.999
    refine: bool = True
    check_init: bool = False
    quality: bool = False
    alpha0: float = 1e-3


@dataclass
class SolveReport:
    """Outcome of :func:`solve_report`.

    Attributes
    ----------
    graph : the graph with the initial guess used as its ``T_init``.
    guess : the initial guess (method, cost, the costs ``auto`` compared).
    result : the solve (batch or tracks).
    evidence : variance factor and chi-square test at the solution.
    check : the second start of ``check_init``, else None.
    quality : quality figures (:func:`graph_quality`) with ``quality``, else None.
    hint : what to try after a stop at the iteration cap (batch), else None.
    """

    graph: PoseGraph
    guess: InitialGuess
    result: GraphSolveResult
    evidence: OptimumEvidence
    check: InitCheck | None
    quality: dict[str, Any] | None
    hint: str | None
    request: SolveRequest

    def summary(self, file: str, out: str | None, read_seconds: float) -> dict[str, Any]:
        """The JSON object of ``ga-ros solve --json`` (``file``: the input, ``out``: the
        written graph or None, ``read_seconds``: time to read the file, s)."""
        graph, result, guess, evidence = self.graph, self.result, self.guess, self.evidence
        req = self.request
        summary = {
            'file': file, 'mode': 'tracks' if req.tracks else 'batch',
            'dim': graph.dim, 'vertices': graph.n_vertices, 'edges': graph.n_edges,
            'initial_cost': result.initial_cost, 'cost': result.cost,
            'objective': result.objective, 'iterations': result.iterations,
            'seconds': result.seconds, 'read_seconds': read_seconds,
            'converged': result.converged, 'reason': result.reason, 'robust': req.robust,
            'stages': result.stages, 'out': out, 'init': guess.method,
            'init_seconds': guess.seconds, 'init_compared': guess.compared,
            'termination': result.reason, 'hint': self.hint,
            'repaired_edges': len(graph.repaired_lines),
            'repaired_lines': list(graph.repaired_lines),
            'dof': evidence.dof, 'variance_factor': evidence.variance_factor,
            'chi2_95': [evidence.chi2_lower, evidence.chi2_upper],
            'chi2_test': evidence.chi2_test,
            'check_init': dataclasses.asdict(self.check) if self.check is not None else None,
        }
        if self.quality is not None:
            summary['quality'] = self.quality
        if result.per_track_ms is not None:
            summary['per_track_ms'] = result.per_track_ms
            summary['rejected'] = result.stages[0].get('rejected', {})
        return summary


def iteration_cap_hint(reason: str, init: str) -> str | None:
    """What to try when the solve stopped at the iteration cap (``None`` otherwise)."""
    if reason != 'max_iterations':
        return None
    also = '' if init == 'chordal' else ' or start elsewhere (--init chordal)'
    return ('stopped at the iteration cap before converging: the result may be short of the '
            f'optimum; raise --max-iterations{also}')


def graph_quality(graph: PoseGraph, T_world_node: FloatArray, alpha0: float) -> dict[str, Any]:
    """Quality figures of the solution (:mod:`ga_ros.core.quality`), without those the summary
    already has (the variance factor and its chi-square test: ``variance_factor``, ``dof``)."""
    from ga_ros.core.quality import QualityConfig, checked_solve, summarise

    t0 = time.perf_counter()
    # one Gauss-Newton step at the solution gives the residuals and N the tests need
    res = checked_solve(graph.network, T_world_node,
                        dataclasses.replace(GRAPH_SOLVER, damping='none', max_iterations=1),
                        fixed=list(graph.fixed) or None, config=QualityConfig(alpha0=alpha0))
    out = summarise(res.quality, graph.network, seconds=time.perf_counter() - t0).as_dict()
    for duplicate in ('sigma0_sq', 'redundancy', 'global_passed'):
        out.pop(duplicate)
    return out


def _absurd(name: str, what: str) -> InputError:
    return InputError(f'{name}: {what}: a vertex or edge holds an absurd value (e.g. 1e308); '
                      'fix the file. Nothing was written')


def solve_report(graph: PoseGraph, request: SolveRequest = SolveRequest(),
                 name: str = 'graph') -> SolveReport:
    """Solve a pose graph as ``ga-ros solve`` does and gather what it reports.

    Parameters
    ----------
    graph : the graph read from its file (its vertices are the ``'file'`` start).
    request : the options.
    name : the file's name, for the messages.

    Raises
    ------
    InputError
        If the initial or the final cost is not finite (an absurd value in the file).
    """
    guess = initial_guess(graph, request.init)
    graph = graph.with_initial_guess(guess.T_world_node)
    initial = guess.cost  # graph_cost at the guess
    if not np.isfinite(initial):
        raise _absurd(name, f'no final cost can be reached, the initial cost is {initial}')
    cfg = None
    if request.tracks:
        result = _solve_tracks(graph, request)
    else:
        overrides = dict(damping=request.damping, max_iterations=request.max_iterations,
                         tolerance=request.tolerance)
        cfg = GraphSolveConfig.with_solver(
            polish_iterations=request.polish_iterations, robust_loss=request.robust,
            robust_scale=request.robust_scale, **{k: v for k, v in overrides.items() if v})
        result = solve_graph(graph, cfg, initial_cost=initial)
    if not np.isfinite(result.cost):
        raise _absurd(name, f'the final cost is {result.cost} (initial {result.initial_cost})')
    evidence = optimum_evidence(graph, result.T_world_node, result.cost)
    check = None
    if request.check_init and cfg is not None:
        check = check_initialization(graph, result.cost, guess.method, cfg)
    quality = None
    if request.quality and cfg is not None:
        quality = graph_quality(graph, result.T_world_node, request.alpha0)
    hint = iteration_cap_hint(result.reason, guess.method) if cfg is not None else None
    return SolveReport(graph, guess, result, evidence, check, quality, hint, request)


def _solve_tracks(graph: PoseGraph, request: SolveRequest) -> GraphSolveResult:
    tracks = read_tracks(request.tracks, graph.vertex_ids)
    return solve_tracks(graph, tracks, window=request.window,
                        damping=request.damping or 'none', robust_loss=request.robust,
                        robust_scale=request.robust_scale,
                        outlier_chi2_prob=request.outlier_prob, refine=request.refine,
                        max_iterations=request.max_iterations or 10,
                        tolerance=request.tolerance or 1e-6)


def write_solution(report: SolveReport, out: str | Path | None = None,
                   tum: str | Path | None = None, kitti: str | Path | None = None) -> None:
    """Write the optimised graph (g2o, every vertex), and the optimised vertices as a TUM
    trajectory (stamp = vertex id in s) and as KITTI poses; None: that file is not written."""
    graph, T = report.graph, report.result.T_world_node
    if out:
        write_g2o(out, graph, T)
    if tum or kitti:  # imported here: start-up of a plain solve
        from ga_ros.io.trajectory import write_kitti, write_tum
    if tum:
        write_tum(tum, graph.vertex_ids * 1_000_000_000, T)
    if kitti:
        write_kitti(kitti, T)
