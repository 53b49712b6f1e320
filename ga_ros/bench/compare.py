"""``ga-ros bench compare``: ga-ros against GTSAM in one run on the same machine (issue 10).

Batch: the paper's aerial survey (25 double tracks, 10 % noise, F2F start, written as g2o) and
every shared pose graph (``--min-poses``: only those of at least that many poses), each solved
by ``ga-ros solve FILE --out OUT`` (its default start, ``--init auto``) and by GTSAM's
Levenberg-Marquardt from the file's initial guess (``gtsam.readG2o``, default
``LevenbergMarquardtParams``, ``gtsam.writeG2o``), each in a fresh process: whole-process wall
time (start-up, parse, solve, write), solver time, iterations, factorisations (ga-ros), peak
RSS of the process, and the cost ``sum e' Omega e`` of both results evaluated by the same code.

Track by track: the aerial survey (K = 5, weighted parameters) through
:class:`~ga_ros.core.window.TrackWindowAligner` against GTSAM's ``IncrementalFixedLagSmoother``
with a lag of K tracks: median and p95 update time, ATE (rigid-aligned) of the final path.

GTSAM is optional: ``pip install -r requirements-bench.txt``; without it only ga-ros runs.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ga_ros.bench.gtsam_runner import INSTALL_HINT, gtsam_installed
from ga_ros.bench.linalg import GRAPHS
from ga_ros.bench.survey import NoisySurvey, noisy_survey


@dataclass
class Run:
    """One process: wall time, CPU time (user + system), peak RSS and what it printed (JSON)."""

    wall_s: float
    peak_rss_mib: float
    out: dict
    cpu_s: float = float('nan')


def _hwm_mib(pid: int) -> float:
    """Peak resident set (``VmHWM``) of a live process, MiB; 0 once it has exited.

    ``ru_maxrss`` from ``wait4`` is not used: Linux carries the forking parent's peak into the
    child across ``exec``, so every child would report at least this benchmark's own size.
    """
    try:
        with open(f'/proc/{pid}/status', encoding='ascii') as f:
            for line in f:
                if line.startswith('VmHWM:'):
                    return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def run_process(args: list[str]) -> Run:
    """Run a Python module in a fresh interpreter, sampling its peak RSS every 20 ms.

    The CPU time is the child's user + system time (``RUSAGE_CHILDREN`` before and after it is
    reaped): on a shared machine it varies far less than the wall time."""
    with tempfile.TemporaryFile('w+') as out, tempfile.TemporaryFile('w+') as err:
        r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        proc = subprocess.Popen([sys.executable, '-m', *args], stdout=out, stderr=err)
        rss = 0.0
        while proc.poll() is None:
            rss = max(rss, _hwm_mib(proc.pid))
            time.sleep(0.02)
        wall = time.perf_counter() - t
        r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpu = r1.ru_utime - r0.ru_utime + r1.ru_stime - r0.ru_stime
        out.seek(0)
        err.seek(0)
        if proc.returncode != 0:
            raise RuntimeError(f'{" ".join(args)} failed: {err.read().strip().splitlines()[-1:]}')
        return Run(wall, rss, json.loads(out.read().strip().splitlines()[-1]), cpu)


def compile_package() -> None:
    """Byte-compile ``ga_ros`` before timing processes, as installing a wheel does.

    An editable install run with ``PYTHONDONTWRITEBYTECODE=1`` (as some CI and sandbox
    environments set) compiles every ga_ros module from source in every process, ~0.3 s of
    start-up that an installed package never pays; GTSAM's side is a compiled extension.
    """
    import compileall

    import ga_ros

    compileall.compile_dir(str(Path(ga_ros.__file__).parent), quiet=1)


def aerial(noise_pct: float = 10.0, seed: int = 0) -> NoisySurvey:
    """The paper's aerial survey (25 double tracks) with ``noise_pct`` % noise, draw ``seed``."""
    return noisy_survey(25, noise_pct, seed)


