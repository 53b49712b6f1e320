"""The additional parameters of a camera source (self-calibration): the rotation error of its
extrinsic ``T_body_cam``, what it corrects in every motion of the camera, and its generator.

A camera's motions (visual odometry, cross-track connections) become body motions with the
extrinsic ``E = T_body_cam``: ``T_body = E T_cam E^-1``. Where the mounting's rotation is off by
``delta`` (rad, a rotation vector in the camera frame), ``E_true = E exp([0, delta])``, every
motion of the camera, consecutive and cross-track alike, is conjugated:
``T_true = X T_meas X^-1`` with ``X = E exp([0, delta]) E^-1``, the rotation ``R_E delta``
about the camera's centre in the body frame.

The parameter is ``phi = R_E delta`` (:class:`ExtrinsicRotationAxis`, rad, body frame, one
scalar per axis: ``extrinsic_rx``, ``extrinsic_ry``, ``extrinsic_rz``), and ``X = [exp(phi), 0]``
rotates about the body origin: the camera's lever arm ``c`` is left out. The exact correction
rotates about ``c``; the two differ by ``(I - R_T) (I - exp(phi)) c`` in a motion's
translation (``R_T`` its rotation): none for a motion without rotation, at most
``2 |phi| |c|`` for a cross-track connection that turns by 180 deg (1.2 cm at 0.03 rad and
0.2 m).

The corrected motion of a connection with the source's other parameters (a camera that is
also named an odometry source: scale, yaw rate, :mod:`.parameters`) is
``T_corr = X S(T_meas) X^-1``, ``S`` the odometry correction. Its right perturbation per unit
of ``phi_a`` (``T_corr(phi + e_a dphi) = T_corr exp(G_a dphi)`` to first order), with
``T_in = S(T_meas)`` and ``exp(phi + dphi) = exp(phi) exp(J_r(phi) dphi)``:

    X exp(eta) T_in exp(-eta) X^-1 = T_corr X exp(Ad(T_in^-1) eta) exp(-eta) X^-1
    G_a = Ad(X) (Ad(T_in^-1) - I) [0, J_r(phi) e_a]

(a first-order generator: checked against central differences in the tests). An odometry
parameter's generator ``G`` of ``T_in`` becomes ``Ad(X) G`` of ``T_corr``.

What the network can see: a constant conjugation of every motion is absorbed by the poses
(``T_i X^-1`` for every ``i`` closes every connection again, with the same positions). So the
extrinsic is determined only against another source of the body's orientation: a body-frame
odometry (wheels, an INS) measuring the same motions or closing loops with the camera's
cross-track connections, fixes with an orientation, a held node. Against such a source a
motion's rotation shows it (a cross-track connection between swaths flown in opposite
directions tilts by ``2 phi_x``, ``2 phi_y``), and so does its translation (rotated by
``exp(phi)``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError
from ga_ros.geometry import se3, so3


@dataclass(frozen=True)
class ExtrinsicRotationAxis:
    """One axis of a camera extrinsic's rotation error ``phi`` (rad, body frame):
    ``T_true = X T_meas X^-1``, ``X = [exp(phi), 0]`` (module doc)."""

    axis: int
    name: str
    unit: str = 'rad'
    family: ClassVar[str] = 'camera'
    #: a first-order correction of a small rotation: known to worse than this (rad) even with
    #: the other parameters known, it is not determined (an extrinsic that is 3 deg off is a
    #: configuration to fix, not a correction to estimate)
    max_sigma: ClassVar[float] = 0.05
    on_fixes: ClassVar[bool] = False
    datum: ClassVar[bool] = False
    unobserved: ClassVar[str] = 'no motion it acts on (every motion the identity)'
    unseen: ClassVar[str] = ('the poses absorb it (no other source of the body orientation: a '
                             'body-frame odometry, fixes with orientation, a held node)')

    def acts_on(self, z: FloatArray, dt_s: FloatArray) -> FloatArray:
        """(m,) how much each motion tells about the parameter (its translation plus its
        rotation; a conjugation leaves only the identity unchanged)."""
        return np.linalg.norm(z[:, :3], axis=1) + np.linalg.norm(z[:, 3:], axis=1)

    def add(self, corrections, mask: np.ndarray, value: float) -> None:
        """Add ``value`` to the connections ``mask`` of ``corrections``
        (:class:`~ga_ros.core.calibration.parameters.MotionCorrections`)."""
        corrections.extrinsic[mask, self.axis] += value

    def generator_of(self, motions) -> FloatArray:
        """(m, 6) ``G_a = Ad(X) (Ad(T_in^-1) - I) [0, J_r(phi) e_a]`` of the corrected motions
        ``motions`` (:class:`~ga_ros.core.calibration.parameters.CorrectedMotions`)."""
        m = motions.T.shape[0]
        phi = motions.extrinsic if motions.extrinsic is not None else np.zeros((m, 3))
        eta = np.zeros((m, 6))
        eta[:, 3:] = so3.right_jacobian(phi)[:, :, self.axis]
        G = (se3.adjoint(se3.inverse(motions.T_in)) @ eta[:, :, None])[:, :, 0] - eta
        X = conjugations(phi)
        return (se3.adjoint(X) @ G[:, :, None])[:, :, 0]


#: The additional parameters of a camera source, by name.
CAMERA_PARAMETERS = {p.name: p for p in (ExtrinsicRotationAxis(0, 'extrinsic_rx'),
                                         ExtrinsicRotationAxis(1, 'extrinsic_ry'),
                                         ExtrinsicRotationAxis(2, 'extrinsic_rz'))}


def camera_parameter(name: str) -> ExtrinsicRotationAxis:
    """The camera parameter called ``name`` (:data:`CAMERA_PARAMETERS`)."""
    try:
        return CAMERA_PARAMETERS[name]
    except KeyError:
        raise InputError(f'unknown camera calibration parameter {name!r}; choose from '
                         f'{sorted(CAMERA_PARAMETERS)}') from None


def conjugations(phi: FloatArray) -> FloatArray:
    """(m, 4, 4) ``X = [exp(phi), 0]`` of rotation vectors ``phi`` (m, 3) (rad, body frame)."""
    phi = np.asarray(phi, dtype=float).reshape(-1, 3)
    X = np.zeros((phi.shape[0], 4, 4))
    X[:, :3, :3] = so3.exp(phi)
    X[:, 3, 3] = 1.0
    return X


def conjugated_covariances(cov: FloatArray, phi: FloatArray, inverse: bool = False
                           ) -> FloatArray:
    """(m, 6, 6) the covariances of motions conjugated by ``X = [exp(phi), 0]``,
    ``X T X^-1``, from those ``cov`` (m, 6, 6) of the motions ``T`` (order ``[x y z rx ry
    rz]``; ``phi`` (m, 3) rad, body frame): ``Ad_X C Ad_X^T`` with ``Ad_X = diag(R, R)``,
    ``R = exp(phi)`` (the adjoint of a pure rotation). Exact, not a linearisation: the
    conjugated motion's translation is ``R t`` and its rotation vector ``R omega``, linear in
    ``[t, omega]`` (and in any tangent perturbation of ``T``). ``inverse``: the covariances
    of ``X^-1 T X`` (``R^T`` in place of ``R``), undoing it."""
    R = so3.exp(np.asarray(phi, dtype=float).reshape(-1, 3))
    if inverse:
        R = np.swapaxes(R, 1, 2)
    A = np.zeros((R.shape[0], 6, 6))
    A[:, :3, :3] = R
    A[:, 3:, 3:] = R
    out = A @ np.asarray(cov, dtype=float).reshape(-1, 6, 6) @ np.swapaxes(A, 1, 2)
    return 0.5 * (out + np.swapaxes(out, 1, 2))


def check_cameras(cameras: Sequence[str], known: Sequence[str], what: str = 'camera') -> None:
    """Every camera to calibrate is a source of the measurements.

    Parameters
    ----------
    cameras : the names to calibrate (``--calibrate-camera``, ``calibrate_cameras``).
    known : the sources the measurements carry (``cam0``, ``odom0``, ...).
    what : how the caller names the setting, for the message.

    Raises
    ------
    InputError
        A name that is not among ``known`` (the message lists them).
    """
    unknown = [c for c in cameras if c not in set(known)]
    if unknown:
        listing = ', '.join(sorted(set(known))) or 'none'
        raise InputError(f'{what} {", ".join(map(repr, unknown))}: no such source; the '
                         f'sources of the measurements are: {listing} (a stereo camera is '
                         "'cam0' unless its parameter source names it otherwise)")


def camera_sources(groups: Sequence[str], cameras: Sequence[str]) -> list[str | None]:
    """(m,) the camera of each connection: its source (the ``source`` of its measurement,
    :func:`~ga_ros.core.measurement.source_or_group`; consecutive and cross-track alike) where
    that is one of ``cameras``, else None."""
    named = set(cameras)
    return [g if g in named else None for g in groups]
