"""Reading rosbag2 bags (mcap or sqlite3) without ROS: topics, measurement encoding, ground truth.

Everything here uses :mod:`rosbags` (pure Python CDR and storage plugins) and never imports
``rclpy``. Messages come out as rosbags message objects (dataclasses with the ROS field names),
converted to core types once, at this edge.

Bag contents understood by the replay
-------------------------------------
* measurements: ``nav_msgs/msg/Odometry`` on ``/ga/measurements`` in the fixed measurement
  encoding (see :mod:`ga_ros.ros.conversions` and the README); decoded by
  :func:`odometry_to_measurement` with exactly the same rules as the rclpy decoder.
* stereo images: ``sensor_msgs/msg/Image`` or ``sensor_msgs/msg/CompressedImage`` on a left and a
  right topic, each with a ``sensor_msgs/msg/CameraInfo`` topic.
* ground truth (optional): ``nav_msgs/msg/Path`` on ``/ga/ground_truth``; the last message on
  the topic holds the whole trajectory, one ``PoseStamped`` per node: ``pose`` = ``T_world_node``,
  ``header.stamp`` = the node's acquisition time and ``header.frame_id`` = the node frame
  ``'ga/<track>/<node>'`` (or any other frame id when the node ids are unknown; matching by stamp
  then). Other pose topics and TF pairs: :mod:`ga_ros.io.groundtruth`.
"""

from __future__ import annotations

import functools
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros import topics
from ga_ros.arrays import FloatArray
from ga_ros.core import encoding
from ga_ros.core.frames import parse_node_frame
from ga_ros.core.measurement import Measurement
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.io.trajectory import Trajectory

#: Message types used by the replay (ROS 2 names).
ODOMETRY = 'nav_msgs/msg/Odometry'
PATH = 'nav_msgs/msg/Path'
IMAGE = 'sensor_msgs/msg/Image'
COMPRESSED_IMAGE = 'sensor_msgs/msg/CompressedImage'
CAMERA_INFO = 'sensor_msgs/msg/CameraInfo'
IMAGE_TYPES = (IMAGE, COMPRESSED_IMAGE)
POSE_STAMPED = 'geometry_msgs/msg/PoseStamped'
POSE_WITH_COVARIANCE = 'geometry_msgs/msg/PoseWithCovarianceStamped'
#: Message types a ground-truth topic may have (:mod:`ga_ros.io.groundtruth` reads them).
GROUND_TRUTH_TYPES = (POSE_STAMPED, POSE_WITH_COVARIANCE, ODOMETRY, PATH)
TF_TOPICS = ('/tf', '/tf_static')

#: ``twist.twist.linear.x`` values of the two measurement kinds.
KIND_FLAG = encoding.KIND_FLAG


