"""Opening and reading a bag: rosbag2 (mcap or sqlite3), an mcap file cut short, or ROS 1."""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from ga_ros.errors import FormatError
from ga_ros.io.bag.mcap_recovery import McapStream, single_mcap
from ga_ros.io.bag.rosbag1 import Ros1Bag
from ga_ros.io.bag.summary import BagInfo, BagMessage, BagTopic, storage_of
from ga_ros.io.bag_messages import typestore


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
        a ROS 1 ``.bag`` file (EuRoC ASL and KITTI folders:
        :func:`ga_ros.io.folder_bag.open_recording`).
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
            self._reader = Ros1Bag(self.path)
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
                                  '.mcap/.db3 file), nor a EuRoC ASL folder (mav0/cam0, '
                                  'mav0/cam1) or a KITTI odometry sequence (image_0, image_1, '
                                  'calib.txt)', str(self.path))
            self.path = files[0]
        try:
            reader = Reader(self.path)
            reader.open()
        except Exception as exc:  # rosbags raises many kinds on corrupt files
            mcap_file = single_mcap(self.path)
            if mcap_file is not None:
                # A recording cut short (no summary / end magic): read what is there.
                fallback = McapStream(mcap_file, f'{type(exc).__name__}: {exc}')
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
        self.info = BagInfo(self.path, storage_of(self.path), n, start, end, topics)

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
        from rosbags.rosbag2 import Reader

        if self._reader is None:
            raise FormatError('bag is not open', str(self.path))
        wanted = None if topics is None else set(topics)
        if not isinstance(self._reader, Reader):  # McapStream, Ros1Bag, a folder's reader
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


def bag_info(path: str | Path) -> BagInfo:
    """Summary (storage, counts, topics) of the bag at ``path``; FormatError if unreadable."""
    with BagReader(path) as bag:
        assert bag.info is not None
        return bag.info
