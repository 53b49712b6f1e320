"""Sensor offsets (``PARAMS_*OFFSET``): edges between sensor frames to and from the robot frame."""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.geometry import se3
from ga_ros.io.g2o.planar import SE2_AXES


def apply_offsets(T: FloatArray, info: FloatArray, param: IntArray,
                   offsets: dict[int, FloatArray], dim: int,
                   inverse: bool) -> tuple[FloatArray, FloatArray]:
    """Sensor-frame edges ``(Z, Omega)`` to robot-frame ``(S Z S^-1, Ad(S^-1)' Omega Ad(S^-1))``
    for the edges that name an offset ``S`` (``inverse``: the other way)."""
    named = np.flatnonzero(param >= 0)
    if named.size == 0:
        return T, info
    keys = np.array(sorted(offsets), dtype=np.int64)
    S = np.stack([offsets[k] for k in keys.tolist()])[np.searchsorted(keys, param[named])]
    Sinv = se3.inverse(S)
    T, info = T.copy(), info.copy()
    A = se3.adjoint(S if inverse else Sinv)   # Omega_new = A' Omega A
    if dim == 2:
        A = A[:, SE2_AXES[:, None], SE2_AXES[None, :]]
    if inverse:
        T[named] = Sinv @ T[named] @ S
    else:
        T[named] = S @ T[named] @ Sinv
    info[named] = np.swapaxes(A, 1, 2) @ info[named] @ A
    info[named] = 0.5 * (info[named] + np.swapaxes(info[named], 1, 2))
    return T, info
