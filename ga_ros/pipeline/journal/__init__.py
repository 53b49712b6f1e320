"""Append-only journal of every change of the aligner's state, and crash recovery (ROS-free).

The alignment node appends each measurement it accepted to ``<state_file>.journal``, one
fixed-size binary record each, written to the OS at once, so even ``kill -9`` loses nothing. It
also saves aligner snapshots (``state_file``, see :mod:`ga_ros.core.window.persistence`) after
window updates; a snapshot stores how many journal records it contains (and the
``<state_file>.json`` sidecar repeats it for older snapshots). :func:`recover` rebuilds the state
on restart: the snapshot if it verifies, plus the journal records after it, replayed in one
batch; without a usable snapshot, the journal alone.

Journal format: the header ``GAJOURNAL2\n`` then records of :data:`RECORD` (little-endian,
381 bytes), each ending with the CRC-32 of its other bytes. Version-1 journals (``GAJOURNAL1``,
no CRC) are still read. A *compacted* journal (``GAJOURNAL3\n``, :mod:`.layout`) embeds the
state at a window update (its base) before its records, so that a recovery from the journal
alone replays only what followed (the session compacts it: ``SessionConfig.compact_records``).

A measurement's record keeps its source (``Measurement.source``, so a restart keeps the
groups of the variance factors): flag :data:`SOURCED` of the kind byte, the name in the strict
lower triangle of ``cov`` (its upper triangle holds the symmetric covariance).

A measurement held by the gap healer (its source node unknown) is journaled on arrival with
flag :data:`HELD`; taken later, it is journaled again as taken; dropped from the held queue
without being taken (refused), again with :data:`DROPPED` (both flags), so a recovery holds
exactly what the live healer held.

Besides measurements, the journal holds every other change of state, in order:

* every absolute fix the aligner accepted (:mod:`ga_ros.core.fixes`), as four or five records
  written together (:func:`encode_fix`): kind ``fix`` (``src_id`` = ``dst_id`` = the node,
  ``stamp_ns`` the fix's stamp, ``z`` the offset ``T_node_sensor`` as ``[t, rotvec]``, ``cov``
  the information the fix entered with, the odometry offset's covariance included), kind
  ``fix_sensor`` (same node and stamp, ``z`` the measured ``T_map_sensor`` as ``[t, rotvec]``,
  ``cov``'s bytes the source's name in UTF-8, NUL padded), kind ``fix_exact`` (both transforms'
  ``[:3, :4]`` exactly), kind ``fix_own`` (the fix's own information) and, when it came with
  one, kind ``fix_offset`` (the offset's covariance): a replay adds the very term between the
  same measurements (:class:`JournaledFix`). A ``fix`` record without its ``fix_sensor`` (damage)
  is skipped; journals of older versions (the first two records only) are still read;
* every track end the session made (:class:`TrackEnd`: ``~/finish_track``, the end of input, the
  idle timeout; a track ended by the next track's first measurement needs no record);
* the map frame's geodetic datum (:class:`Datum`), once known;
* the ``map -> odom`` correction after each window update that changed it (:class:`MapOdom`,
  kind ``map_odom``, ``cov``'s first 12 values ``T_map_odom[:3, :4]``, ``src_id`` the newest
  node then and ``cov``'s next 12 values its pose): a node restarted on the state sends the last
  one until its first update (:attr:`RecoveryResult.map_odom`) and, with the odometry's pose,
  measures the motion across the restart (:mod:`ga_ros.pipeline.session.restore`).

What is done with damage:

* a record cut short at the end (a crash mid-write) is ignored and cut off before the next
  append: it was never acknowledged;
* a record whose CRC fails, a bad header, or a snapshot that fails its checksum: whatever still
  verifies is kept, the damaged file is moved aside to ``<name>.corrupt-<UTC time>`` (never
  deleted) with a message, and a repaired journal holding the intact records takes its place;
* files are never opened through symbolic links, and a state file that is not a ga_ros state is
  refused (:class:`~ga_ros.errors.ForeignFileError`) and left untouched.

The package: :mod:`.records` (the record format), :mod:`.writer` (:class:`MeasurementJournal`),
:mod:`.scan` (reading, damage), :mod:`.layout` (a compacted journal's base),
:mod:`.state_files` (the files beside a state file: the snapshot's sidecar, the map frame's
geodetic datum, the default path), :mod:`.lock` (one writer per state file) and
:mod:`.recovery` (:func:`recover`).
"""

from ga_ros.pipeline.journal.lock import StateLock, lock_path
from ga_ros.pipeline.journal.records import (
    DROPPED,
    HELD,
    RECORD,
    RECORD_V1,
    REVERSED,
    SOURCED,
    TRACK_END_CAUSES,
    Datum,
    Entry,
    JournaledFix,
    MapOdom,
    TrackEnd,
    encode_fix,
    encode_records,
    records_to_entries,
)
from ga_ros.pipeline.journal.recovery import RecoveryResult, recover
from ga_ros.pipeline.journal.scan import JournalScan, read_journal, scan_journal
from ga_ros.pipeline.journal.state_files import (
    DEFAULT_STATE_FILE,
    clear_state,
    datum_path,
    default_state_file,
    journal_path,
    read_datum,
    write_datum,
    write_snapshot_info,
)
from ga_ros.pipeline.journal.writer import MeasurementJournal

__all__ = [
    'DEFAULT_STATE_FILE',
    'DROPPED',
    'StateLock',
    'default_state_file',
    'lock_path',
    'HELD',
    'RECORD',
    'RECORD_V1',
    'REVERSED',
    'SOURCED',
    'TRACK_END_CAUSES',
    'Datum',
    'Entry',
    'JournaledFix',
    'JournalScan',
    'MapOdom',
    'MeasurementJournal',
    'RecoveryResult',
    'TrackEnd',
    'clear_state',
    'datum_path',
    'encode_fix',
    'encode_records',
    'journal_path',
    'read_datum',
    'read_journal',
    'records_to_entries',
    'recover',
    'scan_journal',
    'write_datum',
    'write_snapshot_info',
]
