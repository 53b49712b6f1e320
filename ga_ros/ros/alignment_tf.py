"""TF of the alignment node: ``map -> odom`` (and ``map -> base``), the contest with another
publisher of ``odom``'s parent, and REP 105 ``earth -> map`` (mixin of
:class:`~ga_ros.ros.alignment_node.AlignmentNode`)."""


import time

from tf2_msgs.msg import TFMessage

from ga_ros.inputs.absolute import T_earth_enu
from ga_ros.pipeline.map_to_odom import foreign_odom_parents
from ga_ros.ros import conversions as conv
from ga_ros.ros.qos import (
    latched_qos,
)

#: Another node's ``-> odom`` transform keeps ours off the air this long after it was heard, s.
TF_CONTEST_HOLD_SEC = 5.0


class AlignmentTf:
    """TF publishing of :class:`~ga_ros.ros.alignment_node.AlignmentNode`."""

    def _publish_tf(self) -> None:
        """``map -> odom`` (and optionally ``map -> base``) of the newest correction, stamped at
        the newest odometry pose; not while another node publishes ``odom``'s parent (unless
        ``publish_tf_when_contested``)."""
        s = self.settings
        T_map_odom = self.odom.T_map_odom
        if not s.publish_tf or T_map_odom is None:
            return
        if self.tf_contested_by and not s.publish_tf_when_contested:
            return
        newest = self.odom.latest()
        if newest is None:
            return
        latest, stamp = newest
        stamp = self.odom.stamp(stamp)   # never back
        tfs = [conv.transform_msg(s.map_frame, s.odom_frame, T_map_odom, stamp)]
        if s.publish_map_to_base:
            tfs.append(conv.transform_msg(s.map_frame, s.base_frame, T_map_odom @ latest, stamp))
        self._own_tf[int(stamp)] = T_map_odom.copy()
        while len(self._own_tf) > 1000:
            self._own_tf.pop(next(iter(self._own_tf)))
        self.pub_tf.publish(TFMessage(transforms=tfs))

    def _placement_changed(self, jumps_before: int) -> None:
        """After the map placement may have changed: a jump beyond the fixes' uncertainty is
        logged and reported in the diagnostics at once."""
        if self.odom.jumps_warned > jumps_before:
            self.get_logger().warning(self.odom.warning)
            self._publish_diagnostics()

    @property
    def tf_contested_by(self) -> str:
        """Parent frame of another node's transform to ``odom_frame`` heard within the last
        :data:`TF_CONTEST_HOLD_SEC` ('' when none: ours is published again)."""
        parent, at = self._foreign_tf
        return parent if time.monotonic() - at < TF_CONTEST_HOLD_SEC else ''

    def _on_tf(self, msg: TFMessage) -> None:
        """Another publisher of a transform to ``odom_frame``: warn (throttled), report it in
        the diagnostics and stop publishing ours (unless ``publish_tf_when_contested``)."""
        s = self.settings
        parents = foreign_odom_parents(msg, s.odom_frame, self._own_tf, s.map_frame)
        if not parents:
            return
        first = not self.tf_contested_by
        self._foreign_tf = (parents[0], time.monotonic())
        what = ('publishing ours anyway (publish_tf_when_contested)'
                if s.publish_tf_when_contested else 'not publishing ours')
        self.get_logger().warning(
            f'another node publishes {parents[0]} -> {s.odom_frame} on {s.tf_topic}: a frame has '
            f'one parent; {what}. Stop the other localiser or remap, or set '
            f'publish_tf_when_contested', throttle_duration_sec=max(s.warn_throttle_sec, 1.0))
        if first:
            self._publish_diagnostics()

    def _publish_earth(self) -> None:
        """REP 105 ``earth -> map`` on the static TF topic, once the NavSatFix inputs' ENU
        origin is known (``publish_earth_transform``; the map frame is that ENU frame only
        with ``datum: fixes``)."""
        s = self.settings
        if (self._pub_earth is not None or not s.publish_earth_transform
                or self.absolute is None or self.aligner_config.datum != 'fixes'):
            return
        datum = self.absolute.earth_datum()
        if datum is None:
            return
        self._pub_earth = self.create_publisher(TFMessage, s.tf_topic + '_static',
                                                latched_qos())
        stamp = int(self.get_clock().now().nanoseconds)
        self._pub_earth.publish(TFMessage(transforms=[conv.transform_msg(
            s.earth_frame, s.map_frame, T_earth_enu(datum), stamp)]))
        self.get_logger().info(f'{s.earth_frame} -> {s.map_frame}: ENU at lat {datum[0]:.7f}, '
                               f'lon {datum[1]:.7f}, alt {datum[2]:.2f} m')

