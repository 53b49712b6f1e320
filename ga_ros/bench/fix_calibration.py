"""``ga-ros bench fixcal``: the real Plaza odometry with fixes that have a latency (and, with
``--offset``, a second fix source with a constant offset), adjusted in one batch with and
without the fix sources' additional parameters (:mod:`ga_ros.core.calibration.fix_parameters`).

The run is ``bench fixes``' (:func:`~ga_ros.bench.fixes.load_plaza`: every odometry sample a
node, its stated covariance ``--sigma-xy`` / ``--sigma-yaw`` per step). Fix source ``gnss``:
every ``--interval`` seconds, the true position at ``stamp - --latency`` (the ground truth
interpolated linearly) plus ``N(0, --noise^2)`` per axis, stamped ``stamp``. With ``--offset
X,Y,Z``, a second source ``base`` at the half intervals, same noise, its positions shifted by
the offset (m, ``map``). The datum is the fixes' (a weak gauge prior on the first node, as
``datum='fixes'``).

Columns (position RMSE in 2-D against the ground truth, m; process CPU of this process in s):
``plain``: the batch adjustment without calibration; ``odom cal``: with the odometry's scale and
yaw rate (``CalibrationConfig(fix_parameters=())``, what ``bench fixes``' final + calibration
estimates); ``odom+fix cal``: with the fix sources' offset and time offset too
(``--fix-parameters``, default all four; ``gnss`` is the reference, ``--reference``: its
frame is the ground truth's, so it gets no offset); ``GTSAM LM``: GTSAM's
Levenberg-Marquardt on the same graph without calibration (``GPSFactor`` per fix; skipped
without gtsam). Online (``--no-online`` skips them): the same odometry and fixes fed sample by
sample to the window aligner (``datum='fixes'``, a track ends at each fix, the estimates inline
so the CPU is this process's), each node's estimate when it was added: ``online odom cal`` with
``calibrate`` and the fixes as measured (``calibration_fix_parameters=''``), ``online +fix cal``
with the fix sources' parameters online too (``--fix-parameters`` and ``--reference`` as
``calibration_fix_parameters`` and ``calibration_fix_reference``,
:mod:`ga_ros.core.window.calibration`). Printed below: each fix parameter's estimate with its
sigma (or why it was not estimated) against the truth, in the batch and in the last online
estimate.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import NamedTuple

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.bench.cpu import rmse_cpu_cells
from ga_ros.bench.fixes import DEFAULT_MAT, PlazaRun, _rmse, _step_cov, load_plaza
from ga_ros.bench.gtsam_runner import gtsam_installed
from ga_ros.core.calibration import (
    CalibrationConfig,
    FixObservations,
    fix_priors,
    solve_with_calibration,
)
from ga_ros.core.calibration.fix_parameters import FIX_PARAMETERS
from ga_ros.core.fixes import AbsoluteFix, FixTerm, gauge_information
from ga_ros.core.measurement import Measurement
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior, solve
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.geometry import se3


@dataclass
class FixCalFigures:
    """One setting: RMSE (m) and CPU (s) per column (module doc), the fix parameters' report
    lines and their truth."""

    interval_s: float
    noise_m: float
    latency_s: float
    offset_m: list[float]
    n_poses: int
    n_fixes: int
    rmse_m: dict[str, float] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)
    fix_parameters: list[str] = field(default_factory=list)
    online_fix_parameters: list[str] = field(default_factory=list)


def run_online(run: PlazaRun, obs: FixObservations, cov: FloatArray, cfg: AlignerConfig
               ) -> tuple[FloatArray, list]:
    """The online run of the module doc: ``(each node's pose when it was added (n, 4, 4),
    the last online estimate's parameters)``."""
    n = run.T_true.shape[0]
    al = TrackWindowAligner(cfg, T_world_first=run.T_true[0])
    at: dict[int, list[FixTerm]] = {}
    for term in obs.terms:
        at.setdefault(int(term.node_id), []).append(term)
    online = np.zeros((n, 4, 4))
    online[0] = run.T_true[0]
    track = prev = 0
    for i in range(1, n):
        al.add_measurement(Measurement.from_pose(i - 1, i, prev, track, run.steps[i - 1], cov,
                                                 int(run.stamps_s[i] * 1e9)))
        prev = track
        for node in (0, i) if i == 1 else (i,):
            for term in at.get(node, ()):
                al.add_fix(term)
        if i in at:
            al.finish_track()
            track += 1
        online[i] = al.pose(i)
    al.wait_background()
    book = al.online_calibration
    params = [] if book is None or book.report is None else list(book.report.parameters)
    al.close()
    return online, params


def plaza_fixes(run: PlazaRun, interval_s: float, noise_m: float, latency_s: float,
                offset_m: FloatArray | None, seed: int
                ) -> tuple[FixObservations, np.ndarray, FloatArray]:
    """The fixes of the module doc: the observations, and each fix's node index and measured
    position (for GTSAM)."""
    rng = np.random.default_rng(seed)
    t = run.stamps_s
    info = np.diag([noise_m ** -2] * 3 + [0.0] * 3)
    terms, nodes, pos = [], [], []
    sources = [('gnss', 0.0, np.zeros(3))]
    if offset_m is not None:
        sources.append(('base', 0.5 * interval_s, np.asarray(offset_m, dtype=float)))
    for name, start, off in sources:
        want = np.arange(start, t[-1] + 1e-9, interval_s)
        idx = np.unique(np.abs(t[None, :] - want[:, None]).argmin(axis=1))
        for i in idx:
            at = t[i] - latency_s if name == 'gnss' else t[i]
            p = np.array([np.interp(at, t, run.T_true[:, a, 3]) for a in range(3)])
            p = p + off + rng.normal(0.0, noise_m, 3)
            fix = AbsoluteFix(int(round(t[i] * 1e9)), se3.from_translation_rotvec(
                p, np.zeros(3)), info, name)
            terms.append(FixTerm(int(i), se3.identity(), fix))
            nodes.append(int(i))
            pos.append(p)
    obs = FixObservations(terms, np.repeat(info[None], len(terms), axis=0), t)
    return obs, np.array(nodes), np.array(pos)


class PlazaGraph(NamedTuple):
    """The odometry graph of the Plaza run that the fix benchmarks solve (one node per sample)."""
    ids: IntArray             #: (n,) node ids 0..n-1
    cov: FloatArray           #: (6, 6) each odometry step's covariance [x y z rx ry rz]
    net: ConnectionNetwork    #: the consecutive odometry steps as connections
    cfg: AlignerConfig        #: ``datum='fixes'``: the gauge's sigmas
    gauge: GaussianPrior      #: the weak gauge prior on the first node at its true pose
    dead: FloatArray          #: (n, 4, 4) dead reckoning from the first true pose
    sources: list[str]        #: each step's source ('odom0')
    dt: FloatArray            #: (n - 1,) each step's duration (s)


def plaza_graph(run: PlazaRun, sigma_xy: float, sigma_yaw: float) -> PlazaGraph:
    """The Plaza run's odometry graph with ``sigma_xy`` (m) and ``sigma_yaw`` (rad) per step
    (``sigma_z`` 1 mm, tilt 0.1 mrad: the plane), the weak gauge prior of ``datum='fixes'``
    and the dead-reckoned start."""
    n = run.T_true.shape[0]
    ids = np.arange(n)
    cov = _step_cov(sigma_xy, sigma_yaw, 1e-3, 1e-4)
    net = ConnectionNetwork.from_arrays(ids, np.zeros(n, np.int64), ids[:-1], ids[1:],
                                        se3.to_translation_rotvec(run.steps),
                                        np.repeat(cov[None], n - 1, axis=0))
    cfg = AlignerConfig(datum='fixes')
    gauge = GaussianPrior(ids[:1], run.T_true[:1], gauge_information(
        cfg.gauge_sigma_m, cfg.gauge_sigma_tilt_rad, cfg.gauge_sigma_yaw_rad), weak=True)
    dead = se3.integrate(run.T_true[0], run.steps)
    return PlazaGraph(ids, cov, net, cfg, gauge, dead, ['odom0'] * (n - 1),
                      np.diff(run.stamps_s))


def bench_fixcal(interval_s: float, noise_m: float, latency_s: float,
                 offset_m: FloatArray | None, fix_parameters: tuple[str, ...],
                 reference: tuple[str, ...] = ('gnss',), seed: int = 0,
                 path: str | Path = DEFAULT_MAT, sigma_xy: float = 0.02,
                 sigma_yaw: float = 0.005, with_gtsam: bool = True,
                 with_online: bool = True) -> FixCalFigures:
    """One setting of the benchmark (module doc)."""
    run = load_plaza(path)
    obs, nodes, pos = plaza_fixes(run, interval_s, noise_m, latency_s, offset_m, seed)
    n = run.T_true.shape[0]
    ids, cov, net, cfg, gauge, dead, sources, dt = plaza_graph(run, sigma_xy, sigma_yaw)
    fig = FixCalFigures(interval_s, noise_m, latency_s,
                        [] if offset_m is None else [float(x) for x in offset_m], n, len(obs))
    fig.rmse_m['dead reckoning'] = _rmse(dead, run.T_true)

    def timed(label, fn):
        c0 = time.process_time()
        T = fn()
        fig.cpu_s[label] = time.process_time() - c0
        fig.rmse_m[label] = _rmse(T, run.T_true)

    timed('plain', lambda: solve(net, dead, fixed=[], priors=fix_priors(obs, dead, ids)
                                 + [gauge]).T_world_node)
    timed('odom cal', lambda: solve_with_calibration(
        net, dead, sources, dt, fixed=[], priors=[gauge],
        calibration=CalibrationConfig(fix_parameters=()), fixes=obs)[0].T_world_node)
    report = []

    def with_fix():
        res, rep = solve_with_calibration(
            net, dead, sources, dt, fixed=[], priors=[gauge],
            calibration=CalibrationConfig(fix_parameters=fix_parameters,
                                          fix_reference=reference), fixes=obs)
        report.extend(rep.parameters)
        return res.T_world_node

    timed('odom+fix cal', with_fix)
    truth = {('gnss', 'time_offset'): latency_s}
    if offset_m is not None:
        truth.update({('base', f'offset_{a}'): float(o) for a, o in zip('xyz', offset_m)})
    for p in report:
        if FIX_PARAMETERS.get(p.name) is None:
            continue
        true = truth.get((p.source, p.name), 0.0)
        fig.fix_parameters.append(f'{p.line()}  [truth {true:g} {p.unit}]')
    if with_online:
        online_cfg = AlignerConfig(datum='fixes', calibrate=True, refine_executor='inline',
                                   calibration_fix_parameters='')
        for label, fcfg in (('online odom cal', online_cfg),
                            ('online +fix cal', replace(
                                online_cfg, calibration_fix_parameters=','.join(fix_parameters),
                                calibration_fix_reference=','.join(reference)))):
            c0 = time.process_time()
            T, params = run_online(run, obs, cov, fcfg)
            fig.cpu_s[label] = time.process_time() - c0
            fig.rmse_m[label] = _rmse(T, run.T_true)
        for p in params:
            if FIX_PARAMETERS.get(p.name) is not None:
                true = truth.get((p.source, p.name), 0.0)
                fig.online_fix_parameters.append(f'{p.line()}  [truth {true:g} {p.unit}]')
    if with_gtsam and gtsam_installed():
        from ga_ros.bench.fixes import run_gtsam_batch

        # the fixes of both sources as one GPS stream (same noise), counted with gtsam's import
        timed('GTSAM LM', lambda: run_gtsam_batch(run, nodes, pos, noise_m, cov, cfg))
    return fig


def table(figs: list[FixCalFigures]) -> str:
    """The figures as text (module doc)."""
    cols = ['dead reckoning', 'plain', 'odom cal', 'odom+fix cal', 'GTSAM LM',
            'online odom cal', 'online +fix cal']
    lines = ['ga-ros bench fixcal: Plaza odometry + fixes with a latency (and an offset '
             'source); 2-D position RMSE (m) / process CPU (s) of each batch',
             'interval  noise  latency  offset            fixes  ' + '  '.join(
                 f'{c:>14s}' for c in cols)]
    for f in figs:
        off = ','.join(f'{x:g}' for x in f.offset_m) or '-'
        lines.append(f'{f.interval_s:8g}  {f.noise_m:5g}  {f.latency_s:7g}  {off:16s}  '
                     f'{f.n_fixes:5d}  ' + rmse_cpu_cells(f.rmse_m, f.cpu_s, cols))
        lines += ['    ' + x for x in f.fix_parameters]
        lines += ['    online: ' + x for x in f.online_fix_parameters]
    lines.append('ratio odom+fix cal / odom cal (RMSE): ' + ', '.join(
        f"{f.rmse_m['odom+fix cal'] / f.rmse_m['odom cal']:.3f}" for f in figs))
    if all('online odom cal' in f.rmse_m for f in figs):
        lines.append('ratio online +fix cal / online odom cal (RMSE): ' + ', '.join(
            f"{f.rmse_m['online +fix cal'] / f.rmse_m['online odom cal']:.3f}" for f in figs))
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='ga-ros bench fixcal', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 allow_abbrev=False)
    ap.add_argument('--data', default=str(DEFAULT_MAT), help='Plaza2_.mat')
    ap.add_argument('--intervals', default='10', help='fix intervals (s), comma-separated')
    ap.add_argument('--noise', type=float, default=2.0, help='fix noise (m per axis)')
    ap.add_argument('--latency', type=float, default=0.5, help="gnss's latency (s)")
    ap.add_argument('--offset', default=None,
                    help="X,Y,Z (m): a second source 'base' with this offset")
    ap.add_argument('--fix-parameters', default=','.join(FIX_PARAMETERS),
                    help='the fix parameters estimated (default all)')
    ap.add_argument('--reference', default='gnss',
                    help="fix sources that define the frame (no offset; default gnss, the "
                    "ground truth's frame; '' : none, the better source's offset is dropped)")
    ap.add_argument('--seed', type=int, default=0)
    ap.add_argument('--sigma-xy', type=float, default=0.02)
    ap.add_argument('--sigma-yaw', type=float, default=0.005)
    ap.add_argument('--no-gtsam', action='store_true')
    ap.add_argument('--no-online', action='store_true', help='skip the online columns')
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    if not Path(args.data).is_file():
        print(f'ga-ros bench fixcal: no data file {args.data} (give --data)', file=sys.stderr)
        return 1
    offset = None if args.offset is None else np.array([float(x) for x in
                                                        args.offset.split(',')])
    if offset is not None and offset.size != 3:
        print('ga-ros bench fixcal: --offset takes X,Y,Z', file=sys.stderr)
        return 2
    params = tuple(x for x in args.fix_parameters.split(',') if x)
    reference = tuple(x for x in args.reference.split(',') if x)
    figs = [bench_fixcal(float(i), args.noise, args.latency, offset, params, reference,
                         args.seed, args.data, args.sigma_xy, args.sigma_yaw, not args.no_gtsam,
                         not args.no_online)
            for i in args.intervals.split(',')]
    print(json.dumps([asdict(f) for f in figs]) if args.json else table(figs))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
