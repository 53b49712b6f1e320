"""Scaling benchmark (issue 14 item 3): the aerial survey scaled towards 100,000 poses.

The aerial simulator (:func:`ga_ros.sim.aerial.aerial_scenario`) flies ``--tracks`` double tracks
of ``2 x --positions-per-swath`` poses (default 100 x 1,000 = 100,000 poses) with 5 % noise; the
measurements are fed in acquisition order to :class:`ga_ros.core.window.TrackWindowAligner`
(``K = --window``, ``--policy`` weighted), exactly as the alignment node does. The script prints

* per-track window update time (p50 / p95 / max over the ``--span`` tracks ending at each
  checkpoint of ``--checkpoints``; wall time includes the wait for the background refinement
  at its hand-off, also shown alone; CPU time of the process during the update, and of the
  update's own thread: the process's also counts what the background freeze of the previous
  track had left to do when the update started, which varies with the machine's load) and
  the process's current resident set size there, with
  the RSS growth per pose between checkpoints (from the first checkpoint's RSS; and ``KiB/pose
  fit``, the slope of a least-squares line through the lowest RSS between tracks -- read when
  the measurement that ends each track arrives -- of every ``--span / 2`` tracks since the first
  checkpoint, see :func:`rss_slope`), the refinement worker's RSS, the nodes of the
  refinement in flight and the online path's ATE against the simulator's truth (rigid);
* the state save / restore time and file size at the end (``TrackWindowAligner.save/load``);
* the time and peak RSS (``ru_maxrss``) of the batch refinement of all poses
  (``refine_batch``), unless ``--no-batch``.

Stop early with ``--max-seconds`` (the online run stops after the track that passes it; the
table then says which checkpoints were not reached). Measurements are generated lazily (one
:class:`Measurement` at a time) so that they do not count in the aligner's memory.

Examples::

    ga-ros bench scale --tracks 100 --positions-per-swath 500
    ga-ros bench scale --tracks 30 --positions-per-swath 100 \\
        --checkpoints 10,20,30 --json
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ga_ros.bench.core import NoSolveAligner, peak_rss_mb
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import FREEZE_POLICIES, AlignerConfig, TrackWindowAligner, UpdateResult
from ga_ros.core.window.persistence import save_state
from ga_ros.eval.metrics import ate
from ga_ros.runtime import limit_blas_threads
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb
from ga_ros.sim.scenario import Scenario

PAGE = os.sysconf('SC_PAGE_SIZE')


def rss_mib(pid: int | str = 'self') -> float:
    """Current resident set size of a process (MiB, this one by default), from
    ``/proc/PID/statm``."""
    with open(f'/proc/{pid}/statm') as f:
        return int(f.read().split()[1]) * PAGE / 2**20


def children_rss_mib() -> float:
    """Resident set size of this process's children (the refinement worker; MiB)."""
    total = 0.0
    for task in Path('/proc/self/task').iterdir():
        try:
            pids = (task / 'children').read_text().split()
            total += sum(rss_mib(p) for p in pids)
        except OSError:
            continue
    return total


@dataclass
class Checkpoint:
    """Figures after the update of track ``tracks - 1`` (``tracks`` finished tracks)."""

    tracks: int
    poses: int
    update_ms_p50: float
    update_ms_p95: float
    update_ms_max: float
    cpu_ms_p50: float
    cpu_ms_p95: float
    window_nodes: int
    rss_mib: float
    kib_per_pose_since_first: float | None
    state_bytes_per_pose: float = 0.0
    refine_wait_ms_p50: float = 0.0
    refine_wait_ms_p95: float = 0.0
    worker_rss_mib: float = 0.0
    horizon_nodes: int = 0
    ate_rigid_m: float = 0.0
    thread_cpu_ms_p50: float = 0.0
    thread_cpu_ms_p95: float = 0.0
    kib_per_pose_fit: float | None = None