@functools.lru_cache(maxsize=1)
def typestore() -> Any:
    """The rosbags type store of ROS 2 Jazzy (standard messages; built once, read-only)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


# --------------------------------------------------------------------------- stamps
def stamp_to_ns(stamp: Any) -> int:
    """``builtin_interfaces/Time`` (rosbags object) -> integer nanoseconds."""
    return encoding.stamp_to_ns(stamp)


def ns_to_stamp(stamp_ns: int) -> Any:
    """Integer nanoseconds (>= 0) -> ``builtin_interfaces/Time`` (rosbags object)."""
    t = encoding.split_stamp(stamp_ns)
    return typestore().types['builtin_interfaces/msg/Time'](sec=t.sec, nanosec=t.nanosec)


# --------------------------------------------------------------------------- bag inspection
@dataclass(frozen=True)
class BagTopic:
    """One topic of a bag: name, ROS 2 type (``pkg/msg/Type``) and message count."""

    name: str
    msgtype: str
    count: int


@dataclass(frozen=True)
class BagInfo:
    """Summary of a bag.

    Attributes
    ----------
    path : the bag (a rosbag2 directory, or a single ``.mcap`` / ``.db3`` file).
    storage : ``'mcap'`` or ``'sqlite3'``.
    n_messages : total message count.
    start_ns, end_ns : first and last message (log) times, ns.
    topics : the topics, sorted by name.
    """

    path: Path
    storage: str
    n_messages: int
    start_ns: int
    end_ns: int
    topics: tuple[BagTopic, ...]

    def topic(self, name: str) -> BagTopic | None:
        """The topic called ``name``, or None."""
        for t in self.topics:
            if t.name == name:
                return t
        return None

    @property
    def duration_s(self) -> float:
        """Time between the first and the last message (s)."""
        return max(0, self.end_ns - self.start_ns) * 1e-9


def _storage_of(path: Path) -> str:
    if path.is_dir():
        files = sorted(path.glob('*.mcap')) + sorted(path.glob('*.db3'))
        return 'mcap' if files and files[0].suffix == '.mcap' else 'sqlite3'
    return 'mcap' if path.suffix == '.mcap' else 'sqlite3'


class BagReader:
    """A read-only rosbag2 bag that reports every failure as :class:`FormatError` naming the bag.

    Use as a context manager::

        with BagReader(path) as bag:
            info = bag.info
            for msg in bag.messages(['/ga/measurements']):
                ...

    Parameters
    ----------
    path : a rosbag2 directory (with ``metadata.yaml``), a single ``.mcap`` / ``.db3`` file or
        a ROS 1 ``.bag`` file.
    """

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self._reader: Any = None
        self.info: BagInfo | None = None
        #: Set when the bag is an mcap file cut short: what is wrong with it (read what is there;
        #: :meth:`messages` raises FormatError after the last complete message).
        self.truncated: str | None = None

    def __enter__(self) -> BagReader:
        self.open()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def open(self) -> None:
        """Open the bag and read its summary; FormatError if it is missing or unreadable."""
        from rosbags.rosbag2 import Reader

        if not self.path.exists():
            raise FormatError('bag not found', str(self.path))
        if self.path.is_file() and self.path.suffix == '.bag':
            self._reader = _Ros1Bag(self.path)
            self.info = self._reader.info()
            return
        if self.path.is_file() and self.path.suffix not in ('.mcap', '.db3'):
            raise FormatError(f'unsupported bag storage {self.path.suffix!r}: give a rosbag2 '
                              'directory, a .mcap or .db3 file, or a ROS 1 .bag file',
                              str(self.path))
        if self.path.is_dir() and not (self.path / 'metadata.yaml').exists():
            files = sorted(self.path.glob('*.mcap')) + sorted(self.path.glob('*.db3'))
            if len(files) != 1:
                raise FormatError('not a rosbag2 bag (no metadata.yaml and not exactly one '
                                  '.mcap/.db3 file)', str(self.path))
            self.path = files[0]
        try:
            reader = Reader(self.path)
            reader.open()
        except Exception as exc:  # rosbags raises many kinds on corrupt files
            mcap_file = _single_mcap(self.path)
            if mcap_file is not None:
                # A recording cut short (no summary / end magic): read what is there.
                fallback = _McapStream(mcap_file, f'{type(exc).__name__}: {exc}')
                if fallback.n_messages > 0:
                    self._reader = fallback
                    self.path = mcap_file
                    self.truncated = fallback.problem
                    self.info = fallback.info()
                    return
            raise FormatError(f'cannot open bag: {type(exc).__name__}: {exc}',
                              str(self.path)) from exc
        self._reader = reader
        try:
            topics = tuple(sorted(
                (BagTopic(name, t.msgtype or '?', int(t.msgcount))
                 for name, t in reader.topics.items()), key=lambda t: t.name))
            n = int(reader.message_count)
            start = int(reader.start_time) if n else 0
            end = int(reader.end_time) if n else 0
        except Exception as exc:
            self.close()
            raise FormatError(f'cannot read bag summary: {exc}', str(self.path)) from exc
        self.info = BagInfo(self.path, _storage_of(self.path), n, start, end, topics)

    def close(self) -> None:
        """Close the bag (idempotent)."""
        if self._reader is not None:
            try:
                self._reader.close()
            except Exception:  # noqa: S110 - closing a corrupt bag must not mask the first error
                pass
            self._reader = None

    def messages(self, topics: Iterable[str] | None = None, raw: bool = False
                 ) -> Iterator[BagMessage]:
        """Messages of ``topics`` (all when None) in log-time order.

        Parameters
        ----------
        topics : topic names to read.
        raw : if True, do not deserialise (``BagMessage.msg`` is None; ``data`` holds the CDR).

        Raises
        ------
        FormatError
            If the bag is truncated or corrupt, or a message cannot be deserialised (unknown
            type, bad CDR); the message names the topic and the type. Messages before the
            failure have been yielded.
        """
        if self._reader is None:
            raise FormatError('bag is not open', str(self.path))
        wanted = None if topics is None else set(topics)
        if isinstance(self._reader, (_McapStream, _Ros1Bag)):
            yield from self._reader.messages(wanted, raw, str(self.path))
            return
        conns = [c for c in self._reader.connections if wanted is None or c.topic in wanted]
        store = typestore()
        if not raw:
            self._register_types(conns)
        it = self._reader.messages(connections=conns)
        count = 0
        while True:
            try:
                conn, log_ns, data = next(it)
            except StopIteration:
                return
            except Exception as exc:
                raise FormatError(f'bag is truncated or corrupt after {count} messages: '
                                  f'{type(exc).__name__}: {exc}', str(self.path)) from exc
            msg = None
            if not raw:
                try:
                    msg = store.deserialize_cdr(data, conn.msgtype)
                except Exception as exc:
                    raise FormatError(
                        f'cannot deserialise message {count} on {conn.topic} '
                        f'({conn.msgtype}): {type(exc).__name__}: {exc}', str(self.path)) from exc
            count += 1
            yield BagMessage(conn.topic, conn.msgtype, int(log_ns), msg, bytes(data))

    def _register_types(self, conns: list[Any]) -> None:
        """Make sure every connection's type is known to the (shared, standard) type store."""
        store = typestore()
        for c in conns:
            if c.msgtype not in store.types:
                raise FormatError(f'unknown message type {c.msgtype!r} on topic {c.topic} '
                                  '(only standard ROS 2 Jazzy types are supported)',
                                  str(self.path))


