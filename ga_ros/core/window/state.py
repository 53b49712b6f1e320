"""The declared state of a :class:`~ga_ros.core.window.TrackWindowAligner`.

:class:`WindowState` holds everything the aligner keeps between calls that a snapshot file
saves (:mod:`ga_ros.core.window.persistence` reads and writes it as a whole) or a failed update
puts back (:class:`Rollback`): the node and connection tables (:mod:`~ga_ros.core.window.storage`:
numpy tables, no Python object per node or connection), the tracks, the joint priors, the last
adjustment's window and the counters; and the queries on those tables that every part of the
aligner shares (rows of a track, connections touching a node range, a sub-network).

Rows: nodes by row index in arrival order (``T``, ``cov`` and ``frozen`` have spare capacity
beyond ``idarr.n``); connections by row index in arrival order, their ends as node rows.
Connection ``status``: 0 active, 1 absorbed into a joint prior, 2 excluded as an outlier.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.fixes import FixBook
from ga_ros.core.network import ConnectionNetwork
from ga_ros.core.quality.online_variance import OnlineVarianceComponents
from ga_ros.core.solver import SolveResult
from ga_ros.core.window.calibration import OnlineCalibration
from ga_ros.core.window.received import ReceivedConnections
from ga_ros.core.window.storage import (
    IdIndex,
    Rows,
    SymArray,
    SymRows,
    TrackLists,
    TrackRanges,
    grow_rows,
)

#: Characters of a failed update's traceback the state keeps (:attr:`WindowState.last_failure`;
#: its end: the exception and the innermost frames).
LAST_FAILURE_CHARS = 4000


def no_weighted() -> tuple[IntArray, FloatArray]:
    """No frozen node adjusted as a weighted parameter: ``(node rows (0,), poses (0, 4, 4))``
    (:attr:`WindowState.T_weighted` before any update and after a refinement)."""
    return np.zeros(0, np.int64), np.zeros((0, 4, 4))


@dataclass(eq=False)
class WindowState:
    """What a track-window aligner keeps between calls (see the module docstring).

    Attributes
    ----------
    T_first : (4, 4) pose ``T_world_node`` of the first node (the datum).
    index : node id -> row. idarr, trackarr, stamparr : node id, track id, stamp (ns) by row.
    T : (capacity, 4, 4) ``T_world_node`` by row (frozen nodes: as frozen; window nodes: the
        last adjustment's estimate; the open track: its frame-to-frame chain).
    cov : frozen nodes' marginal covariances ``[x y z rx ry rz]`` (21 values each).
    frozen : (capacity,) whether each node row is frozen.
    src, dst : connection ends (node rows); z : (m, 6) measured motion ``[t, rotvec]``;
        ccov : (m, 21) their covariances; cross : overlap (not consecutive) connections;
        status : 0 active, 1 absorbed, 2 outlier; fp : measurement fingerprints.
    pairs : duplicate keys ``(low id, high id, fingerprint)`` of the connections between two
        unfrozen nodes (:meth:`prune_pairs`); pairs_kept : its size after the last pruning;
        received : every connection's key, for telling a re-delivery to a frozen node
        (:mod:`~ga_ros.core.window.received`; a cache, not saved).
    tracks : track ids in order of appearance; track_nodes : track -> its rows (contiguous);
        track_conns : track -> rows of the connections touching it.
    open_track : the newest track (``None`` before the first measurement); finished : the
        tracks that ended.
    priors : joint priors ``(node rows (k,), T_mean (k, 4, 4), information (6k, 6k))``
        (:class:`~ga_ros.core.window.freeze.JointPrior`).
    last_window : node rows of the last window adjustment.
    T_weighted : the last adjustment's estimate of the frozen nodes it adjusted as weighted
        parameters ``(node rows (k,), (k, 4, 4))``: where the next update starts them.
    rejected : rejected measurements by reason; n_updates, n_outliers : counters.
    n_failed_updates : window updates that failed (state put back) over the whole survey,
        restarts included (saved; a replay of the journal fails them again);
        last_failure : the last one's exception and traceback, its last
        :data:`LAST_FAILURE_CHARS` characters (``''`` if none).
    retired : finished tracks that left the bounded refinement's horizon; past : the joint
        prior of their terms, as ``priors``.
    refine_drift : how far (in standard deviations) the frozen nodes adjusted as weighted
        parameters may have moved from their priors' linearisation points since the last
        installed refinement (:meth:`~ga_ros.core.window.handoff.RefinementHandoff.measure`);
        a refinement starts only when it reaches ``refine_relinearize_sigma``.
    last_result : the last window adjustment (``None``: none, or ``last_pending`` set).
    last_pending : tracks of a window adjustment to recompute on first use (a restored state).
    seen_cache : ``(rows scanned, largest node id, largest track id)`` (:meth:`seen_max`).
    fixes : the absolute fixes of the nodes, with the gauge prior of ``datum='fixes'``
        (:class:`~ga_ros.core.fixes.FixBook`; its gate level set from the config).
    variance : the online variance components' book (group and last values of every
        connection row; :mod:`ga_ros.core.quality.online_variance`), ``None`` when off.
    calibration : the online calibration's book (the source and applied correction of every
        connection row, the last estimate; :mod:`ga_ros.core.window.calibration`), ``None``
        when off.
    """

    T_first: FloatArray = field(default_factory=lambda: np.eye(4))
    index: IdIndex = field(default_factory=IdIndex)
    idarr: Rows = field(default_factory=lambda: Rows((), np.int64))
    trackarr: Rows = field(default_factory=lambda: Rows((), np.int64))
    stamparr: Rows = field(default_factory=lambda: Rows((), np.int64))
    T: FloatArray = field(default_factory=lambda: np.zeros((0, 4, 4)))
    cov: SymArray = field(default_factory=SymArray)
    frozen: BoolArray = field(default_factory=lambda: np.zeros(0, dtype=bool))
    src: Rows = field(default_factory=lambda: Rows((), np.int64))
    dst: Rows = field(default_factory=lambda: Rows((), np.int64))
    z: Rows = field(default_factory=lambda: Rows((6,)))
    ccov: SymRows = field(default_factory=SymRows)
    cross: Rows = field(default_factory=lambda: Rows((), bool))
    status: Rows = field(default_factory=lambda: Rows((), np.int8))
    fp: Rows = field(default_factory=lambda: Rows((), np.uint32))
    pairs: set[tuple[int, int, int]] = field(default_factory=set)
    pairs_kept: int = 0
    tracks: list[int] = field(default_factory=list)
    track_nodes: TrackRanges = field(default_factory=TrackRanges)
    track_conns: TrackLists = field(default_factory=TrackLists)
    open_track: int | None = None
    finished: set[int] = field(default_factory=set)
    priors: list = field(default_factory=list)
    last_window: IntArray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    T_weighted: tuple[IntArray, FloatArray] = field(default_factory=no_weighted)
    rejected: dict[str, int] = field(default_factory=dict)
    n_updates: int = 0
    n_outliers: int = 0
    n_failed_updates: int = 0
    last_failure: str = ''
    retired: int = 0
    past: list = field(default_factory=list)
    refine_drift: float = 0.0
    last_result: SolveResult | None = None
    last_pending: list[int] | None = None
    seen_cache: tuple[int, int, int] = (0, -1, -1)
    fixes: FixBook = field(default_factory=FixBook)
    variance: OnlineVarianceComponents | None = None
    calibration: OnlineCalibration | None = None
    received: ReceivedConnections = field(default_factory=ReceivedConnections)

    def finished_order(self) -> list[int]:
        """The finished tracks in order of appearance.

        A track finishes only as the open (newest) track, so the finished tracks are the first
        ones of :attr:`tracks`: a slice, checked at its two ends, with no scan of the survey's
        tracks (a scan only if that does not hold)."""
        k = len(self.finished)
        if k <= len(self.tracks) and (k == 0 or self.tracks[k - 1] in self.finished) and (
                k == len(self.tracks) or self.tracks[k] not in self.finished):
            return self.tracks[:k]
        return [t for t in self.tracks if t in self.finished]

    def unfrozen_tail(self, tracks: list[int]) -> list[int]:
        """The tracks of ``tracks`` (in order of appearance) that are not frozen. Tracks freeze
        oldest first, so they are its last ones: found from the end, without looking at the
        frozen tracks before them."""
        k = len(tracks)
        while k > 0 and not self.frozen[self.track_nodes.start(tracks[k - 1])]:
            k -= 1
        return tracks[k:]

    def seen_max(self) -> tuple[int, int]:
        """Largest node id and track id seen so far (-1 before the first measurement); kept
        up to date incrementally."""
        n = self.idarr.n
        done, max_id, max_track = self.seen_cache
        if done != n:
            if done > n:
                done, max_id, max_track = 0, -1, -1
            max_id = max(max_id, int(self.idarr.a[done:].max()))
            max_track = max(max_track, int(self.trackarr.a[done:].max()))
            self.seen_cache = (n, max_id, max_track)
        return max_id, max_track

    def prune_pairs(self) -> None:
        """Keep only the duplicate keys of connections whose two nodes are not frozen (a
        measurement that touches a frozen node is refused before the duplicate test). Such
        connections come after the first connection that can touch the first unfrozen node
        (:meth:`rows_from`): only those rows are scanned."""
        _, r0 = self.rows_from(self.first_unfrozen())
        frozen = self.frozen[:self.idarr.n]
        src, dst = self.src.a[r0:], self.dst.a[r0:]
        live = r0 + np.flatnonzero(~frozen[src] & ~frozen[dst])
        ids = self.idarr.a
        a, b = ids[self.src.a[live]], ids[self.dst.a[live]]
        self.pairs = set(zip(np.minimum(a, b).tolist(), np.maximum(a, b).tolist(),
                             self.fp.a[live].tolist()))
        self.pairs_kept = len(self.pairs)

    def add_node(self, node_id: int, track: int, stamp_ns: int, T: FloatArray) -> int:
        """Store a new node; returns its row."""
        k = self.idarr.append(node_id)
        self.trackarr.append(track)
        self.stamparr.append(stamp_ns)
        self.index.add(node_id, k)
        if k >= self.T.shape[0]:  # amortised growth; the spare rows stay untouched
            self.T = grow_rows(self.T, k + 1)
            self.cov.grow(self.T.shape[0])
            self.frozen = grow_rows(self.frozen, self.T.shape[0])
        self.T[k] = T
        self.cov[k] = 0.0
        self.frozen[k] = False
        if track not in self.track_nodes:
            self.tracks.append(track)
        self.track_nodes.add(track, k)
        self.open_track = track
        return k

    @property
    def ids(self) -> IntArray:
        """Node ids by row (a view of the storage)."""
        return self.idarr.a

    @property
    def track(self) -> IntArray:
        """Track id of each node row (a view of the storage)."""
        return self.trackarr.a

    @property
    def stamp(self) -> IntArray:
        """Stamp (ns) of each node row (a view of the storage)."""
        return self.stamparr.a

    def first_unfrozen(self) -> int:
        """Row of the first node that is not frozen (the node count if every one is)."""
        n = self.idarr.n
        frozen = self.frozen[:n]
        lo = int(np.argmin(frozen)) if n else 0  # the first False (a scan, no copy)
        return n if n and frozen[lo] else lo

    def rows_from(self, lo: int) -> tuple[int, int]:
        """``(lo, r0)``: node row ``lo`` (clipped to the node count) and the first connection
        row that can touch a node ``>= lo``. Node rows follow creation order and a track's rows
        are contiguous; a connection is stored after both its nodes, so every connection
        touching a node ``>= lo`` comes at or after the first connection of ``lo``'s track."""
        n = self.idarr.n
        if lo >= n:
            return n, self.src.n
        first = self.track_conns.get(int(self.trackarr.a[lo]))
        return lo, (int(first[0]) if first is not None and len(first) else 0)

    def horizon_rows(self, f: int, m: int | None = None) -> IntArray:
        """Rows of the connections between nodes ``>= f`` among the first ``m`` (default all),
        sorted.

        A connection is stored after both its nodes, and node rows follow creation order, so
        every such connection comes at or after the one that created node ``f``, hence at or
        after the first connection of ``f``'s track: only the rows from there are scanned (of
        the horizon's size, whatever the survey's length; a gather of the horizon tracks'
        connection lists would cost ~20 ms per call at a horizon of 30 tracks of 200 poses)."""
        m = self.src.n if m is None else int(m)
        if f >= self.idarr.n:
            return np.zeros(0, dtype=np.int64)
        r0 = min(self.rows_from(f)[1], m)
        ends = (self.src.a[r0:m] >= f) & (self.dst.a[r0:m] >= f)
        return r0 + np.flatnonzero(ends)

    def track_connections(self, tracks: list[int]) -> IntArray:
        """Sorted rows of the connections that touch any of ``tracks``."""
        none = np.zeros(0, dtype=np.int64)
        return np.unique(np.concatenate([np.asarray(self.track_conns.get(t, none), np.int64)
                                         for t in tracks] or [none]))

    def subnetwork(self, nodes: IntArray, conns: IntArray,
                    cov: FloatArray | None = None,
                    z: FloatArray | None = None) -> ConnectionNetwork:
        """Network of some nodes (by index, distinct) and connections among them (already
        validated); ``cov``: the connections' (m, 6, 6) covariances if the caller has them
        unpacked; ``z``: their (m, 6) motions in place of the stored ones (the online
        calibration's motions as measured). The connections' ends are located by a binary
        search among ``nodes`` (no index array over all the survey's nodes)."""
        order = np.argsort(nodes, kind='stable')
        srt = nodes[order]

        def local(rows: IntArray) -> IntArray:
            return order[np.searchsorted(srt, rows)]

        return ConnectionNetwork.from_arrays(
            self.idarr.a[nodes], self.trackarr.a[nodes],
            local(self.src.a[conns]), local(self.dst.a[conns]),
            self.z.a[conns] if z is None else z,
            self.ccov.a[conns] if cov is None else cov)


