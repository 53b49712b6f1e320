"""The ground a downward camera's images are projected onto (ROS-free).

Two surfaces, both giving the ground height ``z`` (m, in ``map``) at map ``x, y`` (m):

* :class:`GroundPlane` -- ``z`` constant: each image maps to the mosaic by one homography;
* :class:`HeightGrid` -- a height model on a regular grid (bilinear), e.g. from the keyframes'
  dense stereo points (:func:`height_grid_from_points`): each image is orthorectified, so the
  relief's parallax does not misregister the images of neighbouring tracks.

Grid convention: cells are anchored on ``map``'s origin, so every height grid of one cell size
shares its cells: global cell ``(i, j)`` (:func:`cell_index`) holds ``x`` in
``[j * cell_m, (j + 1) * cell_m)`` and ``-y`` in ``[i * cell_m, (i + 1) * cell_m)``. A
:class:`HeightGrid` stores a window of them with row 0 the largest ``y``: the centre of its cell
``(row, col)`` is at ``x = x_min + (col + 0.5) * cell_m``, ``y = y_max - (row + 0.5) * cell_m``.

The height model (:func:`height_grid_from_points`, and the live one that follows the
corrections, :class:`ga_ros.mapping.live_surface.LiveHeightGrid`) is one local operator
(:func:`ground_heights`) on the per-cell medians of the points: holes filled by normalised
convolution at the scales :attr:`SurfaceConfig.fill_sigmas_cells`, then a normalised Gaussian
smoothing. Each height depends only on the medians within :meth:`SurfaceConfig.radius_cells`
cells; farther from any point the ground is unknown (NaN): a mosaic leaves those pixels
uncovered.
"""

from __future__ import annotations

from dataclasses import dataclass, field

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
class SurfaceConfig:
    """Settings of the height model (module docstring).

    Attributes
    ----------
    cell_m : cell size (m).
    min_points : cells with fewer points are holes.
    fill_sigmas_cells : scales of the hole filling (Gaussian sigma, cells), tried in order; each
        kernel is cut at 3 sigma.
    smooth_cells : sigma of the final smoothing (cells; 0: none).
    max_points_per_keyframe : a keyframe's points are evenly strided down to this many before
        use (0: all), the same offline and live.
    """

    cell_m: float = 2.0
    min_points: int = 3
    fill_sigmas_cells: tuple[float, ...] = field(default=(1.0, 2.0, 4.0, 8.0))
    smooth_cells: float = 1.0
    max_points_per_keyframe: int = 4000

    def __post_init__(self) -> None:
        if not self.cell_m > 0 or self.min_points < 1 or self.smooth_cells < 0 \
                or any(not s > 0 for s in self.fill_sigmas_cells) \
                or self.max_points_per_keyframe < 0:
            raise InputError('height grid: cell_m and fill sigmas must be > 0, min_points >= 1, '
                             'smooth_cells and max_points_per_keyframe >= 0')

    def radius_cells(self) -> int:
        """Cells (Chebyshev distance) beyond which a median no longer affects a height."""
        fill = max((_kernel_radius(s) for s in self.fill_sigmas_cells), default=0)
        return fill + (_kernel_radius(self.smooth_cells) if self.smooth_cells > 0 else 0)


