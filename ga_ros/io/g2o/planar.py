"""Planar (SE(2)) poses embedded in SE(3): ``z = 0``, rotation about ``z``."""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import FloatArray

#: index of the 2-D components [x y theta] inside our 6-vector [x y z rx ry rz]
SE2_AXES = np.array([0, 1, 5])


def se2_to_se3(xyt: FloatArray) -> FloatArray:
    """Planar poses ``[x, y, theta]`` (m, rad) ``(..., 3)`` as ``(..., 4, 4)`` with ``z = 0``."""
    xyt = np.asarray(xyt, dtype=float)
    c, s = np.cos(xyt[..., 2]), np.sin(xyt[..., 2])
    T = np.zeros(xyt.shape[:-1] + (4, 4))
    T[..., 0, 0], T[..., 0, 1], T[..., 1, 0], T[..., 1, 1] = c, -s, s, c
    T[..., 2, 2] = T[..., 3, 3] = 1.0
    T[..., 0, 3], T[..., 1, 3] = xyt[..., 0], xyt[..., 1]
    return T


def se3_to_se2(T: FloatArray) -> FloatArray:
    """``[x, y, yaw]`` ``(..., 3)`` of poses ``(..., 4, 4)`` (yaw = atan2(R10, R00), in
    ``(-pi, pi]``); ``z`` and tilt are dropped."""
    T = np.asarray(T, dtype=float)
    return np.stack([T[..., 0, 3], T[..., 1, 3], np.arctan2(T[..., 1, 0], T[..., 0, 0])],
                    axis=-1)
