"""Append-only journal of every accepted measurement (ROS-free): the node's crash insurance.

The alignment node appends each measurement it accepted to ``<state_file>.journal``, one
fixed-size binary record each, flushed to the OS at once, so even ``kill -9`` loses nothing. It
also saves aligner snapshots (``state_file``, ``.npz``) after window updates, together with the
number of journal records they contain (``<state_file>.json``). On restart it loads the snapshot
and replays the records after it; if there is no usable snapshot it replays the whole journal
into a fresh aligner, which reproduces the state exactly (the aligner is deterministic). A
truncated last record (a crash mid-write) is ignored and cut off before the next append.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from ga_ros.core.measurement import Measurement
from ga_ros.errors import FormatError

_KINDS = ('consecutive', 'cross')
#: One record per measurement (little-endian, 377 bytes).
RECORD = np.dtype([('src_id', '<i8'), ('dst_id', '<i8'), ('src_track', '<i8'),
                   ('dst_track', '<i8'), ('stamp_ns', '<i8'), ('kind', 'u1'),
                   ('z', '<f8', (6,)), ('cov', '<f8', (6, 6))])
_MAGIC = b'GAJOURNAL1\n'


def journal_path(state_file: str | os.PathLike) -> Path:
    """The journal that goes with a state file: ``<state_file>.journal``."""
    return Path(str(state_file) + '.journal')


def snapshot_info_path(state_file: str | os.PathLike) -> Path:
    """Sidecar of a snapshot: ``<state_file>.json`` with ``{"journal_records": n}``."""
    return Path(str(state_file) + '.json')


def write_snapshot_info(state_file: str | os.PathLike, journal_records: int) -> None:
    """Record (atomically) how many journal records the snapshot ``state_file`` contains."""
    path = snapshot_info_path(state_file)
    tmp = path.with_name(path.name + '.tmp')
    tmp.write_text(json.dumps({'journal_records': int(journal_records)}))
    os.replace(tmp, path)


def read_snapshot_info(state_file: str | os.PathLike) -> int:
    """Journal records contained in the snapshot (0 if the sidecar is missing or bad)."""
    try:
        return int(json.loads(snapshot_info_path(state_file).read_text())['journal_records'])
    except (OSError, ValueError, KeyError, TypeError):
        return 0


def _complete_records(path: Path) -> int:
    size = path.stat().st_size
    if size < len(_MAGIC):
        return 0
    return (size - len(_MAGIC)) // RECORD.itemsize


class MeasurementJournal:
    """Appends measurements to ``path`` (created with a magic header if missing).

    Attributes
    ----------
    count : number of complete records in the file.
    """

    def __init__(self, path: str | os.PathLike) -> None:
        self.path = Path(path)
        self._file = None
        self.count = _complete_records(self.path) if self.path.exists() else 0

    def _open(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        exists = self.path.exists() and self.path.stat().st_size >= len(_MAGIC)
        self._file = open(self.path, 'r+b' if exists else 'wb')  # noqa: SIM115 - kept open
        if exists:
            if self._file.read(len(_MAGIC)) != _MAGIC:
                self._file.close()
                self._file = None
                raise FormatError('not a ga_ros measurement journal', str(self.path))
            self.count = _complete_records(self.path)
            end = len(_MAGIC) + self.count * RECORD.itemsize
            self._file.truncate(end)          # drop a record cut short by a crash
            self._file.seek(end)
        else:
            self._file.write(_MAGIC)
            self.count = 0

    def append(self, m: Measurement) -> None:
        """Write one record and flush it to the OS (survives a killed process)."""
        if self._file is None:
            self._open()
        rec = np.zeros(1, RECORD)
        rec['src_id'], rec['dst_id'] = m.src_id, m.dst_id
        rec['src_track'], rec['dst_track'] = m.src_track, m.dst_track
        rec['stamp_ns'], rec['kind'] = m.stamp_ns, _KINDS.index(m.kind)
        rec['z'][0] = m.z
        rec['cov'][0] = m.cov
        self._file.write(rec.tobytes())
        self._file.flush()
        self.count += 1

    def truncate(self, n: int) -> None:
        """Keep the first ``n`` records only (the state was restored to a snapshot holding
        them)."""
        n = max(0, min(int(n), self.count))
        self.close()
        if self.path.exists():
            with open(self.path, 'r+b') as f:
                f.truncate(len(_MAGIC) + n * RECORD.itemsize)
        self.count = n

    def clear(self) -> None:
        """Drop every record."""
        self.close()
        self.path.unlink(missing_ok=True)
        self.count = 0

    def close(self) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None


def read_journal(path: str | os.PathLike, start: int = 0) -> list[Measurement]:
    """The complete records of a journal from record ``start`` on, in order (``[]`` if the file
    does not exist)."""
    path = Path(path)
    if not path.exists():
        return []
    data = path.read_bytes()
    if not data:
        return []
    if not data.startswith(_MAGIC):
        raise FormatError('not a ga_ros measurement journal', str(path))
    body = data[len(_MAGIC):]
    n = len(body) // RECORD.itemsize
    recs = np.frombuffer(body[:n * RECORD.itemsize], dtype=RECORD)[max(int(start), 0):]
    out = []
    for r in recs:
        kind = int(r['kind'])
        if kind >= len(_KINDS):
            raise FormatError(f'bad kind {kind} in a journal record', str(path))
        out.append(Measurement(int(r['src_id']), int(r['dst_id']), int(r['src_track']),
                               int(r['dst_track']), np.array(r['z'], dtype=float),
                               np.array(r['cov'], dtype=float), int(r['stamp_ns']),
                               _KINDS[kind]))
    return out
