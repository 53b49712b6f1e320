"""Stereo calibration: rectified intrinsics and baseline, with rectification of raw images.

A :class:`CameraModel` mirrors ``sensor_msgs/CameraInfo`` (``K``, ``D``, ``R``, ``P``) without
importing ROS. :meth:`StereoCalibration.from_camera_models` decides whether the images need
rectifying: a camera is rectified when its distortion is zero and ``R`` is the identity
(then ``P[:3, :3]`` is used as is); otherwise undistort-rectify maps are built from
``K, D, R, P`` (``cv2.initUndistortRectifyMap``), as for real cameras with lens distortion.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError


@dataclass(frozen=True)
class CameraModel:
    """One camera's calibration, field for field as in ``sensor_msgs/CameraInfo``.

    Attributes
    ----------
    width, height : image size (px).
    K : (3, 3) raw intrinsics.
    D : (k,) distortion coefficients (``plumb_bob``: k1 k2 t1 t2 k3); empty or zeros: none.
    R : (3, 3) rectification rotation.
    P : (3, 4) projection of the rectified camera; ``P[0, 3] = -fx' * baseline`` on the right.
    distortion_model : ``'plumb_bob'``, ``'rational_polynomial'`` or ``'equidistant'``.
    """

    width: int
    height: int
    K: FloatArray
    D: FloatArray = field(default_factory=lambda: np.zeros(0))
    R: FloatArray = field(default_factory=lambda: np.eye(3))
    P: FloatArray | None = None
    distortion_model: str = 'plumb_bob'

    def projection(self) -> FloatArray:
        """(3, 4) ``P``, defaulting to ``[K | 0]``."""
        if self.P is None:
            return np.hstack([np.asarray(self.K, float), np.zeros((3, 1))])
        return np.asarray(self.P, float).reshape(3, 4)

    def is_rectified(self) -> bool:
        """True when the images need no undistortion or rectification."""
        D = np.asarray(self.D, float).ravel()
        R = np.asarray(self.R, float).reshape(3, 3)
        same_k = np.allclose(self.projection()[:3, :3], np.asarray(self.K, float).reshape(3, 3),
                             rtol=1e-6, atol=1e-6)
        return (D.size == 0 or not np.any(D)) and np.allclose(R, np.eye(3)) and same_k


@dataclass(frozen=True)
class StereoCalibration:
    """Rectified stereo geometry plus (optional) rectification maps.

    Attributes
    ----------
    width, height : image size (px).
    K : (3, 3) intrinsics of the rectified left (and right) image.
    baseline_m : baseline (m).
    maps_left, maps_right : ``(map_x, map_y)`` float32 remap tables, or None when the input
        is already rectified.
    """

    width: int
    height: int
    K: FloatArray
    baseline_m: float
    maps_left: tuple[np.ndarray, np.ndarray] | None = None
    maps_right: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def needs_rectification(self) -> bool:
        """True when :meth:`rectify` remaps the images."""
        return self.maps_left is not None

    @staticmethod
    def rectified(width: int, height: int, K: FloatArray, baseline_m: float) -> StereoCalibration:
        """Calibration of an already rectified pair."""
        K = np.asarray(K, float).reshape(3, 3)
        if width <= 0 or height <= 0 or baseline_m <= 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError('stereo calibration needs positive size, focal length and baseline')
        return StereoCalibration(int(width), int(height), K, float(baseline_m))

    @staticmethod
    def from_camera_models(left: CameraModel, right: CameraModel) -> StereoCalibration:
        """Calibration from the two CameraInfo-like models (see module doc).

        Raises
        ------
        InputError
            Sizes differ, the baseline is not positive, or the matrices are malformed.
        """
        if (left.width, left.height) != (right.width, right.height):
            raise InputError(f'left camera is {left.width}x{left.height}, '
                             f'right camera is {right.width}x{right.height}')
        try:
            Pl, Pr = left.projection(), right.projection()
        except ValueError as exc:
            raise InputError(f'malformed projection matrix: {exc}') from exc
        if not (np.all(np.isfinite(Pl)) and np.all(np.isfinite(Pr))):
            raise InputError('camera matrices must be finite')
        if Pr[0, 0] <= 0:
            raise InputError('right projection has a non-positive focal length')
        baseline = -Pr[0, 3] / Pr[0, 0]
        if not baseline > 0:
            raise InputError(f'stereo baseline from P_right[0, 3] is {baseline:g} m; '
                             'expected a positive baseline (right camera to the right)')
        K = Pl[:3, :3].copy()
        if left.is_rectified() and right.is_rectified():
            return StereoCalibration.rectified(left.width, left.height, K, baseline)
        size = (int(left.width), int(left.height))
        maps = []
        for cam, P in ((left, Pl), (right, Pr)):
            Kc = np.asarray(cam.K, float).reshape(3, 3)
            D = np.asarray(cam.D, float).ravel()
            R = np.asarray(cam.R, float).reshape(3, 3)
            if cam.distortion_model == 'equidistant':
                mx, my = cv2.fisheye.initUndistortRectifyMap(Kc, D[:4], R, P[:3, :3], size,
                                                             cv2.CV_32FC1)
            else:
                mx, my = cv2.initUndistortRectifyMap(Kc, D if D.size else None, R, P[:3, :3],
                                                     size, cv2.CV_32FC1)
            maps.append((mx, my))
        return StereoCalibration(size[0], size[1], K, float(baseline), maps[0], maps[1])

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistort and rectify a raw pair (identity when already rectified)."""
        if self.maps_left is None or self.maps_right is None:
            return left, right
        return (cv2.remap(left, *self.maps_left, cv2.INTER_LINEAR),
                cv2.remap(right, *self.maps_right, cv2.INTER_LINEAR))
