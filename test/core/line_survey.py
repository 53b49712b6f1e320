"""A straight survey with position fixes, and its least-squares solution written out by hand.

Rotations are identity and known to 1e-6 rad, so the se3 adjustment of the survey with position
fixes is the linear positions problem :func:`wls_positions` solves with numpy, independently of
the aligner. Used by the absolute-fix tests of the core (``test_fixes_core.py``) and of the
refinement (``window/test_fixes_refinement.py``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.geometry import se3

GAUGE_M = 100.0  # m, the gauge prior's position sigma (AlignerConfig.gauge_sigma_m)


class LineSurvey(NamedTuple):
    """Measurements of a straight survey (unpacks as ``measurements, z, p_true``).

    Attributes
    ----------
    measurements : consecutive motions, node i to i + 1, stamps ``(i + 1)`` s.
    z : (n - 1, 3) measured translations (m).
    p_true : (n, 3) true positions (m), the first at the origin.
    """

    measurements: list[Measurement]
    z: np.ndarray
    p_true: np.ndarray


def line_survey(rng: np.random.Generator, n_tracks: int, per_track: int,
                sigma_t: float) -> LineSurvey:
    """A straight survey along x (steps of ``[1, 0.2, 0]`` m) measured with ``sigma_t`` m of
    noise per axis, ``per_track`` nodes per track."""
    n = n_tracks * per_track
    step = np.array([1.0, 0.2, 0.0])
    p_true = np.cumsum(np.vstack([np.zeros(3), np.tile(step, (n - 1, 1))]), axis=0)
    cov = np.diag([sigma_t ** 2] * 3 + [1e-12] * 3)
    ms, z = [], []
    for i in range(n - 1):
        t = step + rng.normal(0, sigma_t, 3)
        z.append(t)
        ms.append(Measurement(i, i + 1, i // per_track, (i + 1) // per_track,
                              np.concatenate([t, np.zeros(3)]), cov, stamp_ns=(i + 1) * 10 ** 9))
    return LineSurvey(ms, np.array(z), p_true)


def wls_positions(n: int, z: np.ndarray, sigma_t: float,
                  fixes: dict[int, tuple[np.ndarray, float]],
                  gauge: tuple[np.ndarray, float] = (np.zeros(3), GAUGE_M)) -> np.ndarray:
    """Positions (n, 3) by weighted least squares: ``p_{i+1} - p_i = z_i`` (sigma ``sigma_t``),
    ``p_k = fix_k`` (``fixes[k] = (position, sigma)``), ``p_0 = gauge`` (weak)."""
    rows, rhs, w = [], [], []
    for i in range(n - 1):
        for a in range(3):
            r = np.zeros(3 * n)
            r[3 * (i + 1) + a], r[3 * i + a] = 1.0, -1.0
            rows.append(r)
            rhs.append(z[i, a])
            w.append(1.0 / sigma_t ** 2)
    for k, (p, s) in list(fixes.items()) + [(0, gauge)]:
        for a in range(3):
            r = np.zeros(3 * n)
            r[3 * k + a] = 1.0
            rows.append(r)
            rhs.append(p[a])
            w.append(1.0 / s ** 2)
    A, b, W = np.array(rows), np.array(rhs), np.diag(w)
    return np.linalg.solve(A.T @ W @ A, A.T @ W @ b).reshape(n, 3)


def gnss_fix(node_id: int, stamp_ns: int, p_world: np.ndarray, sigma_m: float) -> FixTerm:
    """A position fix of a node (rotation unknown, ``sigma_m`` per axis), source ``gnss``."""
    T = se3.from_translation_rotvec(p_world, np.zeros(3))
    return FixTerm(node_id, se3.identity(), AbsoluteFix.from_covariance(
        stamp_ns, T, np.diag([sigma_m ** 2] * 3 + [-1.0] * 3), 'gnss'))


def feed(al: TrackWindowAligner, measurements: list[Measurement],
         fixes: dict[int, tuple[np.ndarray, float]]) -> None:
    """Feed the measurements to ``al``, each fix (``fixes[node] = (position, sigma)``, see
    :func:`gnss_fix`) right after the measurement that introduces its node."""
    for m in measurements:
        al.add_measurement(m)
        if m.dst_id in fixes:
            p, s = fixes[m.dst_id]
            al.add_fix(gnss_fix(m.dst_id, m.stamp_ns, p, s))


def fixes_aligner(window_tracks: int, refine_every_tracks: int = 0,
                  **kw) -> TrackWindowAligner:
    """The aligner of these tests: datum from the fixes, the weak gauge of :func:`wls_positions`
    with rotations pinned, dense priors, no fix gate, the refinement inline."""
    cfg = AlignerConfig(window_tracks=window_tracks, datum='fixes',
                        refine_every_tracks=refine_every_tracks, refine_executor='inline',
                        gauge_sigma_m=GAUGE_M, gauge_sigma_tilt_rad=1e-6,
                        gauge_sigma_yaw_rad=1e-6, prior_band=-1, fix_gate_prob=0.0, **kw)
    return TrackWindowAligner(cfg)
