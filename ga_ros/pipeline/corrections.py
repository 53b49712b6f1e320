"""Per-update corrections: what a consumer needs to re-anchor the keyframes that moved.

A mapping consumer that built its map from earlier poses needs to know which keyframes moved
and where to, not the whole corrected path again. A window update moves whole tracks smoothly,
so the message carries only **anchor** keyframes of the correction field and the consumer
interpolates the correction between consecutive anchors (the convention, exactly, is in
``docs/node.md``; :func:`interpolate_correction` is its arithmetic, shared by the tracker and
every consumer):

* the **correction** of a keyframe held at ``T_held`` and now at ``T_new`` is the left
  (``map``-frame) transform ``dT = T_new T_held^-1``: rotation ``R_d = R_new R_held^T`` (as a
  unit quaternion ``q_d``) and translation ``t_d = t_new - R_d t_held``. A track that moves
  rigidly has one constant correction, whatever its shape;
* an entry of the message is a keyframe's new pose. An entry marked **span** (its
  ``header.frame_id`` ends with :data:`~ga_ros.topics.CORRECTIONS_SPAN_SUFFIX`) also re-anchors
  every keyframe the consumer holds whose stamp lies strictly between the previous entry's stamp
  ``s_a`` and its own ``s_b``: with ``f = (s - s_a) / (s_b - s_a)`` (float64 of the integer
  nanosecond differences), ``q = normalise((1 - f) q_a + f q_b')`` (``q_b' = -q_b`` when
  ``q_a . q_b < 0``), ``t = (1 - f) t_a + f t_b``, and the keyframe goes to
  ``R = R(q) R_held``, ``t = R(q) t_held + t``, where ``(q_a, t_a)``, ``(q_b, t_b)`` are the
  corrections of the two anchors (from the poses held before the message);
* keyframes outside every span and not in the message keep their pose.

:class:`CorrectionTracker` keeps what a consumer holds after applying every message (the
interpolated poses, not the true ones; poses after the message's quaternion round trip,
:func:`decoded`) and, after each update, returns :class:`Corrections`: every keyframe whose
corrected pose differs from the held one by more than :class:`CorrectionThresholds`
(translation in metres OR rotation in radians) is re-anchored, as an entry or inside a span,
and every interpolated keyframe lands within the thresholds of its corrected pose; the anchors
are chosen greedily along the path (each span as long as the interpolation keeps its keyframes
within the thresholds). Keyframes added since the previous call are entries. So a consumer
holds every keyframe within the thresholds of the corrected path, however many updates it saw;
with both thresholds 0 every change is an entry (no interpolation is exact) and the consumer
holds the decoded corrected path bit for bit. The two keyframes that share a stamp (the first
two of a survey) are never in a span and are sent together. :class:`HeldPoses` is the consumer's
side: ``map_node``, the replay's map and the tests apply the messages through it.

The first call after :meth:`CorrectionTracker.restart` (a start, a resume, a reset or a
``load_state``), or after the aligner was replaced, returns every keyframe with ``full`` set: a
consumer drops what it held and takes them. ``alignment_node`` and the replay both drive this
one class and :func:`corrections_cdr` (the message's bytes).

Cost: vectorised over the keyframes compared (numpy): every span of up to :data:`WIDTH`
keyframes from every moved row is interpolated at once (one call per length and interior
offset, on slices of the rows); a span of a chain that reaches :data:`WIDTH`
tries longer ones, one call per range of lengths (ranges growing threefold), and the chain
itself is a loop over integers (about 20 ms of CPU per update on the aerial survey's ~1,100
compared keyframes, ``ga-ros bench corrections``). With the track-window aligner the
comparison starts at the first row the update could change
(:meth:`~ga_ros.core.window.aligner.TrackWindowAligner.mutable_rows` taken at the previous
call), so it is proportional to the window and the refinement's horizon, not to the survey;
other aligners, several updates between two calls, or a batch refinement compare every row.

ROS-free.
"""

from __future__ import annotations

import bisect
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from ga_ros import topics
from ga_ros.arrays import BoolArray, FloatArray, IntArray
from ga_ros.core.config_ranges import check_ranges, ranged
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.io.cdr import framed_path_cdr

