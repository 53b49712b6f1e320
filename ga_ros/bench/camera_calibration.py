"""``ga-ros bench camcal``: a camera mounted with a rotation error, its cross-track
connections adjusted with a body-frame odometry in one batch, with and without the camera's
extrinsic rotation as additional parameters (:mod:`ga_ros.core.calibration.camera_parameters`).

The survey is :func:`~ga_ros.sim.camera_survey.swath_survey` (``--swaths`` swaths of 30
keyframes 2 m apart, 10 m between swaths, flown in alternating directions; the odometry
``odom0`` on every consecutive motion, the camera ``cam0`` on a cross-track connection every
third keyframe to the next swath, its motions conjugated by the error ``--phi`` (rad, body
frame); the first keyframe held at its true pose), one survey per seed.

Columns (3-D position RMSE against the truth, m; process CPU of this process, s, all threads):
``plain``: the batch adjustment without calibration; ``odom cal``: the default calibration
(the odometry's scale and yaw rate; no camera named); ``+camera cal``:
``CalibrationConfig(cameras=('cam0',))``; ``GTSAM LM``: GTSAM's Levenberg-Marquardt on the
same graph (``BetweenFactorPose3``, which cannot express the conjugation: without calibration;
skipped without gtsam). Printed below each row: the camera's estimates with their sigmas (or
why not estimated) against the truth; last, the ratio ``+camera cal`` / ``GTSAM LM``.
"""

from __future__ import annotations

import argparse
import json
import time
from dataclasses import asdict, dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.bench.cpu import rmse_cpu_cells
from ga_ros.bench.gtsam_runner import gtsam_installed
from ga_ros.core.calibration import CalibrationConfig, solve_with_calibration
from ga_ros.core.solver import solve
from ga_ros.geometry import se3
from ga_ros.sim.camera_survey import CameraSurvey, swath_survey

COLUMNS = ('plain', 'odom cal', '+camera cal', 'GTSAM LM')


@dataclass
class CamCalFigures:
    """One survey's figures (module doc)."""

    seed: int
    phi: list[float]
    n_nodes: int
    n_cross: int
    rmse_m: dict[str, float] = field(default_factory=dict)
    cpu_s: dict[str, float] = field(default_factory=dict)
    estimates: list[str] = field(default_factory=list)


def _rmse(T: FloatArray, T_true: FloatArray) -> float:
    return float(np.sqrt(np.mean(np.sum((T[:, :3, 3] - T_true[:, :3, 3]) ** 2, axis=1))))


def gtsam_batch(s: CameraSurvey) -> FloatArray:
    """GTSAM Levenberg-Marquardt on the survey's graph, the first node held by a tight prior
    (module doc)."""
    import gtsam

    order = [3, 4, 5, 0, 1, 2]  # ga_ros [x y z rx ry rz] -> GTSAM Pose3 [rx ry rz x y z]
    arr = s.network.arrays()
    graph = gtsam.NonlinearFactorGraph()
    graph.add(gtsam.PriorFactorPose3(0, gtsam.Pose3(s.T_true[0]),
                                     gtsam.noiseModel.Isotropic.Sigma(6, 1e-6)))
    motions = se3.from_translation_rotvec(arr.z[:, :3], arr.z[:, 3:])
    for a, b, T, c in zip(arr.src.tolist(), arr.dst.tolist(), motions, arr.cov):
        graph.add(gtsam.BetweenFactorPose3(a, b, gtsam.Pose3(T), gtsam.noiseModel.Gaussian
                                           .Covariance(c[np.ix_(order, order)])))
    init = gtsam.Values()
    for i, T in enumerate(s.T_init):
        init.insert(i, gtsam.Pose3(T))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    out = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    return np.array([out.atPose3(i).matrix() for i in range(s.T_init.shape[0])])


def bench_camcal(seed: int, phi: FloatArray, n_swaths: int = 6,
                 with_gtsam: bool = True) -> CamCalFigures:
    """One survey of the benchmark (module doc)."""
    s = swath_survey(np.random.default_rng(seed), phi, n_swaths=n_swaths)
    fig = CamCalFigures(seed, [float(x) for x in phi], s.T_true.shape[0],
                        sum(g == 'cam0' for g in s.groups))

    def timed(label, fn):
        c0 = time.process_time()
        T = fn()
        fig.cpu_s[label] = time.process_time() - c0
        fig.rmse_m[label] = _rmse(T, s.T_true)

    timed('plain', lambda: solve(s.network, s.T_init, fixed=s.fixed).T_world_node)
    timed('odom cal', lambda: solve_with_calibration(
        s.network, s.T_init, s.sources, s.dt_s, fixed=s.fixed,
        groups=s.groups)[0].T_world_node)
    report = []

    def camera():
        res, rep = solve_with_calibration(s.network, s.T_init, s.sources, s.dt_s,
                                          fixed=s.fixed, groups=s.groups,
                                          calibration=CalibrationConfig(cameras=('cam0',)))
        report.extend(p for p in rep.parameters if p.source == 'cam0')
        return res.T_world_node

    timed('+camera cal', camera)
    fig.estimates = [f'{p.line()}  [truth {t:g} rad]' for p, t in zip(report, phi)]
    if with_gtsam and gtsam_installed():
        timed('GTSAM LM', lambda: gtsam_batch(s))
    return fig


def table(figs: list[CamCalFigures]) -> str:
    """The figures as text (module doc)."""
    lines = ["ga-ros bench camcal: swaths in alternating directions, odometry + a camera's "
             'cross-track connections with an extrinsic rotation error; 3-D position RMSE (m) '
             '/ process CPU (s) of each batch',
             'seed  nodes  cross  phi (rad)              ' + '  '.join(
                 f'{c:>14s}' for c in COLUMNS)]
    for f in figs:
        phi = ','.join(f'{x:g}' for x in f.phi)
        lines.append(f'{f.seed:4d}  {f.n_nodes:5d}  {f.n_cross:5d}  {phi:21s}  '
                     + rmse_cpu_cells(f.rmse_m, f.cpu_s, COLUMNS))
        lines += ['    ' + x for x in f.estimates]
    if all('GTSAM LM' in f.rmse_m for f in figs):
        lines.append('ratio +camera cal / GTSAM LM (RMSE): ' + ', '.join(
            f"{f.rmse_m['+camera cal'] / f.rmse_m['GTSAM LM']:.3f}" for f in figs))
    return '\n'.join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='ga-ros bench camcal', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 allow_abbrev=False)
    ap.add_argument('--seeds', default='0,1,2', help='one survey per seed, comma-separated')
    ap.add_argument('--phi', default='0.02,-0.01,0.03',
                    help="the camera extrinsic's rotation error X,Y,Z (rad, body frame)")
    ap.add_argument('--swaths', type=int, default=6)
    ap.add_argument('--no-gtsam', action='store_true')
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    phi = np.array([float(x) for x in args.phi.split(',')])
    if phi.size != 3:
        ap.error('--phi takes X,Y,Z')
    figs = [bench_camcal(int(k), phi, args.swaths, not args.no_gtsam)
            for k in args.seeds.split(',') if k]
    print(json.dumps([asdict(f) for f in figs]) if args.json else table(figs))
    return 0
