"""The g2o record types (tags, field counts, dimension) and the vectorised parsing of their fields.

Each record type's lines are parsed as one numpy array; every parser raises a
:class:`~ga_ros.errors.FormatError` naming the file and line of the first bad field.
"""

from __future__ import annotations

import operator
from dataclasses import dataclass
from itertools import chain

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import FormatError
from ga_ros.geometry import se3
from ga_ros.io.g2o.planar import se2_to_se3

TAG_VERTEX_SE3 = 'VERTEX_SE3:QUAT'
TAG_EDGE_SE3 = 'EDGE_SE3:QUAT'
TAG_PARAMS_SE3 = 'PARAMS_SE3OFFSET'
TAG_VERTEX_SE2 = 'VERTEX_SE2'
TAG_EDGE_SE2 = 'EDGE_SE2'
TAG_PARAMS_SE2 = 'PARAMS_SE2OFFSET'
TAG_VERTEX_TORO = 'VERTEX2'
TAG_EDGE_TORO = 'EDGE2'
TAG_FIX = 'FIX'

#: tag -> (dimension, kind, allowed field counts including the tag)
RECORD_SPEC: dict[str, tuple[int, str, tuple[int, ...]]] = {
    TAG_VERTEX_SE3: (3, 'vertex', (9,)), TAG_EDGE_SE3: (3, 'edge', (31, 32)),
    TAG_PARAMS_SE3: (3, 'param', (9,)),
    TAG_VERTEX_SE2: (2, 'vertex', (5,)), TAG_EDGE_SE2: (2, 'edge', (12, 13)),
    TAG_PARAMS_SE2: (2, 'param', (5,)),
    TAG_VERTEX_TORO: (2, 'vertex', (5,)), TAG_EDGE_TORO: (2, 'edge', (12,)),
}
#: TORO's EDGE2 information order (ff fs ss rr fr sr) as positions of the g2o upper triangle
#: (11 12 13 22 23 33): g2o value k is TORO value TORO_FROM_G2O[k]
TORO_FROM_G2O = np.array([0, 1, 4, 2, 5, 3])
#: a quaternion whose norm is further than this from 1 is rejected rather than normalised
_QUAT_NORM_TOL = 1e-2


