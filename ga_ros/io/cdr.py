"""``nav_msgs/msg/Path`` serialized directly from arrays (CDR, what DDS sends).

A corrected path of 100,000 poses built as rclpy message objects (one ``PoseStamped`` each) and
then serialized takes seconds of the node's time (``ga-ros bench path-msg``); the same
bytes written with numpy take milliseconds. ``Publisher.publish`` accepts them as they are
(rclpy publishes ``bytes`` raw). The layout is plain CDR (XCDR1, little endian, the
encapsulation header ``00 01 00 00``): every primitive aligned to its size from the start of
the payload; checked byte for byte against ``rclpy.serialization.serialize_message`` in
``test/ros/test_path_outputs.py``.

ROS-free (no rclpy import).
"""

from __future__ import annotations

import struct
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import InputError
from ga_ros.geometry import se3

_ENCAPSULATION = b'\x00\x01\x00\x00'  # CDR, little endian


def _pad(n: int, k: int) -> int:
    return -n % k


def path_cdr(T_world_node: FloatArray, stamps_ns: IntArray, frame_id: str,
             stamp_ns: int | None = None) -> bytes:
    """Serialized ``nav_msgs/msg/Path`` of poses ``(n, 4, 4)`` in ``frame_id``.

    The same message as ``conversions.path_to_msg(T_world_node, stamps_ns, frame_id,
    stamp_ns)`` serialized: each pose stamped with ``stamps_ns`` (ns >= 0), orientation as a
    unit quaternion ``x y z w`` with ``w >= 0``; the path's header stamp is ``stamp_ns``
    (default: the last pose's stamp, 0 for an empty path).
    """
    buf = PathCdr(frame_id)
    buf.update(T_world_node, stamps_ns)
    if stamp_ns is None:
        stamp_ns = int(np.asarray(stamps_ns).reshape(-1)[-1]) if buf.n else 0
    return buf.message(stamp_ns)


class PathCdr:
    """A serialized ``nav_msgs/msg/Path`` kept up to date row by row (:func:`path_cdr` is its
    one-shot use): an update re-encodes only the rows that changed and appends the new ones.

    Every pose element has the same size for one ``frame_id`` (only the first one's padding
    differs), so row ``k`` sits at a fixed offset: :meth:`update` writes rows ``from_row ..
    n - 1`` in place (the rows before are kept as encoded), :meth:`message` joins the header
    and the rows (one copy of the buffer, the message's own size). The buffer grows by
    doubling, so appending costs O(1) per pose.

    Parameters
    ----------
    frame_id : the path's and every pose's ``header.frame_id``.
    """

    def __init__(self, frame_id: str) -> None:
        self.frame_id = frame_id
        frame = frame_id.encode() + b'\x00'
        self._L = L = len(frame)
        self._head0 = struct.pack('<iII', 0, 0, L) + frame
        self._head0 += b'\x00' * _pad(len(self._head0), 4)
        # one PoseStamped: sec, nanosec, frame_id (length + bytes), padding to 8, 7 doubles.
        # The first element starts 4-aligned, the next ones 8-aligned (each ends with doubles).
        start = len(self._head0) + 4                 # the element count follows
        self._first_pad = _pad(start + 12 + L, 8)
        self._stride = 12 + L + _pad(12 + L, 8) + 56
        self._first = self._stride - _pad(12 + L, 8) + self._first_pad
        self._fixed = np.frombuffer(struct.pack('<I', L) + frame, np.uint8)
        self._body = np.zeros(0, np.uint8)
        self.n = 0

    def _offset(self, k: int) -> int:
        """Byte offset of row ``k`` in the rows' buffer."""
        return 0 if k == 0 else self._first + (k - 1) * self._stride

    def update(self, T_world_node: FloatArray, stamps_ns: IntArray, from_row: int = 0) -> None:
        """The path is now ``n`` rows whose rows ``from_row ..`` are ``T_world_node`` (k, 4, 4)
        and ``stamps_ns`` (k,) ns (so ``n = from_row + k``); rows before ``from_row`` keep
        their encoding (the caller knows they did not change). ``from_row`` is at most the
        rows held.

        Raises
        ------
        InputError
            Mismatched lengths, a negative stamp or ``from_row`` beyond the rows held.
        """
        T = np.asarray(T_world_node, dtype=float).reshape(-1, 4, 4)
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        lo, k = int(from_row), T.shape[0]
        if stamps.shape[0] != k:
            raise InputError(f'{k} poses but {stamps.shape[0]} stamps')
        if not 0 <= lo <= self.n:
            raise InputError(f'row {lo} is beyond the {self.n} rows held')
        if k and stamps.min() < 0:
            raise InputError('stamps must be >= 0 ns')
        n = lo + k
        size = self._offset(n)
        if size > self._body.size:
            body = np.zeros(max(size, 2 * self._body.size, 4096), np.uint8)
            held = self._offset(self.n)
            body[:held] = self._body[:held]
            self._body = body
        self.n = n
        if not k:
            return
        p, q = se3.to_pos_quat(T)
        values = np.concatenate([p, q], axis=1)                      # (k, 7) float64
        secs, nsecs = np.divmod(stamps, 1_000_000_000)
        L = self._L

        def fill(rows: np.ndarray, sl: slice, pad: int) -> None:
            rows[:, 0:4] = secs[sl].astype('<i4')[:, None].view(np.uint8)
            rows[:, 4:8] = nsecs[sl].astype('<u4')[:, None].view(np.uint8)
            rows[:, 8:12 + L] = self._fixed
            d = 12 + L + pad
            rows[:, d:d + 56] = np.ascontiguousarray(values[sl].astype('<f8')).view(np.uint8)

        i = 0
        if lo == 0:   # the first element: its own padding
            fill(self._body[:self._first].reshape(1, self._first), slice(0, 1), self._first_pad)
            i = 1
        if i < k:
            a = self._offset(lo + i)
            rows = self._body[a:a + (k - i) * self._stride].reshape(k - i, self._stride)
            fill(rows, slice(i, k), _pad(12 + L, 8))

    def rewrite(self, rows: IntArray, T_world_node: FloatArray, stamps_ns: IntArray) -> None:
        """Encode again the rows ``rows`` (each below the rows held) with ``T_world_node``
        (k, 4, 4) and ``stamps_ns`` (k,) ns; the other rows are kept."""
        T = np.asarray(T_world_node, dtype=float).reshape(-1, 4, 4)
        stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
        n = self.n
        for k, r in enumerate(np.asarray(rows, np.int64).reshape(-1).tolist()):
            if not 0 <= r < n:
                raise InputError(f'row {r} is beyond the {n} rows held')
            self.update(T[k:k + 1], stamps[k:k + 1], r)   # row r (n is then r + 1) ...
            self.n = n                                     # ... the rows after it kept

    def message(self, stamp_ns: int) -> bytes:
        """The serialized path of the rows held, its header stamped ``stamp_ns`` (ns >= 0)."""
        if stamp_ns < 0:
            raise InputError('stamps must be >= 0 ns')
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        head = struct.pack('<iI', sec, nsec) + self._head0[8:] + struct.pack('<I', self.n)
        return _ENCAPSULATION + head + self._body[:self._offset(self.n)].tobytes()


