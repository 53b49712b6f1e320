"""Append-only journal of every accepted measurement, and crash recovery (ROS-free).

The alignment node appends each measurement it accepted to ``<state_file>.journal``, one
fixed-size binary record each, written to the OS at once, so even ``kill -9`` loses nothing. It
also saves aligner snapshots (``state_file``, see :mod:`ga_ros.core.window.persistence`) after
window
updates; a snapshot stores how many journal records it contains (and the ``<state_file>.json``
sidecar repeats it for older snapshots). :func:`recover` rebuilds the state on restart: the
snapshot if it verifies, plus the journal records after it, replayed in one batch.

Journal format: the header ``GAJOURNAL2\\n`` then records of :data:`RECORD` (little-endian,
381 bytes), each ending with the CRC-32 of its other bytes. Version-1 journals (``GAJOURNAL1``,
no CRC) are still read.

The node also appends every absolute fix the aligner accepted (:mod:`ga_ros.core.fixes`), in the
order it gave them, as two records written together (:func:`encode_fix`): kind ``fix``
(``src_id`` = ``dst_id`` = the node, ``stamp_ns`` the fix's stamp, ``z`` the offset
``T_node_sensor`` as ``[t, rotvec]``, ``cov`` the information the fix entered with, the
odometry offset's covariance included) and kind ``fix_sensor`` (same node and stamp, ``z`` the
measured ``T_map_sensor`` as ``[t, rotvec]``, ``cov``'s bytes the source's name in UTF-8, NUL
padded). A replay gives them to the aligner between the same measurements, so the recovered state
is the one lost. A ``fix`` record without its ``fix_sensor`` (damage) is skipped.
What is done with damage:

* a record cut short at the end (a crash mid-write) is ignored and cut off before the next
  append: it was never acknowledged;
* a record whose CRC fails, a bad header, or a snapshot that fails its checksum: whatever still
  verifies is kept, the damaged file is moved aside to ``<name>.corrupt-<UTC time>`` (never
  deleted) with a message, and a repaired journal holding the intact records takes its place;
* files are never opened through symbolic links, and a state file that is not a ga_ros state is
  refused (:class:`~ga_ros.errors.ForeignFileError`) and left untouched.
"""

from __future__ import annotations

import json
import os
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.gaps import reversed_measurement
from ga_ros.core.measurement import KINDS, Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.core.window.persistence import is_state_file, load_state, save_state
from ga_ros.errors import CorruptFileError, ForeignFileError, FormatError, GaError, InputError
from ga_ros.geometry import se3
from ga_ros.io.atomic import atomic_write, check_regular, move_aside, open_nofollow, read_bytes

#: Record kinds of an absolute fix (module doc): beyond the measurement kinds, no flag bits.
_FIX, _FIX_SENSOR = 0x3E, 0x3F
#: What the journal holds, in order: measurements and absolute fixes.
Entry = Measurement | FixTerm
_FIELDS = [('src_id', '<i8'), ('dst_id', '<i8'), ('src_track', '<i8'), ('dst_track', '<i8'),
           ('stamp_ns', '<i8'), ('kind', 'u1'), ('z', '<f8', (6,)), ('cov', '<f8', (6, 6))]
#: One version-1 record (no checksum, 377 bytes).
RECORD_V1 = np.dtype(_FIELDS)
#: One record: the measurement, then the CRC-32 of its 377 bytes (little-endian, 381 bytes).
RECORD = np.dtype(_FIELDS + [('crc', '<u4')])
_MAGIC = b'GAJOURNAL2\n'
_MAGIC_V1 = b'GAJOURNAL1\n'
_PAYLOAD = RECORD_V1.itemsize
_KIND_AT = RECORD.fields['kind'][1]
#: Bit of the kind byte set on a measurement that was *held* (its source node was unknown, see
#: :mod:`ga_ros.core.gaps`), not yet taken by the aligner; the low bits index :data:`KINDS`.
HELD = 0x80
#: Bit of the kind byte set on a measurement the aligner took *reversed*
#: (:func:`~ga_ros.core.gaps.reversed_measurement`): the record holds it as it arrived.
REVERSED = 0x40


def journal_path(state_file: str | os.PathLike) -> Path:
    """The journal that goes with a state file: ``<state_file>.journal``."""
    return Path(str(state_file) + '.journal')


def snapshot_info_path(state_file: str | os.PathLike) -> Path:
    """Sidecar of a snapshot: ``<state_file>.json`` with ``{"journal_records": n}``."""
    return Path(str(state_file) + '.json')


