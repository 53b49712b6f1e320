"""Stereo source of the replay: bag images -> stereo VO + cross-track matching -> measurements.

The same core objects as ``vo_node`` (:class:`ga_ros.vo.odometry.StereoOdometry` and
:class:`ga_ros.vo.crosstrack.CrossTrackMatcher`), fed in bag order: left and right images are
paired by equal header stamps, the calibration comes from the first ``CameraInfo`` of each side
(raw images are rectified when it says so), and the corrected path of every alignment update is
given back to the matcher, as ``vo_node`` gets the alignment node's corrected path.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import FormatError, GaError, InputError
from ga_ros.io.bag import CAMERA_INFO, COMPRESSED_IMAGE, IMAGE, BagReader, TopicPlan, stamp_to_ns
from ga_ros.replay.pipeline import SourceItem

#: Largest stamp difference (ns) between the two images of a pair.
PAIR_TOL_NS = 1_000_000
#: Unpaired images kept per side before the oldest is dropped.
MAX_PENDING = 50


@dataclass(frozen=True)
class StereoReplayConfig:
    """VO and cross-track settings of the replay (None = the modules' defaults).

    Attributes
    ----------
    vo : :class:`ga_ros.vo.odometry.VoConfig`.
    cross : :class:`ga_ros.vo.crosstrack.CrossTrackConfig`; ``cross_track=False`` disables it.
    cross_track : emit cross-track connections.
    feedback : give the corrected path back to the matcher after each alignment update.
    """

    vo: Any = None
    cross: Any = None
    cross_track: bool = True
    feedback: bool = True


def camera_model(msg: Any) -> Any:
    """rosbags ``sensor_msgs/CameraInfo`` -> :class:`ga_ros.vo.calibration.CameraModel`."""
    from ga_ros.vo.calibration import CameraModel

    try:
        return CameraModel(int(msg.width), int(msg.height),
                           np.asarray(msg.k, float).reshape(3, 3),
                           np.asarray(msg.d, float).ravel(),
                           np.asarray(msg.r, float).reshape(3, 3),
                           np.asarray(msg.p, float).reshape(3, 4),
                           str(msg.distortion_model or 'plumb_bob'))
    except ValueError as exc:
        raise InputError(f'malformed CameraInfo: {exc}') from exc


def decode_image(msg: Any, msgtype: str) -> np.ndarray:
    """rosbags ``Image`` / ``CompressedImage`` -> grey ``uint8`` (height, width) array.

    Raises
    ------
    InputError
        Undecodable data or an unsupported encoding.
    """
    import cv2

    if msgtype == COMPRESSED_IMAGE:
        img = cv2.imdecode(np.asarray(msg.data, dtype=np.uint8), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise InputError(f'cannot decode compressed image (format {msg.format!r})')
        return img
    if msgtype != IMAGE:
        raise InputError(f'not an image type: {msgtype}')
    enc = str(msg.encoding).lower()
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = np.asarray(msg.data, dtype=np.uint8)
    channels = {'mono8': 1, '8uc1': 1, 'bgr8': 3, 'rgb8': 3, 'bgra8': 4, 'rgba8': 4,
                'mono16': 2, '16uc1': 2}.get(enc)
    if channels is None:
        raise InputError(f'unsupported image encoding {msg.encoding!r}')
    if h <= 0 or w <= 0 or step < w * channels or data.size < h * step:
        raise InputError(f'image data ({data.size} bytes) does not match {w}x{h}, step {step}')
    rows = data[:h * step].reshape(h, step)[:, :w * channels]
    if enc in ('mono16', '16uc1'):
        dt = '>u2' if msg.is_bigendian else '<u2'
        return (rows.copy().view(dt).reshape(h, w) >> 8).astype(np.uint8)
    img = rows.reshape(h, w, channels) if channels > 1 else rows.reshape(h, w)
    if channels == 1:
        return np.ascontiguousarray(img)
    code = {'bgr8': cv2.COLOR_BGR2GRAY, 'rgb8': cv2.COLOR_RGB2GRAY, 'bgra8': cv2.COLOR_BGRA2GRAY,
            'rgba8': cv2.COLOR_RGBA2GRAY}[enc]
    return cv2.cvtColor(np.ascontiguousarray(img), code)


@dataclass
class StereoStats:
    """Counts of the stereo source (written to the replay summary)."""

    pairs: int = 0
    unpaired: int = 0
    keyframes: int = 0
    lost: int = 0
    cross_attempts: int = 0
    cross_accepted: int = 0
    reasons: dict[str, int] = field(default_factory=dict)


class StereoSource:
    """Iterates a bag's stereo pairs through VO and yields :class:`SourceItem` measurements.

    Parameters
    ----------
    bag : open bag; ``plan`` : its topic plan (``source == 'stereo'``).
    config : :class:`StereoReplayConfig` (None = defaults).
    counter : ``counter[0]`` is incremented per processed pair (progress).
    """

    def __init__(self, bag: BagReader, plan: TopicPlan, config: Any, counter: list[int]) -> None:
        self.bag = bag
        self.plan = plan
        if config is None or not isinstance(config, StereoReplayConfig):
            config = StereoReplayConfig(vo=config)
        self.config = config
        self.counter = counter
        self.stats = StereoStats()
        self.vo: Any = None
        self.matcher: Any = None
        self._info: dict[str, Any] = {}

    # -- feedback from the aligner (what vo_node gets from the alignment node's path topic)
    def on_corrected(self, node_ids: IntArray, T_world_node: FloatArray) -> None:
        if self.matcher is not None and self.config.feedback and len(node_ids):
            self.matcher.set_corrected_poses(np.asarray(node_ids), T_world_node)

    def _start(self) -> None:
        from ga_ros.vo.calibration import StereoCalibration
        from ga_ros.vo.crosstrack import CrossTrackConfig, CrossTrackMatcher
        from ga_ros.vo.odometry import StereoOdometry, VoConfig

        calib = StereoCalibration.from_camera_models(camera_model(self._info['left']),
                                                     camera_model(self._info['right']))
        self.vo = StereoOdometry(calib, self.config.vo or VoConfig())
        if self.config.cross_track:
            self.matcher = CrossTrackMatcher(calib.K, calib.width, calib.height,
                                             self.config.cross or CrossTrackConfig())

    def _reason(self, key: str) -> None:
        self.stats.reasons[key] = self.stats.reasons.get(key, 0) + 1

    def __iter__(self) -> Iterator[SourceItem]:
        from ga_ros.vo.odometry import StereoFrame

        p = self.plan
        sides = {p.left_image: 'left', p.right_image: 'right'}
        infos = {p.left_info: 'left', p.right_info: 'right'}
        pending: dict[str, dict[int, tuple[Any, str, int]]] = {'left': {}, 'right': {}}
        for bm in self.bag.messages(p.topics):
            if bm.topic in infos and bm.msgtype == CAMERA_INFO:
                self._info.setdefault(infos[bm.topic], bm.msg)
                continue
            if bm.topic not in sides:
                continue
            side = sides[bm.topic]
            other = 'right' if side == 'left' else 'left'
            stamp = stamp_to_ns(bm.msg.header.stamp)
            match = None
            for s in pending[other]:
                if abs(s - stamp) <= PAIR_TOL_NS:
                    match = s
                    break
            if match is None:
                pending[side][stamp] = (bm.msg, bm.msgtype, bm.log_ns)
                if len(pending[side]) > MAX_PENDING:
                    pending[side].pop(next(iter(pending[side])))
                    self.stats.unpaired += 1
                continue
            omsg, otype, _ = pending[other].pop(match)
            # drop older unpaired images of both sides (they will never pair)
            for d in pending.values():
                for s in [s for s in d if s < min(stamp, match)]:
                    d.pop(s)
                    self.stats.unpaired += 1
            pair = {side: (bm.msg, bm.msgtype), other: (omsg, otype)}
            self.counter[0] += 1
            self.stats.pairs += 1
            yield from self._process(pair, stamp if side == 'left' else match, bm.log_ns,
                                     StereoFrame)

    def _process(self, pair: dict[str, tuple[Any, str]], stamp: int, log_ns: int,
                 frame_cls: Any) -> Iterator[SourceItem]:
        if self.vo is None:
            if 'left' not in self._info or 'right' not in self._info:
                self._reason('no CameraInfo yet')
                yield SourceItem(None, log_ns, error='stereo: image pair before its CameraInfo')
                return
            try:
                self._start()
            except InputError as exc:
                raise FormatError(f'bad CameraInfo: {exc}', str(self.bag.path)) from exc
        try:
            left = decode_image(*pair['left'])
            right = decode_image(*pair['right'])
            res = self.vo.process(frame_cls(left, right, int(stamp)))
        except GaError as exc:
            self._reason('bad pair')
            yield SourceItem(None, log_ns, error=f'stereo: {exc}')
            return
        if res.status == 'lost':
            self.stats.lost += 1
            self._reason('lost: ' + re.sub(r'[0-9][0-9.]*', '#', res.reason or '?'))
        stamps = {}
        if res.keyframe is not None:
            self.stats.keyframes += 1
            stamps[int(res.keyframe.node_id)] = int(res.keyframe.stamp_ns)
        if res.measurement is not None:
            yield SourceItem(res.measurement, log_ns, node_stamps=stamps or None)
            stamps = {}
        elif stamps:
            yield SourceItem(None, log_ns, node_stamps=stamps)
        if res.keyframe is not None and self.matcher is not None:
            for a in self.matcher.add(res.keyframe):
                self.stats.cross_attempts += 1
                if a.accepted and a.measurement is not None:
                    self.stats.cross_accepted += 1
                    yield SourceItem(a.measurement, log_ns, node_stamps=stamps or None)


def stereo_measurements(bag: BagReader, plan: TopicPlan, config: Any,
                        counter: list[int]) -> StereoSource:
    """The stereo source of :func:`ga_ros.replay.pipeline.replay` (see :class:`StereoSource`)."""
    return StereoSource(bag, plan, config, counter)
