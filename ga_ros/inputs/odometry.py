"""A standard odometry or pose stream -> keyframes -> relative-motion Measurements (ROS-free).

:class:`OdometryInput` is configured per input like robot_localization's ``odomN``/``poseN``
(:class:`OdometryInputConfig`: name, frame, covariance policy, keyframe and track rules) and fed
one sample at a time (:meth:`OdometryInput.add_sample`) with what a ``nav_msgs/Odometry``,
``geometry_msgs/PoseWithCovarianceStamped`` or ``PoseStamped`` carries, converted to numpy at
the edge: the stamp (ns), ``T_odom_base`` (4x4) and the 6x6 pose and twist covariances
(``[x y z rx ry rz]``; None when the message has none).

Keyframes
    The first sample is keyframe ``first_node_id`` (or the id a restarted input continues from,
    :meth:`OdometryInput.continue_from`, which after samples starts a fresh chain at the next
    sample); a sample becomes the next keyframe when its
    travel from the last keyframe exceeds ``keyframe_travel_m``, its rotation
    ``keyframe_rotation_deg`` or its time ``keyframe_interval_s``. At each new keyframe the
    motion ``T_kf_new = T_odom_kf^-1 T_odom_new`` is emitted as a ``'consecutive'``
    :class:`~ga_ros.core.measurement.Measurement` between the two keyframes' node ids.

Motion covariance (``covariance_source``; right perturbation ``T_kf_new exp(xi)``)
    ``'twist'``: the twist covariance ``Sigma_v`` (body frame, per second) integrated over the
    interval, each sample's velocity error independent:
    ``C <- Ad(D_k^-1) C Ad(D_k^-1)^T + dt_k^2 Sigma_v,k`` with ``D_k`` the motion from the
    previous sample (first order in the errors; the same reading as robot_localization's).
    ``'pose_difference'``: an odometry integrates independent increments, so its pose errors
    are a random walk: ``C_new = Ad(T^-1) C_kf Ad(T^-1)^T + C_motion``, whence
    ``C_motion = C_new - Ad(T^-1) C_kf Ad(T^-1)^T`` (``T = T_kf_new``), used when positive
    definite. Poses of one stream are correlated, so the independent sum would be far too large.
    ``'pose_independent'``: ``Ad(T^-1) C_kf Ad(T^-1)^T + C_new``, for poses with independent
    errors (e.g. a localiser in a prior map).
    ``'default'``: the documented default below, always.
    ``'auto'`` (the default): twist when every sample since the keyframe had a usable twist
    covariance, else the pose difference when positive definite, else the default.

    Pose covariances are read in ``pose_covariance_frame``: ``'parent'`` (the message
    definition's reading: position and rotation errors along the axes of ``header.frame_id``,
    as robot_localization reads them) is turned into the body frame by
    ``C_body = B^T C_parent B``, ``B = blkdiag(R, R)``, ``R`` the rotation of ``T_odom_base``;
    ``'body'`` is used as is (ga_ros's own convention).

Default covariance
    A covariance that is missing (None), all zeros (Nav2's ``/odom``), marked unknown (``-1`` in
    its first element, the REP 145 habit), not finite or not positive definite is replaced by
    the paper's noise model (:class:`ga_ros.sim.noise.NoiseModel`):
    ``sigma_t = p |t|`` (m) and ``sigma_w = p max(|w|, |t| / depth)`` (rad) per axis with
    ``p = default_noise_percent / 100`` and ``depth = default_depth_m``, floored at
    ``default_sigma_floor_m`` / ``default_sigma_floor_rad`` so that a still robot keeps a
    positive definite covariance. Each use is counted (:attr:`InputStats.default_covariances`)
    and flagged (:attr:`InputUpdate.default_covariance`) so that the node can warn (throttled).

Track boundaries
    :class:`ga_ros.core.tracks.TrackSegmenter` (heading reversal, distance, time, a fixed number
    of keyframes, or :meth:`OdometryInput.request_track_boundary`), the same one the VO uses.

External constraints
    :meth:`OdometryInput.constraint_from_stamps` maps a relative pose between two stamps onto
    the nearest keyframes (within ``constraint_tolerance_s``) with the odometry between each
    keyframe and its stamp, interpolated on SE(3) between the neighbouring samples;
    :meth:`OdometryInput.constraint_from_nodes` takes node ids directly. Both return
    ``'cross'`` Measurements.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.core.tracks import TrackRules, TrackSegmenter, refuse_former_names
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.inputs.names import ODOMETRY, source_name
from ga_ros.sim.noise import NoiseModel

COVARIANCE_SOURCES = ('auto', 'twist', 'pose_difference', 'pose_independent', 'default')


@dataclass(frozen=True)
class OdometryInputConfig:
    """One odometry / pose input (mirrors robot_localization's per-sensor ``odomN`` settings).

    Attributes
    ----------
    name : the input's name (``odom0``, ``pose0``, ...), used in messages.
    frame_id : expected ``header.frame_id`` of the stream ('' accepts any).
    covariance_source : ``'auto'``, ``'twist'``, ``'pose_difference'``, ``'pose_independent'``
        or ``'default'`` (see the module doc).
    pose_covariance_frame : ``'parent'`` (axes of ``header.frame_id``) or ``'body'``.
    default_noise_percent : default motion noise in percent of the motion (module doc).
    default_depth_m : distance (m) converting a translation into its equivalent rotation
        ``|t| / depth`` in the default model (the scale of the scene around the robot).
    default_sigma_floor_m : smallest default translation sigma per axis (m).
    default_sigma_floor_rad : smallest default rotation sigma per axis (rad).
    keyframe_travel_m : new keyframe after this travel from the last one (m; 0: off).
    keyframe_rotation_deg : new keyframe after this rotation (deg; 0: off).
    keyframe_interval_s : new keyframe after this time (s; 0: off).
    track : track boundaries (parameters ``<name>.track.<field>``,
        :class:`ga_ros.core.tracks.TrackRules`; default one track, ``mode`` ``'none'``).
    constraint_tolerance_s : largest time between a constraint's stamp and its keyframe (s).
    history_s : odometry kept for interpolating constraint stamps (s).
    max_gap_s : a further (secondary) input: largest interval between two of its samples
        around or inside a keyframe interval that it still measures; a longer gap is a dropout
        (s; :mod:`ga_ros.inputs.secondary`).
    first_node_id : node id of the first keyframe.
    """

    name: str = source_name(ODOMETRY, 0)
    frame_id: str = ''
    covariance_source: str = 'auto'
    pose_covariance_frame: str = 'parent'
    default_noise_percent: float = 5.0
    default_depth_m: float = 10.0
    default_sigma_floor_m: float = 0.01
    default_sigma_floor_rad: float = 0.002
    keyframe_travel_m: float = 1.0
    keyframe_rotation_deg: float = 15.0
    keyframe_interval_s: float = 0.0
    track: TrackRules = TrackRules()
    constraint_tolerance_s: float = 2.0
    history_s: float = 600.0
    max_gap_s: float = 1.0
    first_node_id: int = 0

    def __post_init__(self) -> None:
        if self.covariance_source not in COVARIANCE_SOURCES:
            raise InputError(f'{self.name}: unknown covariance_source '
                             f'{self.covariance_source!r}; use one of {COVARIANCE_SOURCES}')
        if self.pose_covariance_frame not in ('parent', 'body'):
            raise InputError(f"{self.name}: pose_covariance_frame must be 'parent' or 'body'")
        if not (self.keyframe_travel_m > 0 or self.keyframe_rotation_deg > 0
                or self.keyframe_interval_s > 0):
            raise InputError(f'{self.name}: set at least one of keyframe_travel_m, '
                             'keyframe_rotation_deg, keyframe_interval_s > 0')
        if min(self.default_sigma_floor_m, self.default_sigma_floor_rad) <= 0:
            raise InputError(f'{self.name}: default sigma floors must be > 0')
        self.noise_model()
        if not isinstance(self.track, TrackRules):
            raise InputError(f'{self.name}: track must be a TrackRules, got '
                             f'{type(self.track).__name__}')

    @classmethod
    def from_mapping(cls, name: str, values: Mapping[str, object]) -> OdometryInputConfig:
        """The config of input ``name`` from a mapping (a section of ``config/inputs.yaml``).

        Raises
        ------
        InputError
            An unknown key (a typo would otherwise be ignored) or an invalid value.
        """
        known = {f.name: f.default for f in fields(cls) if f.name != 'name'}
        refuse_former_names([f'{name}.{k}' for k in values], f'{name}.')
        unknown = sorted(set(values) - set(known))
        if unknown:
            raise InputError(f'{name}: unknown input settings {unknown}; known: {sorted(known)}')
        for key, value in values.items():
            _check_setting(f'{name}.{key}', value, known[key])
        values = dict(values)
        if 'track' in values:
            track = values['track']
            if isinstance(track, Mapping):
                for key, value in track.items():
                    _check_setting(f'{name}.track.{key}', value, getattr(TrackRules(), key, None))
            values['track'] = TrackRules.from_mapping(track, f'{name}.track')
        return cls(name=str(name), **values)

    def noise_model(self) -> NoiseModel:
        """The paper's noise model behind the default covariance."""
        return NoiseModel(self.default_noise_percent, self.default_depth_m)

    def default_covariance(self, z: FloatArray) -> FloatArray:
        """(6, 6) default covariance of a motion ``z = [t, w]`` (m, rad; see the module doc)."""
        s = self.noise_model().sigmas(np.asarray(z, float))[0]
        s[:3] = np.maximum(s[:3], self.default_sigma_floor_m)
        s[3:] = np.maximum(s[3:], self.default_sigma_floor_rad)
        return np.diag(s * s)


@dataclass(frozen=True)
class InputUpdate:
    """Outcome of one :meth:`OdometryInput.add_sample`.

    Attributes
    ----------
    stamp_ns : the sample's time (ns).
    keyframe_id : node id of the current reference keyframe.
    track_id : its track.
    new_keyframe : the sample became a keyframe.
    new_track : the keyframe starts a new track.
    measurement : the motion from the previous keyframe (at a new keyframe after the first).
    covariance_source : ``'twist'``, ``'pose_difference'``, ``'pose_independent'`` or
        ``'default'`` for the measurement ('' without one).
    default_covariance : the default covariance replaced a missing or unusable one.
    """

    stamp_ns: int
    keyframe_id: int
    track_id: int
    new_keyframe: bool = False
    new_track: bool = False
    measurement: Measurement | None = None
    covariance_source: str = ''
    default_covariance: bool = False


@dataclass(frozen=True)
class InputStats:
    """Counters of an :class:`OdometryInput` (for diagnostics and throttled warnings).

    Attributes
    ----------
    samples : samples accepted.
    keyframes : keyframes made.
    measurements : consecutive measurements emitted.
    constraints : cross measurements made from external constraints.
    default_covariances : measurements or constraints whose covariance was the default.
    missing_covariances : those of them whose stream had no covariance at all (no usable twist
        or pose covariance); the others had one that could not be used (e.g. a pose covariance
        that does not grow from the keyframe, so their difference is not positive definite).
    """

    samples: int
    keyframes: int
    measurements: int
    constraints: int
    default_covariances: int
    missing_covariances: int = 0


def _check_setting(key: str, value: object, default: object) -> None:
    """A setting of the type of its default: a finite number (an integer within int64 where the
    default is one), a bool or a string; :class:`InputError` naming ``key`` otherwise."""
    shown = repr(value) if len(repr(value)) <= 40 else repr(value)[:40] + '...'
    if isinstance(default, bool) or isinstance(default, str):
        if not isinstance(value, type(default)):
            raise InputError(f'{key} must be a {type(default).__name__}, got {shown}')
        return
    if isinstance(default, int | float):
        if isinstance(value, bool) or not isinstance(value, int | float | np.integer
                                                     | np.floating):
            raise InputError(f'{key} must be a number, got {shown}')
        if isinstance(default, int) and not isinstance(value, int | np.integer):
            raise InputError(f'{key} must be an integer, got {shown}')
        if not (abs(value) < 2**63 and np.isfinite(float(value))):
            raise InputError(f'{key} must be a finite number below 2^63 in size, got {shown}')


def usable_covariance(cov: FloatArray | None) -> bool:
    """True for a finite, symmetric, positive definite 6x6 covariance.

    False for None, all zeros, the ``-1`` "unknown" marker in the first element, non-finite or
    indefinite matrices: the cases a publisher uses to say it has no covariance.
    """
    if cov is None:
        return False
    c = np.asarray(cov, float)
    if c.shape != (6, 6) or not np.all(np.isfinite(c)) or c[0, 0] == -1.0:
        return False
    if np.abs(c - c.T).max() > 1e-6 * np.abs(c).max() + 1e-12:
        return False
    return bool(np.linalg.eigvalsh(c).min() > 1e-12 * max(float(np.abs(c).max()), 1e-300))


def transport_covariance(T_a_b: FloatArray, C_a: FloatArray) -> FloatArray:
    """``Ad(T_a_b^-1) C_a Ad(T_a_b^-1)^T``: a right-perturbation covariance at ``a`` seen at
    ``b`` (``T_a exp(x) T_a_b = T_a T_a_b exp(Ad(T_a_b^-1) x)``)."""
    A = se3.adjoint(se3.inverse(T_a_b))
    return A @ C_a @ A.T


def interpolate_pose(T_a: FloatArray, T_b: FloatArray, alpha: float) -> FloatArray:
    """Geodesic interpolation ``T_a exp(alpha log(T_a^-1 T_b))`` (``alpha`` in [0, 1])."""
    return T_a @ se3.exp(alpha * se3.local(T_a, T_b))


def body_pose_covariance(T_odom_base: FloatArray, pose_cov: FloatArray | None,
                         frame: str) -> FloatArray | None:
    """A sample's pose covariance in the body frame (None when unusable, see
    :func:`usable_covariance`).

    Parameters
    ----------
    T_odom_base : (4, 4) the sample's pose.
    pose_cov : (6, 6) its covariance ``[x y z rx ry rz]``, or None.
    frame : ``'parent'`` (axes of ``header.frame_id``: ``C_body = B^T C B``,
        ``B = blkdiag(R, R)``) or ``'body'`` (returned as is).
    """
    if not usable_covariance(pose_cov):
        return None
    C = np.asarray(pose_cov, float)
    if frame == 'parent':
        B = np.zeros((6, 6))
        B[:3, :3] = B[3:, 3:] = np.asarray(T_odom_base, float)[:3, :3]
        C = B.T @ C @ B
    return C


def check_pose(T: FloatArray, what: str) -> FloatArray:
    """``T`` as a float array if it is a finite 4x4 pose with a rotation matrix.

    Raises
    ------
    InputError
        Another shape, non-finite values or no rotation matrix (``what`` names it).
    """
    T = np.asarray(T, float)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)):
        raise InputError(f'{what} must be a finite 4x4 pose, got shape {T.shape}')
    R = T[:3, :3]
    if np.abs(R.T @ R - np.eye(3)).max() > 1e-6 or np.linalg.det(R) <= 0:
        raise InputError(f'{what} has no rotation matrix (normalise the quaternion)')
    return T