def _is_sidecar(path: Path) -> bool:
    try:
        return 'journal_records' in json.loads(read_bytes(path))
    except (OSError, ValueError, TypeError, GaError):
        return False


def write_snapshot_info(state_file: str | os.PathLike, journal_records: int) -> None:
    """Record (atomically) how many journal records the snapshot ``state_file`` contains."""
    atomic_write(snapshot_info_path(state_file),
                 json.dumps({'journal_records': int(journal_records)}).encode(),
                 is_ours=_is_sidecar)


def read_snapshot_info(state_file: str | os.PathLike) -> int:
    """Journal records contained in the snapshot (0 if the sidecar is missing or bad)."""
    try:
        return int(json.loads(read_bytes(snapshot_info_path(state_file)))['journal_records'])
    except (OSError, ValueError, KeyError, TypeError, GaError):
        return 0


def _crc(records: np.ndarray) -> np.ndarray:
    """CRC-32 of the first 377 bytes (the payload) of each row of a contiguous ``(n, 381)``
    uint8 array of records."""
    flat = memoryview(np.ascontiguousarray(records).reshape(-1))
    size = RECORD.itemsize
    return np.fromiter((zlib.crc32(flat[k:k + _PAYLOAD]) for k in range(0, flat.nbytes, size)),
                       dtype=np.uint32, count=records.shape[0])


_KIND_MASK = 0x3F


def _kind_ok(kind: np.ndarray | int) -> np.ndarray | bool:
    return ((kind & _KIND_MASK) < len(KINDS)) | (kind == _FIX) | (kind == _FIX_SENSOR)


def _is_fix(kind: np.ndarray) -> np.ndarray:
    """Which records are the two of an absolute fix (bool per record)."""
    return np.isin(np.asarray(kind), (_FIX, _FIX_SENSOR))


def encode_records(ms: list[Measurement], flags: int = 0) -> bytes:
    """The journal records of ``ms`` (with their checksums), ready to append; ``flags``:
    :data:`HELD` and / or :data:`REVERSED`, or 0."""
    rec = np.zeros(len(ms), RECORD)
    for name in ('src_id', 'dst_id', 'src_track', 'dst_track', 'stamp_ns'):
        rec[name] = [getattr(m, name) for m in ms]
    rec['kind'] = [KINDS.index(m.kind) | flags for m in ms]
    rec['z'] = np.array([m.z for m in ms], dtype=float).reshape(len(ms), 6)
    rec['cov'] = np.array([m.cov for m in ms], dtype=float).reshape(len(ms), 6, 6)
    return _with_crc(rec)


def _with_crc(rec: np.ndarray) -> bytes:
    raw = rec.view(np.uint8).reshape(rec.size, RECORD.itemsize)
    rec['crc'] = _crc(raw)
    return rec.tobytes()


def encode_fix(term: FixTerm) -> bytes:
    """The two journal records of an absolute fix (module doc), ``term.fix.information`` the
    information it entered the aligner with."""
    rec = np.zeros(2, RECORD)
    rec['src_id'] = rec['dst_id'] = int(term.node_id)
    rec['src_track'] = rec['dst_track'] = -1
    rec['stamp_ns'] = int(term.fix.stamp_ns)
    rec['kind'] = [_FIX, _FIX_SENSOR]
    rec['z'][0] = se3.to_translation_rotvec(term.T_node_sensor)
    rec['z'][1] = se3.to_translation_rotvec(term.fix.T_map_sensor)
    rec['cov'][0] = term.fix.information
    name = term.fix.source.encode('utf-8')[:rec['cov'][1].nbytes]
    rec['cov'][1] = np.frombuffer(name.ljust(rec['cov'][1].nbytes, b'\0'), '<f8').reshape(6, 6)
    return _with_crc(rec)


@dataclass
class JournalScan:
    """What :func:`scan_journal` found in a journal file.

    Attributes
    ----------
    records : structured array (:data:`RECORD_V1` fields) of the intact records, in order.
    n_damaged : records whose checksum (or kind) failed, plus a bad header counted as one.
    torn_tail : bytes of a record cut short at the end (a crash mid-write; not damage).
    header_ok : the header is one of the known magic strings.
    messages : what was wrong, for the log.
    """

    records: np.ndarray
    n_damaged: int = 0
    torn_tail: int = 0
    header_ok: bool = True
    messages: list[str] = field(default_factory=list)

    @property
    def damaged(self) -> bool:
        return self.n_damaged > 0


