"""``ga-ros bench long``: a long survey with an absolute fix every track (issue 36 item 3).

The aerial simulator (:func:`ga_ros.sim.aerial.aerial_scenario`) flies ``--tracks`` double
tracks (default 1,000) of ``2 x --positions-per-swath`` poses (default 2 x 10) with
``--noise`` % noise: consecutive connections and cross-track connections to the adjacent swath.
The last node of every track gets an absolute position fix (its true position plus seeded
Gaussian noise of ``--fix-sigma`` m per axis, rotation unknown) just before the measurement that
ends the track, and the aligner runs with ``datum='fixes'`` and otherwise its default settings
(window, background refinement where the linearisation demands it, inline or in a worker
process by its size, horizon), as ``ga-ros replay --absolute-topic`` does. Measurements are
generated lazily in acquisition order.

Printed (every figure says what it compares):

* update time (``UpdateResult.update_ms``: wall time of the track end, including the wait for
  the background refinement at its hand-off) p50 / p95 over the tracks of ``--early`` (default
  50-100) and of the last 100 tracks (900-1,000 by default), and the ratio of the two p95
  (target <= 1.2: the cost of an update does not grow with the survey);
* the same for the CPU time of all processes (this one, its threads, the refinement worker)
  from one track end to the next: the figure to compare on a loaded machine;
* the mean update time per quarter of the run;
* CPU seconds of all processes (this one, its threads and the refinement worker) over the run,
  and per track;
* RSS (this process plus the worker) at the end of the early range and at the end, and the
  growth per pose between them; the same after a garbage collection and ``malloc_trim`` (what
  the process holds, without the freed heap glibc keeps); the aligner's own state bytes per
  pose.

The machine's load enters every time; the CPU figures are the ones to compare across runs.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field

import numpy as np

from ga_ros.bench.cpu import all_cpu_seconds
from ga_ros.bench.scale import children_rss_mib, lazy_measurements, rss_mib, state_nbytes
from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.geometry import se3
from ga_ros.runtime import limit_blas_threads
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb


@dataclass
class LongSurveyFigures:
    """Results of one run (times in ms, CPU in s, RSS in MiB)."""

    tracks: int
    poses_per_track: int
    update_ms: list[float] = field(default_factory=list)
    refine_wait_ms: list[float] = field(default_factory=list)
    cpu_ms: list[float] = field(default_factory=list)
    cpu_s: float = 0.0
    early: tuple[int, int] = (50, 100)
    late: tuple[int, int] = (900, 1000)
    rss_early_mib: float = 0.0
    rss_end_mib: float = 0.0
    held_early_mib: float = 0.0
    held_end_mib: float = 0.0
    state_bytes_per_pose: float = 0.0
    poses: int = 0
    fixes_used: int = 0
    refinements_installed: int = 0

    def p(self, rng: tuple[int, int], q: float, cpu: bool = False) -> float:
        """Percentile ``q`` of the update time (``cpu``: of the CPU of all processes per track)
        over the tracks ``[rng[0], rng[1])``."""
        a = np.asarray((self.cpu_ms if cpu else self.update_ms)[rng[0]:rng[1]])
        return float(np.percentile(a, q)) if a.size else float('nan')

    def quarters(self) -> list[float]:
        """Mean update time of each quarter of the run's tracks (ms)."""
        return [float(np.mean(q)) for q in np.array_split(np.asarray(self.update_ms), 4)
                if q.size]


def held_rss_mib() -> float:
    """This process's RSS (MiB) after a garbage collection and glibc's ``malloc_trim(0)``,
    which returns the freed heap that the allocator keeps for reuse: the memory the process
    holds. Elsewhere than glibc, the RSS after the collection."""
    import ctypes
    import gc

    gc.collect()
    try:
        ctypes.CDLL(None).malloc_trim(0)
    except (OSError, AttributeError):
        pass
    return rss_mib()


