"""The journal's record format: one fixed-size little-endian record per measurement or per half
of an absolute fix, with its CRC-32, and the conversions between records and measurements / fixes
(format in :mod:`ga_ros.pipeline.journal`)."""

from __future__ import annotations

import zlib
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.gaps import reversed_measurement
from ga_ros.core.measurement import KINDS, Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3

#: Record kinds of an absolute fix (module doc): beyond the measurement kinds, no flag bits.
_FIX, _FIX_SENSOR = 0x3E, 0x3F
#: Record kind of a track end (:class:`TrackEnd`), of the map frame's datum (:class:`Datum`), and
#: the third record of a fix: its two transforms exactly (``cov``'s first 24 values:
#: ``T_node_sensor[:3, :4]`` then ``T_map_sensor[:3, :4]``, row-major), and its fourth: the fix's
#: own information (``cov``; the first record holds the information it entered with), and its
#: fifth, when the fix came with one: the odometry offset's covariance ``C_offset`` (``cov``);
#: the kind of the ``map -> odom`` correction last sent (:class:`MapOdom`).
_TRACK_END, _DATUM, _FIX_EXACT, _FIX_OWN, _FIX_OFFSET = 0x3D, 0x3C, 0x3B, 0x3A, 0x39
_MAP_ODOM = 0x38
#: Why a track was ended (:class:`TrackEnd`): the record stores the index.
TRACK_END_CAUSES = ('finish_track', 'end_of_input', 'idle_timeout')


@dataclass(frozen=True)
class JournaledFix(FixTerm):
    """An absolute fix read back from the journal: ``fix.information`` its own information and
    ``C_offset`` the covariance of its odometry offset (``None``: none, or a journal that did not
    record it; ``fix.information`` is then the information it entered with), so that
    ``aligner.add_fix(term, term.C_offset)`` adds the very term the live aligner added."""

    C_offset: FloatArray | None = None


@dataclass(frozen=True)
class TrackEnd:
    """The open track was ended and its window adjusted (``finish_track``).

    Attributes
    ----------
    track_id : the track that was open.
    cause : one of :data:`TRACK_END_CAUSES` (the ``~/finish_track`` service, the in-band end of
        input, the idle timeout); a replay does the same for every cause.
    """

    track_id: int
    cause: str = 'finish_track'


@dataclass(frozen=True)
class Datum:
    """The map frame's geodetic origin became known: ``lla = (lat_deg, lon_deg, alt_m)``."""

    lla: tuple[float, float, float]


@dataclass(frozen=True)
class MapOdom:
    """The REP 105 correction a window update gave: ``T_map_odom`` (4, 4), ``odom`` the first
    standard input's odometry frame. The node restarted on a state sends it until its first
    update (:meth:`ga_ros.pipeline.map_to_odom.MapToOdom.restore`) instead of the identity.

    ``node_id`` and ``T_map_node`` (4, 4): the aligner's newest node when it was journaled and
    its pose then (``-1`` / ``None``: not given). A restart checks that node's restored pose
    against it: equal, the state did not move since, and the restored ``T_map_odom`` with the
    odometry's pose gives the measured bridge across the restart
    (:mod:`ga_ros.pipeline.session.restore`)."""

    T_map_odom: FloatArray
    node_id: int = -1
    T_map_node: FloatArray | None = None


#: What the journal holds, in order: measurements, absolute fixes, track ends, the datum (and
#: ``map -> odom`` corrections, :class:`MapOdom`, which only a recovery reads:
#: :func:`last_map_odom_entry`).
Entry = Measurement | FixTerm | TrackEnd | Datum
#: The kind byte of a datum record and of a ``map -> odom`` record.
DATUM_KIND, MAP_ODOM_KIND = _DATUM, _MAP_ODOM
_EVENTS = (_FIX, _FIX_SENSOR, _TRACK_END, _DATUM, _FIX_EXACT, _FIX_OWN, _FIX_OFFSET, _MAP_ODOM)
_FIELDS = [('src_id', '<i8'), ('dst_id', '<i8'), ('src_track', '<i8'), ('dst_track', '<i8'),
           ('stamp_ns', '<i8'), ('kind', 'u1'), ('z', '<f8', (6,)), ('cov', '<f8', (6, 6))]