#: Default translation threshold (m): a keyframe whose position moved more is sent.
TRANSLATION_M = 0.01
#: Longest span (keyframes) the tracker tries from every row at once; longer ones are searched
#: from the rows where a chain of spans needs them.
WIDTH = 6
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
    """The entries of one corrections message, in path order (module docstring).

    Attributes
    ----------
    full : every keyframe is here and a consumer drops what it held before (first message after
        a start, resume, reset or ``load_state``).
    rows : (k,) the entries' rows in the corrected path.
    node_ids, track_ids, stamps_ns : (k,) their ids and stamps (ns).
    T_world_node : (k, 4, 4) their corrected poses in the map frame.
    span : (k,) True where the entry closes a span from the previous entry: the keyframes held
        between the two get the interpolated correction (:func:`interpolate_correction`).
    n_moved : keyframes held before and moved beyond a threshold (0 when ``full``), entries or
        interpolated.
    n_added : keyframes new since the previous call (all of them when ``full``).
    n_compared : keyframes whose pose was compared (the cost of the call).
    n_interpolated : keyframes a consumer re-anchors inside spans (not entries).
    """

    full: bool
    rows: IntArray
    node_ids: IntArray
    track_ids: IntArray
    stamps_ns: IntArray
    T_world_node: FloatArray
    span: BoolArray
    n_moved: int
    n_added: int
    n_compared: int
    n_interpolated: int = 0

    def __len__(self) -> int:
        return int(self.rows.size)

    def message(self) -> CorrectionMessage:
        """What a consumer reads from the serialized message (:func:`corrections_cdr`): the
        entries' poses after the quaternion round trip (:func:`decoded`), marker left out."""
        return CorrectionMessage(self.full, self.stamps_ns.copy(), decoded(self.T_world_node),
                                 self.span.copy())


@dataclass(frozen=True)
class CorrectionMessage:
    """A ``ga/corrections`` message as a consumer reads it (marker left out).

    Attributes
    ----------
    full : it opened with the :data:`~ga_ros.topics.CORRECTIONS_FULL_FRAME` marker.
    stamps_ns : (k,) the entries' keyframe stamps (ns).
    T_map_base : (k, 4, 4) their poses in the map frame.
    span : (k,) the entry closes a span from the previous one (its frame ends with
        :data:`~ga_ros.topics.CORRECTIONS_SPAN_SUFFIX`).
    """

    full: bool
    stamps_ns: IntArray
    T_map_base: FloatArray
    span: BoolArray

    def __post_init__(self) -> None:
        k = np.size(self.stamps_ns)
        T = np.asarray(self.T_map_base)
        if T.shape != (k, 4, 4) or np.size(self.span) != k or not np.all(np.isfinite(T)):
            raise InputError(f'corrections of {k} stamps, {np.size(self.span)} span flags and '
                             f'poses of shape {T.shape}, or a pose that is not finite: message '
                             'dropped')
        if k and bool(np.asarray(self.span)[0]):
            raise InputError('corrections: the first entry closes a span (no entry before it): '
                             'message dropped')

    @staticmethod
    def from_poses(frames: list[str], stamps_ns: IntArray, T_map_base: FloatArray
                   ) -> CorrectionMessage:
        """From the ``PoseStamped`` of the ``Path`` in order: their ``header.frame_id``, stamps
        (ns) and poses (decoded with :func:`ga_ros.geometry.se3.from_pos_quat`).

        Raises
        ------
        InputError
            Shapes that do not match, a pose that is not finite, a span without an entry before.
        """
        T = np.asarray(T_map_base, float).reshape(-1, 4, 4)
        stamps = np.asarray(stamps_ns, np.int64).reshape(-1)
        full = bool(frames) and frames[0] == topics.CORRECTIONS_FULL_FRAME
        if full:
            frames, stamps, T = frames[1:], stamps[1:], T[1:]
        span = np.array([f.endswith(topics.CORRECTIONS_SPAN_SUFFIX) for f in frames], bool)
        return CorrectionMessage(full, stamps, T, span)


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


