"""Figures of a point-cloud map (ROS-free): size, covered area, consistency of heights.

On a grid of ``cell_m`` x ``cell_m`` cells in the map's x-y plane:

* ``points``: the map's points;
* ``covered_area_m2``: cells holding at least one point, times ``cell_m**2`` (m^2);
* ``height_spread_m``: for each cell holding at least ``min_points`` points, the standard
  deviation of their heights ``z`` (m); the median over those cells (``median``), their mean
  (``mean``) and 90th percentile (``p90``), and how many cells (``cells``). A surface seen from
  two tracks whose poses disagree shows twice, at two heights: the spread grows with the
  misregistration (and with the relief inside a cell, the same for two maps of one scene), so
  two maps of the same clouds compare by it.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ga_ros.mapping.voxels import voxel_coords


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


def map_figures(points: np.ndarray, cell_m: float = 0.5, min_points: int = 3) -> MapFigures:
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
    nan = float('nan')
    return MapFigures(int(len(P)), float(cell_m), float(len(cells) * cell_m ** 2),
                      int(std.size),
                      float(np.median(std)) if std.size else nan,
                      float(std.mean()) if std.size else nan,
                      float(np.percentile(std, 90)) if std.size else nan)