#: One version-1 record (no checksum, 377 bytes).
RECORD_V1 = np.dtype(_FIELDS)
#: One record: the measurement, then the CRC-32 of its 377 bytes (little-endian, 381 bytes).
RECORD = np.dtype(_FIELDS + [('crc', '<u4')])
MAGIC = b'GAJOURNAL2\n'
MAGIC_V1 = b'GAJOURNAL1\n'
PAYLOAD = RECORD_V1.itemsize
KIND_AT = RECORD.fields['kind'][1]
#: Bit of the kind byte set on a measurement that was *held* (its source node was unknown, see
#: :mod:`ga_ros.core.gaps`), not yet taken by the aligner; the low bits index :data:`KINDS`.
HELD = 0x80
#: Bit of the kind byte set on a measurement the aligner took *reversed*
#: (:func:`~ga_ros.core.gaps.reversed_measurement`): the record holds it as it arrived.
REVERSED = 0x40
#: Bit of the kind byte set on a measurement that carries its source (``Measurement.source``,
#: the group of its variance factor): its UTF-8 bytes, zero-padded, fill the 120 bytes of the
#: strict lower triangle of ``cov`` (the covariance is symmetric: its upper triangle holds it
#: all). Set only for a named source of an exactly symmetric covariance.
SOURCED = 0x20
#: Both :data:`HELD` and :data:`REVERSED`: a held measurement that left the held queue without
#: reaching the aligner (refused: its source node can no longer come, a duplicate), written when
#: it is dropped, so that a recovery does not hold it again.
DROPPED = HELD | REVERSED
#: The kind byte without its flag bits (:data:`HELD`, :data:`REVERSED`, :data:`SOURCED`).
KIND_MASK = 0x1F
#: The strict lower triangle of a 6x6 ``cov`` (row, column indices): where a source is kept.
_LOWER = np.tril_indices(6, -1)
_SOURCE_BYTES = 15 * 8


def record_crcs(records: np.ndarray) -> np.ndarray:
    """CRC-32 of the first 377 bytes (the payload) of each row of a contiguous ``(n, 381)``
    uint8 array of records."""
    flat = memoryview(np.ascontiguousarray(records).reshape(-1))
    size = RECORD.itemsize
    return np.fromiter((zlib.crc32(flat[k:k + PAYLOAD]) for k in range(0, flat.nbytes, size)),
                       dtype=np.uint32, count=records.shape[0])


def kind_ok(kind: np.ndarray | int) -> np.ndarray | bool:
    return ((kind & KIND_MASK) < len(KINDS)) | np.isin(kind, _EVENTS)


def is_event(kind: np.ndarray) -> np.ndarray:
    """Which records are not measurements (absolute fixes, track ends, datum; bool per
    record)."""
    return np.isin(np.asarray(kind), _EVENTS)


def encode_track_end(end: TrackEnd) -> bytes:
    """The journal record of a track end: kind ``track_end``, ``src_track`` = ``dst_track`` =
    the track, ``dst_id`` the index of its cause in :data:`TRACK_END_CAUSES`."""
    rec = np.zeros(1, RECORD)
    rec['src_id'] = -1
    rec['src_track'] = rec['dst_track'] = int(end.track_id)
    rec['dst_id'] = TRACK_END_CAUSES.index(end.cause)
    rec['kind'] = _TRACK_END
    return _with_crc(rec)


