"""Trajectory files: TUM (``timestamp x y z qx qy qz qw``) and KITTI (3x4 of ``T_world_cam``).

* TUM RGB-D format: one pose per line, ``timestamp`` in seconds (written with 9 decimals, read
  exactly into integer nanoseconds), position ``x y z`` (m) and unit quaternion ``qx qy qz qw``
  of ``T_world_cam``; ``#`` comment lines are skipped.
* KITTI odometry format: one pose per line, the first three rows of ``T_world_cam`` row-major
  (``r11 r12 r13 tx r21 r22 r23 ty r31 r32 r33 tz``); no timestamps.

Readers validate every line (field count, numbers, unit quaternion / rotation matrix) and raise
:class:`FormatError` with ``file:line``; writers write to a temporary name and rename.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.safe_write import atomic_write

#: tolerance on |q| - 1 (TUM) and on ||R'R - I|| (KITTI) before a pose is rejected
_ROTATION_TOL = 1e-3


@dataclass(frozen=True)
class Trajectory:
    """The one trajectory type of ga_ros: timestamped poses of nodes, read and written by
    :mod:`ga_ros.io` in every format (TUM, KITTI, ``nav_msgs/Path`` in bags).

    Attributes
    ----------
    stamps_ns : (n,) int64 acquisition times, ns.
    T_world_node : (n, 4, 4) poses (node -> ``frame_id``).
    node_ids, track_ids : (n,) int64 ids, ``-1`` where unknown (default: all unknown).
    frame_id : frame the poses are expressed in.
    covariances : (n, 6, 6) pose covariances ``[x y z rx ry rz]`` (right perturbation), or None.
    """

    stamps_ns: IntArray
    T_world_node: FloatArray
    node_ids: IntArray | None = None
    track_ids: IntArray | None = None
    frame_id: str = 'map'
    covariances: FloatArray | None = None

    def __post_init__(self) -> None:
        n = int(np.asarray(self.stamps_ns).shape[0])
        for name in ('node_ids', 'track_ids'):
            if getattr(self, name) is None:
                object.__setattr__(self, name, np.full(n, -1, dtype=np.int64))

    def __len__(self) -> int:
        return int(self.stamps_ns.shape[0])

    @property
    def T_world_cam(self) -> FloatArray:
        """The poses, named as for a camera trajectory (same array as ``T_world_node``)."""
        return self.T_world_node


def _read_lines(path: str | os.PathLike) -> list[tuple[int, list[str]]]:
    try:
        text = Path(path).read_text()
    except (OSError, UnicodeDecodeError) as exc:
        raise FormatError(f'cannot read: {exc}', str(path)) from None
    out = []
    for lineno, raw in enumerate(text.splitlines(), start=1):
        fields = raw.replace(',', ' ').split()
        if fields and not fields[0].startswith('#'):
            out.append((lineno, fields))
    return out


def _floats(fields: list[str], path: str, line: int) -> FloatArray:
    try:
        values = np.array([float(f) for f in fields])
    except ValueError:
        raise FormatError(f'non-numeric value in {" ".join(fields)!r}', path, line) from None
    if not np.isfinite(values).all():
        raise FormatError('NaN or infinite value', path, line)
    return values


def _table(rows: list[tuple[int, list[str]]], first: int, path: str) -> FloatArray:
    """The numeric fields ``first:`` of every row as one (n, k) array (all converted at once;
    the first bad line is named on failure)."""
    try:
        values = np.array([f[first:] for _, f in rows], dtype=float)
    except ValueError:
        for lineno, fields in rows:
            _floats(fields[first:], path, lineno)
        raise
    finite = np.isfinite(values).all(axis=1)
    if not finite.all():
        raise FormatError('NaN or infinite value', path, rows[int(np.argmin(finite))][0])
    return values


#: Largest |stamp| (s) of a trajectory file: int64 nanoseconds reach 9.22e9 s (year 2262).
_MAX_STAMP_S = 9.2e9


def _stamp_ns(text: str, path: str, line: int) -> int:
    """Seconds as a decimal string -> integer ns, exactly (no float rounding)."""
    s = text.strip()
    neg = s.startswith('-')
    if neg or s.startswith('+'):
        s = s[1:]
    whole, _, frac = s.partition('.')
    shown = repr(text) if len(text) <= 40 else f'{text[:20]!r}... ({len(text)} characters)'
    if (not whole and not frac) or not (whole or '0').isdigit() or not (frac or '0').isdigit():
        try:  # exponent notation and the like: fall back to float
            seconds = float(text)
        except ValueError:
            raise FormatError(f'timestamp {shown} is not a number', path, line) from None
        if not abs(seconds) < _MAX_STAMP_S:
            raise FormatError(f'timestamp {shown} is not a time within +-{_MAX_STAMP_S:.3g} s',
                              path, line)
        return int(round(seconds * 1e9))
    if len(whole.lstrip('0')) > 10 or int(whole or '0') >= _MAX_STAMP_S:
        raise FormatError(f'timestamp {shown} is not a time within +-{_MAX_STAMP_S:.3g} s',
                          path, line)
    ns = int(whole or '0') * 10**9 + int((frac + '0' * 9)[:9])
    return -ns if neg else ns


def _write_atomic(path: str | os.PathLike, lines: list[str]) -> None:
    if not Path(path).parent.is_dir():
        raise FormatError(f'cannot write: no directory {Path(path).parent}', str(path))
    try:
        atomic_write(path, ''.join(line + '\n' for line in lines).encode())
    except OSError as exc:
        raise FormatError(f'cannot write: {exc}', str(path)) from None


def _check_poses(T: FloatArray) -> FloatArray:
    T = np.asarray(T, dtype=float)
    if T.ndim != 3 or T.shape[1:] != (4, 4):
        raise InputError(f'poses must have shape (n, 4, 4), got {T.shape}')
    if not np.isfinite(T).all():
        raise InputError('poses have NaN or inf entries; refusing to write them')
    return T


def read_tum(path: str | os.PathLike) -> Trajectory:
    """Read a TUM trajectory (``timestamp x y z qx qy qz qw`` per line; commas also accepted).

    Raises
    ------
    FormatError
        ``file:line`` of a line with a wrong field count, a non-numeric value, or a quaternion
        whose norm is not 1 (within 1e-3; otherwise it is normalised).
    """
    spath = str(path)
    rows = _read_lines(path)
    for lineno, fields in rows:
        if len(fields) != 8:
            raise FormatError(f'TUM line needs 8 fields (timestamp x y z qx qy qz qw), '
                              f'got {len(fields)}', spath, lineno)
    if not rows:
        return Trajectory(np.zeros(0, dtype=np.int64), np.zeros((0, 4, 4)))
    v = _table(rows, 1, spath)
    norms = np.linalg.norm(v[:, 3:], axis=1)
    bad = np.nonzero(np.abs(norms - 1.0) > _ROTATION_TOL)[0]
    if bad.size:
        k = int(bad[0])
        raise FormatError(f'quaternion has norm {norms[k]:.6g}, not 1', spath, rows[k][0])
    stamps = np.array([_stamp_ns(f[0], spath, ln) for ln, f in rows], dtype=np.int64)
    return Trajectory(stamps, se3.from_pos_quat(v[:, :3], v[:, 3:]))


def write_tum(path: str | os.PathLike, stamps_ns: IntArray, T_world_node: FloatArray,
              decimals: int | None = None) -> None:
    """Write a TUM trajectory.

    Parameters
    ----------
    path : output file.
    stamps_ns : (n,) integer timestamps (ns), written as seconds with 9 decimals.
    T_world_node : (n, 4, 4) poses.
    decimals : digits after the point of the pose values (None: the shortest text that reads
        back to the same float).
    """
    T = _check_poses(T_world_node)
    stamps = np.asarray(stamps_ns).reshape(-1)
    if stamps.shape[0] != T.shape[0]:
        raise InputError(f'{stamps.shape[0]} timestamps for {T.shape[0]} poses')
    if not np.issubdtype(stamps.dtype, np.integer):
        raise InputError('stamps_ns must be integers (nanoseconds)')
    p, q = se3.to_pos_quat(T)
    values = np.concatenate([p, q], axis=1)
    text = (values.astype(str) if decimals is None
            else np.char.mod(f'%.{int(decimals)}f', values))
    if not len(stamps):
        _write_atomic(path, ['# timestamp x y z qx qy qz qw'])
        return
    neg = np.where(stamps < 0, '-', '')
    a = np.abs(stamps.astype(np.int64))
    stamp_text = np.char.add(np.char.add(np.char.add(neg, (a // 10**9).astype(str)), '.'),
                             np.char.zfill((a % 10**9).astype(str), 9))
    rows = np.column_stack([stamp_text, text]) if len(stamps) else np.zeros((0, 8), str)
    lines = ['# timestamp x y z qx qy qz qw'] + [' '.join(r) for r in rows.tolist()]
    _write_atomic(path, lines)


def read_kitti(path: str | os.PathLike) -> FloatArray:
    """Read a KITTI pose file: ``(n, 4, 4)`` poses ``T_world_cam``.

    Raises
    ------
    FormatError
        ``file:line`` of a line without exactly 12 numbers or whose rotation block is not
        orthonormal (``max |R'R - I| > 1e-3``; otherwise it is projected onto SO(3)).
    """
    spath = str(path)
    lines = _read_lines(path)
    for lineno, fields in lines:
        if len(fields) != 12:
            raise FormatError(f'KITTI line needs 12 values (3x4 row-major), got {len(fields)}',
                              spath, lineno)
    if not lines:
        return np.zeros((0, 4, 4))
    M = _table(lines, 0, spath).reshape(-1, 3, 4)
    R = M[:, :, :3]
    err = np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max(axis=(1, 2))
    bad = np.nonzero((err > _ROTATION_TOL) | (np.linalg.det(R) <= 0))[0]
    if bad.size:
        k = int(bad[0])
        raise FormatError(f"rotation block is not a rotation (|R'R - I| = {err[k]:.3g})",
                          spath, lines[k][0])
    T = np.zeros((M.shape[0], 4, 4))
    U, _, Vt = np.linalg.svd(R)
    T[:, :3, :3] = U @ Vt
    T[:, :3, 3] = M[:, :, 3]
    T[:, 3, 3] = 1.0
    return T


def write_kitti(path: str | os.PathLike, T_world_cam: FloatArray) -> None:
    """Write poses ``(n, 4, 4)`` as KITTI lines (12 values, row-major ``[R | t]``)."""
    T = _check_poses(T_world_cam)
    lines = [' '.join(repr(float(x)) for x in T[k, :3, :].reshape(-1)) for k in range(T.shape[0])]
    _write_atomic(path, lines)