def _single_mcap(path: Path) -> Path | None:
    if path.is_file() and path.suffix == '.mcap':
        return path
    if path.is_dir():
        files = sorted(path.glob('*.mcap'))
        return files[0] if len(files) == 1 else None
    return None


class _McapStream:
    """Sequential reader of an mcap file without a valid summary (a recording cut short).

    Uses the ``mcap`` library's stream reader; everything up to the first damaged record is
    read, then :meth:`messages` raises :class:`FormatError` naming the problem.
    """

    def __init__(self, path: Path, open_error: str) -> None:
        self.path = path
        self.problem: str | None = None
        self.counts: dict[int, int] = {}
        self.channels: dict[int, tuple[str, str]] = {}
        self.start_ns = 2**63 - 1
        self.end_ns = 0
        self.n_messages = 0
        self.open_error = open_error
        try:
            for ch, log_ns, _ in self._scan(None):
                self.counts[ch] = self.counts.get(ch, 0) + 1
                self.start_ns = min(self.start_ns, log_ns)
                self.end_ns = max(self.end_ns, log_ns)
                self.n_messages += 1
        except FormatError as exc:
            self.problem = str(exc)
        if self.problem is None:
            self.problem = f'mcap file has no valid summary ({open_error})'

    def _scan(self, wanted: set[str] | None) -> Iterator[tuple[int, int, bytes]]:
        from mcap.records import Channel, Message, Schema
        from mcap.stream_reader import StreamReader

        schemas: dict[int, str] = {}
        n = 0

        def take(records: Iterable[Any]) -> Iterator[tuple[int, int, bytes]]:
            nonlocal n
            for rec in records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec.name
                elif isinstance(rec, Channel):
                    self.channels[rec.id] = (rec.topic, schemas.get(rec.schema_id, '?'))
                elif isinstance(rec, Message):
                    topic = self.channels.get(rec.channel_id, ('?', '?'))[0]
                    n += 1
                    if wanted is None or topic in wanted:
                        yield rec.channel_id, int(rec.log_time), bytes(rec.data)

        try:
            with open(self.path, 'rb') as f:
                yield from take(StreamReader(f, validate_crcs=True).records)
        except Exception as exc:  # EndOfFile, CRC errors, bad records, zstd errors, ...
            detail = f'{type(exc).__name__}: {exc}' if str(exc) else type(exc).__name__
            # the records of a chunk cut short, up to the cut (a chunk is read whole otherwise)
            yield from take(_partial_chunk_records(self.path))
            raise FormatError(f'bag is truncated or corrupt after {n} messages ({detail})',
                              str(self.path)) from exc

    def info(self) -> BagInfo:
        topics = tuple(sorted((BagTopic(t, ty, self.counts.get(cid, 0))
                               for cid, (t, ty) in self.channels.items()), key=lambda t: t.name))
        return BagInfo(self.path, 'mcap', self.n_messages, self.start_ns, self.end_ns, topics)

    def messages(self, wanted: set[str] | None, raw: bool, name: str) -> Iterator[BagMessage]:
        store = typestore()
        for cid, log_ns, data in self._scan(wanted):
            topic, msgtype = self.channels[cid]
            msg = None
            if not raw:
                if msgtype not in store.types:
                    raise FormatError(f'unknown message type {msgtype!r} on topic {topic}', name)
                try:
                    msg = store.deserialize_cdr(data, msgtype)
                except Exception as exc:
                    raise FormatError(f'cannot deserialise a message on {topic} ({msgtype}): '
                                      f'{type(exc).__name__}: {exc}', name) from exc
            yield BagMessage(topic, msgtype, log_ns, msg, data)
        raise FormatError(self.problem or 'bag is truncated', name)

    def close(self) -> None:
        pass


