"""The stereo front end: image messages -> pairs -> stereo VO -> cross-track matching.

One object that ``vo_node`` and the replay both drive, so they pair, decode, calibrate and
match alike:

* **pairing** of left and right images with ONE tolerance (``max_pair_dt_sec``); unpaired images
  older than a pair are dropped, at most ``max_pending`` wait per side;
* **decoding** of ``Image`` (mono8/16, bgr8/8UC3, rgb8, bgra8, rgba8) and ``CompressedImage``
  by :func:`ga_ros.vo.messages.image_to_grey`;
* **calibration** from the two ``CameraInfo`` (:func:`ga_ros.vo.messages.camera_info_to_model`),
  re-made only when it changes (the VO then continues its node and track ids);
* **VO** (:class:`ga_ros.vo.odometry.StereoOdometry`) then **cross-track matching**
  (:class:`ga_ros.vo.crosstrack.CrossTrackMatcher`), as two calls: the caller feeds the VO's
  motion to the aligner in between (:meth:`StereoFrontEnd.match` after
  :meth:`StereoFrontEnd.add_image`), so that the matcher sees the newest corrected path;
* **feedback** of the corrected path (:meth:`set_corrected`, or :meth:`set_corrected_by_stamp`
  for a ``nav_msgs/Path`` whose poses carry the keyframe stamps).

ROS-free: messages are read by field name (rclpy and rosbags messages alike).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.encoding import stamp_to_ns
from ga_ros.core.measurement import Measurement
from ga_ros.errors import GaError
from ga_ros.vo.calibration import CameraModel, StereoCalibration
from ga_ros.vo.crosstrack import CrossAttempt, CrossTrackConfig, CrossTrackMatcher
from ga_ros.vo.messages import camera_info_to_model, image_to_grey, same_model
from ga_ros.vo.odometry import StereoFrame, StereoOdometry, VoConfig, VoResult

#: Keyframe stamps remembered for :meth:`StereoFrontEnd.set_corrected_by_stamp`.
MAX_STAMPS = 50000


@dataclass(frozen=True)
class FrontEndConfig:
    """Settings of the stereo front end.

    Attributes
    ----------
    vo : stereo VO settings.
    cross : cross-track matching settings.
    cross_track : run the cross-track matcher.
    feedback : give corrected poses to the matcher (:meth:`StereoFrontEnd.set_corrected`).
    max_pair_dt_sec : largest stamp difference of a left/right pair (s).
    max_pending : unpaired images kept per side before the oldest is dropped.
    """

    vo: VoConfig = field(default_factory=VoConfig)
    cross: CrossTrackConfig = field(default_factory=CrossTrackConfig)
    cross_track: bool = True
    feedback: bool = True
    max_pair_dt_sec: float = 0.005
    max_pending: int = 50


@dataclass
class StereoStats:
    """Counts of the front end (written to the replay summary).

    ``reasons`` counts why pairs gave no motion (``'no CameraInfo yet'``, ``'bad pair'``,
    ``'lost: ...'`` with numbers replaced by ``#``).
    """

    pairs: int = 0
    unpaired: int = 0
    keyframes: int = 0
    lost: int = 0
    cross_attempts: int = 0
    cross_accepted: int = 0
    reasons: dict[str, int] = field(default_factory=dict)


@dataclass(frozen=True)
class FrameOutput:
    """What one stereo pair gave.

    Attributes
    ----------
    stamp_ns : acquisition time of the pair (the left image's stamp), ns.
    result : the VO result; None when the pair was dropped (see ``error``).
    error : why the pair was dropped (``'stereo: ...'``), else None.
    node_stamps : ``{node id: stamp_ns}`` of a new keyframe (empty otherwise).
    left, right : the decoded grey images (for a debug image), None when dropped.
    """

    stamp_ns: int
    result: VoResult | None = None
    error: str | None = None
    node_stamps: dict[int, int] = field(default_factory=dict)
    left: np.ndarray | None = None
    right: np.ndarray | None = None

    @property
    def measurement(self) -> Measurement | None:
        """The keyframe-to-keyframe motion, if this pair made a new keyframe."""
        return None if self.result is None else self.result.measurement


class StereoFrontEnd:
    """Stereo pairs -> VO motions and cross-track connections (see the module docstring).

    Parameters
    ----------
    config : :class:`FrontEndConfig`.
    """

    def __init__(self, config: FrontEndConfig | None = None) -> None:
        self.config = config or FrontEndConfig()
        self.stats = StereoStats()
        self.odometry: StereoOdometry | None = None
        self.matcher: CrossTrackMatcher | None = None
        self.calibration: StereoCalibration | None = None
        self._models: dict[str, CameraModel] = {}
        self._pending: dict[str, dict[int, Any]] = {'left': {}, 'right': {}}
        self._stamp_to_node: dict[int, int] = {}

    # ------------------------------------------------------------------ calibration
    def set_camera_info(self, side: str, msg: Any) -> StereoCalibration | None:
        """Use a ``CameraInfo`` of ``side``; returns the new calibration when it changed.

        The first pair of models starts the VO; a later different model re-initialises it
        (node and track ids continue); a repeated identical one changes nothing.

        Raises
        ------
        InputError
            A malformed CameraInfo or an inconsistent stereo pair; the previous calibration
            stays.
        """
        model = camera_info_to_model(msg)
        old = self._models.get(side)
        if old is not None and same_model(old, model) and self.calibration is not None:
            return None
        self._models[side] = model
        if len(self._models) < 2:
            return None
        try:
            cal = StereoCalibration.from_camera_models(self._models['left'],
                                                       self._models['right'])
        except GaError:
            if old is not None:
                self._models[side] = old  # keep the last good calibration
            raise
        self.calibration = cal
        if self.odometry is None:
            self.odometry = StereoOdometry(cal, self.config.vo)
        else:
            self.odometry = self.odometry.recalibrated(cal)
        self.matcher = CrossTrackMatcher(cal.K, cal.width, cal.height, self.config.cross)
        return cal

    # ------------------------------------------------------------------ images
    def add_image(self, side: str, msg: Any) -> list[FrameOutput]:
        """Add one image message of ``side`` (``'left'``/``'right'``); process the pair it
        completes, if any (a list of at most one output)."""
        stamp = stamp_to_ns(msg.header.stamp)
        other = 'right' if side == 'left' else 'left'
        tol = int(round(self.config.max_pair_dt_sec * 1e9))
        match = next((s for s in self._pending[other] if abs(s - stamp) <= tol), None)
        if match is None:
            mine = self._pending[side]
            mine[stamp] = msg
            if len(mine) > self.config.max_pending:
                mine.pop(next(iter(mine)))
                self.stats.unpaired += 1
            return []
        omsg = self._pending[other].pop(match)
        for d in self._pending.values():  # older unpaired images will never pair
            for s in [s for s in d if s < min(stamp, match)]:
                d.pop(s)
                self.stats.unpaired += 1
        pair = {side: msg, other: omsg}
        self.stats.pairs += 1
        return [self._process(pair['left'], pair['right'], stamp if side == 'left' else match)]

    def _reason(self, key: str) -> None:
        self.stats.reasons[key] = self.stats.reasons.get(key, 0) + 1

    def _process(self, left_msg: Any, right_msg: Any, stamp_ns: int) -> FrameOutput:
        if self.odometry is None:
            self._reason('no CameraInfo yet')
            return FrameOutput(stamp_ns, error='stereo: no CameraInfo for both cameras yet')
        try:
            left = image_to_grey(left_msg)
            right = image_to_grey(right_msg)
            res = self.odometry.process(StereoFrame(left, right, int(stamp_ns)))
        except GaError as exc:
            self._reason('bad pair')
            return FrameOutput(stamp_ns, error=f'stereo: {exc}')
        if res.status == 'lost':
            self.stats.lost += 1
            self._reason('lost: ' + re.sub(r'[0-9][0-9.]*', '#', res.reason or '?'))
        stamps: dict[int, int] = {}
        if res.keyframe is not None:
            self.stats.keyframes += 1
            stamps[int(res.keyframe.node_id)] = int(res.keyframe.stamp_ns)
            self._stamp_to_node[int(res.keyframe.stamp_ns)] = int(res.keyframe.node_id)
            while len(self._stamp_to_node) > MAX_STAMPS:  # bounded (oldest first)
                self._stamp_to_node.pop(next(iter(self._stamp_to_node)))
        return FrameOutput(stamp_ns, res, None, stamps, left, right)

    def match(self, frame: FrameOutput) -> list[CrossAttempt]:
        """Cross-track matching of the frame's new keyframe (after its motion was used).

        Returns every attempt; the accepted ones carry a ``measurement``.

        Raises
        ------
        GaError
            If the matcher fails on this keyframe (the store is unchanged).
        """
        res = frame.result
        if (res is None or res.keyframe is None or self.matcher is None
                or not self.config.cross_track):
            return []
        attempts = self.matcher.add(res.keyframe)
        self.stats.cross_attempts += len(attempts)
        self.stats.cross_accepted += sum(a.accepted and a.measurement is not None
                                         for a in attempts)
        return attempts

    # ------------------------------------------------------------------ feedback, control
    def set_corrected(self, node_ids: IntArray, T_world_node: FloatArray) -> None:
        """Corrected poses of keyframes (node ids) for the matcher's overlap prediction."""
        if self.matcher is not None and self.config.feedback and len(node_ids):
            self.matcher.set_corrected_poses(np.asarray(node_ids), T_world_node)

    def set_corrected_by_stamp(self, stamps_ns: IntArray, T_world_node: FloatArray) -> int:
        """As :meth:`set_corrected`, with keyframes named by their stamps (a ``nav_msgs/Path``);
        poses of unknown stamps are ignored. Returns how many poses were used."""
        ids, keep = [], []
        for k, s in enumerate(np.asarray(stamps_ns, dtype=np.int64)):
            node = self._stamp_to_node.get(int(s))
            if node is not None:
                ids.append(node)
                keep.append(k)
        if ids:
            self.set_corrected(np.asarray(ids), np.asarray(T_world_node)[keep])
        return len(ids)

    def request_track_boundary(self) -> None:
        """Start a new track at the next keyframe (``track_mode: external``)."""
        if self.odometry is not None:
            self.odometry.request_track_boundary()

