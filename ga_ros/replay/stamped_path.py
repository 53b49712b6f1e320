"""The replay's corrected path after each update, at a cost proportional to what changed.

The replay stamps each node with the stamp of the message that brought it (the aligner's own
stamp where no message carried one; the first node of a measurement bag, which no message
stamps, one median node interval before the second, or its ground-truth stamp), and writes the
whole path as a ``nav_msgs/Path`` after every update. :class:`StampedPath` keeps those stamps
and the serialized message (:class:`~ga_ros.io.cdr.PathCdr`) beside the aligner's path
(:class:`~ga_ros.pipeline.path_mirror.PathMirror`) and, after an update, looks up, encodes and
checks only the rows the update could change, the new ones, and the few rows stamped by a
fallback. The result is the path and the message bytes that the same rules applied to the
whole path give (tested against :meth:`ReplayRun.corrected_from_scratch
<ga_ros.replay.run.ReplayRun.corrected_from_scratch>` after every update).

ROS-free.
"""

from __future__ import annotations

import bisect
from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from ga_ros.arrays import IntArray
from ga_ros.core.window.config import CorrectedPath
from ga_ros.io.cdr import PathCdr
from ga_ros.pipeline.path_mirror import PathMirror


class KnownStamps:
    """The stamps known so far (a multiset, sorted) and the sorted differences of neighbours:
    their first and the median interval as ``np.median(np.diff(np.sort(known)))`` gives it,
    in O(log n) per stamp added (plus a memory move) instead of a sort per call."""

    def __init__(self) -> None:
        self.sorted: list[int] = []
        self.gaps: list[int] = []

    def add(self, s: int) -> None:
        """One more known stamp (ns)."""
        a = self.sorted
        i = bisect.bisect_right(a, s)
        if 0 < i < len(a):
            self.gaps.pop(bisect.bisect_left(self.gaps, a[i] - a[i - 1]))
        if i > 0:
            bisect.insort(self.gaps, s - a[i - 1])
        if i < len(a):
            bisect.insort(self.gaps, a[i] - s)
        a.insert(i, s)

    def before_first(self) -> int:
        """One median interval before the first stamp (two or more known), the first (one),
        0 (none): the stamp of a node no message stamped."""
        a, g = self.sorted, self.gaps
        if len(a) >= 2:
            m = len(g)
            mid = g[m // 2 - 1:m // 2 + 1] if m % 2 == 0 else g[m // 2:m // 2 + 1]
            return int(np.int64(a[0]) - np.mean(np.array(mid, dtype=np.int64)))
        return int(a[0]) if a else 0


class StampedPath:
    """The corrected path with the replay's node stamps, and its ``nav_msgs/Path`` bytes,
    kept in step with the aligner (module docstring).

    Parameters
    ----------
    frame_id : the path's frame.
    stamps : node id -> stamp (ns) of the message that brought it (entries are only added).
    first_stamp : ``(stamps, node ids) -> stamp`` of a node no message stamped, from the
        whole path (:meth:`ReplayRun.first_stamp <ga_ros.replay.run.ReplayRun.first_stamp>`):
        called only where a node other than the first has no stamp at all.
    gt_first : the first node's ground-truth stamp (None: none), asked once.
    """

    def __init__(self, frame_id: str, stamps: Mapping[int, int],
                 first_stamp: Callable[[IntArray, IntArray], int],
                 gt_first: Callable[[], int | None]) -> None:
        self.mirror = PathMirror(frame_id)
        self.cdr = PathCdr(frame_id)
        self._stamps_of = stamps
        self._first_stamp = first_stamp
        self._gt_first = gt_first
        self._gt: tuple[int | None] | None = None
        self._reset()

    def _reset(self) -> None:
        self.d = np.zeros(0, np.int64)        # the messages' stamp by row (-1: none)
        self.out = np.zeros(0, np.int64)      # the stamp written by row
        self.stable_max = np.zeros(0, np.int64)  # running max of the stamps that never change
        self.corr = np.zeros(0, np.int64)     # the corrections' stamp by row (the aligner's)
        self.fallback: set[int] = set()       # rows without a message stamp
        self.known = KnownStamps()
        self.first_row: int | None = None
        self.n = 0

    def sync(self, aligner: Any, first_id: int | None, every_row: bool = False
             ) -> tuple[CorrectedPath, IntArray, IntArray, int]:
        """Bring the path up to the aligner's; returns the aligner's path, the replay's stamps
        by row, the corrections' stamps by row (the aligner's, the replay's where it has none)
        (views, valid until the next call) and the newest of the replay's stamps (the path
        message's header stamp)."""
        cp = self.mirror.sync(aligner, every_row)
        lo, n = self.mirror.changed_from, self.mirror.n
        if lo == 0:
            self._reset()
        self._grow(n)
        ids = cp.node_ids
        # the messages' stamps of the rows that can have changed, and of those that had none
        left = sorted(r for r in self.fallback if r < lo and self._stamps_of.get(
            int(ids[r]), -1) >= 0)
        for r in left:
            self.d[r] = self.out[r] = self._stamps_of[int(ids[r])]
            self.fallback.discard(r)
            self.known.add(int(self.d[r]))
        old = self.d[lo:self.n].copy()
        self.d[lo:n] = [self._stamps_of.get(i, -1) for i in ids[lo:n].tolist()]
        for k in np.flatnonzero(self.d[lo:n] >= 0).tolist():
            r = lo + k
            if r >= self.n or old[k] < 0:
                self.known.add(int(self.d[r]))
        self.fallback.difference_update(range(lo, self.n))
        self.fallback.update((lo + np.flatnonzero(self.d[lo:n] < 0)).tolist())
        if self.first_row is None and first_id is not None:
            hit = np.flatnonzero(ids[lo:n] == first_id)
            self.first_row = lo + int(hit[0]) if hit.size else None
        self.n = n
        # the stamps written: the message's, else the aligner's, else the first node's rule
        out, d, cs = self.out, self.d, cp.stamps_ns
        out[lo:n] = np.where(d[lo:n] < 0, cs[lo:n], d[lo:n])
        rows = sorted(self.fallback)
        before = out[rows].copy()
        for r in rows:
            out[r] = cs[r]
        f = self.first_row
        if f is not None and d[f] < 0:
            out[f] = self._first()
        neg = [r for r in rows if out[r] < 0]
        if neg:   # only the very first node can be unknown: the rule on the whole path
            value = self._first_stamp(out[:n].copy(), ids)
            out[neg] = value
        # the running max of the rows whose stamp never changes (a fallback row's may)
        start = min([lo, *left])
        stable = np.where(d[start:n] >= 0, d[start:n], cs[start:n])
        stable[d[start:n] < 0] = np.iinfo(np.int64).min
        prev = self.stable_max[start - 1] if start > 0 else np.iinfo(np.int64).min
        self.stable_max[start:n] = np.maximum.accumulate(np.maximum(stable, prev))
        top = max([int(self.stable_max[n - 1])] + [int(out[r]) for r in rows]) if n else 0
        corr = self.corr
        corr[start:n] = np.where(cs[start:n] < 0, out[start:n], cs[start:n])
        for r in rows:
            if r < start:
                corr[r] = out[r] if cs[r] < 0 else cs[r]
        # the message: rows from the first changed one, and the fallback rows that changed
        lo_cdr = min(start, self.cdr.n)
        self.cdr.update(cp.T_world_node[lo_cdr:n], out[lo_cdr:n], lo_cdr)
        moved = [r for r, b in zip(rows, before.tolist()) if r < lo_cdr and out[r] != b]
        if moved:
            self.cdr.rewrite(moved, cp.T_world_node[moved], out[moved])
        return cp, out[:n], corr[:n], top

    def message(self, stamp_ns: int) -> bytes:
        """The serialized path (header stamped ``stamp_ns``)."""
        return self.cdr.message(stamp_ns)

    def _first(self) -> int:
        """The first node's stamp when no message stamped it: its ground truth's, else one
        median interval before the first known stamp."""
        if self._gt is None:
            self._gt = (self._gt_first(),)
        return self.known.before_first() if self._gt[0] is None else int(self._gt[0])

    def _grow(self, n: int) -> None:
        if n <= self.d.size:
            return
        cap, m = max(n, 2 * self.d.size, 64), self.n
        for name in ('d', 'out', 'stable_max', 'corr'):
            a = np.zeros(cap, np.int64)
            a[:m] = getattr(self, name)[:m]
            setattr(self, name, a)