#: mcap opcode of a Chunk record.
_MCAP_CHUNK = 0x06


def _partial_chunk_records(path: Path) -> Iterator[Any]:
    """The complete records inside the chunk that an mcap file's end cuts (none if the file is
    not cut inside a chunk, or its compression cannot be read in part).

    Walks the top-level records (``opcode u8, length u64``) after the magic to the first one
    that runs past the end of the file; if it is a Chunk (``start u64, end u64,
    uncompressed_size u64, crc u32, compression string, records u64 + bytes``), its records
    are decompressed as far as they go (zstd and lz4 frames decode a prefix; uncompressed is
    the prefix) and parsed up to the last complete one.
    """
    import io
    import struct

    from mcap.stream_reader import StreamReader

    size = path.stat().st_size
    with open(path, 'rb') as f:
        pos = 8  # magic
        while True:
            f.seek(pos)
            head = f.read(9)
            if len(head) < 9:
                return
            opcode, length = struct.unpack('<BQ', head)
            if pos + 9 + length <= size:
                pos += 9 + length
                continue
            if opcode != _MCAP_CHUNK:
                return
            body = f.read()
            break
    fixed = struct.calcsize('<QQQI')
    if len(body) < fixed + 4:
        return
    (name_len,) = struct.unpack_from('<I', body, fixed)
    at = fixed + 4 + name_len + 8
    if len(body) < at:
        return
    compression = body[fixed + 4:fixed + 4 + name_len].decode('utf-8', 'replace')
    part = body[at:]
    try:
        if compression == 'zstd':
            import zstandard

            data = zstandard.ZstdDecompressor().decompressobj().decompress(part)
        elif compression == 'lz4':
            import lz4.frame

            data = lz4.frame.LZ4FrameDecompressor().decompress(part)
        elif compression == '':
            data = part
        else:
            return
    except Exception:  # noqa: BLE001 - a frame damaged at its start: nothing to recover
        return
    reader = StreamReader(io.BytesIO(data), skip_magic=True)
    try:
        yield from reader.records
    except Exception:  # noqa: S110 - the cut ends the chunk's records
        return


