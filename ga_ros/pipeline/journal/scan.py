"""Reading a journal: its intact records, damaged ones skipped by re-synchronising on the next
record that verifies (what is done with damage: :mod:`ga_ros.pipeline.journal`)."""

from __future__ import annotations

import os
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ga_ros.errors import CorruptFileError, FormatError
from ga_ros.pipeline.journal.layout import HEAD3, MAGIC3, Layout, read_layout
from ga_ros.pipeline.journal.records import (
    KIND_AT,
    MAGIC,
    MAGIC_V1,
    PAYLOAD,
    RECORD,
    RECORD_V1,
    Entry,
    kind_ok,
    record_crcs,
    records_to_entries,
)
from ga_ros.safe_write import check_regular, read_bytes


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
    layout : where the base and the records are (:class:`~ga_ros.pipeline.journal.layout.
        Layout`; ``records`` starts with its ``n_context`` context records).
    base : the bytes of the base state of a compacted journal (``None`` without one, or if it
        fails its checksum: then counted as damage).
    """

    records: np.ndarray
    n_damaged: int = 0
    torn_tail: int = 0
    header_ok: bool = True
    messages: list[str] = field(default_factory=list)
    layout: Layout = field(default_factory=Layout)
    base: bytes | None = None

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
    head = data[:len(MAGIC)]
    scan = JournalScan(empty)
    if head == MAGIC_V1:
        body = data[len(MAGIC):]
        n = len(body) // PAYLOAD
        recs = np.frombuffer(body, RECORD_V1, count=n).copy()
        scan.torn_tail = len(body) - n * PAYLOAD
        good = kind_ok(recs['kind'])
    else:
        if head == MAGIC3:
            try:
                scan.layout = read_layout(data[:HEAD3], str(path))
            except CorruptFileError as exc:
                raise FormatError(f'{exc}: its records cannot be found', str(path)) from None
            lay = scan.layout
            base = data[HEAD3:lay.data_offset]
            if len(base) == lay.base_len and zlib.crc32(base) == lay.base_crc:
                scan.base = base
            else:
                scan.n_damaged += 1
                scan.messages.append(f'{path}: the embedded base state fails its checksum')
        elif head != MAGIC:
            scan.header_ok = False
            scan.n_damaged += 1
            scan.messages.append(f'{path}: bad journal header {head!r}')
        body = data[scan.layout.data_offset:]
        n = len(body) // RECORD.itemsize
        full = np.frombuffer(body, RECORD, count=n)
        scan.torn_tail = len(body) - n * RECORD.itemsize
        raw = np.frombuffer(body, np.uint8, count=n * RECORD.itemsize).reshape(
            n, RECORD.itemsize)
        good = (record_crcs(raw) == full['crc']) & kind_ok(full['kind'])
        if good.all():
            recs = np.frombuffer(raw[:, :PAYLOAD].tobytes(), RECORD_V1, count=n).copy()
        else:  # damage: walk the file, re-synchronising on the next record that verifies
            offsets, skipped, scan.torn_tail = _resync(body)
            recs = np.frombuffer(b''.join(body[o:o + PAYLOAD] for o in offsets), RECORD_V1,
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
    if end > len(body) or not kind_ok(body[offset + KIND_AT]):
        return False
    return zlib.crc32(body[offset:offset + PAYLOAD]) == int.from_bytes(
        body[offset + PAYLOAD:end], 'little')


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


def read_journal(path: str | os.PathLike, start: int = 0) -> list[Entry]:
    """The measurements and fixes of a journal's intact records from record ``start`` on, in
    order (``[]`` if the file does not exist). Damaged records are skipped (see
    :func:`scan_journal`)."""
    return records_to_entries(scan_journal(path).records[max(int(start), 0):])
