"""Where a journal's records begin: right after the header ``GAJOURNAL2\\n``, or, in a compacted
journal (``GAJOURNAL3\\n``), after the *base* it embeds: the state when it was compacted.

A compacted journal is::

    'GAJOURNAL3\\n' | start u64 | n_context u64 | arrivals i64 | newest_stamp_ns i64
    | base_len u64 | base CRC-32 u32 | CRC-32 of the six fields u32
    | base (base_len bytes: a state file's bytes, ga_ros.core.window.persistence)
    | records (as in version 2)

``start`` is the number of journal records the base holds (the journal's records are numbered
on from there, so a snapshot's ``journal_records`` keeps its meaning across compactions);
the first ``n_context`` records are already in the base and kept only for what the gap healer
needs after a restart (the bridges, the measurements taken reversed, the datum: they are never
replayed); ``arrivals`` and ``newest_stamp_ns`` are the gap healer's arrival count and newest
stamp at the compaction.
"""

from __future__ import annotations

import struct
import zlib
from dataclasses import dataclass

from ga_ros.errors import CorruptFileError
from ga_ros.pipeline.journal.records import MAGIC

#: Header of a compacted journal.
MAGIC3 = b'GAJOURNAL3\n'
_FIELDS = struct.Struct('<QQqqQI')
_CRC = struct.Struct('<I')
#: Bytes before the base of a compacted journal.
HEAD3 = len(MAGIC3) + _FIELDS.size + _CRC.size


@dataclass(frozen=True)
class Layout:
    """Where a journal's parts are (module doc).

    Attributes
    ----------
    data_offset : byte offset of the first record.
    start : journal records the base holds (0 without a base).
    n_context : records after the base that it already holds (never replayed).
    arrivals, newest_stamp_ns : the gap healer's arrival count and newest stamp at the base.
    base_len, base_crc : the base's size in bytes and its CRC-32 (0 without a base).
    """

    data_offset: int = len(MAGIC)
    start: int = 0
    n_context: int = 0
    arrivals: int = 0
    newest_stamp_ns: int = -2**63
    base_len: int = 0
    base_crc: int = 0

    @property
    def has_base(self) -> bool:
        return self.base_len > 0

    def record_offset(self, k: int) -> int:
        """Byte offset of file record ``k`` (0-based, context records included)."""
        from ga_ros.pipeline.journal.records import RECORD
        return self.data_offset + int(k) * RECORD.itemsize


def compacted_header(start: int, n_context: int, arrivals: int, newest_stamp_ns: int,
                     base_len: int, base_crc: int) -> bytes:
    """The bytes before the base of a compacted journal (module doc)."""
    fields = _FIELDS.pack(int(start), int(n_context), int(arrivals), int(newest_stamp_ns),
                          int(base_len), int(base_crc) & 0xFFFFFFFF)
    return MAGIC3 + fields + _CRC.pack(zlib.crc32(fields))


def read_layout(head: bytes, name: str = 'journal') -> Layout:
    """The layout of a journal from its first bytes (at least :data:`HEAD3` of a compacted one;
    a version-2 or version-1 header gives the plain layout).

    Raises
    ------
    CorruptFileError
        A compacted journal whose header fails its checksum (its records cannot be found).
    """
    if not head.startswith(MAGIC3):
        return Layout()
    raw = head[len(MAGIC3):HEAD3]
    if len(raw) < _FIELDS.size + _CRC.size or zlib.crc32(raw[:_FIELDS.size]) != _CRC.unpack(
            raw[_FIELDS.size:])[0]:
        raise CorruptFileError('compacted journal header fails its checksum', name)
    start, n_context, arrivals, newest, base_len, base_crc = _FIELDS.unpack(raw[:_FIELDS.size])
    return Layout(HEAD3 + base_len, start, n_context, arrivals, newest, base_len, base_crc)
