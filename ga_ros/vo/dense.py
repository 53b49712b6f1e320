"""Dense stereo points of a rectified pair (ROS-free): :class:`DenseStereo`.

The disparity of every pixel of the rectified left image comes from OpenCV's semi-global
matching (``cv2.StereoSGBM``, 1/16 px), computed over ``[0, num_disparities)`` px. Each valid
pixel ``(u, v)`` of disparity ``d`` (px) is triangulated in the left camera's optical frame
(REP 103 optical: ``z`` forward, ``x`` right, ``y`` down), in metres::

    z = fx * B / d,   x = (u - cx) * z / fx,   y = (v - cy) * z / fy

with ``fx, fy, cx, cy`` of the rectified left projection and ``B`` the baseline
(:class:`ga_ros.vo.calibration.StereoCalibration`, which takes them from ``P_left`` and
``P_right``; both rectified cameras share ``cx``, as ``cv2.stereoRectify`` with
``CALIB_ZERO_DISPARITY`` gives them). Each point carries the grey level of its left pixel as
intensity (0-255). Pixels without a valid match (SGBM's uniqueness, left-right and speckle
checks), with a disparity below ``min_disparity_px`` or farther than ``max_range_m`` are
dropped; ``pixel_stride`` keeps every ``stride``-th pixel of every ``stride``-th row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError
from ga_ros.runtime import lazy_import
from ga_ros.vo.calibration import StereoCalibration

cv2 = lazy_import('cv2')  # imported on first use (start-up of the command line)

#: ``mode`` of :class:`DenseStereoConfig` -> the name of OpenCV's SGBM mode in ``cv2``.
SGBM_MODES = {'sgbm': 'STEREO_SGBM_MODE_SGBM', 'hh': 'STEREO_SGBM_MODE_HH',
              '3way': 'STEREO_SGBM_MODE_SGBM_3WAY'}


@dataclass(frozen=True)
class DenseStereoConfig:
    """Settings of :class:`DenseStereo` (``vo_node`` parameters ``cloud_<field>``).

    Attributes
    ----------
    num_disparities : disparity search range ``[0, num_disparities)`` (px, a positive multiple
        of 16); points nearer than ``fx * B / num_disparities`` are lost, and the
        ``num_disparities`` leftmost columns have no match.
    block_size : SGBM matched block size (px, odd, 1-11).
    uniqueness_ratio : SGBM: the best match must beat the second best by this (%).
    speckle_window_size : SGBM: connected disparity blobs smaller than this (px) are removed
        (0: no speckle filter).
    speckle_range : SGBM: largest disparity step inside one blob (px).
    disp12_max_diff : SGBM: largest left-right disparity disagreement (px; < 0: no check).
    mode : ``'sgbm'`` (5 directions), ``'hh'`` (8 directions, slower) or ``'3way'`` (faster).
    pixel_stride : keep every ``pixel_stride``-th pixel of every ``pixel_stride``-th row (1: all).
    min_disparity_px : smallest kept disparity (px): the far limit ``fx * B / min_disparity_px``.
    max_range_m : farthest kept point, by depth ``z`` (m; 0: no limit).
    """

    num_disparities: int = 64
    block_size: int = 5
    uniqueness_ratio: int = 10
    speckle_window_size: int = 100
    speckle_range: int = 2
    disp12_max_diff: int = 1
    mode: str = 'sgbm'
    pixel_stride: int = 2
    min_disparity_px: float = 1.0
    max_range_m: float = 0.0

    def __post_init__(self) -> None:
        if self.num_disparities <= 0 or self.num_disparities % 16:
            raise InputError(f'cloud_num_disparities must be a positive multiple of 16, got '
                             f'{self.num_disparities}')
        if not (1 <= self.block_size <= 11 and self.block_size % 2 == 1):
            raise InputError(f'cloud_block_size must be odd and in 1-11, got {self.block_size}')
        if self.mode not in SGBM_MODES:
            raise InputError(f'cloud_mode must be one of {", ".join(SGBM_MODES)}, got '
                             f'{self.mode!r}')
        if self.pixel_stride < 1:
            raise InputError(f'cloud_pixel_stride must be >= 1, got {self.pixel_stride}')
        if not self.min_disparity_px > 0 or self.max_range_m < 0:
            raise InputError('cloud_min_disparity_px must be > 0 and cloud_max_range_m >= 0 '
                             '(0: no limit)')
        if min(self.uniqueness_ratio, self.speckle_window_size, self.speckle_range) < 0:
            raise InputError('cloud_uniqueness_ratio, cloud_speckle_window_size and '
                             'cloud_speckle_range must be >= 0')


@dataclass(frozen=True)
class StereoCloud:
    """Points of one rectified pair in the left camera's optical frame.

    Attributes
    ----------
    points : (n, 3) float32 ``x y z`` (m), optical frame (``z`` forward, ``x`` right, ``y`` down).
    intensity : (n,) float32 grey level of each point's left pixel (0-255).
    """

    points: np.ndarray
    intensity: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])


class DenseStereo:
    """Rectified pair -> :class:`StereoCloud` by semi-global matching (module doc).

    Parameters
    ----------
    config : the settings (the matcher is built once from them).
    """

    def __init__(self, config: DenseStereoConfig | None = None) -> None:
        self.config = config or DenseStereoConfig()
        c = self.config
        area = c.block_size * c.block_size  # grey images: one channel
        self._sgbm = cv2.StereoSGBM_create(
            minDisparity=0, numDisparities=c.num_disparities, blockSize=c.block_size,
            P1=8 * area, P2=32 * area, disp12MaxDiff=c.disp12_max_diff, preFilterCap=63,
            uniquenessRatio=c.uniqueness_ratio, speckleWindowSize=c.speckle_window_size,
            speckleRange=c.speckle_range, mode=getattr(cv2, SGBM_MODES[c.mode]))

    def disparity(self, left: np.ndarray, right: np.ndarray) -> FloatArray:
        """(height, width) float32 disparity of the rectified left image (px); NaN where SGBM
        found no valid match.

        Raises
        ------
        InputError
            The images are not two uint8 grey images of the same size.
        """
        left, right = np.asarray(left), np.asarray(right)
        if (left.ndim != 2 or left.shape != right.shape or left.dtype != np.uint8
                or right.dtype != np.uint8):
            raise InputError(f'dense stereo needs two uint8 grey images of one size, got '
                             f'{left.dtype}{left.shape} and {right.dtype}{right.shape}')
        raw = self._sgbm.compute(left, right)  # int16, 16 * disparity; invalid: -16
        disp = raw.astype(np.float32) * np.float32(1.0 / 16.0)
        disp[raw < 0] = np.nan
        return disp

    def cloud(self, left: np.ndarray, right: np.ndarray,
              calibration: StereoCalibration) -> StereoCloud:
        """Points of a rectified pair (uint8 grey) with the rectified ``calibration``.

        Raises
        ------
        InputError
            Images that are not uint8 grey, or not of the calibration's size.
        """
        if np.shape(left) != (calibration.height, calibration.width):
            raise InputError(f'dense stereo: images of shape {np.shape(left)}, calibration of '
                             f'{calibration.width}x{calibration.height}')
        c = self.config
        s = c.pixel_stride
        disp = self.disparity(left, right)[::s, ::s]
        K = np.asarray(calibration.K, float)
        fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
        fb = fx * calibration.baseline_m
        d_min = c.min_disparity_px
        if c.max_range_m > 0:
            d_min = max(d_min, fb / c.max_range_m)
        with np.errstate(invalid='ignore'):
            valid = disp >= d_min  # NaN compares False
        rows, cols = np.nonzero(valid)
        d = disp[rows, cols].astype(float)
        z = fb / d
        v = rows * s
        u = cols * s
        points = np.empty((d.size, 3), np.float32)
        points[:, 0] = (u - cx) * z / fx
        points[:, 1] = (v - cy) * z / fy
        points[:, 2] = z
        intensity = np.asarray(left)[v, u].astype(np.float32)
        return StereoCloud(points, intensity)