def decoded(T: FloatArray) -> FloatArray:
    """(k, 4, 4) the poses a consumer reads back from a ``Path`` carrying ``T`` (position and
    unit quaternion, :func:`ga_ros.geometry.se3.to_pos_quat` then
    :func:`~ga_ros.geometry.se3.from_pos_quat`): what the tracker holds for an entry."""
    T = np.asarray(T, float).reshape(-1, 4, 4)
    if not len(T):
        return T.copy()
    return se3.from_pos_quat(*se3.to_pos_quat(T))


# Elementwise arithmetic only (no BLAS, no transcendental functions, no reductions whose order
# could depend on an array's layout): the tracker and a consumer get the same bits from the
# same inputs, so the tracker knows exactly what the consumer holds.

def _mul33(A: FloatArray, B: FloatArray) -> FloatArray:
    """(k, 3, 3) products ``A @ B`` in a fixed order of operations."""
    return (A[:, :, 0, None] * B[:, None, 0, :] + A[:, :, 1, None] * B[:, None, 1, :]
            + A[:, :, 2, None] * B[:, None, 2, :])


def _mul3v(A: FloatArray, v: FloatArray) -> FloatArray:
    """(k, 3) products ``A @ v``."""
    return A[:, :, 0] * v[:, 0, None] + A[:, :, 1] * v[:, 1, None] + A[:, :, 2] * v[:, 2, None]


def _quat(R: FloatArray) -> FloatArray:
    """(k, 4) unit quaternions ``x y z w`` of rotations (k, 3, 3) (Shepperd's pivot)."""
    r00, r11, r22 = R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]
    s21, s02, s10 = R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]
    a01, a02, a12 = R[:, 0, 1] + R[:, 1, 0], R[:, 0, 2] + R[:, 2, 0], R[:, 1, 2] + R[:, 2, 1]
    diag = np.stack([r00 + r11 + r22, r00 - r11 - r22, r11 - r00 - r22, r22 - r00 - r11], 1)
    k = np.argmax(diag, axis=1)
    piv = 1.0 + diag[np.arange(len(k)), k]
    cand = np.stack([np.stack([s21, s02, s10, piv], 1), np.stack([piv, a01, a02, s21], 1),
                     np.stack([a01, piv, a12, s02], 1), np.stack([a02, a12, piv, s10], 1)], 1)
    return _normalised(cand[np.arange(len(k)), k])


def _normalised(q: FloatArray) -> FloatArray:
    n = np.sqrt(q[:, 0] * q[:, 0] + q[:, 1] * q[:, 1] + q[:, 2] * q[:, 2] + q[:, 3] * q[:, 3])
    return q / n[:, None]


def _rotation(q: FloatArray) -> FloatArray:
    """(k, 3, 3) rotations of unit quaternions ``x y z w``."""
    x, y, z, w = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, xw, yw, zw = x * y, x * z, y * z, x * w, y * w, z * w
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0], R[:, 0, 1], R[:, 0, 2] = 1.0 - 2.0 * (yy + zz), 2.0 * (xy - zw), 2.0 * (xz + yw)
    R[:, 1, 0], R[:, 1, 1], R[:, 1, 2] = 2.0 * (xy + zw), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - xw)
    R[:, 2, 0], R[:, 2, 1], R[:, 2, 2] = 2.0 * (xz - yw), 2.0 * (yz + xw), 1.0 - 2.0 * (xx + yy)
    return R


def correction(T_new: FloatArray, T_held: FloatArray) -> tuple[FloatArray, FloatArray]:
    """The left corrections ``dT = T_new T_held^-1`` of keyframes held at ``T_held`` and now at
    ``T_new`` ((k, 4, 4) in ``map``): the rotation ``R_d = R_new R_held^T`` as unit quaternions
    (k, 4) ``x y z w`` and the translation ``t_new - R_d t_held`` (k, 3) (m)."""
    Rd = _mul33(T_new[:, :3, :3], np.swapaxes(T_held[:, :3, :3], 1, 2))
    return _quat(Rd), T_new[:, :3, 3] - _mul3v(Rd, T_held[:, :3, 3])


def span_fraction(stamps_ns: IntArray, s_a: IntArray, s_b: IntArray) -> FloatArray:
    """(k,) ``f = (s - s_a) / (s_b - s_a)`` of keyframes stamped ``stamps_ns`` inside spans
    from ``s_a`` to ``s_b`` (ns, per keyframe or one for all): float64 of the integer
    differences."""
    s = np.asarray(stamps_ns, np.int64)
    return ((s - np.asarray(s_a, np.int64)).astype(np.float64)
            / (np.asarray(s_b, np.int64) - np.asarray(s_a, np.int64)).astype(np.float64))


