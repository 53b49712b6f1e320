"""Writing rosbag2 bags (mcap storage) without ROS, and the replay's output messages.

:class:`BagWriter` wraps :class:`rosbags.rosbag2.Writer`: topics are registered on first use and
the bag is always closed into a valid file (``metadata.yaml`` + one ``.mcap``), also when the
caller fails half-way, so partial outputs stay readable (Foxglove, ``mcap``, rosbags).

The bag is written as ``<path>.partial/<name>`` and renamed to ``<path>`` when closed
(:func:`ga_ros.safe_write.staging_directory`): a process killed half-way leaves
``<path>.partial``, which the next run into the same place removes, never a bag that looks
complete. A symbolic link at ``<path>`` is refused.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.io.bag_messages import header, matrix_to_pose_msg, typestore
from ga_ros.safe_write import commit_directory, remove_staging, staging_directory


class BagWriter:
    """An mcap rosbag2 bag being written.

    Parameters
    ----------
    path : output directory (rosbag2 layout: ``path/metadata.yaml`` and ``path/<name>.mcap``).
    overwrite : if True and ``path`` is an existing rosbag2 directory (only bag files: ``.mcap``,
        ``.db3``, ``metadata.yaml``; also the leftovers of a killed older run), it is replaced
        when the new bag is closed; any other existing path is an error (left untouched).
    storage : ``'mcap'`` (default) or ``'sqlite3'``.
    compress : zstd-compress the mcap chunks (readable by rosbags, ``mcap``, Foxglove, ros2 bag).
    """

    def __init__(self, path: str | Path, overwrite: bool = False, storage: str = 'mcap',
                 compress: bool = True) -> None:
        self.path = Path(path)
        self.overwrite = overwrite
        self.storage = storage
        self.compress = compress
        self._writer: Any = None
        self._staging: Path | None = None
        self._conns: dict[str, Any] = {}
        self.counts: dict[str, int] = {}

    def __enter__(self) -> BagWriter:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Create the bag; FormatError if the path exists and may not be replaced."""
        from rosbags.rosbag2 import CompressionFormat, CompressionMode, StoragePlugin, Writer

        plugin = {'mcap': StoragePlugin.MCAP, 'sqlite3': StoragePlugin.SQLITE3}.get(self.storage)
        if plugin is None:
            raise InputError(f"storage must be 'mcap' or 'sqlite3', got {self.storage!r}")
        if not self.overwrite and os.path.lexists(self.path):
            raise FormatError('output exists (will not overwrite: pass overwrite=True or choose '
                              'another path)', str(self.path))
        staging = staging_directory(self.path, self._replaceable)
        self._staging = staging
        try:
            writer = Writer(staging / self.path.name, version=9, storage_plugin=plugin)
            if self.compress and self.storage == 'mcap':
                writer.set_compression(CompressionMode.STORAGE, CompressionFormat.ZSTD)
            writer.open()
            self._writer = writer
        except Exception as exc:
            raise FormatError(f'cannot create bag: {exc}', str(self.path)) from exc

    def write(self, topic: str, msgtype: str, msg: Any, log_ns: int) -> None:
        """Serialise ``msg`` (a rosbags object of ``msgtype``) and append it at time ``log_ns``."""
        data = typestore().serialize_cdr(msg, msgtype)
        self.write_raw(topic, msgtype, data, log_ns)

    def write_raw(self, topic: str, msgtype: str, data: bytes, log_ns: int) -> None:
        """Append already serialised CDR ``data`` of ``msgtype`` at time ``log_ns``."""
        if self._writer is None:
            raise FormatError('bag is not open for writing', str(self.path))
        conn = self._conns.get(topic)
        if conn is None:
            conn = self._writer.add_connection(topic, msgtype, typestore=typestore())
            self._conns[topic] = conn
            self.counts[topic] = 0
        elif conn.msgtype != msgtype:
            raise InputError(f'topic {topic} already has type {conn.msgtype}, not {msgtype}')
        self._writer.write(conn, int(log_ns), data)
        self.counts[topic] += 1

    def close(self) -> None:
        """Finish the bag (writes the summary and ``metadata.yaml``) and move it to ``path``;
        idempotent."""
        if self._writer is not None:
            writer, self._writer = self._writer, None
            writer.close()
        if self._staging is not None:
            staging, self._staging = self._staging, None
            try:
                commit_directory(staging / self.path.name, self.path, self._replaceable)
                remove_staging(staging)
            except OSError as exc:
                raise FormatError(f'cannot move the finished bag into place: {exc}',
                                  str(self.path)) from None

    def _replaceable(self, path: Path) -> bool:
        """``path`` (an existing directory) may be replaced: ``overwrite`` is set and it holds
        only rosbag2 files (``metadata.yaml``, ``.mcap``, ``.db3``)."""
        allowed = {'.mcap', '.db3', '.yaml', '.db3-wal', '.db3-shm'}
        names = list(path.iterdir())
        return self.overwrite and all(p.is_file() and not p.is_symlink()
                                      and (p.suffix in allowed or p.name.endswith(tuple(allowed)))
                                      for p in names)


