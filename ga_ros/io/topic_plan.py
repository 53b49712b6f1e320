"""Which topics of a bag the replay reads (:func:`plan_topics`), and what a ground-truth option
names in it (:func:`plan_ground_truth`).

Bag contents understood by the replay
-------------------------------------
* measurements: ``nav_msgs/msg/Odometry`` on ``/ga/measurements`` in the fixed measurement
  encoding (see :mod:`ga_ros.ros.conversions` and the README); decoded by
  :func:`ga_ros.io.bag_messages.odometry_to_measurement` with exactly the same rules as the
  rclpy decoder.
* stereo images: ``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage`` on a left and a
  right topic, each with a ``sensor_msgs/msg/CameraInfo`` topic.
* ground truth (optional): ``nav_msgs/msg/Path`` on ``/ga/ground_truth``; the last message on
  the topic holds the whole trajectory, one ``PoseStamped`` per node: ``pose`` = ``T_world_node``,
  ``header.stamp`` = the node's acquisition time and ``header.frame_id`` = the node frame
  ``'ga/<track>/<node>'`` (or any other frame id when the node ids are unknown; matching by stamp
  then). Other pose topics and TF pairs: :mod:`ga_ros.io.groundtruth`.
"""

from __future__ import annotations

from dataclasses import dataclass

from ga_ros import topics
from ga_ros.errors import FormatError, InputError
from ga_ros.io.bag.summary import BagInfo
from ga_ros.io.bag_messages import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    GROUND_TRUTH_TYPES,
    IMAGE_TYPES,
    ODOMETRY,
    TF_TOPICS,
)


@dataclass(frozen=True)
class TopicConfig:
    """Topic names the replay reads; empty strings are detected automatically.

    Attributes
    ----------
    measurements : the measurement encoding (``nav_msgs/Odometry``).
    left_image, right_image : stereo images (``Image`` or ``CompressedImage``); '' = detect.
    left_info, right_info : their ``CameraInfo`` topics; '' = detect.
    ground_truth : ground-truth ``nav_msgs/Path`` ('' = none).
    source : ``'auto'`` (measurements if that topic is in the bag, else images),
        ``'measurements'`` or ``'stereo'``.
    calibration : calibration files used when the bag has no ``CameraInfo`` (e.g. EuRoC's two
        ``sensor.yaml``; :func:`ga_ros.vo.calibration.read_stereo_calibration`); () = none.
    """

    measurements: str = topics.resolve(topics.MEASUREMENTS)
    left_image: str = ''
    right_image: str = ''
    left_info: str = ''
    right_info: str = ''
    ground_truth: str = topics.resolve(topics.GROUND_TRUTH)
    source: str = 'auto'
    calibration: tuple[str, ...] = ()


@dataclass(frozen=True)
class TopicPlan:
    """What the replay will read from a bag (the result of :func:`plan_topics`).

    ``source`` is ``'measurements'`` or ``'stereo'``; unused topics are ''. ``notes`` explains
    each choice (printed by ``ga-ros replay --info``).
    """

    source: str
    measurements: str = ''
    left_image: str = ''
    right_image: str = ''
    left_info: str = ''
    right_info: str = ''
    ground_truth: str = ''
    notes: tuple[str, ...] = ()
    calibration: tuple[str, ...] = ()

    @property
    def topics(self) -> tuple[str, ...]:
        """Every topic the replay reads."""
        names = (self.measurements, self.left_image, self.right_image, self.left_info,
                 self.right_info, self.ground_truth)
        return tuple(n for n in names if n)


#: Words that mark a left / right camera topic (ROS stereo drivers, EuRoC's cam0 / cam1).
SIDE_WORDS = {'left': ('left', 'cam0'), 'right': ('right', 'cam1')}


def _side_topics(info: BagInfo, types: tuple[str, ...], side: str) -> list[str]:
    return [t.name for t in info.topics if t.msgtype in types
            and any(w in t.name.lower() for w in SIDE_WORDS[side])]


def _info_for(info: BagInfo, image_topic: str) -> str:
    """The CameraInfo topic whose namespace is the longest prefix of ``image_topic`` ('')."""
    best, best_len, tie = '', -1, False
    for t in info.topics:
        if t.msgtype != CAMERA_INFO:
            continue
        ns = t.name.rsplit('/', 1)[0]
        if image_topic.startswith(ns + '/'):
            if len(ns) > best_len:
                best, best_len, tie = t.name, len(ns), False
            elif len(ns) == best_len:
                tie = True
    return '' if tie else best


def parse_tf_pair(spec: str) -> tuple[str, str] | None:
    """``'tf:PARENT:CHILD'`` -> ``(PARENT, CHILD)``; None for a topic name."""
    if not spec.startswith('tf:'):
        return None
    parts = spec[3:].split(':')
    if len(parts) != 2 or not all(p.strip('/') for p in parts):
        raise InputError(f'ground truth {spec!r}: a TF pair is tf:PARENT:CHILD, e.g. '
                         'tf:map:base_link')
    return parts[0].strip('/'), parts[1].strip('/')


