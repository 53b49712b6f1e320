"""The height model of :mod:`ga_ros.mapping.surface` kept up to date as keyframes arrive and
move (ROS-free): :class:`LiveHeightGrid`.

Each keyframe's points are kept in its own frame (:func:`ga_ros.mapping.surface.keyframe_points`)
with its pose ``T_map_kf``; placed, they fall into the anchored cells of ``map``. A change (points
added, a pose moved) marks the cells its old and new points fall in; :meth:`LiveHeightGrid.
commit` recomputes those cells' medians from every keyframe's points in them, then runs
:func:`ga_ros.mapping.surface.ground_heights` on a window reaching ``2 * radius_cells`` around
them and keeps the heights within ``radius_cells`` (every input of those is in the window, and
the operator gives each cell the same sum wherever the window lies): the heights equal those of
:func:`ga_ros.mapping.surface.height_grid_from_points` of all the points, and the cells whose
height changed are returned. The cost is in proportion to the cells the change touches, not
to the grid's size. The grid is one dense array that grows to the cells reached.

Memory: a live keyframe keeps its points (at most ``max_points_per_keyframe``; 12 bytes each for
a ``float32`` cloud, as ``PointCloud2`` gives them) and their placement (16 bytes each): about
110 kB per keyframe at the default 4,000 points. :meth:`LiveHeightGrid.merge` drops a keyframe's
points into the **static layer**: per cell at most ``2 * STATIC_BINS + 1`` weighted heights
(12 bytes each; 124 bytes a cell with the medians and heights, whatever the keyframes merged).
At a merge, each cell's merged points (and the weighted heights merged there before) are split
by the cell's upper median at that moment (over all its points, live and merged): those below
it into ``STATIC_BINS`` bins of equal weight, each kept as its upper median with the bin's
weight, those equal to it as one, those above it as below. No point crosses the median, so a
merge changes no median and no height. Afterwards a cell's median is the weighted upper median
of its live points and its weighted heights: equal to the median of all the points as long as
the live points of the cell do not change (merged keyframes no longer move), an approximation
once they do (to within the bin of the merged points where the median then falls).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import InputError
from ga_ros.mapping.surface import (
    HeightGrid,
    SurfaceConfig,
    cell_index,
    cell_medians,
    ground_heights,
    keyframe_points,
    place_points,
)

#: Cells added beyond what is needed when the grid grows (fewer re-allocations).
GROW_CELLS = 32
#: Bins of equal weight the merged points of a cell below (and above) its median are kept as.
STATIC_BINS = 4
_SLOTS = 2 * STATIC_BINS + 1


@dataclass
class _Points:
    points: np.ndarray          # (k, 3) in the points' frame
    T_kf_points: FloatArray     # the points' frame in the keyframe's frame
    T_map_kf: FloatArray | None = None
    i: np.ndarray | None = None  # placed: global cells and heights of the points
    j: np.ndarray | None = None
    z: np.ndarray | None = None


class LiveHeightGrid:
    """Keyframe points + poses -> the ground heights, updated where they change (module
    docstring)."""

    def __init__(self, config: SurfaceConfig = SurfaceConfig()) -> None:
        self.config = config
        self.keyframes: dict[int, _Points] = {}
        #: poses of keyframes without points yet
        self.pending_poses: dict[int, FloatArray] = {}
        self.i0 = self.j0 = 0
        self.medians = np.zeros((0, 0))
        self.heights = np.zeros((0, 0))
        #: static layer: per cell, the weighted heights standing for the merged points (weight 0:
        #: an empty slot)
        self.static_z = np.zeros((0, 0, _SLOTS))
        self.static_w = np.zeros((0, 0, _SLOTS), np.int32)
        #: keyframes merged into the static layer
        self.merged = 0
        self._dirty: list[tuple[np.ndarray, np.ndarray]] = []
        self._range = (float('nan'), float('nan'))
        #: cells recomputed (the work)
        self.cells_computed = 0

    # ------------------------------------------------------------------ inputs
    def add_points(self, key: int, points: np.ndarray,
                   T_kf_points: FloatArray | None = None) -> None:
        """A keyframe's points (k, 3, m) in the frame whose pose in the keyframe's frame is
        ``T_kf_points`` (default: the identity; e.g. ``T_base_cam`` for a camera's cloud):
        placed at ``T_map_kf @ T_kf_points``; replaces earlier ones."""
        old = self.keyframes.get(key)
        self._unplace(old)
        T = old.T_map_kf if old is not None else self.pending_poses.pop(key, None)
        ext = np.eye(4) if T_kf_points is None else np.asarray(T_kf_points, float)
        pts = keyframe_points(points, self.config)
        small = pts.astype(np.float32)
        if np.array_equal(small, pts):  # a float32 cloud (a PointCloud2's) is kept as it came
            pts = small
        kf = self.keyframes[key] = _Points(pts, ext)
        self._place(kf, T)

    def set_pose(self, key: int, T_map_kf: FloatArray) -> bool:
        """A keyframe's pose (4, 4); True when it has points and the pose changed."""
        T = np.asarray(T_map_kf, float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise InputError('height grid: a keyframe pose must be a finite 4x4 transform')
        kf = self.keyframes.get(key)
        if kf is None:
            self.pending_poses[key] = T.copy()
            while len(self.pending_poses) > 100_000:
                self.pending_poses.pop(next(iter(self.pending_poses)))
            return False
        if kf.T_map_kf is not None and np.array_equal(kf.T_map_kf, T):
            return False
        self._unplace(kf)
        self._place(kf, T.copy())
        return True

    def unplace_all(self) -> None:
        """Forget every pose (a full corrections message follows with the new ones)."""
        for kf in self.keyframes.values():
            self._unplace(kf)
            kf.T_map_kf = None
        self.pending_poses.clear()

    def _unplace(self, kf: _Points | None) -> None:
        if kf is not None and kf.i is not None:
            self._dirty.append((kf.i, kf.j))
            kf.i = kf.j = kf.z = None

    def _place(self, kf: _Points, T: FloatArray | None) -> None:
        kf.T_map_kf = T
        if T is None or not len(kf.points):
            return
        p = place_points(kf.points.astype(float), T @ kf.T_kf_points)
        i, j = cell_index(p[:, 0], p[:, 1], self.config.cell_m)
        kf.i, kf.j = i.astype(np.int32), j.astype(np.int32)
        kf.z = p[:, 2]
        self._dirty.append((kf.i, kf.j))

    # ------------------------------------------------------------------ work
    def _grow(self, i_lo: int, i_hi: int, j_lo: int, j_hi: int) -> None:
        """Make the arrays cover global cells ``[i_lo, i_hi] x [j_lo, j_hi]``."""
        rows, cols = self.medians.shape
        if rows and self.i0 <= i_lo and i_hi < self.i0 + rows and self.j0 <= j_lo \
                and j_hi < self.j0 + cols:
            return
        if rows:
            i_lo, j_lo = min(i_lo, self.i0), min(j_lo, self.j0)
            i_hi, j_hi = max(i_hi, self.i0 + rows - 1), max(j_hi, self.j0 + cols - 1)
        i_lo, j_lo, i_hi, j_hi = i_lo - GROW_CELLS, j_lo - GROW_CELLS, i_hi + GROW_CELLS, \
            j_hi + GROW_CELLS
        med = np.full((i_hi - i_lo + 1, j_hi - j_lo + 1), np.nan)
        hts = med.copy()
        sz = np.zeros(med.shape + (_SLOTS,))
        sn = np.zeros(med.shape + (_SLOTS,), np.int32)
        if rows:
            win = (slice(self.i0 - i_lo, self.i0 - i_lo + rows),
                   slice(self.j0 - j_lo, self.j0 - j_lo + cols))
            med[win], hts[win] = self.medians, self.heights
            sz[win], sn[win] = self.static_z, self.static_w
        self.i0, self.j0, self.medians, self.heights = i_lo, j_lo, med, hts
        self.static_z, self.static_w = sz, sn

    def commit(self) -> tuple[IntArray, IntArray]:
        """Recompute what the changes since the last commit touched; returns the global cells
        ``(i, j)`` whose height changed (NaN to a value, a value to NaN, or another value)."""
        if not self._dirty:
            return np.zeros(0, np.int64), np.zeros(0, np.int64)
        di = np.concatenate([d[0] for d in self._dirty])
        dj = np.concatenate([d[1] for d in self._dirty])
        self._dirty = []
        R = self.config.radius_cells()
        lo_i, hi_i, lo_j, hi_j = int(di.min()), int(di.max()), int(dj.min()), int(dj.max())
        self._grow(lo_i - 2 * R, hi_i + 2 * R, lo_j - 2 * R, hi_j + 2 * R)
        # the dirty cells' medians, from every keyframe's points in them
        mask = np.zeros(self.medians.shape, bool)
        mask[di - self.i0, dj - self.j0] = True
        self.medians[mask] = np.nan
        i, j, med = self._medians(mask, lo_i, hi_i, lo_j, hi_j, self.config.min_points)
        self.medians[i - self.i0, j - self.j0] = med
        # heights within R of the dirty cells, from a window within 2 R
        w = (slice(lo_i - 2 * R - self.i0, hi_i + 2 * R + 1 - self.i0),
             slice(lo_j - 2 * R - self.j0, hi_j + 2 * R + 1 - self.j0))
        new = ground_heights(self.medians[w], self.config)[R:-R or None, R:-R or None]
        out = (slice(lo_i - R - self.i0, hi_i + R + 1 - self.i0),
               slice(lo_j - R - self.j0, hi_j + R + 1 - self.j0))
        old = self.heights[out]
        changed = ~((new == old) | (np.isnan(new) & np.isnan(old)))
        self.heights[out] = new
        self.cells_computed += new.size
        if changed.any():
            known = np.isfinite(self.heights)
            self._range = ((float(self.heights[known].min()), float(self.heights[known].max()))
                           if known.any() else (float('nan'), float('nan')))
        ci, cj = np.nonzero(changed)
        return ci + lo_i - R, cj + lo_j - R

    def _medians(self, mask: np.ndarray, lo_i: int, hi_i: int, lo_j: int, hi_j: int,
                 min_points: int, extra: tuple[_Points, ...] = ()
                 ) -> tuple[IntArray, IntArray, FloatArray]:
        """Upper medians of the cells of ``mask`` (a grid-sized bool array, true cells within
        global ``[lo_i, hi_i] x [lo_j, hi_j]``) over the live keyframes' points, those of
        ``extra`` and the static layer: ``(i, j, median)`` of the cells with ``min_points`` or
        more."""
        parts_i, parts_j, parts_z = [], [], []
        for kf in (*self.keyframes.values(), *extra):
            if kf.i is None or kf.i.size == 0 or kf.i.max() < lo_i or kf.i.min() > hi_i \
                    or kf.j.max() < lo_j or kf.j.min() > hi_j:
                continue
            sel = mask[kf.i - self.i0, kf.j - self.j0]
            if sel.any():
                parts_i.append(kf.i[sel])
                parts_j.append(kf.j[sel])
                parts_z.append(kf.z[sel])
        win = (slice(lo_i - self.i0, hi_i + 1 - self.i0),
               slice(lo_j - self.j0, hi_j + 1 - self.j0))
        si, sj, ss = np.nonzero(mask[win][..., None] & (self.static_w[win] > 0))
        if si.size == 0:
            if not parts_z:
                return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
            return cell_medians(np.concatenate(parts_i), np.concatenate(parts_j),
                                np.concatenate(parts_z), min_points)
        si, sj = si + lo_i - self.i0, sj + lo_j - self.j0
        n_live = sum(len(z) for z in parts_z)
        w = np.r_[np.ones(n_live, np.int64), self.static_w[si, sj, ss]]
        return weighted_cell_medians(np.concatenate(parts_i + [si + self.i0]),
                                     np.concatenate(parts_j + [sj + self.j0]),
                                     np.concatenate(parts_z + [self.static_z[si, sj, ss]]), w,
                                     min_points)

    def merge(self, keys: list[int]) -> int:
        """Drop these keyframes' points into the static layer (module docstring): no median or
        height changes; later poses of these keys are the caller's to ignore. Returns the
        keyframes merged (keys without points are skipped)."""
        gone = [self.keyframes.pop(k) for k in keys if k in self.keyframes]
        self.merged += len(gone)
        placed = [kf for kf in gone if kf.i is not None and kf.i.size]
        if not placed:
            return len(gone)
        mi = np.concatenate([kf.i for kf in placed])
        mj = np.concatenate([kf.j for kf in placed])
        lo_i, hi_i, lo_j, hi_j = int(mi.min()), int(mi.max()), int(mj.min()), int(mj.max())
        self._grow(lo_i, hi_i, lo_j, hi_j)
        mask = np.zeros(self.medians.shape, bool)
        mask[mi - self.i0, mj - self.j0] = True
        # the upper median of every point of the cell, the merged ones included
        i, j, med = self._medians(mask, lo_i, hi_i, lo_j, hi_j, 1, tuple(placed))
        at = np.full(self.medians.shape, np.nan)
        at[i - self.i0, j - self.j0] = med
        # what the merged cells keep: the merged points and the weighted heights already there
        si, sj, ss = np.nonzero(mask[..., None] & (self.static_w > 0))
        fi = np.r_[mi - self.i0, si]
        fj = np.r_[mj - self.j0, sj]
        fz = np.concatenate([kf.z for kf in placed] + [self.static_z[si, sj, ss]])
        fw = np.r_[np.ones(mi.size, np.int64), self.static_w[si, sj, ss]]
        m = at[fi, fj]
        side = np.where(fz < m, 0, np.where(fz == m, 1, 2))
        order = np.lexsort((fz, side, fj, fi))
        fi, fj, fz, fw, side = fi[order], fj[order], fz[order], fw[order], side[order]
        first = np.flatnonzero(np.r_[True, (fi[1:] != fi[:-1]) | (fj[1:] != fj[:-1])
                                     | (side[1:] != side[:-1])])
        group = np.repeat(np.arange(first.size), np.diff(np.r_[first, fz.size]))
        cw = np.cumsum(fw)
        start = (cw - fw)[first]
        total = np.r_[start[1:], cw[-1]] - start
        b = (STATIC_BINS * (cw - fw - start[group])) // total[group]
        slot = np.where(side == 0, b, np.where(side == 1, STATIC_BINS, STATIC_BINS + 1 + b))
        cell = fi * self.medians.shape[1] + fj
        ci, cs, cz = weighted_cell_medians(cell, slot, fz, fw, 1)
        _, inverse = np.unique(cell * _SLOTS + slot, return_inverse=True)
        weight = np.bincount(inverse, weights=fw).astype(np.int64)
        self.static_w[mask] = 0
        rows, cols = np.divmod(ci, self.medians.shape[1])
        self.static_z[rows, cols, cs] = cz
        self.static_w[rows, cols, cs] = weight
        return len(gone)

    def clear_static(self) -> None:
        """Forget the static layer (a reset); its cells are recomputed at the next commit."""
        i, j = np.nonzero(self.static_w.any(axis=2))
        if i.size:
            self._dirty.append(((i + self.i0).astype(np.int32), (j + self.j0).astype(np.int32)))
        self.static_z[:] = 0.0
        self.static_w[:] = 0

    # ------------------------------------------------------------------ outputs
    @property
    def z_range(self) -> tuple[float, float]:
        """Lowest and highest known height (m) at the last commit; NaN, NaN when none."""
        return self._range

    def window(self, i_lo: int, i_hi: int, j_lo: int, j_hi: int) -> HeightGrid:
        """The heights of global cells ``[i_lo, i_hi] x [j_lo, j_hi]`` as a
        :class:`HeightGrid` (NaN outside what is known)."""
        z = np.full((i_hi - i_lo + 1, j_hi - j_lo + 1), np.nan)
        rows, cols = self.heights.shape
        a0, a1 = max(i_lo, self.i0), min(i_hi, self.i0 + rows - 1)
        b0, b1 = max(j_lo, self.j0), min(j_hi, self.j0 + cols - 1)
        if a1 >= a0 and b1 >= b0:
            z[a0 - i_lo:a1 - i_lo + 1, b0 - j_lo:b1 - j_lo + 1] = \
                self.heights[a0 - self.i0:a1 - self.i0 + 1, b0 - self.j0:b1 - self.j0 + 1]
        c = self.config.cell_m
        return HeightGrid(z, j_lo * c, -i_lo * c, c)

    def nbytes(self) -> int:
        """Bytes held by the points and the arrays."""
        return self.points_nbytes() + self.grid_nbytes()

    def points_nbytes(self) -> int:
        """Bytes held by the live keyframes' points and their placement."""
        return sum(kf.points.nbytes + (0 if kf.i is None else
                                       kf.i.nbytes + kf.j.nbytes + kf.z.nbytes)
                   for kf in self.keyframes.values())

    def grid_nbytes(self) -> int:
        """Bytes held by the per-cell arrays (medians, heights, static layer)."""
        return self.medians.nbytes + self.heights.nbytes + self.static_z.nbytes \
            + self.static_w.nbytes


def weighted_cell_medians(i: IntArray, j: IntArray, z: FloatArray, w: IntArray,
                          min_points: int) -> tuple[IntArray, IntArray, FloatArray]:
    """:func:`ga_ros.mapping.surface.cell_medians` of points with integer weights ``w`` (>= 1):
    the upper median of each cell as if each point were there ``w`` times, for the cells whose
    weights add up to ``min_points`` or more: ``(i, j, median)``."""
    if z.size == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0)
    order = np.lexsort((z, j, i))
    i, j, z, w = i[order], j[order], z[order], np.asarray(w, np.int64)[order]
    first = np.flatnonzero(np.r_[True, (i[1:] != i[:-1]) | (j[1:] != j[:-1])])
    cw = np.cumsum(w)
    before = np.r_[0, cw[first[1:] - 1]]
    totals = np.diff(np.r_[before, cw[-1]])
    group = np.repeat(np.arange(first.size), np.diff(np.r_[first, z.size]))
    hit = np.flatnonzero(cw - before[group] > (totals // 2)[group])
    at = hit[np.searchsorted(hit, first)]
    keep = totals >= min_points
    return i[first[keep]], j[first[keep]], z[at[keep]]