@dataclass
class Stage:
    """One stage of ``refine_batch`` (``--stages``): wall time, RSS when it started, the highest
    RSS sampled while it ran (a C call that holds the GIL, e.g. a CHOLMOD factorisation, is not
    sampled) and the process's peak RSS (``ru_maxrss``) when it ended (MiB): a stage that raised
    the process's peak shows it there."""

    name: str
    seconds: float
    rss_start_mib: float
    rss_peak_mib: float
    maxrss_after_mib: float = 0.0


class StageProbe:
    """Times the stages of ``refine_batch`` (the batch ``solve``, the covariances of the frozen
    nodes, the rebuilt joint priors) by wrapping the functions it calls, and samples the RSS
    every 5 ms in a thread for each stage's peak. Benchmark only: the wrappers are removed on
    exit."""

    def __init__(self) -> None:
        import ga_ros.core.window.aligner as window

        self.stages: list[Stage] = []
        self._peak = 0.0
        self._stop = False
        self._targets = [(window, 'solve'), (window, 'absorbed_priors'),
                         (window.SolveResult, 'covariance')]
        self._saved = [getattr(o, a) for o, a in self._targets]

    def _sample(self) -> None:
        while not self._stop:
            with self._lock:
                self._peak = max(self._peak, rss_mib())
            time.sleep(0.005)

    def _wrap(self, name: str, fn):
        def wrapped(*args, **kwargs):
            with self._lock:
                start = self._peak = rss_mib()
            t = time.perf_counter()
            try:
                return fn(*args, **kwargs)
            finally:
                with self._lock:
                    peak = max(self._peak, rss_mib())
                self.stages.append(Stage(name, time.perf_counter() - t, start, peak,
                                         peak_rss_mb()))
        return wrapped

    def __enter__(self) -> StageProbe:
        import threading

        for (obj, attr), fn in zip(self._targets, self._saved):
            setattr(obj, attr, self._wrap(attr, fn))
        self._lock = threading.Lock()
        self._thread = threading.Thread(target=self._sample, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop = True
        self._thread.join()
        for (obj, attr), fn in zip(self._targets, self._saved):
            setattr(obj, attr, fn)


@dataclass
class ScaleFigures:
    """Everything the benchmark measured (JSON with ``--json``)."""

    tracks_requested: int
    poses_per_track: int
    window_tracks: int
    policy: str
    scenario_seconds: float
    tracks_done: int
    poses_done: int
    connections_done: int
    online_seconds: float
    update_ms: list[float] = field(default_factory=list)
    update_cpu_ms: list[float] = field(default_factory=list)
    update_thread_cpu_ms: list[float] = field(default_factory=list)
    update_rss_mib: list[float] = field(default_factory=list)
    update_rss_before_mib: list[float] = field(default_factory=list)
    update_poses: list[int] = field(default_factory=list)
    checkpoints: list[Checkpoint] = field(default_factory=list)
    missing_checkpoints: list[int] = field(default_factory=list)
    save_seconds: float | None = None
    load_seconds: float | None = None
    load_note: str = ''
    state_mib: float | None = None
    batch_seconds: float | None = None
    batch_iterations: int | None = None
    batch_converged: bool | None = None
    rss_before_batch_mib: float | None = None
    peak_rss_before_batch_mib: float | None = None
    peak_rss_after_batch_mib: float | None = None
    batch_stages: list[Stage] = field(default_factory=list)


def state_nbytes(al: TrackWindowAligner) -> int:
    """Bytes the aligner's state holds (filled rows of its tables, the id index, the
    duplicate keys, the joint priors), without the spare capacity and the last adjustment."""
    n = al.state.idarr.n
    st = al.state
    arrays = [st.idarr.a, st.trackarr.a, st.stamparr.a, st.T[:n], st.cov.packed[:n],
              st.frozen[:n], st.src.a, st.dst.a, st.z.a, st.ccov.packed, st.cross.a,
              al.state.status.a, al.state.fp.a]
    arrays += [al.state.track_conns[t] for t in al.state.tracks if t in al.state.track_conns]
    for idx, mean, info in al.state.priors:  # a block-banded information: its BSR arrays
        arrays += [idx, mean] + ([info.data, info.indices, info.indptr]
                                 if hasattr(info, 'indptr') else [info])
    total = sum(a.nbytes for a in arrays) + al.state.index.nbytes()
    total += sys.getsizeof(al.state.pairs) + 160 * len(al.state.pairs)  # 3-tuples of ints
    return total


def rss_slope(poses: list[int], rss: list[float], block: int) -> float:
    """KiB per pose of the least-squares line through the lowest RSS sample (MiB) of each run of
    ``block`` consecutive samples (the first run also takes the samples left over), against the
    poses there: the growth of the memory the process
    returns to between tracks. Single samples also catch window-sized transients that come and
    go from one track to the next (~27 MiB at 200-pose tracks: the window's factor and selected
    inverse, in the heap or given back to the kernel depending on where glibc placed them), which
    a two-point difference or a plain fit turns into a growth per pose; a leak raises the
    minima too."""
    x, y = np.asarray(poses, float), np.asarray(rss, float)
    block = max(1, int(block))
    k = x.size // block
    if k < 2:
        return float('nan')
    # k runs of `block` samples ending at the last one; the first also takes the remainder
    bounds = [0] + [x.size - (k - i) * block for i in range(1, k)] + [x.size]
    low = [a + int(np.argmin(y[a:b])) for a, b in zip(bounds[:-1], bounds[1:])]
    return 1024.0 * float(np.polyfit(x[low], y[low], 1)[0])


def scenario(args: argparse.Namespace):
    """The scaled aerial survey, its noisy measurements and the figures to fill."""
    t0 = time.perf_counter()
    sc = aerial_scenario(n_tracks=args.tracks, positions_per_swath=args.positions_per_swath)
    noisy = perturb(sc.true_motions('se3'), NoiseModel(args.noise, sc.depth_m),
                    np.random.default_rng(args.seed))
    fig = ScaleFigures(args.tracks, 2 * args.positions_per_swath, args.window, args.policy,
                       time.perf_counter() - t0, 0, 0, 0, 0.0)
    return sc, noisy, fig


def batch_only(args: argparse.Namespace) -> ScaleFigures:
    """``--batch-only``: the whole survey's state without window updates, poses at the
    simulator's truth (as if the online alignment had converged there), then ``refine_batch``."""
    sc, noisy, fig = scenario(args)
    al = NoSolveAligner(aligner_config(args), sc.T_world_node[0])
    t_start = time.perf_counter()
    chunk: list[Measurement] = []
    for m in lazy_measurements(sc, noisy.z, noisy.cov):
        chunk.append(m)
        if len(chunk) == 10_000:  # covariances checked together (same result, faster)
            al.add_measurements(chunk)
            chunk = []
    al.add_measurements(chunk)
    al.finish_track()
    fig.online_seconds = time.perf_counter() - t_start
    n = al.state.idarr.n
    al.state.T[:n] = sc.T_world_node[al.state.idarr.a]
    st = al.stats
    fig.poses_done, fig.connections_done = st.n_nodes, st.n_connections
    fig.tracks_done = len(al.state.tracks)
    del sc, noisy
    refine(al, fig, args.stages)
    return fig


def refine(al: TrackWindowAligner, fig: ScaleFigures, stages: bool = False) -> None:
    """``al.refine_batch()`` with its time, iterations and the process's RSS before and peak
    RSS after, into ``fig`` (with ``stages``: per stage too, see :class:`StageProbe`)."""
    fig.rss_before_batch_mib = rss_mib()
    fig.peak_rss_before_batch_mib = peak_rss_mb()
    if stages:
        with StageProbe() as probe:
            up = al.refine_batch()
        fig.batch_stages = probe.stages
    else:
        up = al.refine_batch()
    fig.batch_seconds = up.update_ms / 1e3
    fig.batch_iterations, fig.batch_converged = up.iterations, up.converged
    fig.peak_rss_after_batch_mib = peak_rss_mb()


def lazy_measurements(sc: Scenario, z: np.ndarray, cov: np.ndarray) -> Iterator[Measurement]:
    """The scenario's connections in acquisition order (as ``Scenario.measurements``), one at a
    time, so that 600,000 measurement objects never exist at once."""
    order = np.lexsort((sc.src, sc.dst))
    tr, st, cons = sc.track_ids, sc.stamps_ns, sc.consecutive
    for k in order.tolist():
        i, j = int(sc.src[k]), int(sc.dst[k])
        yield Measurement(i, j, int(tr[i]), int(tr[j]), z[k], cov[k], int(st[j]),
                          'consecutive' if cons[k] else 'cross')


RESTORE = """
import sys, time
from ga_ros.core.window.persistence import load_state
t = time.perf_counter()
al = load_state(sys.argv[1]).aligner
print(time.perf_counter() - t, al.stats.n_nodes)
"""


def timed_restore(path: Path, n_nodes: int, timeout_s: float) -> tuple[float | None, str]:
    """Seconds of ``load_state(path).aligner`` in a child process (so that a slow restore
    can be cut at ``timeout_s``), and a note."""
    import subprocess

    try:
        res = subprocess.run([sys.executable, '-c', RESTORE, str(path)], capture_output=True,
                             text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return None, f'not finished after {timeout_s:.0f} s'
    if res.returncode != 0:
        return None, f'failed: {res.stderr.strip()[-300:]}'
    seconds, n = res.stdout.split()
    if int(n) != n_nodes:
        return None, f'restored {n} nodes instead of {n_nodes}'
    return float(seconds), 'ok'


def aligner_config(args: argparse.Namespace) -> AlignerConfig:
    """The aligner's settings from the command line (the rest: AlignerConfig's defaults)."""
    extra = {k: int(v) for k, v in (('refine_every_tracks', args.refine_every),
                                    ('refine_horizon_tracks', args.refine_horizon),
                                    ('prior_band', args.prior_band),
                                    ('prior_hubs', args.prior_hubs)) if v is not None}
    return AlignerConfig(window_tracks=args.window, freeze_policy=args.policy, **extra)


class UpdateRecorder:
    """Records each window update of :func:`run` into its :class:`ScaleFigures` and takes a
    :class:`Checkpoint` when the number of finished tracks is one of ``checkpoints``."""

    def __init__(self, args: argparse.Namespace, al: TrackWindowAligner, sc: Scenario,
                 fig: ScaleFigures, checkpoints: list[int]) -> None:
        self.args, self.al, self.sc, self.fig = args, al, sc, fig
        self.checkpoints = checkpoints
        self.waits: list[float] = []
        self.first_cp: Checkpoint | None = None

    def record(self, up: UpdateResult, cpu_ms: float, thread_ms: float,
               rss_before: float) -> None:
        """One update: its wall time (ms), the CPU time (ms) of the process and of the
        update's own thread during it, the RSS (MiB) before the track's last measurement."""
        fig, al = self.fig, self.al
        fig.update_ms.append(up.update_ms)
        fig.update_cpu_ms.append(cpu_ms)
        fig.update_thread_cpu_ms.append(thread_ms)
        fig.update_rss_mib.append(rss_mib())
        fig.update_rss_before_mib.append(rss_before)
        fig.update_poses.append(al.stats.n_nodes)
        self.waits.append(up.refine_wait_ms)
        if self.args.verbose:
            print(f'  track {up.track_id:4d}: {up.update_ms:9.1f} ms ({cpu_ms:9.1f} ms CPU, '
                  f'{thread_ms:.1f} in its thread), '
                  f'window {up.n_window_nodes} nodes, {up.iterations} iterations, '
                  f'{up.n_outliers} excluded / {up.n_readmitted} re-admitted by the gate, '
                  f'RSS {fig.update_rss_mib[-1]:.0f} MiB, '
                  f'refinement wait + install {up.refine_wait_ms:.0f} ms'
                  + (f' (refinement after {up.refined_after_tracks} tracks: '
                     f'{up.refine_reason})' if up.refined_after_tracks >= 0 else ''),
                  file=sys.stderr, flush=True)
        if len(fig.update_ms) in self.checkpoints:
            fig.checkpoints.append(self._checkpoint(up))

    def _checkpoint(self, up: UpdateResult) -> Checkpoint:
        """Figures over the ``--span`` updates ending with ``up``."""
        fig, al, span = self.fig, self.al, self.args.span
        done = len(fig.update_ms)
        ms = np.array(fig.update_ms[max(0, done - span):])
        cpu = np.array(fig.update_cpu_ms[max(0, done - span):])
        own = np.array(fig.update_thread_cpu_ms[max(0, done - span):])
        wait = np.array(self.waits[max(0, done - span):])
        poses = done * fig.poses_per_track
        path = al.corrected_path()
        snap = al.handoff.snap
        cp = Checkpoint(done, poses, float(np.percentile(ms, 50)),
                        float(np.percentile(ms, 95)), float(ms.max()),
                        float(np.percentile(cpu, 50)), float(np.percentile(cpu, 95)),
                        up.n_window_nodes, fig.update_rss_mib[-1], None,
                        state_nbytes(al) / max(1, al.stats.n_nodes),
                        float(np.percentile(wait, 50)), float(np.percentile(wait, 95)),
                        children_rss_mib(), 0 if snap is None else snap.node_ids.size,
                        ate(path.T_world_node, self.sc.T_world_node[path.node_ids]).rmse,
                        float(np.percentile(own, 50)), float(np.percentile(own, 95)))
        first = self.first_cp
        if first is None:
            self.first_cp = cp
        elif poses > first.poses:
            cp.kib_per_pose_since_first = (1024.0 * (cp.rss_mib - first.rss_mib)
                                           / (poses - first.poses))
            cp.kib_per_pose_fit = rss_slope(fig.update_poses[first.tracks - 1:],
                                            fig.update_rss_before_mib[first.tracks - 1:],
                                            max(1, span // 2))
        return cp


def run(args: argparse.Namespace) -> ScaleFigures:
    """The online run over the whole survey (or until ``--max-seconds``), then the state save
    and restore and the batch refinement unless ``--no-save`` / ``--no-batch``."""
    sc, noisy, fig = scenario(args)
    checkpoints = sorted({int(c) for c in args.checkpoints.split(',') if c.strip()})
    al = TrackWindowAligner(aligner_config(args), sc.T_world_node[0])
    rec = UpdateRecorder(args, al, sc, fig, checkpoints)
    t_start = time.perf_counter()
    if _stream(args, al, sc, noisy, rec, t_start):
        rss_before = rss_mib()
        cpu0, own0 = time.process_time(), time.thread_time()
        last = al.finish_track()
        if last is not None:
            rec.record(last, 1e3 * (time.process_time() - cpu0),
                       1e3 * (time.thread_time() - own0), rss_before)
    fig.online_seconds = time.perf_counter() - t_start
    st = al.stats
    fig.tracks_done = len(fig.update_ms)
    fig.poses_done, fig.connections_done = st.n_nodes, st.n_connections
    fig.missing_checkpoints = [c for c in checkpoints if c > fig.tracks_done]
    if not args.no_save:
        save_and_restore(al, fig, args.restore_timeout)
    if not args.no_batch:
        refine(al, fig, args.stages)
    return fig


def _stream(args: argparse.Namespace, al: TrackWindowAligner, sc: Scenario, noisy,
            rec: UpdateRecorder, t_start: float) -> bool:
    """Feed the survey's measurements in acquisition order, recording every update; False when
    stopped by ``--max-seconds`` (the last track then stays open), True at the end of the
    survey."""
    rss_before = rss_mib()
    for m in lazy_measurements(sc, noisy.z, noisy.cov):
        if al.open_track is not None and int(m.dst_track) != al.open_track:
            rss_before = rss_mib()  # this measurement ends the track: the RSS between tracks
        cpu0, own0 = time.process_time(), time.thread_time()
        ups = al.add_measurement(m)
        for up in ups:  # at most one: the CPU time of the call is the update's
            rec.record(up, 1e3 * (time.process_time() - cpu0),
                       1e3 * (time.thread_time() - own0), rss_before)
        if ups and args.max_seconds and time.perf_counter() - t_start > args.max_seconds:
            return False
    return True


def save_and_restore(al: TrackWindowAligner, fig: ScaleFigures, timeout_s: float) -> None:
    """Save the aligner's state to a temporary file and restore it in a child process
    (:func:`timed_restore`): times, file size and note into ``fig``."""
    st = al.stats
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / 'state.npz'
        t = time.perf_counter()
        save_state(al, path)
        fig.save_seconds = time.perf_counter() - t
        fig.state_mib = path.stat().st_size / 2**20
        fig.load_seconds, fig.load_note = timed_restore(path, st.n_nodes, timeout_s)


def _fmt(x: float | None, spec: str = '.2f') -> str:
    return '-' if x is None else format(x, spec)


def print_table(fig: ScaleFigures) -> None:
    print(f'aerial survey: {fig.tracks_requested} double tracks x {fig.poses_per_track} poses '
          f'requested; window K = {fig.window_tracks}, {fig.policy}; scenario built in '
          f'{fig.scenario_seconds:.1f} s')
    print(f'online: {fig.tracks_done} tracks, {fig.poses_done:,} poses, '
          f'{fig.connections_done:,} connections in {fig.online_seconds:.0f} s')
    print()
    print('| tracks | poses | update ms p50 | p95 | max | CPU ms p50 | CPU p95 | thread CPU ms '
          'p50 / p95 | refinement wait ms p50 / p95 | window nodes | refinement nodes | '
          'RSS MiB | worker RSS MiB | '
          'KiB/pose since first | KiB/pose fit | state B/pose | ATE rigid m |')
    print('|---:|---:|---:|---:|---:|---:|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|')
    for c in fig.checkpoints:
        print(f'| {c.tracks} | {c.poses:,} | {c.update_ms_p50:.0f} | {c.update_ms_p95:.0f} | '
              f'{c.update_ms_max:.0f} | {c.cpu_ms_p50:.0f} | {c.cpu_ms_p95:.0f} | '
              f'{c.thread_cpu_ms_p50:.0f} / {c.thread_cpu_ms_p95:.0f} | '
              f'{c.refine_wait_ms_p50:.0f} / {c.refine_wait_ms_p95:.0f} | '
              f'{c.window_nodes:,} | {c.horizon_nodes:,} | {c.rss_mib:.0f} | '
              f'{c.worker_rss_mib:.0f} | {_fmt(c.kib_per_pose_since_first)} | '
              f'{_fmt(c.kib_per_pose_fit)} | '
              f'{c.state_bytes_per_pose:.0f} | {c.ate_rigid_m:.3f} |')
    for c in fig.missing_checkpoints:
        print(f'| {c} | {c * fig.poses_per_track:,} | not reached | | | | | | | | | | | | | | |')
    if len(fig.checkpoints) >= 2:
        a, b = fig.checkpoints[0], fig.checkpoints[-1]
        print(f'\np95 ratio, {b.tracks} vs {a.tracks} tracks: wall '
              f'{b.update_ms_p95 / a.update_ms_p95:.2f}, CPU {b.cpu_ms_p95 / a.cpu_ms_p95:.2f}, '
              f'thread CPU {b.thread_cpu_ms_p95 / a.thread_cpu_ms_p95:.2f}')
    print()
    if fig.save_seconds is not None:
        restore = (f'{fig.load_seconds:.2f} s' if fig.load_seconds is not None
                   else fig.load_note)
        print(f'state save {fig.save_seconds:.2f} s, restore {restore}, '
              f'file {fig.state_mib:.1f} MiB ({fig.poses_done:,} poses)')
    if fig.batch_seconds is not None:
        print(f'batch refinement of {fig.poses_done:,} poses: {fig.batch_seconds:.1f} s, '
              f'{fig.batch_iterations} iterations, converged {fig.batch_converged}; RSS before '
              f'{fig.rss_before_batch_mib:.0f} MiB (process peak so far '
              f'{fig.peak_rss_before_batch_mib:.0f}), peak RSS after '
              f'{fig.peak_rss_after_batch_mib:.0f} MiB')
    if fig.batch_stages:
        print('\n| stage of refine_batch | s | RSS at start MiB | sampled peak MiB | '
              'process peak after MiB |')
        print('|---|---:|---:|---:|---:|')
        for st in fig.batch_stages:
            print(f'| {st.name} | {st.seconds:.1f} | {st.rss_start_mib:.0f} | '
                  f'{st.rss_peak_mib:.0f} | {st.maxrss_after_mib:.0f} |')


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog='ga-ros bench scale', description=__doc__.split('\n\n')[0], allow_abbrev=False)
    p.add_argument('--tracks', type=int, default=100, help='double tracks (default 100)')
    p.add_argument('--positions-per-swath', type=int, default=500,
                   help='poses per swath; a double track has twice as many (default 500)')
    p.add_argument('--window', type=int, default=5, help='window tracks K (default 5)')
    p.add_argument('--policy', default='weighted', choices=tuple(FREEZE_POLICIES))
    p.add_argument('--noise', type=float, default=5.0, help='noise level in percent')
    p.add_argument('--refine-every', type=int, default=None,
                   help='refine_every_tracks (default: the aligner default; 0 = off)')
    p.add_argument('--refine-horizon', type=int, default=None,
                   help='refine_horizon_tracks (default: the aligner default; 0 = the whole '
                        'survey)')
    p.add_argument('--prior-band', type=int, default=None,
                   help='prior_band (default: the aligner default; -1 = dense priors)')
    p.add_argument('--prior-hubs', type=int, default=None,
                   help='prior_hubs (default: the aligner default)')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--checkpoints', default='25,100,500',
                   help='comma-separated track counts where figures are taken')
    p.add_argument('--span', type=int, default=10,
                   help='tracks before each checkpoint over which update times are summarised')
    p.add_argument('--max-seconds', type=float, default=0.0,
                   help='stop the online run after this many seconds (0 = no limit)')
    p.add_argument('--no-batch', action='store_true', help='skip the batch refinement')
    p.add_argument('--no-save', action='store_true', help='skip the state save/restore')
    p.add_argument('--batch-only', action='store_true',
                   help='only the batch refinement: the state is filled without window updates '
                        'and the poses set to the truth (peak RSS and time of refine_batch)')
    p.add_argument('--stages', action='store_true',
                   help='time and peak RSS of each stage of the batch refinement')
    p.add_argument('--restore-timeout', type=float, default=300.0,
                   help='give up the (child-process) state restore after this many seconds')
    p.add_argument('--json', action='store_true', help='print the figures as JSON')
    p.add_argument('-v', '--verbose', action='store_true', help='one line per track on stderr')
    args = p.parse_args(argv)
    with limit_blas_threads():
        fig = batch_only(args) if args.batch_only else run(args)
    if args.json:
        print(json.dumps(asdict(fig), indent=1))
    else:
        print_table(fig)
    return 0

