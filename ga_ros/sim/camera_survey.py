"""A survey whose camera is mounted with a rotation error: the set-up of a camera's extrinsic
calibration (:mod:`ga_ros.core.calibration.camera_parameters`), with the truth known.

:func:`swath_survey`: a vehicle flies ``n_swaths`` parallel swaths along ``x`` in alternating
directions (``per_swath`` keyframes ``step_m`` apart, swaths ``spacing_m`` apart in ``y``, one
keyframe every ``dt_s`` seconds). A body-frame odometry ``odom0`` measures every consecutive
motion (the turns between swaths included) without systematic error; the camera ``cam0``
measures cross-track connections between neighbouring swaths (every ``cross_every``-th
keyframe to the keyframe of the next swath nearest to it), each turning by 180 deg. The
camera's extrinsic is off by ``phi`` (rad, body frame): its motions are
``T_meas = X^-1 T_true X exp(xi)``, ``X = [exp(phi), 0]``, so that the correction
``X T_meas X^-1`` of :mod:`~ga_ros.core.calibration.camera_parameters` gives back the true
motion up to the noise. The first keyframe is held at its true pose.

:func:`line_survey`: the camera alone on a straight line (every motion a translation along
``x``, the same conjugation), with position fixes every ``fix_every`` keyframes and the weak
gauge prior of ``datum='fixes'`` (1000 m, 0.05 rad roll/pitch, 3 rad yaw) at the first node.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.calibration.camera_parameters import conjugations
from ga_ros.core.measurement import Measurement
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.solver import GaussianPrior
from ga_ros.geometry import se3
from ga_ros.sim.biased import fix_priors_every

#: The odometry's noise per motion ``[x y z rx ry rz]`` (m, rad), also its stated covariance.
ODOMETRY_SIGMA = np.array([0.02, 0.02, 0.01, 0.001, 0.001, 0.003])
#: The camera's noise per motion (m, rad), also its stated covariance.
CAMERA_SIGMA = np.array([0.02, 0.02, 0.02, 0.002, 0.002, 0.002])


@dataclass(frozen=True)
class CameraSurvey:
    """The truth and the measurements.

    Attributes
    ----------
    T_true : (n, 4, 4) true poses.
    network : the connections (node ids 0..n-1), motions as measured.
    T_init : (n, 4, 4) an initial guess (the consecutive motions integrated from the true
        first pose).
    sources : (m,) each connection's odometry source (``'odom0'``, or ``'cam0'`` for the
        camera's consecutive motions; None for cross-track connections).
    groups : (m,) each connection's source, cross-track included (``'odom0'``, ``'cam0'``).
    dt_s : (m,) each motion's duration (s).
    fixed : node ids held.
    priors : the fixes and the gauge prior (none for :func:`swath_survey`).
    """

    T_true: FloatArray
    network: ConnectionNetwork
    T_init: FloatArray
    sources: list[str | None]
    groups: list[str]
    dt_s: FloatArray
    fixed: list[int]
    priors: list[GaussianPrior]


def _measured(rng: np.random.Generator, T_true_rel: FloatArray, phi: FloatArray,
              sigma: FloatArray) -> FloatArray:
    """(m, 6) the true motions ``T_true_rel`` (m, 4, 4) conjugated, ``X^-1 T X exp(xi)``,
    with ``xi ~ N(0, diag(sigma^2))``."""
    X = conjugations(np.broadcast_to(np.asarray(phi, dtype=float), (T_true_rel.shape[0], 3)))
    T = se3.inverse(X) @ T_true_rel @ X
    return se3.to_translation_rotvec(T @ se3.exp(rng.standard_normal((T.shape[0], 6)) * sigma))


def swath_survey(rng: np.random.Generator, phi: FloatArray = (0.0, 0.0, 0.0),
                 n_swaths: int = 6, per_swath: int = 30, step_m: float = 2.0,
                 spacing_m: float = 10.0, dt_s: float = 1.0, cross_every: int = 3,
                 camera_consecutive: bool = False) -> CameraSurvey:
    """Simulate the swath survey of the module doc; ``phi`` (3,) the extrinsic's rotation
    error (rad, body frame); ``camera_consecutive``: the camera measures every consecutive
    motion too (its visual odometry beside ``odom0``; source ``cam0``)."""
    n = n_swaths * per_swath
    T = np.repeat(np.eye(4)[None], n, axis=0)
    for k in range(n_swaths):
        rows = slice(k * per_swath, (k + 1) * per_swath)
        x = np.arange(per_swath) * step_m
        if k % 2:
            x = x[::-1]
            T[rows, :3, :3] = np.diag([-1.0, -1.0, 1.0])
        T[rows, 0, 3] = x
        T[rows, 1, 3] = k * spacing_m
    src = list(range(n - 1))
    dst = list(range(1, n))
    groups = ['odom0'] * (n - 1)
    cross = [False] * (n - 1)
    if camera_consecutive:
        src += list(range(n - 1))
        dst += list(range(1, n))
        groups += ['cam0'] * (n - 1)
        cross += [False] * (n - 1)
    for k in range(n_swaths - 1):
        for a in range(0, per_swath, cross_every):
            i = k * per_swath + a
            j = (k + 1) * per_swath + (per_swath - 1 - a)  # the same x in the next swath
            src.append(i)
            dst.append(j)
            groups.append('cam0')
            cross.append(True)
    src_a, dst_a = np.array(src), np.array(dst)
    rel = se3.inverse(T[src_a]) @ T[dst_a]
    cam = np.array(groups) == 'cam0'
    z = np.zeros((src_a.size, 6))
    z[~cam] = se3.to_translation_rotvec(rel[~cam] @ se3.exp(
        rng.standard_normal(((~cam).sum(), 6)) * ODOMETRY_SIGMA))
    z[cam] = _measured(rng, rel[cam], phi, CAMERA_SIGMA)
    cov = np.where(cam[:, None, None], np.diag(CAMERA_SIGMA ** 2), np.diag(ODOMETRY_SIGMA ** 2))
    ids = np.arange(n)
    net = ConnectionNetwork.from_arrays(ids, ids // per_swath, src_a, dst_a, z, cov)
    T_init = se3.integrate(T[0], se3.from_translation_rotvec(z[~cam, :3], z[~cam, 3:]))
    dt = np.abs(dst_a - src_a).astype(float) * dt_s
    sources = [None if c else g for g, c in zip(groups, cross)]
    return CameraSurvey(T, net, T_init, sources, groups, dt, [0], [])


def line_survey(rng: np.random.Generator, phi: FloatArray = (0.0, 0.0, 0.0),
                n_nodes: int = 120, step_m: float = 1.0, dt_s: float = 1.0,
                fix_every: int = 10, fix_sigma_m: float = 0.5) -> CameraSurvey:
    """Simulate the straight-line survey of the module doc: the camera ``cam0``'s consecutive
    motions along ``x`` (``phi`` (3,) its extrinsic's rotation error, rad, body frame) and
    position fixes."""
    T = np.repeat(np.eye(4)[None], n_nodes, axis=0)
    T[:, 0, 3] = np.arange(n_nodes) * step_m
    m = n_nodes - 1
    z = _measured(rng, se3.inverse(T[:-1]) @ T[1:], phi, CAMERA_SIGMA)
    cov = np.repeat(np.diag(CAMERA_SIGMA ** 2)[None], m, axis=0)
    ids = np.arange(n_nodes)
    net = ConnectionNetwork.from_arrays(ids, np.zeros(n_nodes, int), ids[:-1], ids[1:], z, cov)
    T_init = se3.integrate(T[0], se3.from_translation_rotvec(z[:, :3], z[:, 3:]))
    return CameraSurvey(T, net, T_init, ['cam0'] * m, ['cam0'] * m,
                        np.full(m, float(dt_s)), [],
                        fix_priors_every(rng, T, fix_every, fix_sigma_m))


def live_measurements(survey: CameraSurvey, per_swath: int) -> list[Measurement]:
    """A :func:`swath_survey` as a live stream, in the order a node receives it: each
    keyframe's ``odom0`` motion, then the ``cam0`` cross-track connections that end at it
    (one track per swath of ``per_swath`` keyframes; stamps: keyframe index in s)."""
    arr = survey.network.arrays()
    cross: dict[int, list[int]] = {}
    for c in range(len(arr)):
        if survey.groups[c] == 'cam0':
            cross.setdefault(int(arr.dst[c]), []).append(c)
    ms = []
    for c in range(len(arr)):
        if survey.groups[c] != 'odom0':
            continue
        i, j = int(arr.src[c]), int(arr.dst[c])
        ms.append(Measurement(i, j, i // per_swath, j // per_swath, arr.z[c], arr.cov[c],
                              j * 10 ** 9, 'consecutive', 'odom0'))
        ms += [Measurement(int(arr.src[k]), j, int(arr.src[k]) // per_swath, j // per_swath,
                           arr.z[k], arr.cov[k], j * 10 ** 9, 'cross', 'cam0')
               for k in cross.get(j, [])]
    return ms
