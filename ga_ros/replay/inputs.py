"""Replay source for standard inputs: odometry / pose topics (+ constraints, track boundaries).

A loop over the bag's messages in log order calling the same
:class:`ga_ros.pipeline.inputs.InputFrontEnd` as the live alignment node; each measurement it
makes becomes one :class:`~ga_ros.replay.source.SourceItem`. A stereo camera beside the
odometry (:class:`CameraTopics`) adds cross-track connections on the odometry's keyframes, fed
back with the corrected path of every update (:meth:`InputSource.on_corrected`).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import FormatError
from ga_ros.inputs.absolute import ABSOLUTE_TYPES
from ga_ros.inputs.messages import INPUT_TYPES, ODOMETRY
from ga_ros.io.bag import BagInfo, BagReader
from ga_ros.io.bag_messages import CAMERA_INFO, IMAGE_TYPES, TF_TOPICS
from ga_ros.io.topic_plan import TopicPlan, plan_ground_truth
from ga_ros.pipeline.absolute import AbsoluteFrontEnd, AbsoluteSpec
from ga_ros.pipeline.inputs import InputFrontEnd, InputSpec
from ga_ros.pipeline.keyframe_camera import KeyframeCamera, KeyframeCameraConfig
from ga_ros.replay.source import SourceItem

#: Type of the track-boundary topic.
EMPTY = 'std_msgs/msg/Empty'


@dataclass(frozen=True)
class CameraTopics:
    """A stereo camera beside the odometry (:mod:`ga_ros.pipeline.keyframe_camera`).

    Attributes
    ----------
    left_image, right_image : ``sensor_msgs/Image`` or ``CompressedImage`` topics.
    left_info, right_info : ``CameraInfo`` topics ('' with ``calibration`` files).
    calibration : calibration files for a bag without ``CameraInfo``
        (:func:`ga_ros.vo.calibration.read_stereo_calibration`).
    config : extrinsic, image-to-keyframe tolerance, feature and matcher settings.
    """

    left_image: str
    right_image: str
    left_info: str = ''
    right_info: str = ''
    calibration: tuple[str, ...] = ()
    config: KeyframeCameraConfig = field(default_factory=KeyframeCameraConfig)


@dataclass(frozen=True)
class InputTopics:
    """The standard-input topics of a replay.

    Attributes
    ----------
    inputs : odometry / pose inputs (their ``msgtype`` is taken from the bag).
    constraints : external constraints topic (``nav_msgs/Odometry``; '' = none).
    track_boundary : ``std_msgs/Empty`` topic that starts a new track ('' = none).
    warn_throttle_s : smallest interval between two default-covariance warnings (s).
    camera : a stereo camera beside the odometry (None: none).
    absolutes : absolute inputs (fixes: GNSS, AMCL, ...; :mod:`ga_ros.pipeline.absolute`; their
        ``msgtype`` is taken from the bag).
    """

    inputs: tuple[InputSpec, ...] = ()
    constraints: str = ''
    track_boundary: str = ''
    warn_throttle_s: float = 10.0
    camera: CameraTopics | None = None
    absolutes: tuple[AbsoluteSpec, ...] = ()

    @property
    def topics(self) -> list[str]:
        """Every topic these inputs read (not the ground truth)."""
        out = [s.topic for s in self.inputs] + [self.constraints, self.track_boundary]
        if self.camera is not None:
            c = self.camera
            out += [c.left_image, c.right_image, c.left_info, c.right_info]
        out += [a.topic for a in self.absolutes]
        return [t for t in out if t]


def plan_inputs(info: BagInfo, config: InputTopics, ground_truth: str) -> tuple[
        TopicPlan, tuple[InputSpec, ...]]:
    """Check the input topics against the bag; the plan and the inputs with the bag's types.

    Raises
    ------
    FormatError
        A missing topic or one of the wrong type (the message lists the bag's topics).
    """
    name = str(info.path)
    listing = ', '.join(f'{t.name} [{t.msgtype}]' for t in info.topics) or 'no topics'

    def check(topic: str, types: tuple[str, ...], what: str) -> str:
        t = info.topic(topic)
        if t is None:
            raise FormatError(f'missing topic {topic} ({what}); the bag has: {listing}', name)
        if t.msgtype not in types:
            raise FormatError(f'topic {topic} ({what}) has type {t.msgtype}, expected '
                              + ' or '.join(types), name)
        return t.msgtype

    specs = tuple(replace(s, msgtype=check(s.topic, INPUT_TYPES, f'input {s.name}'))
                  for s in config.inputs)
    for a in config.absolutes:
        check(a.topic, ABSOLUTE_TYPES, f'absolute input {a.name}')
    notes = [f'source: {s.name} {s.topic} ({s.msgtype}), keyframes every '
             f'{s.config.keyframe_travel_m:g} m / {s.config.keyframe_rotation_deg:g} deg'
             for s in specs]
    notes += [f'absolute: {a.name} {a.topic} ({info.topic(a.topic).msgtype})'
              for a in config.absolutes]
    if config.constraints:
        check(config.constraints, (ODOMETRY,), 'external constraints')
        notes.append(f'external constraints: {config.constraints}')
    if config.track_boundary:
        check(config.track_boundary, (EMPTY,), 'track boundaries')
        notes.append(f'track boundaries: {config.track_boundary}')
    cam = config.camera
    if cam is not None:
        check(cam.left_image, IMAGE_TYPES, 'left image')
        check(cam.right_image, IMAGE_TYPES, 'right image')
        for t in (cam.left_info, cam.right_info):
            if t:
                check(t, (CAMERA_INFO,), 'camera info')
        if not (cam.left_info and cam.right_info) and not cam.calibration:
            raise FormatError('a camera beside the odometry needs --left-info and --right-info '
                              'or --calibration files', name)
        notes.append(f'camera beside the odometry: {cam.left_image}, {cam.right_image}, '
                     f'images within {cam.config.max_image_offset_s:g} s of a keyframe')
    gt, note = plan_ground_truth(info, ground_truth)
    if gt:
        notes.append(note)
    return TopicPlan('inputs', ground_truth=gt, notes=tuple(notes)), specs


class InputSource:
    """Iterable of :class:`SourceItem` from the standard inputs of a bag (module doc).

    ``counter[0]`` counts the messages read; :attr:`warnings` keeps the throttled warnings.
    """

    def __init__(self, bag: BagReader, specs: tuple[InputSpec, ...], config: InputTopics,
                 counter: list[int]) -> None:
        self.bag = bag
        self.config = config
        camera = None
        if config.camera is not None:
            camera = KeyframeCamera(config.camera.config)
            if config.camera.calibration:
                from ga_ros.vo.calibration import read_stereo_calibration

                models = read_stereo_calibration(list(config.camera.calibration))
                camera.set_camera_models(models.left, models.right)
        self.front = InputFrontEnd(specs, config.warn_throttle_s, camera=camera)
        assert self.bag.info is not None
        self.absolute = AbsoluteFrontEnd(
            [replace(a, msgtype=self.bag.info.topic(a.topic).msgtype) for a in config.absolutes],
            config.warn_throttle_s)
        self.counter = counter
        self.warnings: list[str] = []
        #: called with each ``/tf`` and ``/tf_static`` message of the bag (topic, type, CDR,
        #: message, log time), e.g. to copy them into the output bag; None: not read.
        self.passthrough: Callable[[str, str, bytes | None, Any, int], None] | None = None

    @property
    def source_names(self) -> tuple[str, ...]:
        """The sources of this replay's measurements: the odometry inputs' names, the
        camera's (when one is beside them), and ``cross`` for the external constraints."""
        out = tuple(self.front.specs)
        if self.front.camera is not None:
            out += (self.front.camera.source,)
        return out + (('cross',) if self.config.constraints else ())

    @property
    def stats(self) -> dict[str, object]:
        """Per-input counters and the warnings (in the replay summary)."""
        out = self.front.stats()
        if self.absolute.specs:
            out['absolute'] = {**self.absolute.stats(), 'datums': self.absolute.datums()}
        final = [self.front.default_covariance_message(n) for n in self.front.specs]
        out['warnings'] = {'count': len(self.warnings), 'first': ''.join(self.warnings[:1]),
                           'final': [m for m in final if m]}
        return out

    def earth_datum(self) -> tuple[float, float, float] | None:
        """The NavSatFix inputs' ENU origin, once known
        (:meth:`~ga_ros.pipeline.absolute.AbsoluteFrontEnd.earth_datum`)."""
        return self.absolute.earth_datum()

    def map_to_odom(self, node_ids: IntArray, T_map_node: FloatArray) -> FloatArray | None:
        """REP 105 ``T_map_odom`` (:meth:`InputFrontEnd.map_to_odom`)."""
        return self.front.map_to_odom(node_ids, T_map_node)

    def on_corrected(self, node_ids: IntArray, T_map_node: FloatArray) -> None:
        """The corrected path of an update, for the camera's overlap prediction."""
        self.front.set_corrected(node_ids, T_map_node)

    def __iter__(self) -> Iterator[SourceItem]:
        topics = self.config.topics
        cam = self.config.camera
        images = {cam.left_image: 'left', cam.right_image: 'right'} if cam else {}
        infos = {cam.left_info: 'left', cam.right_info: 'right'} if cam else {}
        infos.pop('', None)
        assert self.bag.info is not None
        tf = [t for t in TF_TOPICS if self.bag.info.topic(t) and (
            self.passthrough is not None or (t == '/tf_static' and self.absolute.specs))]
        for bm in self.bag.messages(topics + tf):
            if bm.topic in tf:
                if self.passthrough is not None and bm.data is not None:  # not from ROS 1
                    self.passthrough(bm.topic, bm.msgtype, bm.data, bm.msg, bm.log_ns)
                if bm.topic == '/tf_static' and self.absolute.specs:  # the lever arms
                    self.absolute.static_transform(bm.msg)
                continue
            self.counter[0] += 1
            if bm.topic == self.config.track_boundary:
                self.front.track_boundary()
                continue
            absolute = self.absolute.by_topic(bm.topic)
            if absolute is not None:
                ab = self.absolute.message(absolute.name, bm.msg)
                if ab.warning:
                    self.warnings.append(ab.warning)
                if ab.error:
                    yield SourceItem(None, bm.log_ns, error=f'absolute: {ab.error}')
                yield from self._fixes(bm.log_ns)
                continue
            if bm.topic == self.config.constraints:
                step = self.front.constraint(bm.msg)
            elif bm.topic in images:
                step = self.front.image(images[bm.topic], bm.msg)
            elif bm.topic in infos:
                step = self.front.camera_info(infos[bm.topic], bm.msg)
            else:
                spec = self.front.by_topic(bm.topic)
                assert spec is not None
                step = self.front.sample(spec.name, bm.msg, bm.msgtype)
            if step.warning:
                self.warnings.append(step.warning)
            if step.error:
                yield SourceItem(None, bm.log_ns, error=f'input: {step.error}')
            elif not step.measurements:
                if step.node_stamps:
                    yield SourceItem(None, bm.log_ns, node_stamps=step.node_stamps)
            for k, m in enumerate(step.measurements):
                yield SourceItem(m, bm.log_ns, node_stamps=step.node_stamps if k == 0 else None)
            if self.absolute.specs and bm.topic != self.config.constraints:
                yield from self._fixes(bm.log_ns)

    def _fixes(self, log_ns: int) -> Iterator[SourceItem]:
        """The queued fixes the primary odometry now covers (a track boundary at the next
        keyframe if one asks for it)."""
        ab = self.absolute.resolve(self.front.inputs[self.front.primary])
        if ab.end_track:
            self.front.track_boundary()
        if ab.error:
            yield SourceItem(None, log_ns, error=f'absolute: {ab.error}')
        if ab.fixes:
            yield SourceItem(None, log_ns, fixes=ab.fixes)
