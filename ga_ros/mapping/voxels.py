"""Voxel grids of point clouds (ROS-free): keys, per-voxel sums, and an accumulator that adds
and removes one contribution at a time.

A point ``p`` (m) falls in the voxel ``floor(p / voxel_m)`` (integer coordinates per axis),
packed into one int64 key (:func:`voxel_keys`, 21 bits per axis: ``|floor(p / voxel_m)| <
2**20``, +-52 km at 5 cm; points beyond are dropped). A voxel's point is the centroid of the
points in it, its intensity their mean. :class:`VoxelAccumulator` keeps, per voxel, the count
and the sums of ``x y z intensity`` (float64), so a contribution (:class:`Contribution`: the
per-voxel sums of one keyframe's points) is added or subtracted in time proportional to its
own voxels, whatever the size of the map.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import InputError

#: Bits per axis of a packed voxel key.
AXIS_BITS = 21
#: Offset of each axis' integer coordinate in its key field: coordinates in ``[-OFFSET, OFFSET)``.
OFFSET = 1 << (AXIS_BITS - 1)
_MASK = (1 << AXIS_BITS) - 1


@dataclass(frozen=True)
class Contribution:
    """Per-voxel sums of a set of points.

    Attributes
    ----------
    keys : (v,) int64 distinct voxel keys (:func:`voxel_keys`), ascending.
    counts : (v,) int64 points per voxel.
    sums : (v, 4) float64 sums of ``x y z intensity`` per voxel (m, m, m, intensity units).
    """

    keys: IntArray
    counts: IntArray
    sums: FloatArray

    @property
    def n_points(self) -> int:
        """Points summed."""
        return int(self.counts.sum())


def voxel_coords(points: np.ndarray, voxel_m: float) -> tuple[IntArray, np.ndarray]:
    """``(ijk, ok)``: (n, 3) int64 voxel coordinates ``floor(p / voxel_m)`` of (n, 3) points
    (m) and the (n,) mask of those inside the key range (finite, ``|ijk| < OFFSET``)."""
    with np.errstate(invalid='ignore', over='ignore'):
        q = np.floor(np.asarray(points, float) / float(voxel_m))
        ok = np.all(np.isfinite(q) & (q >= -OFFSET) & (q < OFFSET), axis=1)
    ijk = np.zeros(q.shape, dtype=np.int64)
    ijk[ok] = q[ok].astype(np.int64)
    return ijk, ok


def pack(ijk: IntArray) -> IntArray:
    """(n,) int64 keys of (n, 3) voxel coordinates in ``[-OFFSET, OFFSET)``."""
    u = (np.asarray(ijk, np.int64) + OFFSET) & _MASK
    return (u[:, 0] << (2 * AXIS_BITS)) | (u[:, 1] << AXIS_BITS) | u[:, 2]


def unpack(keys: IntArray) -> IntArray:
    """(n, 3) voxel coordinates of (n,) keys (inverse of :func:`pack`)."""
    k = np.asarray(keys, np.int64)
    out = np.stack([(k >> (2 * AXIS_BITS)) & _MASK, (k >> AXIS_BITS) & _MASK, k & _MASK], axis=1)
    return out - OFFSET


def voxel_keys(points: np.ndarray, voxel_m: float) -> tuple[IntArray, np.ndarray]:
    """``(keys, ok)``: the packed voxel key of each point inside the key range and the (n,)
    mask of those points (:func:`voxel_coords`)."""
    ijk, ok = voxel_coords(points, voxel_m)
    return pack(ijk[ok]), ok


def contribution(points: np.ndarray, intensity: np.ndarray, voxel_m: float) -> Contribution:
    """The per-voxel sums of (n, 3) ``points`` (m) and (n,) ``intensity`` on a grid of
    ``voxel_m`` (points outside the key range or not finite are left out).

    Raises
    ------
    InputError
        ``voxel_m`` not > 0, or shapes that do not match.
    """
    if not voxel_m > 0:
        raise InputError(f'voxel size must be > 0 m, got {voxel_m}')
    P = np.asarray(points, float).reshape(-1, 3)
    inten = np.asarray(intensity, float).reshape(-1)
    if inten.shape[0] != P.shape[0]:
        raise InputError(f'{P.shape[0]} points but {inten.shape[0]} intensities')
    keys, ok = voxel_keys(P, voxel_m)
    P, inten = P[ok], inten[ok]
    ukeys, inverse = np.unique(keys, return_inverse=True)
    v = ukeys.size
    counts = np.bincount(inverse, minlength=v).astype(np.int64)
    sums = np.empty((v, 4))
    for c in range(3):
        sums[:, c] = np.bincount(inverse, weights=P[:, c], minlength=v)
    sums[:, 3] = np.bincount(inverse, weights=inten, minlength=v)
    return Contribution(ukeys.astype(np.int64), counts, sums)


def downsample(points: np.ndarray, intensity: np.ndarray, voxel_m: float
               ) -> tuple[np.ndarray, np.ndarray]:
    """``(points, intensity)``: one point per occupied voxel of ``voxel_m`` (the centroid, the
    mean intensity), float32, in key order (deterministic)."""
    c = contribution(points, intensity, voxel_m)
    mean = c.sums / c.counts[:, None]
    return mean[:, :3].astype(np.float32), mean[:, 3].astype(np.float32)


class VoxelAccumulator:
    """Per-voxel counts and sums of ``x y z intensity`` under additions and removals.

    Slots of the arrays are looked up by key in a dict (one look-up per voxel of the
    contribution added); a voxel whose count returns to 0 frees its slot for reuse, so memory
    follows the voxels in use, not the history.
    """

    def __init__(self) -> None:
        self._slot: dict[int, int] = {}
        cap = 1024
        self._keys = np.zeros(cap, np.int64)
        self._counts = np.zeros(cap, np.int64)
        self._sums = np.zeros((cap, 4))
        self._free: list[int] = []
        self._size = 0  # slots ever handed out (the arrays' used prefix)

    def __len__(self) -> int:
        """Occupied voxels."""
        return len(self._slot)

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays (the dict not counted)."""
        return int(self._keys.nbytes + self._counts.nbytes + self._sums.nbytes)

    def _grow(self, need: int) -> None:
        cap = self._keys.size
        if need <= cap:
            return
        new = max(need, 2 * cap)
        for name in ('_keys', '_counts', '_sums'):
            old = getattr(self, name)
            arr = np.zeros((new,) + old.shape[1:], old.dtype)
            arr[:cap] = old
            setattr(self, name, arr)

    def add(self, c: Contribution) -> IntArray:
        """Add a contribution; returns (v,) the slots of its voxels (for :meth:`remove`)."""
        get = self._slot.get
        slots = np.fromiter((get(k, -1) for k in c.keys.tolist()), np.int64, c.keys.size)
        new = np.flatnonzero(slots < 0)
        if new.size:
            reuse = min(new.size, len(self._free))
            fresh = new.size - reuse
            got = [self._free.pop() for _ in range(reuse)]
            self._grow(self._size + fresh)
            got += range(self._size, self._size + fresh)
            self._size += fresh
            slots[new] = got
            for k, s in zip(c.keys[new].tolist(), got):
                self._slot[k] = s
            self._keys[slots[new]] = c.keys[new]
        self._counts[slots] += c.counts
        self._sums[slots] += c.sums
        return slots

    def remove(self, c: Contribution, slots: np.ndarray) -> None:
        """Subtract a contribution added before at ``slots`` (what :meth:`add` returned)."""
        slots = np.asarray(slots, np.int64)
        assert np.array_equal(self._keys[slots], c.keys), 'not the contribution added there'
        self._counts[slots] -= c.counts
        self._sums[slots] -= c.sums
        empty = slots[self._counts[slots] <= 0]
        if empty.size:
            self._counts[empty] = 0
            self._sums[empty] = 0.0
            for s, k in zip(empty.tolist(), self._keys[empty].tolist()):
                del self._slot[k]
                self._free.append(s)

    def clear(self) -> None:
        """Forget every voxel."""
        self.__init__()

    def voxels(self) -> tuple[IntArray, IntArray, FloatArray]:
        """``(keys, counts, sums)`` of the occupied voxels, in key order."""
        used = np.flatnonzero(self._counts[:self._size] > 0)
        order = np.argsort(self._keys[used], kind='stable')
        used = used[order]
        return self._keys[used].copy(), self._counts[used].copy(), self._sums[used].copy()

    def centroids(self) -> tuple[np.ndarray, np.ndarray]:
        """``(points, intensity)``: (v, 3) float32 centroid (m) and (v,) float32 mean intensity
        of every occupied voxel, in key order."""
        _, counts, sums = self.voxels()
        mean = sums / np.maximum(counts, 1)[:, None]
        return mean[:, :3].astype(np.float32), mean[:, 3].astype(np.float32)