def interpolate_correction(q_a: FloatArray, t_a: FloatArray, q_b: FloatArray, t_b: FloatArray,
                           f: FloatArray, T_held: FloatArray) -> FloatArray:
    """The new poses (k, 4, 4) of keyframes held at ``T_held`` (k, 4, 4) inside spans whose
    anchors have the corrections ``(q_a, t_a)``, ``(q_b, t_b)`` (:func:`correction`; (k, 4) and
    (k, 3) per keyframe, or one of each for all) at fractions ``f`` (k,) (:func:`span_fraction`):
    ``q = normalise((1 - f) q_a + f q_b)`` (``q_b`` negated where ``q_a . q_b < 0``), ``t = (1 -
    f) t_a + f t_b``, new pose ``R(q) R_held``, ``R(q) t_held + t``. The one definition of the
    convention: the tracker and every consumer call it."""
    T_held = np.asarray(T_held, float).reshape(-1, 4, 4)
    q_a, q_b = np.reshape(q_a, (-1, 4)), np.reshape(q_b, (-1, 4))
    t_a, t_b = np.reshape(t_a, (-1, 3)), np.reshape(t_b, (-1, 3))
    dot = q_a[:, 0] * q_b[:, 0] + q_a[:, 1] * q_b[:, 1] + q_a[:, 2] * q_b[:, 2] \
        + q_a[:, 3] * q_b[:, 3]
    q_b = np.where((dot < 0)[:, None], -q_b, q_b)
    f = np.asarray(f, np.float64).reshape(-1, 1)
    g = 1.0 - f
    R = _rotation(_normalised(g * q_a + f * q_b))
    out = np.zeros_like(T_held)
    out[:, :3, :3] = _mul33(R, T_held[:, :3, :3])
    out[:, :3, 3] = _mul3v(R, T_held[:, :3, 3]) + (g * t_a + f * t_b)
    out[:, 3, 3] = 1.0
    return out


def _span_rows(a: IntArray, b: IntArray) -> tuple[IntArray, IntArray]:
    """For spans from row ``a[j]`` to ``b[j]``: ``(j, i)`` of every interior row ``a < i < b``,
    in order."""
    counts = np.maximum(np.asarray(b) - np.asarray(a) - 1, 0)
    j = np.repeat(np.arange(counts.size), counts)
    start = np.cumsum(counts) - counts
    return j, np.asarray(a)[j] + 1 + (np.arange(j.size) - start[j])


