"""``map_node``: the point-cloud map of the keyframe clouds at their corrected poses.

An adapter of :class:`ga_ros.pipeline.cloud_map.CloudMapBuilder` (the replay's ``--map``
builds the same map, :mod:`ga_ros.replay.map_outputs`): it subscribes to

* ``ga/keyframe_cloud`` (``sensor_msgs/PointCloud2`` of ``vo_node``, in the camera's frame,
  stamped with the keyframe's stamp; decoded by its own field descriptions,
  :func:`ga_ros.mapping.pointcloud2.decode_pointcloud2`);
* ``ga/corrections`` (``nav_msgs/Path``: the keyframes that moved or were added, the
  ``ga/full_path`` marker at restarts; ``docs/node.md``): only the keyframes named are
  re-anchored, so an update costs in proportion to what moved, not to the map's size;
* ``ga/corrected_path`` (transient local): every keyframe, used until the first corrections
  message (a map node started after the alignment node);
* ``/tf_static``: the camera's extrinsic ``base_frame -> <cloud frame>`` (else the parameter
  ``T_base_camera``, else the identity with ``assume_identity_extrinsic``; clouds wait for it).

Publishes ``ga/map`` (``sensor_msgs/PointCloud2`` in ``map_frame``, transient local, fields
``x y z intensity`` float32: one point per occupied voxel of ``voxel_m``), every
``publish_period_sec`` when the map changed. Service ``~/save_map`` (``std_srvs/Trigger``)
writes the map to ``map_file`` (binary little-endian PLY, :mod:`ga_ros.mapping.ply`), as does
the node's shutdown with ``save_on_shutdown``. Memory is bounded
(:class:`ga_ros.mapping.cloud_map.CloudMapConfig`: per-keyframe decimation, a static layer
beyond ``max_live_keyframes``). A bad message is counted, warned about (throttled) and dropped;
the node goes on.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from nav_msgs.msg import Path as PathMsg
from rclpy.node import Node
from sensor_msgs.msg import PointCloud2
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from ga_ros import topics
from ga_ros.core.extrinsic import ExtrinsicConfig
from ga_ros.errors import GaError
from ga_ros.mapping.cloud_map import CloudMapConfig
from ga_ros.mapping.ply import write_ply
from ga_ros.mapping.pointcloud2 import decode_pointcloud2
from ga_ros.pipeline.cloud_map import CloudMapBuilder
from ga_ros.pipeline.journal.state_files import default_state_file
from ga_ros.pipeline.params import parameter_names
from ga_ros.ros import conversions as conv
from ga_ros.ros.bounded_log import BoundedLogging
from ga_ros.ros.params import declare_config
from ga_ros.ros.qos import latched_qos, stream_qos, tf_static_qos
from ga_ros.ros.runner import node_usage, run_node

NODE_NAME = 'map_node'
#: Depth of the corrections subscription (as the alignment node's publisher).
CORRECTIONS_DEPTH = 100


@dataclass(frozen=True)
class MapNodeSettings:
    """ROS-side settings of :class:`MapNode` (``config/map.yaml``).

    Attributes
    ----------
    keyframe_cloud_topic : input keyframe clouds (``PointCloud2`` in the camera's frame).
    corrections_topic : input corrections (``nav_msgs/Path``).
    path_topic : input corrected path (``nav_msgs/Path``, transient local).
    map_topic : output map (``PointCloud2`` in ``map_frame``, transient local).
    map_frame : frame of the map and of the poses (REP 105 ``map``).
    publish_period_sec : the map is published at most this often, when it changed (s).
    map_file : where ``~/save_map`` and the shutdown write the map (PLY); '' = ``$ROS_HOME/
        ga_ros/<namespace>/<node name>/map.ply``.
    save_on_shutdown : write ``map_file`` when the node shuts down (if the map has points).
    cloud_queue : depth of the keyframe-cloud subscription (messages).
    tf_static_topic : static TF topic read for the camera's extrinsic.
    warn_throttle_sec : minimum seconds between repeated warnings.
    """

    keyframe_cloud_topic: str = topics.KEYFRAME_CLOUD
    corrections_topic: str = topics.CORRECTIONS
    path_topic: str = topics.CORRECTED_PATH
    map_topic: str = topics.MAP_CLOUD
    map_frame: str = 'map'
    publish_period_sec: float = 1.0
    map_file: str = ''
    save_on_shutdown: bool = True
    cloud_queue: int = 20
    tf_static_topic: str = '/tf_static'
    warn_throttle_sec: float = 5.0


def corrections_from_msg(msg: Any) -> tuple[bool, np.ndarray, np.ndarray]:
    """``(full, stamps_ns, T_map_base)`` of a ``ga/corrections`` message: ``full`` when its
    first pose is the :data:`ga_ros.topics.CORRECTIONS_FULL_FRAME` marker (then left out).

    Raises
    ------
    InputError
        A pose that is not a valid transform (:func:`ga_ros.ros.conversions.path_msg_to_poses`).
    """
    poses = list(msg.poses)
    full = bool(poses) and poses[0].header.frame_id == topics.CORRECTIONS_FULL_FRAME
    T = conv.path_msg_to_poses(msg).reshape(-1, 4, 4)
    stamps = np.array([conv.stamp_to_ns(ps.header.stamp) for ps in poses], dtype=np.int64)
    if full:
        T, stamps = T[1:], stamps[1:]
    return full, stamps, T


class MapNode(BoundedLogging, Node):
    """Adapter: clouds, corrections, path -> :class:`CloudMapBuilder` -> ``ga/map``."""

    def __init__(self, **kwargs: Any) -> None:
        """``kwargs`` go to :class:`rclpy.node.Node` (e.g. ``context``,
        ``parameter_overrides`` in tests)."""
        super().__init__(NODE_NAME, **kwargs)
        self.settings: MapNodeSettings = declare_config(self, MapNodeSettings)
        self.map_config: CloudMapConfig = declare_config(self, CloudMapConfig)
        self.extrinsic_config: ExtrinsicConfig = declare_config(self, ExtrinsicConfig)
        self.extrinsic_config.from_parameters()  # a malformed T_base_camera fails at start
        s = self.settings
        self.builder = CloudMapBuilder(self.map_config, self.extrinsic_config)
        self.map_file = Path(s.map_file) if s.map_file else (
            default_state_file(self.get_namespace(), self.get_name()).parent / 'map.ply')
        self.counts = {'bad_clouds': 0, 'bad_corrections': 0, 'bad_paths': 0, 'published': 0,
                       'saved': 0}
        self._last_warn: dict[str, float] = {}
        self.pub_map = self.create_publisher(PointCloud2, s.map_topic, latched_qos(1))
        self.create_subscription(TFMessage, s.tf_static_topic, self._on_tf_static,
                                 tf_static_qos())
        self.create_subscription(PointCloud2, s.keyframe_cloud_topic, self._on_cloud,
                                 stream_qos(max(1, s.cloud_queue)))
        self.create_subscription(PathMsg, s.corrections_topic, self._on_corrections,
                                 stream_qos(CORRECTIONS_DEPTH))
        self.create_subscription(PathMsg, s.path_topic, self._on_path, latched_qos(1))
        self.create_service(Trigger, '~/save_map', self._on_save)
        if s.publish_period_sec > 0:
            self.create_timer(s.publish_period_sec, self.publish_map)

    # ------------------------------------------------------------------ callbacks
    def _warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last_warn.get(key, -1e18) >= self.settings.warn_throttle_sec:
            self._last_warn[key] = now
            self.get_logger().warning(text)

    def _on_tf_static(self, msg: TFMessage) -> None:
        self.builder.add_tf_static(msg)

    def _on_cloud(self, msg: PointCloud2) -> None:
        try:
            cloud = decode_pointcloud2(msg)
            self.builder.add_cloud(conv.stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                                   cloud.points, cloud.intensity)
        except (GaError, ValueError) as exc:
            self.counts['bad_clouds'] += 1
            self._warn('cloud', f'keyframe cloud dropped: {exc}')
            return
        if self.builder.extrinsic_error:
            self._warn('extrinsic', f'keyframe clouds wait: {self.builder.extrinsic_error}')

    def _on_corrections(self, msg: PathMsg) -> None:
        try:
            full, stamps, T = corrections_from_msg(msg)
            self.builder.on_corrections(full, stamps, T)
        except (GaError, ValueError) as exc:
            self.counts['bad_corrections'] += 1
            self._warn('corrections', f'corrections message dropped: {exc}')

    def _on_path(self, msg: PathMsg) -> None:
        if self.builder.corrections_seen:
            return
        try:
            T = conv.path_msg_to_poses(msg).reshape(-1, 4, 4)
            stamps = np.array([conv.stamp_to_ns(ps.header.stamp) for ps in msg.poses],
                              dtype=np.int64)
            self.builder.on_path(stamps, T)
        except (GaError, ValueError) as exc:
            self.counts['bad_paths'] += 1
            self._warn('path', f'corrected path dropped: {exc}')

    # ------------------------------------------------------------------ outputs
    def publish_map(self, force: bool = False) -> bool:
        """Publish the map if it changed since the last time (or ``force``); True if sent."""
        if not (self.builder.take_changed() or force):
            return False
        cloud = self.builder.cloud()
        self.pub_map.publish(conv.cloud_to_pointcloud2(
            cloud.points, cloud.intensity, self.settings.map_frame,
            self.get_clock().now().nanoseconds))
        self.counts['published'] += 1
        return True

    def save_map(self) -> tuple[Path, int]:
        """Write the map to ``map_file`` (PLY); returns the path and the points written.

        Raises
        ------
        GaError
            The file cannot be written (a link, a directory, no permission).
        """
        cloud = self.builder.cloud()
        path = write_ply(self.map_file, cloud.points, cloud.intensity,
                         comments=(f'ga_ros map_node map, frame {self.settings.map_frame}',))
        self.counts['saved'] += 1
        return path, len(cloud)

    def _on_save(self, _request: Trigger.Request, response: Trigger.Response
                 ) -> Trigger.Response:
        try:
            path, n = self.save_map()
        except GaError as exc:
            response.success, response.message = False, f'map not saved: {exc}'
            return response
        response.success, response.message = True, f'{n} points written to {path}'
        return response

    def destroy_node(self) -> None:
        """Save the map (``save_on_shutdown``, when it has points), then destroy the node."""
        if self.settings.save_on_shutdown and len(self.builder.map.voxels):
            try:
                path, n = self.save_map()
                print(f'{NODE_NAME}: {n} points written to {path}', file=sys.stderr)
            except GaError as exc:
                print(f'{NODE_NAME}: map not saved at shutdown: {exc}', file=sys.stderr)
        super().destroy_node()

    def diagnostic_values(self) -> dict[str, object]:
        """Counts and sizes of the map (for tests and logs)."""
        m, c = self.builder.map, self.builder.counts
        return {'clouds': c.clouds, 'clouds_waiting': len(self.builder.waiting),
                'corrections': c.corrections, 'full_corrections': c.full, 'paths': c.paths,
                'moved': c.moved, 'points_moved': c.points_moved, 'live_keyframes': m.n_live,
                'static_keyframes': m.n_static, 'unplaced_clouds': m.n_unplaced,
                'voxels': len(m.voxels), 'bytes': m.nbytes(), **self.counts}


def declared_parameters() -> list[str]:
    """Every parameter ``map_node`` declares (built from its config dataclasses, no rclpy)."""
    return (parameter_names(MapNodeSettings) + parameter_names(CloudMapConfig)
            + parameter_names(ExtrinsicConfig))


def main(args: list[str] | None = None) -> int:
    """Console entry point ``map_node`` (also ``python -m ga_ros.ros.map_node``)."""
    return run_node(MapNode, NODE_NAME, args,
                    usage=lambda: node_usage(NODE_NAME, __doc__, declared_parameters()))


if __name__ == '__main__':
    sys.exit(main())
