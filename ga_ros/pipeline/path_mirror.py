"""The corrected path kept in step with an aligner, at a cost proportional to what changed.

Every output after an update (the ``nav_msgs/Path``, the corrections, the window path, the
newest pose, ``map -> odom``) reads the aligner's corrected path. Copying it whole at every
update (:meth:`TrackWindowAligner.corrected_path
<ga_ros.core.window.aligner.TrackWindowAligner.corrected_path>`) costs a time that grows with
the survey. :class:`PathMirror` holds a copy and, after an update, copies only the rows that
update could change: from the first row the aligner could change at the previous call
(:meth:`~ga_ros.core.window.aligner.TrackWindowAligner.mutable_rows`, rows before it are
retired and frozen tracks, unchanged whatever the survey's length) to the end, new rows
included. So the copy, and the serialized path it maintains (:class:`~ga_ros.io.cdr.PathCdr`),
cost O(window + refinement horizon + new rows) per update, not O(survey); the message's bytes
themselves are one copy of a buffer.

The whole path is copied again (exactly as from scratch) after a change that is not one window
update: another aligner object (a reset, a restore, ``load_state``), two or more updates since
the previous call, an aligner without ``mutable_rows`` (the batch aligner) or ``every_row``
(``refine_batch``). The path it returns is always equal, bit for bit, to
``aligner.corrected_path()`` (tested after every update of surveys with fixes and restarts).

ROS-free.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from ga_ros.arrays import BoolArray, IntArray
from ga_ros.core.window.config import CorrectedPath
from ga_ros.io.cdr import PathCdr


class PathMirror:
    """A copy of an aligner's corrected path, refreshed from the rows that can have changed
    (module docstring).

    Parameters
    ----------
    frame_id : the frame of the serialized path (:meth:`path_message`), e.g. ``map``.
    """

    def __init__(self, frame_id: str = 'map') -> None:
        self._ids = np.zeros(0, np.int64)
        self._tracks = np.zeros(0, np.int64)
        self._stamps = np.zeros(0, np.int64)
        self._T = np.zeros((0, 4, 4))
        self._frozen = np.zeros(0, bool)
        self.n = 0
        #: the first row the last :meth:`sync` copied (rows before it were kept as they were)
        self.changed_from = 0
        #: whether the aligner's path says which nodes are frozen (else all read as movable)
        self.has_frozen = True
        self.cdr = PathCdr(frame_id)
        self._cdr_dirty_from = 0
        self._aligner_id: int | None = None
        self._n_updates: int | None = None
        self._first_mutable = 0

    def restart(self) -> None:
        """Forget the copy: the next :meth:`sync` copies every row."""
        self._aligner_id = None
        self._n_updates = None
        self._first_mutable = 0

    def sync(self, aligner: Any, every_row: bool = False) -> CorrectedPath:
        """Bring the copy up to ``aligner``'s corrected path and return it (views of the copy:
        valid until the next call; callers that keep it copy it).

        Parameters
        ----------
        aligner : the aligner (track-window or batch, anything with ``corrected_path()``).
        every_row : copy every row (after a change that is not a window update, such as
            ``refine_batch``).
        """
        stats = getattr(aligner, 'stats', None)
        n_updates = getattr(stats, 'n_updates', None)
        rows = getattr(aligner, 'mutable_rows', None)
        lo = 0
        if (not every_row and rows is not None and id(aligner) == self._aligner_id
                and n_updates is not None and self._n_updates is not None
                and 0 <= int(n_updates) - self._n_updates <= 1):
            lo = min(self._first_mutable, self.n)   # one update since: no row before changed
        part = aligner.corrected_path(lo) if lo else aligner.corrected_path()
        self._store(lo, part)
        self._aligner_id = id(aligner)
        self._n_updates = None if n_updates is None else int(n_updates)
        self._first_mutable = int(rows()[0]) if rows is not None else 0
        return self.path()

    def path(self) -> CorrectedPath:
        """The copy as it is (views, valid until the next :meth:`sync`)."""
        n = self.n
        return CorrectedPath(self._ids[:n], self._tracks[:n], self._stamps[:n], self._T[:n],
                             self._frozen[:n])

    def set_stamps(self, from_row: int, stamps_ns: IntArray) -> None:
        """Replace the stamps of rows ``from_row ..`` (a caller with stamps of its own, such as
        the replay's message stamps); the serialized path follows."""
        lo = int(from_row)
        s = np.asarray(stamps_ns, np.int64).reshape(-1)
        self._stamps[lo:lo + s.size] = s
        self._cdr_dirty_from = min(self._cdr_dirty_from, lo)

    def path_message(self, stamp_ns: int) -> bytes:
        """The serialized ``nav_msgs/Path`` of the copy in ``frame_id`` (the bytes of
        :func:`~ga_ros.io.cdr.path_cdr`), header stamped ``stamp_ns``: the rows changed since the
        last call are encoded again, the others kept."""
        lo = min(self._cdr_dirty_from, self.cdr.n, self.n)
        self.cdr.update(self._T[lo:self.n], self._stamps[lo:self.n], lo)
        self._cdr_dirty_from = self.n
        return self.cdr.message(stamp_ns)

    def movable_rows(self) -> tuple[int, BoolArray]:
        """``(lo, movable)``: every row before ``lo`` is frozen, ``movable`` (k,) says which
        rows ``lo ..`` are not (the window path without reading the frozen history)."""
        lo = min(self._first_mutable, self.n)
        return lo, ~self._frozen[lo:self.n]

    def _store(self, lo: int, part: CorrectedPath) -> None:
        ids = np.asarray(part.node_ids, np.int64).reshape(-1)
        k = ids.size
        n = lo + k
        self._grow(n)
        self._ids[lo:n] = ids
        self._tracks[lo:n] = np.asarray(part.track_ids, np.int64).reshape(-1)
        self._stamps[lo:n] = np.asarray(part.stamps_ns, np.int64).reshape(-1)
        self._T[lo:n] = np.asarray(part.T_world_node, float).reshape(-1, 4, 4)
        frozen = getattr(part, 'frozen', None)
        self.has_frozen = frozen is not None
        self._frozen[lo:n] = (np.zeros(k, bool) if frozen is None
                              else np.asarray(frozen, bool).reshape(-1))
        self.n = n
        self.changed_from = lo
        self._cdr_dirty_from = min(self._cdr_dirty_from, lo)

    def _grow(self, n: int) -> None:
        """Room for ``n`` rows (doubling: appending costs O(1) per row)."""
        if n <= self._ids.size:
            return
        cap, m = max(n, 2 * self._ids.size, 64), self.n

        def bigger(a: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
            out = np.zeros((cap, *shape), a.dtype)
            out[:m] = a[:m]
            return out

        self._ids, self._tracks = bigger(self._ids, ()), bigger(self._tracks, ())
        self._stamps, self._frozen = bigger(self._stamps, ()), bigger(self._frozen, ())
        self._T = bigger(self._T, (4, 4))


def newest_not_in_track(track_ids: IntArray, track: int | None) -> int | None:
    """Row of the newest entry of ``track_ids`` that is not ``track`` (the newest row if
    ``track`` is None; None if there is none), reading back from the end only as far as the
    rows of ``track`` reach there (doubling chunks): the open track's length, not the path's."""
    t = np.asarray(track_ids).reshape(-1)
    n = t.size
    if track is None:
        return n - 1 if n else None
    hi, step = n, 16
    while hi > 0:
        lo = max(hi - step, 0)
        other = np.flatnonzero(t[lo:hi] != track)
        if other.size:
            return lo + int(other[-1])
        hi, step = lo, 2 * step
    return None
