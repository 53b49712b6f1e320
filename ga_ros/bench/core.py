"""Benchmarks of the estimator on the paper's aerial scenario (issues 2 and 4).

* :func:`bench_batch`: one batch solve of the whole survey from the F2F initial guess.
* :func:`bench_window`: the survey flown online, track by track, through the
  :class:`~ga_ros.core.window.TrackWindowAligner`, with per-track update times, ATE against the
  batch solution, and peak memory.

Memory is the process's peak resident set size (``ru_maxrss``), which includes the Python
interpreter and the imported libraries (~150 MB).
"""

from __future__ import annotations

import json
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ga_ros.bench.cpu import all_cpu_seconds
from ga_ros.bench.gtsam_runner import gtsam_installed
from ga_ros.bench.stages import STAGES, counted_work, timed_stages
from ga_ros.bench.survey import noisy_survey
from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
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
    per_track_cpu_ms_p50: float = float('nan')  # CPU time of the update call's thread (a
    per_track_cpu_ms_p95: float = float('nan')  # loaded machine's wall clock counts others)
    gtsam_ms_p50: float = float('nan')  # GTSAM IncrementalFixedLagSmoother, same survey and run
    gtsam_ms_p95: float = float('nan')
    gtsam_ate_rigid_m: float = float('nan')
    gtsam_cpu_ms_p50: float = float('nan')
    gtsam_cpu_ms_p95: float = float('nan')
    refine_every_tracks: int = 1
    # CPU ms per track, mean over the tracks with a full window, by stage (STAGES, 'other' the
    # rest of the thread): {'track end': {stage: ms}, 'background': {stage: ms}}
    stage_cpu_ms: dict | None = None
    measurement_cpu_us: float = float('nan')  # mean CPU of a call that ends no track
    # CPU per track of everything but the update call's thread and the measurements: the
    # freeze ahead's thread, the refinement worker process, the process pool's threads
    background_cpu_ms_p50: float = float('nan')
    total_cpu_ms_p50: float = float('nan')  # per track: update call + outputs + background
    total_cpu_ms_p95: float = float('nan')
    full_window_tracks: int = 0  # tracks with a full window (those of the stage means)
    # work per track by part and kind ('window linearisations': mean over the tracks with a
    # full window; bench.stages.counted_work)
    work_per_track: dict | None = None


def _stage_table(records: list[dict]) -> dict:
    """Mean CPU ms per track of each stage, per thread role, over ``records`` (one
    :meth:`~ga_ros.bench.stages.StageClock.take` per track, with its thread's rest under
    ``other``)."""
    out = {}
    for role in ('track end', 'background'):
        names = [*STAGES, 'other']
        out[role] = {k: float(np.mean([r.get((role, k), 0.0) for r in records]))
                     if records else float('nan') for k in names}
    return out


def _publish_outputs(al: TrackWindowAligner, track_id: int) -> None:
    """What a node publishes after an update (:mod:`ga_ros.ros.alignment_outputs`): the corrected
    path and the covariance of the newest adjusted node."""
    cp = al.corrected_path()
    mine = np.nonzero(np.asarray(cp.track_ids) == track_id)[0]
    if mine.size:
        al.covariance(int(cp.node_ids[mine[-1]]))


def bench_window(n_tracks: int = 25, policy: str = 'weighted', window_tracks: int = 5,
                 noise_pct: float = 5.0, seed: int = 0, compare_batch: bool = True,
                 with_gtsam: bool = False,
                 refine_every_tracks: int | None = None) -> WindowFigures:
    """Fly the aerial survey online and time each track's update.

    ``refine_every_tracks``: the aligner's background refinement (default: the aligner's
    default; 0 is the plain window). After each track end the outputs a node publishes are
    computed (the corrected path, the newest adjusted node's covariance) and the freeze
    computed ahead is waited for (a live survey flies the next track meanwhile). Per track:
    the CPU of the update call's thread (``per_track_cpu_ms_*``), the CPU of the whole process
    tree minus that thread's (``background_cpu_ms_p50``: the freeze ahead's thread, the
    refinement worker process), and their sum with the outputs (``total_cpu_ms_*``); the
    measurements that end no track are counted apart (``measurement_cpu_us``). The CPU of
    each thread is split into the stages of :data:`~ga_ros.bench.stages.STAGES`
    (``stage_cpu_ms``, means over the tracks with a full window), and the linearisations,
    gradient passes, costs and factorisations of each track are counted by part
    (``work_per_track``, :func:`~ga_ros.bench.stages.counted_work`, the same means).

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
    updates, cpu_ms, totals, background, records, other_us = [], [], [], [], [], []
    works = []
    t0 = time.perf_counter()
    with timed_stages() as clock, counted_work() as work:
        tree0, main0 = all_cpu_seconds(), time.thread_time()
        for m in list(ms) + [None]:
            c0 = time.thread_time()
            new = al.add_measurement(m) if m is not None else [al.finish_track()]
            cpu = 1e3 * (time.thread_time() - c0)
            new = [u for u in new if u is not None]
            if not new:
                other_us.append(1e3 * cpu)
                continue
            # the call that ended a track: its update (+ one measurement), then the outputs
            c1 = time.thread_time()
            _publish_outputs(al, new[-1].track_id)
            outputs = 1e3 * (time.thread_time() - c1)
            # the next freeze, computed ahead in the background (freeze_ahead) while a live
            # survey flies the next track: waited for here
            al.wait_background()
            tree1, main1 = all_cpu_seconds(), time.thread_time()
            # everything since the last track end outside this thread: the freeze ahead, the
            # refinement worker process (its CPU of this interval), the pool's threads
            bg = max(0.0, 1e3 * ((tree1 - tree0) - (main1 - main0)))
            tree0, main0 = tree1, main1
            stages = clock.take()
            stages[('track end', 'other')] = cpu - sum(
                v for (role, k), v in stages.items() if role == 'track end' and k != 'outputs')
            stages[('background', 'other')] = bg - sum(
                v for (role, _), v in stages.items() if role == 'background')
            cpu_ms.append(cpu)
            background.append(bg)
            totals.append(cpu + outputs + bg)
            records.append(stages)
            works.append(work.take())
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
    full = records[window_tracks + 1:] or records  # the window full, its first freeze done
    full_work = works[window_tracks + 1:] or works
    fig = WindowFigures(
        n_tracks, sc.n_nodes, sc.n_connections, policy, window_tracks, total,
        float(np.percentile(ms_, 50)), float(np.percentile(ms_, 95)), float(ms_.max()), rss,
        rig_w, rig_b, raw_w, raw_b, 100.0 * (rig_w - rig_b) / rig_b,
        100.0 * (raw_w - raw_b) / raw_b, float(ms_.mean()),
        float(np.percentile(cpu_ms, 50)), float(np.percentile(cpu_ms, 95)),
        refine_every_tracks=al.config.refine_every_tracks,
        stage_cpu_ms=_stage_table(full),
        measurement_cpu_us=float(np.mean(other_us)) if other_us else float('nan'),
        background_cpu_ms_p50=float(np.percentile(background, 50)),
        total_cpu_ms_p50=float(np.percentile(totals, 50)),
        total_cpu_ms_p95=float(np.percentile(totals, 95)), full_window_tracks=len(full),
        work_per_track={f'{part} {kind}': float(np.mean([w.get((part, kind), 0)
                                                          for w in full_work]))
                        for part, kind in sorted({k for w in full_work for k in w})})
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
