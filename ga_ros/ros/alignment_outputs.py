"""Outputs of the alignment node: path, corrections, window path, pose, odometry and markers
(mixin of :class:`~ga_ros.ros.alignment_node.AlignmentNode`)."""


import time
from typing import Any

import numpy as np

from ga_ros.pipeline.corrections import corrections_cdr
from ga_ros.ros import conversions as conv
from ga_ros.ros.view import connection_view


class AlignmentOutputs:
    """Published outputs of :class:`~ga_ros.ros.alignment_node.AlignmentNode`."""

    def _publish_all(self) -> None:
        """Publish path, newest pose, odometry, markers and diagnostics; never raises."""
        try:
            self._publish_outputs()
        except Exception as exc:  # noqa: BLE001 - publishing must not stop the node
            self.session.last_error = f'publish: {type(exc).__name__}: {exc}'
            self.get_logger().error(f'could not publish the outputs: {self.session.last_error}',
                                    throttle_duration_sec=self.settings.warn_throttle_sec)
        self._publish_diagnostics()

    def _publish_outputs(self) -> None:
        """Every output of an update, from the corrected path kept in step with the aligner
        (:class:`~ga_ros.pipeline.path_mirror.PathMirror`: the rows the update could change
        are copied, not the whole path)."""
        s = self.settings
        cp = self.paths.sync(self.aligner)
        self._path_nodes = len(cp.node_ids)
        if len(cp.node_ids):
            stamp_ns = int(cp.stamps_ns[-1])
        else:
            stamp_ns = self.get_clock().now().nanoseconds
        self._path_dirty = True
        if time.perf_counter() >= self._next_full_path:
            self._publish_full_path(stamp_ns)
        self._publish_corrections(cp, stamp_ns)
        lo, movable = self.paths.movable_rows()   # every row before lo is frozen
        rows = lo + np.flatnonzero(movable)
        self.pub_window.publish(conv.path_to_msg(cp.T_world_node[rows], cp.stamps_ns[rows],
                                                 s.map_frame, stamp_ns))
        warned = self.odom.jumps_warned
        self.odom.update(cp.node_ids, cp.T_world_node,
                         adjusted=self.session.counts.updates > 0 or self._resumed)
        if self.odom.placed_by == 'aligner':   # a restart sends it until its first update
            self.session.journal_map_odom(self.odom.T_map_odom)
        self._placement_changed(warned)
        if self.front is not None:
            self.front.set_corrected(cp.node_ids, cp.T_world_node)
        self._publish_tf()
        k = self.session.newest_adjusted(cp)
        if k is not None:
            cov = self.session.covariance_or_unknown(int(cp.node_ids[k]))
            t_k = int(cp.stamps_ns[k])
            self.pub_pose.publish(conv.pose_with_covariance_msg(cp.T_world_node[k], cov,
                                                                s.map_frame, t_k))
            self.pub_odom.publish(conv.odometry_msg(cp.T_world_node[k], cov, s.map_frame,
                                                    s.base_frame, t_k))
        if s.publish_markers:
            self._markers_dirty = True
            if self.pub_markers.get_subscription_count() > 0:
                self._publish_markers()

    def _publish_corrections(self, cp: Any, stamp_ns: int) -> None:
        """The keyframes moved or added since the last corrections message (none: nothing
        sent), :class:`~ga_ros.pipeline.corrections.CorrectionTracker`."""
        c = self.corrections.after_update(self.aligner, cp)
        if c is not None:   # CDR bytes (rclpy publishes them raw), the replay's too
            self.pub_corrections.publish(corrections_cdr(c, self.settings.map_frame, stamp_ns))

    def _publish_markers(self, force: bool = False) -> None:
        """The network as markers. Built only when someone listens (RViz, Foxglove): otherwise
        marked dirty and sent by the 1 Hz timer once a subscriber appears. Never raises."""
        if not (self._markers_dirty or force):
            return
        s = self.settings
        try:
            cp = self.aligner.corrected_path()
            view = connection_view(self.aligner)
            colors = np.where(np.asarray(cp.frozen, dtype=bool)[:, None],
                              [[0.5, 0.5, 0.5, 1.0]], [[0.2, 0.4, 1.0, 1.0]])
            colors[self.session.unjoined(cp.node_ids)] = [1.0, 0.55, 0.0, 1.0]  # behind a bridge
            conn_rgba = conv.connection_rgba(view.normalized_residual, view.status,
                                             s.residual_color_scale, view.w)
            stamp_ns = int(cp.stamps_ns[-1]) if len(cp.node_ids) else 0
            self.pub_markers.publish(conv.network_markers(
                view.p_world_node, view.src_index, view.dst_index,
                view.normalized_residual, s.map_frame, stamp_ns, node_colors=colors,
                residual_scale=s.residual_color_scale, connection_colors=conn_rgba))
            self._markers_dirty = False
        except Exception as exc:  # noqa: BLE001 - visualisation must not stop the node
            self._markers_dirty = False
            self.get_logger().warning(f'markers not published: {exc}',
                                      throttle_duration_sec=10.0)

    def _publish_full_path(self, stamp_ns: int) -> None:
        """The corrected path as of the last :meth:`PathMirror.sync
        <ga_ros.pipeline.path_mirror.PathMirror.sync>`: its serialized message is kept and only
        the rows that changed are encoded again (:class:`~ga_ros.io.cdr.PathCdr`)."""
        self._next_full_path = time.perf_counter() + self.settings.full_path_min_period_sec
        self._path_dirty = False
        self.pub_path.publish(self.paths.path_message(stamp_ns))

    def _full_path_timer(self) -> None:
        if self._path_dirty and time.perf_counter() >= self._next_full_path:
            cp = self.paths.sync(self.aligner)
            if len(cp.node_ids):
                self._publish_full_path(int(cp.stamps_ns[-1]))

    def _markers_timer(self) -> None:
        if self._markers_dirty and self.pub_markers.get_subscription_count() > 0:
            self._publish_markers()

    def _publish_newest_odom(self) -> None:
        """Odometry of the newest node (open track: not adjusted yet, covariance unknown, i.e.
        ``covariance[0] = -1`` as ROS messages mark it)."""
        self._next_odom_time = time.perf_counter() + 1.0 / self.settings.odom_max_rate_hz
        cp = self.paths.sync(self.aligner)
        if not len(cp.node_ids):
            return
        self._last_odom_node = int(cp.node_ids[-1])
        cov = np.zeros((6, 6))
        cov[0, 0] = -1.0
        self.pub_odom.publish(conv.odometry_msg(cp.T_world_node[-1], cov, self.settings.map_frame,
                                                self.settings.base_frame,
                                                int(cp.stamps_ns[-1])))

