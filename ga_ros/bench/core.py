"""Benchmarks of the estimator on the paper's aerial scenario (issues 2 and 4).

* :func:`bench_batch`: one batch solve of the whole survey from the F2F initial guess.
* :func:`bench_window`: the survey flown online, track by track, through the
  :class:`~ga_ros.core.window.TrackWindowAligner`, with per-track update times, ATE against the
  batch solution, and peak memory.

Memory is the process's peak resident set size (``ru_maxrss``), which includes the Python
interpreter and the imported libraries (~150 MB).
"""

from __future__ import annotations

import inspect
import json
import resource
import subprocess
import sys
import tempfile
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ga_ros.bench.gtsam_runner import gtsam_installed
from ga_ros.bench.survey import noisy_survey
from ga_ros.core.linalg import blocks as _blocks
from ga_ros.core.linalg import cholmod as _cholmod
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.solver.problem import _Problem
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window import update as _update
from ga_ros.core.window.handoff import RefinementHandoff
from ga_ros.eval.metrics import ate


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0



class NoSolveAligner(TrackWindowAligner):
    """Fills an aligner's state of a survey's size and shape quickly, for benchmarks of what
    does not depend on the estimates (persistence, the batch refinement's memory): a track end
    marks the track finished and freezes the tracks leaving the window with a fixed
    covariance (1e-4 I), without solving anything."""

    def finish_track(self) -> None:
        if self._open_track is None or self._open_track in self._finished:
            return None
        self._finished.add(self._open_track)
        finished = [t for t in self._tracks if t in self._finished]
        for t in finished[:-self.config.window_tracks]:
            nodes = self._track_nodes[t]
            if not self._frozen[nodes[0]]:
                self._cov[nodes] = 1e-4 * np.eye(6)
                self._frozen[nodes] = True
        self._n_updates += 1
        return None

@dataclass
class BatchFigures:
    nodes: int
    connections: int
    equations: int
    observations: int
    unknowns: int
    iterations: int
    converged: bool
    seconds: float
    peak_rss_mb: float
    f2f_ate_m: float
    ga_ate_m: float
    tolerance: float
    cost: float


def bench_batch(n_tracks: int = 25, noise_pct: float = 5.0, seed: int = 0,
                tolerance: float = 1e-4) -> BatchFigures:
    """Batch mixed adjustment of the aerial survey (25 double tracks x 204 positions).

    Converged means the largest correction is below ``tolerance`` (0.1 mm / 0.1 mrad by
    default; the cost no longer changes in its 10th digit by then).
    """
    sc, nm = noisy_survey(n_tracks, noise_pct, seed)
    net = sc.network(nm.z, nm.cov)
    T0 = sc.f2f(nm.z)
    t0 = time.perf_counter()
    res = solve(net, T0, SolverConfig(tolerance=tolerance))
    seconds = time.perf_counter() - t0
    return BatchFigures(net.n_nodes, net.n_connections, res.n_equations, res.n_observations,
                        res.n_unknowns, res.iterations, res.converged, seconds, peak_rss_mb(),
                        ate(T0, sc.T_world_node, 'first').rmse,
                        ate(res.T_world_node, sc.T_world_node, 'first').rmse, tolerance, res.cost)


@dataclass
class WindowFigures:
    tracks: int
    nodes: int
    connections: int
    policy: str
    window_tracks: int
    total_seconds: float
    per_track_ms_p50: float
    per_track_ms_p95: float
    per_track_ms_max: float
    peak_rss_mb: float
    ate_rigid_window_m: float
    ate_rigid_batch_m: float
    ate_raw_window_m: float
    ate_raw_batch_m: float
    gap_rigid_pct: float
    gap_raw_pct: float
    per_track_ms_mean: float = float('nan')
    per_track_cpu_ms_p50: float = float('nan')  # CPU time of the process (a loaded machine's
    per_track_cpu_ms_p95: float = float('nan')  # wall clock counts other processes too)
    gtsam_ms_p50: float = float('nan')  # GTSAM IncrementalFixedLagSmoother, same survey and run
    gtsam_ms_p95: float = float('nan')
    gtsam_ate_rigid_m: float = float('nan')
    gtsam_cpu_ms_p50: float = float('nan')
    gtsam_cpu_ms_p95: float = float('nan')
    refine_every_tracks: int = 1
    # CPU ms p50 over the track-end calls of each part of the update (see UPDATE_PARTS)
    breakdown_cpu_ms_p50: dict | None = None
    measurement_cpu_us: float = float('nan')  # mean CPU of a call that ends no track