@dataclass
class BatchRow:
    graph: str
    poses: int
    ga_wall_s: float
    ga_cpu_s: float
    ga_solver_s: float
    ga_iterations: int
    ga_factorisations: int
    ga_rss_mib: float
    ga_cost: float
    gt_wall_s: float = float('nan')
    gt_cpu_s: float = float('nan')
    gt_solver_s: float = float('nan')
    gt_iterations: int = -1
    gt_rss_mib: float = float('nan')
    gt_cost: float = float('nan')


def best_row(rows: list[BatchRow]) -> BatchRow:
    """One row from repeated runs of the same graph: each time and peak-RSS column is its own
    minimum over the runs (the run least disturbed by the other processes of a shared machine),
    iterations, factorisations and costs those of the first run (they do not change)."""
    out = BatchRow(**asdict(rows[0]))
    for f in ('ga_wall_s', 'ga_cpu_s', 'ga_solver_s', 'ga_rss_mib', 'gt_wall_s', 'gt_cpu_s',
              'gt_solver_s', 'gt_rss_mib'):
        setattr(out, f, min(getattr(r, f) for r in rows))
    return out


def batch_row(name: str, path: Path, tmp: Path, with_gtsam: bool) -> BatchRow:
    from ga_ros.io.g2o import graph_cost, read_g2o

    g = read_g2o(path)
    ga = run_process(['ga_ros.cli.main', 'solve', str(path), '--out', str(tmp / 'ga.g2o'),
                      '--json'])
    res = ga.out
    fact = sum(int(s.get('factorisations', 0)) for s in res['stages'])
    row = BatchRow(name, g.n_vertices, ga.wall_s, ga.cpu_s, res['seconds'], res['iterations'],
                   fact, ga.peak_rss_mib, res['cost'])
    if with_gtsam:
        gt = run_process(['ga_ros.bench.gtsam_runner', 'batch', str(path), str(tmp / 'gt.g2o')])
        out = read_g2o(tmp / 'gt.g2o')
        index = {int(v): k for k, v in enumerate(out.vertex_ids)}
        T = out.T_init[[index[int(v)] for v in g.vertex_ids]]
        row.gt_wall_s, row.gt_solver_s = gt.wall_s, gt.out['solver_seconds']
        row.gt_cpu_s = gt.cpu_s
        row.gt_iterations, row.gt_rss_mib = gt.out['iterations'], gt.peak_rss_mib
        row.gt_cost = graph_cost(g, T)
    return row


@dataclass
class TrackRow:
    tracks: int
    window: int
    ga_p50_ms: float
    ga_p95_ms: float
    ga_ate_m: float
    gt_p50_ms: float = float('nan')
    gt_p95_ms: float = float('nan')
    gt_ate_m: float = float('nan')


def dump_tracks(path: Path, sc, nm) -> None:
    """The aerial survey's connections (node indices, acquisition order) for the GTSAM runner."""
    index = {int(v): k for k, v in enumerate(sc.node_ids)}
    ms = sc.measurements(nm.z, nm.cov)
    np.savez(path, src=np.array([index[m.src_id] for m in ms]),
             dst=np.array([index[m.dst_id] for m in ms]), z=np.stack([m.z for m in ms]),
             cov=np.stack([m.cov for m in ms]), node_track=np.asarray(sc.track_ids),
             T_first=sc.T_world_node[0])


def track_row(tmp: Path, window: int, with_gtsam: bool) -> TrackRow:
    from ga_ros.bench.core import bench_window
    from ga_ros.eval.metrics import ate

    fig = bench_window(25, 'weighted', window, 10.0, 0, compare_batch=False)
    row = TrackRow(25, window, fig.per_track_ms_p50, fig.per_track_ms_p95,
                   fig.ate_rigid_window_m)
    if with_gtsam:
        sc, nm = aerial()
        dump_tracks(tmp / 'tracks.npz', sc, nm)
        gt = run_process(['ga_ros.bench.gtsam_runner', 'tracks', str(tmp / 'tracks.npz'),
                          str(window)])
        ms = np.asarray(gt.out['update_ms'])
        row.gt_p50_ms, row.gt_p95_ms = float(np.median(ms)), float(np.percentile(ms, 95))
        row.gt_ate_m = ate(np.asarray(gt.out['T_world_node']), sc.T_world_node, 'rigid').rmse
    return row