def encode_datum(datum: Datum) -> bytes:
    """The journal record of the map frame's datum: kind ``datum``, ``z[:3]`` =
    ``(lat_deg, lon_deg, alt_m)``."""
    rec = np.zeros(1, RECORD)
    rec['src_id'] = rec['dst_id'] = rec['src_track'] = rec['dst_track'] = -1
    rec['kind'] = _DATUM
    rec['z'][0, :3] = [float(v) for v in datum.lla]
    return _with_crc(rec)


def encode_map_odom(entry: MapOdom) -> bytes:
    """The journal record of a ``map -> odom`` correction: kind ``map_odom``, ``cov``'s first
    12 values ``T_map_odom[:3, :4]`` (row-major, exact); with a node, ``src_id`` its id and
    ``cov``'s next 12 values ``T_map_node[:3, :4]``."""
    T = np.asarray(entry.T_map_odom, dtype=float)
    N = np.eye(4) if entry.T_map_node is None else np.asarray(entry.T_map_node, dtype=float)
    for what, M in (('map -> odom', T), ('the node pose', N)):
        if M.shape != (4, 4) or not np.isfinite(M).all():
            raise InputError(f'{what} must be a finite (4, 4) transform, got shape {M.shape}')
    rec = np.zeros(1, RECORD)
    rec['src_id'] = rec['dst_id'] = rec['src_track'] = rec['dst_track'] = -1
    rec['kind'] = _MAP_ODOM
    rec['cov'][0].reshape(-1)[:12] = T[:3, :4].ravel()
    if entry.T_map_node is not None and entry.node_id >= 0:
        rec['src_id'] = int(entry.node_id)
        rec['cov'][0].reshape(-1)[12:24] = N[:3, :4].ravel()
    return _with_crc(rec)


def encode_records(ms: list[Measurement], flags: int = 0) -> bytes:
    """The journal records of ``ms`` (with their checksums), ready to append; ``flags``:
    :data:`HELD` and / or :data:`REVERSED`, or 0."""
    rec = np.zeros(len(ms), RECORD)
    for name in ('src_id', 'dst_id', 'src_track', 'dst_track', 'stamp_ns'):
        rec[name] = [getattr(m, name) for m in ms]
    rec['kind'] = [KINDS.index(m.kind) | flags for m in ms]
    rec['z'] = np.array([m.z for m in ms], dtype=float).reshape(len(ms), 6)
    rec['cov'] = np.array([m.cov for m in ms], dtype=float).reshape(len(ms), 6, 6)
    for k, m in enumerate(ms):
        name = str(m.source).encode('utf-8')
        if name and len(name) <= _SOURCE_BYTES and (rec['cov'][k] == rec['cov'][k].T).all():
            rec['kind'][k] |= SOURCED
            rec['cov'][k][_LOWER] = np.frombuffer(name.ljust(_SOURCE_BYTES, b'\0'), '<f8')
    return _with_crc(rec)


def _with_crc(rec: np.ndarray) -> bytes:
    raw = rec.view(np.uint8).reshape(rec.size, RECORD.itemsize)
    rec['crc'] = record_crcs(raw)
    return rec.tobytes()


