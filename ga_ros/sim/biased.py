"""Odometry with systematic errors and position fixes: the set-up of self-calibration
(:mod:`ga_ros.core.calibration`), with the truth known.

A ground robot drives :func:`~ga_ros.sim.sources.weaving_path` (``n_nodes`` keyframes
``step_m`` apart, one every ``dt_s`` seconds). Its odometry ``odom0`` measures each motion
with a scale error and a yaw-rate bias: ``T_meas = [R Rz(-omega dt), t / (1 + k)] exp(xi)``
with ``xi ~ N(0, diag(sigma^2))``, so that the corrections ``k`` (``scale``) and ``omega``
(``yaw_rate``, rad/s) of :mod:`ga_ros.core.calibration.parameters` give back the true motion.
Every ``fix_every`` nodes (the first included) a position fix ``p_true + N(0, fix_sigma_m^2 I)``
enters as a :class:`~ga_ros.core.solver.GaussianPrior` of the position only; the first node
also has the weak gauge prior of ``datum='fixes'`` (1000 m, 0.05 rad roll/pitch, 3 rad yaw) at
its true pose. :func:`biased_fixes` adds fix sources with an offset and a latency (the
parameters of :mod:`ga_ros.core.calibration.fix_parameters`), one by one.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.linalg as sla

from ga_ros.arrays import FloatArray
from ga_ros.core.calibration.fix_parameters import FixObservations
from ga_ros.core.calibration.parameters import corrected_motions
from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior
from ga_ros.geometry import se3
from ga_ros.sim.sources import weaving_path


@dataclass(frozen=True)
class BiasedSurvey:
    """The truth, the biased odometry and the fixes.

    Attributes
    ----------
    T_true : (n, 4, 4) true poses.
    network : the odometry connections (node ids 0..n-1, measured motions).
    T_dead : (n, 4, 4) the odometry integrated from the true first pose (an initial guess).
    priors : the fixes and the gauge prior.
    dt_s : (n-1,) each motion's duration (s).
    sources : (n-1,) each connection's source (``'odom0'``).
    """

    T_true: FloatArray
    network: ConnectionNetwork
    T_dead: FloatArray
    priors: list[GaussianPrior]
    dt_s: FloatArray
    sources: list[str]


def biased_survey(rng: np.random.Generator, n_nodes: int = 300, step_m: float = 1.0,
                  dt_s: float = 0.5, scale: float = 0.0, yaw_rate: float | FloatArray = 0.0,
                  sigma_xy_m: float = 0.01, sigma_yaw_rad: float = 0.002,
                  fix_every: int = 30, fix_sigma_m: float = 1.0,
                  stated_sigma_xy_m: float | None = None,
                  stated_sigma_yaw_rad: float | None = None) -> BiasedSurvey:
    """Simulate the survey of the module doc; ``scale``, ``yaw_rate``: the true corrections
    ``k`` and ``omega`` (rad/s; ``yaw_rate`` (n-1,): one per motion, a bias that varies);
    ``sigma_*``: the odometry's noise per motion (also its stated
    covariance: x, y ``sigma_xy_m``, z 1 mm, roll/pitch 0.1 mrad, yaw ``sigma_yaw_rad``);
    ``stated_*``: a stated covariance other than the true noise (None: the true one)."""
    T = weaving_path(n_nodes, step_m)
    rel = se3.inverse(T[:-1]) @ T[1:]
    m = n_nodes - 1
    dt = np.full(m, float(dt_s))
    z_true = se3.to_translation_rotvec(rel)
    # the biased motion: corrected_motions with the opposite corrections inverts them exactly
    biased = corrected_motions(z_true, dt, np.full(m, 1.0 / (1.0 + scale) - 1.0),
                               -np.broadcast_to(np.asarray(yaw_rate, dtype=float), (m,)))
    sig = np.array([sigma_xy_m, sigma_xy_m, 1e-3, 1e-4, 1e-4, sigma_yaw_rad])
    meas = biased @ se3.exp(rng.standard_normal((m, 6)) * sig)
    stated = sig.copy()
    if stated_sigma_xy_m is not None:
        stated[:2] = stated_sigma_xy_m
    if stated_sigma_yaw_rad is not None:
        stated[5] = stated_sigma_yaw_rad
    cov = np.repeat(np.diag(stated ** 2)[None], m, axis=0)
    ids = np.arange(n_nodes)
    net = ConnectionNetwork.from_arrays(ids, ids // 100, ids[:-1], ids[1:],
                                        se3.to_translation_rotvec(meas), cov)
    dead = se3.integrate(T[0], meas)
    return BiasedSurvey(T, net, dead, fix_priors_every(rng, T, fix_every, fix_sigma_m), dt,
                        ['odom0'] * m)


def fix_priors_every(rng: np.random.Generator, T_true: FloatArray, fix_every: int,
                     fix_sigma_m: float) -> list[GaussianPrior]:
    """``[gauge, fixes]`` of a simulated survey: a weak gauge prior on node 0 (position 1,000 m,
    roll and pitch 0.05 rad, yaw 3 rad) and a position fix every ``fix_every`` nodes from 0
    (``T_true`` (n, 4, 4) plus ``N(0, fix_sigma_m^2 I)`` per axis, m; no orientation)."""
    T = np.asarray(T_true, dtype=float)
    at = np.arange(0, T.shape[0], fix_every)
    means = np.repeat(np.eye(4)[None], at.size, axis=0)
    means[:, :3, 3] = T[at, :3, 3] + rng.normal(0.0, fix_sigma_m, (at.size, 3))
    info = np.diag([fix_sigma_m ** -2] * 3 + [0.0] * 3)
    fixes = GaussianPrior(at, means, sla.block_diag(*[info] * at.size))
    gauge = GaussianPrior.from_covariances([0], T[:1], np.diag(
        [1e6, 1e6, 1e6, 0.05 ** 2, 0.05 ** 2, 9.0])[None])
    return [gauge, fixes]


@dataclass(frozen=True)
class FixSource:
    """A simulated fix source with systematic errors (:func:`biased_fixes`).

    Attributes
    ----------
    name : its ``source`` (``fix0``, ...).
    every : a fix every this many keyframes, ``first`` the first one's keyframe.
    sigma_m : its noise per axis (m), also its stated covariance.
    offset_m : (3,) its constant offset ``b`` (m, map frame): ``p_fix = p_true + b``.
    latency_s : its time offset ``tau`` (s): the fix stamped at a keyframe measured the
        position ``tau`` earlier.
    """

    name: str
    every: int = 10
    first: int = 0
    sigma_m: float = 0.5
    offset_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    latency_s: float = 0.0


def biased_fixes(rng: np.random.Generator, T_true: FloatArray, stamps_s: FloatArray,
                 sources: list[FixSource]) -> FixObservations:
    """Position fixes of ``sources`` on the keyframes of a path (``T_true`` (n, 4, 4) true
    poses, ``stamps_s`` (n,) their stamps, increasing): each stamped at its keyframe, measuring
    the position at ``stamp - latency_s`` (the true path interpolated linearly between
    keyframes, clamped at its ends) plus the offset and ``N(0, sigma_m^2 I)``; no lever arm.
    Returns the fixes one by one, in ``sources``' order."""
    P = np.asarray(T_true, dtype=float)[:, :3, 3]
    t = np.asarray(stamps_s, dtype=float)
    terms, infos = [], []
    for src in sources:
        info = np.diag([src.sigma_m ** -2] * 3 + [0.0] * 3)
        for k in range(src.first, t.size, src.every):
            at = t[k] - src.latency_s
            p = np.array([np.interp(at, t, P[:, i]) for i in range(3)])
            T = np.eye(4)
            T[:3, 3] = p + np.asarray(src.offset_m) + rng.normal(0.0, src.sigma_m, 3)
            terms.append(FixTerm(k, np.eye(4), AbsoluteFix(int(round(t[k] * 1e9)), T, info,
                                                           src.name)))
            infos.append(info)
    return FixObservations(terms, np.array(infos).reshape(-1, 6, 6), t)
