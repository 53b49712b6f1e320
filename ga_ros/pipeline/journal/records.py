"""The journal's record format: one fixed-size little-endian record per measurement or per half
of an absolute fix, with its CRC-32, and the conversions between records and measurements / fixes
(format in :mod:`ga_ros.pipeline.journal`)."""

from __future__ import annotations

import zlib

import numpy as np

from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.core.gaps import reversed_measurement
from ga_ros.core.measurement import KINDS, Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3

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
#: The kind byte without its flag bits (:data:`HELD`, :data:`REVERSED`).
KIND_MASK = 0x3F


def record_crcs(records: np.ndarray) -> np.ndarray:
    """CRC-32 of the first 377 bytes (the payload) of each row of a contiguous ``(n, 381)``
    uint8 array of records."""
    flat = memoryview(np.ascontiguousarray(records).reshape(-1))
    size = RECORD.itemsize
    return np.fromiter((zlib.crc32(flat[k:k + PAYLOAD]) for k in range(0, flat.nbytes, size)),
                       dtype=np.uint32, count=records.shape[0])


def kind_ok(kind: np.ndarray | int) -> np.ndarray | bool:
    return ((kind & KIND_MASK) < len(KINDS)) | (kind == _FIX) | (kind == _FIX_SENSOR)


def is_fix(kind: np.ndarray) -> np.ndarray:
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
    rec['crc'] = record_crcs(raw)
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


def records_to_entries(recs: np.ndarray, taken: bool = False) -> list[Entry]:
    """Journal records (structured array) as measurements and fixes (:class:`FixTerm`), in
    order; a ``fix`` record without its ``fix_sensor`` record (or the reverse) is skipped. The
    measurements as they arrived, or as the aligner took them if ``taken`` (:func:`as_taken`).
    """
    kinds = recs['kind']
    fix_at = np.flatnonzero(is_fix(kinds))
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
    return [Measurement(a, b, c, d, z[k], cov[k], e, KINDS[f & KIND_MASK])
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
