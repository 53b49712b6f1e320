"""The ground a downward camera's images are projected onto (ROS-free).

Two surfaces, both giving the ground height ``z`` (m, in ``map``) at map ``x, y`` (m):

* :class:`GroundPlane` -- ``z`` constant: each image maps to the mosaic by one homography;
* :class:`HeightGrid` -- a height model on a regular grid (bilinear), e.g. from the keyframes'
  dense stereo points (:func:`height_grid_from_points`): each image is orthorectified, so the
  relief's parallax does not misregister the images of neighbouring tracks.

Grid convention (the same as the mosaic's, :class:`ga_ros.mapping.mosaic.Georeference`): row 0
is the north (largest ``y``) edge; the centre of cell ``(row, col)`` is at
``x = x_min + (col + 0.5) * cell_m``, ``y = y_max - (row + 0.5) * cell_m``.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError


@dataclass(frozen=True)
class GroundPlane:
    """The horizontal plane ``z = z_m`` of ``map`` (m)."""

    z_m: float

    @property
    def z_range(self) -> tuple[float, float]:
        """Lowest and highest ground height (m)."""
        return float(self.z_m), float(self.z_m)

    def heights(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Ground height (m) at map ``x, y`` (m), any matching shapes."""
        return np.full(np.shape(x), self.z_m, np.float32)


@dataclass(frozen=True)
class HeightGrid:
    """A ground height model on a north-up grid (module docstring), bilinear in between.

    Attributes
    ----------
    z : (rows, cols) float32 heights (m, in ``map``), every cell filled.
    x_min, y_max : map coordinates of the grid's north-west corner (m).
    cell_m : cell size (m).
    """

    z: np.ndarray
    x_min: float
    y_max: float
    cell_m: float

    @property
    def z_range(self) -> tuple[float, float]:
        """Lowest and highest ground height (m)."""
        return float(self.z.min()), float(self.z.max())

    def heights(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Ground height (m) at map ``x, y`` (m), any matching 2-D shapes; clamped at the edge."""
        gx = ((np.asarray(x) - self.x_min) / self.cell_m - 0.5).astype(np.float32)
        gy = ((self.y_max - np.asarray(y)) / self.cell_m - 0.5).astype(np.float32)
        shape = gx.shape
        if gx.ndim != 2:
            gx, gy = gx.reshape(1, -1), gy.reshape(1, -1)
        out = np.empty(gx.shape, np.float32)
        step = 16384  # cv2.remap takes at most 32767 columns
        for c0 in range(0, gx.shape[1], step):
            out[:, c0:c0 + step] = cv2.remap(self.z, gx[:, c0:c0 + step], gy[:, c0:c0 + step],
                                             cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
        return out.reshape(shape)


def _fill_holes(z: np.ndarray, have: np.ndarray) -> np.ndarray:
    """Fill the cells without data by normalised convolution at growing scales (a smooth
    extrapolation from the nearest filled cells)."""
    z = np.where(have, z, 0).astype(np.float32)
    w = have.astype(np.float32)
    out = z.copy()
    missing = ~have
    sigma = 1.0
    while missing.any():
        num = cv2.GaussianBlur(z * w, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        den = cv2.GaussianBlur(w, (0, 0), sigma, borderType=cv2.BORDER_CONSTANT)
        ok = missing & (den > 1e-6)
        out[ok] = num[ok] / den[ok]
        missing &= ~ok
        sigma *= 2.0
        if sigma > 4 * max(z.shape):
            break
    return out


def height_grid_from_points(points_map: FloatArray, cell_m: float,
                            bounds: tuple[float, float, float, float] | None = None,
                            min_points: int = 3, smooth_cells: float = 1.0) -> HeightGrid:
    """A :class:`HeightGrid` from ground points in ``map``: the median ``z`` per cell, holes
    filled from the nearest cells, lightly smoothed.

    Parameters
    ----------
    points_map : (n, 3) points ``x y z`` in ``map`` (m).
    cell_m : cell size (m).
    bounds : ``(x_min, x_max, y_min, y_max)`` of the grid (m); default: the points' extent.
    min_points : cells with fewer points are holes.
    smooth_cells : Gaussian smoothing of the result (sigma in cells; 0: none).

    Raises
    ------
    InputError
        No finite point, or a cell size that is not positive.
    """
    p = np.asarray(points_map, float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if p.shape[0] == 0:
        raise InputError('height grid: no finite ground point (no dense stereo point was '
                         'computed; give a ground plane height instead)')
    if not cell_m > 0:
        raise InputError(f'height grid: cell size must be > 0 m, got {cell_m}')
    if bounds is None:
        bounds = (float(p[:, 0].min()), float(p[:, 0].max()),
                  float(p[:, 1].min()), float(p[:, 1].max()))
    x_min, x_max, y_min, y_max = bounds
    cols = max(int(np.ceil((x_max - x_min) / cell_m)), 1)
    rows = max(int(np.ceil((y_max - y_min) / cell_m)), 1)
    c = np.floor((p[:, 0] - x_min) / cell_m).astype(np.int64)
    r = np.floor((y_max - p[:, 1]) / cell_m).astype(np.int64)
    ok = (c >= 0) & (c < cols) & (r >= 0) & (r < rows)
    cell = r[ok] * cols + c[ok]
    z = p[ok, 2]
    order = np.lexsort((z, cell))
    cell, z = cell[order], z[order]
    first = np.flatnonzero(np.r_[True, cell[1:] != cell[:-1]])
    counts = np.diff(np.r_[first, cell.size])
    median = z[first + counts // 2]
    grid = np.zeros(rows * cols, np.float32)
    have = np.zeros(rows * cols, bool)
    keep = counts >= min_points
    grid[cell[first[keep]]] = median[keep]
    have[cell[first[keep]]] = True
    if not have.any():
        raise InputError(f'height grid: no cell of {cell_m} m holds {min_points} points')
    filled = _fill_holes(grid.reshape(rows, cols), have.reshape(rows, cols))
    if smooth_cells > 0:
        filled = cv2.GaussianBlur(filled, (0, 0), smooth_cells, borderType=cv2.BORDER_REPLICATE)
    return HeightGrid(filled.astype(np.float32), float(x_min), float(y_max), float(cell_m))


def ground_from_keyframe_points(points_cam: list[np.ndarray | None], T_map_cam: FloatArray,
                                cell_m: float = 2.0) -> HeightGrid:
    """The ground under keyframes from their points in their own camera frames (e.g. the dense
    stereo points of ``ga/keyframe_cloud``): each placed with its keyframe's pose, then
    :func:`height_grid_from_points`.

    Parameters
    ----------
    points_cam : per keyframe (k, 3) points ``x y z`` in its camera frame (m), or None.
    T_map_cam : (n, 4, 4) the keyframes' camera poses in ``map``, one per entry of
        ``points_cam``.
    cell_m : cell of the height grid (m).

    Raises
    ------
    InputError
        No keyframe has points, or the two lists differ in length.
    """
    T = np.asarray(T_map_cam, float).reshape(-1, 4, 4)
    if len(points_cam) != T.shape[0]:
        raise InputError(f'ground: {len(points_cam)} point sets for {T.shape[0]} poses')
    pts = [np.asarray(p, float).reshape(-1, 3) @ Ti[:3, :3].T + Ti[:3, 3]
           for p, Ti in zip(points_cam, T) if p is not None and len(p)]
    if not pts:
        raise InputError('ground: no keyframe has stereo points; give the ground height '
                         '(a GroundPlane) instead')
    return height_grid_from_points(np.concatenate(pts), cell_m)