#: The parts of a window update timed by :func:`bench_window` (CPU ms, exclusive: a part
#: called inside another counts in the outer one), and the functions that do them.
#: ``solve``: the factor's solves (the steps); ``gradient``: the gradient after each step (its
#: residuals, cost and the next chord step's gradient, :meth:`~ga_ros.core.solver.problem._Problem.
#: gradient_ahead`); ``problem``: the window problem's node and connection sets and the
#: connections' kept terms.
UPDATE_PARTS = {
    'linearise': ((_Problem, 'linear_system'), (_blocks.BlockPattern, 'assemble')),
    'factor': ((_cholmod.SparseCholesky, '__init__'), (_cholmod.SparseCholesky, 'refactor')),
    'solve': ((_cholmod.SparseCholesky, 'solve'),),
    'gradient': ((_Problem, 'gradient'), (_Problem, 'gradient_ahead')),
    'problem': ((_update.WindowUpdate, 'window_problem'),),
    'gate': ((_update, 'outliers'), (_update, 'readmissible')),
    'freeze': ((TrackWindowAligner, '_freeze'),),
    'refinement': ((RefinementHandoff, 'install_due'), (RefinementHandoff, 'smooth'),
                   (RefinementHandoff, 'start')),
}


@contextmanager
def _timed_parts(totals: dict[str, float]):
    """Add the CPU ms spent in each part of :data:`UPDATE_PARTS` to ``totals`` while active
    (the functions are wrapped for the duration, then put back)."""
    depth = [0]

    def wrap(part, fn):
        def timed(*args, **kwargs):
            if depth[0]:
                return fn(*args, **kwargs)
            depth[0] += 1
            c0 = time.process_time()
            try:
                return fn(*args, **kwargs)
            finally:
                totals[part] = totals.get(part, 0.0) + 1e3 * (time.process_time() - c0)
                depth[0] -= 1
        return timed

    saved = [(owner, name, inspect.getattr_static(owner, name))
             for targets in UPDATE_PARTS.values() for owner, name in targets]
    try:
        for part, targets in UPDATE_PARTS.items():
            for owner, name in targets:
                setattr(owner, name, wrap(part, inspect.getattr_static(owner, name)))
        yield totals
    finally:
        for owner, name, fn in saved:
            setattr(owner, name, fn)


