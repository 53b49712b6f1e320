"""Monte-Carlo position NEES of the published covariances: policy x swath length x noise.

Issue #15 item 2 asks the published covariances to be honest (mean position NEES 3 +- 30 %)
for every policy, batch and after refinement. For every swath length of ``--per-swath`` and
noise level of ``--noise`` (percent of the true motion, :mod:`ga_ros.sim.noise`) the script flies
``--runs`` noisy aerial surveys of ``--tracks`` double tracks
(:func:`ga_ros.sim.aerial.aerial_scenario`) and prints the mean position NEES
(:func:`ga_ros.eval.position_nees`, over all nodes but the datum and all runs) of

* ``batch``: one adjustment of every connection (:func:`ga_ros.core.solver.solve`);
* each window policy of ``--policies`` (``weighted``, ``marginal``; ``+refine``: the background
  refinement after every track, run inline) fed the measurements in acquisition order, window
  ``--window`` tracks, refinement off unless ``+refine``;

and, with ``--profile``, the same NEES by track (the oldest first: frozen longest) and by
quarter of the position along the swath. ``diff`` is the mean squared Mahalanobis distance of
the window's estimate from the batch one under the batch covariance (0 when the window
reproduces the batch solution, as it does in the linear limit).

Examples::

    ga-ros bench nees --per-swath 100,400 --noise 1,5,10 --runs 3
    ga-ros bench nees --per-swath 400 --noise 10 --runs 2 --profile
    ga-ros bench nees --vce --tracks 6 --per-swath 100 --noise 5 --runs 10
    ga-ros bench nees --fix-vce --tracks 6 --per-swath 30 --fix-true 0.5,2,3 --runs 10

``--vce``: the stated covariances wrong by 4x and a biased source, with and without variance
components (:mod:`ga_ros.bench.nees_vce`). ``--fix-vce``: a GNSS that states 0.5 m where its
errors are 2-3 m, with and without the fix source's variance factor
(:mod:`ga_ros.bench.fix_vce`).
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import dataclass, field

import numpy as np

from ga_ros.core.solver import SolverConfig, solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.eval import position_nees
from ga_ros.runtime import limit_blas_threads
from ga_ros.sim.aerial import aerial_scenario
from ga_ros.sim.noise import NoiseModel, perturb


@dataclass
class Cell:
    """NEES of one estimator over the runs of one (swath length, noise) setting."""

    nees: list = field(default_factory=list)  # (n,) per node, one array per run
    diff: list = field(default_factory=list)  # (n,) squared distance to batch, batch sd
    seconds: float = 0.0

    def mean(self) -> float:
        return float(np.mean(np.concatenate(self.nees)))


def run_setting(tracks: int, per_swath: int, percent: float, runs: int, window: int,
                policies: list[str], seed: int) -> dict[str, Cell]:
    """Monte-Carlo of one setting: ``{estimator: Cell}`` (``'batch'`` first)."""
    sc = aerial_scenario(n_tracks=tracks, positions_per_swath=per_swath)
    rng = np.random.default_rng(seed)
    ids, truth = sc.node_ids[1:], sc.T_world_node[1:]
    cells = {k: Cell() for k in ['batch'] + policies}
    for _ in range(runs):
        nm = perturb(sc.true_motions(), NoiseModel(percent, sc.depth_m), rng)
        t0 = time.process_time()
        b = solve(sc.network(nm.z, nm.cov), sc.f2f(nm.z),
                  SolverConfig(tolerance=1e-8, max_iterations=50))
        cov_b = b.covariance(ids)
        cells['batch'].seconds += time.process_time() - t0
        cells['batch'].nees.append(position_nees(b.T_world_node[1:], cov_b, truth))
        cells['batch'].diff.append(np.zeros(ids.size))
        ms = sc.measurements(nm.z, nm.cov)
        for pol in policies:
            t0 = time.process_time()
            name, _, extra = pol.partition('+')
            cfg = AlignerConfig(window_tracks=window, freeze_policy=name,
                                refine_every_tracks=1 if extra == 'refine' else 0,
                                refine_executor='inline')
            al = TrackWindowAligner(cfg, sc.T_world_node[0])
            al.add_measurements(ms)
            al.finish_track()
            T_w = al.corrected_path().T_world_node[1:]
            cells[pol].nees.append(position_nees(T_w, al.covariances(ids), truth))
            cells[pol].diff.append(position_nees(T_w, cov_b, b.T_world_node[1:]))
            cells[pol].seconds += time.process_time() - t0
            al.close()
    return cells


def profile_lines(cells: dict[str, Cell], tracks: int, per_swath: int) -> list[str]:
    """NEES by track and by quarter of the along-swath position, per estimator."""
    node = np.arange(1, 2 * tracks * per_swath)
    track = node // (2 * per_swath)
    k = node % per_swath
    along = np.where((node // per_swath) % 2 == 0, k, per_swath - 1 - k)  # distance from x=0
    quarter = np.minimum(4 * along // per_swath, 3)
    out = []
    for name, c in cells.items():
        v = np.stack(c.nees)
        d = np.stack(c.diff)
        by_t = ' '.join(f'{v[:, track == t].mean():7.1f}' for t in range(tracks))
        by_q = ' '.join(f'{v[:, quarter == q].mean():7.1f}' for q in range(4))
        dd = ' '.join(f'{d[:, track == t].mean():6.1f}' for t in range(tracks))
        out.append(f'    {name:16s} by track {by_t} | by quarter {by_q} | diff by track {dd}')
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        prog='ga-ros bench nees', description=__doc__.split('\n')[0], allow_abbrev=False)
    ap.add_argument('--tracks', type=int, default=4)
    ap.add_argument('--per-swath', default='100,200,400', help='comma list of poses per swath')
    ap.add_argument('--noise', default='1,5,10', help='comma list of noise levels (percent)')
    ap.add_argument('--runs', type=int, default=3)
    ap.add_argument('--window', type=int, default=2)
    ap.add_argument('--policies', default='weighted,marginal,weighted+refine')
    ap.add_argument('--seed', type=int, default=1)
    ap.add_argument('--profile', action='store_true', help='NEES by track and along the swath')
    ap.add_argument('--json', action='store_true', help='also print one JSON line per setting')
    ap.add_argument('--vce', action='store_true',
                    help='instead: covariances stated 4x too small / 4x too large / with a '
                         'biased source, with and without variance components (batch and '
                         'online; ga_ros/bench/nees_vce.py); first --per-swath and --noise')
    ap.add_argument('--bias-sigmas', type=float, default=1.0,
                    help="--vce: the biased case's constant yaw bias per motion, in its sigmas")
    ap.add_argument('--fix-vce', action='store_true',
                    help='instead: a GNSS stating --fix-stated m where its errors are '
                         "--fix-true m, with and without the fix source's variance factor "
                         '(online and batch; ga_ros/bench/fix_vce.py); --tracks swaths of '
                         'the first --per-swath poses')
    ap.add_argument('--fix-stated', type=float, default=0.5,
                    help='--fix-vce: the sigma (m per axis) the fixes state')
    ap.add_argument('--fix-true', default='0.5,2,3',
                    help="--fix-vce: comma list of the fixes' true sigmas (m), a case each")
    ap.add_argument('--fix-every', type=int, default=5,
                    help='--fix-vce: a fix every this many nodes')
    args = ap.parse_args(argv)
    limit_blas_threads(1)
    if args.fix_vce:
        from ga_ros.bench.fix_vce import GnssSurvey, fix_vce_lines, run_fix_vce

        base = GnssSurvey(args.tracks, int(args.per_swath.split(',')[0]), args.fix_every,
                          args.fix_stated)
        true_m = [float(x) for x in args.fix_true.split(',') if x]
        result = run_fix_vce(base, true_m, args.runs, args.seed, args.window)
        print('\n'.join(fix_vce_lines(base, result, args.runs)))
        return 0
    if args.vce:
        from ga_ros.bench.nees_vce import run_vce_nees, vce_lines

        per = int(args.per_swath.split(',')[0])
        pct = float(args.noise.split(',')[0])
        print(f'NEES with wrong covariances: {args.tracks} double tracks of {per} poses a '
              f'swath, {pct:g} % noise, window {args.window}, {args.runs} runs (same draws in '
              f'every case), seed {args.seed}')
        result = run_vce_nees(args.tracks, per, pct, args.runs, args.window, args.seed,
                              args.bias_sigmas)
        print('\n'.join(vce_lines(result, args.runs)))
        return 0
    policies = [p for p in args.policies.split(',') if p]
    print(f'mean position NEES (expected 3, target 2.1-3.9); {args.tracks} double tracks, '
          f'window {args.window}, {args.runs} runs per setting, seed {args.seed}')
    head = ' '.join(f'{k:>16s}' for k in ['batch'] + policies)
    print(f'{"poses/swath":>11s} {"noise %":>7s} {head}   (mean diff to batch, batch sd^2)')
    for per in [int(x) for x in args.per_swath.split(',')]:
        for pct in [float(x) for x in args.noise.split(',')]:
            cells = run_setting(args.tracks, per, pct, args.runs, args.window, policies,
                                args.seed)
            vals = ' '.join(f'{c.mean():16.2f}' for c in cells.values())
            diffs = ' '.join(f'{float(np.mean(np.concatenate(c.diff))):.1f}'
                             for k, c in cells.items() if k != 'batch')
            print(f'{per:11d} {pct:7.1f} {vals}   ({diffs})', flush=True)
            if args.profile:
                print('\n'.join(profile_lines(cells, args.tracks, per)), flush=True)
            if args.json:
                print(json.dumps({'per_swath': per, 'noise_pct': pct, **{
                    k: {'nees': c.mean(), 'cpu_s': c.seconds,
                        'diff': float(np.mean(np.concatenate(c.diff)))}
                    for k, c in cells.items()}}), flush=True)
    return 0