def framed_path_cdr(T_world_node: FloatArray, stamps_ns: IntArray, pose_frames: list[str],
                    frame_id: str, stamp_ns: int) -> bytes:
    """Serialized ``nav_msgs/msg/Path`` whose poses each carry their own ``header.frame_id``
    (``pose_frames[i]``, e.g. a node frame ``ga/<track>/<node>``); the path's header is
    ``frame_id`` at ``stamp_ns``. Poses ``(n, 4, 4)`` stamped with ``stamps_ns`` (ns >= 0),
    orientation a unit quaternion ``x y z w`` with ``w >= 0``.

    One ``struct`` pack per pose (the frames differ in length, so the layout is not a fixed
    stride as in :func:`path_cdr`): microseconds per pose, against ~0.15 ms for an rclpy
    ``PoseStamped``. Checked against ``rclpy.serialization`` in ``test/ros/test_path_outputs.py``.
    """
    T = np.asarray(T_world_node, dtype=float).reshape(-1, 4, 4)
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    n = T.shape[0]
    if stamps.shape[0] != n or len(pose_frames) != n:
        raise InputError(f'{n} poses but {stamps.shape[0]} stamps and {len(pose_frames)} frames')
    if (n and stamps.min() < 0) or stamp_ns < 0:
        raise InputError('stamps must be >= 0 ns')
    frame = frame_id.encode() + b'\x00'
    sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
    out = bytearray(struct.pack('<iII', sec, nsec, len(frame)) + frame)
    out += b'\x00' * _pad(len(out), 4) + struct.pack('<I', n)
    if n:
        p, q = se3.to_pos_quat(T)
        values = np.concatenate([p, q], axis=1).tolist()
        secs, nsecs = np.divmod(stamps, 1_000_000_000)
        secs, nsecs = secs.tolist(), nsecs.tolist()
    for k in range(n):   # offsets count from the payload's start (after the encapsulation)
        f = pose_frames[k].encode() + b'\x00'
        out += b'\x00' * _pad(len(out), 4)
        out += struct.pack('<iII', secs[k], nsecs[k], len(f)) + f
        out += b'\x00' * _pad(len(out), 8)
        out += struct.pack('<7d', *values[k])
    return _ENCAPSULATION + bytes(out)


