"""``sensor_msgs/PointCloud2`` -> numpy by the message's own field descriptions (ROS-free).

Reads rclpy and rosbags messages alike (fields by name: ``fields``, ``point_step``,
``row_step``, ``height``, ``width``, ``is_bigendian``, ``data``), as RViz and Foxglove do: each
of ``x``, ``y``, ``z`` (and ``intensity`` when present) at its ``offset`` with its ``datatype``
(any of the eight ``PointField`` types), records ``point_step`` bytes apart, rows ``row_step``
bytes apart, in the byte order ``is_bigendian`` says. Points with a non-finite coordinate are
dropped (a cloud with ``is_dense`` false may hold NaN for invalid pixels).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ga_ros.errors import InputError
from ga_ros.vo.messages import message_bytes

#: ``sensor_msgs/PointField`` datatype constants -> numpy type (without byte order).
POINTFIELD_TYPES = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}


@dataclass(frozen=True)
class DecodedCloud:
    """Points of a ``PointCloud2``.

    Attributes
    ----------
    points : (n, 3) float32 ``x y z`` in the message's ``header.frame_id`` (m).
    intensity : (n,) float32 ``intensity`` field (0 where the cloud has none).
    dropped : points left out for a non-finite coordinate.
    """

    points: np.ndarray
    intensity: np.ndarray
    dropped: int


def decode_pointcloud2(msg: Any) -> DecodedCloud:
    """The ``x y z`` (and ``intensity``) of a ``PointCloud2`` (module docstring).

    Raises
    ------
    InputError
        No ``x``/``y``/``z`` field, an unknown datatype, a field beyond ``point_step``, or data
        shorter than ``height`` rows of ``row_step`` bytes.
    """
    fields = {str(f.name): f for f in msg.fields}
    missing = [n for n in 'xyz' if n not in fields]
    if missing:
        raise InputError(f'PointCloud2 without field(s) {", ".join(missing)} (has '
                         f'{", ".join(fields) or "none"})')
    step, h, w = int(msg.point_step), int(msg.height), int(msg.width)
    row = int(msg.row_step)
    order = '>' if msg.is_bigendian else '<'
    names = [n for n in ('x', 'y', 'z', 'intensity') if n in fields]
    formats, offsets = [], []
    for n in names:
        f = fields[n]
        t = POINTFIELD_TYPES.get(int(f.datatype))
        if t is None:
            raise InputError(f'PointCloud2 field {n}: unknown datatype {f.datatype}')
        size = np.dtype(t).itemsize
        if int(f.offset) + size > step:
            raise InputError(f'PointCloud2 field {n} at offset {f.offset} lies beyond point_step '
                             f'{step}')
        formats.append(order + t)
        offsets.append(int(f.offset))
    data = message_bytes(msg.data)
    if h * w == 0:
        return DecodedCloud(np.zeros((0, 3), np.float32), np.zeros(0, np.float32), 0)
    if step <= 0 or row < w * step or data.size < h * row:
        raise InputError(f'PointCloud2 data of {data.size} bytes does not hold {h} rows of '
                         f'{row} bytes ({w} points of {step} bytes)')
    rows = data[:h * row].reshape(h, row)[:, :w * step]
    dt = np.dtype({'names': names, 'formats': formats, 'offsets': offsets, 'itemsize': step})
    rec = np.ascontiguousarray(rows).view(dt).reshape(-1)
    P = np.stack([rec['x'], rec['y'], rec['z']], axis=1).astype(np.float32)
    inten = (rec['intensity'].astype(np.float32) if 'intensity' in names
             else np.zeros(len(rec), np.float32))
    ok = np.all(np.isfinite(P), axis=1)
    if not ok.all():
        P, inten = P[ok], inten[ok]
    return DecodedCloud(P, inten, int((~ok).sum()))