def scan_journal(path: str | os.PathLike) -> JournalScan:
    """Read a journal and sort its records into intact and damaged ones (see module doc).

    A missing or empty file gives no records. Raises :class:`UnsafePathError` for a symbolic
    link, :class:`FormatError` for a file that holds no ga_ros journal record at all.
    """
    path = Path(path)
    empty = np.zeros(0, RECORD_V1)
    if not check_regular(path):
        return JournalScan(empty)
    data = read_bytes(path)
    if not data:
        return JournalScan(empty)
    head = data[:len(_MAGIC)]
    scan = JournalScan(empty)
    if head == _MAGIC_V1:
        body = data[len(_MAGIC):]
        n = len(body) // _PAYLOAD
        recs = np.frombuffer(body, RECORD_V1, count=n).copy()
        scan.torn_tail = len(body) - n * _PAYLOAD
        good = _kind_ok(recs['kind'])
    else:
        if head != _MAGIC:
            scan.header_ok = False
            scan.n_damaged += 1
            scan.messages.append(f'{path}: bad journal header {head!r}')
        body = data[len(_MAGIC):]
        n = len(body) // RECORD.itemsize
        full = np.frombuffer(body, RECORD, count=n)
        scan.torn_tail = len(body) - n * RECORD.itemsize
        raw = np.frombuffer(body, np.uint8, count=n * RECORD.itemsize).reshape(
            n, RECORD.itemsize)
        good = (_crc(raw) == full['crc']) & _kind_ok(full['kind'])
        if good.all():
            recs = np.frombuffer(raw[:, :_PAYLOAD].tobytes(), RECORD_V1, count=n).copy()
        else:  # damage: walk the file, re-synchronising on the next record that verifies
            offsets, skipped, scan.torn_tail = _resync(body)
            recs = np.frombuffer(b''.join(body[o:o + _PAYLOAD] for o in offsets), RECORD_V1,
                                 count=len(offsets)).copy()
            good = np.ones(len(offsets), dtype=bool)
            scan.n_damaged += skipped
            scan.messages.append(f'{path}: {skipped} damaged byte range(s); '
                                 f'{len(offsets)} intact records kept')
        if not scan.header_ok and not good.any():
            raise FormatError('not a ga_ros measurement journal (bad header, no intact record)',
                              str(path))
    bad = np.flatnonzero(~good)
    if bad.size:
        scan.n_damaged += int(bad.size)
        scan.messages.append(f'{path}: {bad.size} damaged record(s) (first #{int(bad[0])}) '
                             f'of {n}; {int(good.sum())} intact ones kept')
    scan.records = recs[good]
    return scan


def _record_ok(body: bytes, offset: int) -> bool:
    end = offset + RECORD.itemsize
    if end > len(body) or not _kind_ok(body[offset + _KIND_AT]):
        return False
    return zlib.crc32(body[offset:offset + _PAYLOAD]) == int.from_bytes(
        body[offset + _PAYLOAD:end], 'little')


def _resync(body: bytes) -> tuple[list[int], int, int]:
    """Offsets of the records that verify, walking from the start and, after a damaged
    stretch, trying every byte offset until a record verifies again. Returns the offsets, the
    number of damaged stretches skipped, and the length of a torn tail (0 if none)."""
    offsets, skipped, pos, size = [], 0, 0, RECORD.itemsize
    while pos + size <= len(body):
        if _record_ok(body, pos):
            offsets.append(pos)
            pos += size
            continue
        nxt = next((p for p in range(pos + 1, len(body) - size + 1) if _record_ok(body, p)),
                   None)
        skipped += 1
        if nxt is None:
            return offsets, skipped, 0
        pos = nxt
    return offsets, skipped, len(body) - pos