def plan_ground_truth(info: BagInfo, spec: str) -> tuple[str, str]:
    """What a ground-truth option names in a bag: ``(spec, note)``; ``('', note)`` when the
    bag does not have it.

    Parameters
    ----------
    spec : a topic name or ``tf:PARENT:CHILD``.

    Raises
    ------
    FormatError
        A topic of a type that is not a pose (:data:`GROUND_TRUTH_TYPES`).
    InputError
        A malformed TF pair.
    """
    none = 'ground truth: none (no errors against ground truth will be reported)'
    if not spec:
        return '', none
    pair = parse_tf_pair(spec)
    if pair is not None:
        tf = [t for t in TF_TOPICS if info.topic(t) is not None]
        if not tf:
            return '', f'ground truth: none (no /tf in the bag for {spec})'
        return spec, f'ground truth: {pair[0]} -> {pair[1]} from {" + ".join(tf)}'
    t = info.topic(spec)
    if t is None:
        return '', none
    if t.msgtype not in GROUND_TRUTH_TYPES:
        raise FormatError(f'ground truth topic {spec} has type {t.msgtype}; expected one of '
                          + ', '.join(GROUND_TRUTH_TYPES) + ' (or tf:PARENT:CHILD for a TF pair)',
                          str(info.path))
    return spec, f'ground truth: {spec} ({t.msgtype})'


def plan_topics(info: BagInfo, config: TopicConfig = TopicConfig()) -> TopicPlan:
    """Decide which topics of a bag the replay uses.

    Raises
    ------
    InputError
        If a configured topic is missing or has the wrong type, the bag has neither measurements
        nor a stereo image pair, or the images have no CameraInfo.
    """
    src = config.source
    if src not in ('auto', 'measurements', 'stereo'):
        raise InputError(f"source must be 'auto', 'measurements' or 'stereo', got {src!r}")
    notes: list[str] = []
    name = str(info.path)

    def check(topic: str, types: tuple[str, ...], what: str) -> None:
        t = info.topic(topic)
        if t is None:
            raise FormatError(f'missing topic {topic} ({what}); the bag has: '
                              + (', '.join(x.name for x in info.topics) or 'no topics'), name)
        if t.msgtype not in types:
            raise FormatError(f'topic {topic} ({what}) has type {t.msgtype}, expected '
                              + ' or '.join(types), name)

    gt, note = plan_ground_truth(info, config.ground_truth)
    notes.append(note)

    has_meas = info.topic(config.measurements) is not None
    if src == 'measurements' or (src == 'auto' and has_meas):
        check(config.measurements, (ODOMETRY,), 'measurements')
        notes.append(f'source: measurements from {config.measurements} (nav_msgs/Odometry, '
                     'the ga_ros measurement encoding); no visual odometry')
        return TopicPlan('measurements', measurements=config.measurements, ground_truth=gt,
                         notes=tuple(notes))

    def image_topic(side: str) -> str:
        cands = _side_topics(info, IMAGE_TYPES, side)
        if len(cands) > 1:
            comp = [c for c in cands if info.topic(c).msgtype == COMPRESSED_IMAGE]
            cands = comp if len(comp) == 1 else cands
        for word in ('image_raw', 'image_rect'):  # CameraInfo describes the raw image
            if len(cands) > 1:
                some = [c for c in cands if c.endswith(word)]
                cands = some if len(some) == 1 else cands
        return cands[0] if len(cands) == 1 else ''

    left = config.left_image or image_topic('left')
    right = config.right_image or image_topic('right')
    if not left or not right:
        raise FormatError(
            f'no usable input: neither a measurements topic ({config.measurements}) nor a '
            'left/right image pair (set the topic names explicitly); the bag has: '
            + (', '.join(f'{t.name} [{t.msgtype}]' for t in info.topics) or 'no topics'), name)
    check(left, IMAGE_TYPES, 'left images')
    check(right, IMAGE_TYPES, 'right images')
    left_info = config.left_info or _info_for(info, left)
    right_info = config.right_info or _info_for(info, right)
    if config.calibration and not (config.left_info or config.right_info):
        notes.append(f'source: stereo images {left} + {right}, calibration from '
                     f'{" + ".join(config.calibration)}; visual odometry runs in-process')
        return TopicPlan('stereo', left_image=left, right_image=right, ground_truth=gt,
                         notes=tuple(notes), calibration=tuple(config.calibration))
    if not left_info or not right_info:
        missing = 'left' if not left_info else 'right'
        raise FormatError(f'no CameraInfo for the {missing} images '
                          f'({left if missing == "left" else right}; EuRoC-converted bags have '
                          'none): pass the calibration (--calibration cam0/sensor.yaml '
                          'cam1/sensor.yaml, or a YAML of the left and right CameraInfo '
                          'fields) or set the CameraInfo topics explicitly', name)
    check(left_info, (CAMERA_INFO,), 'left camera info')
    check(right_info, (CAMERA_INFO,), 'right camera info')
    for topic in (left_info, right_info):
        if info.topic(topic).count == 0:
            raise FormatError(f'CameraInfo topic {topic} has no messages', name)
    notes.append(f'source: stereo images {left} + {right} '
                 f'({info.topic(left).msgtype.rsplit("/", 1)[1]}), calibration {left_info} + '
                 f'{right_info}; visual odometry runs in-process')
    return TopicPlan('stereo', left_image=left, right_image=right, left_info=left_info,
                     right_info=right_info, ground_truth=gt, notes=tuple(notes))