def encode_fix(term: FixTerm, entered: FloatArray | None = None,
               C_offset: FloatArray | None = None) -> bytes:
    """The journal records of an absolute fix (module doc): ``entered`` the information it
    entered the aligner with (default ``term.fix.information``), ``C_offset`` the covariance of
    its odometry offset as given to ``add_fix`` (``None``: none). The third record holds both
    transforms exactly, the fourth the fix's own information and the fifth ``C_offset``, so a
    replay adds the very term (:class:`JournaledFix`; a journal of an older version holds the
    first two only: the transforms then come from their ``[t, rotvec]``)."""
    rec = np.zeros(4 if C_offset is None else 5, RECORD)
    rec['src_id'] = rec['dst_id'] = int(term.node_id)
    rec['src_track'] = rec['dst_track'] = -1
    rec['stamp_ns'] = int(term.fix.stamp_ns)
    rec['kind'] = [_FIX, _FIX_SENSOR, _FIX_EXACT, _FIX_OWN, _FIX_OFFSET][:rec.size]
    rec['cov'][3] = term.fix.information
    if C_offset is not None:
        rec['cov'][4] = np.asarray(C_offset, float).reshape(6, 6)
    exact = np.concatenate([np.asarray(term.T_node_sensor, float)[:3, :4].ravel(),
                            np.asarray(term.fix.T_map_sensor, float)[:3, :4].ravel()])
    rec['cov'][2].reshape(-1)[:24] = exact
    rec['z'][0] = se3.to_translation_rotvec(term.T_node_sensor)
    rec['z'][1] = se3.to_translation_rotvec(term.fix.T_map_sensor)
    rec['cov'][0] = term.fix.information if entered is None else entered
    name = term.fix.source.encode('utf-8')[:rec['cov'][1].nbytes]
    rec['cov'][1] = np.frombuffer(name.ljust(rec['cov'][1].nbytes, b'\0'), '<f8').reshape(6, 6)
    return _with_crc(rec)


def records_to_entries(recs: np.ndarray, taken: bool = False) -> list[Entry]:
    """Journal records (structured array) as measurements, fixes (:class:`FixTerm`), track ends
    (:class:`TrackEnd`) and datums (:class:`Datum`), in order (``map -> odom`` records are
    skipped: :func:`last_map_odom_entry`); a ``fix`` record without its
    ``fix_sensor`` record (or the reverse) is skipped. The measurements as they arrived, or as
    the aligner took them if ``taken`` (:func:`as_taken`).
    """
    kinds = recs['kind']
    fix_at = np.flatnonzero(is_event(kinds))
    convert = as_taken if taken else records_to_measurements
    if fix_at.size == 0:
        return convert(recs)
    out: list[Entry] = []
    start = 0
    for k in fix_at.tolist():
        if k > start:
            out += convert(recs[start:k])
        start = k + 1
        if kinds[k] == _TRACK_END:
            cause = int(recs[k]['dst_id'])
            out.append(TrackEnd(int(recs[k]['src_track']), TRACK_END_CAUSES[cause]
                                if 0 <= cause < len(TRACK_END_CAUSES) else 'finish_track'))
            continue
        if kinds[k] == _DATUM:
            lat, lon, alt = (float(v) for v in recs[k]['z'][:3])
            out.append(Datum((lat, lon, alt)))
            continue
        if kinds[k] != _FIX or k + 1 >= kinds.size or kinds[k + 1] != _FIX_SENSOR:
            continue
        a, b = recs[k], recs[k + 1]
        if int(a['src_id']) != int(b['src_id']) or int(a['stamp_ns']) != int(b['stamp_ns']):
            continue
        source = np.ascontiguousarray(b['cov'], '<f8').tobytes().rstrip(b'\0')
        T_node_sensor = se3.from_translation_rotvec(a['z'][:3], a['z'][3:])
        T_map_sensor = se3.from_translation_rotvec(b['z'][:3], b['z'][3:])
        if k + 2 < kinds.size and kinds[k + 2] == _FIX_EXACT:
            c = recs[k + 2]
            if int(c['src_id']) == int(a['src_id']) and int(c['stamp_ns']) == int(a['stamp_ns']):
                exact = np.array(c['cov'], float).reshape(-1)
                T_node_sensor[:3, :4] = exact[:12].reshape(3, 4)
                T_map_sensor[:3, :4] = exact[12:24].reshape(3, 4)
        own = _part(recs, k + 3, _FIX_OWN, a)
        C_offset = _part(recs, k + 4, _FIX_OFFSET, a) if own is not None else None
        try:
            fix = AbsoluteFix(int(a['stamp_ns']), T_map_sensor,
                              np.array(a['cov'], float) if own is None else own,
                              source.decode('utf-8', 'replace'))
        except InputError:
            continue
        out.append(JournaledFix(int(a['src_id']), T_node_sensor, fix, C_offset))
    if start < kinds.size:
        out += convert(recs[start:])
    return out