@dataclass
class Rollback:
    """What a failed update puts back (:meth:`TrackWindowAligner.finish_track
    <ga_ros.core.window.TrackWindowAligner.finish_track>`): the rows an update can change (from
    ``node_row`` and ``conn_row``, the aligner's mutable rows: of the window and the refinement
    horizon, not of the whole survey, so that the copy costs the same at every track) and the
    small bookkeeping of :data:`KEPT` around them."""

    node_row: int
    conn_row: int
    T: FloatArray
    cov21: FloatArray
    frozen: BoolArray
    status: IntArray
    bookkeeping: dict

    #: Fields of :class:`WindowState` saved and restored as they are (replaced, never changed in
    #: place, by an update; ``priors`` is copied as a list).
    KEPT = ('priors', 'last_window', 'n_outliers', 'n_updates', 'T_weighted', 'retired', 'past',
            'refine_drift', 'last_result', 'last_pending')

    @classmethod
    def of(cls, state: WindowState, rows: tuple[int, int]) -> Rollback:
        """The state's rows from ``rows = (node row, connection row)`` and its bookkeeping,
        copied."""
        lo, r0 = rows
        n = state.idarr.n
        book = {k: getattr(state, k) for k in cls.KEPT}
        book['priors'] = list(state.priors)
        return cls(lo, r0, state.T[lo:n].copy(), state.cov.packed[lo:n].copy(),
                   state.frozen[lo:n].copy(), state.status.a[r0:].copy(), book)

    def restore(self, state: WindowState) -> None:
        """Put the copied rows and bookkeeping back (rows added since are not touched)."""
        lo, r0 = self.node_row, self.conn_row
        hi = lo + self.frozen.size
        state.T[lo:hi] = self.T
        state.cov.packed[lo:hi] = self.cov21
        state.frozen[lo:hi] = self.frozen
        state.status.a[r0:r0 + self.status.size] = self.status
        for k, v in self.bookkeeping.items():
            setattr(state, k, v)

    @property
    def nbytes(self) -> int:
        """Bytes of the copied rows."""
        return self.T.nbytes + self.cov21.nbytes + self.frozen.nbytes + self.status.nbytes