def records_to_entries(recs: np.ndarray, taken: bool = False) -> list[Entry]:
    """Journal records (structured array) as measurements and fixes (:class:`FixTerm`), in
    order; a ``fix`` record without its ``fix_sensor`` record (or the reverse) is skipped. The
    measurements as they arrived, or as the aligner took them if ``taken`` (:func:`as_taken`).
    """
    kinds = recs['kind']
    fix_at = np.flatnonzero(_is_fix(kinds))
    convert = as_taken if taken else records_to_measurements
    if fix_at.size == 0:
        return convert(recs)
    out: list[Entry] = []
    start = 0
    for k in fix_at.tolist():
        if k > start:
            out += convert(recs[start:k])
        start = k + 1
        if kinds[k] != _FIX or k + 1 >= kinds.size or kinds[k + 1] != _FIX_SENSOR:
            continue
        a, b = recs[k], recs[k + 1]
        if int(a['src_id']) != int(b['src_id']) or int(a['stamp_ns']) != int(b['stamp_ns']):
            continue
        source = np.ascontiguousarray(b['cov'], '<f8').tobytes().rstrip(b'\0')
        try:
            fix = AbsoluteFix(int(a['stamp_ns']), se3.from_translation_rotvec(b['z'][:3],
                                                                            b['z'][3:]),
                              np.array(a['cov'], float), source.decode('utf-8', 'replace'))
        except InputError:
            continue
        out.append(FixTerm(int(a['src_id']),
                           se3.from_translation_rotvec(a['z'][:3], a['z'][3:]), fix))
    if start < kinds.size:
        out += convert(recs[start:])
    return out


def records_to_measurements(recs: np.ndarray) -> list[Measurement]:
    """Journal records (structured array) as :class:`Measurement` objects, in order, as they
    arrived (held or not: :func:`held_records`; reversed by the aligner or not:
    :func:`as_taken`)."""
    cols = [recs[f].tolist() for f in ('src_id', 'dst_id', 'src_track', 'dst_track',
                                       'stamp_ns', 'kind')]
    z, cov = np.array(recs['z'], dtype=float), np.array(recs['cov'], dtype=float)
    return [Measurement(a, b, c, d, z[k], cov[k], e, KINDS[f & _KIND_MASK])
            for k, (a, b, c, d, e, f) in enumerate(zip(*cols))]


def held_records(recs: np.ndarray) -> np.ndarray:
    """Which journal records are held measurements (bool per record)."""
    return (np.asarray(recs['kind']) & HELD) != 0


def as_taken(recs: np.ndarray) -> list[Measurement]:
    """Journal records as the aligner took them (those marked :data:`REVERSED` reversed)."""
    rev = ((np.asarray(recs['kind']) & REVERSED) != 0).tolist()
    return [reversed_measurement(m) if r else m
            for m, r in zip(records_to_measurements(recs), rev)]


def reversed_records(recs: np.ndarray) -> list[Measurement]:
    """The measurements (as they arrived) that the aligner took reversed."""
    return records_to_measurements(recs[(np.asarray(recs['kind']) & REVERSED) != 0])


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


def held_queue(recs: np.ndarray) -> HeldQueue:
    """The held queue to restore after a restart: the held records that no later record
    admitted (matched by nodes and stamp), with their arrival numbers."""
    held = held_records(recs)
    bridge = (recs['kind'] & _KIND_MASK) == KINDS.index('bridge')
    src, dst, stamp = (recs[f].tolist() for f in ('src_id', 'dst_id', 'stamp_ns'))
    pending: dict[tuple[int, int, int], list[int]] = {}
    seq: dict[int, int] = {}
    out = HeldQueue()
    for k in range(len(held)):
        key = (src[k], dst[k], stamp[k])
        if bridge[k]:
            continue
        if held[k]:
            pending.setdefault(key, []).append(k)
        else:
            done = pending.get(key)
            if done:  # a held measurement taken later: not an arrival
                seq.pop(done.pop(0))
                continue
        out.arrivals += 1
        out.newest_stamp_ns = max(out.newest_stamp_ns, stamp[k])
        if held[k]:
            seq[k] = out.arrivals
    rows = sorted(seq)
    ms = records_to_measurements(recs[np.array(rows, dtype=np.int64)])
    out.held = [(m, seq[k]) for m, k in zip(ms, rows)]
    return out