class CorrectionTracker:
    """The poses a consumer holds, and the corrections to send after each update (module
    docstring).

    Parameters
    ----------
    thresholds : when a keyframe counts as moved; also how far an interpolated keyframe may be
        from its corrected pose.
    """

    def __init__(self, thresholds: CorrectionThresholds = CorrectionThresholds()) -> None:
        self.thresholds = thresholds
        self._ids = np.zeros(0, dtype=np.int64)
        self._stamps = np.zeros(0, dtype=np.int64)
        self._held = np.zeros((0, 4, 4))
        self._n = 0
        self._sorted = True
        self._full_pending = True
        self._aligner: Callable[[], Any] = _nothing
        self._n_updates: int | None = None
        self._first_mutable = 0

    def restart(self) -> None:
        """Forget what was sent: the next call returns every keyframe (none after a reset:
        an empty message), ``full`` set."""
        self._n = 0
        self._sorted = True
        self._full_pending = True
        self._aligner = _nothing
        self._n_updates = None
        self._first_mutable = 0

    @property
    def n_held(self) -> int:
        """Keyframes a consumer holds (sent so far since the last full message)."""
        return self._n

    def held(self) -> FloatArray:
        """(n, 4, 4) the poses a consumer that applied every message holds, in path order."""
        return self._held[:self._n].copy()

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
        if self._aligner() is not aligner:   # (a weak reference: an id could be reused)
            self.restart()
        from_row = 0
        if (not every_row and n_updates is not None and self._n_updates is not None
                and int(n_updates) - self._n_updates <= 1):
            from_row = self._first_mutable   # one update since: it changed no row before
        out = self.compare(path, from_row)
        self._aligner = _reference(aligner)
        self._n_updates = None if n_updates is None else int(n_updates)
        rows = getattr(aligner, 'mutable_rows', None)
        self._first_mutable = int(rows()[0]) if rows is not None else 0
        return out

    def compare(self, path: Any, from_row: int = 0) -> Corrections | None:
        """The corrections of ``path`` (``node_ids``, ``track_ids``, ``stamps_ns``,
        ``T_world_node`` in path order, rows append-only) against the poses held, and hold
        what a consumer holds after applying them. None: nothing moved or was added.

        Parameters
        ----------
        path : the corrected path (a :class:`~ga_ros.core.window.config.CorrectedPath`).
        from_row : rows before it are known unchanged since the previous call (not compared).
            A path that is shorter than what is held, or whose compared node ids differ, is a
            new one: full message.
        """
        ids = np.asarray(path.node_ids, dtype=np.int64).reshape(-1)
        stamps = np.asarray(path.stamps_ns, dtype=np.int64).reshape(-1)
        T = np.asarray(path.T_world_node, dtype=float).reshape(-1, 4, 4)
        n, held = ids.size, self._n
        lo = min(max(int(from_row), 0), held)
        full = (self._full_pending or n < held
                or not np.array_equal(ids[lo:held], self._ids[lo:held]))
        self._grow(n)
        if full:
            held = lo = 0
            self._sorted = True
        entries = np.zeros(0, np.int64)
        span = np.zeros(0, bool)
        n_moved = n_interp = 0
        if held > lo:
            Tq = decoded(T[lo:held])
            hit = moved(Tq, self._held[lo:held], self.thresholds)
            n_moved = int(np.count_nonzero(hit))
            if n_moved:
                entries, span, n_interp = self._anchor(lo, held, Tq, hit)
        new = np.arange(held, n, dtype=np.int64)
        if new.size and held and stamps[held] == stamps[held - 1] and (
                entries.size == 0 or entries[-1] != held - 1):
            # the first new keyframe shares its stamp with the last held: name both (module
            # docstring)
            self._held[held - 1] = decoded(T[held - 1:held])[0]
            entries = np.append(entries, held - 1)
            span = np.append(span, False)
        if new.size:   # the new keyframes: entries, held as decoded
            self._held[held:n] = decoded(T[held:n])
            self._ids[held:n] = ids[held:n]
            prev = self._stamps[held - 1:held]
            self._stamps[held:n] = stamps[held:n]
            self._sorted = bool(self._sorted and np.all(np.diff(np.concatenate(
                [prev, stamps[held:n]])) >= 0))
        self._n = n
        rows = np.concatenate([entries, new])
        span = np.concatenate([span, np.zeros(new.size, bool)])
        if rows.size == 0 and not full:
            return None
        self._full_pending = False
        return Corrections(full, rows, ids[rows], np.asarray(path.track_ids, np.int64)[rows],
                           stamps[rows], T[rows], span, n_moved, n - held, held - lo, n_interp)

    def _grow(self, n: int) -> None:
        """Room for ``n`` rows (doubling: appending costs O(1) per keyframe)."""
        if n <= self._ids.size:
            return
        cap = max(n, 2 * self._ids.size, 64)
        ids, stamps, held = np.zeros(cap, np.int64), np.zeros(cap, np.int64), np.zeros((cap, 4, 4))
        ids[:self._n], stamps[:self._n] = self._ids[:self._n], self._stamps[:self._n]
        held[:self._n] = self._held[:self._n]
        self._ids, self._stamps, self._held = ids, stamps, held

    def _anchor(self, lo: int, hi: int, Tq: FloatArray, hit: BoolArray
                ) -> tuple[IntArray, BoolArray, int]:
        """Choose the entries that re-anchor the moved rows of ``lo:hi`` (``Tq``: their
        decoded corrected poses, ``hit``: moved) and hold the result; returns the entries'
        rows, their span flags and the keyframes interpolated.

        Greedy along the path: a chain of spans starts at a moved row and each span reaches as
        far as its interior stays within the thresholds (spans of up to :data:`WIDTH` rows
        are tried from every row at once, longer ones searched where a chain needs them); a
        chain ends where the next moved row is out of reach, and the next starts there."""
        H = self._held
        old = H[lo:hi].copy()   # the poses held before this message (the spans' reference)
        st = self._stamps[lo:hi]
        # rows sharing a stamp with a neighbour (the first two of a survey): never in a span;
        # one of a pair sent within lo:hi sends the other
        ext = self._stamps[max(lo - 1, 0):min(hi + 1, self._n)]
        off = 1 if lo > 0 else 0
        eq = ext[1:] == ext[:-1]
        pinned = np.zeros(hi - lo, bool)
        for shift in (0, 1):
            r = np.flatnonzero(eq) + shift - off
            pinned[r[(r >= 0) & (r < hi - lo)]] = True
        same = np.flatnonzero(st[1:] == st[:-1])
        need = hit.copy()
        pair = need[same] | need[same + 1]
        need[same[pair]] = need[same[pair] + 1] = True
        moved_rows = np.flatnonzero(need)
        spans = (self._sorted and moved_rows.size > 1
                 and (self.thresholds.translation_m > 0 or self.thresholds.rotation_rad > 0))
        entries: list[int] = []
        flags: list[bool] = []
        n_interp = 0
        if spans:
            q, t = correction(Tq, old)
            cum_pinned = np.concatenate([[0], np.cumsum(pinned)])
            # moved() without its square roots and arcsine: distance and chord squared against
            # the thresholds' (the chord of an angle r is 2 sqrt 2 sin(r / 2))
            dt2 = self.thresholds.translation_m ** 2
            ch2 = 8.0 * np.sin(min(self.thresholds.rotation_rad, np.pi) / 2.0) ** 2

        def beyond(P: FloatArray, T: FloatArray) -> BoolArray:
            d = P[:, :3, 3] - T[:, :3, 3]
            R = (P[:, :3, :3] - T[:, :3, :3]).reshape(-1, 9)
            return (np.einsum('ij,ij->i', d, d) > dt2) | (np.einsum('ij,ij->i', R, R) > ch2)

        def spans_from(a0: IntArray, b0: IntArray) -> tuple[BoolArray, IntArray, FloatArray]:
            """For spans from ``a0[j]`` to ``b0[j]``: whether each keeps its interior within
            the thresholds and touches no pinned row, where its interior starts in the poses,
            and the interior's new poses."""
            j, i = _span_rows(a0, b0)
            P = interpolate_correction(q[a0[j]], t[a0[j]], q[b0[j]], t[b0[j]],
                                       span_fraction(st[i], st[a0[j]], st[b0[j]]), old[i])
            bad = np.bincount(j, beyond(P, Tq[i]), a0.size) > 0
            bad |= cum_pinned[b0 + 1] > cum_pinned[a0]
            return ~bad, np.cumsum(b0 - a0 - 1) - (b0 - a0 - 1), P

        if spans:   # every span of up to WIDTH rows from every row of the moved range at once
            # (ending at or before the last moved row r1): for each length e and interior
            # offset d, the rows a + d of every span (a, a + e) are one slice, so the table
            # is 2 + 3 + ... + WIDTH - 1 calls on slices, without gathering rows
            r0, r1 = int(moved_rows[0]), int(moved_rows[-1])
            good = np.zeros((r1 - r0, WIDTH - 1), bool)
            table_P: dict[tuple[int, int], FloatArray] = {}
            for e in range(2, WIDTH + 1):
                n_e = r1 - e - r0 + 1          # spans from a = r0 .. r1 - e
                if n_e <= 0:
                    break
                A, B = slice(r0, r0 + n_e), slice(r0 + e, r0 + e + n_e)
                bad = cum_pinned[r0 + e + 1:r0 + e + 1 + n_e] > cum_pinned[r0:r0 + n_e]
                for d in range(1, e):
                    D = slice(r0 + d, r0 + d + n_e)
                    P = interpolate_correction(q[A], t[A], q[B], t[B],
                                               span_fraction(st[D], st[A], st[B]), old[D])
                    bad |= beyond(P, Tq[D])
                    table_P[e, d] = P
                good[:n_e, e - 2] = ~bad
            # per row, the farthest good end of the table (its index in 2 .. WIDTH; -1: none)
            best = np.where(good.any(1), good.shape[1] - 1 - np.argmax(good[:, ::-1], axis=1),
                            -1).tolist()
        # the next moved row after each row of the moved range (integers: the chain below is a
        # plain loop, its cost a few operations per anchor)
        moved_list = moved_rows.tolist()
        nxt = np.full(hi - lo + 1, -1, np.int64)
        if moved_rows.size:
            r = np.arange(hi - lo)
            k_next = np.searchsorted(moved_rows, r, side='right')
            nxt[:hi - lo] = np.where(k_next < moved_rows.size,
                                     moved_rows[np.minimum(k_next, moved_rows.size - 1)], -1)
        nxt = nxt.tolist()
        n_ends = WIDTH - 1

        def reach(a: int, last: int) -> tuple[int, FloatArray | None]:
            """The farthest end ``b <= last`` of a span from ``a`` whose interior lands within
            the thresholds, and the interior's new poses (None: no span reaches ``a + 2``)."""
            j = best[a - r0]
            if j < 0:
                return a + 1, None
            b = a + 2 + j
            P = np.stack([table_P[b - a, d][a - r0] for d in range(1, b - a)])
            lo_d, hi_d = WIDTH + 1, 3 * WIDTH
            while j == n_ends - 1 and a + lo_d <= last:
                # every span of the table is good: try longer ones, only the new ends
                b0 = np.arange(a + lo_d, min(a + hi_d, last) + 1)
                good, at0, P0 = spans_from(np.full(b0.size, a), b0)
                ok2 = np.flatnonzero(good)
                if ok2.size:
                    b = int(b0[ok2[-1]])
                    P = P0[at0[ok2[-1]]:at0[ok2[-1]] + b - a - 1]
                if not good.all():
                    break
                lo_d, hi_d = hi_d + 1, 3 * hi_d
            return b, P

        k = 0
        while k < len(moved_list):
            a = moved_list[k]
            entries.append(a)
            flags.append(False)
            H[lo + a] = Tq[a]
            while spans and not pinned[a]:    # extend the chain of spans from a
                if nxt[a] < 0:
                    break                     # no moved row after a
                b, P = reach(a, r1)
                if P is None or b < nxt[a]:
                    break                     # the next moved row starts a new chain
                H[lo + a + 1:lo + b] = P
                H[lo + b] = Tq[b]
                n_interp += b - a - 1
                entries.append(b)
                flags.append(True)
                a = b
            k = bisect.bisect_right(moved_list, a)
        return lo + np.asarray(entries, np.int64), np.asarray(flags, bool), n_interp