# --------------------------------------------------------------------------- output messages
def pose_with_covariance_msg(T_world_node: FloatArray, cov: FloatArray, frame_id: str,
                             stamp_ns: int) -> Any:
    """``geometry_msgs/PoseWithCovarianceStamped`` (rosbags): pose ``T_world_node`` with the 6x6
    covariance of its right perturbation, ``[x y z rx ry rz]``."""
    types = typestore().types
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (6, 6):
        raise InputError(f'covariance must be 6x6, got {cov.shape}')
    return types['geometry_msgs/msg/PoseWithCovarianceStamped'](
        header=header(frame_id, stamp_ns),
        pose=types['geometry_msgs/msg/PoseWithCovariance'](
            pose=matrix_to_pose_msg(T_world_node), covariance=cov.reshape(36).copy()))


def residual_color(normalized_residual: FloatArray, scale: float = 3.0) -> FloatArray:
    """Mahalanobis residual norms ``(m,)`` -> RGBA ``(m, 4)``: green at 0, yellow at ``scale/2``,
    red at ``scale`` and above, grey when non-finite (same palette as the alignment node)."""
    r = np.asarray(normalized_residual, dtype=float).reshape(-1)
    s = np.clip(np.nan_to_num(r, nan=0.0) / max(scale, 1e-12), 0.0, 1.0)
    rgba = np.empty((r.size, 4))
    rgba[:, 0] = np.clip(2.0 * s, 0.0, 1.0)
    rgba[:, 1] = np.clip(2.0 * (1.0 - s), 0.0, 1.0)
    rgba[:, 2] = 0.0
    rgba[:, 3] = 1.0
    rgba[~np.isfinite(r)] = (0.5, 0.5, 0.5, 1.0)
    return rgba


#: the network markers' node size and line width (m) and namespace
NODE_SCALE, LINE_WIDTH, NAMESPACE = 2.0, 0.5, 'ga'


def transform_msg(parent: str, child: str, T_parent_child: FloatArray, stamp_ns: int) -> Any:
    """``geometry_msgs/TransformStamped`` (rosbags): the pose of ``child`` in ``parent``."""
    types = typestore().types
    p, q = se3.to_pos_quat(np.asarray(T_parent_child, dtype=float))
    return types['geometry_msgs/msg/TransformStamped'](
        header=header(parent, stamp_ns), child_frame_id=child,
        transform=types['geometry_msgs/msg/Transform'](
            translation=types['geometry_msgs/msg/Vector3'](x=p[0], y=p[1], z=p[2]),
            rotation=types['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3])))


def tf_message(transforms: list[Any]) -> Any:
    """``tf2_msgs/TFMessage`` (rosbags) holding ``transforms`` (TransformStamped)."""
    return typestore().types['tf2_msgs/msg/TFMessage'](transforms=list(transforms))


def odometry_msg(T_world_node: FloatArray, cov: FloatArray, frame_id: str, child_frame_id: str,
                 stamp_ns: int) -> Any:
    """``nav_msgs/Odometry`` (rosbags) of a corrected pose (twist zero, its covariance -1:
    unknown), the stream evo and mapping nodes read."""
    types = typestore().types
    pwc = pose_with_covariance_msg(T_world_node, cov, frame_id, stamp_ns)
    vec = types['geometry_msgs/msg/Vector3']
    twist_cov = np.zeros(36)
    twist_cov[0] = -1.0
    return types['nav_msgs/msg/Odometry'](
        header=pwc.header, child_frame_id=child_frame_id, pose=pwc.pose,
        twist=types['geometry_msgs/msg/TwistWithCovariance'](
            twist=types['geometry_msgs/msg/Twist'](linear=vec(x=0.0, y=0.0, z=0.0),
                                                   angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=twist_cov))
