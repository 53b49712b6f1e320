"""A stereo camera beside any odometry: cross-track connections on the odometry's keyframes.

A robot that navigates with wheel / DVL / INS odometry and carries a stereo camera gets the
cross-track connections of the stereo pipeline on the keyframes its odometry input defines
(:class:`ga_ros.inputs.odometry.OdometryInput`):

* **images to keyframes**: left/right images are paired as by the stereo front end (one
  tolerance, :class:`ga_ros.pipeline.stereo.StereoFrontEnd`); each odometry keyframe takes the
  pair nearest to its stamp within ``max_image_offset_s`` (decided once a pair at or after the
  keyframe's stamp arrived); a keyframe without one, or whose nearest pair an earlier keyframe
  took (two keyframes within one image period, e.g. in a turn), is counted and gets no
  cross-track connection;
* **keyframe records**: the pair's ORB features and stereo points, extracted by the stereo VO's
  own keyframe initialisation (:class:`ga_ros.vo.odometry.StereoOdometry`, re-initialised on
  the pair), posed at the odometry's ``T_odom_base T_base_cam`` and named by the odometry's
  node, track and segment (swath) ids;
* **overlap prediction and verification**: :class:`ga_ros.vo.crosstrack.CrossTrackMatcher`
  predicts overlap from the current corrected poses of those keyframes
  (:meth:`KeyframeCamera.set_corrected`, ``T_world_base T_base_cam``) and verifies it with the
  images;
* **frames**: a verified camera motion ``T_ca_cb`` becomes the base motion between the two
  image stamps, :func:`ga_ros.geometry.se3.change_frame` with the extrinsic ``T_base_cam``; the
  caller ties those stamps to the keyframes by the odometry between them
  (:meth:`ga_ros.inputs.odometry.OdometryInput.constraint_from_stamps`).

ROS-free: messages are read by field name (rclpy and rosbags messages alike).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import GaError, InputError
from ga_ros.geometry import se3
from ga_ros.pipeline.stereo import FrontEndConfig, ImagePair, StereoFrontEnd
from ga_ros.vo.calibration import CameraModel
from ga_ros.vo.messages import image_to_grey
from ga_ros.vo.odometry import StereoFrame


@dataclass(frozen=True)
class KeyframeCameraConfig:
    """Settings of :class:`KeyframeCamera`.

    Attributes
    ----------
    front : stereo pairing tolerance (``max_pair_dt_sec``), keyframe feature extraction
        (``vo``: ORB features, stereo matching), cross-track matching (``cross``) and the
        camera's name (``source``, default ``cam0``: its connections' ``Measurement.source``).
    T_base_camera : the extrinsic ``T_base_cam`` as ``x y z qx qy qz qw`` (m; the camera's
        optical frame in the base frame, as ``static_transform_publisher`` takes it).
    max_image_offset_s : largest time between a keyframe and the image pair used for it (s).
    max_waiting_pairs : image pairs kept for keyframes still to come.
    """

    front: FrontEndConfig = field(default_factory=FrontEndConfig)
    T_base_camera: tuple[float, ...] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0)
    max_image_offset_s: float = 0.25
    max_waiting_pairs: int = 50

    def __post_init__(self) -> None:
        if len(self.T_base_camera) != 7:
            raise InputError('T_base_camera must be 7 numbers: x y z qx qy qz qw, got '
                             f'{len(self.T_base_camera)}')
        q = np.asarray(self.T_base_camera[3:], float)
        if not np.all(np.isfinite(self.T_base_camera)) or abs(np.linalg.norm(q) - 1) > 1e-3:
            raise InputError(f'T_base_camera {self.T_base_camera}: the quaternion must be '
                             'finite and of unit length')
        if self.max_image_offset_s <= 0 or self.max_waiting_pairs < 1:
            raise InputError('max_image_offset_s must be > 0 and max_waiting_pairs >= 1')

    @property
    def T_base_cam(self) -> FloatArray:
        """(4, 4) the extrinsic."""
        v = np.asarray(self.T_base_camera, float)
        return se3.from_pos_quat(v[:3], v[3:] / np.linalg.norm(v[3:]))


@dataclass(frozen=True)
class CameraConnection:
    """A verified cross-track connection in the base frame, between two image stamps.

    Attributes
    ----------
    src_id, dst_id : the keyframes (node ids) the two images were taken for.
    src_stamp_ns, dst_stamp_ns : the images' stamps (ns).
    T_src_dst : (4, 4) motion of the base from the first image's time to the second's.
    cov : (6, 6) its covariance ``[x y z rx ry rz]`` (right perturbation).
    """

    src_id: int
    dst_id: int
    src_stamp_ns: int
    dst_stamp_ns: int
    T_src_dst: FloatArray
    cov: FloatArray


@dataclass
class KeyframeCameraStats:
    """Counts of a :class:`KeyframeCamera`.

    Attributes
    ----------
    pairs : image pairs made.
    keyframes_with_image : keyframes that got an image pair (and a store record).
    keyframes_without_image : keyframes with no pair within ``max_image_offset_s``, or whose
        nearest pair an earlier keyframe took.
    keyframes_without_features : keyframes whose pair gave too few stereo features.
    cross_attempts, cross_accepted : verified candidates, accepted connections.
    """

    pairs: int = 0
    keyframes_with_image: int = 0
    keyframes_without_image: int = 0
    keyframes_without_features: int = 0
    cross_attempts: int = 0
    cross_accepted: int = 0


@dataclass(frozen=True)
class _Keyframe:
    node_id: int
    track_id: int
    segment: int
    stamp_ns: int
    T_odom_base: FloatArray


class KeyframeCamera:
    """Stereo images matched to odometry keyframes -> cross-track connections (module doc).

    Parameters
    ----------
    config : the settings.
    """

    def __init__(self, config: KeyframeCameraConfig | None = None) -> None:
        self.config = config or KeyframeCameraConfig()
        self.T_base_cam = self.config.T_base_cam
        self.front = StereoFrontEnd(self.config.front)
        self.stats = KeyframeCameraStats()
        self._pairs: deque[ImagePair] = deque(maxlen=self.config.max_waiting_pairs)
        self._waiting: list[_Keyframe] = []
        self._image_stamp: dict[int, int] = {}
        self._last_used_ns = -1

    @property
    def source(self) -> str:
        """The camera's name, the ``Measurement.source`` of its cross-track connections."""
        return self.config.front.source

    # ------------------------------------------------------------------ calibration
    def set_camera_info(self, side: str, msg: Any) -> None:
        """A ``CameraInfo`` of ``side`` (``'left'``/``'right'``).

        Raises
        ------
        InputError
            A malformed or inconsistent calibration (the previous one stays).
        """
        self.front.set_camera_info(side, msg)

    def set_camera_models(self, left: CameraModel, right: CameraModel) -> None:
        """A calibration read from files (bags without ``CameraInfo``)."""
        self.front.set_camera_models(left, right)

    # ------------------------------------------------------------------ inputs
    def add_image(self, side: str, msg: Any) -> list[CameraConnection]:
        """One image message; the connections of the keyframes it completes."""
        pair = self.front.pair_image(side, msg)
        if pair is None:
            return []
        self.stats.pairs += 1
        self._pairs.append(pair)
        return self._resolve()

    def add_keyframe(self, node_id: int, track_id: int, segment: int, stamp_ns: int,
                     T_odom_base: FloatArray) -> list[CameraConnection]:
        """A new keyframe of the odometry; its connections if its image pair is already here
        (else when a later pair decides it)."""
        self._waiting.append(_Keyframe(int(node_id), int(track_id), int(segment),
                                       int(stamp_ns), np.asarray(T_odom_base, float)))
        return self._resolve()

    def forget_keyframes(self) -> None:
        """Forget the odometry's keyframes (those waiting for an image pair and the records the
        matcher holds; the calibration and the image pairs stay): the odometry starts a fresh
        keyframe chain whose ids name other nodes
        (:meth:`InputFrontEnd.continue_from <ga_ros.pipeline.inputs.InputFrontEnd.continue_from>`).
        Cross-track connections then come only between keyframes of the new chain."""
        self._waiting.clear()
        self._image_stamp.clear()
        self.front.forget_keyframes()

    def set_corrected(self, node_ids: IntArray, T_world_base: FloatArray) -> None:
        """Corrected base poses of keyframes (node ids) for the overlap prediction."""
        T = np.asarray(T_world_base, float).reshape(-1, 4, 4) @ self.T_base_cam
        self.front.set_corrected(np.asarray(node_ids), T)

    # ------------------------------------------------------------------ helpers
    def _resolve(self) -> list[CameraConnection]:
        out: list[CameraConnection] = []
        tol = int(self.config.max_image_offset_s * 1e9)
        while len(self._waiting) > self.config.max_waiting_pairs:  # the camera stopped
            self._waiting.pop(0)
            self.stats.keyframes_without_image += 1
        while self._waiting and self._pairs:
            kf = self._waiting[0]
            if self._pairs[-1].stamp_ns < kf.stamp_ns:
                break  # a nearer pair may still come
            self._waiting.pop(0)
            best = min(self._pairs, key=lambda p: abs(p.stamp_ns - kf.stamp_ns))
            if abs(best.stamp_ns - kf.stamp_ns) > tol or best.stamp_ns <= self._last_used_ns:
                self.stats.keyframes_without_image += 1
                continue
            out += self._match(kf, best)
        return out

    def _match(self, kf: _Keyframe, pair: ImagePair) -> list[CameraConnection]:
        front = self.front
        if front.odometry is None or front.matcher is None:
            self.stats.keyframes_without_image += 1
            return []
        try:
            left, right = image_to_grey(pair.left), image_to_grey(pair.right)
            front.odometry.reset()  # the VO's keyframe initialisation extracts the record
            res = front.odometry.process(StereoFrame(left, right, int(pair.stamp_ns)))
        except GaError:
            res = None
        if res is None or res.keyframe is None:
            self.stats.keyframes_without_features += 1
            return []
        self.stats.keyframes_with_image += 1
        record = replace(res.keyframe, node_id=kf.node_id, track_id=kf.track_id,
                         segment=kf.segment, stamp_ns=int(pair.stamp_ns),
                         T_world_kf=kf.T_odom_base @ self.T_base_cam)
        self._image_stamp[kf.node_id] = int(pair.stamp_ns)
        self._last_used_ns = int(pair.stamp_ns)
        attempts = front.matcher.add(record)
        self.stats.cross_attempts += len(attempts)
        out = []
        for a in attempts:
            m = a.measurement
            if not a.accepted or m is None or m.src_id not in self._image_stamp:
                continue
            T_ca_cb = se3.from_translation_rotvec(m.z[:3], m.z[3:])
            T, cov = se3.change_frame(T_ca_cb, m.cov, self.T_base_cam)
            out.append(CameraConnection(int(m.src_id), int(m.dst_id),
                                        self._image_stamp[int(m.src_id)], int(pair.stamp_ns),
                                        T, cov))
        self.stats.cross_accepted += len(out)
        self._forget()
        return out

    def _forget(self) -> None:
        """Image stamps only of keyframes the matcher still stores."""
        if self.front.matcher is None or len(self._image_stamp) <= 2 * len(self.front.matcher):
            return
        kept = set(self.front.matcher.node_ids)
        self._image_stamp = {k: v for k, v in self._image_stamp.items() if k in kept}