def run(args: argparse.Namespace) -> LongSurveyFigures:
    """The online run (module doc)."""
    sc = aerial_scenario(n_tracks=args.tracks, positions_per_swath=args.positions_per_swath)
    rng = np.random.default_rng(args.seed)
    noisy = perturb(sc.true_motions('se3'), NoiseModel(args.noise, sc.depth_m), rng)
    n_per = 2 * args.positions_per_swath
    fig = LongSurveyFigures(args.tracks, n_per)
    early = tuple(int(x) for x in args.early.split(','))
    fig.early = (min(early[0], args.tracks), min(early[1], args.tracks))
    fig.late = (max(fig.early[1], args.tracks - 100), args.tracks)
    cfg = AlignerConfig(datum='fixes', window_tracks=args.window,
                        refine_executor=args.executor)
    al = TrackWindowAligner(cfg, T_world_first=sc.T_world_node[0])
    fix_cov = np.diag([args.fix_sigma ** 2] * 3 + [-1.0] * 3)
    last_of = {}
    for i, t in enumerate(sc.track_ids.tolist()):
        last_of[t] = i  # node ids follow flight order: the track's last node
    stamps = sc.stamps_ns
    fixed = set()
    cpu0 = cpu_last = all_cpu_seconds()
    for m in lazy_measurements(sc, noisy.z, noisy.cov):
        t_open = al.open_track
        if t_open is not None and int(m.dst_track) != t_open and t_open not in fixed:
            k = last_of[t_open]
            p = sc.T_world_node[k][:3, 3] + rng.normal(0.0, args.fix_sigma, 3)
            fix = AbsoluteFix.from_covariance(int(stamps[k]),
                                              se3.from_translation_rotvec(p, np.zeros(3)),
                                              fix_cov, 'fix0')
            al.add_fix(FixTerm(k, se3.identity(), fix))
            fixed.add(t_open)
        for up in al.add_measurement(m):
            fig.update_ms.append(up.update_ms)
            fig.refine_wait_ms.append(up.refine_wait_ms)
            cpu = all_cpu_seconds()
            fig.cpu_ms.append(1e3 * (cpu - cpu_last))
            cpu_last = cpu
            done = len(fig.update_ms)
            if done == fig.early[1]:
                fig.rss_early_mib = rss_mib() + children_rss_mib()
                fig.held_early_mib = held_rss_mib() + children_rss_mib()
            if args.verbose:
                print(f'  track {done - 1:5d}: {up.update_ms:8.1f} ms (refinement wait '
                      f'{up.refine_wait_ms:.0f} ms), CPU of all processes since the last '
                      f'track {fig.cpu_ms[-1]:.0f} ms', file=sys.stderr, flush=True)
    up = al.finish_track()
    if up is not None:
        fig.update_ms.append(up.update_ms)
        fig.refine_wait_ms.append(up.refine_wait_ms)
        fig.cpu_ms.append(1e3 * (all_cpu_seconds() - cpu_last))
    fig.rss_end_mib = rss_mib() + children_rss_mib()
    fig.held_end_mib = held_rss_mib() + children_rss_mib()
    fig.cpu_s = all_cpu_seconds() - cpu0
    fig.poses = al.stats.n_nodes
    fig.state_bytes_per_pose = state_nbytes(al) / max(1, fig.poses)
    fig.fixes_used = al.fix_stats.added - al.fix_stats.outliers
    fig.refinements_installed = al.handoff.n_refinements
    al.close()
    return fig


def print_table(fig: LongSurveyFigures) -> None:
    e, late = fig.early, fig.late
    n = len(fig.update_ms)
    print(f'long survey: {n} double tracks x {fig.poses_per_track} poses ({fig.poses:,} poses), '
          f'a fix at the end of every track ({fig.fixes_used} used), cross-track connections; '
          f"datum='fixes', default window and refinement ({fig.refinements_installed} "
          'refinements installed)')
    print()
    print('| tracks | update ms (wall, incl. refinement wait) p50 | p95 | CPU ms of all '
          'processes per track p50 | p95 |')
    print('|---|---:|---:|---:|---:|')
    for a, b in (e, late):
        print(f'| {a}-{b} | {fig.p((a, b), 50):.1f} | {fig.p((a, b), 95):.1f} | '
              f'{fig.p((a, b), 50, True):.1f} | {fig.p((a, b), 95, True):.1f} |')
    print(f'\np95 of tracks {late[0]}-{late[1]} / p95 of tracks {e[0]}-{e[1]}: update time '
          f'{fig.p(late, 95) / fig.p(e, 95):.2f} (target <= 1.2), CPU of all processes '
          f'{fig.p(late, 95, True) / fig.p(e, 95, True):.2f}')
    print('mean update ms per quarter of the run: '
          + ' / '.join(f'{q:.1f}' for q in fig.quarters()))
    print(f'CPU of all processes (this one, its threads, the refinement worker): '
          f'{fig.cpu_s:.1f} s, {1e3 * fig.cpu_s / max(1, n):.1f} ms per track')
    span = (n - e[1]) * fig.poses_per_track
    growth = (1024.0 * (fig.rss_end_mib - fig.rss_early_mib) / span) if span > 0 else 0.0
    print(f'RSS (this process + worker): {fig.rss_early_mib:.0f} MiB after track {e[1]}, '
          f'{fig.rss_end_mib:.0f} MiB at the end: {growth:.2f} KiB per pose between them, '
          f'{1024.0 * fig.rss_end_mib / max(1, fig.poses):.1f} KiB per pose overall; '
          f'aligner state {fig.state_bytes_per_pose:.0f} B per pose')
    held = (1024.0 * (fig.held_end_mib - fig.held_early_mib) / span) if span > 0 else 0.0
    print(f'RSS held (the same after a garbage collection and malloc_trim: without the freed '
          f'heap glibc keeps for reuse): {fig.held_early_mib:.0f} MiB after track {e[1]}, '
          f'{fig.held_end_mib:.0f} MiB at the end: {held:.2f} KiB per pose between them')


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog='ga-ros bench long', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument('--tracks', type=int, default=1000, help='double tracks (default 1000)')
    p.add_argument('--positions-per-swath', type=int, default=10,
                   help='poses per swath; a double track has twice as many (default 10)')
    p.add_argument('--noise', type=float, default=5.0, help='noise level in percent')
    p.add_argument('--fix-sigma', type=float, default=2.0, help='fix noise, m per axis')
    p.add_argument('--window', type=int, default=5, help='window tracks K (default 5)')
    p.add_argument('--executor', default='auto', choices=('auto', 'process', 'thread', 'inline'),
                   help='refine_executor (default: auto, the default of the aligner)')
    p.add_argument('--early', default='50,100',
                   help='first and last+1 track of the early range (default 50,100)')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--json', action='store_true')
    p.add_argument('-v', '--verbose', action='store_true', help='one line per track on stderr')
    args = p.parse_args(argv)
    with limit_blas_threads():
        fig = run(args)
    if args.json:
        print(json.dumps(asdict(fig)))
    else:
        print_table(fig)
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
