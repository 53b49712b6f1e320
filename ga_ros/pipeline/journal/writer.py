"""Appending to a journal: :class:`MeasurementJournal`."""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.fixes import FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.errors import CorruptFileError
from ga_ros.pipeline.journal.layout import HEAD3, MAGIC3, Layout, compacted_header, read_layout
from ga_ros.pipeline.journal.records import (
    MAGIC,
    RECORD,
    Datum,
    MapOdom,
    TrackEnd,
    encode_datum,
    encode_fix,
    encode_map_odom,
    encode_records,
    encode_track_end,
)
from ga_ros.safe_write import atomic_write, check_regular, open_nofollow


class MeasurementJournal:
    """Appends measurements (and fixes, track ends, the datum) to ``path`` (created with a magic
    header if missing).

    The file is never opened through a symbolic link (:class:`UnsafePathError`). A file with a
    bad header or damaged records is refused (:class:`CorruptFileError`): run :func:`recover`
    first, which repairs it without losing the intact records.

    Attributes
    ----------
    count : journal records so far: those of the base of a compacted journal
        (:mod:`~ga_ros.pipeline.journal.layout`) plus the records after it (the number a
        snapshot stores).
    layout : where the file's records begin (the base of a compacted journal before them).
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._fd: int | None = None
        self.layout = Layout()
        self.count = self._complete_records()

    @property
    def since_base(self) -> int:
        """Records after the base (or since the start, without one): what a recovery from the
        journal alone replays."""
        return self.count - self.layout.start

    def _file_records(self, size: int) -> int:
        return max(size - self.layout.data_offset, 0) // RECORD.itemsize

    def _count_of(self, file_records: int) -> int:
        return self.layout.start + max(file_records - self.layout.n_context, 0)

    def _end(self) -> int:
        """Byte offset after the last complete record."""
        return self.layout.record_offset(self.count - self.layout.start + self.layout.n_context)

    def _complete_records(self) -> int:
        if not check_regular(self.path):
            return 0
        fd = open_nofollow(self.path, os.O_RDONLY)
        try:
            self.layout = read_layout(os.pread(fd, HEAD3, 0), str(self.path))
            size = os.fstat(fd).st_size
        finally:
            os.close(fd)
        return self._count_of(self._file_records(size))

    def _open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = open_nofollow(self.path, os.O_RDWR | os.O_CREAT)
        try:
            size = os.fstat(fd).st_size
            if size == 0:
                os.write(fd, MAGIC)
                self.layout = Layout()
                self.count = 0
            else:
                head = os.pread(fd, HEAD3, 0)
                if not head.startswith((MAGIC, MAGIC3)):
                    raise CorruptFileError(
                        'not a version-2 ga_ros journal (bad header or an old version); run '
                        'ga_ros.pipeline.journal.recover() on the state file to repair or convert '
                        'it', str(self.path))
                self.layout = read_layout(head, str(self.path))
                self.count = self._count_of(self._file_records(size))
                end = self._end()
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

    def append_fix(self, term: FixTerm, entered: FloatArray | None = None,
                   C_offset: FloatArray | None = None) -> None:
        """Write the records of an absolute fix (:func:`encode_fix`: ``entered`` the information
        it entered the aligner with, ``C_offset`` its offset's covariance) in one system
        call."""
        data = encode_fix(term, entered, C_offset)
        self._write(data, len(data) // RECORD.itemsize)

    def append_track_end(self, end: TrackEnd) -> None:
        """Write the record of a track end (:func:`encode_track_end`)."""
        self._write(encode_track_end(end), 1)

    def append_datum(self, datum: Datum) -> None:
        """Write the record of the map frame's datum (:func:`encode_datum`)."""
        self._write(encode_datum(datum), 1)

    def append_map_odom(self, entry: MapOdom) -> None:
        """Write the record of a ``map -> odom`` correction (:func:`encode_map_odom`)."""
        self._write(encode_map_odom(entry), 1)

    def _write(self, data: bytes, n_records: int) -> None:
        if self._fd is None:
            self._open()
        try:
            written = os.write(self._fd, data)
            while written < len(data):
                written += os.write(self._fd, data[written:])
        except OSError:  # e.g. a full disk: cut a partly written record off, so the next
            end = self._end()  # append starts aligned
            try:
                os.ftruncate(self._fd, end)
                os.lseek(self._fd, end, os.SEEK_SET)
            except OSError:
                pass
            raise
        self.count += n_records

    def file_records(self) -> np.ndarray:
        """The file's records (context records first), as written by this journal: read back
        without checks (:func:`~ga_ros.pipeline.journal.scan_journal` checks)."""
        self.open()
        n = self.count - self.layout.start + self.layout.n_context
        raw = os.pread(self._fd, n * RECORD.itemsize, self.layout.data_offset)
        return np.frombuffer(raw, RECORD, count=len(raw) // RECORD.itemsize)

    def compact(self, base: list[bytes | memoryview], context: np.ndarray, arrivals: int,
                newest_stamp_ns: int) -> None:
        """Replace the file (atomically) by a compacted journal: the base state ``base`` (the
        bytes of a state holding all :attr:`count` records), then the ``context`` records
        (:data:`RECORD` rows, already in the base, kept for the gap healer), and nothing else;
        ``arrivals`` and ``newest_stamp_ns`` the gap healer's. On an error the file is as it
        was."""
        crc, size = 0, 0
        for chunk in base:
            crc = zlib.crc32(chunk, crc)
            size += memoryview(chunk).nbytes
        context = np.ascontiguousarray(context, RECORD)
        head = compacted_header(self.count, context.size, arrivals, newest_stamp_ns, size, crc)
        self.close()
        atomic_write(self.path, [head, *base, context.tobytes()])
        self.layout = read_layout(head, str(self.path))

    def sync(self) -> None:
        """``fsync`` the journal (durability across a power cut, not only a killed process)."""
        if self._fd is not None:
            os.fsync(self._fd)

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` records only (the state was restored to a snapshot holding
        them; never fewer than the base holds)."""
        n = max(self.layout.start, min(int(n), self.count))
        self.close()
        if check_regular(self.path):
            fd = open_nofollow(self.path, os.O_RDWR)
            try:
                os.ftruncate(fd, self.layout.record_offset(n - self.layout.start
                                                           + self.layout.n_context))
            finally:
                os.close(fd)
        self.count = n

    def clear(self) -> None:
        """Drop every record and the base (the file keeps only its header)."""
        self.close()
        if check_regular(self.path):
            atomic_write(self.path, MAGIC)
        self.layout = Layout()
        self.count = 0

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