def _is_float(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def parse_floats(F: np.ndarray, lines: IntArray, path: str) -> FloatArray:
    """``(k, c)`` numbers of a ``(k, c)`` array of strings, or the first bad line's error."""
    try:
        values = F.astype(float)  # float() of each string, in C (~15 % faster than map)
    except ValueError:
        for row, line in zip(F.tolist(), lines.tolist()):  # error path only
            bad = [f for f in row if not _is_float(f)]
            if bad:
                raise FormatError(f'non-numeric value {bad[0]!r}', path, line) from None
        raise
    finite = np.isfinite(values).reshape(len(values), -1).all(axis=1)
    if not finite.all():
        raise FormatError('NaN or infinite value', path, int(lines[np.argmin(finite)]))
    return values


def parse_ids(F: np.ndarray, lines: IntArray, path: str, what: str = 'vertex id') -> IntArray:
    """``(k,)`` non-negative integer ids of a ``(k,)`` array of strings, or the first bad line's
    error."""
    try:
        values = np.fromiter(map(int, F), dtype=np.int64, count=F.size)
        ok = values >= 0
    except (ValueError, OverflowError):
        # error path only; 19 digits bound int() (Python refuses > 4300 digits with an error)
        ok = np.array([f.isdigit() and len(f) <= 19 and int(f) < 2**63 for f in F.tolist()])
        values = None
    if not ok.all():
        k = int(np.argmin(ok))
        text = str(F[k])
        shown = repr(text) if len(text) <= 40 else f'{text[:20]!r}... ({len(text)} characters)'
        raise FormatError(f'{what} must be a non-negative integer below 2^63, got {shown}', path,
                          int(lines[k]))
    return values


def _unit_quaternions(q: FloatArray, lines: IntArray, path: str) -> FloatArray:
    norm = np.linalg.norm(q, axis=1)
    bad = np.abs(norm - 1.0) > _QUAT_NORM_TOL
    if bad.any():
        k = int(np.argmax(bad))
        raise FormatError(f'quaternion [qx qy qz qw] has norm {norm[k]:.6g}, not 1', path,
                          int(lines[k]))
    return q / norm[:, None]


def first_duplicate(ids: IntArray, lines: IntArray) -> tuple[int, int, int] | None:
    """``(id, earlier line, later line)`` of the earliest repeated id (ids in line order)."""
    order = np.argsort(ids, kind='stable')
    s = ids[order]
    dup = np.flatnonzero(s[1:] == s[:-1])
    if dup.size == 0:
        return None
    later = lines[order[dup + 1]]
    k = int(np.argmin(later))
    return int(s[dup[k]]), int(lines[order[dup[k]]]), int(later[k])


@dataclass(frozen=True)
class RecordGroup:
    """The lines of one tag with one field count, as a ``(k, c)`` object array of strings."""

    tag: str
    lines: IntArray
    F: np.ndarray


def parse_poses(values: FloatArray, dim: int, lines: IntArray, path: str) -> FloatArray:
    """``(k, 4, 4)`` poses of ``[x y z qx qy qz qw]`` or ``[x y theta]`` rows."""
    if dim == 3:
        return se3.from_pos_quat(values[:, :3], _unit_quaternions(values[:, 3:7], lines, path))
    return se2_to_se3(values)


def split_lines(text: str, path: str
                 ) -> tuple[list[RecordGroup], list[tuple[int, list[str]]], list[list[str]]]:
    """Group the records by (tag, field count); ``FIX`` lines apart. Checks tags and counts.
    Also returns every line's fields (line ``k`` at ``k - 1``)."""
    rows = [ln.split() for ln in text.splitlines()]
    tag_list = [r[0] if r else '#' for r in rows]
    tags = np.array(tag_list)
    counts = np.fromiter(map(len, rows), dtype=np.int64, count=len(rows))
    lines = np.arange(1, len(rows) + 1)
    # not np.char.startswith: importing numpy.char costs a few ms of every command's start-up
    used = ~np.fromiter((t.startswith('#') for t in tag_list), dtype=bool, count=len(rows))
    known = np.isin(tags, [*RECORD_SPEC, TAG_FIX])
    if (used & ~known).any():
        k = int(np.argmax(used & ~known))
        raise FormatError(f'unknown tag {tags[k]!r} (supported: {", ".join(RECORD_SPEC)}, FIX)',
                          path, int(lines[k]))
    fix = [(int(lines[k]), rows[k][1:]) for k in np.flatnonzero(tags == TAG_FIX)]
    groups: list[RecordGroup] = []
    for tag, (_, _, allowed) in RECORD_SPEC.items():
        mine = tags == tag
        wrong = mine & ~np.isin(counts, allowed)
        if wrong.any():
            k = int(np.argmax(wrong))
            need = ' or '.join(map(str, allowed))
            raise FormatError(f'{tag} needs {need} fields, got {counts[k]}', path, int(lines[k]))
        for c in allowed:
            idx = np.flatnonzero(mine & (counts == c))
            if idx.size:
                F = np.array(list(chain.from_iterable(operator.itemgetter(*idx)(rows)))
                             if idx.size > 1 else rows[idx[0]], dtype=object)
                groups.append(RecordGroup(tag, lines[idx], F.reshape(idx.size, c)))
    return groups, fix, rows


def graph_dim(groups: list[RecordGroup], spath: str) -> int:
    """The graph's dimension, 2 or 3; refuses a mix of 2-D and 3-D records or an empty file."""
    first = {d: min((int(g.lines[0]) for g in groups if RECORD_SPEC[g.tag][0] == d), default=0)
             for d in (2, 3)}
    if first[2] and first[3]:
        later, earlier = max(first[2], first[3]), min(first[2], first[3])
        d_late = 2 if first[2] == later else 3
        raise FormatError(f'this is a {d_late}-D record but line {earlier} made this a '
                          f'{5 - d_late}-D graph; mixed files are not supported', spath, later)
    if not groups:
        raise FormatError('no vertices and no edges (VERTEX_SE3:QUAT / EDGE_SE3:QUAT or '
                          'VERTEX_SE2 / EDGE_SE2 lines) found', spath)
    return 3 if first[3] else 2


def groups_of_kind(groups: list[RecordGroup], name: str) -> list[RecordGroup]:
    """The groups of one record kind (``'param'``, ``'vertex'`` or ``'edge'``)."""
    return [g for g in groups if RECORD_SPEC[g.tag][1] == name]
