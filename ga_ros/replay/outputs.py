"""Files the replay writes: the output mcap bag, TUM trajectories, the PNG plot, summary JSON.

Every file goes through :mod:`ga_ros.safe_write` (temporary file, fsync, rename; symbolic links
refused) and the destinations are checked before the replay starts, so a link in the output
directory stops the run at once, with its target untouched.

Time base: every message of the output bag is logged at the log time of the input message that
caused it (the final poses, odometry and paths at the last input log time), so the output bag
stays on the recorder's clock, in order, whatever its header stamps say (a bag recorded in
simulation time keeps wall-clock log times).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros import topics
from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.encoding import network_index
from ga_ros.errors import FormatError
from ga_ros.geometry import se3
from ga_ros.io.bag_messages import PATH, trajectory_to_path_msg
from ga_ros.io.bag_writer import (
    LINE_WIDTH,
    NAMESPACE,
    NODE_SCALE,
    BagWriter,
    odometry_msg,
    pose_with_covariance_msg,
    residual_color,
    tf_message,
    transform_msg,
)
from ga_ros.io.cdr import network_markers_cdr
from ga_ros.io.trajectory import Trajectory, write_tum
from ga_ros.pipeline.corrections import Corrections, CorrectionThresholds, corrections_cdr
from ga_ros.safe_write import check_destinations, save_figure, write_json


@dataclass(frozen=True)
class OutputConfig:
    """Names of the replay's outputs.

    Attributes
    ----------
    map_frame : frame of the corrected and F2F paths and poses (REP 105 ``map``).
    path_topic : corrected path (``nav_msgs/Path``), written after every track update and at
        the end.
    f2f_topic : frame-to-frame integrated path (``nav_msgs/Path``), written at the end.
    pose_topic : corrected pose of every node with covariance
        (``geometry_msgs/PoseWithCovarianceStamped``), written at the end (header stamp: the
        node's time; log time: the last input log time).
    measurements_topic : the measurements used (``nav_msgs/Odometry``, the ga_ros encoding).
    markers_topic : the connection network (``visualization_msgs/MarkerArray``) after every
        update.
    ground_truth_topic : the ground truth copied from the input bag, if it has one.
    bag_name : name of the output bag directory inside the output directory.
    odom_topic : corrected pose of every node as ``nav_msgs/Odometry`` (``map_frame`` ->
        ``sensor_frame``), written at the end, header stamped at the node (evo reads it).
    sensor_frame : ``child_frame_id`` of the corrected odometry (the robot's base frame).
    odom_frame : REP 105 odometry frame: ``map_frame -> odom_frame`` goes on ``tf_topic``.
    tf_topic, tf_static_topic : TF topics of the output bag (the input bag's are copied there).
    corrections_topic : anchors of the keyframes moved, and those added, since the previous
        message (``nav_msgs/Path``, the node's ``ga/corrections``), written after every track
        update and after the final batch.
    corrections : when a keyframe counts as moved there (the node's defaults).
    """

    map_frame: str = 'map'
    path_topic: str = topics.resolve(topics.CORRECTED_PATH)
    f2f_topic: str = topics.resolve(topics.F2F_PATH)
    pose_topic: str = topics.resolve(topics.CORRECTED_POSE)
    measurements_topic: str = topics.resolve(topics.MEASUREMENTS)
    markers_topic: str = topics.resolve(topics.NETWORK_MARKERS)
    ground_truth_topic: str = topics.resolve(topics.GROUND_TRUTH)
    bag_name: str = 'replay_bag'
    odom_topic: str = topics.resolve(topics.CORRECTED_ODOM)
    sensor_frame: str = 'base_link'
    odom_frame: str = 'odom'
    tf_topic: str = '/tf'
    tf_static_topic: str = '/tf_static'
    corrections_topic: str = topics.resolve(topics.CORRECTIONS)
    corrections: CorrectionThresholds = CorrectionThresholds()


def misclosure(T_world_node: FloatArray, src: IntArray, dst: IntArray, z: FloatArray,
               cov: FloatArray) -> FloatArray:
    """Mahalanobis norm of each connection's misclosure at the given poses (unitless).

    ``e = log(Z^-1 T_i^-1 T_j)`` (right perturbation, ``[x y z rx ry rz]``), ``d = sqrt(e'
    cov^-1 e)``; ``src``/``dst`` are node indices into ``T_world_node`` (n, 4, 4), ``z`` (m, 6)
    the measured ``[t, w]`` and ``cov`` (m, 6, 6) their covariances.
    """
    if len(src) == 0:
        return np.zeros(0)
    Z = se3.from_translation_rotvec(z[:, :3], z[:, 3:])
    e = se3.misclosure(Z, T_world_node[src], T_world_node[dst])
    return np.sqrt(np.maximum(np.einsum('ki,ki->k', e, np.linalg.solve(cov, e[..., None])[..., 0]),
                              0.0))


def plot_trajectories(path: Path, ga: FloatArray, f2f: FloatArray | None,
                      gt: FloatArray | None, title: str, online: FloatArray | None = None,
                      fixes: FloatArray | None = None, frame: str = 'map') -> None:
    """Top view (x-y, m) in the map frame ``frame`` of the corrected (GA), online, F2F and
    ground-truth positions and the fixes, as a PNG.

    Parameters
    ----------
    ga, f2f, gt, online : (n, 3) positions (all but ga may be None).
    fixes : (m, 3) positions of the absolute fixes, or None.
    """
    import matplotlib

    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 6), dpi=110)
    try:
        if gt is not None and len(gt):
            ax.plot(gt[:, 0], gt[:, 1], '-', color='0.55', lw=2.5,
                    label='ground truth (at the keyframes)')
        if fixes is not None and len(fixes):
            ax.plot(fixes[:, 0], fixes[:, 1], '.', color='tab:green', ms=3, label='fixes')
        if f2f is not None and len(f2f):
            ax.plot(f2f[:, 0], f2f[:, 1], '-', color='tab:red', lw=1.0,
                    label='F2F (odometry, anchored as GA)')
        if online is not None and len(online):
            ax.plot(online[:, 0], online[:, 1], '--', color='tab:orange', lw=0.8,
                    label='GA online')
        if len(ga):
            ax.plot(ga[:, 0], ga[:, 1], '-', color='tab:blue', lw=1.0,
                    label='GA (final batch)' if online is not None else 'GA (corrected)')
        ax.set_xlabel(f'x in {frame} (m)')
        ax.set_ylabel(f'y in {frame} (m)')
        ax.set_aspect('equal', adjustable='datalim')
        ax.grid(True, alpha=0.3)
        ax.legend(loc='best')
        ax.set_title(title, fontsize=9)
        fig.tight_layout()
        save_figure(fig, path)
    finally:
        plt.close(fig)


class ReplayOutputs:
    """The output directory of one replay: bag (opened at once), then TUM/PNG/JSON at the end.

    Parameters
    ----------
    out_dir : directory (created); an existing output bag in it is replaced.
    config : topic and file names.

    Raises
    ------
    UnsafePathError
        An output file or the bag's path is a symbolic link or not a regular file (nothing is
        written).
    """

    #: the files written at the end (besides the bag)
    FILES = ('trajectory_ga.tum', 'trajectory_online.tum', 'trajectory_f2f.tum',
             'trajectory_gt.tum', 'trajectory_gt_raw.tum', 'trajectory.png', 'summary.json')

    def __init__(self, out_dir: str | Path, config: OutputConfig = OutputConfig()) -> None:
        self.dir = Path(out_dir)
        self.config = config
        try:
            self.dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise FormatError(f'cannot create output directory: {exc}', str(self.dir)) from exc
        check_destinations(*(self.dir / name for name in self.FILES))
        self.bag = BagWriter(self.dir / config.bag_name, overwrite=True)
        self.bag.open()
        self.files: dict[str, Path] = {'bag': self.bag.path}

    # ---- streaming outputs
    def measurement(self, msgtype: str, data: bytes | None, msg: Any, log_ns: int) -> None:
        """Copy one measurement (raw CDR when available) into the output bag."""
        if data is not None:
            self.bag.write_raw(self.config.measurements_topic, msgtype, data, log_ns)
        else:
            self.bag.write(self.config.measurements_topic, msgtype, msg, log_ns)

    def path(self, traj: Trajectory, log_ns: int, topic: str | None = None) -> None:
        """A corrected (or F2F) path in the map frame, header stamped at its newest node,
        logged at ``log_ns``."""
        stamp = int(traj.stamps_ns.max()) if len(traj) else None
        msg = trajectory_to_path_msg(traj, frame_id=self.config.map_frame, stamp_ns=stamp)
        self.bag.write(topic or self.config.path_topic, PATH, msg, log_ns)

    def path_bytes(self, data: bytes, log_ns: int, topic: str | None = None) -> None:
        """A serialized corrected path (``nav_msgs/Path`` CDR, e.g.
        :class:`~ga_ros.replay.stamped_path.StampedPath`), logged at ``log_ns``."""
        self.bag.write_raw(topic or self.config.path_topic, PATH, data, log_ns)

    def corrections(self, c: Corrections, stamp_ns: int, log_ns: int) -> None:
        """The corrections of an update (:mod:`ga_ros.pipeline.corrections`), header stamped
        at ``stamp_ns`` (the corrected path's newest keyframe), logged at ``log_ns``."""
        self.bag.write_raw(self.config.corrections_topic, PATH,
                           corrections_cdr(c, self.config.map_frame, stamp_ns), log_ns)

    def markers(self, p_world_node: FloatArray, src: IntArray, dst: IntArray,
                residual: FloatArray, log_ns: int, stamp_ns: int) -> None:
        """The connection network coloured by misclosure, header stamped at ``stamp_ns`` (the
        input's time base), logged at ``log_ns``."""
        net = network_index(p_world_node, src, dst)
        data = network_markers_cdr(net.p, net.src, net.dst, residual_color(residual),
                                   self.config.map_frame, stamp_ns, NODE_SCALE, LINE_WIDTH,
                                   NAMESPACE)
        self.bag.write_raw(self.config.markers_topic, 'visualization_msgs/msg/MarkerArray',
                           data, log_ns)

    def poses(self, traj: Trajectory, covs: FloatArray, log_ns: int) -> None:
        """Corrected pose with covariance of every node, header stamped at the node's time,
        logged at ``log_ns`` (the last input log time)."""
        for k in range(len(traj)):
            s = int(traj.stamps_ns[k])
            self.bag.write(self.config.pose_topic,
                           'geometry_msgs/msg/PoseWithCovarianceStamped',
                           pose_with_covariance_msg(traj.T_world_node[k], covs[k],
                                                    self.config.map_frame, s), log_ns)

    def odometry(self, traj: Trajectory, covs: FloatArray, log_ns: int) -> None:
        """Corrected pose of every node as ``nav_msgs/Odometry``, header stamped at the node,
        logged at ``log_ns`` (the last input log time)."""
        c = self.config
        for k in range(len(traj)):
            s = int(traj.stamps_ns[k])
            self.bag.write(c.odom_topic, 'nav_msgs/msg/Odometry',
                           odometry_msg(traj.T_world_node[k], covs[k], c.map_frame,
                                        c.sensor_frame, s), log_ns)

    def map_to_odom(self, T_map_odom: FloatArray, stamp_ns: int, log_ns: int) -> None:
        """The REP 105 correction ``map_frame -> odom_frame`` on ``tf_topic``."""
        c = self.config
        msg = tf_message([transform_msg(c.map_frame, c.odom_frame, T_map_odom, stamp_ns)])
        self.bag.write(c.tf_topic, 'tf2_msgs/msg/TFMessage', msg, log_ns)

    def odom_to_base(self, T_odom_base: FloatArray, stamp_ns: int, log_ns: int) -> None:
        """REP 105 ``odom_frame -> sensor_frame`` (the odometry's pose of the robot) on
        ``tf_topic``."""
        c = self.config
        msg = tf_message([transform_msg(c.odom_frame, c.sensor_frame, T_odom_base, stamp_ns)])
        self.bag.write(c.tf_topic, 'tf2_msgs/msg/TFMessage', msg, log_ns)

    def earth_to_map(self, T_earth_map: FloatArray, stamp_ns: int, log_ns: int,
                     earth_frame: str = 'earth') -> None:
        """REP 105 ``earth -> map_frame`` (ECEF to the map frame) on ``tf_static_topic``."""
        c = self.config
        msg = tf_message([transform_msg(earth_frame, c.map_frame, T_earth_map, stamp_ns)])
        self.bag.write(c.tf_static_topic, 'tf2_msgs/msg/TFMessage', msg, log_ns)

    def copy(self, topic: str, msgtype: str, data: bytes | None, msg: Any, log_ns: int) -> None:
        """Copy a message of the input bag (raw CDR when available)."""
        if data is not None:
            self.bag.write_raw(topic, msgtype, data, log_ns)
        else:
            self.bag.write(topic, msgtype, msg, log_ns)

    def ground_truth(self, traj: Trajectory, log_ns: int) -> None:
        """The ground truth path (node frame ids kept when known)."""
        node_frames = bool(len(traj)) and bool((traj.node_ids >= 0).all()
                                               and (traj.track_ids >= 0).all())
        msg = trajectory_to_path_msg(traj, node_frames=node_frames)  # stamped at its last pose
        self.bag.write(self.config.ground_truth_topic, PATH, msg, log_ns)

    # ---- final files
    def tum(self, name: str, traj: Trajectory) -> Path:
        """Write ``name`` (TUM format) and register it."""
        p = self.dir / name
        write_tum(p, traj.stamps_ns, traj.T_world_node, decimals=9)
        self.files[p.stem] = p
        return p

    def plot(self, name: str, ga: FloatArray, f2f: FloatArray | None, gt: FloatArray | None,
             title: str, online: FloatArray | None = None, fixes: FloatArray | None = None,
             frame: str = 'map') -> Path:
        """Write the PNG plot (:func:`plot_trajectories`) and register it."""
        p = self.dir / name
        plot_trajectories(p, ga, f2f, gt, title, online=online, fixes=fixes, frame=frame)
        self.files['plot'] = p
        return p

    def summary(self, data: Mapping[str, Any]) -> Path:
        """Write ``summary.json``."""
        p = self.dir / 'summary.json'
        write_json(p, data, indent=2, sort_keys=True, default=_json_default)
        self.files['summary'] = p
        return p

    def close(self) -> None:
        """Finish the output bag (valid mcap with summary); idempotent."""
        self.bag.close()


def _json_default(o: object) -> Any:
    if isinstance(o, np.integer):
        return int(o)
    if isinstance(o, np.floating):
        return float(o)
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    return str(o)