def table(batch: list[BatchRow], tracks: list[TrackRow]) -> str:
    lines = ['| graph | poses | ga-ros whole s | GTSAM whole s | ratio | whole CPU s ga-ros / '
             'GTSAM | CPU ratio | ga-ros solver s | GTSAM solver s | ratio | iterations '
             'ga-ros / GTSAM | factorisations ga-ros | cost ratio | peak RSS MiB ga-ros / '
             'GTSAM |',
             '|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|']
    for r in batch:
        lines.append(
            f'| {r.graph} | {r.poses} | {r.ga_wall_s:.2f} | {r.gt_wall_s:.2f} | '
            f'{r.ga_wall_s / r.gt_wall_s:.2f} | {r.ga_cpu_s:.2f} / {r.gt_cpu_s:.2f} | '
            f'{r.ga_cpu_s / r.gt_cpu_s:.2f} | {r.ga_solver_s:.2f} | {r.gt_solver_s:.2f} | '
            f'{r.ga_solver_s / r.gt_solver_s:.2f} | {r.ga_iterations} / {r.gt_iterations} | '
            f'{r.ga_factorisations} | {r.ga_cost / r.gt_cost:.6f} | '
            f'{r.ga_rss_mib:.0f} / {r.gt_rss_mib:.0f} |')
    lines += ['', '| track by track (aerial, 10 %) | K | ga-ros p50 / p95 ms | GTSAM IFLS p50 / '
              'p95 ms | p50 ratio | ATE rigid m ga-ros / GTSAM |',
              '|---|---:|---:|---:|---:|---:|']
    for t in tracks:
        lines.append(f'| {t.tracks} tracks | {t.window} | {t.ga_p50_ms:.0f} / '
                     f'{t.ga_p95_ms:.0f} | {t.gt_p50_ms:.0f} / {t.gt_p95_ms:.0f} | '
                     f'{t.ga_p50_ms / t.gt_p50_ms:.2f} | {t.ga_ate_m:.3f} / {t.gt_ate_m:.3f} |')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog='ga-ros bench compare', description=__doc__.split('\n\n')[0], allow_abbrev=False)
    p.add_argument('--data', type=Path, default=GRAPHS, help=f'pose graphs (default {GRAPHS})')
    p.add_argument('--window', type=int, default=5)
    p.add_argument('--no-tracks', action='store_true', help='batch rows only')
    p.add_argument('--min-poses', type=int, default=0,
                   help='batch: only the pose graphs of at least this many poses (default 0: '
                   'every graph)')
    p.add_argument('--repeat', type=int, default=1,
                   help='batch: run each graph N times (ga-ros and GTSAM in turn, fresh '
                   'processes) and report each time column as its minimum (default 1)')
    p.add_argument('--json', action='store_true')
    args = p.parse_args(argv)
    with_gtsam = gtsam_installed()
    if not with_gtsam:
        print(INSTALL_HINT, file=sys.stderr)
    compile_package()
    from ga_ros.io.g2o import PoseGraph, read_g2o, write_g2o

    batch: list[BatchRow] = []
    tracks: list[TrackRow] = []
    with tempfile.TemporaryDirectory() as d:
        tmp = Path(d)
        sc, nm = aerial()
        write_g2o(tmp / 'aerial.g2o', PoseGraph.from_network(sc.network(nm.z, nm.cov),
                                                             sc.f2f(nm.z)))
        files = [('aerial (10 %)', tmp / 'aerial.g2o')]
        for f in sorted(args.data.glob('*.g2o')) if args.data.is_dir() else []:
            if read_g2o(f).n_vertices >= args.min_poses:
                files.append((f.stem, f))
        for name, path in files:
            batch.append(best_row([batch_row(name, path, tmp, with_gtsam)
                                   for _ in range(max(1, args.repeat))]))
            print(f'# {name}: done', file=sys.stderr, flush=True)
        if not args.no_tracks:
            tracks.append(track_row(tmp, args.window, with_gtsam))
    if args.json:
        print(json.dumps({'batch': [asdict(r) for r in batch],
                          'tracks': [asdict(t) for t in tracks]}))
    else:
        print(table(batch, tracks))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