@dataclass(frozen=True)
class HeightGrid:
    """A ground height model on a north-up window of the anchored cells (module docstring),
    bilinear in between; NaN where the ground is unknown.

    Attributes
    ----------
    z : (rows, cols) float64 heights (m, in ``map``); NaN: unknown.
    x_min, y_max : map coordinates of the window's north-west corner (m), multiples of
        ``cell_m``.
    cell_m : cell size (m).
    """

    z: np.ndarray
    x_min: float
    y_max: float
    cell_m: float

    @property
    def z_range(self) -> tuple[float, float]:
        """Lowest and highest known ground height (m); NaN, NaN when none is known."""
        if not np.isfinite(self.z).any():
            return float('nan'), float('nan')
        return float(np.nanmin(self.z)), float(np.nanmax(self.z))

    def heights(self, x: FloatArray, y: FloatArray) -> FloatArray:
        """Ground height (m, float32) at map ``x, y`` (m), any matching shapes: bilinear between
        the cell centres, NaN where a neighbouring cell is unknown or outside the window."""
        gx = (np.asarray(x, float) - self.x_min) / self.cell_m - 0.5
        gy = (self.y_max - np.asarray(y, float)) / self.cell_m - 0.5
        c0 = np.floor(gx)
        r0 = np.floor(gy)
        fx, fy = gx - c0, gy - r0
        rows, cols = self.z.shape
        pad = np.full((rows + 2, cols + 2), np.nan)
        pad[1:-1, 1:-1] = self.z
        c = np.clip(c0, -1, cols).astype(np.int64) + 1
        r = np.clip(r0, -1, rows).astype(np.int64) + 1
        c1, r1 = np.minimum(c + 1, cols + 1), np.minimum(r + 1, rows + 1)
        out = ((pad[r, c] * (1 - fx) + pad[r, c1] * fx) * (1 - fy)
               + (pad[r1, c] * (1 - fx) + pad[r1, c1] * fx) * fy)
        return out.astype(np.float32)


def cell_index(x: FloatArray, y: FloatArray, cell_m: float) -> tuple[np.ndarray, np.ndarray]:
    """Global cell ``(i, j)`` (int64 arrays) of map ``x, y`` (m): ``i = floor(-y / cell_m)``,
    ``j = floor(x / cell_m)`` (module docstring)."""
    return (np.floor(-np.asarray(y, float) / cell_m).astype(np.int64),
            np.floor(np.asarray(x, float) / cell_m).astype(np.int64))


