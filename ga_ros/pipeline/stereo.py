"""The stereo front end: image messages -> pairs -> stereo VO -> cross-track matching.

One object that ``vo_node`` and the replay both drive, so they pair, decode, calibrate and
match alike:

* **pairing** of left and right images with ONE tolerance (``max_pair_dt_sec``); unpaired images
  older than a pair are dropped, at most ``max_pending`` wait per side (:meth:`pair_image`,
  cheap, then :meth:`process_pair`; :meth:`add_image` does both; ``vo_node`` queues the pairs
  in between); a pair completed before the calibration (its ``CameraInfo``, of the same stamp,
  arriving just after the images) waits for it (:meth:`hold_until_calibrated`,
  :meth:`release_held`), so that the arrival order of images and ``CameraInfo`` changes
  nothing;
* **accounting**: every pair is counted once, as a measurement or under the reason it gave
  none (:class:`StereoStats`);
* **decoding** of ``Image`` (mono8/16, bgr8/8UC3, rgb8, bgra8, rgba8) and ``CompressedImage``
  by :func:`ga_ros.vo.messages.image_to_grey`;
* **calibration** from the two ``CameraInfo`` (:func:`ga_ros.vo.messages.camera_info_to_model`),
  re-made only when it changes (the VO then continues its node and track ids);
* **VO** (:class:`ga_ros.vo.odometry.StereoOdometry`) then **cross-track matching**
  (:class:`ga_ros.vo.crosstrack.CrossTrackMatcher`), as two calls: the caller feeds the VO's
  motion to the aligner in between (:meth:`StereoFrontEnd.match` after
  :meth:`StereoFrontEnd.add_image`), so that the matcher sees the newest corrected path;
* **frames**: the VO measures the left camera's optical frame; with the camera's extrinsic
  (:meth:`set_extrinsic`, :class:`ga_ros.core.extrinsic.Extrinsic`: ``/tf_static``, parameters
  or the identity) every measurement is converted to the robot's ``base_link`` motion (and
  covariance) before it leaves, and :meth:`base_pose` gives the frame's ``T_odom_base``;
* **source**: every measurement leaves named by the camera (``source``, default ``cam0``,
  :mod:`ga_ros.inputs.names`), so its variance factor and its extrinsic's rotation
  (``docs/calibration.md``) are its own;
* **keyframe clouds** on request (:meth:`StereoFrontEnd.keyframe_cloud`, for map building):
  the dense stereo points of a new keyframe's rectified pair (:class:`ga_ros.vo.dense.DenseStereo`,
  settings ``cloud``); never computed unless asked (it costs CPU), and the VO's outputs are the
  same whether asked or not;
* **feedback** of the corrected path (:meth:`set_corrected`, or :meth:`set_corrected_by_stamp`
  for a ``nav_msgs/Path`` whose poses carry the keyframe stamps).

ROS-free: messages are read by field name (rclpy and rosbags messages alike).
"""

from __future__ import annotations

import re
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.encoding import stamp_to_ns
from ga_ros.core.extrinsic import Extrinsic, ExtrinsicConfig
from ga_ros.core.measurement import Measurement
from ga_ros.errors import GaError, InputError
from ga_ros.inputs.names import CAMERA_SOURCE, check_source_name
from ga_ros.pipeline.params import config_from_params
from ga_ros.vo.calibration import CameraModel, StereoCalibration
from ga_ros.vo.crosstrack import CrossAttempt, CrossTrackConfig, CrossTrackMatcher
from ga_ros.vo.dense import DenseStereo, DenseStereoConfig, StereoCloud
from ga_ros.vo.messages import camera_info_to_model, image_to_grey, same_model
from ga_ros.vo.odometry import StereoFrame, StereoOdometry, VoConfig, VoResult

#: Keyframe stamps remembered for :meth:`StereoFrontEnd.set_corrected_by_stamp`.
MAX_STAMPS = 50000

