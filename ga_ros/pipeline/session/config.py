"""Settings of an alignment session besides the aligner's."""

from __future__ import annotations

from dataclasses import dataclass

from ga_ros.core.gaps import GapConfig


@dataclass(frozen=True)
class SessionConfig:
    """Settings of the session besides the aligner's.

    Attributes
    ----------
    state_file : ``.npz`` snapshot for save/load and resume on start (``''``: none).
    autosave : journal every accepted measurement and save a snapshot after every update.
    fsync_period_sec : durability of the journal. Every record is written to the OS at once
        (a killed process loses nothing); it is also ``fsync``-ed to disk (a power cut loses
        nothing) after every measurement if 0, else at most every this many seconds.
    gaps : how measurements whose source node is unknown wait and are bridged
        (:class:`~ga_ros.core.gaps.GapConfig`).
    state_required : a state file that cannot be used at start (its directory is a file, is
        read-only, ...) stops the start (:class:`~ga_ros.errors.PersistenceError`) instead of
        running without persistence.
    compact_records : compact the journal at a window update once this many records follow
        its base: the journal is replaced (atomically) by the state then (its *base*) and the few
        records the gap healer needs, so a recovery from the journal alone replays only what
        came after (0: never; the journal then grows with the survey and so does its replay).
    lock_owner : if not empty, :meth:`~ga_ros.pipeline.session.AlignmentSession.resume` takes
        the state file's lock (:class:`~ga_ros.pipeline.journal.lock.StateLock`) under this name
        (the node: its full name) and holds it until ``close``; a state file locked by another
        is then a state file that cannot be used. Empty: no lock (a library caller that owns its
        path).
    """

    state_file: str = ''
    autosave: bool = True
    fsync_period_sec: float = 1.0
    gaps: GapConfig = GapConfig()
    state_required: bool = False
    compact_records: int = 1000
    lock_owner: str = ''
