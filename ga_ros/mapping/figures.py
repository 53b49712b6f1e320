"""Figures of a point-cloud map (ROS-free): size, covered area, consistency of heights.

On a grid of ``cell_m`` x ``cell_m`` cells in the map's x-y plane:

* ``points``: the map's points;
* ``covered_area_m2``: cells holding at least one point, times ``cell_m**2`` (m^2);
* ``height_spread_m``: for each cell holding at least ``min_points`` points, the standard
  deviation of their heights ``z`` (m); the median over those cells (``median``), their mean
  (``mean``) and 90th percentile (``p90``), and how many cells (``cells``). A surface seen from
  two tracks whose poses disagree shows twice, at two heights: the spread grows with the
  misregistration (and with the relief inside a cell, the same for two maps of one scene), so
  two maps of the same clouds compare by it;
* ``track_height_spread_m`` (:func:`group_height_spread`): the consistency *between* tracks:
  for each cell seen by at least two tracks (each with at least ``min_points`` points in it),
  the standard deviation over those tracks of each track's mean height in the cell (m); the
  median, mean and 90th percentile over the cells, and how many. Averaging each track's points
  first removes most of the stereo noise: what is left is where the tracks' poses disagree (a
  step at a seam), plus the relief sampled differently by two footprints.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ga_ros.mapping.voxels import voxel_coords


@dataclass(frozen=True)
class Spread:
    """Statistics of per-cell spreads (m): median, mean, 90th percentile, over ``cells``."""

    median: float
    mean: float
    p90: float
    cells: int

    @staticmethod
    def of(values: np.ndarray) -> Spread:
        """The statistics of (k,) per-cell values (NaN when k is 0)."""
        v = np.asarray(values, float)
        if v.size == 0:
            nan = float('nan')
            return Spread(nan, nan, nan, 0)
        return Spread(float(np.median(v)), float(v.mean()), float(np.percentile(v, 90)),
                      int(v.size))

    def as_dict(self) -> dict[str, Any]:
        return {'median': self.median, 'mean': self.mean, 'p90': self.p90, 'cells': self.cells}


def group_height_spread(points: np.ndarray, groups: np.ndarray, cell_m: float = 2.0,
                        min_points: int = 3) -> Spread:
    """Per ``cell_m`` x-y cell, the standard deviation over the groups (e.g. tracks) seeing
    it of each group's mean height there (module docstring: ``track_height_spread_m``).

    Parameters
    ----------
    points : (n, 3) points in the map (m).
    groups : (n,) integer group of each point (its keyframe's track).
    min_points : a group counts in a cell with at least this many points there.
    """
    P = np.asarray(points, float).reshape(-1, 3)
    g = np.asarray(groups, np.int64).reshape(-1)
    ij, ok = voxel_coords(np.c_[P[:, :2], np.zeros(len(P))], cell_m)
    if not ok.any():
        return Spread.of(np.zeros(0))
    keys = np.c_[ij[ok, :2], g[ok]]
    z = P[ok, 2]
    cg, inv, cnt = np.unique(keys, axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    mean_z = np.bincount(inv, weights=z) / cnt
    keep = cnt >= min_points
    cg, mean_z = cg[keep], mean_z[keep]
    if len(cg) == 0:
        return Spread.of(np.zeros(0))
    cells, ci, cc = np.unique(cg[:, :2], axis=0, return_inverse=True, return_counts=True)
    ci = ci.reshape(-1)
    m = np.bincount(ci, weights=mean_z) / cc
    var = np.bincount(ci, weights=(mean_z - m[ci]) ** 2) / cc
    return Spread.of(np.sqrt(var[cc >= 2]))


@dataclass(frozen=True)
class MapFigures:
    """:func:`map_figures` of one map (module docstring; lengths in m, areas in m^2)."""

    points: int
    cell_m: float
    covered_area_m2: float
    spread_cells: int
    height_spread_median_m: float
    height_spread_mean_m: float
    height_spread_p90_m: float

    def as_dict(self) -> dict[str, Any]:
        """The figures as ``summary.json`` holds them."""
        return {'points': self.points, 'cell_m': self.cell_m,
                'covered_area_m2': self.covered_area_m2,
                'height_spread_m': {'median': self.height_spread_median_m,
                                    'mean': self.height_spread_mean_m,
                                    'p90': self.height_spread_p90_m,
                                    'cells': self.spread_cells}}


def map_figures(points: np.ndarray, cell_m: float = 2.0, min_points: int = 3) -> MapFigures:
    """Figures of (n, 3) map points (m) on a ``cell_m`` grid (module docstring); NaN spreads
    when no cell holds ``min_points``."""
    P = np.asarray(points, float).reshape(-1, 3)
    ij, ok = voxel_coords(np.c_[P[:, :2], np.zeros(len(P))], cell_m)
    P, ij = P[ok], ij[ok, :2]
    if len(P) == 0:
        nan = float('nan')
        return MapFigures(0, float(cell_m), 0.0, 0, nan, nan, nan)
    cells, inverse, counts = np.unique(ij, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    z = P[:, 2]
    mean = np.bincount(inverse, weights=z) / counts
    var = np.bincount(inverse, weights=(z - mean[inverse]) ** 2) / counts
    std = np.sqrt(var[counts >= min_points])
    s = Spread.of(std)
    return MapFigures(int(len(P)), float(cell_m), float(len(cells) * cell_m ** 2), s.cells,
                      s.median, s.mean, s.p90)
