"""Compact, growable tables behind :class:`~ga_ros.core.window.TrackWindowAligner`.

A survey of 100,000 poses has ~600,000 connections; the aligner keeps every one of them (a
batch refinement needs them all), so what each costs matters (issue 14: < 2 KiB per pose). These
tables hold numbers in numpy arrays instead of Python objects (a Python ``int`` in a list costs
~36 bytes, a dict entry ~100), symmetric 6x6 covariances as their 21 upper-triangle values, and
grow by allocating a larger zeroed array and copying: the capacity not yet written is never
touched, so it takes address space but no resident memory.
"""

from __future__ import annotations

import mmap
import sys
from collections.abc import Iterable

import numpy as np

from ga_ros.arrays import FloatArray, IntArray

#: Row and column of the 21 upper-triangle entries of a 6x6 matrix, row by row.
IU6 = np.triu_indices(6)
#: Their positions in the row-major 36 values of a 6x6 matrix.
IU6_FLAT = IU6[0] * 6 + IU6[1]


#: Arrays of at least this many bytes live in their own anonymous memory map (see :func:`zeros`).
MMAP_MIN_BYTES = 1 << 20


def zeros(shape: tuple[int, ...], dtype=float) -> np.ndarray:
    """A zeroed array whose untouched pages take no resident memory.

    ``np.zeros`` gets its memory from ``calloc``; once a process has freed large blocks (a
    solver does, all the time), glibc serves allocations up to 32 MiB from its heap and must
    clear recycled memory, which makes every byte of a growable table's spare capacity
    resident. An array of at least :data:`MMAP_MIN_BYTES` is therefore placed in its own
    anonymous ``mmap``: the kernel hands out zero pages as they are first written, and the
    whole map is returned to the system when the array is freed.
    """
    dtype = np.dtype(dtype)
    nbytes = int(np.prod(shape, dtype=np.int64)) * dtype.itemsize
    if nbytes < MMAP_MIN_BYTES:
        return np.zeros(shape, dtype=dtype)
    return np.frombuffer(mmap.mmap(-1, nbytes), dtype=dtype).reshape(shape)


