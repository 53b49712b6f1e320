"""The files beside a state file: the journal's path, the snapshot's sidecar, a journal written
anew from intact records, and the clearing of the whole state (``~/reset``)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ga_ros.core.window.persistence import is_state_file
from ga_ros.errors import ForeignFileError, FormatError, GaError
from ga_ros.pipeline.journal.layout import MAGIC3
from ga_ros.pipeline.journal.records import MAGIC, RECORD, RECORD_V1, record_crcs
from ga_ros.pipeline.journal.scan import scan_journal
from ga_ros.safe_write import atomic_write, check_regular, open_nofollow, read_bytes

#: The ``state_file`` value that means the default path (:func:`default_state_file`).
DEFAULT_STATE_FILE = 'default'


def default_state_file(namespace: str, name: str, ros_home: str | None = None) -> Path:
    """Where a node keeps its state by default: ``$ROS_HOME/ga_ros/<namespace>/<name>/state``
    (``ROS_HOME`` defaults to ``~/.ros``; ``namespace`` ``'/'`` or ``'/robot1'``, as ROS gives
    it), so that each node of a graph has its own (:class:`~ga_ros.pipeline.journal.lock.
    StateLock` refuses a second user).

    ``ros_home`` : the ROS home directory (default: the ``ROS_HOME`` environment variable, else
    ``~/.ros``).
    """
    home = ros_home or os.environ.get('ROS_HOME') or os.path.join(os.path.expanduser('~'),
                                                                  '.ros')
    parts = [p for p in namespace.split('/') if p]
    if not name or '/' in name or name in ('.', '..') or any(p in ('.', '..') for p in parts):
        raise FormatError(f'node name {name!r} / namespace {namespace!r} cannot name a folder')
    return Path(home, 'ga_ros', *parts, name, 'state')


def journal_path(state_file: str | os.PathLike) -> Path:
    """The journal that goes with a state file: ``<state_file>.journal``."""
    return Path(str(state_file) + '.journal')


def snapshot_info_path(state_file: str | os.PathLike) -> Path:
    """Sidecar of a snapshot: ``<state_file>.json`` with ``{"journal_records": n}``."""
    return Path(str(state_file) + '.json')


def _json_with_key(key: str) -> Callable[[Path], bool]:
    """A test that a file is ours: a JSON object holding ``key``."""
    def holds(path: Path) -> bool:
        try:
            return key in json.loads(read_bytes(path))
        except (OSError, ValueError, TypeError, GaError):
            return False
    return holds


_is_sidecar = _json_with_key('journal_records')
_is_datum_file = _json_with_key('datum_lla')


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


def datum_path(state_file: str | os.PathLike) -> Path:
    """The map frame's geodetic origin beside a state file: ``<state_file>.datum.json`` with
    ``{"datum_lla": [lat_deg, lon_deg, alt_m]}`` (the ENU origin of the NavSatFix inputs, which
    the saved poses and fixes are expressed in)."""
    return Path(str(state_file) + '.datum.json')


def write_datum(state_file: str | os.PathLike, datum_lla: tuple[float, float, float]) -> None:
    """Record (atomically) the map frame's origin ``[lat_deg, lon_deg, alt_m]`` beside
    ``state_file`` (:func:`datum_path`), so a restart keeps the frame of the saved state.

    Raises
    ------
    OSError, ForeignFileError, UnsafePathError
        The file cannot be written, or a file of that name is not ga_ros's.
    """
    values = [float(v) for v in datum_lla]
    if len(values) != 3 or not np.isfinite(values).all():
        raise FormatError(f'a datum is [lat_deg, lon_deg, alt_m], got {values}')
    atomic_write(datum_path(state_file), json.dumps({'datum_lla': values}).encode(),
                 is_ours=_is_datum_file)


def read_datum(state_file: str | os.PathLike) -> tuple[float, float, float] | None:
    """The map frame's origin ``(lat_deg, lon_deg, alt_m)`` saved beside ``state_file``, or
    ``None`` without one.

    Raises
    ------
    FormatError
        The file exists but does not hold a datum (move it aside or delete it).
    """
    path = datum_path(state_file)
    if not check_regular(path):
        return None
    try:
        values = [float(v) for v in json.loads(read_bytes(path))['datum_lla']]
    except (ValueError, KeyError, TypeError) as exc:
        raise FormatError(f'{path} does not hold a datum ({exc}): move it aside or delete '
                          'it') from None
    if len(values) != 3 or not np.isfinite(values).all():
        raise FormatError(f'{path}: a datum is [lat_deg, lon_deg, alt_m], got {values}: move '
                          'it aside or delete it')
    return values[0], values[1], values[2]


def clear_state(state_file: str | os.PathLike) -> list[Path]:
    """Forget a saved state (the ``~/reset`` service): delete the snapshot, its sidecar and
    the datum file, and empty the journal, but only files that are ga_ros's own; never a
    foreign file, never through a symbolic link (:class:`ForeignFileError`,
    :class:`~ga_ros.errors.UnsafePathError`; then nothing at all is changed). Returns the files
    changed."""
    state, side, jpath = Path(state_file), snapshot_info_path(state_file), journal_path(state_file)
    datum = datum_path(state_file)
    present = [p for p in (state, side, datum, jpath) if check_regular(p)]
    for p, ours in ((state, is_state_file), (side, _is_sidecar), (datum, _is_datum_file)):
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
            atomic_write(jpath, MAGIC)
        else:
            os.unlink(p)
    return present


def has_v2_header(path: Path) -> bool:
    """The journal has a current header (version 2, or a compacted journal's)."""
    fd = open_nofollow(path, os.O_RDONLY)
    try:
        return os.pread(fd, len(MAGIC), 0) in (MAGIC, MAGIC3)
    finally:
        os.close(fd)


def rewrite_journal(path: Path, records: np.ndarray,
                    head: list[bytes] | None = None) -> None:
    """Write a journal holding ``records`` (atomically, never through a link): after ``head``
    (a compacted journal's header and base) or, by default, as version 2."""
    rec = np.zeros(records.size, RECORD)
    for name in RECORD_V1.names:
        rec[name] = records[name]
    raw = rec.view(np.uint8).reshape(records.size, RECORD.itemsize)
    rec['crc'] = record_crcs(raw)
    atomic_write(path, [*(head or [MAGIC]), rec.tobytes()])
