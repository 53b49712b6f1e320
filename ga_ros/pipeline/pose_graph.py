"""Pose-graph optimisation of a :class:`ga_ros.io.g2o.PoseGraph`, ROS-free.

Batch mode (:func:`solve_graph`) solves the whole graph with the mixed adjustment (``se3``
model, which minimises the g2o/GTSAM cost ``sum e' Omega e``) from the graph's initial guess
with Powell's dogleg (or Levenberg-Marquardt followed by undamped Gauss-Newton iterations, kept
only if they lower the cost). Track mode (:func:`solve_tracks`) replays the graph
track by track through :class:`ga_ros.core.window.TrackWindowAligner`, as the live node would,
and finishes with its batch refinement. ``ga-ros solve`` is the command line over both.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.chi2 import chi2_quantile
from ga_ros.core.initialization import INIT_METHODS, PoseGraphEdges, initialize
from ga_ros.core.solver import SolverConfig, losses, solve
from ga_ros.errors import (
    DegenerateGeometryError,
    FormatError,
    InputError,
    NetworkError,
    SolverError,
)
from ga_ros.geometry import se3
from ga_ros.io.g2o import PoseGraph, edge_errors, graph_cost

if TYPE_CHECKING:  # track mode only: imported where it is used (start-up of a batch solve)
    from ga_ros.core.measurement import Measurement


@dataclass(frozen=True)
class GraphSolveConfig:
    """Settings of :func:`solve_graph`: a :class:`SolverConfig` (one set of solver rules) and
    what only a pose-graph solve has.

    Attributes
    ----------
    solver : the solver settings; the defaults of a batch pose-graph solve are
        :data:`GRAPH_SOLVER` (``se3``, Powell's dogleg -- Gauss-Newton steps while they lower the
        cost, at most one factorisation per iteration, none for a chord step near the optimum
        (``chord_decrease``) --, at most 100 iterations, ``tolerance`` 1e-8 m/rad,
        ``cost_tolerance`` 1e-5, the default of GTSAM's ``relativeErrorTol``; ``factor='auto'``:
        a simplicial factor where CHOLMOD finds it cheaper). ``damping='lm'``
        runs a Levenberg-Marquardt first stage, then the undamped polish below.
    polish_iterations : cap on the undamped iterations run after an LM stage (0: none).
    planar : solve 2-D graphs with the ``se2`` model (3 unknowns per vertex, the same cost and
        optimum as their SE(3) embedding, about 8x less factorisation work); False solves them
        embedded in SE(3) (6 unknowns, unit information on ``z rx ry``).
    """

    solver: SolverConfig = field(default_factory=lambda: GRAPH_SOLVER)
    polish_iterations: int = 30
    planar: bool = True

    def __post_init__(self) -> None:
        if self.polish_iterations < 0:
            raise InputError('polish_iterations >= 0 required')
        if self.solver.model != 'se3':
            raise InputError("a pose graph is solved with the se3 model (2-D graphs with se2, "
                             "see planar): leave model at 'se3'")

    @classmethod
    def with_solver(cls, polish_iterations: int = 30, planar: bool = True,
                    **solver: object) -> GraphSolveConfig:
        """A config whose solver is :data:`GRAPH_SOLVER` with the given fields replaced, e.g.
        ``GraphSolveConfig.with_solver(robust_loss='cauchy')``."""
        return cls(replace(GRAPH_SOLVER, **solver), polish_iterations, planar)

    def solver_config(self, damping: str | None = None, max_iterations: int | None = None,
                      dim: int = 3) -> SolverConfig:
        """The first stage's :class:`SolverConfig` (or a stage with another damping/cap) for a
        graph of dimension ``dim`` (2: the ``se2`` model when :attr:`planar`)."""
        model = 'se2' if dim == 2 and self.planar else self.solver.model
        return replace(self.solver, damping=damping or self.solver.damping,
                       max_iterations=max_iterations or self.solver.max_iterations, model=model)


#: Solver settings of a batch pose-graph solve (see :class:`GraphSolveConfig`).
GRAPH_SOLVER = SolverConfig(model='se3', damping='dogleg', max_iterations=100, tolerance=1e-8,
                            cost_tolerance=1e-5, factor='auto')


@dataclass
class GraphSolveResult:
    """Outcome of :func:`solve_graph`.

    Attributes
    ----------
    T_world_node : (n, 4, 4) optimised vertex poses, graph vertex order.
    cost : ``sum e' Omega e`` at the solution (:func:`graph_cost`).
    initial_cost : the same at the initial guess.
    objective : the minimised objective (``cost``, or the robust cost with a robust loss).
    iterations : solver iterations over all stages.
    seconds : wall time of the solver stages (s): the solves, and after an LM stage the
        evaluation that accepts or refuses its polish; file I/O, the initial cost and the
        independent evaluation of the first stage's result (:func:`graph_cost`) excluded.
    converged : whether the last accepted stage met the tolerance.
    reason : termination reason of the last accepted stage.
    stages : per-stage summary (name, iterations, seconds, objective, accepted, reason).
    per_track_ms : track mode only: update time of each track (ms).
    """

    T_world_node: FloatArray
    cost: float
    initial_cost: float
    objective: float
    iterations: int
    seconds: float
    converged: bool
    reason: str
    stages: list[dict] = field(default_factory=list)
    per_track_ms: list[float] | None = None


def robust_objective(graph: PoseGraph, T_world_node: FloatArray, loss: str = 'none',
                     scale: float = 3.0) -> float:
    """``sum rho(e' Omega e)`` with the solver's robust loss ``loss`` of scale ``scale``
    (:func:`ga_ros.core.solver.losses.robust_loss`; ``rho(r2) = r2`` for ``'none'``)."""
    e = edge_errors(graph, T_world_node)
    r2 = np.einsum('ki,kij,kj->k', e, graph.information, e)
    return float(np.sum(losses.robust_loss(loss, scale).rho(r2)))


def solve_graph(graph: PoseGraph, config: GraphSolveConfig | None = None,
                initial_cost: float | None = None) -> GraphSolveResult:
    """Batch-optimise a pose graph from its own initial guess (``graph.T_init``).

    The datum is the ``FIX`` vertices of the file, or else its first vertex. ``initial_cost``:
    :func:`graph_cost` at ``graph.T_init`` when the caller has it (else it is evaluated here).

    Raises
    ------
    NetworkError
        Vertices not connected to the datum.
    SolverError, DegenerateGeometryError
        The first stage failed (a failing polish stage is discarded instead).
    """
    cfg = config or GraphSolveConfig()
    fixed = list(graph.fixed) or None
    if initial_cost is None:
        initial_cost = graph_cost(graph, graph.T_init)
    stages: list[dict] = []
    last: list = [None, 0.0]  # the poses whose graph_cost was evaluated last, and that cost

    def objective(T: FloatArray) -> float:
        if cfg.solver.robust_loss != 'none':
            return robust_objective(graph, T, cfg.solver.robust_loss, cfg.solver.robust_scale)
        last[:] = [T, graph_cost(graph, T)]  # without a robust loss the objective is the cost
        return last[1]

    first = cfg.solver_config(dim=graph.dim)
    # the file's information is the weight matrix: not inverted back from the covariances
    weights = (graph.information if (first.model, graph.dim) in (('se3', 3), ('se2', 2))
               else None)
    t = time.perf_counter()
    res = solve(graph.network, graph.T_init, first, fixed=fixed, weights=weights)
    seconds = time.perf_counter() - t
    # the independent evaluation of the result (reported; the solver has its own cost)
    T, best = res.T_world_node, objective(res.T_world_node)
    iterations, converged, reason = res.iterations, res.converged, res.reason
    stages.append(dict(name=cfg.solver.damping, iterations=res.iterations,
                       factorisations=res.factorisations, reason=res.reason,
                       seconds=seconds, objective=best, accepted=True))
    if cfg.solver.damping == 'lm' and cfg.polish_iterations > 0:
        polish = cfg.solver_config('none', cfg.polish_iterations, dim=graph.dim)
        t = time.perf_counter()
        try:
            res2 = solve(graph.network, T, polish, fixed=fixed, weights=weights)
            value = objective(res2.T_world_node)
            ok = bool(np.isfinite(value) and value <= best * (1 + 1e-12) + 1e-300)
            why = res2.reason
        except (SolverError, DegenerateGeometryError) as exc:  # GN failed: LM result stands
            res2, value, ok, why = None, float('nan'), False, f'failed: {exc}'
        polish_seconds = time.perf_counter() - t  # its objective decides: timed with it
        seconds += polish_seconds
        stages.append(dict(name='gauss-newton', iterations=res2.iterations if res2 else 0,
                           factorisations=res2.factorisations if res2 else 0,
                           reason=why, seconds=polish_seconds, objective=value,
                           accepted=ok))
        if res2 is not None:
            iterations += res2.iterations
        if ok and res2 is not None:
            T, best, converged, reason = res2.T_world_node, value, res2.converged, res2.reason
    cost = last[1] if last[0] is T else graph_cost(graph, T)
    return GraphSolveResult(T_world_node=T, cost=cost, initial_cost=initial_cost,
                            objective=best, iterations=iterations, seconds=seconds,
                            converged=converged, reason=reason, stages=stages)


# ------------------------------------------------------------------------------ track mode
def read_tracks(path: str | Path, vertex_ids: IntArray) -> IntArray:
    """Track id of every vertex from a CSV file (a header line, then ``node_id,track_id``).

    Returns
    -------
    (n,) track ids in the order of ``vertex_ids``.

    Raises
    ------
    FormatError
        ``file:line`` of a malformed line, a duplicate or unknown node, a negative track id;
        or a vertex without a track.
    """
    import csv  # track mode only (start-up of a batch solve)

    spath = str(path)
    try:
        lines = Path(path).read_text().splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f'cannot read: {exc}', spath) from None
    index = {int(v): k for k, v in enumerate(vertex_ids)}
    tracks = np.full(len(vertex_ids), -1, dtype=np.int64)
    seen: dict[int, int] = {}
    for lineno, row in enumerate(csv.reader(lines), start=1):
        if lineno == 1 or not row or not ''.join(row).strip() or row[0].startswith('#'):
            continue
        if len(row) != 2:
            raise FormatError(f'expected node_id,track_id, got {len(row)} fields', spath, lineno)
        try:
            node, track = int(row[0]), int(row[1])
        except ValueError:
            raise FormatError(f'node_id and track_id must be integers, got {row!r}',
                              spath, lineno) from None
        if track < 0:
            raise FormatError(f'track id must be non-negative, got {track}', spath, lineno)
        if node not in index:
            raise FormatError(f'node {node} is not a vertex of the graph', spath, lineno)
        if node in seen:
            raise FormatError(f'node {node} already has a track (line {seen[node]})',
                              spath, lineno)
        seen[node] = lineno
        tracks[index[node]] = track
    if (tracks < 0).any():
        missing = np.asarray(vertex_ids)[tracks < 0][:10].tolist()
        raise FormatError(f'{int((tracks < 0).sum())} vertices have no track, e.g. {missing}',
                          spath)
    return tracks


def replay_order(graph: PoseGraph, tracks: IntArray) -> IntArray:
    """Vertex indices in the order a live run reveals them: by track id, then file order."""
    tracks = np.asarray(tracks, dtype=np.int64)
    return np.lexsort((np.arange(graph.n_vertices), tracks))


def replay_measurements(graph: PoseGraph, tracks: IntArray,
                        stamp_step_ns: int = 100_000_000) -> list[Measurement]:
    """The graph's edges as the measurement stream of a live run.

    Vertices appear in :func:`replay_order`; an edge is revealed when its later end appears, and
    is oriented so that ``dst`` is that new vertex (an edge given the other way is inverted:
    ``T_dst_src = T_src_dst^-1``, covariance ``Ad(T) S Ad(T)'``, which leaves ``e' Omega e``
    unchanged since ``e_ji = -Ad(T_ij) e_ij`` exactly). ``kind`` is ``'consecutive'`` for an edge
    to the vertex revealed just before in the same track, ``'cross'`` otherwise; of the edges a
    vertex reveals, the consecutive one comes first (it places the vertex, as visual odometry
    would), the others keep their file order. ``stamp_ns`` is the rank of ``dst`` times
    ``stamp_step_ns``.

    Raises
    ------
    NetworkError
        A vertex (other than the first) has no edge to any earlier vertex, so a live run could
        not place it.
    """
    tracks = np.asarray(tracks, dtype=np.int64)
    order = replay_order(graph, tracks)
    rank = np.empty(graph.n_vertices, dtype=np.int64)
    rank[order] = np.arange(graph.n_vertices)
    src, dst = graph.edge_src, graph.edge_dst
    later_is_src = rank[src] > rank[dst]
    a = np.where(later_is_src, dst, src)       # earlier end
    b = np.where(later_is_src, src, dst)       # later end (the new vertex)
    reach = np.zeros(graph.n_vertices, dtype=bool)
    reach[b] = True
    reach[order[0]] = True
    if not reach.all():
        k = int(order[np.argmin(reach[order])])
        raise NetworkError(f'vertex {int(graph.vertex_ids[k])} has no edge to an earlier vertex '
                           f'in track order, so a live run could not place it')
    cov = graph.network.arrays().cov
    ids = graph.vertex_ids
    from ga_ros.core.measurement import Measurement

    out: list[Measurement] = []
    consecutive = (tracks[a] == tracks[b]) & (rank[b] == rank[a] + 1)
    for k in np.lexsort((np.arange(graph.n_edges), ~consecutive, rank[b])):
        T, S = graph.T_meas[k], cov[k]
        if later_is_src[k]:
            Ad = se3.adjoint(T)
            T, S = se3.inverse(T), Ad @ S @ Ad.T
            S = 0.5 * (S + S.T)
        i, j = int(a[k]), int(b[k])
        kind = 'consecutive' if consecutive[k] else 'cross'
        out.append(Measurement.from_pose(int(ids[i]), int(ids[j]), int(tracks[i]),
                                         int(tracks[j]), T, S, int(rank[j]) * stamp_step_ns,
                                         kind))
    return out


def solve_tracks(graph: PoseGraph, tracks: IntArray, window: int = 5,
                 damping: str = 'none', robust_loss: str = 'none', robust_scale: float = 3.0,
                 outlier_chi2_prob: float = 0.999, refine: bool = True,
                 max_iterations: int = 10, tolerance: float = 1e-6) -> GraphSolveResult:
    """Solve a pose graph track by track as the live alignment node would.

    The edges are fed to :class:`ga_ros.core.window.TrackWindowAligner` in the order of
    :func:`replay_measurements` (a track ends when a vertex of the next one appears); the first
    vertex in track order is the datum, at its initial pose. With ``refine`` the aligner's final
    batch refinement follows. The per-track update times go to ``per_track_ms``.
    """
    from ga_ros.core.window import ALIGNER_SOLVER, AlignerConfig, TrackWindowAligner

    t0 = time.perf_counter()
    initial_cost = graph_cost(graph, graph.T_init)
    measurements = replay_measurements(graph, tracks)
    first = int(replay_order(graph, tracks)[0])
    solver = replace(ALIGNER_SOLVER, damping=damping, robust_loss=robust_loss,
                     robust_scale=robust_scale, max_iterations=max_iterations, tolerance=tolerance)
    cfg = AlignerConfig(window_tracks=window, solver=solver,
                        outlier_chi2_prob=outlier_chi2_prob)
    aligner = TrackWindowAligner(cfg, T_world_first=graph.T_init[first])
    updates = []
    for m in measurements:
        try:
            updates.extend(aligner.add_measurement(m))
        except InputError:  # a live node drops it (e.g. an edge to a frozen track); counted
            pass
    last = aligner.finish_track()
    if last is not None:
        updates.append(last)
    stages = [dict(name='tracks', iterations=sum(u.iterations for u in updates),
                   seconds=time.perf_counter() - t0, tracks=len(updates),
                   outliers=sum(u.n_outliers for u in updates),
                   failed=[u.track_id for u in updates if u.reason.startswith('failed')],
                   rejected=dict(aligner.stats.n_rejected),
                   objective=None, accepted=True, reason=updates[-1].reason if updates else '')]

    def poses() -> FloatArray:
        path = aligner.corrected_path()
        if path.node_ids.size != graph.n_vertices:
            missing = np.setdiff1d(graph.vertex_ids, path.node_ids)
            raise NetworkError(f'track mode could not place {missing.size} vertices (e.g. '
                               f'{missing[:5].tolist()}): every edge to them was rejected '
                               f'({aligner.stats.n_rejected})')
        T = np.empty_like(graph.T_init)
        T[graph.network.indices_of(path.node_ids)] = path.T_world_node
        return T

    T = poses()
    stages[0]['objective'] = robust_objective(graph, T, robust_loss, robust_scale)
    stages[0]['cost'] = graph_cost(graph, T)
    iterations = stages[0]['iterations']
    converged = all(u.converged for u in updates)
    reason = stages[0]['reason']
    if refine:
        t = time.perf_counter()
        up = aligner.refine_batch()
        T = poses()
        iterations += up.iterations
        converged, reason = up.converged, up.reason
        stages.append(dict(name='refine_batch', iterations=up.iterations, reason=up.reason,
                           seconds=time.perf_counter() - t, accepted=True,
                           objective=robust_objective(graph, T, robust_loss, robust_scale)))
    return GraphSolveResult(
        T_world_node=T, cost=graph_cost(graph, T), initial_cost=initial_cost,
        objective=robust_objective(graph, T, robust_loss, robust_scale), iterations=iterations,
        seconds=time.perf_counter() - t0, converged=converged, reason=reason, stages=stages,
        per_track_ms=[float(u.update_ms) for u in updates])


# ------------------------------------------------------------ initialisation and evidence
@dataclass(frozen=True)
class InitialGuess:
    """An initial guess of a pose graph and where it came from.

    Attributes
    ----------
    T_world_node : (n, 4, 4) poses in the graph's vertex order.
    method : ``'file'`` or one of :data:`ga_ros.core.initialization.INIT_METHODS`: the start
        used.
    cost : ``sum e' Omega e`` at the guess.
    seconds : wall time of the initialisation (s), the compared starts included.
    compared : ``'auto'`` only: ``{method: cost}`` of every start compared (the file's guess
        and chordal); empty otherwise.
    """

    T_world_node: FloatArray
    method: str
    cost: float
    seconds: float
    compared: dict[str, float] = field(default_factory=dict)


def graph_edges(graph: PoseGraph) -> PoseGraphEdges:
    """The graph's edges in the form :mod:`ga_ros.core.initialization` takes."""
    return PoseGraphEdges(n=graph.n_vertices, src=graph.edge_src, dst=graph.edge_dst,
                          T_meas=graph.T_meas, information=graph.information, dim=graph.dim)


def datum_index(graph: PoseGraph) -> int:
    """Index of the datum vertex: the first ``FIX`` vertex, else the first vertex."""
    if graph.fixed:
        return int(graph.network.index_of(graph.fixed[0]))
    return 0


def initial_guess(graph: PoseGraph, method: str = 'auto') -> InitialGuess:
    """An initial guess for :func:`solve_graph`.

    Parameters
    ----------
    graph : the graph.
    method : ``'file'`` (the file's vertices), ``'odometry'``, ``'spanning-tree'``,
        ``'chordal'`` (see :mod:`ga_ros.core.initialization`), or ``'auto'`` (default): of the
        cheap starts, the file's vertices (if it has any) and chordal, the one with the lower
        cost ``sum e' Omega e`` (:attr:`InitialGuess.compared` lists both). The solver converges
        to a local minimum near its start; a file's guess that chains noisy odometry is a poor
        one on large-noise graphs (torus3D: 59,907 from the file's guess, 24,235 from chordal),
        and where the file's guess is already good (an earlier solution) it keeps it. Comparing
        starts costs one chordal initialisation and one cost evaluation, not a second
        solve. The datum vertex (:func:`datum_index`) keeps its file
        pose when the file has one (identity otherwise), so a ``FIX`` vertex stays put.

    Raises
    ------
    InputError
        ``'file'`` asked for an edge-only graph, or an unknown method.
    NetworkError
        A vertex is not connected to the datum.
    """
    t0 = time.perf_counter()
    if method == 'auto':
        if not graph.has_guess:
            return replace(_guess(graph, 'chordal'), seconds=time.perf_counter() - t0)
        starts = [_guess(graph, 'file')]
        try:
            starts.append(_guess(graph, 'chordal'))
        except (DegenerateGeometryError, SolverError):  # no chordal start: the file's stands
            pass
        best = min(starts, key=lambda g: g.cost if np.isfinite(g.cost) else np.inf)
        return replace(best, seconds=time.perf_counter() - t0,
                       compared={g.method: g.cost for g in starts})
    return _guess(graph, method)


def _guess(graph: PoseGraph, method: str) -> InitialGuess:
    """The initial guess of one method (:func:`initial_guess` without ``'auto'``)."""
    t0 = time.perf_counter()
    if method == 'file':
        if not graph.has_guess:
            raise InputError(f'{graph.path or "the graph"} has no vertices, so no initial guess of'
                             f' its own: use --init chordal, spanning-tree or odometry')
        T = graph.T_init
    elif method in INIT_METHODS:
        root = datum_index(graph)
        T = initialize(graph_edges(graph), method, root)
        T = graph.T_init[root] @ T   # the datum keeps its pose (identity for edge-only files)
    else:
        raise InputError(f"init must be 'auto', 'file' or one of {INIT_METHODS}, got {method!r}")
    return InitialGuess(T_world_node=T, method=method, cost=graph_cost(graph, T),
                        seconds=time.perf_counter() - t0)


@dataclass(frozen=True)
class OptimumEvidence:
    """What a solution says about itself (is it the global optimum of a consistent model?).

    Attributes
    ----------
    cost : ``sum e' Omega e`` at the solution.
    dof : redundancy ``r = d m - d (n - n_datum)`` (``d`` = 6 in 3-D, 3 in 2-D).
    variance_factor : a-posteriori variance factor ``s0^2 = cost / r`` (1 when the information
        matrices are right and the solution is the global optimum; ``nan`` if ``r <= 0``).
    chi2_lower, chi2_upper : the two-sided 95 % interval of ``chi2(r)`` (2.5 % and 97.5 %).
    chi2_test : ``'pass'`` (cost inside the interval), ``'cost too large'`` (a local minimum,
        outliers, or optimistic information) or ``'cost too small'`` (pessimistic
        information), ``'n/a'`` when ``r <= 0``.
    """

    cost: float
    dof: int
    variance_factor: float
    chi2_lower: float
    chi2_upper: float
    chi2_test: str


def optimum_evidence(graph: PoseGraph, T_world_node: FloatArray,
                     cost: float | None = None) -> OptimumEvidence:
    """The a-posteriori variance factor and its chi-square test at 95 % for a solution
    (``cost``: :func:`graph_cost` at ``T_world_node`` when the caller has it)."""
    d = 6 if graph.dim == 3 else 3
    n_datum = len(graph.fixed) or 1
    dof = d * graph.n_edges - d * (graph.n_vertices - n_datum)
    if cost is None:
        cost = graph_cost(graph, T_world_node)
    if dof <= 0:
        return OptimumEvidence(cost, dof, float('nan'), float('nan'), float('nan'), 'n/a')
    lo, hi = chi2_quantile(dof, 0.025), chi2_quantile(dof, 0.975)  # no scipy.special import
    test = 'pass' if lo <= cost <= hi else ('cost too large' if cost > hi else 'cost too small')
    return OptimumEvidence(cost=cost, dof=dof, variance_factor=cost / dof, chi2_lower=lo,
                           chi2_upper=hi, chi2_test=test)


@dataclass(frozen=True)
class InitCheck:
    """Outcome of re-solving from another initialisation (``--check-init``).

    Attributes
    ----------
    method : the other initialisation.
    initial_cost : its cost before solving.
    cost : the cost it converged to.
    lower : whether it reached a lower cost than the solution checked (by more than
        ``rtol`` relative), i.e. the solution checked was a local minimum.
    relative_difference : ``(cost_checked - cost) / cost_checked``.
    """

    method: str
    initial_cost: float
    cost: float
    lower: bool
    relative_difference: float


def check_initialization(graph: PoseGraph, cost: float, used: str,
                         config: GraphSolveConfig | None = None,
                         rtol: float = 1e-6) -> InitCheck:
    """Solve again from another initialisation and compare (chordal, or spanning tree when
    the solution checked came from chordal)."""
    method = 'spanning-tree' if used == 'chordal' else 'chordal'
    guess = initial_guess(graph, method)
    res = solve_graph(graph.with_initial_guess(guess.T_world_node), config)
    rel = (cost - res.cost) / max(abs(cost), 1e-300)
    return InitCheck(method=method, initial_cost=guess.cost, cost=res.cost,
                     lower=bool(rel > rtol), relative_difference=float(rel))