# Why a stereo pair gave no measurement (the keys of :attr:`StereoStats.reasons`; one per pair).
NO_CAMERA_INFO = 'no CameraInfo yet'
BAD_PAIR = 'bad image pair'
TEXTURELESS = 'textureless'
TOO_FEW_POINTS = 'too few stereo points'
FIRST_KEYFRAME = 'first keyframe (no motion yet)'
NOT_KEYFRAME = 'not a keyframe'
LOST = 'lost'
#: A pair the caller dropped before the VO saw it (``vo_node``'s queue was full).
DROPPED = 'dropped (queue full)'
#: A pair refused because the camera's extrinsic is not known yet (``vo_node`` waits for it).
NO_EXTRINSIC = 'no camera extrinsic yet'


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
    extrinsic : where the camera's pose in ``base_link`` comes from.
    cloud : dense stereo of the keyframe clouds (:meth:`StereoFrontEnd.keyframe_cloud`;
        parameters ``cloud_`` + :class:`ga_ros.vo.dense.DenseStereoConfig` fields).
    source : the camera's name, carried by every measurement it makes (``Measurement.source``:
        its consecutive motions and cross-track connections; the name of its variance group
        and of its extrinsic's parameters, ``docs/calibration.md``; at most
        :data:`~ga_ros.core.encoding.SOURCE_BYTES` bytes).
    """

    vo: VoConfig = field(default_factory=VoConfig)
    cross: CrossTrackConfig = field(default_factory=CrossTrackConfig)
    cross_track: bool = True
    feedback: bool = True
    max_pair_dt_sec: float = 0.005
    max_pending: int = 50
    extrinsic: ExtrinsicConfig = field(default_factory=ExtrinsicConfig)
    cloud: DenseStereoConfig = field(default_factory=DenseStereoConfig)
    source: str = CAMERA_SOURCE

    def __post_init__(self) -> None:
        check_source_name(self.source, 'the camera source (parameter source)')


#: Parameters of ``config/vo.yaml`` that only ``vo_node`` uses (topics, frames, queues): the replay
#: accepts and ignores them (a test checks they are the node's other settings).
NODE_ONLY_PARAMS = frozenset({
    'left_image_topic', 'right_image_topic', 'left_info_topic', 'right_info_topic', 'compressed',
    'measurements_topic', 'odometry_topic', 'path_topic', 'track_boundary_topic',
    'debug_image_topic', 'publish_debug_image', 'odom_frame', 'image_queue', 'pair_queue',
    'diagnostics_topic', 'diagnostics_period_sec', 'warn_throttle_sec', 'publish_odom_tf',
    'tf_topic', 'tf_static_topic', 'qos_reliability', 'loss_warn_fraction', 'idle_end_track_s',
    'keyframe_cloud_topic', 'publish_keyframe_cloud', 'keyframe_image_topic',
    'keyframe_info_topic', 'publish_keyframe_image'})


def front_end_config_from_params(params: Mapping[str, Any],
                                 base: FrontEndConfig | None = None) -> FrontEndConfig:
    """:class:`FrontEndConfig` from ``vo_node``'s parameters (``config/vo.yaml`` names: the
    :class:`VoConfig` fields, ``cross_`` + :class:`CrossTrackConfig` fields, ``cloud_`` +
    :class:`ga_ros.vo.dense.DenseStereoConfig` fields, ``cross_track``,
    ``max_pair_dt_sec``, ``source``; :data:`NODE_ONLY_PARAMS` are ignored), over ``base``.

    Raises
    ------
    InputError
        An unknown parameter name or a value of the wrong type.
    """
    base = base or FrontEndConfig()
    vo, used_vo = config_from_params(VoConfig, params, base=base.vo)
    cross, used_cross = config_from_params(CrossTrackConfig, params, 'cross_', base=base.cross)
    ext, used_ext = config_from_params(ExtrinsicConfig, params, base=base.extrinsic)
    cloud, used_cloud = config_from_params(DenseStereoConfig, params, 'cloud_', base=base.cloud)
    rest = {k: v for k, v in params.items()
            if k in ('cross_track', 'max_pair_dt_sec', 'source')}
    top, used_top = config_from_params(FrontEndConfig, rest, base=replace(
        base, vo=vo, cross=cross, extrinsic=ext, cloud=cloud))
    unknown = (set(params) - used_vo - used_cross - used_ext - used_cloud - used_top
               - NODE_ONLY_PARAMS)
    if unknown:
        raise InputError(f'unknown VO parameter(s) {", ".join(sorted(unknown))}; the names are '
                         'those of config/vo.yaml')
    return top


@dataclass
class StereoStats:
    """Counts of the front end (written to the replay summary and vo_node's diagnostics).

    Every pair is counted once: either in ``measurements`` or under one key of ``reasons``
    (:data:`NO_CAMERA_INFO`, :data:`BAD_PAIR`, :data:`TEXTURELESS`, :data:`TOO_FEW_POINTS`,
    :data:`FIRST_KEYFRAME`, :data:`NOT_KEYFRAME`, :data:`LOST`, :data:`DROPPED`,
    :data:`NO_EXTRINSIC`), so that
    ``pairs == measurements + sum(reasons.values())`` once every pair is processed.
    ``lost_reasons`` details the lost tracks (numbers replaced by ``#``). ``unpaired`` counts
    images (not pairs) that never found a partner within ``max_pair_dt_sec``;
    ``camera_info_rejected`` the CameraInfo messages refused (the calibration stays).
    """

    pairs: int = 0
    measurements: int = 0
    unpaired: int = 0
    keyframes: int = 0
    lost: int = 0
    cross_attempts: int = 0
    cross_accepted: int = 0
    camera_info_rejected: int = 0
    reasons: dict[str, int] = field(default_factory=dict)
    lost_reasons: dict[str, int] = field(default_factory=dict)

    def summary(self) -> str:
        """One line: what the pairs gave, e.g. ``'95 pairs: 0 measurements, 94 not a keyframe,
        1 first keyframe (no motion yet); 2 unpaired images'``."""
        parts = [f'{self.measurements} measurements'] + [
            f'{n} {k}' for k, n in sorted(self.reasons.items(), key=lambda kv: -kv[1])]
        text = f'{self.pairs} pairs: ' + ', '.join(parts)
        if self.unpaired:
            text += f'; {self.unpaired} unpaired images'
        if self.camera_info_rejected:
            text += f'; {self.camera_info_rejected} CameraInfo rejected'
        return text


@dataclass(frozen=True)
class ImagePair:
    """A left and a right image message whose stamps agree within ``max_pair_dt_sec``.

    Attributes
    ----------
    left, right : the image messages.
    stamp_ns : the left image's stamp (ns).
    """

    left: Any
    right: Any
    stamp_ns: int


@dataclass(frozen=True)
class FrameOutput:
    """What one stereo pair gave.

    Attributes
    ----------
    stamp_ns : acquisition time of the pair (the left image's stamp), ns.
    result : the VO result; None when the pair was dropped (see ``error``).
    error : why the pair was dropped (``'stereo: ...'``), else None.
    reason : why the pair gave no measurement (a key of :attr:`StereoStats.reasons`), '' when
        it gave one.
    node_stamps : ``{node id: stamp_ns}`` of a new keyframe (empty otherwise).
    left, right : the decoded grey images (for a debug image), None when dropped.
    """

    stamp_ns: int
    result: VoResult | None = None
    error: str | None = None
    node_stamps: dict[int, int] = field(default_factory=dict)
    left: np.ndarray | None = None
    right: np.ndarray | None = None
    reason: str = ''

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
        self._held: list[ImagePair] = []  # pairs completed before the calibration
        self._stamp_to_node: dict[int, int] = {}
        self._dense: DenseStereo | None = None  # built at the first keyframe cloud
        #: the camera's pose in ``base_link`` (None: not resolved yet, the identity is used)
        self.extrinsic: Extrinsic | None = None

    # ------------------------------------------------------------------ frames
    def set_extrinsic(self, extrinsic: Extrinsic) -> None:
        """Use ``extrinsic`` for every measurement and pose from now on."""
        self.extrinsic = extrinsic

    def base_pose(self, T_world_cam: FloatArray) -> FloatArray:
        """``T_odom_base`` of the VO's integrated camera pose (the identity extrinsic while none
        is set)."""
        if self.extrinsic is None:
            return np.asarray(T_world_cam, float)
        return self.extrinsic.pose(T_world_cam)

    def _to_base(self, m: Measurement | None) -> Measurement | None:
        """A camera measurement as the base's (with the extrinsic, once set), named by the
        camera's ``source``."""
        if m is None:
            return m
        if self.extrinsic is not None:
            m = self.extrinsic.motion(m)
        return replace(m, source=self.config.source)

    # ------------------------------------------------------------------ calibration
    def set_camera_info(self, side: str, msg: Any) -> StereoCalibration | None:
        """Use a ``CameraInfo`` of ``side``; returns the new calibration when it changed.

        The first pair of models starts the VO; a later different model re-initialises it
        (node and track ids continue); a repeated identical one changes nothing. A rejected
        CameraInfo is never stored (a later valid one is used as if it came first).

        Raises
        ------
        InputError
            A malformed CameraInfo (zero or non-finite ``K``, ``P``, ``R``, ``D``) or an
            inconsistent stereo pair; the previous calibration stays.
        """
        try:
            model = camera_info_to_model(msg)
            old = self._models.get(side)
            if old is not None and same_model(old, model) and self.calibration is not None:
                return None
            models = dict(self._models)
            models[side] = model
            if len(models) < 2:
                self._models = models
                return None
            cal = StereoCalibration.from_camera_models(models['left'], models['right'])
        except GaError:
            self.stats.camera_info_rejected += 1
            raise
        self._models = models
        return self._use(cal)

    def set_camera_models(self, left: CameraModel, right: CameraModel) -> StereoCalibration:
        """Use a calibration read from files (a bag without ``CameraInfo``, e.g. EuRoC's
        ``sensor.yaml``, :func:`ga_ros.vo.calibration.read_stereo_calibration`).

        Raises
        ------
        InputError
            An inconsistent stereo pair.
        """
        cal = StereoCalibration.from_camera_models(left, right)
        self._models = {'left': left, 'right': right}
        return self._use(cal)

    def _use(self, cal: StereoCalibration) -> StereoCalibration:
        self.calibration = cal
        if self.odometry is None:
            self.odometry = StereoOdometry(cal, self.config.vo)
        else:
            self.odometry = self.odometry.recalibrated(cal)
        self.matcher = CrossTrackMatcher(cal.K, cal.width, cal.height, self.config.cross)
        return cal

    def forget_keyframes(self) -> None:
        """Forget the keyframe records the cross-track matcher holds (a fresh, empty matcher;
        the calibration and the VO stay): their node ids no longer name the nodes of the state
        (``~/load_state`` replaced it)."""
        if self.calibration is not None:
            cal = self.calibration
            self.matcher = CrossTrackMatcher(cal.K, cal.width, cal.height, self.config.cross)
        self._stamp_to_node.clear()

    # ------------------------------------------------------------------ images
    def add_image(self, side: str, msg: Any) -> list[FrameOutput]:
        """Add one image message of ``side`` (``'left'``/``'right'``); process the pair it
        completes, if any (a list of at most one output; none while the pair waits for the
        calibration: :meth:`release_held` gives it once that has come)."""
        pair = self.pair_image(side, msg)
        if pair is None or self.hold_until_calibrated(pair):
            return []
        return [self.process_pair(pair)]

    def hold_until_calibrated(self, pair: ImagePair) -> bool:
        """Keep a pair completed before the calibration; True when kept (the caller gets it
        back from :meth:`release_held`), False when the calibration is there (process it).

        At most ``max_pending`` pairs wait; an older one is then counted under
        :data:`NO_CAMERA_INFO` and forgotten.
        """
        if self.odometry is not None:
            return False
        self._held.append(pair)
        while len(self._held) > self.config.max_pending:
            self._held.pop(0)
            self._reason(NO_CAMERA_INFO)
        return True

    @property
    def n_held(self) -> int:
        """Pairs waiting for the calibration (:meth:`hold_until_calibrated`)."""
        return len(self._held)

    def release_held(self, final: bool = False) -> list[ImagePair]:
        """The pairs kept by :meth:`hold_until_calibrated`, oldest first, once the calibration
        is there (else none); ``final``: all of them whatever the calibration (the end of the
        input: :meth:`process_pair` then counts each under :data:`NO_CAMERA_INFO`)."""
        if self.odometry is None and not final:
            return []
        held, self._held = sorted(self._held, key=lambda p: p.stamp_ns), []
        return held

    def pair_image(self, side: str, msg: Any) -> ImagePair | None:
        """Pair one image message of ``side`` with a waiting one of the other side (cheap: no
        decoding). Returns the completed pair (counted in ``stats.pairs``), else None."""
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
            return None
        omsg = self._pending[other].pop(match)
        for d in self._pending.values():  # older unpaired images will never pair
            for s in [s for s in d if s < min(stamp, match)]:
                d.pop(s)
                self.stats.unpaired += 1
        self.stats.pairs += 1
        if side == 'left':
            return ImagePair(msg, omsg, stamp)
        return ImagePair(omsg, msg, match)

    def count_dropped(self, pair: ImagePair, reason: str = DROPPED) -> FrameOutput:
        """Count a pair that the caller drops unprocessed (:data:`DROPPED`,
        :data:`NO_EXTRINSIC`)."""
        self._reason(reason)
        error = ('stereo: pair dropped (queue full)' if reason == DROPPED
                 else f'stereo: pair refused: {reason}')
        return FrameOutput(pair.stamp_ns, error=error, reason=reason)

    def _reason(self, key: str) -> None:
        self.stats.reasons[key] = self.stats.reasons.get(key, 0) + 1

    def process_pair(self, pair: ImagePair) -> FrameOutput:
        """Decode a pair and run the VO on it; the output names why it gave no measurement."""
        stamp_ns = pair.stamp_ns
        if self.odometry is None:
            self._reason(NO_CAMERA_INFO)
            return FrameOutput(stamp_ns, error='stereo: no CameraInfo for both cameras yet',
                               reason=NO_CAMERA_INFO)
        try:
            left = image_to_grey(pair.left)
            right = image_to_grey(pair.right)
            res = self.odometry.process(StereoFrame(left, right, int(stamp_ns)))
        except GaError as exc:
            self._reason(BAD_PAIR)
            return FrameOutput(stamp_ns, error=f'stereo: {exc}', reason=BAD_PAIR)
        res.measurement = self._to_base(res.measurement)
        reason = ''
        if res.status == 'lost':
            self.stats.lost += 1
            reason = LOST
            key = re.sub(r'[0-9][0-9.]*', '#', res.reason or '?')
            self.stats.lost_reasons[key] = self.stats.lost_reasons.get(key, 0) + 1
        elif res.status == 'rejected':
            reason = TEXTURELESS if res.reason.startswith('textureless') else TOO_FEW_POINTS
        elif res.measurement is None:
            reason = FIRST_KEYFRAME if res.status == 'initialised' else NOT_KEYFRAME
        if reason:
            self._reason(reason)
        else:
            self.stats.measurements += 1
        stamps: dict[int, int] = {}
        if res.keyframe is not None:
            self.stats.keyframes += 1
            stamps[int(res.keyframe.node_id)] = int(res.keyframe.stamp_ns)
            self._stamp_to_node[int(res.keyframe.stamp_ns)] = int(res.keyframe.node_id)
            while len(self._stamp_to_node) > MAX_STAMPS:  # bounded (oldest first)
                self._stamp_to_node.pop(next(iter(self._stamp_to_node)))
        return FrameOutput(stamp_ns, res, None, stamps, left, right, reason)

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
        for a in attempts:
            a.measurement = self._to_base(a.measurement)
        self.stats.cross_attempts += len(attempts)
        self.stats.cross_accepted += sum(a.accepted and a.measurement is not None
                                         for a in attempts)
        return attempts

    def keyframe_pair(self, frame: FrameOutput) -> tuple[np.ndarray, np.ndarray] | None:
        """The rectified (left, right) images of the frame's new keyframe (intrinsics
        ``calibration.K``); None when the frame made no keyframe."""
        res = frame.result
        if (res is None or res.keyframe is None or self.calibration is None
                or frame.left is None or frame.right is None):
            return None
        return self.calibration.rectify(frame.left, frame.right)

    def keyframe_cloud(self, frame: FrameOutput,
                       pair: tuple[np.ndarray, np.ndarray] | None = None) -> StereoCloud | None:
        """Dense stereo points of the frame's new keyframe, in the left camera's optical frame
        (m; :class:`ga_ros.vo.dense.DenseStereo` on the rectified pair, settings
        ``config.cloud``); None when the frame made no keyframe. ``pair``: the rectified pair
        when already computed (:meth:`keyframe_pair`). Reads the frame's images only: the VO's
        state and outputs are unchanged.

        Raises
        ------
        InputError
            The frame's images do not match the calibration.
        """
        pair = pair if pair is not None else self.keyframe_pair(frame)
        if pair is None:
            return None
        if self._dense is None:
            self._dense = DenseStereo(self.config.cloud)
        return self._dense.cloud(pair[0], pair[1], self.calibration)

    # ------------------------------------------------------------------ feedback, control
    def set_corrected(self, node_ids: IntArray, T_world_node: FloatArray) -> None:
        """Corrected poses of keyframes (node ids) for the matcher's overlap prediction."""
        if self.matcher is not None and self.config.feedback and len(node_ids):
            T = np.asarray(T_world_node, float)
            if self.extrinsic is not None:  # base poses in the map -> the matcher's camera poses
                T = self.extrinsic.camera_pose(T)
            self.matcher.set_corrected_poses(np.asarray(node_ids), T)

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
        """Start a new track at the next keyframe (``track.mode: external``)."""
        if self.odometry is not None:
            self.odometry.request_track_boundary()

