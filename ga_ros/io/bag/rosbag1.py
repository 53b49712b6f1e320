"""Reading a ROS 1 ``.bag`` file with rosbags."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

from ga_ros.errors import FormatError
from ga_ros.io.bag.summary import BagInfo, BagMessage, BagTopic


class Ros1Bag:
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
