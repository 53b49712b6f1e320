"""What a bag holds: its topics and summary, and one message read from it."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any


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


def storage_of(path: Path) -> str:
    """``'mcap'`` or ``'sqlite3'``: the storage of a bag file or rosbag2 directory."""
    if path.is_dir():
        files = sorted(path.glob('*.mcap')) + sorted(path.glob('*.db3'))
        return 'mcap' if files and files[0].suffix == '.mcap' else 'sqlite3'
    return 'mcap' if path.suffix == '.mcap' else 'sqlite3'


@dataclass(frozen=True)
class BagMessage:
    """One message read from a bag: topic, type, log time (ns), rosbags object, raw CDR bytes
    (None for a ROS 1 bag)."""

    topic: str
    msgtype: str
    log_ns: int
    msg: Any
    data: bytes | None = field(repr=False)