class OdometryInput:
    """An odometry / pose stream turned into keyframe Measurements (see the module doc).

    Parameters
    ----------
    config : the input's settings.
    """

    def __init__(self, config: OdometryInputConfig = OdometryInputConfig()) -> None:
        self.config = config
        self.segmenter = TrackSegmenter(config.track)
        self._first_id = self._next_id = int(config.first_node_id)
        self._stamps: list[int] = []
        self._poses: list[FloatArray] = []
        self._kf_ids: list[int] = []
        self._kf_stamps: list[int] = []
        self._kf_poses: list[FloatArray] = []
        self._kf_tracks: list[int] = []
        self._kf_cov: FloatArray | None = None
        self._twist_cov = np.zeros((6, 6))
        self._twist_ok = True
        self._n = dict(samples=0, keyframes=0, measurements=0, constraints=0,
                       default_covariances=0, missing_covariances=0)

    # ------------------------------------------------------------------ public
    @property
    def stats(self) -> InputStats:
        """Counters so far."""
        return InputStats(**self._n)

    def request_track_boundary(self) -> None:
        """Start a new track at the next keyframe (e.g. from a topic)."""
        self.segmenter.request_boundary()

    def continue_from(self, node_id: int, track_id: int) -> None:
        """Number the keyframes from ``node_id``, the first one on track ``track_id``
        (instead of ``first_node_id`` and track 0): a restarted input continuing the survey of a
        restored state after its nodes and tracks.

        Before the first sample this only sets the numbering. After samples (the state was
        replaced under a running input, ``~/load_state``) it starts a fresh keyframe chain: the
        keyframes so far are forgotten (their ids no longer name the state's nodes), the next
        sample is keyframe ``node_id`` with no motion from the one before, and the track rules
        start afresh on track ``track_id``. The samples kept (``history_s``) and the counters
        stay: the stream goes on, and a constraint or fix stamped after the new first keyframe
        is tied to it by the odometry as before.

        Raises
        ------
        InputError
            Negative ids.
        """
        if int(node_id) < 0 or int(track_id) < 0:
            raise InputError(f'{self.config.name}: node and track ids must be >= 0, got '
                             f'{node_id}, {track_id}')
        self._first_id = self._next_id = int(node_id)
        self._kf_ids, self._kf_stamps, self._kf_poses, self._kf_tracks = [], [], [], []
        self._kf_cov = None
        self._twist_cov = np.zeros((6, 6))
        self._twist_ok = True
        self.segmenter = TrackSegmenter(self.config.track)
        self.segmenter.track_id = int(track_id)

    def add_sample(self, stamp_ns: int, T_odom_base: FloatArray,
                   pose_cov: FloatArray | None = None,
                   twist_cov: FloatArray | None = None) -> InputUpdate:
        """Feed one sample of the stream.

        Parameters
        ----------
        stamp_ns : its time (ns), strictly after the previous sample's.
        T_odom_base : (4, 4) pose of the base in the stream's frame.
        pose_cov : (6, 6) pose covariance ``[x y z rx ry rz]`` (frame per
            ``pose_covariance_frame``), or None (``PoseStamped``).
        twist_cov : (6, 6) body-frame twist covariance ((m/s)^2, (rad/s)^2), or None.

        Raises
        ------
        InputError
            A malformed pose or a stamp not after the previous one (nothing changed; restart
            the input, e.g. with a new :class:`OdometryInput`, when a bag loops).
        """
        T = check_pose(T_odom_base, f'{self.config.name}: T_odom_base')
        stamp = int(stamp_ns)
        if self._stamps and stamp <= self._stamps[-1]:
            raise InputError(f'{self.config.name}: stamp {stamp} ns is not after the previous '
                             f'sample ({self._stamps[-1]} ns); restart the input on a loop')
        C_pose = body_pose_covariance(T, pose_cov, self.config.pose_covariance_frame)
        if not self._kf_ids:   # the first sample, or the first after continue_from
            self._append(stamp, T)
            track = self._make_keyframe(stamp, T, C_pose)
            return InputUpdate(stamp, self._kf_ids[-1], track, True, True)
        D = se3.relative(self._poses[-1], T)
        dt = (stamp - self._stamps[-1]) * 1e-9
        if usable_covariance(twist_cov):
            self._twist_cov = (transport_covariance(D, self._twist_cov)
                               + dt * dt * np.asarray(twist_cov))
        else:
            self._twist_ok = False
        self._append(stamp, T)
        if not self._is_keyframe(stamp, T):
            return InputUpdate(stamp, self._kf_ids[-1], self._kf_tracks[-1])
        T_rel = se3.relative(self._kf_poses[-1], T)
        cov, source, default = self._motion_covariance(T_rel, C_pose)
        src_id, src_track = self._kf_ids[-1], self._kf_tracks[-1]
        before = self.segmenter.track_id
        track = self._make_keyframe(stamp, T, C_pose)
        meas = Measurement.from_pose(src_id, self._kf_ids[-1], src_track, track, T_rel, cov,
                                     stamp, 'consecutive', self.config.name)
        self._n['measurements'] += 1
        return InputUpdate(stamp, self._kf_ids[-1], track, True, track != before, meas, source,
                           default)

    def constraint_from_nodes(self, src_id: int, dst_id: int, T_src_dst: FloatArray,
                              cov: FloatArray | None) -> Measurement:
        """A ``'cross'`` Measurement between two known keyframes (e.g. a loop closure).

        ``cov`` (right perturbation of ``T_src_dst``) is replaced by the default when unusable
        (counted in :attr:`InputStats.default_covariances`).

        Raises
        ------
        InputError
            Unknown node ids, a self-loop or a malformed pose.
        """
        T = check_pose(T_src_dst, f'{self.config.name}: constraint T_src_dst')
        i, j = self._kf_index(src_id), self._kf_index(dst_id)
        if i == j:
            raise InputError(f'{self.config.name}: constraint from node {src_id} to itself')
        C = self._constraint_cov(T, cov)
        self._n['constraints'] += 1
        return Measurement.from_pose(src_id, dst_id, self._kf_tracks[i], self._kf_tracks[j], T,
                                     C, self._kf_stamps[j], 'cross')

    def constraint_from_stamps(self, stamp_a_ns: int, stamp_b_ns: int, T_a_b: FloatArray,
                               cov: FloatArray | None,
                               nodes: tuple[int, int] | None = None) -> Measurement:
        """A ``'cross'`` Measurement from a relative pose between the base at two stamps.

        Each stamp is mapped to its nearest keyframe ``k`` (within ``constraint_tolerance_s``;
        or to the keyframes ``nodes`` (node ids) when given, e.g. those an image was taken
        for) and the odometry ``T_k_a`` from the keyframe to the stamp, interpolated between the
        neighbouring samples. The result is ``T_ka_kb = T_ka_a T_a_b T_kb_b^-1`` with covariance
        ``Ad(T_kb_b) C Ad(T_kb_b)^T`` plus the noise model's covariance of the two offsets
        (``default_noise_percent`` of each offset, no floor: zero at a keyframe's own stamp)
        carried to ``kb``.

        Raises
        ------
        InputError
            A stamp outside the odometry received so far or with no keyframe within the
            tolerance (send constraints after the odometry that covers them), both stamps on one
            keyframe, or a malformed pose.
        """
        T_ab = check_pose(T_a_b, f'{self.config.name}: constraint T_a_b')
        ka, kb = nodes if nodes is not None else (None, None)
        ia, T_ka_a = self._anchor(int(stamp_a_ns), ka)
        ib, T_kb_b = self._anchor(int(stamp_b_ns), kb)
        if ia == ib:
            raise InputError(f'{self.config.name}: both constraint stamps map to keyframe '
                             f'{self._kf_ids[ia]}; the constraint adds nothing')
        T_b_kb = se3.inverse(T_kb_b)
        T = T_ka_a @ T_ab @ T_b_kb
        C_ab = self._constraint_cov(T_ab, cov)
        C = transport_covariance(T_b_kb, C_ab)
        offset = self.config.noise_model()
        C = C + transport_covariance(T_ab @ T_b_kb,
                                     offset.covariances(se3.to_translation_rotvec(T_ka_a))[0])
        C = C + offset.covariances(se3.to_translation_rotvec(T_b_kb))[0]
        self._n['constraints'] += 1
        return Measurement.from_pose(self._kf_ids[ia], self._kf_ids[ib], self._kf_tracks[ia],
                                     self._kf_tracks[ib], T, 0.5 * (C + C.T),
                                     self._kf_stamps[ib], 'cross')

    def latest_pose(self) -> FloatArray | None:
        """(4, 4) ``T_odom_base`` of the newest sample (None before any)."""
        return self._poses[-1].copy() if self._poses else None

    def keyframe_pose(self, node_id: int) -> FloatArray:
        """(4, 4) ``T_odom_kf`` of a keyframe."""
        return self._kf_poses[self._kf_index(node_id)].copy()

    def keyframe_stamp(self, node_id: int) -> int:
        """The stamp (ns) of a keyframe."""
        return int(self._kf_stamps[self._kf_index(node_id)])

    @property
    def keyframe_ids(self) -> tuple[int, int]:
        """``(first, end)``: the keyframes' node ids are ``first .. end - 1`` (consecutive; an
        empty range before the first keyframe), each with its :meth:`keyframe_pose`."""
        return self._first_id, self._first_id + len(self._kf_ids)

    # ----------------------------------------------------------------- helpers
    def _append(self, stamp: int, T: FloatArray) -> None:
        self._stamps.append(stamp)
        self._poses.append(T)
        self._n['samples'] += 1
        horizon = stamp - int(self.config.history_s * 1e9)
        drop = 0
        while drop < len(self._stamps) - 2 and self._stamps[drop + 1] < horizon:
            drop += 1
        if drop:
            del self._stamps[:drop], self._poses[:drop]

    def _is_keyframe(self, stamp: int, T: FloatArray) -> bool:
        cfg = self.config
        T_rel = se3.relative(self._kf_poses[-1], T)
        travel = float(np.linalg.norm(T_rel[:3, 3]))
        angle = float(np.arccos(np.clip(0.5 * (np.trace(T_rel[:3, :3]) - 1.0), -1.0, 1.0)))
        dt = (stamp - self._kf_stamps[-1]) * 1e-9
        return ((cfg.keyframe_travel_m > 0 and travel >= cfg.keyframe_travel_m)
                or (cfg.keyframe_rotation_deg > 0
                    and angle >= np.deg2rad(cfg.keyframe_rotation_deg))
                or (cfg.keyframe_interval_s > 0 and dt >= cfg.keyframe_interval_s))

    def _make_keyframe(self, stamp: int, T: FloatArray, C_pose: FloatArray | None) -> int:
        self.segmenter.update(T, stamp)
        track = self.segmenter.track_id
        self._kf_ids.append(self._next_id)
        self._next_id += 1
        self._kf_stamps.append(stamp)
        self._kf_poses.append(T)
        self._kf_tracks.append(track)
        self._kf_cov = C_pose
        self._twist_cov = np.zeros((6, 6))
        self._twist_ok = True
        self._n['keyframes'] += 1
        return track

    def _motion_covariance(self, T_rel: FloatArray, C_new: FloatArray | None
                           ) -> tuple[FloatArray, str, bool]:
        """Covariance of the keyframe motion, its source and whether it is the default."""
        src = self.config.covariance_source
        if src in ('auto', 'twist') and self._twist_ok and usable_covariance(self._twist_cov):
            return 0.5 * (self._twist_cov + self._twist_cov.T), 'twist', False
        if src in ('auto', 'pose_difference', 'pose_independent') and (
                self._kf_cov is not None and C_new is not None):
            prior = transport_covariance(T_rel, self._kf_cov)
            C = C_new + prior if src == 'pose_independent' else C_new - prior
            C = 0.5 * (C + C.T)
            if usable_covariance(C):
                return C, 'pose_independent' if src == 'pose_independent' else (
                    'pose_difference'), False
        self._n['default_covariances'] += 1
        twist_usable = self._twist_ok and usable_covariance(self._twist_cov)
        if not twist_usable and C_new is None:
            self._n['missing_covariances'] += 1
        return self.config.default_covariance(se3.to_translation_rotvec(T_rel)), 'default', True

    def _constraint_cov(self, T: FloatArray, cov: FloatArray | None) -> FloatArray:
        if usable_covariance(cov):
            return np.asarray(cov, float)
        self._n['default_covariances'] += 1
        self._n['missing_covariances'] += 1
        return self.config.default_covariance(se3.to_translation_rotvec(T))

    def _kf_index(self, node_id: int) -> int:
        i = int(node_id) - self._first_id
        if not 0 <= i < len(self._kf_ids):
            raise InputError(f'{self.config.name}: unknown node id {node_id} (keyframes '
                             f'{self._first_id}..{self._next_id - 1})')
        return i

    def _anchor(self, stamp: int, node: int | None = None) -> tuple[int, FloatArray]:
        """Index of the keyframe nearest to ``stamp`` (or of keyframe ``node``) and the
        odometry ``T_kf_stamp``."""
        name = self.config.name
        if not self._stamps or not self._stamps[0] <= stamp <= self._stamps[-1]:
            raise InputError(f'{name}: constraint stamp {stamp} ns is outside the odometry '
                             'received so far; send constraints after the odometry covering them')
        if not self._kf_ids:   # continue_from started a new chain: no keyframe of it yet
            raise InputError(f'{name}: no keyframe yet (the keyframes start again at node '
                             f'{self._first_id}, at the next sample)')
        ks = np.asarray(self._kf_stamps)
        i = int(np.argmin(np.abs(ks - stamp))) if node is None else self._kf_index(node)
        if abs(int(ks[i]) - stamp) * 1e-9 > self.config.constraint_tolerance_s:
            raise InputError(f'{name}: no keyframe within {self.config.constraint_tolerance_s}'
                             f' s of constraint stamp {stamp} ns; raise constraint_tolerance_s'
                             ' or lower the keyframe thresholds')
        T_odom_stamp = self._odom_at(stamp)
        return i, se3.relative(self._kf_poses[i], T_odom_stamp)

    def offset_at(self, stamp_ns: int) -> tuple[int, FloatArray, FloatArray]:
        """``(node id, T_kf_stamp, covariance)``: the keyframe at or before ``stamp_ns``, the
        odometry from it to the stamp (interpolated on SE(3) between the neighbouring samples)
        and that offset's covariance from the noise model (``default_noise_percent`` of the
        offset, no floor: zero at the keyframe's own stamp), right perturbation.

        Raises
        ------
        InputError
            A stamp outside the odometry kept so far (``history_s``) or before the first
            keyframe.
        """
        stamp = int(stamp_ns)
        if not self._stamps or not self._stamps[0] <= stamp <= self._stamps[-1]:
            raise InputError(f'{self.config.name}: stamp {stamp} ns is outside the odometry '
                             'kept so far')
        i = int(np.searchsorted(np.asarray(self._kf_stamps), stamp, side='right')) - 1
        if i < 0:
            raise InputError(f'{self.config.name}: stamp {stamp} ns is before the first keyframe')
        T_odom_stamp = self._odom_at(stamp)
        T = se3.relative(self._kf_poses[i], T_odom_stamp)
        C = self.config.noise_model().covariances(se3.to_translation_rotvec(T))[0]
        return self._kf_ids[i], T, C

    def _odom_at(self, stamp: int) -> FloatArray:
        """``T_odom_base`` at ``stamp`` (ns, within the samples kept): the sample at that stamp,
        else the SE(3) interpolation between its two neighbours."""
        s = np.asarray(self._stamps)
        j = int(np.searchsorted(s, stamp))
        if s[j] == stamp:
            return self._poses[j]
        alpha = (stamp - int(s[j - 1])) / (int(s[j]) - int(s[j - 1]))
        return interpolate_pose(self._poses[j - 1], self._poses[j], alpha)

    @property
    def latest_stamp_ns(self) -> int | None:
        """Stamp (ns) of the newest sample (None before any)."""
        return self._stamps[-1] if self._stamps else None
