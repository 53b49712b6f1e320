"""The additional parameters of an odometry source (self-calibration): what each corrects in a
measured motion, and its generator (the derivative of the corrected motion).

A source's measured motion ``T_meas = [R, t]`` (``T_src_dst``, body frame of ``src``) becomes
``T_corr = [R Rz(omega dt), (1 + k) t]`` with

* ``k`` (:class:`ScaleCorrection`, dimensionless): the correction of the translation's scale,
  ``t_true = (1 + k) t_meas`` (a wheel radius that is 1 % too small: ``k = 0.01``);
* ``omega`` (:class:`YawRateCorrection`, rad/s): the correction of the yaw rate about the body
  ``z`` axis over the motion's duration ``dt`` (s), ``R_true = R_meas Rz(omega dt)``: a gyro or
  odometry heading that drifts at ``-omega`` rad/s (a source's yaw-rate bias is ``-omega``).
  Per second, not per metre: a heading bias that accrues while the robot stands still (the
  CMU Plaza run's wheel odometry drifts 8 deg in its first 20 s at rest) is a rate.

Both are linear in the corrected motion and commute. The generator ``G`` of a parameter is
the right perturbation of ``T_corr`` per unit of it, ``T_corr(x + dx) = T_corr(x) exp(G dx)``
(exact for both), so the misclosure ``e = log(T_corr^-1 T_i^-1 T_j)`` of a connection changes
by ``de/dx = -J_l(e)^-1 G`` (:func:`misclosure_jacobian`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.calibration.camera_parameters import conjugations
from ga_ros.errors import InputError
from ga_ros.geometry import se3


def _rz(angle: FloatArray) -> FloatArray:
    c, s = np.cos(angle), np.sin(angle)
    R = np.zeros(np.shape(angle) + (3, 3))
    R[..., 0, 0], R[..., 0, 1], R[..., 1, 0], R[..., 1, 1] = c, -s, s, c
    R[..., 2, 2] = 1.0
    return R


class _OdometryParameter:
    """What every additional parameter of an odometry source shares: it acts on the source's
    motions (not on fixes), its sigma is not bounded (step 2 of :mod:`.batch`), and its
    generator is conjugated like the motions it corrects."""

    family: ClassVar[str] = 'odometry'
    max_sigma: ClassVar[float] = float('inf')
    on_fixes: ClassVar[bool] = False
    datum: ClassVar[bool] = False
    unseen: ClassVar[str] = 'no fixes or loop closures that see it'

    def generator(self, R_corr: FloatArray, t_meas: FloatArray, dt_s: FloatArray) -> FloatArray:
        raise NotImplementedError

    def generator_of(self, motions: CorrectedMotions) -> FloatArray:
        """(m, 6) ``G`` of the corrected motions ``motions`` (``Ad(X) G`` where a camera's
        extrinsic correction conjugates them, :mod:`.camera_parameters`)."""
        return motions.outer(self.generator(motions.T_in[:, :3, :3], motions.z[:, :3],
                                            motions.dt_s))


@dataclass(frozen=True)
class ScaleCorrection(_OdometryParameter):
    """``t_true = (1 + k) t_meas`` (module doc); ``k`` dimensionless."""

    name: str = 'scale'
    unit: str = '1'
    unobserved: ClassVar[str] = 'no motion it acts on (no translation)'

    def acts_on(self, z: FloatArray, dt_s: FloatArray) -> FloatArray:
        """(m,) how much each motion tells about the parameter (its translation, m)."""
        return np.linalg.norm(z[:, :3], axis=1)

    def generator(self, R_corr: FloatArray, t_meas: FloatArray, dt_s: FloatArray) -> FloatArray:
        """(m, 6) ``G``: ``[R_corr' t_meas, 0]``."""
        G = np.zeros((t_meas.shape[0], 6))
        G[:, :3] = np.einsum('mji,mj->mi', R_corr, t_meas)
        return G

    def add(self, corrections: MotionCorrections, mask: np.ndarray, value: float) -> None:
        """Add ``value`` to the scale of the connections ``mask``."""
        corrections.scale[mask] += value


@dataclass(frozen=True)
class YawRateCorrection(_OdometryParameter):
    """``R_true = R_meas Rz(omega dt)`` (module doc); ``omega`` in rad/s."""

    name: str = 'yaw_rate'
    unit: str = 'rad/s'
    unobserved: ClassVar[str] = 'no motion it acts on (no durations: stamps?)'

    def acts_on(self, z: FloatArray, dt_s: FloatArray) -> FloatArray:
        """(m,) how much each motion tells about the parameter (its duration, s)."""
        return np.asarray(dt_s, dtype=float)

    def generator(self, R_corr: FloatArray, t_meas: FloatArray, dt_s: FloatArray) -> FloatArray:
        """(m, 6) ``G``: ``[0, 0, 0, 0, 0, dt]``."""
        G = np.zeros((t_meas.shape[0], 6))
        G[:, 5] = dt_s
        return G

    def add(self, corrections: MotionCorrections, mask: np.ndarray, value: float) -> None:
        """Add ``value`` to the yaw rate of the connections ``mask``."""
        corrections.yaw_rate[mask] += value


#: The additional parameters of an odometry source, by name.
PARAMETERS = {p.name: p for p in (ScaleCorrection(), YawRateCorrection())}


def parameter(name: str) -> ScaleCorrection | YawRateCorrection:
    """The parameter called ``name`` (:data:`PARAMETERS`)."""
    try:
        return PARAMETERS[name]
    except KeyError:
        raise InputError(f'unknown calibration parameter {name!r}; choose from '
                         f'{sorted(PARAMETERS)}') from None


def corrected_motions(z: FloatArray, dt_s: FloatArray, scale: FloatArray,
                      yaw_rate: FloatArray, extrinsic: FloatArray | None = None) -> FloatArray:
    """(m, 4, 4) ``T_corr`` of measured motions ``z`` (m, 6) ``[t, w]`` with per-connection
    ``scale`` ``k`` and ``yaw_rate`` ``omega`` (rad/s; ``dt_s`` (m,) s), module doc; with
    ``extrinsic`` (m, 3) a camera's extrinsic rotation correction ``phi`` (rad, body frame):
    ``X T_corr X^-1`` (:mod:`.camera_parameters`)."""
    z = np.asarray(z, dtype=float)
    T = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
    T[:, :3, 3] *= (1.0 + np.asarray(scale, dtype=float))[:, None]
    T[:, :3, :3] = T[:, :3, :3] @ _rz(np.asarray(yaw_rate, dtype=float) * dt_s)
    if extrinsic is not None and np.any(extrinsic):
        X = conjugations(extrinsic)
        T = X @ T @ se3.inverse(X)
    return T


@dataclass
class MotionCorrections:
    """The corrections of every connection's motion: ``scale`` (m,) ``k``, ``yaw_rate`` (m,)
    ``omega`` (rad/s) and ``extrinsic`` (m, 3) ``phi`` (rad, body frame; a camera's,
    :mod:`.camera_parameters`)."""

    scale: FloatArray
    yaw_rate: FloatArray
    extrinsic: FloatArray

    @staticmethod
    def zeros(m: int) -> MotionCorrections:
        return MotionCorrections(np.zeros(m), np.zeros(m), np.zeros((m, 3)))

    def apply(self, z: FloatArray, dt_s: FloatArray) -> CorrectedMotions:
        """The motions ``z`` (m, 6) of durations ``dt_s`` (m,) corrected."""
        T_in = corrected_motions(z, dt_s, self.scale, self.yaw_rate)
        if not np.any(self.extrinsic):
            return CorrectedMotions(np.asarray(z, dtype=float), np.asarray(dt_s, dtype=float),
                                    T_in, T_in, None)
        X = conjugations(self.extrinsic)
        return CorrectedMotions(np.asarray(z, dtype=float), np.asarray(dt_s, dtype=float),
                                T_in, X @ T_in @ se3.inverse(X), self.extrinsic.copy())


@dataclass
class CorrectedMotions:
    """Measured motions and their corrections: ``z`` (m, 6) as measured, ``dt_s`` (m,) s,
    ``T_in`` (m, 4, 4) with the odometry parameters (``S(T_meas)``), ``T`` (m, 4, 4) the
    corrected motions ``X T_in X^-1``, ``extrinsic`` (m, 3) ``phi`` (None: all zero,
    ``T = T_in``)."""

    z: FloatArray
    dt_s: FloatArray
    T_in: FloatArray
    T: FloatArray
    extrinsic: FloatArray | None

    def rows(self, sel: np.ndarray) -> CorrectedMotions:
        """The connections ``sel`` (a mask or indices)."""
        return CorrectedMotions(self.z[sel], self.dt_s[sel], self.T_in[sel], self.T[sel],
                                None if self.extrinsic is None else self.extrinsic[sel])

    def outer(self, G: FloatArray) -> FloatArray:
        """(m, 6) a generator ``G`` of ``T_in`` as one of ``T``: ``Ad(X) G``."""
        if self.extrinsic is None:
            return G
        return (se3.adjoint(conjugations(self.extrinsic)) @ G[:, :, None])[:, :, 0]


def misclosure_jacobian(e: FloatArray, G: FloatArray) -> FloatArray:
    """(m, 6) ``de/dx = -J_l(e)^-1 G`` of misclosures ``e`` (m, 6) for generators ``G`` (m, 6)
    (module doc)."""
    return -(se3.left_jacobian_inv(e) @ G[:, :, None])[:, :, 0]