class _Ros1Bag:
    """A ROS 1 ``.bag`` file read with rosbags (``AnyReader``: the bag's own message
    definitions). Messages keep the ROS 1 field names (``header.seq`` besides the ROS 2 ones);
    ``BagMessage.data`` is None (no CDR: copies are re-encoded), and raw reading is refused."""

    def __init__(self, path: Path) -> None:
        from rosbags.highlevel import AnyReader

        self.path = path
        try:
            self.reader = AnyReader([path])
            self.reader.open()
        except Exception as exc:  # rosbags raises many kinds on corrupt files
            raise FormatError(f'cannot open ROS 1 bag: {type(exc).__name__}: {exc}',
                              str(path)) from exc

    def info(self) -> BagInfo:
        counts: dict[str, int] = {}
        types: dict[str, str] = {}
        for c in self.reader.connections:
            counts[c.topic] = counts.get(c.topic, 0) + int(c.msgcount)
            types[c.topic] = c.msgtype
        n = int(self.reader.message_count)
        topics = tuple(BagTopic(t, types[t], counts[t]) for t in sorted(types))
        return BagInfo(self.path, 'rosbag1', n, int(self.reader.start_time) if n else 0,
                       int(self.reader.end_time) if n else 0, topics)

    def messages(self, wanted: set[str] | None, raw: bool, name: str) -> Iterator[BagMessage]:
        if raw:
            raise FormatError('a ROS 1 bag cannot be played raw; convert it first with '
                              '`rosbags-convert --src BAG --dst DIR`', name)
        conns = [c for c in self.reader.connections if wanted is None or c.topic in wanted]
        count = 0
        try:
            for conn, log_ns, data in self.reader.messages(connections=conns):
                msg = self.reader.deserialize(data, conn.msgtype)
                count += 1
                yield BagMessage(conn.topic, conn.msgtype, int(log_ns), msg, None)
        except FormatError:
            raise
        except Exception as exc:
            raise FormatError(f'ROS 1 bag is truncated or corrupt after {count} messages: '
                              f'{type(exc).__name__}: {exc}', name) from exc

    def close(self) -> None:
        self.reader.close()


@dataclass(frozen=True)
class BagMessage:
    """One message read from a bag: topic, type, log time (ns), rosbags object, raw CDR bytes
    (None for a ROS 1 bag)."""

    topic: str
    msgtype: str
    log_ns: int
    msg: Any
    data: bytes | None = field(repr=False)


def bag_info(path: str | Path) -> BagInfo:
    """Summary (storage, counts, topics) of the bag at ``path``; FormatError if unreadable."""
    with BagReader(path) as bag:
        assert bag.info is not None
        return bag.info


# --------------------------------------------------------------------------- topic selection
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


# --------------------------------------------------------------------------- poses
def pose_msg_to_matrix(pose: Any) -> FloatArray:
    """``geometry_msgs/Pose`` (rosbags) -> 4x4; InputError on NaN or a non-unit quaternion
    (:func:`ga_ros.core.encoding.pose_to_matrix`)."""
    return encoding.pose_to_matrix(pose)


def matrix_to_pose_msg(T: FloatArray) -> Any:
    """4x4 pose -> ``geometry_msgs/Pose`` (rosbags object)."""
    p, q = se3.to_pos_quat(np.asarray(T, dtype=float))
    return _pose_msg(p.tolist(), q.tolist())


def _pose_msg(p: list[float], q: list[float]) -> Any:
    types = typestore().types
    return types['geometry_msgs/msg/Pose'](
        position=types['geometry_msgs/msg/Point'](x=p[0], y=p[1], z=p[2]),
        orientation=types['geometry_msgs/msg/Quaternion'](x=q[0], y=q[1], z=q[2], w=q[3]))


# --------------------------------------------------------------------------- measurements
def odometry_to_measurement(msg: Any) -> Measurement:
    """Decode a rosbags ``nav_msgs/Odometry`` in the measurement encoding, with exactly the
    rules of the alignment node (:func:`ga_ros.core.encoding.decode_measurement`)."""
    return encoding.decode_measurement(msg)


