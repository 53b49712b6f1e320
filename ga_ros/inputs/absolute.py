"""Absolute inputs (GNSS, AMCL, USBL, motion capture) -> :class:`~ga_ros.core.fixes.AbsoluteFix`
(ROS-free, duck-typed: rclpy and rosbags messages alike).

Message types (:data:`ABSOLUTE_TYPES`)
    ``geometry_msgs/msg/PoseWithCovarianceStamped`` (AMCL's ``/amcl_pose``, a USBL or motion
    capture pose) and ``nav_msgs/msg/Odometry`` (its pose part): a pose of the sensor in
    ``header.frame_id`` (the map frame) with a covariance ``[x y z rx ry rz]`` about the map's
    axes. ``sensor_msgs/msg/NavSatFix``: latitude, longitude, altitude (WGS84), converted to a
    local East-North-Up frame (:func:`geodetic_to_enu`, exact WGS84 formulas through ECEF) whose
    origin is the ``datum`` parameter ``[lat_deg, lon_deg, alt_m]`` when ``use_datum`` (as
    navsat_transform's ``wait_for_datum`` / ``datum``), else the first fix used
    (:attr:`AbsoluteDecoder.datum`, written to the replay's summary; the map frame is
    then that ENU frame). A NavSatFix with ``status.status == STATUS_NO_FIX`` (-1) is dropped
    and counted (``fix_no_fix``); ``STATUS_UNKNOWN`` (-2, Jazzy's default: a driver that does not
    fill the status) is used, as robot_localization's navsat_transform does;
    ``position_covariance_type`` is honoured (``UNKNOWN``: the default; ``APPROXIMATED`` and
    ``DIAGONAL_KNOWN``: the diagonal; ``KNOWN``: the full matrix, ENU axes); a NavSatFix never
    has a known orientation. Every NavSatFix input without its own datum shares one origin.

Position only or full pose (REP 145 practice)
    A variance ``-1``, NaN, infinite or at least ``unknown_variance`` marks an unknown
    dimension: zero information there (:func:`ga_ros.core.fixes.fix_information`). So AMCL's
    pose (x, y, yaw variances, the others 0 or huge) is an x-y-yaw fix when its z, roll and
    pitch variances are huge; zeros in those rows are read as "not measured" too when
    ``zero_is_unknown`` (the default: AMCL publishes zeros there). ``position_only`` ignores
    any orientation.

Missing covariance
    An all-zero covariance (or a NavSatFix with ``COVARIANCE_TYPE_UNKNOWN``) is replaced by
    the documented default ``default_sigma_m`` per position axis and, for a pose type,
    ``default_sigma_rad`` per rotation axis (position only if ``default_sigma_rad <= 0``);
    each use is counted (``default_covariances``) so the front end can warn, throttled.

Lever arm
    The fix is of the sensor, the graph's nodes are of the base (:class:`ga_ros.core.fixes.
    FixTerm`). The sensor's frame is a NavSatFix's ``header.frame_id`` or an Odometry's
    ``child_frame_id`` (a PoseWithCovarianceStamped is of the base, as AMCL's); its pose in
    ``base_frame`` comes from ``/tf_static`` when ``lever_arm_from_tf`` and the static tree links
    them (:class:`ga_ros.core.extrinsic.TransformTree`, the one ``/tf_static`` reader), else
    from ``T_base_sensor`` ``[x, y, z, qx, qy, qz, qw]``.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, fields
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.encoding import pose_to_matrix, stamp_to_ns
from ga_ros.core.extrinsic import TransformTree, renamed_parameter_error
from ga_ros.core.fixes import UNKNOWN_VARIANCE, AbsoluteFix
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.inputs.messages import resolve_type
from ga_ros.inputs.names import FIX, source_name

POSE_COV = 'geometry_msgs/msg/PoseWithCovarianceStamped'
ODOMETRY = 'nav_msgs/msg/Odometry'
NAVSAT = 'sensor_msgs/msg/NavSatFix'
#: ``sensor_msgs/NavSatStatus.STATUS_NO_FIX``: the receiver has no position (message dropped)
STATUS_NO_FIX = -1
#: Message types an absolute input accepts.
ABSOLUTE_TYPES = (POSE_COV, ODOMETRY, NAVSAT)
ABSOLUTE_ALIASES = {'pose_with_covariance': POSE_COV, 'pose_cov': POSE_COV, 'amcl': POSE_COV,
                    'odometry': ODOMETRY, 'odom': ODOMETRY, 'navsatfix': NAVSAT, 'gnss': NAVSAT,
                    'gps': NAVSAT, 'geometry_msgs/PoseWithCovarianceStamped': POSE_COV,
                    'nav_msgs/Odometry': ODOMETRY, 'sensor_msgs/NavSatFix': NAVSAT}

# WGS84 (NIMA TR8350.2): semi-major axis (m) and flattening
_A = 6378137.0
_F = 1.0 / 298.257223563
_E2 = _F * (2.0 - _F)


def absolute_type(name: str) -> str:
    """The full message type of an absolute input type (full name or alias).

    Raises
    ------
    InputError
        An unknown type.
    """
    return resolve_type(name, ABSOLUTE_TYPES, ABSOLUTE_ALIASES, 'absolute input')


def geodetic_to_ecef(lat_deg: FloatArray, lon_deg: FloatArray, alt_m: FloatArray) -> FloatArray:
    """WGS84 geodetic coordinates -> ECEF (m), ``(..., 3)``: ``x = (N + h) cos(lat) cos(lon)``,
    ``y = (N + h) cos(lat) sin(lon)``, ``z = (N (1 - e^2) + h) sin(lat)`` with the prime
    vertical radius ``N = a / sqrt(1 - e^2 sin^2(lat))``."""
    lat, lon = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    h = np.asarray(alt_m, float)
    N = _A / np.sqrt(1.0 - _E2 * np.sin(lat) ** 2)
    return np.stack([(N + h) * np.cos(lat) * np.cos(lon), (N + h) * np.cos(lat) * np.sin(lon),
                     (N * (1.0 - _E2) + h) * np.sin(lat)], axis=-1)


def enu_rotation(lat_deg: float, lon_deg: float) -> FloatArray:
    """(3, 3) rotation ``R_enu_ecef`` of the local East-North-Up frame at a point."""
    lat, lon = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    sl, cl, so, co = np.sin(lat), np.cos(lat), np.sin(lon), np.cos(lon)
    return np.array([[-so, co, 0.0], [-sl * co, -sl * so, cl], [cl * co, cl * so, sl]])


def geodetic_to_enu(lat_deg, lon_deg, alt_m, datum: Sequence[float]) -> FloatArray:
    """WGS84 geodetic coordinates -> East-North-Up (m) about ``datum = [lat, lon, alt]``."""
    d = np.asarray(datum, float)
    p = geodetic_to_ecef(lat_deg, lon_deg, alt_m) - geodetic_to_ecef(d[0], d[1], d[2])
    return p @ enu_rotation(d[0], d[1]).T


def T_earth_enu(datum: Sequence[float]) -> FloatArray:
    """(4, 4) pose of the East-North-Up frame at ``datum = [lat_deg, lon_deg, alt_m]`` in ECEF
    (REP 105's ``earth`` frame): ``p_earth = R_enu_ecef' p_enu + ecef(datum)``, the inverse of
    :func:`geodetic_to_enu`. With the map frame the NavSatFix inputs' ENU frame, it is the
    ``earth -> map`` transform."""
    d = np.asarray(datum, float)
    if d.shape != (3,) or not np.isfinite(d).all():
        raise InputError(f'a datum must be [lat_deg, lon_deg, alt_m], got {d.tolist()}')
    T = np.eye(4)
    T[:3, :3] = enu_rotation(d[0], d[1]).T
    T[:3, 3] = geodetic_to_ecef(d[0], d[1], d[2])
    return T


@dataclass(frozen=True)
class AbsoluteInputConfig:
    """One absolute input (mirrors robot_localization's ``poseN`` / navsat_transform settings).

    Attributes
    ----------
    name : the input's name (``fix0``, ``amcl0``, ...).
    frame_id : expected ``header.frame_id`` of a pose type ('' accepts any); the map frame.
    default_sigma_m : position sigma (m, per axis) used when the message has no covariance.
    default_sigma_rad : rotation sigma (rad, per axis) used then for a pose type; <= 0: such
        a fix is position only.
    unknown_variance : variances at or above this (m^2, rad^2) mark an unknown dimension.
    zero_is_unknown : a zero variance beside known ones marks an unknown dimension (AMCL).
    position_only : ignore the orientation of pose types.
    use_datum : the ENU origin of a NavSatFix input is ``datum``; ``False``: the first fix.
    datum : ``[lat_deg, lon_deg, alt_m]`` of that origin.
    T_base_sensor : the sensor's pose in the base frame, ``[x, y, z, qx, qy, qz, qw]`` (m,
        quaternion x y z w: the ``T_base_<sensor>`` convention of
        :mod:`ga_ros.core.extrinsic`), when ``/tf_static`` does not give it (the old
        ``lever_arm_m`` is refused with the new name).
    lever_arm_from_tf : take ``T_base_sensor`` from ``/tf_static`` when it links
        ``base_frame`` to the sensor's frame.
    base_frame : the robot's base frame (REP 105 ``base_link``).
    ends_track : a used fix ends the current track at the next keyframe, so the window update
        that uses it runs then (the online estimate follows the fixes).
    track_min_interval_s : at least this long between two tracks ended by fixes (s).
    tolerance_s : a fix waits at most this long for the odometry that covers its stamp (s).
    """

    name: str = source_name(FIX, 0)
    frame_id: str = ''
    default_sigma_m: float = 5.0
    default_sigma_rad: float = 0.0
    unknown_variance: float = UNKNOWN_VARIANCE
    zero_is_unknown: bool = True
    position_only: bool = False
    use_datum: bool = False
    datum: tuple[float, ...] = (0.0, 0.0, 0.0)
    T_base_sensor: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    lever_arm_from_tf: bool = True
    base_frame: str = 'base_link'
    ends_track: bool = True
    track_min_interval_s: float = 10.0
    tolerance_s: float = 5.0

    def __post_init__(self) -> None:
        object.__setattr__(self, 'datum', tuple(float(v) for v in self.datum))
        object.__setattr__(self, 'T_base_sensor', tuple(float(v) for v in self.T_base_sensor))
        if len(self.datum) != 3 or not np.isfinite(self.datum).all():
            raise InputError(f'{self.name}.datum must be [lat_deg, lon_deg, alt_m], got '
                             f'{list(self.datum)}')
        v = np.asarray(self.T_base_sensor, float)
        if v.shape != (7,) or not np.isfinite(v).all() or abs(np.linalg.norm(v[3:]) - 1) > 1e-3:
            raise InputError(f'{self.name}.T_base_sensor must be [x, y, z, qx, qy, qz, qw] '
                             f'(m, unit quaternion), got {list(self.T_base_sensor)}')
        if not (self.default_sigma_m > 0 and self.unknown_variance > 0
                and self.track_min_interval_s >= 0 and self.tolerance_s >= 0):
            raise InputError(f'{self.name}: default_sigma_m and unknown_variance must be > 0, '
                             'track_min_interval_s and tolerance_s >= 0')

    @classmethod
    def from_mapping(cls, name: str, values: Mapping[str, object]) -> AbsoluteInputConfig:
        """The config of input ``name`` from a mapping of its fields.

        Raises
        ------
        InputError
            An unknown setting or a bad value.
        """
        if 'lever_arm_m' in values:
            raise renamed_parameter_error(f'{name}.lever_arm_m', f'{name}.T_base_sensor')
        known = {f.name for f in fields(cls)}
        unknown = set(values) - known
        if unknown:
            raise InputError(f'absolute input {name!r}: unknown settings {sorted(unknown)}; '
                             f'known: {sorted(known - {"name"})}')
        return cls(name=name, **dict(values))

    @property
    def T_base_sensor_matrix(self) -> FloatArray:
        """(4, 4) the sensor's pose in the base frame (the lever arm) of ``T_base_sensor``."""
        v = np.asarray(self.T_base_sensor, float)
        return se3.from_pos_quat(v[:3], v[3:])


@dataclass
class AbsoluteStats:
    """Counters of one absolute input."""

    messages: int = 0
    fixes: int = 0
    default_covariances: int = 0
    lever_arm_from_tf: int = 0
    dropped: dict[str, int] = field(default_factory=dict)


class AbsoluteDecoder:
    """Messages of one absolute input -> fixes (module doc).

    Parameters
    ----------
    config : the input's settings.
    msgtype : its message type (full name or alias).
    """

    def __init__(self, config: AbsoluteInputConfig, msgtype: str) -> None:
        self.config = config
        self.msgtype = absolute_type(msgtype)
        self.datum: tuple[float, float, float] | None = (
            tuple(config.datum) if config.use_datum else None)  # type: ignore[assignment]
        self.stats = AbsoluteStats()

    def drop(self, reason: str) -> None:
        """Count a dropped message."""
        self.stats.dropped[reason] = self.stats.dropped.get(reason, 0) + 1

    def sensor_frame(self, msg: Any) -> str:
        """The frame of the sensor that made a message (module doc; '' for the base)."""
        if self.msgtype == NAVSAT:
            return str(msg.header.frame_id).lstrip('/')
        if self.msgtype == ODOMETRY:
            return str(msg.child_frame_id).lstrip('/')
        return ''

    def T_base_sensor(self, sensor_frame: str, static: TransformTree | None) -> FloatArray:
        """(4, 4) the sensor's pose in the base frame (module doc: ``/tf_static`` or
        ``T_base_sensor``; a loop in the static tree counts as not linked)."""
        cfg = self.config
        if cfg.lever_arm_from_tf and static is not None and sensor_frame:
            try:
                T = static.lookup(cfg.base_frame, sensor_frame)
            except InputError:
                T = None
            if T is not None:
                self.stats.lever_arm_from_tf += 1
                return T
        return cfg.T_base_sensor_matrix

    def decode(self, msg: Any) -> tuple[AbsoluteFix, bool]:
        """``(fix, used the default covariance)`` of one message.

        Raises
        ------
        InputError
            A malformed message, a NavSatFix without a fix (``reason``-counted by the caller),
            a frame other than ``frame_id``, or a covariance without a known dimension.
        """
        cfg = self.config
        self.stats.messages += 1
        stamp = stamp_to_ns(msg.header.stamp)
        if self.msgtype == NAVSAT:
            T, cov, default = self._navsat(msg)
        else:
            frame = str(msg.header.frame_id).lstrip('/')
            if cfg.frame_id and frame != cfg.frame_id.lstrip('/'):
                raise InputError(f'{cfg.name}: frame {frame!r}, expected {cfg.frame_id!r}')
            T = pose_to_matrix(msg.pose.pose)
            cov = np.asarray(msg.pose.covariance, dtype=float).reshape(6, 6).copy()
            default = not np.any(cov[np.isfinite(cov)])
            if default:
                cov = self._default(with_rotation=cfg.default_sigma_rad > 0)
            if cfg.position_only:
                cov[3:, :] = 0.0
                cov[:, 3:] = 0.0
                cov[3:, 3:] = -np.eye(3)
        if cfg.zero_is_unknown:
            d = np.diag(cov)
            zero = np.isfinite(d) & (d == 0)
            if zero.any() and (np.isfinite(d) & (d > 0)).any():
                cov[zero, :] = 0.0
                cov[:, zero] = 0.0
                cov[zero, zero] = -1.0
        fix = AbsoluteFix.from_covariance(stamp, T, cov, cfg.name, cfg.unknown_variance)
        self.stats.fixes += 1
        self.stats.default_covariances += int(default)
        return fix, default

    def _default(self, with_rotation: bool) -> FloatArray:
        cfg = self.config
        rot = cfg.default_sigma_rad ** 2 if with_rotation else -1.0
        return np.diag([cfg.default_sigma_m ** 2] * 3 + [rot] * 3)

    def _navsat(self, msg: Any) -> tuple[FloatArray, FloatArray, bool]:
        status = int(getattr(getattr(msg, 'status', None), 'status', 0))
        if status == STATUS_NO_FIX:
            err = InputError(f'{self.config.name}: NavSatFix without a fix (status {status})')
            err.fix_reason = 'fix_no_fix'
            raise err
        lla = np.array([msg.latitude, msg.longitude, msg.altitude], dtype=float)
        if not np.isfinite(lla).all():
            raise InputError(f'{self.config.name}: NavSatFix with a non-finite position',
                             reason='non_finite')
        if self.datum is None:
            self.datum = (float(lla[0]), float(lla[1]), float(lla[2]))
        T = np.eye(4)
        T[:3, 3] = geodetic_to_enu(lla[0], lla[1], lla[2], self.datum)
        ctype = int(getattr(msg, 'position_covariance_type', 0))
        C3 = np.asarray(msg.position_covariance, dtype=float).reshape(3, 3)
        default = ctype == 0 or not np.any(C3[np.isfinite(C3)])
        cov = -np.eye(6)
        if default:
            cov[:3, :3] = self.config.default_sigma_m ** 2 * np.eye(3)
        elif ctype in (1, 2):
            cov[:3, :3] = np.diag(np.diag(C3))
        else:
            cov[:3, :3] = C3
        return T, cov, default