class _Writer:
    """CDR (XCDR1, little endian) written field by field: every primitive aligned to its size
    from the start of the payload (after the encapsulation header)."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []
        self.n = 0

    def align(self, k: int) -> None:
        pad = _pad(self.n, k)
        if pad:
            self.raw(b'\x00' * pad)

    def raw(self, data: bytes) -> None:
        self.parts.append(data)
        self.n += len(data)

    def put(self, fmt: str, *values: Any, align: int) -> None:
        self.align(align)
        self.raw(struct.pack('<' + fmt, *values))

    def string(self, text: str) -> None:
        data = text.encode() + b'\x00'
        self.put('I', len(data), align=4)
        self.raw(data)

    def header(self, frame_id: str, stamp_ns: int) -> None:
        sec, nsec = divmod(int(stamp_ns), 1_000_000_000)
        self.put('iI', sec, nsec, align=4)
        self.string(frame_id)

    def array(self, values: np.ndarray, dtype: str, align: int) -> None:
        """A sequence of fixed-size elements: its count, then the values (k, ...) as ``dtype``,
        the first aligned to ``align`` (nothing but the count when empty)."""
        a = np.ascontiguousarray(values, dtype=dtype)
        self.put('I', a.shape[0], align=4)
        if a.shape[0]:
            self.align(align)
            self.raw(a.tobytes())


def network_markers_cdr(p_world_node: FloatArray, src_index: IntArray, dst_index: IntArray,
                        rgba: FloatArray, frame_id: str, stamp_ns: int, node_scale: float,
                        line_width: float, namespace: str) -> bytes:
    """Serialized ``visualization_msgs/MarkerArray`` of the connection network, in the layout
    of the alignment node's markers (a ``DELETEALL`` marker, a ``SPHERE_LIST`` of the nodes
    ``p_world_node`` (n, 3), a ``LINE_LIST`` of the connections ``src_index -> dst_index``
    coloured ``rgba`` (m, 4)), written from the arrays: the bytes rosbags serializes for the
    same message built object by object (checked in ``test/replay/test_stamped_path.py``),
    at a copy's cost per node instead of a message object per point."""
    p = np.asarray(p_world_node, dtype=float).reshape(-1, 3)
    src = np.asarray(src_index, dtype=np.int64).reshape(-1)
    dst = np.asarray(dst_index, dtype=np.int64).reshape(-1)
    pos, quat = se3.to_pos_quat(np.eye(4))
    pose = [float(v) for v in pos.tolist() + quat.tolist()]
    w = _Writer()
    w.put('I', 3, align=4)

    def marker(kind: int, action: int, mid: int, ns: str, scale: float, points: np.ndarray,
               color: tuple[float, ...], colors: np.ndarray) -> None:
        w.header(frame_id, stamp_ns)
        w.string(ns)
        w.put('iii', mid, kind, action, align=4)
        w.put('7d', *pose, align=8)
        w.put('3d', scale, scale, scale, align=8)
        w.put('4f', *color, align=4)
        w.put('iI', 0, 0, align=4)          # lifetime
        w.put('?', False, align=1)          # frame_locked
        w.array(points, '<f8', 8)
        w.array(colors, '<f4', 4)
        w.string('')                        # texture_resource
        w.header('', 0)                     # texture: header, format, data
        w.string('')
        w.put('I', 0, align=4)
        w.put('I', 0, align=4)              # uv_coordinates
        w.string('')                        # text
        w.string('')                        # mesh_resource
        w.string('')                        # mesh_file: filename, data
        w.put('I', 0, align=4)
        w.put('?', False, align=1)          # mesh_use_embedded_materials

    white = (1.0, 1.0, 1.0, 1.0)
    none = np.zeros((0, 3))
    marker(0, 3, 0, namespace, 1.0, none, white, np.zeros((0, 4)))       # ARROW, DELETEALL
    marker(7, 0, 0, namespace + '/nodes', float(node_scale), p, (0.2, 0.4, 1.0, 1.0),
           np.zeros((0, 4)))                                             # SPHERE_LIST, ADD
    ends = np.empty((2 * src.size, 3))
    ends[0::2] = p[src]
    ends[1::2] = p[dst]
    marker(5, 0, 1, namespace + '/connections', float(line_width), ends, white,
           np.repeat(np.asarray(rgba, float).reshape(-1, 4), 2, axis=0))  # LINE_LIST, ADD
    return _ENCAPSULATION + b''.join(w.parts)
