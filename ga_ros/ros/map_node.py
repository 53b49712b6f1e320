"""``map_node``: the point-cloud map of the keyframe clouds at their corrected poses.

An adapter of :class:`ga_ros.pipeline.cloud_map.CloudMapBuilder` (the replay's ``--map``
builds the same map, :mod:`ga_ros.replay.map_outputs`): it subscribes to

* ``ga/keyframe_cloud`` (``sensor_msgs/PointCloud2`` of ``vo_node``, in the camera's frame,
  stamped with the keyframe's stamp; decoded by its own field descriptions,
  :func:`ga_ros.mapping.pointcloud2.decode_pointcloud2`);
* ``ga/corrections`` (``nav_msgs/Path``: anchor keyframes of what moved, with spans whose
  keyframes get the interpolated correction, and the keyframes added; the ``ga/full_path``
  marker at restarts; ``docs/node.md``), applied by the shared convention
  (:class:`ga_ros.pipeline.corrections.HeldPoses`): only the keyframes it sets are
  re-anchored, so an update costs in proportion to what moved, not to the map's size;
* ``ga/corrected_path`` (transient local): every keyframe, used until the first corrections
  message (a map node started after the alignment node);
* ``/tf_static``: the camera's extrinsic ``base_frame -> <cloud frame>`` (else the parameter
  ``T_base_camera``, else the identity with ``assume_identity_extrinsic``; clouds wait for it);
* ``ga/keyframe_image`` (``sensor_msgs/Image`` of ``vo_node``: each keyframe's rectified left
  image, same stamp and frame as its cloud) and ``ga/keyframe_camera_info``
  (``sensor_msgs/CameraInfo``, its ``k``), with ``mosaic_enabled``: the live mosaic
  (:class:`ga_ros.pipeline.mosaic_map.LiveMosaic`, parameters ``mosaic_*``), orthorectified
  on the height model of the keyframe clouds (the offline mosaic's), which re-warps only the
  keyframes whose pose or ground changed.

Publishes ``ga/map`` (``sensor_msgs/PointCloud2`` in ``map_frame``, transient local, fields
``x y z intensity`` float32: one point per occupied voxel of ``voxel_m``), every
``publish_period_sec`` when the map changed. Service ``~/save_map`` (``std_srvs/Trigger``)
writes the map to ``map_file`` (binary little-endian PLY, :mod:`ga_ros.mapping.ply`), as does
the node's shutdown with ``save_on_shutdown``; with the mosaic, both also write ``mosaic_file``
(PNG + ``.json`` georeference + ``.pgw`` world file, :func:`ga_ros.mapping.mosaic.save_mosaic`).
The mosaic is published on ``ga/mosaic`` (``sensor_msgs/Image`` mono8 in ``map_frame``, rows
north first, 0 where not covered; transient local) with its georeference on ``ga/mosaic_info``
(``nav_msgs/MapMetaData``, same stamp: ``resolution`` m/px, ``origin`` the south-west corner,
the ``OccupancyGrid`` convention, :func:`ga_ros.mapping.mosaic.map_metadata_fields`), every
``publish_period_sec`` when it changed. ``/diagnostics`` carries
:meth:`MapNode.diagnostic_values` every ``diagnostics_period_sec``. Memory is bounded
(:class:`ga_ros.mapping.cloud_map.CloudMapConfig`: per-keyframe decimation, a static layer
beyond ``max_live_keyframes``; :class:`ga_ros.pipeline.mosaic_map.MosaicMapConfig`: a pixel
cap, keyframes merged into static layers beyond ``mosaic_max_live_keyframes``: their image,
patch and cloud points released, later corrections of them ignored and counted). Both merge
**settled** keyframes, not the oldest: a keyframe whose pose has not moved by more than
``settle_voxels`` voxels (``mosaic_settle_px`` mosaic pixels) over the last ``settle_updates``
(``mosaic_settle_updates``) corrections messages; keyframes that keep moving (a refinement, a
loop closure or a fix still correcting an old track) stay live. The bounds are hard caps: when
too few have settled, the most settled are merged all the same, counted as forced
(``static_settled`` / ``static_forced``, ``mosaic_merged_settled`` / ``mosaic_merged_forced``
in ``/diagnostics``). A bad
message is counted, warned about (throttled) and dropped; the node goes on.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import MapMetaData
from nav_msgs.msg import Path as PathMsg
from rclpy.clock import Clock as RosClock
from rclpy.clock import ClockType
from rclpy.node import Node
from sensor_msgs.msg import CameraInfo, Image, PointCloud2
from std_srvs.srv import Trigger
from tf2_msgs.msg import TFMessage

from ga_ros import topics
from ga_ros.core.extrinsic import ExtrinsicConfig
from ga_ros.errors import GaError
from ga_ros.mapping.cloud_map import CloudMapConfig
from ga_ros.mapping.mosaic import image_fields, map_metadata_fields, save_mosaic
from ga_ros.mapping.ply import write_ply
from ga_ros.mapping.pointcloud2 import decode_pointcloud2
from ga_ros.pipeline.cloud_map import CloudMapBuilder
from ga_ros.pipeline.corrections import CorrectionMessage
from ga_ros.pipeline.journal.state_files import default_state_file
from ga_ros.pipeline.mosaic_map import LiveMosaic, MosaicMapConfig
from ga_ros.pipeline.params import parameter_names
from ga_ros.ros import conversions as conv
from ga_ros.ros.bounded_log import BoundedLogging
from ga_ros.ros.params import declare_config
from ga_ros.ros.qos import latched_qos, stream_qos, tf_static_qos
from ga_ros.ros.runner import node_usage, run_node
from ga_ros.vo.messages import image_to_grey

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
    keyframe_image_topic : input keyframe images (``Image``, rectified, the clouds' stamps).
    keyframe_info_topic : input ``CameraInfo`` of the rectified camera (its ``k``).
    mosaic_topic : output mosaic (``Image`` in ``map_frame``, transient local).
    mosaic_info_topic : output georeference of the mosaic (``MapMetaData``, transient local).
    mosaic_file : where ``~/save_map`` and the shutdown write the mosaic (PNG, with ``.json``
        and ``.pgw`` beside); '' = ``mosaic.png`` beside ``map_file``.
    diagnostics_topic : output ``diagnostic_msgs/DiagnosticArray`` with the counts.
    diagnostics_period_sec : period of the diagnostics (s, wall clock; 0 disables).
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
    keyframe_image_topic: str = topics.KEYFRAME_IMAGE
    keyframe_info_topic: str = topics.KEYFRAME_CAMERA_INFO
    mosaic_topic: str = topics.MOSAIC
    mosaic_info_topic: str = topics.MOSAIC_INFO
    mosaic_file: str = ''
    diagnostics_topic: str = topics.DIAGNOSTICS
    diagnostics_period_sec: float = 1.0
    warn_throttle_sec: float = 5.0


def corrections_from_msg(msg: Any) -> CorrectionMessage:
    """A ``ga/corrections`` message as the consumers read it
    (:class:`~ga_ros.pipeline.corrections.CorrectionMessage`: the ``ga/full_path`` marker and
    the span endings of the frame ids read, the marker left out).

    Raises
    ------
    InputError
        A pose that is not a valid transform (:func:`ga_ros.ros.conversions.path_msg_to_poses`)
        or a span without an entry before it.
    """
    poses = list(msg.poses)
    T = conv.path_msg_to_poses(msg).reshape(-1, 4, 4)
    stamps = np.array([conv.stamp_to_ns(ps.header.stamp) for ps in poses], dtype=np.int64)
    return CorrectionMessage.from_poses([ps.header.frame_id for ps in poses], stamps, T)


class MapNode(BoundedLogging, Node):
    """Adapter: clouds, corrections, path -> :class:`CloudMapBuilder` -> ``ga/map``."""

    def __init__(self, **kwargs: Any) -> None:
        """``kwargs`` go to :class:`rclpy.node.Node` (e.g. ``context``,
        ``parameter_overrides`` in tests)."""
        super().__init__(NODE_NAME, **kwargs)
        self.settings: MapNodeSettings = declare_config(self, MapNodeSettings)
        self.map_config: CloudMapConfig = declare_config(self, CloudMapConfig)
        self.extrinsic_config: ExtrinsicConfig = declare_config(self, ExtrinsicConfig)
        self.mosaic_config: MosaicMapConfig = declare_config(self, MosaicMapConfig, 'mosaic_')
        self.extrinsic_config.from_parameters()  # a malformed T_base_camera fails at start
        s = self.settings
        self.builder = CloudMapBuilder(self.map_config, self.extrinsic_config)
        self.map_file = Path(s.map_file) if s.map_file else (
            default_state_file(self.get_namespace(), self.get_name()).parent / 'map.ply')
        self.mosaic_file = (Path(s.mosaic_file) if s.mosaic_file
                            else self.map_file.with_name('mosaic.png'))
        self.mosaic = LiveMosaic(self.mosaic_config) if self.mosaic_config.enabled else None
        #: ``k`` of the last keyframe CameraInfo (None before one came)
        self.K: np.ndarray | None = None
        #: keyframe images waiting for the CameraInfo or the camera's extrinsic:
        #: (stamp, frame, grey image)
        self.images_waiting: list[tuple[int, str, np.ndarray]] = []
        #: keyframe clouds for the mosaic's ground waiting for the camera's extrinsic:
        #: (stamp, frame, points in the camera's frame)
        self.clouds_waiting: list[tuple[int, str, np.ndarray]] = []
        self.counts = {'bad_clouds': 0, 'bad_corrections': 0, 'bad_paths': 0, 'published': 0,
                       'saved': 0, 'bad_images': 0, 'mosaics_published': 0, 'mosaics_saved': 0}
        self._last_warn: dict[str, float] = {}
        self.pub_map = self.create_publisher(PointCloud2, s.map_topic, latched_qos(1))
        self.create_subscription(TFMessage, s.tf_static_topic, self._on_tf_static,
                                 tf_static_qos())
        self.create_subscription(PointCloud2, s.keyframe_cloud_topic, self._on_cloud,
                                 stream_qos(max(1, s.cloud_queue)))
        self.create_subscription(PathMsg, s.corrections_topic, self._on_corrections,
                                 stream_qos(CORRECTIONS_DEPTH))
        self.create_subscription(PathMsg, s.path_topic, self._on_path, latched_qos(1))
        self.pub_mosaic = self.pub_mosaic_info = None
        if self.mosaic is not None:
            self.pub_mosaic = self.create_publisher(Image, s.mosaic_topic, latched_qos(1))
            self.pub_mosaic_info = self.create_publisher(MapMetaData, s.mosaic_info_topic,
                                                         latched_qos(1))
            self.create_subscription(Image, s.keyframe_image_topic, self._on_image,
                                     stream_qos(max(1, s.cloud_queue)))
            self.create_subscription(CameraInfo, s.keyframe_info_topic, self._on_info,
                                     stream_qos(max(1, s.cloud_queue)))
        self.pub_diag = self.create_publisher(DiagnosticArray, s.diagnostics_topic,
                                              stream_qos())
        self.create_service(Trigger, '~/save_map', self._on_save)
        if s.publish_period_sec > 0:
            self.create_timer(s.publish_period_sec, self.publish_outputs)
        if s.diagnostics_period_sec > 0:  # wall clock: reports also while sim time stands
            self.create_timer(s.diagnostics_period_sec, self.publish_diagnostics,
                              clock=RosClock(clock_type=ClockType.STEADY_TIME))

    # ------------------------------------------------------------------ callbacks
    def _warn(self, key: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last_warn.get(key, -1e18) >= self.settings.warn_throttle_sec:
            self._last_warn[key] = now
            self.get_logger().warning(text)

    def _on_tf_static(self, msg: TFMessage) -> None:
        self.builder.add_tf_static(msg)
        self._place_images()

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
        if self.mosaic is not None and self.mosaic.surface is not None:
            self.clouds_waiting.append((conv.stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                                        np.asarray(cloud.points)))
            del self.clouds_waiting[:-max(1, self.mosaic_config.max_waiting)]
            self._place_images()

    def _on_info(self, msg: CameraInfo) -> None:
        K = np.asarray(msg.k, float).reshape(3, 3)
        if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0):
            self.counts['bad_images'] += 1
            self._warn('image', 'keyframe CameraInfo dropped: k is not a valid camera matrix')
            return
        self.K = K
        self._place_images()

    def _on_image(self, msg: Image) -> None:
        try:
            grey = image_to_grey(msg)
        except (GaError, ValueError) as exc:
            self.counts['bad_images'] += 1
            self._warn('image', f'keyframe image dropped: {exc}')
            return
        self.images_waiting.append((conv.stamp_to_ns(msg.header.stamp), msg.header.frame_id,
                                    grey))
        del self.images_waiting[:-max(1, self.mosaic_config.max_waiting)]
        self._place_images()

    def _place_images(self) -> None:
        """Give the mosaic the keyframe clouds whose extrinsic is known and the images whose
        intrinsics and extrinsic are known."""
        if self.mosaic is None:
            return
        clouds, self.clouds_waiting = self.clouds_waiting, []
        for stamp, frame, points in clouds:
            try:
                ext = self.builder.extrinsic(frame)
            except GaError:  # unknown extrinsic: wait for /tf_static (the map warns)
                self.clouds_waiting.append((stamp, frame, points))
                continue
            try:
                self.mosaic.add_cloud(stamp, points, ext.T_base_cam)
            except GaError as exc:
                self._warn('cloud', f'keyframe cloud dropped by the mosaic: {exc}')
        if self.K is None or not self.images_waiting:
            self._warn_refused()
            return
        waiting, self.images_waiting = self.images_waiting, []
        for stamp, frame, grey in waiting:
            try:
                ext = self.builder.extrinsic(frame)
            except GaError as exc:  # unknown extrinsic: wait for /tf_static
                self.images_waiting.append((stamp, frame, grey))
                self._warn('extrinsic', f'keyframe images wait: {exc}')
                continue
            try:
                self.mosaic.add_image(stamp, grey, self.K, ext.T_base_cam)
            except GaError as exc:
                self.counts['bad_images'] += 1
                self._warn('image', f'keyframe image dropped: {exc}')
        self._warn_refused()

    def _warn_refused(self) -> None:
        if self.mosaic is not None and self.mosaic.last_error:
            self._warn('mosaic', self.mosaic.last_error)
            self.mosaic.last_error = ''

    def _mosaic_poses(self, stamps: np.ndarray, T: np.ndarray) -> None:
        """The poses the map took, for the mosaic (keys as the map names them)."""
        if self.mosaic is None:
            return
        self.mosaic.set_poses(self.builder.keys(stamps), T)
        self._warn_refused()

    def _on_corrections(self, msg: PathMsg) -> None:
        try:
            c = corrections_from_msg(msg)
            taken = self.builder.on_corrections(c)
            if self.mosaic is not None and c.full:
                self.mosaic.unplace_all()
                if len(c.stamps_ns) == 0:
                    self.mosaic.clear_static()
            self._mosaic_poses(taken.stamps_ns, taken.T_map_base)
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
            self._mosaic_poses(stamps, T)
        except (GaError, ValueError) as exc:
            self.counts['bad_paths'] += 1
            self._warn('path', f'corrected path dropped: {exc}')

    # ------------------------------------------------------------------ outputs
    def publish_outputs(self) -> None:
        """The timer: the map and the mosaic, each if it changed."""
        self.publish_map()
        self.publish_mosaic()

    def publish_mosaic(self, force: bool = False) -> bool:
        """Publish the mosaic (``Image``) and its georeference (``MapMetaData``, same stamp)
        if it changed since the last time (or ``force``); True if sent."""
        if self.mosaic is None or not (self.mosaic.take_changed() or force):
            return False
        mosaic = self.mosaic.mosaic()
        if mosaic is None:
            return False
        stamp = conv.ns_to_stamp(self.get_clock().now().nanoseconds)
        img = Image(**{k: v for k, v in image_fields(mosaic).items() if k != 'data'})
        img.data = mosaic_bytes(mosaic)
        img.header.stamp, img.header.frame_id = stamp, self.settings.map_frame
        f = map_metadata_fields(mosaic.georef)
        info = MapMetaData(resolution=f['resolution'], width=f['width'], height=f['height'])
        info.map_load_time = stamp
        (info.origin.position.x, info.origin.position.y,
         info.origin.position.z) = f['origin']['position']
        (info.origin.orientation.x, info.origin.orientation.y, info.origin.orientation.z,
         info.origin.orientation.w) = f['origin']['orientation']
        self.pub_mosaic.publish(img)
        self.pub_mosaic_info.publish(info)
        self.counts['mosaics_published'] += 1
        return True

    def save_mosaic(self) -> dict[str, str] | None:
        """Write the mosaic to ``mosaic_file`` (+ ``.json``, ``.pgw``); None when there is none.

        Raises
        ------
        GaError
            A file cannot be written (a link, a directory, no permission).
        """
        mosaic = None if self.mosaic is None else self.mosaic.mosaic()
        if mosaic is None:
            return None
        files = save_mosaic(self.mosaic_file, mosaic)
        self.counts['mosaics_saved'] += 1
        return files

    def publish_diagnostics(self) -> None:
        """Publish :meth:`diagnostic_values` on ``diagnostics_topic`` (WARN while clouds or
        images wait for the camera's extrinsic, or the mosaic refused keyframes)."""
        values = self.diagnostic_values()
        problems = []
        if self.builder.extrinsic_error:
            problems.append(f'keyframe clouds wait: {self.builder.extrinsic_error}')
        if values.get('mosaic_refused'):
            problems.append(f"{values['mosaic_refused']} keyframes refused by the mosaic")
        self.pub_diag.publish(conv.diagnostics_msg(
            f'{self.get_fully_qualified_name()}: map', 'ga_ros', values,
            self.get_clock().now().nanoseconds, level=1 if problems else 0,
            message='; '.join(problems) or 'ok'))

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
            files = self.save_mosaic()
        except GaError as exc:
            response.success, response.message = False, f'map not saved: {exc}'
            return response
        response.success, response.message = True, f'{n} points written to {path}' + (
            '' if files is None else f'; mosaic written to {files["png"]}')
        return response

    def destroy_node(self) -> None:
        """Save the map (``save_on_shutdown``, when it has points), then destroy the node."""
        if self.settings.save_on_shutdown and len(self.builder.map.voxels):
            try:
                path, n = self.save_map()
                print(f'{NODE_NAME}: {n} points written to {path}', file=sys.stderr)
            except GaError as exc:
                print(f'{NODE_NAME}: map not saved at shutdown: {exc}', file=sys.stderr)
        if self.settings.save_on_shutdown and self.mosaic is not None:
            try:
                files = self.save_mosaic()
                if files is not None:
                    print(f'{NODE_NAME}: mosaic written to {files["png"]}', file=sys.stderr)
            except GaError as exc:
                print(f'{NODE_NAME}: mosaic not saved at shutdown: {exc}', file=sys.stderr)
        super().destroy_node()

    def diagnostic_values(self) -> dict[str, object]:
        """Counts and sizes of the map (for tests and logs)."""
        m, c = self.builder.map, self.builder.counts
        return {'clouds': c.clouds, 'clouds_waiting': len(self.builder.waiting),
                'corrections': c.corrections, 'full_corrections': c.full, 'paths': c.paths,
                'moved': c.moved, 'points_moved': c.points_moved, 'live_keyframes': m.n_live,
                'static_keyframes': m.n_static, 'static_settled': m.static_settled,
                'static_forced': m.static_forced, 'unplaced_clouds': m.n_unplaced,
                'voxels': len(m.voxels), 'bytes': m.nbytes(), **self.mosaic_values(),
                **self.counts}

    def mosaic_values(self) -> dict[str, object]:
        """The mosaic's counts and sizes (``mosaic_*``; empty when it is off)."""
        mo = self.mosaic
        if mo is None:
            return {}
        c = mo.counts
        return {'mosaic_images': c.images, 'mosaic_images_waiting': len(self.images_waiting),
                'mosaic_live_keyframes': mo.n_placed, 'mosaic_frozen': c.frozen,
                'mosaic_merged_settled': c.merged_settled,
                'mosaic_merged_forced': c.merged_forced,
                'mosaic_warps': c.warps, 'mosaic_tiles_composited': c.tiles_composited,
                'mosaic_tiles': len(mo.tiles), 'mosaic_refused': c.refused,
                'mosaic_dropped': c.dropped, 'mosaic_metres_per_pixel': mo.metres_per_pixel,
                'mosaic_clouds': c.clouds, 'mosaic_clouds_waiting': len(self.clouds_waiting),
                'mosaic_ground_rewarps': c.ground_rewarps,
                'mosaic_merged_moves_ignored': c.merged_moves_ignored,
                'mosaic_merged_max_shift_m': c.merged_max_shift_m,
                'mosaic_bytes': mo.nbytes()}


def declared_parameters() -> list[str]:
    """Every parameter ``map_node`` declares (built from its config dataclasses, no rclpy)."""
    return (parameter_names(MapNodeSettings) + parameter_names(CloudMapConfig)
            + parameter_names(ExtrinsicConfig) + parameter_names(MosaicMapConfig, 'mosaic_'))


def mosaic_bytes(mosaic: object) -> bytes:
    """The ``data`` of the mosaic's ``sensor_msgs/Image`` (:func:`image_fields`)."""
    return np.ascontiguousarray(image_fields(mosaic)['data']).tobytes()  # type: ignore[arg-type]


def main(args: list[str] | None = None) -> int:
    """Console entry point ``map_node`` (also ``python -m ga_ros.ros.map_node``)."""
    return run_node(MapNode, NODE_NAME, args,
                    usage=lambda: node_usage(NODE_NAME, __doc__, declared_parameters()))


if __name__ == '__main__':
    sys.exit(main())
