"""``ga-ros bench fixes``: real odometry plus absolute position fixes, against GTSAM (issue 25).

The run: the CMU Plaza data set, run 2 (``Plaza2_.mat``, see ``data/README.md``): real wheel
odometry steps ``DR`` (distance, heading change) at 10 Hz between the ground-truth samples ``GT``
(x, y, theta; the travel direction is ``theta + pi``), 1,354 m. Fixes: the ground-truth position
every ``interval_s`` seconds plus seeded Gaussian noise of ``noise_m`` per axis (x, y and z, the
true z being 0), the first at the first sample.

The same graph for every solver: one node per sample (SE(3), the plane embedded), one
between-factor per odometry step with the covariance ``diag(sigma_xy^2, sigma_xy^2, sigma_z^2,
sigma_tilt^2, sigma_tilt^2, sigma_yaw^2)`` (body frame, per step; ``sigma_z`` 1 mm,
``sigma_tilt`` 0.1 mrad: the plane), one 3-D position factor per
fix (``noise_m^2 I``), and the weak gauge prior of ``datum='fixes'`` on the first node
(:class:`~ga_ros.core.window.AlignerConfig`: 1000 m, 0.05 rad roll/pitch, 3 rad yaw) at the
initial pose (the first ground-truth pose; the odometry integrated from it is every solver's
initial guess).

Figures (2-D position RMSE against the ground truth, over every sample):

* dead reckoning; the fixes alone (linear interpolation between fixes, held at the ends);
* ga-ros online: the :class:`~ga_ros.core.window.TrackWindowAligner` fed sample by sample, a
  track ending at each fix (``finish_track`` right after ``add_fix``); each pose's estimate when
  it was first published: after the update for a fix's node, else the last estimate chained
  with the odometry; ga-ros final: ``refine_batch`` at the end; the aligner runs with its
  default settings (a background refinement, inline or in a worker process by its size, where
  the linearisation demands it, ``refine_relinearize_sigma``), as ``ga-ros replay`` does;
* GTSAM batch: Levenberg-Marquardt on the whole graph; GTSAM iSAM2: ``update`` at each fix with
  the factors and poses since the previous one; online = each pose's estimate when it was added
  (after that update for a fix's node, else the last estimate chained with the odometry, as for
  ga-ros), final = the estimate after the last update. iSAM2 with its default parameters
  relinearises lazily (threshold 0.1, every 10th update) and takes one Gauss-Newton step per
  update, so its online estimate is not the converged one; ``--isam2-converged`` adds a column
  with ``relinearizeThreshold`` 1e-4, ``relinearizeSkip`` 1 and three extra ``update()`` calls
  per fix (the filtering solution that the window aligner computes).

ga-ros final + calibration (``--no-calibration`` skips it): ``refine_batch`` again with
``calibration=CalibrationConfig()`` (:mod:`ga_ros.core.calibration`): the odometry's scale and
yaw-rate corrections are estimated with the poses where the network determines them and they
pass their significance test, and the calibrated source's noise is re-estimated; the column
``stated-noise`` is the same with its stated noise (``CalibrationConfig(noise=False)``);
``cal<=final`` and ``cal<=batch`` count the seeds of the fix noise (``--seeds``) where it is
at most ga-ros final without calibration, GTSAM batch (one draw of 5 m noise can leave the
calibrated batch behind where the mean over draws is well ahead: docs/calibration.md).
GTSAM's ``BetweenFactorPose3`` cannot express a yaw-rate bias, so GTSAM runs without
calibration and the ratio printed is against GTSAM batch without it. ga-ros final + calibration
(random walk) (``--no-walk`` skips it): the same with the yaw rate a random walk
(:class:`~ga_ros.core.calibration.RandomWalk`, ``--walk-segment``, ``--walk-sigma``).
ga-ros online + calibration (skipped with ``--no-calibration`` too): the online run again with
``AlignerConfig(calibrate=True)`` (:mod:`ga_ros.core.window.calibration`: the corrections
estimated online and applied to the motions as they enter), against iSAM2 online, with its
CPU (all processes) and its last online estimate.

Beside the RMSE table: the CPU seconds of all processes (this one with its threads, and the
refinement worker) of ga-ros online, ga-ros final, GTSAM batch LM and GTSAM iSAM2 (updated at
each fix), and the mean ``update_ms`` (wall) and CPU (the calling thread's) of the calls that
end a track, per quarter of the run's tracks (flat when the cost of an update does not grow
with the survey). A stage table splits ga-ros online's CPU (seconds over the whole run,
from a third run of it whose stage timers wrap the stages' functions: their own CPU counts in
that run, not in the totals above): the stages of :data:`ga_ros.bench.stages.STAGES` (each
counting its own time: a stage function called inside another counts in its own stage),
``admission`` (each measurement's checks and storage,
:func:`~ga_ros.core.window.admission.check_measurement` / ``apply_measurement``),
``refinement`` (:func:`~ga_ros.core.window.refinement.refine_snapshot`
run in this process: inline or in a thread), ``other`` (the rest of this process: the update
code between the stages, the stage timers, building the measurements and fixes),
``worker process`` (the refinement worker's CPU, its start-up included) and ``start-up`` (the
first run's CPU above the second's: lazy imports, numba and the compiled kernels' load).

GTSAM is optional (``pip install -r requirements-bench.txt``); without it those columns are
skipped with a note.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.bench.cpu import all_cpu_seconds
from ga_ros.bench.data import SHARED_DATA
from ga_ros.bench.gtsam_runner import gtsam_installed
from ga_ros.core.calibration import CalibrationConfig, ParameterModel, RandomWalk
from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.geometry import se3

#: The data file: ``real/plaza2/Plaza2_.mat`` in :data:`ga_ros.bench.data.SHARED_DATA`.
DEFAULT_MAT = SHARED_DATA / 'real' / 'plaza2' / 'Plaza2_.mat'


@dataclass(frozen=True)
class PlazaRun:
    """The real run: ``T_true`` (n, 4, 4) ground-truth poses, ``steps`` (n-1, 4, 4) odometry
    motions ``T_i_i+1``, ``stamps_s`` (n,)."""

    T_true: FloatArray
    steps: FloatArray
    stamps_s: FloatArray


def load_plaza(path: str | Path = DEFAULT_MAT) -> PlazaRun:
    """Read ``Plaza2_.mat`` (module doc)."""
    from scipy.io import loadmat

    d = loadmat(str(path))
    gt, dr = np.asarray(d['GT'], float), np.asarray(d['DR'], float)
    yaw = gt[:, 3] + np.pi
    n = gt.shape[0]
    T = np.zeros((n, 4, 4))
    T[:] = np.eye(4)
    T[:, 0, 0], T[:, 0, 1] = np.cos(yaw), -np.sin(yaw)
    T[:, 1, 0], T[:, 1, 1] = np.sin(yaw), np.cos(yaw)
    T[:, 0, 3], T[:, 1, 3] = gt[:, 1], gt[:, 2]
    z = np.zeros((n - 1, 6))
    z[:, 0], z[:, 5] = dr[:, 1], dr[:, 2]
    steps = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
    return PlazaRun(T, steps, gt[:, 0] - gt[0, 0])


@dataclass
class FixBenchFigures:
    """Results of one setting (RMSE in m; NaN where GTSAM was not run)."""

    interval_s: float
    noise_m: float
    n_poses: int
    n_fixes: int
    dead_reckoning_m: float
    fixes_alone_m: float
    ours_online_m: float
    ours_final_m: float
    ours_final_cal_m: float = float('nan')
    ours_final_cal_noise_m: float = float('nan')
    ours_final_cal_stated_m: float = float('nan')
    ours_final_cal_walk_m: float = float('nan')
    ours_final_cal_walk_cpu_s: float = float('nan')
    gtsam_batch_m: float = float('nan')
    isam2_online_m: float = float('nan')
    isam2_final_m: float = float('nan')
    isam2_converged_online_m: float = float('nan')
    ours_seconds: float = float('nan')
    gtsam_seconds: float = float('nan')
    isam2_seconds: float = float('nan')
    ours_online_cpu_s: float = float('nan')
    ours_online_warm_cpu_s: float = float('nan')
    ours_online_staged_cpu_s: float = float('nan')
    ours_final_cpu_s: float = float('nan')
    gtsam_batch_cpu_s: float = float('nan')
    isam2_cpu_s: float = float('nan')
    ours_final_cal_cpu_s: float = float('nan')
    ours_online_cal_m: float = float('nan')
    ours_online_cal_cpu_s: float = float('nan')
    calibration: list[str] = field(default_factory=list)
    walk_calibration: list[str] = field(default_factory=list)
    online_calibration: list[str] = field(default_factory=list)
    online_cal_wins: int = 0
    # the seeds where ours final + calibration <= ours final (without calibration) / GTSAM LM
    final_cal_wins: int = 0
    final_cal_batch_wins: int = 0
    update_ms_quarters: list[float] = field(default_factory=list)
    update_cpu_ms_quarters: list[float] = field(default_factory=list)
    cal_update_ms_quarters: list[float] = field(default_factory=list)
    cal_update_cpu_ms_quarters: list[float] = field(default_factory=list)
    stage_cpu_s: dict[str, float] = field(default_factory=dict)
    # the staged run's work per track end by part and kind ('window linearisations': mean)
    work_per_update: dict[str, float] = field(default_factory=dict)
    fix_outliers: int = 0
    notes: list[str] = field(default_factory=list)
    seeds: int = 1
    online_wins: int = 0


def _rmse(T: FloatArray, T_true: FloatArray) -> float:
    d = T[:, :2, 3] - T_true[:, :2, 3]
    return float(np.sqrt(np.mean(np.sum(d * d, axis=1))))


def _step_cov(sigma_xy: float, sigma_yaw: float, sigma_z: float, sigma_tilt: float
              ) -> FloatArray:
    return np.diag([sigma_xy ** 2, sigma_xy ** 2, sigma_z ** 2, sigma_tilt ** 2,
                    sigma_tilt ** 2, sigma_yaw ** 2])


def make_fixes(run: PlazaRun, interval_s: float, noise_m: float, seed: int
               ) -> tuple[np.ndarray, FloatArray]:
    """``(sample indices (f,), fixed positions (f, 3))``: the sample nearest to every multiple
    of ``interval_s``, its true position plus seeded noise (module doc)."""
    rng = np.random.default_rng(seed)
    want = np.arange(0.0, run.stamps_s[-1] + 1e-9, interval_s)
    idx = np.unique(np.abs(run.stamps_s[None, :] - want[:, None]).argmin(axis=1))
    p = run.T_true[idx, :3, 3] + rng.normal(0.0, noise_m, (idx.size, 3))
    return idx, p


def _interpolated(run: PlazaRun, idx: np.ndarray, p: FloatArray) -> FloatArray:
    T = np.repeat(np.eye(4)[None], run.T_true.shape[0], axis=0)
    for a in range(3):
        T[:, a, 3] = np.interp(run.stamps_s, run.stamps_s[idx], p[:, a])
    return T


@dataclass
class OursRun:
    """ga-ros online and final poses (module doc), the fixes gated out, each update's
    ``update_ms``, the CPU ms of each call that ended a track (``update_cpu_ms``, the calling
    thread's), the CPU seconds of all processes (this one with its threads, the refinement
    worker) of the online run and of the final ``refine_batch``, and the online run's CPU
    seconds per stage (module doc)."""

    online: FloatArray
    final: FloatArray
    outliers: int
    update_ms: list[float]
    online_cpu_s: float
    final_cpu_s: float
    final_cal: FloatArray | None = None
    final_cal_noise: FloatArray | None = None
    final_cal_stated: FloatArray | None = None
    final_cal_cpu_s: float = float('nan')
    final_cal_walk: FloatArray | None = None
    final_cal_walk_cpu_s: float = float('nan')
    calibration: list[str] = field(default_factory=list)
    walk_calibration: list[str] = field(default_factory=list)
    online_calibration: list[str] = field(default_factory=list)
    update_cpu_ms: list[float] = field(default_factory=list)
    stage_cpu_s: dict[str, float] = field(default_factory=dict)
    work_per_update: dict[str, float] = field(default_factory=dict)


def _fix_stages() -> dict[str, tuple[tuple[object, str], ...]]:
    """:data:`ga_ros.bench.stages.STAGES` with ``admission`` and ``refinement`` (module doc)."""
    from ga_ros.bench.stages import STAGES
    from ga_ros.core.window import aligner, worker

    return {**STAGES,
            'admission': ((aligner, 'check_measurement'), (aligner, 'apply_measurement')),
            'refinement': ((worker, 'refine_snapshot'),)}


def run_ours(run: PlazaRun, idx: np.ndarray, p: FloatArray, noise_m: float, cov: FloatArray,
             cfg: AlignerConfig, calibration: CalibrationConfig | None = None,
             stages: bool = False, final: bool = True,
             walk: tuple[ParameterModel, ...] = ()) -> OursRun:
    """ga-ros online and final (module doc), with its update times and CPU; with
    ``calibration``, also final + calibration: ``refine_batch(calibration=...)`` after the
    final one (the odometry's scale and yaw-rate corrections estimated with the poses);
    ``stages``: the online run's CPU by stage too (its timers wrap the stages' functions and
    add their own CPU, so a run timed by stages is not the one whose total is reported);
    ``final=False``: the online run only (``final`` is then the online estimate at the end);
    with ``cfg.calibrate``, ``online_calibration`` holds the online estimate's lines;
    ``walk`` (with ``calibration``): final + calibration again with these parameter models
    (``calibration``'s ``models``, a random walk's: module doc)."""
    import resource
    from contextlib import nullcontext

    from ga_ros.bench.stages import counted_work, timed_stages

    def own_cpu() -> float:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    with (timed_stages(_fix_stages() if stages else {}, exclusive=True) as clock,
          counted_work() if stages else nullcontext() as work):
        cpu0, own0 = all_cpu_seconds(), own_cpu()
        n = run.T_true.shape[0]
        al = TrackWindowAligner(cfg, T_world_first=run.T_true[0])
        fix_at = dict(zip(idx.tolist(), range(idx.size)))
        fix_cov = np.diag([noise_m ** 2] * 3 + [-1.0] * 3)
        online = np.zeros((n, 4, 4))
        online[0] = run.T_true[0]
        track = prev_track = 0

        def add_fix(i: int) -> None:
            f = fix_at[i]
            fix = AbsoluteFix.from_covariance(int(run.stamps_s[i] * 1e9),
                                              se3.from_translation_rotvec(p[f], np.zeros(3)),
                                              fix_cov, 'fix0')
            al.add_fix(FixTerm(i, se3.identity(), fix))

        update_ms, update_cpu_ms = [], []
        for i in range(1, n):
            for up in al.add_measurement(Measurement.from_pose(
                    i - 1, i, prev_track, track, run.steps[i - 1], cov,
                    int(run.stamps_s[i] * 1e9))):
                update_ms.append(up.update_ms)
            prev_track = track
            if i == 1 and 0 in fix_at:
                add_fix(0)  # enters the first track's update
            if i in fix_at:
                add_fix(i)
                c0 = time.thread_time()
                up = al.finish_track()
                if up is not None:
                    update_ms.append(up.update_ms)
                    update_cpu_ms.append(1e3 * (time.thread_time() - c0))
                track += 1
            online[i] = al.pose(i)
        al.wait_background()
        cpu1, own1 = all_cpu_seconds(), own_cpu()
    if al.stats.n_failed_updates:  # the figures then are not those of the method
        print(f'ga-ros bench fixes: {al.stats.n_failed_updates} failed window updates, the '
              f'last: {al.stats.last_failure}', file=sys.stderr)
    stage_cpu_s = {}
    for (_, stage), ms in clock.take().items():
        stage_cpu_s[stage] = stage_cpu_s.get(stage, 0.0) + 1e-3 * ms
    if stages:
        stage_cpu_s['other'] = own1 - own0 - sum(stage_cpu_s.values())
        stage_cpu_s['worker process'] = (cpu1 - cpu0) - (own1 - own0)
    work_per_update = ({f'{part} {kind}': n / max(len(update_cpu_ms), 1)
                        for (part, kind), n in sorted(work.take().items())} if stages else {})
    book = al.online_calibration
    online_cal = book.report.lines() if book is not None and book.report is not None else []
    if final:
        al.refine_batch()
    final_T = al.corrected_path().T_world_node.copy()
    cpu2 = all_cpu_seconds()
    out = OursRun(online, final_T, al.fix_stats.outliers, update_ms, cpu1 - cpu0, cpu2 - cpu1,
                  update_cpu_ms=update_cpu_ms, stage_cpu_s=stage_cpu_s,
                  online_calibration=online_cal, work_per_update=work_per_update)
    if calibration is not None:
        al.refine_batch(calibration=calibration)
        out.final_cal = al.corrected_path().T_world_node.copy()
        out.final_cal_cpu_s = all_cpu_seconds() - cpu2
        out.calibration = al.calibration.lines() if al.calibration is not None else []
        # the other noise setting: the stated noise, or the re-estimated one
        al.refine_batch(calibration=replace(calibration, noise=not calibration.noise))
        other = al.corrected_path().T_world_node.copy()
        if calibration.noise:
            out.final_cal_noise, out.final_cal_stated = out.final_cal, other
        else:
            out.final_cal_noise, out.final_cal_stated = other, out.final_cal
        if walk:
            cpu3 = all_cpu_seconds()
            al.refine_batch(calibration=replace(calibration, models=walk))
            out.final_cal_walk = al.corrected_path().T_world_node.copy()
            out.final_cal_walk_cpu_s = all_cpu_seconds() - cpu3
            out.walk_calibration = al.calibration.lines() if al.calibration is not None else []
    al.close()
    return out


def _gtsam_graph(run, idx, p, noise_m, cov, cfg):
    import gtsam

    n = run.T_true.shape[0]
    order = [3, 4, 5, 0, 1, 2]  # ga_ros [x y z rx ry rz] -> GTSAM Pose3 [rx ry rz x y z]
    odo = gtsam.noiseModel.Gaussian.Covariance(cov[np.ix_(order, order)])
    gauge = gtsam.noiseModel.Diagonal.Sigmas(np.array(
        [cfg.gauge_sigma_tilt_rad, cfg.gauge_sigma_tilt_rad, cfg.gauge_sigma_yaw_rad]
        + [cfg.gauge_sigma_m] * 3))
    gps = gtsam.noiseModel.Isotropic.Sigma(3, noise_m)
    between = [gtsam.BetweenFactorPose3(i - 1, i, gtsam.Pose3(run.steps[i - 1]), odo)
               for i in range(1, n)]
    prior = gtsam.PriorFactorPose3(0, gtsam.Pose3(run.T_true[0]), gauge)
    fixes = {int(i): gtsam.GPSFactor(int(i), gtsam.Point3(*p[f]), gps)
             for f, i in enumerate(idx)}
    return between, prior, fixes


def run_gtsam_batch(run, idx, p, noise_m, cov, cfg) -> FloatArray:
    """GTSAM Levenberg-Marquardt on the whole graph (module doc)."""
    import gtsam

    between, prior, fixes = _gtsam_graph(run, idx, p, noise_m, cov, cfg)
    graph = gtsam.NonlinearFactorGraph()
    graph.add(prior)
    for f in between:
        graph.add(f)
    for f in fixes.values():
        graph.add(f)
    init = gtsam.Values()
    T = run.T_true[0]
    init.insert(0, gtsam.Pose3(T))
    for i in range(1, run.T_true.shape[0]):
        T = T @ run.steps[i - 1]
        init.insert(i, gtsam.Pose3(T))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-10)
    params.setAbsoluteErrorTol(1e-10)
    params.setMaxIterations(100)
    res = gtsam.LevenbergMarquardtOptimizer(graph, init, params).optimize()
    return np.array([res.atPose3(i).matrix() for i in range(run.T_true.shape[0])])


def run_isam2(run, idx, p, noise_m, cov, cfg, converged: bool = False
              ) -> tuple[FloatArray, FloatArray]:
    """GTSAM iSAM2 updated at each fix: online and final poses (module doc)."""
    import gtsam

    between, prior, fixes = _gtsam_graph(run, idx, p, noise_m, cov, cfg)
    params = gtsam.ISAM2Params()
    if converged:
        params.setRelinearizeThreshold(1e-4)
        params.relinearizeSkip = 1
    isam = gtsam.ISAM2(params)
    n = run.T_true.shape[0]
    online = np.zeros((n, 4, 4))
    graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    graph.add(prior)
    last = run.T_true[0]
    values.insert(0, gtsam.Pose3(last))
    online[0] = last
    for i in range(n):
        if i > 0:
            graph.add(between[i - 1])
            last = last @ run.steps[i - 1]
            values.insert(i, gtsam.Pose3(last))
        if i in fixes or i == 0:
            if i in fixes:
                graph.add(fixes[i])
            isam.update(graph, values)
            for _ in range(3 if converged else 0):
                isam.update()
            graph, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
            last = isam.calculateEstimatePose3(i).matrix()
        online[i] = last
    if graph.size():
        isam.update(graph, values)
    est = isam.calculateEstimate()
    final = np.array([est.atPose3(i).matrix() for i in range(n)])
    return online, final


def bench_fixes(interval_s: float, noise_m: float, seed: int = 0, path: str | Path = DEFAULT_MAT,
                sigma_xy: float = 0.02, sigma_yaw: float = 0.005, window_tracks: int = 5,
                with_gtsam: bool = True, isam2_converged: bool = False,
                refine_every: int | None = None, executor: str | None = None,
                calibrate: bool = True, relinearize_sigma: float | None = None,
                walk: tuple[ParameterModel, ...] = (RandomWalk('yaw_rate'),),
                online_noise: bool = False) -> FixBenchFigures:
    """One setting of the benchmark (module doc); ``refine_every``, ``executor``,
    ``relinearize_sigma``: the aligner's ``refine_every_tracks``, ``refine_executor`` and
    ``refine_relinearize_sigma`` (``None``: its defaults, as ``ga-ros replay`` runs it: a
    refinement at a track's end once the frozen nodes drifted by 1 sigma, inline or in a worker
    process by its size);
    ``calibrate``: also the final batch with self-calibration, and with ``walk``'s parameter
    models (by default the yaw rate as a random walk; ``()``: not run); ``online_noise``: the
    online + calibration run with ``calibration_noise`` (the calibrated source's noise
    re-estimated online too)."""
    run = load_plaza(path)
    idx, p = make_fixes(run, interval_s, noise_m, seed)
    cov = _step_cov(sigma_xy, sigma_yaw, 1e-3, 1e-4)
    extra = {k: v for k, v in (('refine_every_tracks', refine_every),
                               ('refine_executor', executor),
                               ('refine_relinearize_sigma', relinearize_sigma)) if v is not None}
    cfg = AlignerConfig(window_tracks=window_tracks, datum='fixes', **extra)
    n = run.T_true.shape[0]
    dead = np.zeros((n, 4, 4))
    dead[0] = run.T_true[0]
    for i in range(1, n):
        dead[i] = dead[i - 1] @ run.steps[i - 1]
    t0 = time.perf_counter()
    ours = run_ours(run, idx, p, noise_m, cov, cfg, CalibrationConfig() if calibrate else None,
                    walk=walk)
    t_ours = time.perf_counter() - t0
    warm = run_ours(run, idx, p, noise_m, cov, cfg)  # the same again: start-up already paid
    staged = run_ours(run, idx, p, noise_m, cov, cfg, stages=True)  # and timed by stages
    for again in (warm, staged):
        if not (np.array_equal(again.online, ours.online)
                and np.array_equal(again.final, ours.final)):
            raise AssertionError('ga-ros online: a run again differs from the first one')
    fig = FixBenchFigures(interval_s, noise_m, n, int(idx.size), _rmse(dead, run.T_true),
                          _rmse(_interpolated(run, idx, p), run.T_true),
                          _rmse(ours.online, run.T_true), _rmse(ours.final, run.T_true),
                          ours_seconds=t_ours, fix_outliers=ours.outliers,
                          ours_online_cpu_s=ours.online_cpu_s,
                          ours_online_warm_cpu_s=warm.online_cpu_s,
                          ours_final_cpu_s=ours.final_cpu_s,
                          calibration=ours.calibration,
                          ours_final_cal_cpu_s=ours.final_cal_cpu_s,
                          update_ms_quarters=_quarters(ours.update_ms),
                          update_cpu_ms_quarters=_quarters(ours.update_cpu_ms),
                          stage_cpu_s={**staged.stage_cpu_s, 'start-up': ours.online_cpu_s
                                       - warm.online_cpu_s},
                          ours_online_staged_cpu_s=staged.online_cpu_s,
                          work_per_update=staged.work_per_update)
    if calibrate:  # ours online + calibration: the online run with AlignerConfig.calibrate
        cal = run_ours(run, idx, p, noise_m, cov,
                       replace(cfg, calibrate=True, calibration_noise=online_noise), final=False)
        fig.ours_online_cal_m = _rmse(cal.online, run.T_true)
        fig.ours_online_cal_cpu_s = cal.online_cpu_s
        fig.cal_update_ms_quarters = _quarters(cal.update_ms)
        fig.cal_update_cpu_ms_quarters = _quarters(cal.update_cpu_ms)
        fig.online_calibration = cal.online_calibration
    if ours.final_cal is not None:
        fig.ours_final_cal_m = _rmse(ours.final_cal, run.T_true)
    if ours.final_cal_noise is not None:
        fig.ours_final_cal_noise_m = _rmse(ours.final_cal_noise, run.T_true)
    if ours.final_cal_stated is not None:
        fig.ours_final_cal_stated_m = _rmse(ours.final_cal_stated, run.T_true)
    if ours.final_cal_walk is not None:
        fig.ours_final_cal_walk_m = _rmse(ours.final_cal_walk, run.T_true)
        fig.ours_final_cal_walk_cpu_s = ours.final_cal_walk_cpu_s
        fig.walk_calibration = ours.walk_calibration
    if with_gtsam and gtsam_installed():
        t0, c0 = time.perf_counter(), all_cpu_seconds()
        fig.gtsam_batch_m = _rmse(run_gtsam_batch(run, idx, p, noise_m, cov, cfg), run.T_true)
        fig.gtsam_seconds = time.perf_counter() - t0
        fig.gtsam_batch_cpu_s = all_cpu_seconds() - c0
        t0, c0 = time.perf_counter(), all_cpu_seconds()
        on, fin = run_isam2(run, idx, p, noise_m, cov, cfg)
        fig.isam2_seconds = time.perf_counter() - t0
        fig.isam2_cpu_s = all_cpu_seconds() - c0
        fig.isam2_online_m, fig.isam2_final_m = _rmse(on, run.T_true), _rmse(fin, run.T_true)
        if isam2_converged:
            on, _ = run_isam2(run, idx, p, noise_m, cov, cfg, converged=True)
            fig.isam2_converged_online_m = _rmse(on, run.T_true)
    elif with_gtsam:
        fig.notes.append('GTSAM not installed (pip install -r requirements-bench.txt): its '
                         'columns skipped')
    return fig


def _quarters(values: list[float]) -> list[float]:
    """The means of the four quarters of ``values`` (in order)."""
    return [float(np.mean(q)) for q in np.array_split(np.asarray(values, float), 4) if q.size]


def mean_over_seeds(figs: list[FixBenchFigures]) -> list[FixBenchFigures]:
    """One figure per setting (interval, noise): the mean of every number over the seeds
    of the fix noise (``seeds`` the count; ``final_cal_wins`` / ``final_cal_batch_wins`` how
    many seeds had ga-ros final + calibration <= ga-ros final / GTSAM batch; ``online_wins`` how
    many seeds had ga-ros online
    <= iSAM2 online); the calibration lines and notes of the first seed."""
    out: list[FixBenchFigures] = []
    keys = list(dict.fromkeys((f.interval_s, f.noise_m) for f in figs))
    for key in keys:
        group = [f for f in figs if (f.interval_s, f.noise_m) == key]
        first = group[0]
        mean = FixBenchFigures(**{**asdict(first), 'calibration': list(first.calibration),
                                  'walk_calibration': list(first.walk_calibration),
                                  'online_calibration': list(first.online_calibration),
                                  'notes': list(first.notes)})
        for name, value in asdict(first).items():
            if isinstance(value, float):
                setattr(mean, name, float(np.mean([getattr(f, name) for f in group])))
        mean.update_ms_quarters = list(np.mean([f.update_ms_quarters for f in group], axis=0))
        mean.update_cpu_ms_quarters = list(np.mean([f.update_cpu_ms_quarters for f in group],
                                                   axis=0))
        for name in ('cal_update_ms_quarters', 'cal_update_cpu_ms_quarters'):
            if all(getattr(f, name) for f in group):
                setattr(mean, name, list(np.mean([getattr(f, name) for f in group], axis=0)))
        mean.work_per_update = {k: float(np.mean([f.work_per_update.get(k, 0.0)
                                                  for f in group]))
                                for k in dict.fromkeys(k for f in group
                                                       for k in f.work_per_update)}
        mean.fix_outliers = int(sum(f.fix_outliers for f in group))
        mean.seeds = len(group)
        mean.online_wins = sum(int(f.ours_online_m <= f.isam2_online_m) for f in group)
        mean.online_cal_wins = sum(int(f.ours_online_cal_m <= f.isam2_online_m) for f in group)
        mean.final_cal_wins = sum(int(f.ours_final_cal_m <= f.ours_final_m) for f in group)
        mean.final_cal_batch_wins = sum(int(f.ours_final_cal_m <= f.gtsam_batch_m)
                                        for f in group)
        out.append(mean)
    return out


def _work_table(rows: list[tuple[str, dict[str, float]]], per: str) -> str:
    """The work counts ``{'part kind': mean}`` of :func:`~ga_ros.bench.stages.counted_work`
    as a table, one line per part and setting: linearisations (``N`` assembled), gradient
    passes, costs evaluated alone and numeric factorisations, ``per`` saying per what."""
    from ga_ros.bench.stages import WORK_KINDS, WORK_PARTS

    out = [f'Work of ga-ros online {per} (mean; bench.stages.counted_work: linearisations = '
           'N and gradient assembled, gradients = a gradient pass without N, costs = a cost '
           'evaluated alone, factorisations = numeric sparse Cholesky; the refinement in '
           'this process only)',
           f'{"setting":14s}  {"part":13s}  ' + '  '.join(WORK_KINDS)]
    for label, work in rows:
        for part in [*WORK_PARTS, 'other']:
            if any(f'{part} {k}' in work for k in WORK_KINDS):
                out.append(f'{label:14s}  {part:13s}  ' + '  '.join(
                    f'{work.get(f"{part} {k}", 0.0):{len(k)}.2f}' for k in WORK_KINDS))
    return '\n'.join(out)


def table(figs: list[FixBenchFigures]) -> str:
    """The figures as a text table (RMSE in m; ratios ours / GTSAM), means over the seeds
    where ``figs`` holds several per setting (:func:`mean_over_seeds`)."""
    n_seeds = max(sum(1 for g in figs if (g.interval_s, g.noise_m) == (f.interval_s, f.noise_m))
                  for f in figs) if figs else 1
    figs = mean_over_seeds(figs)
    head = ('interval  noise  fixes  dead-reck  fixes-only  ours-online  ours-final  '
            'gtsam-batch  isam2-online  isam2-final  final/batch  online/isam2  gated  '
            'isam2-conv-online  online<=isam2')
    lines = []
    if n_seeds > 1:
        lines += [f'RMSE and CPU: means over {n_seeds} seeds of the fix noise (ratios: of the '
                  'means); online<=isam2: the seeds where ours online <= iSAM2 online; gated: '
                  'the sum over the seeds.']
    lines += [head]
    for f in figs:
        lines.append(
            f'{f.interval_s:6.0f} s {f.noise_m:4.0f} m {f.n_fixes:6d} {f.dead_reckoning_m:10.2f} '
            f'{f.fixes_alone_m:11.2f} {f.ours_online_m:12.2f} {f.ours_final_m:11.2f} '
            f'{f.gtsam_batch_m:12.2f} {f.isam2_online_m:13.2f} {f.isam2_final_m:12.2f} '
            f'{f.ours_final_m / f.gtsam_batch_m:12.3f} {f.ours_online_m / f.isam2_online_m:13.3f}'
            f' {f.fix_outliers:6d} {f.isam2_converged_online_m:18.2f}'
            f'  {f.online_wins:6d} of {f.seeds}')
    if any(np.isfinite(f.ours_final_cal_m) for f in figs):
        lines += ['', 'ours final + calibration: refine_batch(calibration=CalibrationConfig()) '
                  "after ours final: the odometry's scale and yaw-rate corrections estimated "
                  'with the poses where significant (alpha 0.001), and the calibrated '
                  "source's translation and rotation noise re-estimated (damped variance "
                  'factors); stated-noise: the same with the stated noise '
                  '(CalibrationConfig(noise=False)). GTSAM batch without calibration (a '
                  'BetweenFactorPose3 cannot express a yaw-rate bias), so the ratios are '
                  'ours final + calibration / GTSAM batch without calibration. '
                  'cal<=final, cal<=batch: the seeds where ours final + calibration <= ours '
                  'final (without calibration), <= GTSAM batch (one draw of the fix noise '
                  'can leave the calibrated batch behind: docs/calibration.md, Noisy fixes). '
                  'Calibration: of the first seed.',
                  'interval  noise  ours-final+cal  stated-noise  gtsam-batch  final+cal/batch  '
                  'stated/batch  final+cal-cpu  cal<=final  cal<=batch  calibration']
        for f in figs:
            lines.append(
                f'{f.interval_s:6.0f} s {f.noise_m:4.0f} m {f.ours_final_cal_m:15.2f} '
                f'{f.ours_final_cal_stated_m:13.2f} '
                f'{f.gtsam_batch_m:12.2f} {f.ours_final_cal_m / f.gtsam_batch_m:16.3f} '
                f'{f.ours_final_cal_stated_m / f.gtsam_batch_m:13.3f} '
                f'{f.ours_final_cal_cpu_s:14.2f} {f.final_cal_wins:5d} of {f.seeds} '
                f'{f.final_cal_batch_wins:5d} of {f.seeds}  ' + '; '.join(f.calibration))
    if any(np.isfinite(f.ours_final_cal_walk_m) for f in figs):
        lines += ['', 'ours final + calibration (random walk): the same as ours final + '
                  "calibration (noise re-estimated) with the odometry's yaw rate a random walk "
                  '(CalibrationConfig(models=(RandomWalk(...),)): knots every segment_s tied by '
                  'the process noise q; the constant tested for significance as above, the walk '
                  "estimated where it is kept). GTSAM batch without calibration. Walk: knots, "
                  "range, q and its pseudo-observations' v'Pv/r (about 1 where q fits the "
                  'data), of the first seed.',
                  'interval  noise  ours-final+cal  final+cal(walk)  gtsam-batch  '
                  'final+cal/batch  walk/batch  walk-cpu  walk']
        for f in figs:
            lines.append(
                f'{f.interval_s:6.0f} s {f.noise_m:4.0f} m {f.ours_final_cal_m:15.2f} '
                f'{f.ours_final_cal_walk_m:16.2f} {f.gtsam_batch_m:12.2f} '
                f'{f.ours_final_cal_m / f.gtsam_batch_m:16.3f} '
                f'{f.ours_final_cal_walk_m / f.gtsam_batch_m:11.3f} '
                f'{f.ours_final_cal_walk_cpu_s:9.2f}  '
                + '; '.join(x for x in f.walk_calibration if 'random walk' in x))
    if any(np.isfinite(f.ours_online_cal_m) for f in figs):
        lines += ['', 'ours online + calibration: the online run with AlignerConfig(calibrate='
                  "True): after each window update the odometry's scale and yaw-rate "
                  'corrections are estimated on the latest calibration_horizon_tracks finished '
                  'tracks where significant (alpha 0.001) and applied to the motions that enter '
                  'next; CPU of all processes of that online run (first run: with start-up); '
                  'online+cal<=isam2: the seeds where it is <= iSAM2 online; update-ms / '
                  'update-cpu-ms: mean update_ms (wall, waiting for the estimate in the '
                  "background included) and CPU ms of the calling thread (the estimate's "
                  'thread not included) of the calls that end a track, per quarter of the '
                  'run. Online estimate at the end: of the first seed.',
                  'interval  noise  ours-online  ours-online+cal  isam2-online  '
                  'online+cal/isam2  online+cal-cpu  online+cal<=isam2  update-ms-by-quarter  '
                  'update-cpu-ms-by-quarter  online estimate']
        for f in figs:
            lines.append(
                f'{f.interval_s:6.0f} s {f.noise_m:4.0f} m {f.ours_online_m:12.2f} '
                f'{f.ours_online_cal_m:16.2f} {f.isam2_online_m:13.2f} '
                f'{f.ours_online_cal_m / f.isam2_online_m:17.3f} '
                f'{f.ours_online_cal_cpu_s:15.2f} {f.online_cal_wins:11d} of {f.seeds}  '
                + ' / '.join(f'{q:.0f}' for q in f.cal_update_ms_quarters) + '  '
                + ' / '.join(f'{q:.0f}' for q in f.cal_update_cpu_ms_quarters) + '  '
                + '; '.join(x for x in f.online_calibration if 'yaw_rate' in x or 'scale' in x))
    lines += ['', 'CPU seconds of all processes (this one with its threads, the refinement '
              'worker): ga-ros online (the whole online run, as the replay runs it; the first '
              "run in this process, so with the start-up of ga-ros's lazy imports and compiled "
              'kernels), ga-ros online warm (the same run again in this process, bit-identical: '
              'start-up already paid, as in a node that has run for a while), ga-ros final '
              '(refine_batch), GTSAM batch LM (with the import of gtsam), GTSAM iSAM2 updated '
              'at each fix (gtsam already imported); ratios ga-ros online (warm) / iSAM2. Mean '
              "update_ms (wall) and CPU ms (the calling thread's) of the calls that end a "
              "track, per quarter of the run's tracks (first run).",
              'interval  noise  ours-online-cpu  ours-online-warm-cpu  ours-final-cpu  '
              'gtsam-batch-cpu  isam2-cpu  online/isam2  warm/isam2  update-ms-by-quarter  '
              'update-cpu-ms-by-quarter']
    for f in figs:
        lines.append(
            f'{f.interval_s:6.0f} s {f.noise_m:4.0f} m {f.ours_online_cpu_s:16.2f} '
            f'{f.ours_online_warm_cpu_s:21.2f} '
            f'{f.ours_final_cpu_s:15.2f} {f.gtsam_batch_cpu_s:16.2f} {f.isam2_cpu_s:10.2f} '
            f'{f.ours_online_cpu_s / f.isam2_cpu_s:13.1f} '
            f'{f.ours_online_warm_cpu_s / f.isam2_cpu_s:11.1f}  '
            + ' / '.join(f'{q:.0f}' for q in f.update_ms_quarters) + '  '
            + ' / '.join(f'{q:.0f}' for q in f.update_cpu_ms_quarters))
    names = list(dict.fromkeys(k for f in figs for k in f.stage_cpu_s))
    if names:
        lines += ['', "ga-ros online's CPU seconds by stage, from a third run timed by stage "
                  "(module doc; each stage its own time; 'other': the rest of this process, "
                  "'worker process': the refinement worker's CPU; 'start-up': ga-ros online - "
                  "ga-ros online warm; timed-cpu: that run's CPU, the stage timers' own "
                  "included, above the warm run's by their cost)",
                  'interval  noise  ' + '  '.join(names) + '  timed-cpu']
        for f in figs:
            lines.append(f'{f.interval_s:6.0f} s {f.noise_m:4.0f} m  ' + '  '.join(
                f'{f.stage_cpu_s.get(k, 0.0):{len(k)}.3f}' for k in names)
                + f'  {f.ours_online_staged_cpu_s:9.2f}')
    if any(f.work_per_update for f in figs):
        lines += ['', _work_table([(f'{f.interval_s:6.0f} s {f.noise_m:4.0f} m', f.work_per_update)
                                   for f in figs], "per track end of that run's online part")]
    notes = sorted({n for f in figs for n in f.notes})
    return '\n'.join(lines + notes)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='ga-ros bench fixes', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 allow_abbrev=False)
    ap.add_argument('--data', default=str(DEFAULT_MAT), help='Plaza2_.mat')
    ap.add_argument('--intervals', default='10,30,60', help='fix intervals (s), comma-separated')
    ap.add_argument('--noise', default='2,5', help='fix noise (m per axis), comma-separated')
    ap.add_argument('--seed', type=int, default=0, help='seed of the fix noise (the first)')
    ap.add_argument('--seeds', type=int, default=1,
                    help='run every setting with this many seeds of the fix noise (--seed, '
                    '--seed + 1, ...) and print the means (one draw of 5 m noise at 41 fixes '
                    'moves the RMSE by up to 2x)')
    ap.add_argument('--sigma-xy', type=float, default=0.02,
                    help='odometry sigma per 0.1 s step, x and y (m; default 0.02)')
    ap.add_argument('--sigma-yaw', type=float, default=0.005,
                    help="odometry sigma per step, yaw (rad; default 0.005: the odometry's "
                    'heading drifts 5.4e-4 rad per step against the ground truth, 0.054 rad '
                    'per 10 s, one sigma of a random walk of 0.005 per step)')
    ap.add_argument('--window', type=int, default=5, help='tracks (fix intervals) in the window')
    ap.add_argument('--refine-every', type=int, default=None,
                    help="the aligner's refine_every_tracks (background refinement with the "
                    "fixes; default: the aligner's, 1; 0: off)")
    ap.add_argument('--executor', default=None, choices=('auto', 'process', 'thread', 'inline'),
                    help="the aligner's refine_executor (default: the aligner's, auto)")
    ap.add_argument('--relinearize-sigma', type=float, default=None,
                    help="the aligner's refine_relinearize_sigma (default: the aligner's, 1; 0: "
                    'a refinement after every track)')
    ap.add_argument('--no-gtsam', action='store_true')
    ap.add_argument('--isam2-converged', action='store_true',
                    help='also iSAM2 relinearised to convergence at each fix (module doc)')
    ap.add_argument('--no-calibration', action='store_true',
                    help='skip the ours final + calibration and ours online + calibration columns')
    ap.add_argument('--walk-segment', type=float, default=RandomWalk.segment_s,
                    help='final + calibration (random walk): the knot spacing of the yaw '
                    "rate's random walk (s; default %(default)g)")
    ap.add_argument('--walk-sigma', type=float, default=RandomWalk.sigma_per_sqrt_s,
                    help='final + calibration (random walk): its process noise (rad/s per '
                    'sqrt(s); default %(default)g)')
    ap.add_argument('--no-walk', action='store_true',
                    help='skip the final + calibration (random walk) column')
    ap.add_argument('--online-noise', action='store_true',
                    help='ours online + calibration re-estimates the calibrated noise online '
                    '(AlignerConfig.calibration_noise)')
    ap.add_argument('--json', action='store_true')
    args = ap.parse_args(argv)
    if not Path(args.data).is_file():
        print(f'ga-ros bench fixes: no data file {args.data} (give --data)', file=sys.stderr)
        return 1
    if args.seeds < 1:
        print('ga-ros bench fixes: --seeds must be >= 1', file=sys.stderr)
        return 2
    figs = [bench_fixes(float(i), float(s), seed, args.data, args.sigma_xy,
                        args.sigma_yaw, args.window, not args.no_gtsam, args.isam2_converged,
                        args.refine_every, args.executor, not args.no_calibration,
                        args.relinearize_sigma,
                        () if args.no_walk else (RandomWalk('yaw_rate', args.walk_segment,
                                                            args.walk_sigma),),
                        args.online_noise)
            for s in args.noise.split(',') for i in args.intervals.split(',')
            for seed in range(args.seed, args.seed + args.seeds)]
    if args.json:
        print(json.dumps([asdict(f) for f in figs]))
    else:
        print(table(figs))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