def bench_window(n_tracks: int = 25, policy: str = 'weighted', window_tracks: int = 5,
                 noise_pct: float = 5.0, seed: int = 0, compare_batch: bool = True,
                 with_gtsam: bool = False,
                 refine_every_tracks: int | None = None) -> WindowFigures:
    """Fly the aerial survey online and time each track's update.

    ``refine_every_tracks``: the aligner's background refinement (default: the aligner's
    default; 0 is the plain window). The CPU time of each call that ends a track is split into
    the parts of :data:`UPDATE_PARTS` (``other``: the rest); their medians are
    ``breakdown_cpu_ms_p50``.

    With ``with_gtsam`` (and ``gtsam`` importable), the same survey also runs through GTSAM's
    ``IncrementalFixedLagSmoother`` with a lag of ``window_tracks`` tracks, in a child process
    of the same run (:mod:`ga_ros.bench.gtsam_runner`), for the ratio of update times.
    """
    sc, nm = noisy_survey(n_tracks, noise_pct, seed)
    ms = sc.measurements(nm.z, nm.cov)
    cfg = AlignerConfig(window_tracks=window_tracks, freeze_policy=policy)
    if refine_every_tracks is not None:
        cfg = AlignerConfig(window_tracks=window_tracks, freeze_policy=policy,
                            refine_every_tracks=int(refine_every_tracks))
    al = TrackWindowAligner(cfg, sc.T_world_node[0])
    updates, cpu_ms, parts, other_us = [], [], [], []
    t0 = time.perf_counter()
    with _timed_parts({}) as totals:
        for m in list(ms) + [None]:
            totals.clear()
            c0 = time.process_time()
            new = al.add_measurement(m) if m is not None else [al.finish_track()]
            cpu = 1e3 * (time.process_time() - c0)
            new = [u for u in new if u is not None]
            if new:  # CPU time of the call that ended a track: its update (+ one measurement)
                cpu_ms.append(cpu)
                parts.append({**totals, 'other': cpu - sum(totals.values())})
                # the next freeze, computed ahead in the background (freeze_ahead) while a live
                # survey flies the next track: waited for here, its CPU counted apart
                parts[-1]['freeze (background)'] = al.wait_background()
            else:
                other_us.append(1e3 * cpu)
            updates += new
    total = time.perf_counter() - t0
    rss = peak_rss_mb()
    T_win = al.corrected_path().T_world_node
    if compare_batch:
        T_batch = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z),
                        SolverConfig(tolerance=1e-6)).T_world_node
    else:
        T_batch = T_win
    ms_ = np.array([u.update_ms for u in updates])
    rig_w, rig_b = (ate(T, sc.T_world_node, 'rigid').rmse for T in (T_win, T_batch))
    raw_w, raw_b = (ate(T, sc.T_world_node, 'first').rmse for T in (T_win, T_batch))
    fig = WindowFigures(
        n_tracks, sc.n_nodes, sc.n_connections, policy, window_tracks, total,
        float(np.percentile(ms_, 50)), float(np.percentile(ms_, 95)), float(ms_.max()), rss,
        rig_w, rig_b, raw_w, raw_b, 100.0 * (rig_w - rig_b) / rig_b,
        100.0 * (raw_w - raw_b) / raw_b, float(ms_.mean()),
        float(np.percentile(cpu_ms, 50)), float(np.percentile(cpu_ms, 95)),
        refine_every_tracks=al.config.refine_every_tracks,
        breakdown_cpu_ms_p50={k: float(np.median([p.get(k, 0.0) for p in parts]))
                              for k in (*UPDATE_PARTS, 'other', 'freeze (background)')},
        measurement_cpu_us=float(np.mean(other_us)) if other_us else float('nan'))
    al.close()
    if with_gtsam and gtsam_installed():
        (fig.gtsam_ms_p50, fig.gtsam_ms_p95, fig.gtsam_ate_rigid_m, fig.gtsam_cpu_ms_p50,
         fig.gtsam_cpu_ms_p95) = _gtsam_window(sc, ms, window_tracks)
    return fig


def _gtsam_window(sc, ms, window_tracks: int) -> tuple[float, float, float, float, float]:
    """p50 / p95 update ms (wall), rigid-aligned ATE, p50 / p95 update CPU ms of GTSAM's
    IncrementalFixedLagSmoother on the survey's measurements ``ms`` (lag of ``window_tracks``
    tracks), run by :mod:`ga_ros.bench.gtsam_runner` in a child process."""
    index = {int(v): k for k, v in enumerate(sc.node_ids)}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / 'tracks.npz'
        np.savez(path, src=np.array([index[m.src_id] for m in ms]),
                 dst=np.array([index[m.dst_id] for m in ms]), z=np.stack([m.z for m in ms]),
                 cov=np.stack([m.cov for m in ms]), node_track=np.asarray(sc.track_ids),
                 T_first=sc.T_world_node[0])
        run = subprocess.run([sys.executable, '-m', 'ga_ros.bench.gtsam_runner', 'tracks',
                              str(path), str(window_tracks)], capture_output=True, text=True,
                             check=True)
    out = json.loads(run.stdout.strip().splitlines()[-1])
    ms_, cpu = np.asarray(out['update_ms']), np.asarray(out['update_cpu_ms'])
    return (float(np.percentile(ms_, 50)), float(np.percentile(ms_, 95)),
            ate(np.asarray(out['T_world_node']), sc.T_world_node, 'rigid').rmse,
            float(np.percentile(cpu, 50)), float(np.percentile(cpu, 95)))


def as_dict(fig) -> dict:
    return asdict(fig)