class HeldPoses:
    """A consumer's side of ``ga/corrections``: the pose it holds for each keyframe, by stamp,
    and :meth:`apply` of a message (the convention of the module docstring, through
    :func:`interpolate_correction`). ``map_node``'s maps and the replay's map take the poses it
    returns.

    Keyframes are kept sorted by stamp; two keyframes may share a stamp (the first two of a
    survey): a message names such a stamp twice (the first is the keyframe before); named once,
    it is the later keyframe's.
    """

    def __init__(self) -> None:
        self.stamps_ns = np.zeros(0, np.int64)
        self.T_map_base = np.zeros((0, 4, 4))

    def __len__(self) -> int:
        return int(self.stamps_ns.size)

    def clear(self) -> None:
        """Hold nothing (what a full message starts with)."""
        self.stamps_ns = np.zeros(0, np.int64)
        self.T_map_base = np.zeros((0, 4, 4))

    def set_poses(self, stamps_ns: IntArray, T_map_base: FloatArray) -> None:
        """Hold exactly these poses (every keyframe: a corrected path taken before the first
        corrections message)."""
        stamps = np.asarray(stamps_ns, np.int64).reshape(-1)
        T = np.asarray(T_map_base, float).reshape(-1, 4, 4)
        order = np.argsort(stamps, kind='stable')
        self.stamps_ns, self.T_map_base = stamps[order], T[order].copy()

    def apply(self, msg: CorrectionMessage) -> tuple[IntArray, FloatArray]:
        """Take a message; returns the stamps (ns, sorted; a shared stamp twice) and new poses
        ``T_map_base`` of every keyframe whose pose it set: its entries and the keyframes held
        inside its spans.

        Raises
        ------
        InputError
            A span whose anchors are not both held, or whose stamps do not increase: nothing is
            changed.
        """
        S, H = self.stamps_ns, self.T_map_base
        if msg.full:   # drop what is held (on success only)
            S, H = np.zeros(0, np.int64), np.zeros((0, 4, 4))
        E = np.asarray(msg.stamps_ns, np.int64).reshape(-1)
        left, right = np.searchsorted(S, E, 'left'), np.searchsorted(S, E, 'right')
        idx = np.where(right > left, right - 1, -1)
        uniq, counts = np.unique(E, return_counts=True)
        for s in uniq[counts > 1].tolist():   # a shared stamp named twice: in order
            named = np.flatnonzero(E == s)
            j = np.arange(named.size)
            idx[named] = np.where(left[named] + j < right[named], left[named] + j, -1)
        changed = np.zeros(S.size, bool)
        newT = H.copy()
        k = np.flatnonzero(msg.span)
        if k.size:
            a, b = idx[k - 1], idx[k]
            if np.any(a < 0) or np.any(b < 0) or np.any(E[k] <= E[k - 1]):
                raise InputError('corrections: a span whose anchors are not both held or whose '
                                 'stamps do not increase: message dropped')
            i0, i1 = np.searchsorted(S, E[k - 1], 'right'), np.searchsorted(S, E[k], 'left')
            j, i = _span_rows(i0 - 1, i1)
            q, t = correction(np.concatenate([msg.T_map_base[k - 1], msg.T_map_base[k]]),
                              np.concatenate([H[a], H[b]]))
            m = k.size
            newT[i] = interpolate_correction(q[j], t[j], q[m + j], t[m + j],
                                             span_fraction(S[i], E[k - 1][j], E[k][j]), H[i])
            changed[i] = True
        held = idx >= 0
        newT[idx[held]] = msg.T_map_base[held]
        changed[idx[held]] = True
        fresh = np.flatnonzero(~held)
        if fresh.size:
            at = np.searchsorted(S, E[fresh], 'right')
            S = np.insert(S, at, E[fresh])
            newT = np.insert(newT, at, msg.T_map_base[fresh], axis=0)
            changed = np.insert(changed, at, True)
        self.stamps_ns, self.T_map_base = S, newT
        return S[changed], newT[changed]