class MeasurementJournal:
    """Appends measurements to ``path`` (created with a magic header if missing).

    The file is never opened through a symbolic link (:class:`UnsafePathError`). A file with a
    bad header or damaged records is refused (:class:`CorruptFileError`): run :func:`recover`
    first, which repairs it without losing the intact records.

    Attributes
    ----------
    count : number of complete records in the file.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._fd: int | None = None
        self.count = self._complete_records()

    def _complete_records(self) -> int:
        if not check_regular(self.path):
            return 0
        size = os.lstat(self.path).st_size
        return max(size - len(_MAGIC), 0) // RECORD.itemsize

    def _open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = open_nofollow(self.path, os.O_RDWR | os.O_CREAT)
        try:
            size = os.fstat(fd).st_size
            if size == 0:
                os.write(fd, _MAGIC)
                self.count = 0
            else:
                head = os.pread(fd, len(_MAGIC), 0)
                if head != _MAGIC:
                    raise CorruptFileError(
                        'not a version-2 ga_ros journal (bad header or an old version); run '
                        'ga_ros.pipeline.journal.recover() on the state file to repair or convert '
                        'it', str(self.path))
                self.count = (size - len(_MAGIC)) // RECORD.itemsize
                end = len(_MAGIC) + self.count * RECORD.itemsize
                os.ftruncate(fd, end)     # drop a record cut short by a crash
                os.lseek(fd, end, os.SEEK_SET)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd

    def open(self) -> None:
        """Open (or create) the file for appending now rather than at the first record, so that
        a path that cannot be written shows at start. Raises ``OSError`` or
        :class:`CorruptFileError` as the first append would."""
        if self._fd is None:
            self._open()

    def append(self, m: Measurement, flags: int = 0) -> None:
        """Write one record to the OS at once (survives a killed process); ``flags``:
        :data:`HELD` (not taken by the aligner), :data:`REVERSED` (taken reversed), or 0."""
        self.append_many([m], flags)

    def append_many(self, ms: list[Measurement], flags: int = 0) -> None:
        """Write several records in one system call."""
        if ms:
            self._write(encode_records(ms, flags), len(ms))

    def append_fix(self, term: FixTerm) -> None:
        """Write the two records of an absolute fix (:func:`encode_fix`) in one system call."""
        self._write(encode_fix(term), 2)

    def _write(self, data: bytes, n_records: int) -> None:
        if self._fd is None:
            self._open()
        try:
            written = os.write(self._fd, data)
            while written < len(data):
                written += os.write(self._fd, data[written:])
        except OSError:  # e.g. a full disk: cut a partly written record off, so the next
            end = len(_MAGIC) + self.count * RECORD.itemsize  # append starts aligned
            try:
                os.ftruncate(self._fd, end)
                os.lseek(self._fd, end, os.SEEK_SET)
            except OSError:
                pass
            raise
        self.count += n_records

    def sync(self) -> None:
        """``fsync`` the journal (durability across a power cut, not only a killed process)."""
        if self._fd is not None:
            os.fsync(self._fd)

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` records only (the state was restored to a snapshot holding
        them)."""
        n = max(0, min(int(n), self.count))
        self.close()
        if check_regular(self.path):
            fd = open_nofollow(self.path, os.O_RDWR)
            try:
                os.ftruncate(fd, len(_MAGIC) + n * RECORD.itemsize)
            finally:
                os.close(fd)
        self.count = n

    def clear(self) -> None:
        """Drop every record (the file keeps only its header)."""
        self.close()
        if check_regular(self.path):
            atomic_write(self.path, _MAGIC)
        self.count = 0

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def read_journal(path: str | os.PathLike, start: int = 0) -> list[Entry]:
    """The measurements and fixes of a journal's intact records from record ``start`` on, in
    order (``[]`` if the file does not exist). Damaged records are skipped (see
    :func:`scan_journal`)."""
    return records_to_entries(scan_journal(path).records[max(int(start), 0):])


def clear_state(state_file: str | os.PathLike) -> list[Path]:
    """Forget a saved state (the ``~/reset`` service): delete the snapshot and its sidecar and
    empty the journal, but only files that are ga_ros's own; never a foreign file, never through
    a symbolic link (:class:`ForeignFileError`, :class:`~ga_ros.errors.UnsafePathError`; then
    nothing at all is changed). Returns the files changed."""
    state, side, jpath = Path(state_file), snapshot_info_path(state_file), journal_path(state_file)
    present = [p for p in (state, side, jpath) if check_regular(p)]
    for p, ours in ((state, is_state_file), (side, _is_sidecar)):
        if p in present and not ours(p):
            raise ForeignFileError(f'{p} is not a ga_ros file: nothing was cleared')
    if jpath in present and os.lstat(jpath).st_size:
        try:
            scan_journal(jpath)
        except FormatError:
            raise ForeignFileError(f'{jpath} is not a ga_ros journal: nothing was cleared') \
                from None
    for p in present:
        if p == jpath:
            atomic_write(jpath, _MAGIC)
        else:
            os.unlink(p)
    return present


