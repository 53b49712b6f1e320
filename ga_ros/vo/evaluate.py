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
    cal = StereoCalibration.rectified(rig.width, rig.height, rig.K, rig.baseline_m)
    vo = StereoOdometry(cal, c.vo)
    matcher = CrossTrackMatcher(rig.K, rig.width, rig.height, c.cross_config)
    rng = np.random.default_rng(c.seed + 1)
    n = len(survey.T_world_cam) if frames is None else min(int(frames), len(survey.T_world_cam))
    kf_frame: dict[int, int] = {}
    cons_t, cons_r, cons_rel, cons_nees = [], [], [], []
    straight_nees: list[float] = []
    turn_nees: list[float] = []
    status_count: dict[str, int] = {}
    attempts = []
    vo_seconds = 0.0
    vo_cpu = 0.0
    cross_seconds = 0.0
    for i in range(n):
        left, right = scene.render_pair(survey.T_world_cam[i], rng)
        t0, c0 = time.perf_counter(), time.process_time()
        res = vo.process(StereoFrame(left, right, int(survey.stamps_ns[i])))
        vo_seconds += time.perf_counter() - t0
        vo_cpu += time.process_time() - c0
        status_count[res.status] = status_count.get(res.status, 0) + 1
        if res.status in ('initialised', 'keyframe', 'lost') and res.keyframe_id >= 0:
            kf_frame[res.keyframe_id] = i
        m = res.measurement
        if m is not None:
            T_true = se3.relative(survey.T_world_cam[kf_frame[m.src_id]], survey.T_world_cam[i])
            dt, dr, nees = motion_errors(T_true, m)
            cons_t.append(dt)
            cons_r.append(dr)
            cons_rel.append(100.0 * dt / max(float(np.linalg.norm(T_true[:3, 3])), 1e-9))
            cons_nees.append(nees)
            turn = bool(survey.in_turn[kf_frame[m.src_id]] or survey.in_turn[i])
            (turn_nees if turn else straight_nees).append(nees)
        if c.cross and res.keyframe is not None:
            t0 = time.perf_counter()
            attempts.extend(matcher.add(res.keyframe))
            cross_seconds += time.perf_counter() - t0
    out: dict = {
        'size': f'{c.width}x{c.height}', 'frames': n, 'keyframes': len(kf_frame),
        'status': status_count,
        'vo_pairs_per_s': n / max(vo_seconds, 1e-9),
        'vo_pairs_per_cpu_s': n / max(vo_cpu, 1e-9),
        'consecutive': {
            'translation_error_pct': _stats(cons_rel), 'translation_error_m': _stats(cons_t),
            'rotation_error_deg': _stats(cons_r), 'nees': _stats(cons_nees),
            'nees_swaths': _stats(straight_nees), 'nees_turns': _stats(turn_nees)},
    }
    if not c.cross:
        return out
    correct, cross_nees, cross_t = [], [], []
    accepted_pairs = set()
    reasons: dict[str, int] = {}
    for a in attempts:
        if not a.accepted:
            reasons[a.gate] = reasons.get(a.gate, 0) + 1
            continue
        m = a.measurement
        T_true = se3.relative(survey.T_world_cam[kf_frame[m.src_id]],
                              survey.T_world_cam[kf_frame[m.dst_id]])
        dt, dr, nees = motion_errors(T_true, m)
        ok = dt < c.correct_translation_m and dr < c.correct_rotation_deg
        correct.append(ok)
        cross_t.append(dt)
        if ok:
            cross_nees.append(nees)
        accepted_pairs.add((min(m.src_id, m.dst_id), max(m.src_id, m.dst_id)))
    # Recall over keyframe pairs of different swaths with a true overlap >= the threshold,
    # limited to pairs the store could still hold (within the window of tracks).
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
    out['cross'] = {
        'attempts': len(attempts), 'accepted': len(correct), 'correct': int(np.sum(correct)),
        'precision': float(np.mean(correct)) if correct else float('nan'),
        'true_pairs': n_true, 'found_pairs': n_found,
        'recall': n_found / n_true if n_true else float('nan'),
        'translation_error_m': _stats(cross_t), 'nees_correct': _stats(cross_nees),
        'rejections': reasons, 'seconds_per_keyframe': cross_seconds / max(len(kf_frame), 1),
    }
    return out
