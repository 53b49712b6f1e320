"""All conversions between ROS 2 messages and the ROS-free core types of ga_ros.

The measurement encoding (standard message types only; no custom message package is built)
---------------------------------------------------------------------------------------------
One ``nav_msgs/msg/Odometry`` per connection, on ``/ga/measurements``:

* ``header.frame_id = 'ga/<src_track>/<src_id>'``,
  ``child_frame_id = 'ga/<dst_track>/<dst_id>'`` (decimal
  non-negative integers, at most :data:`MAX_ID`);
* ``header.stamp``: acquisition time of the ``dst`` frame;
* ``pose.pose``: the motion ``T_src_dst`` (position in m, unit quaternion ``x y z w``);
* ``pose.covariance``: 6x6 row-major covariance of the right perturbation of ``T_src_dst``, order
  ``[x y z rx ry rz]`` (m, rad);
* ``twist.twist.linear.x``: ``1.0`` marks a cross-track (overlap) connection, ``0.0`` a consecutive
  one; the rest of the twist is zero;
* ``twist.covariance``: the measurement's source (``Measurement.source``, the group of its
  variance factor), its UTF-8 bytes one per element, zero-padded (all zero: none;
  :func:`ga_ros.core.encoding.source_to_values`).

Every function here is a pure conversion: it validates at the boundary (raising
:class:`ga_ros.errors.InputError`) and never touches a node or a publisher.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np
from builtin_interfaces.msg import Time
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from geometry_msgs.msg import (
    Point,
    Pose,
    PoseStamped,
    PoseWithCovarianceStamped,
    TransformStamped,
)
from nav_msgs.msg import Odometry, Path
from sensor_msgs.msg import PointCloud2, PointField
from std_msgs.msg import ColorRGBA
from visualization_msgs.msg import Marker, MarkerArray

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core import encoding, frames
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.io.bag_writer import residual_color  # one palette for the node and the replay
from ga_ros.ros.view import ABSORBED, OUTLIER

#: Largest accepted node or track id (ids above it are "absurd" and rejected).
MAX_ID = frames.MAX_ID
#: ``twist.twist.linear.x`` values of the two measurement kinds.
KIND_FLAG = encoding.KIND_FLAG


# --------------------------------------------------------------------------- stamps, frames
def stamp_to_ns(stamp: Time) -> int:
    """``builtin_interfaces/Time`` -> integer nanoseconds."""
    return encoding.stamp_to_ns(stamp)


def ns_to_stamp(stamp_ns: int) -> Time:
    """Integer nanoseconds (>= 0) -> ``builtin_interfaces/Time``."""
    t = encoding.split_stamp(stamp_ns)
    return Time(sec=t.sec, nanosec=t.nanosec)


def node_frame_id(track_id: int, node_id: int) -> str:
    """Frame id ``'ga/<track_id>/<node_id>'`` that carries a node in the measurement encoding
    (delegates to :func:`ga_ros.core.frames.node_frame`, shared with the ROS-free bag reader)."""
    return frames.node_frame(track_id, node_id)


def parse_node_frame_id(frame_id: str) -> tuple[int, int]:
    """Parse ``'ga/<track_id>/<node_id>'`` into ``(track_id, node_id)``.

    Raises InputError if malformed (a leading ``/`` is tolerated); see
    :func:`ga_ros.core.frames.parse_node_frame`.
    """
    return frames.parse_node_frame(frame_id)


# --------------------------------------------------------------------------- poses, covariances
def pose_to_msg(T: FloatArray) -> Pose:
    """4x4 pose -> ``geometry_msgs/Pose`` (position m, quaternion ``x y z w``)."""
    p, q = se3.to_pos_quat(np.asarray(T, dtype=float))
    msg = Pose()
    msg.position.x, msg.position.y, msg.position.z = (float(v) for v in p)
    msg.orientation.x, msg.orientation.y, msg.orientation.z, msg.orientation.w = (
        float(v) for v in q)
    return msg


def msg_to_pose(msg: Pose) -> FloatArray:
    """``geometry_msgs/Pose`` -> 4x4 pose; InputError on NaN or a non-unit quaternion."""
    return encoding.pose_to_matrix(msg)


def covariance_to_msg(cov: FloatArray) -> FloatArray:
    """6x6 covariance -> 36 row-major float64 values (``[x y z rx ry rz]`` order)."""
    cov = np.asarray(cov, dtype=float)
    if cov.shape != (6, 6):
        raise InputError(f'covariance must be 6x6, got {cov.shape}')
    return np.ascontiguousarray(cov).reshape(36).copy()


def msg_to_covariance(values: Sequence[float], check: bool = True) -> FloatArray:
    """36 row-major values -> 6x6 covariance; with ``check``, InputError unless finite, symmetric
    and positive definite (:func:`ga_ros.core.encoding.covariance_from_values`)."""
    if check:
        return encoding.covariance_from_values(values)
    return np.asarray(values, dtype=float).reshape(6, 6)


# --------------------------------------------------------------------------- measurements
def measurement_to_odometry(m: Measurement) -> Odometry:
    """Encode a :class:`Measurement` as ``nav_msgs/Odometry`` (see the module docstring)."""
    if m.kind not in KIND_FLAG:
        raise InputError(f"measurement kind must be 'consecutive' or 'cross', got {m.kind!r}")
    msg = Odometry()
    msg.header.frame_id = node_frame_id(m.src_track, m.src_id)
    msg.child_frame_id = node_frame_id(m.dst_track, m.dst_id)
    msg.header.stamp = ns_to_stamp(m.stamp_ns)
    msg.pose.pose = pose_to_msg(m.T_src_dst)
    msg.pose.covariance = covariance_to_msg(m.cov)
    msg.twist.twist.linear.x = KIND_FLAG[m.kind]
    msg.twist.covariance = encoding.source_to_values(m.source)
    return msg


def odometry_to_measurement(msg: Odometry) -> Measurement:
    """Decode ``nav_msgs/Odometry`` into a :class:`Measurement`
    (:func:`ga_ros.core.encoding.decode_measurement`, shared with the bag reader)."""
    return encoding.decode_measurement(msg)


# --------------------------------------------------------------------------- outputs
def path_to_msg(T_world_node: FloatArray, stamps_ns: Sequence[int] | IntArray, frame_id: str,
                stamp_ns: int | None = None) -> Path:
    """Corrected poses ``(n, 4, 4)`` in ``frame_id`` -> ``nav_msgs/Path`` (one pose per node).

    ``stamps_ns`` gives each pose's stamp; the path header gets ``stamp_ns`` (default: the last
    node's stamp, or 0 for an empty path).
    """
    T_world_node = np.asarray(T_world_node, dtype=float).reshape(-1, 4, 4)
    stamps = np.asarray(stamps_ns, dtype=np.int64).reshape(-1)
    if stamps.shape[0] != T_world_node.shape[0]:
        raise InputError(f'{T_world_node.shape[0]} poses but {stamps.shape[0]} stamps')
    msg = Path()
    msg.header.frame_id = frame_id
    if stamp_ns is None:
        stamp_ns = int(stamps[-1]) if stamps.size else 0
    msg.header.stamp = ns_to_stamp(stamp_ns)
    if T_world_node.shape[0]:
        p, q = se3.to_pos_quat(T_world_node)
        p, q = p.tolist(), q.tolist()
    poses = []
    for k in range(T_world_node.shape[0]):
        ps = PoseStamped()
        ps.header.frame_id = frame_id
        ps.header.stamp = ns_to_stamp(int(stamps[k]))
        ps.pose.position.x, ps.pose.position.y, ps.pose.position.z = p[k]
        o = ps.pose.orientation
        o.x, o.y, o.z, o.w = q[k]
        poses.append(ps)
    msg.poses = poses
    return msg


def path_msg_to_poses(msg: Path) -> FloatArray:
    """``nav_msgs/Path`` -> ``(n, 4, 4)`` poses (for tests and tools)."""
    if not msg.poses:
        return np.zeros((0, 4, 4))
    p = np.array([[s.pose.position.x, s.pose.position.y, s.pose.position.z] for s in msg.poses])
    q = np.array([[s.pose.orientation.x, s.pose.orientation.y, s.pose.orientation.z,
                   s.pose.orientation.w] for s in msg.poses])
    return se3.from_pos_quat(p, q)


def pose_with_covariance_msg(T_world_node: FloatArray, cov: FloatArray, frame_id: str,
                             stamp_ns: int) -> PoseWithCovarianceStamped:
    """Pose ``T_world_node`` with 6x6 covariance (right perturbation, ``[x y z rx ry rz]``)."""
    msg = PoseWithCovarianceStamped()
    msg.header.frame_id = frame_id
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.pose.pose = pose_to_msg(T_world_node)
    msg.pose.covariance = covariance_to_msg(cov)
    return msg


def odometry_msg(T_world_node: FloatArray, cov: FloatArray, frame_id: str, child_frame_id: str,
                 stamp_ns: int) -> Odometry:
    """Corrected pose of ``child_frame_id`` in ``frame_id`` as ``nav_msgs/Odometry`` (the output
    stream for mapping nodes; the twist is unknown and left zero with zero covariance)."""
    msg = Odometry()
    msg.header.frame_id = frame_id
    msg.child_frame_id = child_frame_id
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.pose.pose = pose_to_msg(T_world_node)
    msg.pose.covariance = covariance_to_msg(cov)
    return msg


def network_markers(p_world_node: FloatArray, src_index: IntArray, dst_index: IntArray,
                    normalized_residual: FloatArray, frame_id: str, stamp_ns: int,
                    node_colors: FloatArray | None = None, node_scale: float = 0.2,
                    line_width: float = 0.05, residual_scale: float = 3.0,
                    namespace: str = 'ga',
                    connection_colors: FloatArray | None = None) -> MarkerArray:
    """The connection network as a ``MarkerArray`` for RViz / Foxglove.

    Parameters
    ----------
    p_world_node : (n, 3) node positions in ``frame_id`` (m).
    src_index, dst_index : (m,) node indices of the connections' ends.
    normalized_residual : (m,) Mahalanobis norm of each connection's residual (unitless); colours
        the connection lines via :func:`residual_color`.
    node_colors : (n, 4) RGBA per node (default: blue).
    connection_colors : (m, 4) RGBA per connection (default: from ``normalized_residual``).

    Returns
    -------
    MarkerArray with a ``DELETEALL`` marker first, then a ``SPHERE_LIST`` of nodes (id 0) and a
    ``LINE_LIST`` of connections (id 1).
    """
    net = encoding.network_index(p_world_node, src_index, dst_index)
    p, src, dst = net.p, net.src, net.dst
    stamp = ns_to_stamp(stamp_ns)
    clear = Marker(action=Marker.DELETEALL)
    clear.header.frame_id = frame_id
    clear.ns = namespace

    nodes = Marker(type=Marker.SPHERE_LIST, action=Marker.ADD, id=0)
    nodes.header.frame_id = frame_id
    nodes.header.stamp = stamp
    nodes.ns = namespace + '/nodes'
    nodes.pose.orientation.w = 1.0
    nodes.scale.x = nodes.scale.y = nodes.scale.z = float(node_scale)
    nodes.points = [Point(x=x, y=y, z=z) for x, y, z in p.tolist()]
    if node_colors is None:
        nodes.color = ColorRGBA(r=0.2, g=0.4, b=1.0, a=1.0)
    else:
        nc = np.asarray(node_colors, dtype=float).reshape(-1, 4)
        nodes.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
        nodes.colors = [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in nc.tolist()]

    lines = Marker(type=Marker.LINE_LIST, action=Marker.ADD, id=1)
    lines.header.frame_id = frame_id
    lines.header.stamp = stamp
    lines.ns = namespace + '/connections'
    lines.pose.orientation.w = 1.0
    lines.scale.x = float(line_width)
    lines.color = ColorRGBA(r=1.0, g=1.0, b=1.0, a=1.0)
    ends = np.empty((2 * src.size, 3))
    ends[0::2] = p[src]
    ends[1::2] = p[dst]
    lines.points = [Point(x=x, y=y, z=z) for x, y, z in ends.tolist()]
    if connection_colors is None:
        connection_colors = residual_color(normalized_residual, residual_scale)
    rgba = np.asarray(connection_colors, dtype=float).reshape(-1, 4)
    if rgba.shape[0] != src.size:
        raise InputError(f'{rgba.shape[0]} connection colours for {src.size} connections')
    rgba = np.repeat(rgba, 2, axis=0)
    lines.colors = [ColorRGBA(r=r, g=g, b=b, a=a) for r, g, b, a in rgba.tolist()]
    return MarkerArray(markers=[clear, nodes, lines])


#: RGBA of a connection excluded by the gate (magenta) and alpha of an absorbed one (faded).
OUTLIER_RGBA = (1.0, 0.0, 1.0, 1.0)
ABSORBED_ALPHA = 0.3


def connection_rgba(normalized_residual: FloatArray, status: IntArray, scale: float,
                    w: FloatArray | None = None) -> FloatArray:
    """Colour of each connection line, ``(m, 4)`` RGBA.

    The palette is :func:`residual_color` (green at 0, yellow at ``scale / 2``, red at ``scale``
    and above, grey when unknown) of the connection's Mahalanobis misclosure, or, when ``w`` is
    given (quality control on), of its largest ``|w|`` (Baarda's w-statistic at its last
    adjustment): with ``scale`` = the w-test's critical value (3.29 at ``alpha0 = 1e-3``, 3.89 at
    1e-4) red means *rejected by the w-test*. Connections excluded by the gate (``status`` 2) are
    magenta, those absorbed into a prior (``status`` 1) faded.
    """
    value = np.abs(np.asarray(w, dtype=float)) if w is not None else normalized_residual
    rgba = residual_color(value, scale)
    status = np.asarray(status).reshape(-1)
    rgba[status == OUTLIER] = OUTLIER_RGBA
    rgba[status == ABSORBED, 3] = ABSORBED_ALPHA
    return rgba


def quality_values(summary: object | None) -> dict[str, object]:
    """Diagnostics key/values of a :class:`ga_ros.core.quality.QualitySummary` (the last window
    update's; empty when quality control is off).

    Keys: ``quality/global_test`` (``pass``/``fail``: the variance factor's chi-square test),
    ``quality/sigma0_sq``, ``quality/w_max`` (largest ``|w|``) and ``quality/w_max_connection``
    (``src->dst`` node ids), ``quality/w_critical``, ``quality/n_w_rejected`` (connections whose
    w-test rejects), ``quality/redundancy_min`` (smallest redundancy number),
    ``quality/mdb_median_m`` and ``quality/mdb_median_deg`` (median minimal detectable bias),
    ``quality/ms`` (its cost).
    """
    if summary is None:
        return {}
    s = summary
    return {
        'quality/global_test': 'pass' if s.global_passed else 'fail',
        'quality/sigma0_sq': float(s.sigma0_sq),
        'quality/w_max': float(s.w_max),
        'quality/w_max_connection': f'{s.w_max_src_id}->{s.w_max_dst_id}',
        'quality/w_critical': float(s.w_critical),
        'quality/n_w_rejected': int(s.n_w_rejected),
        'quality/redundancy_min': float(s.redundancy_number_min),
        'quality/mdb_median_m': float(s.mdb_median_m),
        'quality/mdb_median_deg': float(np.degrees(s.mdb_median_rad)),
        'quality/ms': 1e3 * float(s.seconds),
    }


def diagnostics_msg(name: str, hardware_id: str, values: Mapping[str, object], stamp_ns: int,
                    level: int = 0, message: str = 'ok') -> DiagnosticArray:
    """One ``DiagnosticStatus`` with ``values`` as key/value strings (floats with 6 significant
    digits). ``level``: 0 OK, 1 WARN, 2 ERROR, 3 STALE."""
    status = DiagnosticStatus(level=bytes([int(level)]), name=name, hardware_id=hardware_id,
                              message=message)
    kv = []
    for key, value in values.items():
        if isinstance(value, float | np.floating):
            text = f'{float(value):.6g}'
        else:
            text = str(value)
        kv.append(KeyValue(key=str(key), value=text))
    status.values = kv
    msg = DiagnosticArray(status=[status])
    msg.header.stamp = ns_to_stamp(stamp_ns)
    return msg


def diagnostics_to_dict(msg: DiagnosticArray) -> dict[str, str]:
    """Flatten the key/values of every status in a ``DiagnosticArray`` (for tests and tools)."""
    return {kv.key: kv.value for status in msg.status for kv in status.values}


def transform_msg(parent: str, child: str, T_parent_child: FloatArray,
                  stamp_ns: int) -> TransformStamped:
    """``geometry_msgs/TransformStamped``: the pose of ``child`` in ``parent`` (a TF edge)."""
    msg = TransformStamped()
    msg.header.frame_id = parent
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.child_frame_id = child
    p, q = se3.to_pos_quat(np.asarray(T_parent_child, dtype=float))
    tr = msg.transform
    tr.translation.x, tr.translation.y, tr.translation.z = (float(v) for v in p)
    tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w = (float(v) for v in q)
    return msg


# --------------------------------------------------------------------------- point clouds
#: Layout of :func:`cloud_to_pointcloud2`: little-endian float32 ``x y z intensity``, 16 bytes.
CLOUD_DTYPE = np.dtype({'names': ['x', 'y', 'z', 'intensity'], 'formats': ['<f4'] * 4,
                        'offsets': [0, 4, 8, 12], 'itemsize': 16})


def cloud_to_pointcloud2(points: np.ndarray, intensity: np.ndarray, frame_id: str,
                         stamp_ns: int) -> PointCloud2:
    """``sensor_msgs/PointCloud2`` of ``n`` points, as RViz and Foxglove read it.

    One unordered row (``height`` 1, ``width`` n); fields ``x y z intensity``, each ``FLOAT32``
    (count 1) at offsets 0, 4, 8, 12; ``point_step`` 16, ``row_step`` 16 n, little-endian;
    ``is_dense`` true (every point finite: pass only valid points).

    Parameters
    ----------
    points : (n, 3) ``x y z`` in ``frame_id`` (m).
    intensity : (n,) a value per point (e.g. the grey level 0-255).
    frame_id : the points' frame (a camera's optical frame for keyframe clouds).
    stamp_ns : ``header.stamp`` (ns).

    Raises
    ------
    InputError
        Shapes that do not match, or a non-finite value.
    """
    P = np.asarray(points)
    inten = np.asarray(intensity).reshape(-1)
    if P.ndim != 2 or P.shape[1] != 3 or inten.shape[0] != P.shape[0]:
        raise InputError(f'a cloud needs (n, 3) points and (n,) intensities, got '
                         f'{P.shape} and {np.shape(intensity)}')
    arr = np.empty(P.shape[0], CLOUD_DTYPE)
    arr['x'], arr['y'], arr['z'] = P[:, 0], P[:, 1], P[:, 2]
    arr['intensity'] = inten
    if not np.all(np.isfinite(arr.view('<f4'))):
        raise InputError('a cloud with is_dense true must hold finite values only')
    msg = PointCloud2()
    msg.header.stamp = ns_to_stamp(stamp_ns)
    msg.header.frame_id = frame_id
    msg.height, msg.width = 1, int(P.shape[0])
    msg.fields = [PointField(name=name, offset=int(CLOUD_DTYPE.fields[name][1]),
                             datatype=PointField.FLOAT32, count=1)
                  for name in CLOUD_DTYPE.names]
    msg.is_bigendian = False
    msg.point_step = CLOUD_DTYPE.itemsize
    msg.row_step = CLOUD_DTYPE.itemsize * msg.width
    msg.data = arr.tobytes()  # the structured array's bytes: no per-point loop
    msg.is_dense = True
    return msg
