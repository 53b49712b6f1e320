"""``ga-ros bench fixwalk``: the real Plaza odometry with fixes whose offset wanders (a GNSS
receiver's multipath and atmosphere), adjusted in one batch without calibration, with a
constant fix offset, and with the offset a random walk about its constant
(:class:`~ga_ros.core.calibration.models.BiasWalk`), where the truth is known.

The run is ``bench fixes``' (:func:`~ga_ros.bench.fixes.load_plaza`: every odometry sample a
node, its stated covariance ``--sigma-xy`` / ``--sigma-yaw`` per step, by default close to
the odometry's own noise against the ground truth, the weak gauge prior of
``datum='fixes'`` on the first node). One fix source ``gnss``: every ``--interval`` seconds the
true position plus an offset ``b(t)`` in x and y plus white noise ``N(0, --noise^2)`` per axis
(x, y, z), stated with ``--noise``. The offset (``--truth``):

* ``walk``: a first-order Gauss-Markov process per axis (``--walk-sigma`` m stationary
  sigma, ``--walk-tau`` s correlation time: its increments over ``dt`` have the sigma
  ``sqrt(2 / tau) walk_sigma sqrt(dt)`` for ``dt << tau``), starting from its stationary
  distribution;
* ``constant``: ``--offset X,Y`` (m) over the whole run;
* ``none``: no offset.

Columns (2-D position RMSE against the ground truth, m / process CPU, s): ``plain``: the batch
without calibration; ``odom+const``: with the odometry's scale and yaw rate and the fix
source's constant offset (x, y; ``CalibrationConfig(fix_parameters=('offset_x',
'offset_y'))``: with one fix source its constant offset is the frame's and is not determined,
so this is the odometry calibration); ``odom+walk``: the same with each offset a
``BiasWalk`` (knots every ``--segment`` s, process noise ``--q`` m/sqrt(s) given);
``odom+walk q est``: the same with ``q`` estimated from the data (``estimate_sigma``, from
``--q``); ``GTSAM LM``: GTSAM's Levenberg-Marquardt on the same graph without calibration
(``GPSFactor`` per fix; skipped without gtsam). ``rmse frame`` below: the same against the
truth moved by the offset's mean over the fixes (what a single fix source cannot see: the
frame it defines). Printed below: each offset's estimate (walk or why not), and for a walk the
share of its knots within 3 sigma of the truth (the true offset at the knot less its mean over
the fixes).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.bench.cpu import rmse_cpu_cells
from ga_ros.bench.fix_calibration import plaza_graph
from ga_ros.bench.fixes import DEFAULT_MAT, PlazaRun, load_plaza
from ga_ros.bench.gtsam_runner import gtsam_installed
from ga_ros.core.calibration import (
    AdditionalParameter,
    BiasWalk,
    CalibrationConfig,
    FixObservations,
    fix_priors,
    solve_with_calibration,
)
from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.solver import solve
from ga_ros.geometry import se3

#: The columns of the table, in order (module doc).
COLUMNS = ('plain', 'odom+const', 'odom+walk', 'odom+walk q est', 'GTSAM LM')


@dataclass
class FixWalkFigures:
    """One setting: RMSE (m) against the truth and against the truth in the fixes' frame, CPU
    (s) per column (module doc); the offsets' report lines; the share of the knots within 3
    sigma of the truth per walk column."""

    truth: str
    interval_s: float
    noise_m: float
    n_poses: int
    n_fixes: int
    mean_offset_m: list[float]
    rmse_m: dict[str, float] = field(default_factory=dict)
    rmse_frame_m: dict[str, float] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)
    offsets: dict[str, list[str]] = field(default_factory=dict)
    knots_within_3sigma: dict[str, float] = field(default_factory=dict)


def gauss_markov(t_s: FloatArray, sigma_m: float, tau_s: float, rng: np.random.Generator
                 ) -> FloatArray:
    """(k,) a first-order Gauss-Markov process at the increasing times ``t_s`` (s): stationary
    sigma ``sigma_m`` (m), correlation time ``tau_s`` (s), drawn from its stationary
    distribution at ``t_s[0]`` (exact discretisation ``b_k+1 = a b_k + sqrt(1 - a^2) sigma
    w``, ``a = exp(-dt / tau)``)."""
    b = np.zeros(t_s.size)
    b[0] = rng.normal(0.0, sigma_m)
    for k in range(1, t_s.size):
        a = np.exp(-(t_s[k] - t_s[k - 1]) / tau_s)
        b[k] = a * b[k - 1] + np.sqrt(1.0 - a * a) * sigma_m * rng.normal()
    return b


def wandering_fixes(run: PlazaRun, interval_s: float, noise_m: float, offset: FloatArray,
                    seed: int) -> tuple[FixObservations, np.ndarray, FloatArray, FloatArray]:
    """The fixes of the module doc with the offsets ``offset`` (k, 2) (m, x and y, one per
    fix time ``0, interval_s, ...``): the observations, each fix's node index, measured
    position (for GTSAM) and true offset (k, 2)."""
    rng = np.random.default_rng(seed + 1)
    t = run.stamps_s
    want = np.arange(0.0, t[-1] + 1e-9, interval_s)
    idx = np.abs(t[None, :] - want[:, None]).argmin(axis=1)
    keep = np.r_[True, np.diff(idx) > 0]
    idx, off = idx[keep], np.asarray(offset, dtype=float)[keep]
    info = np.diag([noise_m ** -2] * 3 + [0.0] * 3)
    p = run.T_true[idx, :3, 3].copy()
    p[:, :2] += off
    p += rng.normal(0.0, noise_m, p.shape)
    terms = [FixTerm(int(i), se3.identity(), AbsoluteFix(
        int(round(t[i] * 1e9)), se3.from_translation_rotvec(q, np.zeros(3)), info, 'gnss'))
        for i, q in zip(idx, p)]
    obs = FixObservations(terms, np.repeat(info[None], len(terms), axis=0), t)
    return obs, idx, p, off


def true_offsets(run: PlazaRun, interval_s: float, truth: str, walk_sigma_m: float,
                 walk_tau_s: float, offset_m: FloatArray, seed: int) -> FloatArray:
    """(k, 2) the true offset at each fix time (module doc, ``--truth``)."""
    want = np.arange(0.0, run.stamps_s[-1] + 1e-9, interval_s)
    if truth == 'walk':
        rng = np.random.default_rng(seed)
        return np.stack([gauss_markov(want, walk_sigma_m, walk_tau_s, rng) for _ in range(2)],
                        axis=1)
    if truth == 'constant':
        return np.tile(np.asarray(offset_m, dtype=float)[:2], (want.size, 1))
    return np.zeros((want.size, 2))


def _rmse2(T: FloatArray, T_true: FloatArray, shift: FloatArray) -> float:
    d = T[:, :2, 3] - T_true[:, :2, 3] - shift
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def knots_within(par: AdditionalParameter, fix_t_s: FloatArray, off: FloatArray) -> float:
    """The share of a walk's knots within 3 sigma of the truth: the true offset ``off`` (k,)
    at the fixes ``fix_t_s`` (s), interpolated to the knots, less its mean over the fixes
    plus the estimated constant (the part of the offset the walk can see). NaN without a
    walk."""
    if par.walk is None:
        return float('nan')
    true = np.interp(par.walk.knots_s, fix_t_s, off) - off.mean() + par.value
    err = np.abs(np.asarray(par.walk.values) - true)
    return float(np.mean(err <= 3.0 * np.asarray(par.walk.sigmas)))


def bench_fixwalk(truth: str, interval_s: float, noise_m: float, walk_sigma_m: float,
                  walk_tau_s: float, offset_m: FloatArray, segment_s: float, q: float,
                  seed: int = 0, path: str | Path = DEFAULT_MAT, sigma_xy: float = 0.02,
                  sigma_yaw: float = 0.005, with_gtsam: bool = True) -> FixWalkFigures:
    """One setting of the benchmark (module doc)."""
    run = load_plaza(path)
    off = true_offsets(run, interval_s, truth, walk_sigma_m, walk_tau_s, offset_m, seed)
    obs, nodes, pos, off = wandering_fixes(run, interval_s, noise_m, off, seed)
    n = run.T_true.shape[0]
    ids, cov, net, cfg, gauge, dead, sources, dt = plaza_graph(run, sigma_xy, sigma_yaw)
    mean = off.mean(axis=0)
    fig = FixWalkFigures(truth, interval_s, noise_m, n, len(obs), [float(x) for x in mean])
    fix_t = run.stamps_s[nodes]

    def timed(label, fn):
        c0 = time.process_time()
        T = fn()
        fig.cpu_s[label] = time.process_time() - c0
        fig.rmse_m[label] = _rmse2(T, run.T_true, np.zeros(2))
        fig.rmse_frame_m[label] = _rmse2(T, run.T_true, mean)

    timed('plain', lambda: solve(net, dead, fixed=[], priors=fix_priors(obs, dead, ids)
                                 + [gauge]).T_world_node)
    base = CalibrationConfig(fix_parameters=('offset_x', 'offset_y'))
    walk = (BiasWalk('offset_x', segment_s=segment_s, sigma_per_sqrt_s=q),
            BiasWalk('offset_y', segment_s=segment_s, sigma_per_sqrt_s=q))
    est = tuple(BiasWalk(m.parameter, segment_s=segment_s, sigma_per_sqrt_s=q,
                         estimate_sigma=True) for m in walk)
    for label, cal in (('odom+const', base),
                       ('odom+walk', CalibrationConfig(fix_parameters=base.fix_parameters,
                                                       models=walk)),
                       ('odom+walk q est', CalibrationConfig(
                           fix_parameters=base.fix_parameters, models=est))):
        report: list[AdditionalParameter] = []

        def one(cal=cal, report=report):
            res, rep = solve_with_calibration(net, dead, sources, dt, fixed=[],
                                              priors=[gauge], calibration=cal, fixes=obs)
            report.extend(rep.parameters)
            return res.T_world_node

        timed(label, one)
        fig.offsets[label] = [p.line() for p in report if p.name.startswith('offset')]
        within = [knots_within(p, fix_t, off[:, 'xy'.index(p.name[-1])]) for p in report
                  if p.name.startswith('offset') and p.walk is not None]
        if within:
            fig.knots_within_3sigma[label] = float(np.mean(within))
    if with_gtsam and gtsam_installed():
        from ga_ros.bench.fixes import run_gtsam_batch

        timed('GTSAM LM', lambda: run_gtsam_batch(run, nodes, pos, noise_m, cov, cfg))
    return fig


def table(figs: list[FixWalkFigures]) -> str:
    """The figures as text (module doc)."""
    lines = ['ga-ros bench fixwalk: Plaza odometry + fixes whose offset wanders; 2-D position '
             'RMSE (m) / process CPU (s) of each batch; rmse frame: against the truth moved by '
             "the offset's mean over the fixes (the frame one fix source defines)",
             'truth     interval  noise  fixes  ' + '  '.join(f'{c:>14s}' for c in COLUMNS)]
    for f in figs:
        lines.append(f'{f.truth:8s}  {f.interval_s:8g}  {f.noise_m:5g}  {f.n_fixes:5d}  '
                     + rmse_cpu_cells(f.rmse_m, f.cpu_s, COLUMNS))
        lines.append(f"{'  rmse frame':33s}  " + '  '.join(
            f'{f.rmse_frame_m.get(c, float("nan")):7.3f}       ' for c in COLUMNS)
            + f'   (mean offset {f.mean_offset_m[0]:.2f}, {f.mean_offset_m[1]:.2f} m)')
        for label, ls in f.offsets.items():
            lines += [f'    {label}: {x}' for x in ls]
        for label, share in f.knots_within_3sigma.items():
            lines.append(f'    {label}: knots within 3 sigma of the truth: {100 * share:.0f} %')
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='ga-ros bench fixwalk', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 allow_abbrev=False)
    ap.add_argument('--data', default=str(DEFAULT_MAT), help='Plaza2_.mat')
    ap.add_argument('--truth', default='walk,constant,none',
                    help='the true offsets, comma-separated: walk, constant, none')
    ap.add_argument('--interval', type=float, default=2.0, help='fix interval (s)')
    ap.add_argument('--noise', type=float, default=0.3, help='white fix noise (m per axis)')
    ap.add_argument('--walk-sigma', type=float, default=1.5,
                    help="the true offset's stationary sigma (m, Gauss-Markov)")
    ap.add_argument('--walk-tau', type=float, default=120.0,
                    help="the true offset's correlation time (s)")
    ap.add_argument('--offset', default='1.5,-1.0', help='X,Y (m): the constant truth')
    ap.add_argument('--segment', type=float, default=10.0, help="the walk's knot spacing (s)")
    ap.add_argument('--q', type=float, default=0.2,
                    help="the walk's process noise (m/sqrt(s)), given (and the start of the "
                    "'q est' column)")
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--sigma-xy', type=float, default=0.01,
                    help="the odometry's stated sigma per step (m; its own is about 0.01)")
    ap.add_argument('--sigma-yaw', type=float, default=0.0005,
                    help="the odometry's stated yaw sigma per step (rad; its own 0.0003)")
    ap.add_argument('--no-gtsam', action='store_true')
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    if not Path(args.data).is_file():
        print(f'ga-ros bench fixwalk: no data file {args.data} (give --data)', file=sys.stderr)
        return 1
    offset = np.array([float(x) for x in args.offset.split(',')])
    truths = [x for x in args.truth.split(',') if x]
    if offset.size != 2 or any(x not in ('walk', 'constant', 'none') for x in truths):
        print('ga-ros bench fixwalk: --offset takes X,Y; --truth walk, constant or none',
              file=sys.stderr)
        return 2
    figs = [bench_fixwalk(x, args.interval, args.noise, args.walk_sigma, args.walk_tau, offset,
                          args.segment, args.q, args.seed, args.data, args.sigma_xy,
                          args.sigma_yaw, not args.no_gtsam) for x in truths]
    print(json.dumps([asdict(f) for f in figs]) if args.json else table(figs))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