def grow_rows(a: np.ndarray, need: int) -> np.ndarray:
    """``a`` copied into a zeroed array (:func:`zeros`) of at least ``need`` rows (1.5x
    steps, >= 64)."""
    cap = max(64, need, a.shape[0] + a.shape[0] // 2)
    out = zeros((cap,) + a.shape[1:], a.dtype)
    out[:a.shape[0]] = a
    return out


def pack_sym6(cov: FloatArray) -> FloatArray:
    """The 21 upper-triangle values (row by row) of each symmetric 6x6 matrix in ``cov``
    (``(..., 6, 6)`` -> ``(..., 21)``); the lower triangle is not read."""
    cov = np.asarray(cov, dtype=float)
    return cov.reshape(cov.shape[:-2] + (36,))[..., IU6_FLAT]


def unpack_sym6(packed: FloatArray) -> FloatArray:
    """Symmetric 6x6 matrices from their 21 upper-triangle values (``(..., 21)`` ->
    ``(..., 6, 6)``); exact inverse of :func:`pack_sym6` for symmetric input."""
    packed = np.asarray(packed, dtype=float)
    out = np.empty(packed.shape[:-1] + (6, 6))
    out[..., IU6[0], IU6[1]] = packed
    out[..., IU6[1], IU6[0]] = packed
    return out


class Rows:
    """Append-only table of fixed-shape numpy rows with amortised O(1) growth.

    Parameters
    ----------
    shape : shape of one row (``()`` for scalars).
    dtype : numpy dtype of the rows.
    """

    def __init__(self, shape: tuple[int, ...] = (), dtype=float) -> None:
        self._a = np.zeros((64,) + tuple(shape), dtype=dtype)
        self.n = 0

    @classmethod
    def of(cls, a, dtype) -> Rows:
        """A table holding the rows of ``a`` (copied)."""
        a = np.asarray(a, dtype=dtype)
        rows = cls(a.shape[1:], dtype)
        rows._a = grow_rows(rows._a[:0], a.shape[0] + max(64, a.shape[0] // 8))
        rows._a[:a.shape[0]] = a
        rows.n = a.shape[0]
        return rows

    def append(self, row) -> int:
        """Append one row; returns its index."""
        if self.n == self._a.shape[0]:
            self._a = grow_rows(self._a, self.n + 1)
        self._a[self.n] = row
        self.n += 1
        return self.n - 1

    @property
    def a(self) -> np.ndarray:
        """View of the filled rows (writable; valid until the next append)."""
        return self._a[:self.n]

    def __len__(self) -> int:
        return self.n


class SymRows:
    """Append-only table of symmetric 6x6 matrices kept as their 21 upper-triangle values
    (168 instead of 288 bytes each). ``rows[idx]`` (or ``rows.a[idx]``, the spelling of
    :class:`Rows`) unpacks the selected rows into ``(..., 6, 6)`` arrays; they are exactly
    the matrices appended, which must be symmetric (only the upper triangle is kept)."""

    def __init__(self) -> None:
        self.packed_rows = Rows((21,))

    @classmethod
    def of_packed(cls, packed) -> SymRows:
        """A table holding ``packed`` ``(m, 21)`` rows (copied)."""
        rows = cls()
        rows.packed_rows = Rows.of(np.reshape(packed, (-1, 21)), float)
        return rows

    @property
    def n(self) -> int:
        return self.packed_rows.n

    def __len__(self) -> int:
        return self.packed_rows.n

    def append(self, cov: FloatArray) -> int:
        """Append one symmetric 6x6 matrix; returns its index."""
        return self.packed_rows.append(pack_sym6(cov))

    @property
    def a(self) -> SymRows:
        """The table itself: ``rows.a[idx]`` reads like :attr:`Rows.a` does."""
        return self

    @property
    def packed(self) -> FloatArray:
        """View ``(m, 21)`` of the stored values."""
        return self.packed_rows.a

    def __getitem__(self, idx) -> FloatArray:
        return unpack_sym6(self.packed_rows.a[idx])

    def full(self) -> FloatArray:
        """Every matrix, unpacked ``(m, 6, 6)`` (a new array)."""
        return unpack_sym6(self.packed_rows.a)


class SymArray:
    """Fixed-capacity array of symmetric 6x6 matrices stored as 21 upper-triangle values,
    indexed like a ``(capacity, 6, 6)`` numpy array: ``a[idx]`` unpacks (a new array),
    ``a[idx] = m`` stores the upper triangle of ``m`` (so a slightly asymmetric matrix comes
    back mirrored from its upper triangle)."""

    def __init__(self, capacity: int = 0) -> None:
        self.packed = zeros((capacity, 21))

    @property
    def shape(self) -> tuple[int, int, int]:
        return (self.packed.shape[0], 6, 6)

    def grow(self, capacity: int) -> None:
        """Make room for ``capacity`` matrices (zeros), keeping the stored ones."""
        if capacity > self.packed.shape[0]:
            self.packed = grow_rows(self.packed, capacity)

    def __getitem__(self, idx) -> FloatArray:
        return unpack_sym6(self.packed[idx])

    def __setitem__(self, idx, value) -> None:
        value = np.asarray(value, dtype=float)
        if value.ndim < 2:  # a scalar (e.g. 0.0) fills every entry
            self.packed[idx] = value
        else:
            self.packed[idx] = pack_sym6(value)


class IdIndex:
    """Map from node id (any int64, any order) to row index, without a Python object per id.

    The ids are kept in a sorted array (with their row indices) plus a small dict of the
    latest ones, merged into the arrays when it passes 1/16 of their size (so a lookup is a
    binary search and an insertion amortised O(log n)). Behaves like the ``dict`` it replaces
    for ``in``, ``[]``, :meth:`get` and ``len``.
    """

    def __init__(self) -> None:
        self._keys = np.zeros(0, dtype=np.int64)
        self._vals = np.zeros(0, dtype=np.int64)
        self._recent: dict[int, int] = {}
        self._top = -2**63 - 1  # the largest key of _keys: a new, larger id needs no search

    def _sorted(self, keys: IntArray, vals: IntArray) -> None:
        self._keys, self._vals = keys, vals
        self._top = int(keys[-1]) if keys.size else -2**63 - 1

    @classmethod
    def of(cls, ids: IntArray) -> IdIndex:
        """Index of ``ids`` (row ``k`` holds ``ids[k]``); ``ValueError`` if they repeat."""
        ids = np.asarray(ids, dtype=np.int64)
        index = cls()
        order = np.argsort(ids, kind='stable')
        index._sorted(ids[order], order.astype(np.int64))
        if ids.size > 1 and (np.diff(index._keys) == 0).any():
            raise ValueError('node ids are not unique')
        return index

    def __len__(self) -> int:
        return self._keys.size + len(self._recent)

    def nbytes(self) -> int:
        """Bytes the index holds: its two arrays, plus the dict of the latest ids (its table
        and about 64 bytes per entry for the two ints)."""
        return (self._keys.nbytes + self._vals.nbytes + sys.getsizeof(self._recent)
                + 64 * len(self._recent))

    def get(self, node_id: int, default=None):
        """Row index of ``node_id``, or ``default``."""
        k = self._recent.get(node_id)
        if k is not None:
            return k
        try:
            node = int(node_id)
        except (TypeError, ValueError, OverflowError):
            return default
        if not -2**63 <= node <= self._top:  # above every sorted key: not among them
            return default
        p = int(np.searchsorted(self._keys, node))
        if p < self._keys.size and self._keys[p] == node:
            return int(self._vals[p])
        return default

    def __contains__(self, node_id) -> bool:
        return self.get(node_id) is not None

    def __getitem__(self, node_id) -> int:
        k = self.get(node_id)
        if k is None:
            raise KeyError(node_id)
        return k

    def add(self, node_id: int, k: int) -> None:
        """Record that row ``k`` holds ``node_id`` (a new id)."""
        self._recent[int(node_id)] = int(k)
        if len(self._recent) > max(1024, self._keys.size // 16):
            keys = np.concatenate([self._keys, np.fromiter(self._recent, np.int64)])
            vals = np.concatenate([self._vals, np.fromiter(self._recent.values(), np.int64)])
            order = np.argsort(keys, kind='stable')
            self._sorted(keys[order], vals[order])
            self._recent = {}


class TrackRanges:
    """Rows of each track's nodes. A track's nodes are contiguous rows (a new node of another
    track ends the open track, and a finished track takes no new node), so each track is kept
    as ``[start, stop)``; ``ranges[t]`` gives the row indices as an array."""

    def __init__(self) -> None:
        self._span: dict[int, list[int]] = {}

    @classmethod
    def of(cls, track: IntArray) -> TrackRanges:
        """Ranges of a per-row track array; ``ValueError`` if a track's rows are not
        contiguous."""
        track = np.asarray(track, dtype=np.int64)
        ranges = cls()
        if track.size:
            starts = np.concatenate([[0], np.flatnonzero(np.diff(track)) + 1])
            stops = np.concatenate([starts[1:], [track.size]])
            for t, a, b in zip(track[starts].tolist(), starts.tolist(), stops.tolist()):
                if t in ranges._span:
                    raise ValueError(f'the nodes of track {t} are not contiguous')
                ranges._span[t] = [a, b]
        return ranges

    def add(self, track: int, k: int) -> None:
        """Row ``k`` (the next row) belongs to ``track``."""
        span = self._span.get(track)
        if span is None:
            self._span[track] = [k, k + 1]
        else:
            assert span[1] == k, 'a track takes rows only while it is the newest'
            span[1] = k + 1

    def __contains__(self, track) -> bool:
        return track in self._span

    def start(self, track) -> int:
        """The first row of ``track`` (no array built)."""
        return self._span[track][0]

    def __getitem__(self, track) -> IntArray:
        a, b = self._span[track]
        return np.arange(a, b, dtype=np.int64)

    def __len__(self) -> int:
        return len(self._span)


class TrackLists:
    """Connections (row indices) of each track, as growable int32 arrays: ``lists.get(t, [])``
    returns the array of track ``t`` (as the dict of lists it replaces did)."""

    def __init__(self) -> None:
        self._rows: dict[int, Rows] = {}

    def add(self, tracks: Iterable[int], k: int) -> None:
        """Connection ``k`` touches each of ``tracks`` (distinct)."""
        for t in tracks:
            rows = self._rows.get(t)
            if rows is None:
                rows = self._rows[t] = Rows((), np.int32)
            rows.append(k)

    def get(self, track, default=None):
        rows = self._rows.get(track)
        return default if rows is None else rows.a

    def __getitem__(self, track) -> IntArray:
        return self._rows[track].a

    def __contains__(self, track) -> bool:
        return track in self._rows

    @classmethod
    def of(cls, keys: IntArray, values: IntArray) -> TrackLists:
        """Lists of ``values`` grouped by ``keys`` (each group in increasing value order)."""
        lists = cls()
        keys, values = np.asarray(keys, np.int64), np.asarray(values, np.int64)
        order = np.lexsort((values, keys))
        k, v = keys[order], values[order]
        cuts = np.flatnonzero(np.diff(k)) + 1
        for g, vals in zip(np.split(k, cuts), np.split(v, cuts)):
            if g.size:
                lists._rows[int(g[0])] = Rows.of(vals, np.int32)
        return lists
