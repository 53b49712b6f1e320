"""PLY files of point clouds (ROS-free): binary little-endian, ``x y z intensity`` float32.

The layout (what CloudCompare, MeshLab, Open3D and PDAL read)::

    ply
    format binary_little_endian 1.0
    comment <text>                      (one line per comment)
    element vertex <n>
    property float x
    property float y
    property float z
    property float intensity
    end_header
    <n records of 16 bytes: x y z intensity, float32 little-endian>

Written through :mod:`ga_ros.safe_write` (temporary file, fsync, rename; links refused).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from ga_ros.errors import InputError
from ga_ros.safe_write import write_bytes

#: One vertex record: little-endian float32 ``x y z intensity``.
VERTEX_DTYPE = np.dtype([('x', '<f4'), ('y', '<f4'), ('z', '<f4'), ('intensity', '<f4')])


def ply_bytes(points: np.ndarray, intensity: np.ndarray, comments: tuple[str, ...] = ()
              ) -> bytes:
    """The PLY file of (n, 3) ``points`` (m) and (n,) ``intensity`` (module docstring).

    Raises
    ------
    InputError
        Shapes that do not match, or a comment holding a line break.
    """
    P = np.asarray(points)
    inten = np.asarray(intensity).reshape(-1)
    if P.ndim != 2 or P.shape[1] != 3 or inten.shape[0] != P.shape[0]:
        raise InputError(f'a PLY cloud needs (n, 3) points and (n,) intensities, got {P.shape} '
                         f'and {inten.shape}')
    if any('\n' in c or '\r' in c for c in comments):
        raise InputError('a PLY comment must be one line')
    rec = np.empty(P.shape[0], VERTEX_DTYPE)
    rec['x'], rec['y'], rec['z'] = P[:, 0], P[:, 1], P[:, 2]
    rec['intensity'] = inten
    header = ['ply', 'format binary_little_endian 1.0']
    header += [f'comment {c}' for c in comments]
    header += [f'element vertex {P.shape[0]}', 'property float x', 'property float y',
               'property float z', 'property float intensity', 'end_header']
    return ('\n'.join(header) + '\n').encode('ascii') + rec.tobytes()


def write_ply(path: str | os.PathLike, points: np.ndarray, intensity: np.ndarray,
              comments: tuple[str, ...] = ()) -> Path:
    """Write :func:`ply_bytes` to ``path`` atomically (:func:`ga_ros.safe_write.write_bytes`);
    returns the path."""
    return write_bytes(path, ply_bytes(points, intensity, comments))