def _part(recs: np.ndarray, k: int, kind: int, first: np.void) -> FloatArray | None:
    """The ``cov`` of record ``k`` if it is of ``kind`` and of the fix of record ``first``."""
    if k >= recs.size or recs['kind'][k] != kind:
        return None
    r = recs[k]
    if int(r['src_id']) != int(first['src_id']) or int(r['stamp_ns']) != int(first['stamp_ns']):
        return None
    return np.array(r['cov'], float)


def records_to_measurements(recs: np.ndarray) -> list[Measurement]:
    """Journal records (structured array) as :class:`Measurement` objects, in order, as they
    arrived (held or not: :func:`held_records`; reversed by the aligner or not:
    :func:`as_taken`)."""
    cols = [recs[f].tolist() for f in ('src_id', 'dst_id', 'src_track', 'dst_track',
                                       'stamp_ns', 'kind')]
    z, cov = np.array(recs['z'], dtype=float), np.array(recs['cov'], dtype=float)
    source = [''] * len(cols[0])
    for k in np.flatnonzero(np.asarray(recs['kind']) & SOURCED).tolist():
        raw = np.ascontiguousarray(cov[k][_LOWER], '<f8').tobytes().rstrip(b'\0')
        source[k] = raw.decode('utf-8', 'replace')
        cov[k][_LOWER] = cov[k].T[_LOWER]
    return [Measurement(a, b, c, d, z[k], cov[k], e, KINDS[f & KIND_MASK], source[k])
            for k, (a, b, c, d, e, f) in enumerate(zip(*cols))]


def held_records(recs: np.ndarray) -> np.ndarray:
    """Which journal records are held measurements (bool per record)."""
    return (np.asarray(recs['kind']) & DROPPED) == HELD


def dropped_records(recs: np.ndarray) -> np.ndarray:
    """Which journal records drop a held measurement from the held queue (:data:`DROPPED`;
    bool per record)."""
    return (np.asarray(recs['kind']) & DROPPED) == DROPPED


def as_taken(recs: np.ndarray) -> list[Measurement]:
    """Journal records as the aligner took them (those marked :data:`REVERSED` reversed)."""
    rev = ((np.asarray(recs['kind']) & DROPPED) == REVERSED).tolist()
    return [reversed_measurement(m) if r else m
            for m, r in zip(records_to_measurements(recs), rev)]


def reversed_records(recs: np.ndarray) -> list[Measurement]:
    """The measurements (as they arrived) that the aligner took reversed."""
    return records_to_measurements(recs[(np.asarray(recs['kind']) & DROPPED) == REVERSED])


def last_datum(recs: np.ndarray) -> tuple[float, float, float] | None:
    """The ``(lat_deg, lon_deg, alt_m)`` of the last datum record (``None`` without one)."""
    at = np.flatnonzero(np.asarray(recs['kind']) == _DATUM)
    if not at.size:
        return None
    lat, lon, alt = (float(v) for v in recs[int(at[-1])]['z'][:3])
    return lat, lon, alt


def last_map_odom_entry(recs: np.ndarray) -> MapOdom | None:
    """The last ``map -> odom`` record, with its node and that node's pose when it holds them
    (``None`` without one)."""
    at = np.flatnonzero(np.asarray(recs['kind']) == _MAP_ODOM)
    if not at.size:
        return None
    rec = recs[int(at[-1])]
    values = np.array(rec['cov'], float).reshape(-1)
    T = np.eye(4)
    T[:3, :4] = values[:12].reshape(3, 4)
    node = int(rec['src_id'])
    if node < 0:
        return MapOdom(T)
    N = np.eye(4)
    N[:3, :4] = values[12:24].reshape(3, 4)
    return MapOdom(T, node, N)