def message_poses(c: Corrections, frame_id: str, header_stamp_ns: int
                  ) -> tuple[list[str], IntArray, FloatArray]:
    """The poses of the ``nav_msgs/Path`` of ``c`` on ``ga/corrections`` (in ``frame_id``, the
    map frame), in order: ``(frame_ids, stamps_ns, T_world_node)``, one entry per
    ``PoseStamped``.

    Each entry: ``header.frame_id`` the map frame ``frame_id`` (as every pose of
    ``ga/corrected_path``), followed by :data:`~ga_ros.topics.CORRECTIONS_SPAN_SUFFIX` when it
    closes a span; ``header.stamp`` its keyframe's stamp (what names it: the two keyframes that
    share a stamp are named together, the first is the keyframe before); the pose its corrected
    pose in the map frame. No node ids: with a map frame of up to three characters (``map``) an
    entry is 72 bytes of CDR (stamp, frame, padding, seven doubles), as a pose of the whole
    path, and a span's 80. A full
    message is opened by a marker entry (not a keyframe): ``header.frame_id``
    :data:`~ga_ros.topics.CORRECTIONS_FULL_FRAME`, stamp ``header_stamp_ns``, pose the first
    keyframe's (the identity if there is none), so a display draws no extra segment.
    """
    span_frame = frame_id + topics.CORRECTIONS_SPAN_SUFFIX
    frames = [span_frame if s else frame_id for s in c.span.tolist()]
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
    frames, stamps, T = message_poses(c, frame_id, stamp_ns)
    return framed_path_cdr(T, stamps, frames, frame_id, int(stamp_ns))


def _nothing() -> None:
    """The aligner of a tracker that has seen none."""
    return None


def _reference(obj: Any) -> Callable[[], Any]:
    """A weak reference to ``obj`` (a strong one for an object that cannot have weak ones)."""
    try:
        return weakref.ref(obj)
    except TypeError:
        return lambda: obj
