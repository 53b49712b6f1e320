"""Per-update corrections: the keyframes whose pose moved since a consumer last got it.

A mapping consumer that built its map from earlier poses needs to know which keyframes moved
and where to, not the whole corrected path again. :class:`CorrectionTracker` keeps the pose of
every keyframe as last sent (what a consumer applying every message holds) and, after each
update, returns :class:`Corrections`: the keyframes whose corrected pose differs from the one
sent by more than :class:`CorrectionThresholds` (translation in metres OR rotation in radians),
plus the keyframes added since the previous call. Comparing with the pose last *sent* (not the
previous update's) bounds what a consumer holds: every keyframe within the thresholds of the
corrected path, however many small moves it made; with both thresholds 0 every change is sent
and the consumer holds the corrected path bit for bit.

The first call after :meth:`CorrectionTracker.restart` (a start, a resume, a reset or a
``load_state``), or after the aligner was replaced, returns every keyframe with ``full`` set: a
consumer drops what it held and takes them. ``alignment_node`` and the replay both drive this
one class and :func:`corrections_cdr` (the message's bytes; the convention is in
``docs/node.md``).

Cost: vectorised over the keyframes compared (numpy), never a Python loop over keyframes. With
the track-window aligner the comparison starts at the first row the update could change
(:meth:`~ga_ros.core.window.aligner.TrackWindowAligner.mutable_rows` taken at the previous
call), so it is proportional to the window and the refinement's horizon, not to the survey;
other aligners, several updates between two calls, or a batch refinement compare every row.

ROS-free.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ga_ros import topics
from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.config_ranges import check_ranges, ranged
from ga_ros.core.frames import node_frame
from ga_ros.io.cdr import framed_path_cdr

#: Default translation threshold (m): a keyframe whose position moved more is sent.
TRANSLATION_M = 0.01
#: Default rotation threshold (rad, about 0.06 degree): a keyframe whose attitude turned more is
#: sent (at 50 m range 1 mrad moves a point 5 cm).
ROTATION_RAD = 0.001


@dataclass(frozen=True)
class CorrectionThresholds:
    """When a keyframe counts as moved.

    Attributes
    ----------
    translation_m : a keyframe whose position moved more than this (m, Euclidean) is sent.
    rotation_rad : a keyframe whose orientation turned more than this (rad, angle of
        ``R_sent^T R``) is sent. Both 0: every change, however small, is sent (bit-exact).
    """

    translation_m: float = ranged(TRANSLATION_M, 0.0, 1e6)
    rotation_rad: float = ranged(ROTATION_RAD, 0.0, np.pi)

    def __post_init__(self) -> None:
        check_ranges(self)


@dataclass(frozen=True)
class Corrections:
    """The keyframes to (re)send after one update, in path order.

    Attributes
    ----------
    full : every keyframe is here and a consumer drops what it held before (first message after
        a start, resume, reset or ``load_state``).
    rows : (k,) their rows in the corrected path.
    node_ids, track_ids, stamps_ns : (k,) their ids and stamps (ns).
    T_world_node : (k, 4, 4) their corrected poses in the map frame.
    n_moved : keyframes held before and moved beyond a threshold (0 when ``full``).
    n_added : keyframes new since the previous call (all of them when ``full``).
    n_compared : keyframes whose pose was compared (the cost of the call).
    """

    full: bool
    rows: IntArray
    node_ids: IntArray
    track_ids: IntArray
    stamps_ns: IntArray
    T_world_node: FloatArray
    n_moved: int
    n_added: int
    n_compared: int

    def __len__(self) -> int:
        return int(self.rows.size)


def moved(T_new: FloatArray, T_old: FloatArray, thresholds: CorrectionThresholds) -> BoolArray:
    """(k,) True where pose ``T_new[i]`` differs from ``T_old[i]`` (both ``(k, 4, 4)``) by more
    than a threshold; both thresholds 0: where they differ at all (bitwise).

    The rotation angle is ``2 asin(|R_new - R_old|_F / (2 sqrt 2))`` (exact for rotation
    matrices and accurate at small angles, where ``acos`` of the trace is not).
    """
    differ = np.any(T_new != T_old, axis=(1, 2))
    if thresholds.translation_m == 0 and thresholds.rotation_rad == 0:
        return differ
    dt = np.linalg.norm(T_new[:, :3, 3] - T_old[:, :3, 3], axis=1)
    chord = np.linalg.norm((T_new[:, :3, :3] - T_old[:, :3, :3]).reshape(-1, 9), axis=1)
    dr = 2.0 * np.arcsin(np.minimum(chord / (2.0 * np.sqrt(2.0)), 1.0))
    return differ & ((dt > thresholds.translation_m) | (dr > thresholds.rotation_rad))


class CorrectionTracker:
    """The poses a consumer holds, and the corrections to send after each update (module
    docstring).

    Parameters
    ----------
    thresholds : when a keyframe counts as moved.
    """

    def __init__(self, thresholds: CorrectionThresholds = CorrectionThresholds()) -> None:
        self.thresholds = thresholds
        self._ids = np.zeros(0, dtype=np.int64)
        self._held = np.zeros((0, 4, 4))
        self._n = 0
        self._full_pending = True
        self._aligner_id: int | None = None
        self._n_updates: int | None = None
        self._first_mutable = 0

    def restart(self) -> None:
        """Forget what was sent: the next call returns every keyframe (none after a reset:
        an empty message), ``full`` set."""
        self._n = 0
        self._full_pending = True
        self._aligner_id = None
        self._n_updates = None
        self._first_mutable = 0

    @property
    def n_held(self) -> int:
        """Keyframes a consumer holds (sent so far since the last full message)."""
        return self._n

    def after_update(self, aligner: Any, path: Any | None = None,
                     every_row: bool = False) -> Corrections | None:
        """The corrections after the aligner's latest update(s) (None: nothing moved or was
        added).

        Parameters
        ----------
        aligner : the aligner (track-window or batch); a different aligner object than at the
            previous call (a reset, a ``load_state``) gives a full message.
        path : its ``corrected_path()`` if the caller has it already (saves a copy).
        every_row : compare every row (after a change that is not a window update, such as
            ``refine_batch``, which moves every keyframe).
        """
        path = aligner.corrected_path() if path is None else path
        stats = getattr(aligner, 'stats', None)
        n_updates = getattr(stats, 'n_updates', None)
        if id(aligner) != self._aligner_id:
            self.restart()
        from_row = 0
        if (not every_row and n_updates is not None and self._n_updates is not None
                and int(n_updates) - self._n_updates <= 1):
            from_row = self._first_mutable   # one update since: it changed no row before
        out = self.compare(path, from_row)
        self._aligner_id = id(aligner)
        self._n_updates = None if n_updates is None else int(n_updates)
        rows = getattr(aligner, 'mutable_rows', None)
        self._first_mutable = int(rows()[0]) if rows is not None else 0
        return out

    def compare(self, path: Any, from_row: int = 0) -> Corrections | None:
        """The corrections of ``path`` (``node_ids``, ``track_ids``, ``stamps_ns``,
        ``T_world_node`` in path order, rows append-only) against the poses held, and hold
        them. None: nothing moved or was added.

        Parameters
        ----------
        path : the corrected path (a :class:`~ga_ros.core.window.config.CorrectedPath`).
        from_row : rows before it are known unchanged since the previous call (not compared).
            A path that is shorter than what is held, or whose compared node ids differ, is a
            new one: full message.
        """
        ids = np.asarray(path.node_ids, dtype=np.int64).reshape(-1)
        T = np.asarray(path.T_world_node, dtype=float).reshape(-1, 4, 4)
        n, held = ids.size, self._n
        lo = min(max(int(from_row), 0), held)
        full = (self._full_pending or n < held
                or not np.array_equal(ids[lo:held], self._ids[lo:held]))
        if full:
            rows = np.arange(n, dtype=np.int64)
            n_moved, lo = 0, 0
            n_compared = 0
        else:
            hit = moved(T[lo:held], self._held[lo:held], self.thresholds)
            rows = np.concatenate([lo + np.flatnonzero(hit), np.arange(held, n)]).astype(np.int64)
            n_moved = int(np.count_nonzero(hit))
            n_compared = held - lo
        self._hold(ids, T, rows, n, full)
        if rows.size == 0 and not full:
            return None
        self._full_pending = False
        return Corrections(full, rows, ids[rows], np.asarray(path.track_ids, np.int64)[rows],
                           np.asarray(path.stamps_ns, np.int64)[rows], T[rows], n_moved,
                           n - (0 if full else held), n_compared)

    def _hold(self, ids: IntArray, T: FloatArray, rows: IntArray, n: int, full: bool) -> None:
        """Record the poses sent (``rows`` of ``T``) and the node ids of the new rows (of every
        row when ``full``)."""
        if n > self._ids.size:  # grow by doubling: appending costs O(1) per keyframe
            cap = max(n, 2 * self._ids.size, 64)
            ids_new = np.zeros(cap, dtype=np.int64)
            held_new = np.zeros((cap, 4, 4))
            ids_new[:self._n] = self._ids[:self._n]
            held_new[:self._n] = self._held[:self._n]
            self._ids, self._held = ids_new, held_new
        lo = 0 if full else self._n
        self._ids[lo:n] = ids[lo:n]
        self._held[rows] = T[rows]
        self._n = n


def message_poses(c: Corrections, header_stamp_ns: int) -> tuple[list[str], IntArray, FloatArray]:
    """The poses of the ``nav_msgs/Path`` of ``c`` on ``ga/corrections``, in order:
    ``(frame_ids, stamps_ns, T_world_node)``, one entry per ``PoseStamped``.

    Each keyframe: ``header.frame_id`` its node frame ``ga/<track>/<node>`` (stamps alone are
    not unique: the first two keyframes share one), ``header.stamp`` its stamp, the pose its
    corrected pose in the Path's frame (the map frame). A full message is opened by a marker
    entry (not a keyframe): ``header.frame_id`` :data:`~ga_ros.topics.CORRECTIONS_FULL_FRAME`,
    stamp ``header_stamp_ns``, pose the first keyframe's (the identity if there is none), so a
    display draws no extra segment.
    """
    frames = [node_frame(int(t), int(n)) for t, n in zip(c.track_ids.tolist(),
                                                          c.node_ids.tolist())]
    stamps, T = c.stamps_ns, c.T_world_node
    if c.full:
        frames = [topics.CORRECTIONS_FULL_FRAME] + frames
        stamps = np.concatenate([[int(header_stamp_ns)], stamps]).astype(np.int64)
        T = np.concatenate([T[:1] if len(T) else np.eye(4)[None], T])
    return frames, stamps, T


def corrections_cdr(c: Corrections, frame_id: str, stamp_ns: int) -> bytes:
    """The serialized ``nav_msgs/Path`` of ``c`` on ``ga/corrections`` (CDR, what DDS sends and
    the replay bag stores): header ``frame_id`` (the map frame) at ``stamp_ns`` (the corrected
    path's newest keyframe), poses as :func:`message_poses` lays them out. The node publishes
    these bytes and the replay writes them: the same message by construction."""
    frames, stamps, T = message_poses(c, stamp_ns)
    return framed_path_cdr(T, stamps, frames, frame_id, int(stamp_ns))
