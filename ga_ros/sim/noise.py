"""Noise model of the paper's experiments: Gaussian noise as a percentage of the true motion.

The paper (Sec. V-A) adds "Gaussian noise of 1, 5, 10, 18 and 25 % of the true parameters of the
motion between nodes". Taken literally per component (``sigma_k = pct * |l_k|``) this gives *zero*
noise on every parameter whose true value is zero -- in the paper's scenarios the camera does not
rotate (Sec. V-B: "the camera moves in a horizontal plane with no rotation"), so the rotation
would be noise-free, which no image-based motion estimate is. We therefore scale the noise by the
*size* of the motion, per axis:

* translation, each axis: ``sigma_t = pct * |t|`` (m), with ``|t|`` the length of the true
  translation (10 m between consecutive aerial frames: 1 m at 10 %);
* rotation, each axis: ``sigma_w = pct * max(|w|, |t| / depth)`` (rad), where ``|t| / depth`` is
  the angle the translation subtends at the scene depth (the altitude above the ground, 110 m):
  a rotation of that angle shifts the image as much as the translation does, so a given
  percentage error in the image motion gives the same percentage error in both (10 m at 110 m:
  0.091 rad, so 0.0091 rad = 0.52 deg per axis at 10 %).

The covariance handed to the solver is the true noise covariance ``diag(sigma^2)``. For the
``se3`` model the noise ``xi ~ N(0, diag(sigma^2))`` is the right perturbation of the motion
(``T_meas = T_true exp(xi)``, the network's convention); for the position models (``paper``,
``linear``) it is added to ``[t, w]`` directly (to first order the same thing when the true
rotation is the identity).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError
from ga_ros.geometry import se3

#: Smallest standard deviation used (m or rad), so that a zero motion still has a PD covariance.
SIGMA_FLOOR = 1e-6


@dataclass(frozen=True)
class NoiseModel:
    """Gaussian motion noise scaled by the true motion.

    Attributes
    ----------
    percent : noise level in percent of the true motion (the paper: 1, 5, 10, 18, 25).
    depth_m : scene depth (m) that converts a translation into its equivalent rotation angle
        ``|t| / depth_m`` (the altitude above the ground; 110 m in the aerial scenario).
    """

    percent: float
    depth_m: float = 110.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.percent) or self.percent < 0:
            raise InputError(f'noise percent must be finite and >= 0, got {self.percent}')
        if not np.isfinite(self.depth_m) or self.depth_m <= 0:
            raise InputError(f'noise depth_m must be finite and > 0, got {self.depth_m}')

    def sigmas(self, z_true: FloatArray) -> FloatArray:
        """Per-component standard deviations ``(m, 6)`` (m, rad) for true motions ``(m, 6)``."""
        z_true = np.asarray(z_true, dtype=float).reshape(-1, 6)
        f = self.percent / 100.0
        t_norm = np.linalg.norm(z_true[:, :3], axis=1)
        w_norm = np.linalg.norm(z_true[:, 3:], axis=1)
        w_ref = np.maximum(w_norm, t_norm / self.depth_m)
        out = np.empty_like(z_true)
        out[:, :3] = (f * t_norm)[:, None]
        out[:, 3:] = (f * w_ref)[:, None]
        return np.maximum(out, SIGMA_FLOOR)

    def covariances(self, z_true: FloatArray) -> FloatArray:
        """Covariances ``(m, 6, 6)``: ``diag(sigma^2)`` in the order ``[x y z rx ry rz]``."""
        s = self.sigmas(z_true)
        cov = np.zeros((s.shape[0], 6, 6))
        idx = np.arange(6)
        cov[:, idx, idx] = s * s
        return cov


@dataclass(frozen=True)
class NoisyMotions:
    """Measured motions and their covariances.

    Attributes
    ----------
    z : (m, 6) measured ``[t, w]`` (m, rad) of each connection.
    cov : (m, 6, 6) covariance given to the solver (the true noise covariance).
    """

    z: FloatArray
    cov: FloatArray


def perturb(z_true: FloatArray, noise: NoiseModel, rng: np.random.Generator,
            model: str = 'se3') -> NoisyMotions:
    """Add Gaussian noise to true motions.

    Parameters
    ----------
    z_true : (m, 6) true ``[t, w]`` of each connection (m, rad).
    noise : the noise model (see the module docstring).
    rng : seeded generator; one ``(m, 6)`` standard normal draw is taken from it.
    model : ``'se3'`` (noise is the right perturbation of the motion, ``T_true exp(xi)``) or
        ``'paper'`` / ``'linear'`` (noise added to ``[t, w]``).

    Returns
    -------
    NoisyMotions with ``z`` and ``cov = diag(sigma^2)``.
    """
    if model not in ('se3', 'paper', 'linear'):
        raise InputError(f"model must be 'se3', 'paper' or 'linear', got {model!r}")
    z_true = np.asarray(z_true, dtype=float).reshape(-1, 6)
    s = noise.sigmas(z_true)
    xi = rng.standard_normal(z_true.shape) * s
    if model == 'se3':
        T_true = se3.from_translation_rotvec(z_true[:, :3], z_true[:, 3:])
        z = se3.to_translation_rotvec(T_true @ se3.exp(xi))
    else:
        z = z_true + xi
    return NoisyMotions(z=z, cov=noise.covariances(z_true))
