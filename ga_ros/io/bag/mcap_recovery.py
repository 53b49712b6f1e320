"""Reading an mcap file cut short (a recording killed half-way): every complete message up to
the damage, then a :class:`~ga_ros.errors.FormatError` naming it."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from ga_ros.errors import FormatError
from ga_ros.io.bag.summary import BagInfo, BagMessage, BagTopic
from ga_ros.io.bag_messages import typestore


def single_mcap(path: Path) -> Path | None:
    """The one ``.mcap`` file of ``path`` (the file itself, or the only one in a directory),
    else None."""
    if path.is_file() and path.suffix == '.mcap':
        return path
    if path.is_dir():
        files = sorted(path.glob('*.mcap'))
        return files[0] if len(files) == 1 else None
    return None


class McapStream:
    """Sequential reader of an mcap file without a valid summary (a recording cut short).

    Uses the ``mcap`` library's stream reader; everything up to the first damaged record is
    read, then :meth:`messages` raises :class:`FormatError` naming the problem.
    """

    def __init__(self, path: Path, open_error: str) -> None:
        self.path = path
        self.problem: str | None = None
        self.counts: dict[int, int] = {}
        self.channels: dict[int, tuple[str, str]] = {}
        self.start_ns = 2**63 - 1
        self.end_ns = 0
        self.n_messages = 0
        self.open_error = open_error
        try:
            for ch, log_ns, _ in self._scan(None):
                self.counts[ch] = self.counts.get(ch, 0) + 1
                self.start_ns = min(self.start_ns, log_ns)
                self.end_ns = max(self.end_ns, log_ns)
                self.n_messages += 1
        except FormatError as exc:
            self.problem = str(exc)
        if self.problem is None:
            self.problem = f'mcap file has no valid summary ({open_error})'

    def _scan(self, wanted: set[str] | None) -> Iterator[tuple[int, int, bytes]]:
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader

        schemas: dict[int, str] = {}
        n = 0

        def take(records: Iterable[Any]) -> Iterator[tuple[int, int, bytes]]:
            nonlocal n
            for rec in records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    self.channels[rec.id] = (rec.topic, schemas.get(rec.schema_id, '?'))
                elif isinstance(rec, Message):
                    topic = self.channels.get(rec.channel_id, ('?', '?'))[0]
                    n += 1
                    if wanted is None or topic in wanted:
                        yield rec.channel_id, int(rec.log_time), bytes(rec.data)

        try:
            with open(self.path, 'rb') as f:
                yield from take(StreamReader(f, validate_crcs=True).records)
        except Exception as exc:  # EndOfFile, CRC errors, bad records, zstd errors, ...
            detail = f'{type(exc).__name__}: {exc}' if str(exc) else type(exc).__name__
            # the records of a chunk cut short, up to the cut (a chunk is read whole otherwise)
            yield from take(_partial_chunk_records(self.path))
            raise FormatError(f'bag is truncated or corrupt after {n} messages ({detail})',
                              str(self.path)) from exc

    def info(self) -> BagInfo:
        topics = tuple(sorted((BagTopic(t, ty, self.counts.get(cid, 0))
                               for cid, (t, ty) in self.channels.items()), key=lambda t: t.name))
        return BagInfo(self.path, 'mcap', self.n_messages, self.start_ns, self.end_ns, topics)

    def messages(self, wanted: set[str] | None, raw: bool, name: str) -> Iterator[BagMessage]:
        store = typestore()
        for cid, log_ns, data in self._scan(wanted):
            topic, msgtype = self.channels[cid]
            msg = None
            if not raw:
                if msgtype not in store.types:
                    raise FormatError(f'unknown message type {msgtype!r} on topic {topic}', name)
                try:
                    msg = store.deserialize_cdr(data, msgtype)
                except Exception as exc:
                    raise FormatError(f'cannot deserialise a message on {topic} ({msgtype}): '
                                      f'{type(exc).__name__}: {exc}', name) from exc
            yield BagMessage(topic, msgtype, log_ns, msg, data)
        raise FormatError(self.problem or 'bag is truncated', name)

    def close(self) -> None:
        pass


#: mcap opcode of a Chunk record.
_MCAP_CHUNK = 0x06


def _partial_chunk_records(path: Path) -> Iterator[Any]:
    """The complete records inside the chunk that an mcap file's end cuts (none if the file is
    not cut inside a chunk, or its compression cannot be read in part).

    Walks the top-level records (``opcode u8, length u64``) after the magic to the first one
    that runs past the end of the file; if it is a Chunk (``start u64, end u64,
    uncompressed_size u64, crc u32, compression string, records u64 + bytes``), its records
    are decompressed as far as they go (zstd and lz4 frames decode a prefix; uncompressed is
    the prefix) and parsed up to the last complete one.
    """
    import io
    import struct

    from mcap.stream_reader import StreamReader

    size = path.stat().st_size
    with open(path, 'rb') as f:
        pos = 8  # magic
        while True:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                return
            opcode, length = struct.unpack('<BQ', head)
            if pos + 9 + length <= size:
                pos += 9 + length
                continue
            if opcode != _MCAP_CHUNK:
                return
            body = f.read()
            break
    fixed = struct.calcsize('<QQQI')
    if len(body) < fixed + 4:
        return
    (name_len,) = struct.unpack_from('<I', body, fixed)
    at = fixed + 4 + name_len + 8
    if len(body) < at:
        return
    compression = body[fixed + 4:fixed + 4 + name_len].decode('utf-8', 'replace')
    part = body[at:]
    try:
        if compression == 'zstd':
            import zstandard

            data = zstandard.ZstdDecompressor().decompressobj().decompress(part)
        elif compression == 'lz4':
            import lz4.frame

            data = lz4.frame.LZ4FrameDecompressor().decompress(part)
        elif compression == '':
            data = part
        else:
            return
    except Exception:  # noqa: BLE001 - a frame damaged at its start: nothing to recover
        return
    reader = StreamReader(io.BytesIO(data), skip_magic=True)
    try:
        yield from reader.records
    except Exception:  # noqa: S110 - the cut ends the chunk's records
        return
