"""Whether a measurement touching a frozen node was received before: a re-delivered history
(a publisher's transient-local queue replayed to a restarted node) is a ``duplicate``, a new
measurement to a frozen node is ``frozen``. The duplicate keys of connections between unfrozen
nodes live in :attr:`WindowState.pairs`; those of the others are pruned from it for memory, so
this index answers for them from the connection table itself, built only when such a
measurement arrives (8 bytes per connection)."""

from __future__ import annotations

import numpy as np

from ga_ros.arrays import IntArray

_A = np.uint64(0x9E3779B97F4A7C15)
_B = np.uint64(0xC2B2AE3D27D4EB4F)


def key_hash(low: IntArray | int, high: IntArray | int, fingerprint: IntArray | int) -> np.ndarray:
    """A 64-bit hash of duplicate keys ``(low id, high id, fingerprint)`` (vectorised)."""
    lo = np.asarray(low).astype(np.uint64)
    hi = np.asarray(high).astype(np.uint64)
    fp = np.asarray(fingerprint).astype(np.uint64)
    with np.errstate(over='ignore'):
        return (lo * _A) ^ ((hi + np.uint64(1)) * _B) ^ fp


class ReceivedConnections:
    """Hashes of every stored connection's duplicate key: a sorted array of the rows hashed
    at the last merge plus a short unsorted tail of newer rows (merged when it grows past a
    tenth of the sorted part), so a stream of re-deliveries interleaved with new input costs
    O(log m) per query, amortised."""

    def __init__(self) -> None:
        self._sorted = np.zeros(0, np.uint64)
        self._tail = np.zeros(0, np.uint64)
        self._rows = 0    # connection rows hashed so far

    def contains(self, state: object, key: tuple[int, int, int]) -> bool:
        """Whether a connection with duplicate key ``key`` is in ``state``'s connection table
        (a :class:`~ga_ros.core.window.state.WindowState`)."""
        self._catch_up(state)
        h = key_hash(*key)
        i = int(np.searchsorted(self._sorted, h))
        return bool((i < len(self._sorted) and self._sorted[i] == h) or np.any(self._tail == h))

    def _catch_up(self, state: object) -> None:
        m = state.src.n
        if m < self._rows:                      # the table was rolled back or replaced
            self.__init__()
        if m > self._rows:
            ids = state.idarr.a
            a, b = ids[state.src.a[self._rows:m]], ids[state.dst.a[self._rows:m]]
            new = key_hash(np.minimum(a, b), np.maximum(a, b), state.fp.a[self._rows:m])
            self._tail = np.concatenate([self._tail, new])
            self._rows = m
        if len(self._tail) > max(64, len(self._sorted) // 10):
            self._sorted = np.sort(np.concatenate([self._sorted, self._tail]))
            self._tail = np.zeros(0, np.uint64)
