"""Benchmark of the stereo odometry and cross-track matching on the stereo simulator.

:func:`run_benchmark` renders a seeded lawnmower survey (:mod:`ga_ros.sim.stereo`), runs
:class:`~ga_ros.vo.odometry.StereoOdometry` and :class:`~ga_ros.vo.crosstrack.CrossTrackMatcher`
on it and compares with the ground truth:

* consecutive motions: translation error relative to the distance travelled, rotation error,
  and the NEES ``e^T Sigma^-1 e`` with ``e = log(T_true^-1 T_meas)`` (mean 6 when honest);
* cross-track connections: precision (an accepted connection is correct when its error is
  below ``correct_translation_m`` and ``correct_rotation_deg``) and recall over the keyframe
  pairs of different swaths whose true mutual overlap is at least ``recall_min_overlap``
  (frames in the turns between swaths are left out: their overlap with the end of the
  previous swath is already bridged by the consecutive motions);
* throughput: stereo pairs per second of the odometry alone (rendering excluded), by the wall
  clock and per CPU second of the process (all its threads; robust to other load).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from ga_ros.core.measurement import Measurement
from ga_ros.geometry import se3, so3
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene
from ga_ros.vo.calibration import StereoCalibration
from ga_ros.vo.crosstrack import CrossTrackConfig, CrossTrackMatcher
from ga_ros.vo.odometry import StereoFrame, StereoOdometry, VoConfig


@dataclass(frozen=True)
class BenchConfig:
    """What :func:`run_benchmark` simulates and how it scores.

    Attributes
    ----------
    width, height : image size (px); the rig is :meth:`StereoRig.for_size`.
    n_tracks, positions_per_swath : survey size (double swaths, frames per swath).
    seed : seed of terrain, flight wobble and image noise.
    noise_std : image noise (grey levels).
    cross : run the cross-track matcher.
    correct_translation_m, correct_rotation_deg : error bounds of a correct cross connection.
    recall_min_overlap : true overlap that makes a pair count for the recall (0-1).
    vo, cross_config : parameters of the odometry and of the matcher.
    """

    width: int = 320
    height: int = 240
    n_tracks: int = 2
    positions_per_swath: int = 40
    seed: int = 0
    noise_std: float = 1.5
    cross: bool = True
    correct_translation_m: float = 1.0
    correct_rotation_deg: float = 1.0
    recall_min_overlap: float = 0.7
    vo: VoConfig = field(default_factory=VoConfig)
    cross_config: CrossTrackConfig = field(default_factory=CrossTrackConfig)


def motion_errors(T_true: np.ndarray, m: Measurement) -> tuple[float, float, float]:
    """Translation error (m), rotation error (deg) and NEES of a measurement vs the truth."""
    T_meas = m.T_src_dst
    e = se3.log(se3.inverse(T_true) @ T_meas)
    dt = float(np.linalg.norm(T_true[:3, 3] - T_meas[:3, 3]))
    dr = float(np.rad2deg(np.linalg.norm(so3.log(T_true[:3, :3].T @ T_meas[:3, :3]))))
    return dt, dr, float(e @ np.linalg.solve(m.cov, e))


def _stats(x: list[float]) -> dict:
    a = np.asarray(x, float)
    if a.size == 0:
        return {'n': 0}
    return {'n': int(a.size), 'mean': float(a.mean()), 'median': float(np.median(a)),
            'p90': float(np.percentile(a, 90)), 'max': float(a.max())}


def run_benchmark(config: BenchConfig = BenchConfig(), frames: int | None = None) -> dict:
    """Simulate, run VO (+ cross-track matching) and return the figures as a dict.

    ``frames`` limits the number of stereo pairs processed (None: the whole survey).
    """
    c = config
    survey = lawnmower(LawnmowerConfig(n_tracks=c.n_tracks,
                                       positions_per_swath=c.positions_per_swath, seed=c.seed))
    rig = StereoRig.for_size(c.width, c.height)
    scene = make_scene(survey, rig, seed=c.seed, noise_std=c.noise_std)
    n = len(survey.T_world_cam) if frames is None else min(int(frames), len(survey.T_world_cam))
    run = _run_vo(c, survey, scene, rig, n)
    out: dict = {
        'size': f'{c.width}x{c.height}', 'frames': n, 'keyframes': len(run.kf_frame),
        'status': run.status_count,
        'vo_pairs_per_s': n / max(run.vo_seconds, 1e-9),
        'vo_pairs_per_cpu_s': n / max(run.vo_cpu, 1e-9),
        'consecutive': {
            'translation_error_pct': _stats(run.cons_rel),
            'translation_error_m': _stats(run.cons_t),
            'rotation_error_deg': _stats(run.cons_r), 'nees': _stats(run.cons_nees),
            'nees_swaths': _stats(run.straight_nees), 'nees_turns': _stats(run.turn_nees)},
    }
    if c.cross:
        out['cross'] = _cross_figures(c, run, survey, scene)
    return out


@dataclass
class _VoRun:
    """What :func:`_run_vo` collected: the survey frame of each keyframe id, the errors of the
    consecutive motions (translation m, rotation deg, translation % of travel, NEES; NEES split
    along swaths / in turns), status counts, the matcher's attempts and the times (s)."""

    kf_frame: dict[int, int] = field(default_factory=dict)
    cons_t: list[float] = field(default_factory=list)
    cons_r: list[float] = field(default_factory=list)
    cons_rel: list[float] = field(default_factory=list)
    cons_nees: list[float] = field(default_factory=list)
    straight_nees: list[float] = field(default_factory=list)
    turn_nees: list[float] = field(default_factory=list)
    status_count: dict[str, int] = field(default_factory=dict)
    attempts: list = field(default_factory=list)
    vo_seconds: float = 0.0
    vo_cpu: float = 0.0
    cross_seconds: float = 0.0


