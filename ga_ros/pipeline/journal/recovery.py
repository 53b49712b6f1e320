"""Crash recovery: the state rebuilt from a snapshot and the journal records after it
(:func:`recover`), and the held queue of the gap healer restored from the journal."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import KINDS, Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import (
    is_state_file,
    load_state,
    load_state_bytes,
    save_state,
)
from ga_ros.errors import ForeignFileError, FormatError, GaError, InputError
from ga_ros.pipeline.journal.layout import Layout, compacted_header
from ga_ros.pipeline.journal.records import (
    KIND_MASK,
    RECORD_V1,
    Datum,
    Entry,
    MapOdom,
    TrackEnd,
    dropped_records,
    held_records,
    is_event,
    last_datum,
    last_map_odom_entry,
    records_to_entries,
    records_to_measurements,
    reversed_records,
)
from ga_ros.pipeline.journal.scan import JournalScan, scan_journal
from ga_ros.pipeline.journal.state_files import (
    has_v2_header,
    journal_path,
    read_snapshot_info,
    rewrite_journal,
)
from ga_ros.safe_write import check_regular, move_aside


@dataclass
class HeldQueue:
    """The held measurements of a journal that no later record admitted.

    Attributes
    ----------
    held : ``(measurement, arrival number)`` in order.
    arrivals : measurements held or taken on arrival (the healer's arrival count).
    newest_stamp_ns : the newest stamp of those arrivals.
    """

    held: list[tuple[Measurement, int]] = field(default_factory=list)
    arrivals: int = 0
    newest_stamp_ns: int = -2**63


def held_queue(recs: np.ndarray, arrivals: int = 0, newest_stamp_ns: int = -2**63
               ) -> HeldQueue:
    """The held queue to restore after a restart: the held records that no later record
    admitted (matched by nodes and stamp), with their arrival numbers (counted on from
    ``arrivals``, the newest stamp from ``newest_stamp_ns``: a compacted journal's)."""
    held, dropped = held_records(recs), dropped_records(recs)
    bridge = (recs['kind'] & KIND_MASK) == KINDS.index('bridge')
    src, dst, stamp = (recs[f].tolist() for f in ('src_id', 'dst_id', 'stamp_ns'))
    pending: dict[tuple[int, int, int], list[int]] = {}
    seq: dict[int, int] = {}
    out = HeldQueue(arrivals=int(arrivals), newest_stamp_ns=int(newest_stamp_ns))
    for k in range(len(held)):
        key = (src[k], dst[k], stamp[k])
        if bridge[k]:
            continue
        if held[k]:
            pending.setdefault(key, []).append(k)
        else:
            done = pending.get(key)
            if done:  # a held measurement taken or dropped later: not an arrival
                seq.pop(done.pop(0))
                continue
            if dropped[k]:  # its held record is before the journal's base
                continue
        out.arrivals += 1
        out.newest_stamp_ns = max(out.newest_stamp_ns, stamp[k])
        if held[k]:
            seq[k] = out.arrivals
    rows = sorted(seq)
    ms = records_to_measurements(recs[np.array(rows, dtype=np.int64)])
    out.held = [(m, seq[k]) for m, k in zip(ms, rows)]
    return out


@dataclass
class RecoveryResult:
    """What :func:`recover` restored.

    Attributes
    ----------
    aligner : the restored aligner (empty if there was nothing to restore).
    source : ``'snapshot'``, ``'snapshot+journal'``, ``'journal'`` or ``'empty'``.
    snapshot_records : journal records the snapshot contained (0 without a snapshot; from the
        journal alone: the records its base holds).
    records_replayed : journal entries (measurements, fixes) replayed after the snapshot and
        accepted.
    records_rejected : replayed entries the aligner rejected (e.g. already in the snapshot).
    journal_records : records in the journal now (the count the next snapshot must store).
    moved_aside : damaged files renamed to ``<name>.corrupt-<time>`` (kept, never deleted).
    messages : one line per event, for the log (warnings when anything was damaged).
    seconds : wall time of the recovery.
    held : the held measurements of the journal that were never admitted (the held queue of
        :class:`~ga_ros.core.gaps.GapHealer` to restore).
    bridges : ``(from_id, to_id)`` of every bridge in the journal.
    reversed : the measurements (as they arrived) that the aligner took reversed.
    snapshot_refused : the state file is not a ga_ros state but a journal with intact records
        is beside it: the state was rebuilt from the journal, the file left untouched, and no
        snapshot may be written there.
    datum : the map frame's datum ``(lat_deg, lon_deg, alt_m)`` of the journal's last datum
        record (``None`` without one).
    map_odom_entry : the journal's last ``map -> odom`` record (:class:`MapOdom`: the
        correction the session sent after its last window update, with the newest node then
        and its pose; ``None`` without one); :attr:`map_odom` its ``T_map_odom``.
    """

    aligner: TrackWindowAligner
    source: str
    snapshot_records: int = 0
    records_replayed: int = 0
    records_rejected: int = 0
    journal_records: int = 0
    moved_aside: list[Path] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)
    seconds: float = 0.0
    held: HeldQueue = field(default_factory=HeldQueue)
    bridges: list[tuple[int, int]] = field(default_factory=list)
    reversed: list[Measurement] = field(default_factory=list)
    snapshot_refused: bool = False
    datum: tuple[float, float, float] | None = None
    map_odom_entry: MapOdom | None = None

    @property
    def map_odom(self) -> FloatArray | None:
        """(4, 4) ``T_map_odom`` of :attr:`map_odom_entry` (``None`` without one)."""
        return None if self.map_odom_entry is None else self.map_odom_entry.T_map_odom


def recover(state_file: str | os.PathLike, config: AlignerConfig | None = None,
            checkpoint: bool = True) -> RecoveryResult:
    """Rebuild the aligner from ``state_file`` and its journal, keeping every intact record.

    Parameters
    ----------
    state_file : the snapshot path (its journal is ``<state_file>.journal``).
    config : aligner settings for a state rebuilt from the journal alone, and for the snapshot
        (default: the snapshot's own, else :class:`AlignerConfig` defaults).
    checkpoint : after replaying records or repairing a file, write a fresh snapshot holding
        the journal's record count, so snapshot and journal agree again.

    Raises
    ------
    ForeignFileError : ``state_file`` exists, is not a ga_ros state (left untouched) and no
        journal with intact records is beside it (with one, the state is rebuilt from the
        journal alone: ``snapshot_refused``).
    UnsafePathError : ``state_file`` or the journal is a symbolic link or not a regular file.

    Damaged files are moved aside (never deleted) and reported in ``messages``; a damaged
    journal never discards an intact snapshot, nor a damaged snapshot an intact journal.
    """
    t0 = time.perf_counter()
    state, jpath = Path(state_file), journal_path(state_file)
    out = RecoveryResult(TrackWindowAligner(config or AlignerConfig()), 'empty')
    check_regular(jpath)
    aligner, snap_records, foreign = _load_snapshot(state, jpath, config, out)
    scan = _scan_and_repair(jpath, out)
    records, lay = scan.records, scan.layout
    ctx = min(lay.n_context, int(records.size))
    out.journal_records = lay.start + int(records.size) - ctx
    base = None
    if lay.has_base and (aligner is None or snap_records < lay.start):
        base = _load_base(scan, jpath, config, out)
    if base is not None:  # the journal alone (its base, then the records after it)
        if aligner is not None:
            out.messages.append(f'the snapshot holds {snap_records} journal records, the '
                                f"journal's base {lay.start}: the base is used")
            aligner.close()
        aligner, out.source, tail = base, 'journal', records[ctx:]
        out.snapshot_records = lay.start
    elif aligner is not None:
        out.source, out.snapshot_records = 'snapshot', int(snap_records)
        if scan.damaged:
            # the numbering of the records changed: replay every intact one; those already in
            # the snapshot are rejected (duplicate, frozen) and change nothing
            tail = records[ctx:]
        else:
            if snap_records > out.journal_records:
                out.messages.append(f'the snapshot holds {snap_records} journal records, the '
                                    f'journal only {out.journal_records}: the snapshot is kept')
            tail = records[ctx + max(min(snap_records, out.journal_records) - lay.start, 0):]
    else:
        aligner = out.aligner
        tail = records[ctx:]
        out.source = 'journal' if tail.size else 'empty'
        if lay.has_base:
            out.messages.append(f"{jpath}: no snapshot and the journal's base is unusable: "
                                f'only the {tail.size} records after it are replayed')
    measurements = records[~is_event(records['kind'])]
    out.held = held_queue(measurements, lay.arrivals, lay.newest_stamp_ns)
    bridge = records['kind'] & KIND_MASK == KINDS.index('bridge')
    out.bridges = list(zip(records['src_id'][bridge].tolist(),
                           records['dst_id'][bridge].tolist()))
    out.reversed = reversed_records(records)
    out.datum = last_datum(records)
    out.map_odom_entry = last_map_odom_entry(records)
    # held (or dropped) measurements never reached the aligner
    tail = tail[~held_records(tail) & ~dropped_records(tail)]
    if tail.size:
        out.records_replayed, out.records_rejected = replay_entries(
            aligner, records_to_entries(tail, taken=True))
        if out.source == 'snapshot':
            out.source = 'snapshot+journal'
    out.aligner = aligner
    changed = bool(tail.size or out.moved_aside or snap_records != out.journal_records)
    if (checkpoint and changed or scan.damaged) and out.source != 'empty' and not foreign:
        try:
            save_state(aligner, state, journal_records=out.journal_records)
        except OSError as exc:  # e.g. a full disk: the journal still holds every record
            out.messages.append(f'recovery snapshot {state} not written ({exc}); the journal '
                                'still holds every record')
    out.seconds = time.perf_counter() - t0
    return out


def _load_base(scan: JournalScan, jpath: Path, config: AlignerConfig | None,
               out: RecoveryResult) -> TrackWindowAligner | None:
    """The aligner of a compacted journal's base (``None`` if it is damaged: a message)."""
    if scan.base is None:
        return None
    try:
        return load_state_bytes(scan.base, config, f'{jpath} (base)').aligner
    except GaError as exc:
        out.messages.append(f"{jpath}: the journal's base cannot be used ({exc})")
        return None


def check_state_path(state_file: str | os.PathLike) -> None:
    """Refuse, without writing anything, a state path that :func:`recover` would refuse: a
    symbolic link (state file or journal) or a foreign file with no journal of intact records
    beside it (what is checked before a lock file is made beside it).

    Raises
    ------
    UnsafePathError, ForeignFileError
        As :func:`recover`.
    """
    state, jpath = Path(state_file), journal_path(state_file)
    check_regular(jpath)
    if (check_regular(state) and os.lstat(state).st_size > 0 and not is_state_file(state)
            and not _journal_has_records(jpath)):
        raise ForeignFileError(f'state_file {state} exists and is not a ga_ros state; it is '
                               'left untouched: choose another state_file')


def _load_snapshot(state: Path, jpath: Path, config: AlignerConfig | None,
                   out: RecoveryResult) -> tuple[TrackWindowAligner | None, int, bool]:
    """The snapshot's aligner and the journal records it holds (``None, 0`` without a usable
    snapshot: a damaged one is moved aside), and whether ``state`` is a foreign file (refused,
    left untouched: ``out.snapshot_refused``). Events go to ``out``'s messages.

    Raises
    ------
    ForeignFileError
        ``state`` is a foreign file and no journal with intact records is beside it.
    """
    foreign = check_regular(state) and os.lstat(state).st_size > 0 and not is_state_file(state)
    if foreign:
        if not _journal_has_records(jpath):
            raise ForeignFileError(f'state_file {state} exists and is not a ga_ros state; it is '
                                   'left untouched: choose another state_file')
        out.snapshot_refused = True
        out.messages.append(f'state_file {state} is not a ga_ros state (a damaged snapshot or '
                            'another program file): it is left untouched, the state is '
                            'rebuilt from the journal alone, and no snapshot is written there '
                            'until it is removed')
    elif check_regular(state):  # an empty file too: a damaged snapshot, moved aside
        try:
            saved = load_state(state, config)
            return saved.aligner, (saved.journal_records if saved.journal_records is not None
                                   else read_snapshot_info(state)), False
        except InputError as exc:
            out.moved_aside.append(move_aside(state))
            out.messages.append(f'snapshot {state} is damaged ({exc}); moved aside to '
                                f'{out.moved_aside[-1].name}, rebuilding from the journal')
    return None, 0, foreign


def _scan_and_repair(jpath: Path, out: RecoveryResult) -> JournalScan:
    """The journal's intact records; a damaged journal is moved aside and a version-2 journal
    of the intact records takes its place (a version-1 one is converted). Events go to
    ``out``."""
    try:
        scan = scan_journal(jpath)
    except FormatError as exc:
        scan = JournalScan(np.zeros(0, RECORD_V1), n_damaged=1, header_ok=False,
                           messages=[str(exc)])
    out.messages += scan.messages
    if scan.damaged or (check_regular(jpath) and os.lstat(jpath).st_size
                        and not has_v2_header(jpath)):
        if scan.damaged:
            out.moved_aside.append(move_aside(jpath))
            out.messages.append(f'journal {jpath} moved aside to {out.moved_aside[-1].name}; '
                                f'{scan.records.size} intact records kept')
        lay = scan.layout
        if scan.base is not None:  # the base stays ahead of the records
            head = [compacted_header(lay.start, lay.n_context, lay.arrivals, lay.newest_stamp_ns,
                                     lay.base_len, lay.base_crc), scan.base]
        else:
            head = None
            scan.layout = Layout()
        rewrite_journal(jpath, scan.records, head)
    return scan


def replay_entries(aligner: TrackWindowAligner, entries: list[Entry]) -> tuple[int, int]:
    """Give ``aligner`` journal entries in order: runs of measurements in one batch
    (:meth:`~ga_ros.core.window.aligner.TrackWindowAligner.add_measurements`), each fix and each
    track end (``finish_track``) between them as it came (a fix with the information it entered
    with); datums are skipped (not the aligner's). Returns ``(accepted, rejected)``
    entries; nothing raises for a rejected one, nor for a failed update: with a strict
    aligner (``GA_ROS_STRICT_UPDATES``) the live session reported a bug of an update and went
    on as without strict (:class:`~ga_ros.pipeline.session.outputs.UpdateBug`), so the replay
    runs without strict, to the same state."""
    strict, aligner.strict = getattr(aligner, 'strict', False), False
    try:
        return _replay(aligner, entries)
    finally:
        aligner.strict = strict


def _replay(aligner: TrackWindowAligner, entries: list[Entry]) -> tuple[int, int]:
    """:func:`replay_entries` with the aligner's ``strict`` off."""
    accepted = rejected = 0
    run: list[Measurement] = []

    def flush() -> None:
        nonlocal accepted, rejected
        if run:
            batch = aligner.add_measurements(run)
            accepted, rejected = accepted + batch.n_accepted, rejected + batch.n_rejected
            run.clear()

    for e in entries:
        if isinstance(e, Measurement):
            run.append(e)
            continue
        if isinstance(e, Datum):  # not the aligner's (RecoveryResult.datum)
            continue
        flush()
        try:
            if isinstance(e, TrackEnd):
                if aligner.open_track != e.track_id:  # (a track end the snapshot holds)
                    rejected += 1
                    continue
                aligner.finish_track()  # a failed update leaves the track finished, as live
            else:  # as it came: its own information and offset covariance (JournaledFix)
                aligner.add_fix(e, getattr(e, 'C_offset', None))
            accepted += 1
        except GaError:
            rejected += 1
    flush()
    return accepted, rejected


def _journal_has_records(jpath: Path) -> bool:
    """The journal has a valid header and at least one intact record or an intact base."""
    try:
        scan = scan_journal(jpath)
    except (FormatError, OSError):
        return False
    return scan.header_ok and (scan.records.size > 0 or scan.base is not None)