def keyframe_points(points: np.ndarray | None, config: SurfaceConfig) -> np.ndarray:
    """A keyframe's points as the height model takes them: (k, 3) float64, finite only, evenly
    strided down to ``config.max_points_per_keyframe``."""
    if points is None:
        return np.zeros((0, 3))
    p = np.asarray(points, float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    n = config.max_points_per_keyframe
    if n and p.shape[0] > n:
        p = p[np.linspace(0, p.shape[0] - 1, n).round().astype(np.int64)]
    return p


def place_points(points: np.ndarray, T_map_kf: FloatArray) -> np.ndarray:
    """Points (k, 3) of a keyframe's frame in ``map`` (m)."""
    T = np.asarray(T_map_kf, float)
    return points @ T[:3, :3].T + T[:3, 3]


def cell_medians(i: np.ndarray, j: np.ndarray, z: np.ndarray, min_points: int
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The median ``z`` (upper median) of the points of each cell holding ``min_points`` or
    more: ``(i, j, median)`` arrays, one entry per such cell."""
    if z.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    order = np.lexsort((z, j, i))
    i, j, z = i[order], j[order], z[order]
    first = np.flatnonzero(np.r_[True, (i[1:] != i[:-1]) | (j[1:] != j[:-1])])
    counts = np.diff(np.r_[first, z.size])
    keep = counts >= min_points
    at = first[keep]
    return i[at], j[at], z[at + counts[keep] // 2]


def _kernel_radius(sigma: float) -> int:
    return int(np.ceil(3.0 * sigma))


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    """Separable Gaussian (cut at 3 sigma, normalised taps), zero outside; each output is the
    same sum in the same order wherever it lies (so a window equals the whole grid)."""
    r = _kernel_radius(sigma)
    k = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    k /= k.sum()
    for axis in (0, 1):
        pad = [(0, 0), (0, 0)]
        pad[axis] = (r, r)
        p = np.pad(a, pad)
        n = a.shape[axis]
        out = np.zeros_like(a)
        for t in range(2 * r + 1):
            out += k[t] * (p[t:t + n] if axis == 0 else p[:, t:t + n])
        a = out
    return a


def ground_heights(medians: np.ndarray, config: SurfaceConfig) -> np.ndarray:
    """The height model's local operator on a window of per-cell medians ((rows, cols), NaN
    where a cell has fewer than ``min_points`` points; zero data assumed outside): holes filled
    by normalised convolution at growing scales, then a normalised smoothing. Returns
    (rows, cols) float64 heights, NaN where unknown; each depends only on the medians within
    ``config.radius_cells()``."""
    have = np.isfinite(medians)
    w = have.astype(float)
    z = np.where(have, medians, 0.0)
    out = np.where(have, medians, np.nan)
    missing = ~have
    for s in config.fill_sigmas_cells:
        if not missing.any():
            break
        num, den = _blur(z, s), _blur(w, s)
        ok = missing & (den > 1e-6)
        out[ok] = num[ok] / den[ok]
        missing &= ~ok
    if config.smooth_cells > 0:
        known = np.isfinite(out)
        num = _blur(np.where(known, out, 0.0), config.smooth_cells)
        den = _blur(known.astype(float), config.smooth_cells)
        with np.errstate(invalid='ignore', divide='ignore'):
            out = np.where(known, num / den, np.nan)
    return out


def height_grid_from_points(points_map: FloatArray, config: SurfaceConfig = SurfaceConfig()
                            ) -> HeightGrid:
    """A :class:`HeightGrid` from ground points in ``map`` (m): per-cell medians, then
    :func:`ground_heights` over every cell it can reach.

    Raises
    ------
    InputError
        No finite point, or no cell with ``config.min_points`` points.
    """
    p = np.asarray(points_map, float).reshape(-1, 3)
    p = p[np.all(np.isfinite(p), axis=1)]
    if p.shape[0] == 0:
        raise InputError('height grid: no finite ground point (no dense stereo point was '
                         'computed; give a ground plane height instead)')
    i, j, med = cell_medians(*cell_index(p[:, 0], p[:, 1], config.cell_m), p[:, 2],
                             config.min_points)
    if med.size == 0:
        raise InputError(f'height grid: no cell of {config.cell_m} m holds '
                         f'{config.min_points} points')
    r = config.radius_cells()
    i0, j0 = int(i.min()) - r, int(j.min()) - r
    grid = np.full((int(i.max()) + r + 1 - i0, int(j.max()) + r + 1 - j0), np.nan)
    grid[i - i0, j - j0] = med
    c = config.cell_m
    return HeightGrid(ground_heights(grid, config), j0 * c, -i0 * c, c)


def ground_from_keyframe_points(points_cam: list[np.ndarray | None], T_map_cam: FloatArray,
                                config: SurfaceConfig = SurfaceConfig()) -> HeightGrid:
    """The ground under keyframes from their points in their own camera frames (e.g. the dense
    stereo points of ``ga/keyframe_cloud``): each taken by :func:`keyframe_points`, placed with
    its keyframe's pose, then :func:`height_grid_from_points`.

    Parameters
    ----------
    points_cam : per keyframe (k, 3) points ``x y z`` in its camera frame (m), or None.
    T_map_cam : (n, 4, 4) the keyframes' camera poses in ``map``, one per entry of
        ``points_cam``.
    config : the height model's settings.

    Raises
    ------
    InputError
        No keyframe has points, or the two lists differ in length.
    """
    T = np.asarray(T_map_cam, float).reshape(-1, 4, 4)
    if len(points_cam) != T.shape[0]:
        raise InputError(f'ground: {len(points_cam)} point sets for {T.shape[0]} poses')
    pts = [place_points(keyframe_points(p, config), Ti) for p, Ti in zip(points_cam, T)]
    pts = [p for p in pts if len(p)]
    if not pts:
        raise InputError('ground: no keyframe has stereo points; give the ground height '
                         '(a GroundPlane) instead')
    return height_grid_from_points(np.concatenate(pts), config)
