"""Appending to a journal: :class:`MeasurementJournal`."""

from __future__ import annotations

import os
from pathlib import Path

from ga_ros.arrays import FloatArray
from ga_ros.core.fixes import FixTerm
from ga_ros.core.measurement import Measurement
from ga_ros.errors import CorruptFileError
from ga_ros.io.atomic import atomic_write, check_regular, open_nofollow
from ga_ros.pipeline.journal.records import (
    MAGIC,
    RECORD,
    Datum,
    TrackEnd,
    encode_datum,
    encode_fix,
    encode_records,
    encode_track_end,
)


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
        return max(size - len(MAGIC), 0) // RECORD.itemsize

    def _open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = open_nofollow(self.path, os.O_RDWR | os.O_CREAT)
        try:
            size = os.fstat(fd).st_size
            if size == 0:
                os.write(fd, MAGIC)
                self.count = 0
            else:
                head = os.pread(fd, len(MAGIC), 0)
                if head != MAGIC:
                    raise CorruptFileError(
                        'not a version-2 ga_ros journal (bad header or an old version); run '
                        'ga_ros.pipeline.journal.recover() on the state file to repair or convert '
                        'it', str(self.path))
                self.count = (size - len(MAGIC)) // RECORD.itemsize
                end = len(MAGIC) + self.count * RECORD.itemsize
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

    def _write(self, data: bytes, n_records: int) -> None:
        if self._fd is None:
            self._open()
        try:
            written = os.write(self._fd, data)
            while written < len(data):
                written += os.write(self._fd, data[written:])
        except OSError:  # e.g. a full disk: cut a partly written record off, so the next
            end = len(MAGIC) + self.count * RECORD.itemsize  # append starts aligned
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
                os.ftruncate(fd, len(MAGIC) + n * RECORD.itemsize)
            finally:
                os.close(fd)
        self.count = n

    def clear(self) -> None:
        """Drop every record (the file keeps only its header)."""
        self.close()
        if check_regular(self.path):
            atomic_write(self.path, MAGIC)
        self.count = 0

    def close(self) -> None:
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None