def measurement_to_odometry(m: Measurement) -> Any:
    """Encode a :class:`Measurement` as a rosbags ``nav_msgs/Odometry`` (the fixed encoding)."""
    from ga_ros.core.frames import node_frame

    if m.kind not in KIND_FLAG:
        raise InputError(f"measurement kind must be 'consecutive' or 'cross', got {m.kind!r}")
    types = typestore().types
    cov = np.asarray(m.cov, dtype=float)
    if cov.shape != (6, 6):
        raise InputError(f'covariance must be 6x6, got {cov.shape}')
    zero_cov = np.zeros(36)
    vec = types['geometry_msgs/msg/Vector3']
    return types[ODOMETRY](
        header=header(node_frame(m.src_track, m.src_id), m.stamp_ns),
        child_frame_id=node_frame(m.dst_track, m.dst_id),
        pose=types['geometry_msgs/msg/PoseWithCovariance'](
            pose=matrix_to_pose_msg(m.T_src_dst), covariance=cov.reshape(36).copy()),
        twist=types['geometry_msgs/msg/TwistWithCovariance'](
            twist=types['geometry_msgs/msg/Twist'](
                linear=vec(x=KIND_FLAG[m.kind], y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0)),
            covariance=zero_cov))


def header(frame_id: str, stamp_ns: int) -> Any:
    """``std_msgs/Header`` (rosbags object)."""
    return typestore().types['std_msgs/msg/Header'](stamp=ns_to_stamp(stamp_ns),
                                                    frame_id=str(frame_id))


# --------------------------------------------------------------------------- paths, ground truth
def path_msg_to_trajectory(msg: Any) -> Trajectory:
    """rosbags ``nav_msgs/Path`` -> :class:`Trajectory` (node ids from node frame ids, if any)."""
    n = len(msg.poses)
    stamps = np.empty(n, dtype=np.int64)
    nodes = np.full(n, -1, dtype=np.int64)
    tracks = np.full(n, -1, dtype=np.int64)
    T = np.empty((n, 4, 4))
    for k, ps in enumerate(msg.poses):
        stamps[k] = stamp_to_ns(ps.header.stamp)
        T[k] = pose_msg_to_matrix(ps.pose)
        try:
            tracks[k], nodes[k] = parse_node_frame(ps.header.frame_id)
        except InputError:
            pass
    return Trajectory(stamps, T, nodes, tracks, msg.header.frame_id or 'map')


def trajectory_to_path_msg(traj: Trajectory, frame_id: str | None = None,
                           stamp_ns: int | None = None, node_frames: bool = False) -> Any:
    """:class:`Trajectory` -> rosbags ``nav_msgs/Path``.

    Parameters
    ----------
    frame_id : the path's frame (default: ``traj.frame_id``).
    stamp_ns : the path header's stamp (default: the last pose's stamp).
    node_frames : if True, each pose's ``header.frame_id`` is its node frame
        ``'ga/<track>/<node>'`` (the ground-truth convention); else ``frame_id``.
    """
    from ga_ros.core.frames import node_frame

    types = typestore().types
    frame = frame_id or traj.frame_id
    n = len(traj)
    if stamp_ns is None:
        stamp_ns = int(traj.stamps_ns[-1]) if n else 0
    poses = []
    if n:
        p_all, q_all = se3.to_pos_quat(np.asarray(traj.T_world_node, float).reshape(-1, 4, 4))
        p_all, q_all = p_all.tolist(), q_all.tolist()
    PoseStamped = types['geometry_msgs/msg/PoseStamped']
    for k in range(n):
        f = node_frame(int(traj.track_ids[k]), int(traj.node_ids[k])) if node_frames else frame
        poses.append(PoseStamped(header=header(f, int(traj.stamps_ns[k])),
                                 pose=_pose_msg(p_all[k], q_all[k])))
    return types[PATH](header=header(frame, stamp_ns), poses=poses)