# ------------------------------------------------------------------------------ recovery
@dataclass
class RecoveryResult:
    """What :func:`recover` restored.

    Attributes
    ----------
    aligner : the restored aligner (empty if there was nothing to restore).
    source : ``'snapshot'``, ``'snapshot+journal'``, ``'journal'`` or ``'empty'``.
    snapshot_records : journal records the snapshot contained (0 without a snapshot).
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
    aligner, snap_records = None, 0
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
            aligner = saved.aligner
            snap_records = (saved.journal_records if saved.journal_records is not None
                            else read_snapshot_info(state))
        except InputError as exc:
            out.moved_aside.append(move_aside(state))
            out.messages.append(f'snapshot {state} is damaged ({exc}); moved aside to '
                                f'{out.moved_aside[-1].name}, rebuilding from the journal')
    try:
        scan = scan_journal(jpath)
    except FormatError as exc:
        scan = JournalScan(np.zeros(0, RECORD_V1), n_damaged=1, header_ok=False,
                           messages=[str(exc)])
    out.messages += scan.messages
    if scan.damaged or (check_regular(jpath) and os.lstat(jpath).st_size
                        and not _has_v2_header(jpath)):
        if scan.damaged:
            out.moved_aside.append(move_aside(jpath))
            out.messages.append(f'journal {jpath} moved aside to {out.moved_aside[-1].name}; '
                                f'{scan.records.size} intact records kept')
        _rewrite_journal(jpath, scan.records)
    records = scan.records
    out.journal_records = int(records.size)
    if aligner is not None:
        out.source, out.snapshot_records = 'snapshot', int(snap_records)
        if scan.damaged:
            # the numbering of the records changed: replay every intact one; those already in
            # the snapshot are rejected (duplicate, frozen) and change nothing
            tail = records
        else:
            if snap_records > records.size:
                out.messages.append(f'the snapshot holds {snap_records} journal records, the '
                                    f'journal only {records.size}: the snapshot is kept')
            tail = records[min(snap_records, records.size):]
    else:
        aligner = out.aligner
        tail = records
        out.source = 'journal' if records.size else 'empty'
    out.held = held_queue(records[~_is_fix(records['kind'])])  # measurements only
    bridge = records['kind'] & _KIND_MASK == KINDS.index('bridge')
    out.bridges = list(zip(records['src_id'][bridge].tolist(),
                           records['dst_id'][bridge].tolist()))
    out.reversed = reversed_records(records)
    tail = tail[~held_records(tail)]  # held measurements never reached the aligner
    if tail.size:
        out.records_replayed, out.records_rejected = replay_entries(
            aligner, records_to_entries(tail, taken=True))
        if out.source == 'snapshot':
            out.source = 'snapshot+journal'
    out.aligner = aligner
    changed = bool(tail.size or out.moved_aside or snap_records != records.size)
    if (checkpoint and changed or scan.damaged) and out.source != 'empty' and not foreign:
        try:
            save_state(aligner, state, journal_records=out.journal_records)
        except OSError as exc:  # e.g. a full disk: the journal still holds every record
            out.messages.append(f'recovery snapshot {state} not written ({exc}); the journal '
                                'still holds every record')
    out.seconds = time.perf_counter() - t0
    return out


def replay_entries(aligner: TrackWindowAligner, entries: list[Entry]) -> tuple[int, int]:
    """Give ``aligner`` journal entries in order: runs of measurements in one batch
    (:meth:`~ga_ros.core.window.aligner.TrackWindowAligner.add_measurements`), each fix between
    them as it came (with the information it entered with). Returns ``(accepted, rejected)``
    entries; nothing raises for a rejected one."""
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
        flush()
        try:
            aligner.add_fix(e)
            accepted += 1
        except GaError:
            rejected += 1
    flush()
    return accepted, rejected


def _journal_has_records(jpath: Path) -> bool:
    """The journal has a valid header and at least one intact record."""
    try:
        scan = scan_journal(jpath)
    except (FormatError, OSError):
        return False
    return scan.header_ok and scan.records.size > 0


def _has_v2_header(path: Path) -> bool:
    fd = open_nofollow(path, os.O_RDONLY)
    try:
        return os.pread(fd, len(_MAGIC), 0) == _MAGIC
    finally:
        os.close(fd)


def _rewrite_journal(path: Path, records: np.ndarray) -> None:
    """Write a version-2 journal holding ``records`` (atomically, never through a link)."""
    rec = np.zeros(records.size, RECORD)
    for name in RECORD_V1.names:
        rec[name] = records[name]
    raw = rec.view(np.uint8).reshape(records.size, RECORD.itemsize)
    rec['crc'] = _crc(raw)
    atomic_write(path, [_MAGIC, rec.tobytes()])