def _run_vo(c: BenchConfig, survey, scene, rig: StereoRig, n: int) -> _VoRun:
    """Render the first ``n`` frames, run the odometry (and the matcher on its keyframes) and
    score each consecutive motion against the truth."""
    cal = StereoCalibration.rectified(rig.width, rig.height, rig.K, rig.baseline_m)
    vo = StereoOdometry(cal, c.vo)
    matcher = CrossTrackMatcher(rig.K, rig.width, rig.height, c.cross_config)
    rng = np.random.default_rng(c.seed + 1)
    run = _VoRun()
    kf_frame = run.kf_frame
    for i in range(n):
        left, right = scene.render_pair(survey.T_world_cam[i], rng)
        t0, c0 = time.perf_counter(), time.process_time()
        res = vo.process(StereoFrame(left, right, int(survey.stamps_ns[i])))
        run.vo_seconds += time.perf_counter() - t0
        run.vo_cpu += time.process_time() - c0
        run.status_count[res.status] = run.status_count.get(res.status, 0) + 1
        if res.status in ('initialised', 'keyframe', 'lost') and res.keyframe_id >= 0:
            kf_frame[res.keyframe_id] = i
        m = res.measurement
        if m is not None:
            T_true = se3.relative(survey.T_world_cam[kf_frame[m.src_id]], survey.T_world_cam[i])
            dt, dr, nees = motion_errors(T_true, m)
            run.cons_t.append(dt)
            run.cons_r.append(dr)
            run.cons_rel.append(100.0 * dt / max(float(np.linalg.norm(T_true[:3, 3])), 1e-9))
            run.cons_nees.append(nees)
            turn = bool(survey.in_turn[kf_frame[m.src_id]] or survey.in_turn[i])
            (run.turn_nees if turn else run.straight_nees).append(nees)
        if c.cross and res.keyframe is not None:
            t0 = time.perf_counter()
            run.attempts.extend(matcher.add(res.keyframe))
            run.cross_seconds += time.perf_counter() - t0
    return run


def _cross_figures(c: BenchConfig, run: _VoRun, survey, scene) -> dict:
    """Precision of the accepted cross-track connections, recall, errors and rejections."""
    correct, cross_nees, cross_t = [], [], []
    accepted_pairs = set()
    reasons: dict[str, int] = {}
    for a in run.attempts:
        if not a.accepted:
            reasons[a.gate] = reasons.get(a.gate, 0) + 1
            continue
        m = a.measurement
        T_true = se3.relative(survey.T_world_cam[run.kf_frame[m.src_id]],
                              survey.T_world_cam[run.kf_frame[m.dst_id]])
        dt, dr, nees = motion_errors(T_true, m)
        ok = dt < c.correct_translation_m and dr < c.correct_rotation_deg
        correct.append(ok)
        cross_t.append(dt)
        if ok:
            cross_nees.append(nees)
        accepted_pairs.add((min(m.src_id, m.dst_id), max(m.src_id, m.dst_id)))
    n_true, n_found = _recall_counts(c, run.kf_frame, survey, scene, accepted_pairs)
    return {
        'attempts': len(run.attempts), 'accepted': len(correct),
        'correct': int(np.sum(correct)),
        'precision': float(np.mean(correct)) if correct else float('nan'),
        'true_pairs': n_true, 'found_pairs': n_found,
        'recall': n_found / n_true if n_true else float('nan'),
        'translation_error_m': _stats(cross_t), 'nees_correct': _stats(cross_nees),
        'rejections': reasons,
        'seconds_per_keyframe': run.cross_seconds / max(len(run.kf_frame), 1),
    }


def _recall_counts(c: BenchConfig, kf_frame: dict[int, int], survey, scene,
                   accepted_pairs: set[tuple[int, int]]) -> tuple[int, int]:
    """Keyframe pairs of different swaths with a true overlap >= ``recall_min_overlap``,
    limited to pairs the store could still hold (within the window of tracks), and how many
    of them were accepted."""
    ids = sorted(kf_frame)
    pos = {k: survey.T_world_cam[kf_frame[k]][:3, 3] for k in ids}
    n_true, n_found = 0, 0
    for ai, a in enumerate(ids):
        fa = kf_frame[a]
        for b in ids[ai + 1:]:
            fb = kf_frame[b]
            if survey.swath[fa] == survey.swath[fb] or survey.in_turn[fa] or survey.in_turn[fb]:
                continue
            if survey.track[fb] - survey.track[fa] >= c.cross_config.window_tracks:
                continue
            if np.linalg.norm(pos[a] - pos[b]) > 60.0:
                continue
            ov = min(scene.overlap(survey.T_world_cam[fa], survey.T_world_cam[fb]),
                     scene.overlap(survey.T_world_cam[fb], survey.T_world_cam[fa]))
            if ov >= c.recall_min_overlap:
                n_true += 1
                n_found += (a, b) in accepted_pairs
    return n_true, n_found
