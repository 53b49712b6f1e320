"""Live replay of a rosbag2 bag into a running ROS 2 graph (``ga-ros play``), without ``ros2``.

Publishes every message of a bag (mcap or sqlite3, read with :mod:`rosbags`) as the raw CDR it
was recorded as (no deserialisation: ``Publisher.publish(bytes)``), plus ``/clock``
(``rosgraph_msgs/Clock``) carrying the bag time, so nodes with ``use_sim_time:=true`` run on bag
time. ``rate`` scales the bag's timing (2.0 = twice as fast); ``rate = 0`` publishes as fast as
the subscribers keep up: the publishers are reliable with a deep queue and every ``ack_every``
messages the player waits until all subscribers have acknowledged what was sent
(``Publisher.wait_for_all_acked``). The player exits when the bag is done and every
subscriber has acknowledged the last messages.

Nothing is lost to a restarted node: the measurement topics (``nav_msgs/msg/Odometry``) are
transient local with a history of the whole topic, kept until the player exits; after the bag,
the player waits (``delivery_timeout_s``) until every measurement topic has a subscriber and
every subscriber has acknowledged everything (a node killed and restarted meanwhile gets the
whole history again), and says what was not delivered otherwise (``ga-ros play`` then exits
with :data:`EXIT_NOT_DELIVERED`). The history costs the serialized messages in the player's
memory (about 1.3 kB per measurement, README "Reliability").

Runnable as ``python -m ga_ros.ros.play BAG [--rate R]`` and as ``ga-ros play``.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any

import rclpy
from diagnostic_msgs.msg import KeyValue
from nav_msgs.msg import Odometry
from rclpy.duration import Duration
from rclpy.executors import ExternalShutdownException
from rclpy.node import Node, NodeNameNonExistentError
from rclpy.qos import DurabilityPolicy, HistoryPolicy, QoSProfile, ReliabilityPolicy
from rosgraph_msgs.msg import Clock

from ga_ros import topics
from ga_ros.errors import GaError, InputError
from ga_ros.io.bag import BagReader, BagTopic
from ga_ros.ros.message_types import message_class
from ga_ros.ros.play_args import add_arguments
from ga_ros.ros.qos import latched_qos
from ga_ros.topics import TRACK_END_FRAME

#: Longest history kept per measurement topic, messages.
MAX_HISTORY = 1_000_000
#: Exit code of ``ga-ros play`` when some message was not delivered to every subscriber.
EXIT_NOT_DELIVERED = 3
#: A node at work (it publishes its input-done topic) extends the wait for its confirmation up
#: to this many times the delivery timeout.
AT_WORK_PATIENCE = 10


@dataclass(frozen=True)
class PlayConfig:
    """Settings of a live replay.

    Attributes
    ----------
    rate : playback speed factor (1.0 = real time); 0 = as fast as subscribers keep up.
    topics : topics to publish (empty = all).
    clock : publish ``/clock`` with the bag time.
    clock_period_s : bag-time interval between ``/clock`` messages (s); one is also sent
        before every message whose time moved past it.
    delay_s : wall time to wait after creating the publishers, s (on top of the wait for
        subscribers).
    wait_for_subscribers_s : wait up to this long (s) until a topic of the bag has a matched
        subscriber, before the first message and, if none is left, before exiting (a warning
        if none came; 0 = do not wait).
    end_signal : after the bag, send the end-of-input message (``child_frame_id``
        :data:`ga_ros.topics.TRACK_END_FRAME`) on every measurements topic
        (``.../ga/measurements``, ``nav_msgs/msg/Odometry``), so the last track is processed.
    ack_every : with ``rate = 0``, wait for all subscribers' acknowledgements every this many
        messages.
    ack_timeout_s : longest wait for those acknowledgements (s).
    depth : publisher queue depth.
    delivery_timeout_s : after the bag, wait up to this long (s) until every measurement
        topic has a subscriber and every subscriber has acknowledged everything (a node
        restarted meanwhile gets the whole history); :attr:`PlayStats.undelivered` says what
        was not delivered after it.
    sensor_reliability : QoS reliability of the image and camera-info publishers:
        ``'reliable'`` or ``'best_effort'`` (as most camera drivers publish).
    """

    rate: float = 1.0
    topics: tuple[str, ...] = ()
    clock: bool = True
    clock_period_s: float = 0.01
    delay_s: float = 0.0
    wait_for_subscribers_s: float = 10.0
    end_signal: bool = True
    ack_every: int = 20
    ack_timeout_s: float = 5.0
    depth: int = 1000
    delivery_timeout_s: float = 60.0
    sensor_reliability: str = 'reliable'


@dataclass
class PlayStats:
    """What a replay published: per-topic counts of the bag's messages, ``/clock`` messages,
    end-of-input messages, wall time (s), and what was not delivered (one text per topic not
    acknowledged by every subscriber, or without any subscriber; empty: everything arrived)."""

    counts: dict[str, int] = field(default_factory=dict)
    clock_messages: int = 0
    end_signals: int = 0
    seconds: float = 0.0
    bag_seconds: float = 0.0
    undelivered: list[str] = field(default_factory=list)


def _unnamed(node_name: str) -> bool:
    """Whether the graph gives an endpoint without its node's name (rclpy reports
    ``_NODE_NAME_UNKNOWN_`` until or after DDS knows the participant's name)."""
    return not node_name or node_name.startswith('_NODE_NAME_UNKNOWN')


class BagPlayer:
    """Publishes a bag's messages through a node (see the module docstring).

    Parameters
    ----------
    node : the rclpy node that owns the publishers.
    bag_path : rosbag2 directory or ``.mcap`` / ``.db3`` file.
    config : see :class:`PlayConfig`.
    """

    def __init__(self, node: Node, bag_path: str | Path, config: PlayConfig = PlayConfig()
                 ) -> None:
        if config.rate < 0 or config.rate != config.rate:
            raise InputError(f'rate must be >= 0, got {config.rate}')
        self.node = node
        self.config = config
        self.bag = BagReader(bag_path)
        self.bag.open()
        assert self.bag.info is not None
        info = self.bag.info
        names = [t.name for t in info.topics]
        missing = [t for t in config.topics if t not in names]
        if missing:
            self.bag.close()
            raise InputError(f'topics not in the bag {info.path}: {", ".join(missing)}')
        wanted = [t for t in info.topics if not config.topics or t.name in config.topics]
        if not wanted:
            self.bag.close()
            raise InputError(f'nothing to play: the bag {info.path} has no messages')
        try:
            classes = {t.name: message_class(t.msgtype) for t in wanted}
        except InputError as exc:
            self.bag.close()
            raise InputError(f'{exc} (topic filter --topics can skip it)') from None
        self.publishers = {t.name: node.create_publisher(classes[t.name], t.name,
                                                         self._qos(t))
                           for t in wanted}
        self.end_topics = tuple(t.name for t in wanted if config.end_signal
                                and t.msgtype == 'nav_msgs/msg/Odometry'
                                and t.name.endswith('/' + topics.MEASUREMENTS))
        self.clock_pub = node.create_publisher(Clock, '/clock', 10) if config.clock else None
        self.topics = tuple(classes)
        #: Input-done confirmations, per end topic: node name -> measurements it received
        #: (the largest it reported; see :meth:`_wait_delivered`).
        self.done: dict[str, dict[str, int]] = {t: {} for t in self.end_topics}
        #: Measurement messages published per end topic.
        self.sent = {t: 0 for t in self.end_topics}
        for t in self.end_topics:   # transient local: a confirmation sent before this
            node.create_subscription(KeyValue, topics.input_done_topic(t),   # matched counts
                                     partial(self._on_done, t), latched_qos(10))
        #: Topics whose whole history is kept (the measurements: a restart gets them again).
        self.kept = tuple(t.name for t in wanted if self._keeps_all(t))
        for t in wanted:
            if self._keeps_all(t) and t.count + 1 > MAX_HISTORY:
                node.get_logger().warning(
                    f'{t.name}: {t.count} messages, the history keeps the last {MAX_HISTORY}: '
                    'a node restarted late may miss the first ones')

    @staticmethod
    def _keeps_all(topic: BagTopic) -> bool:
        return topic.msgtype == 'nav_msgs/msg/Odometry'

    def _qos(self, topic: BagTopic) -> QoSProfile:
        """Reliable; measurement topics (``nav_msgs/msg/Odometry``) transient local with a
        history of the whole topic (a subscriber restarted after a crash gets everything
        again), ``/tf_static`` transient local (latched, as tf2 listeners expect), others
        volatile with ``depth``; images and camera info with ``sensor_reliability``."""
        keep_all = self._keeps_all(topic)
        latched = keep_all or topic.name.rsplit('/', 1)[-1] == 'tf_static'
        depth = max(self.config.depth, min(topic.count + 1, MAX_HISTORY)) if keep_all \
            else self.config.depth
        sensor = topic.msgtype in ('sensor_msgs/msg/Image', 'sensor_msgs/msg/CompressedImage',
                                   'sensor_msgs/msg/CameraInfo')
        reliability = (ReliabilityPolicy.BEST_EFFORT
                       if sensor and self.config.sensor_reliability == 'best_effort'
                       else ReliabilityPolicy.RELIABLE)
        return QoSProfile(depth=depth, reliability=reliability,
                          durability=(DurabilityPolicy.TRANSIENT_LOCAL if latched
                                      else DurabilityPolicy.VOLATILE),
                          history=HistoryPolicy.KEEP_LAST)

    def close(self) -> None:
        """Close the bag (the publishers belong to the node)."""
        self.bag.close()

    def wait_for_subscribers(self, timeout_s: float, settle_s: float = 0.3) -> bool:
        """Wait until some topic of the bag has a subscriber and every other topic of the bag
        that the same nodes subscribe to (as the ROS graph lists them) has matched this
        player's publisher too, then ``settle_s`` more; False on timeout (some topic matched
        or not).

        (Not every topic of the bag: a bag usually carries topics nobody listens to, e.g.
        ground truth; but a stereo node's second camera must not lose the first frames because
        its subscription matched later than the first.)
        """
        end = time.monotonic() + timeout_s
        while time.monotonic() < end:
            matched = {t for t, p in self.publishers.items() if p.get_subscription_count() > 0}
            if matched and self._wanted_by_subscribers(matched) <= matched:
                time.sleep(settle_s)
                return True
            time.sleep(0.05)
        return False

    def _wanted_by_subscribers(self, matched: set[str]) -> set[str]:
        """The topics of the bag that the nodes subscribed to any of ``matched`` subscribe to
        (the ROS graph's list of each node's subscriptions; unnamed endpoints skipped)."""
        mine = {('/' + t.lstrip('/')): t for t in self.publishers}
        wanted: set[str] = set()
        for topic in matched:
            for info in self.node.get_subscriptions_info_by_topic(topic):
                if _unnamed(info.node_name):
                    continue
                try:
                    subs = self.node.get_subscriber_names_and_types_by_node(
                        info.node_name, info.node_namespace)
                except NodeNameNonExistentError:  # it left the graph meanwhile
                    continue
                wanted.update(mine[name] for name, _ in subs if name in mine)
        return wanted

    def _clock(self, stamp_ns: int, stats: PlayStats) -> None:
        if self.clock_pub is None:
            return
        msg = Clock()
        msg.clock.sec, msg.clock.nanosec = divmod(int(stamp_ns), 1_000_000_000)
        self.clock_pub.publish(msg)
        stats.clock_messages += 1

    def _wait_acked(self) -> None:
        timeout = Duration(seconds=self.config.ack_timeout_s)
        for p in self.publishers.values():
            p.wait_for_all_acked(timeout)

    def _on_done(self, topic: str, msg: KeyValue) -> None:
        try:
            received = int(msg.value)
        except ValueError:
            received = -1                     # a confirmation that says nothing we can use
        seen = self.done[topic]
        seen[msg.key] = max(seen.get(msg.key, -1), received)

    def confirmers(self, topic: str) -> set[str]:
        """Fully qualified names of the nodes expected to confirm ``topic``: its subscribers
        that ask for the history (:meth:`asks_history`) and the publishers of its input-done
        topic. An endpoint whose node DDS does not name (yet, or any more: rclpy's
        ``_NODE_NAME_UNKNOWN_``, e.g. a killed node's stale endpoint) is not a node to wait for."""
        def fqn(info: Any) -> str:
            ns = info.node_namespace.rstrip('/')
            return f'{ns}/{info.node_name}'

        subs = [i for i in self.node.get_subscriptions_info_by_topic(topic)
                if i.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL]
        pubs = self.node.get_publishers_info_by_topic(topics.input_done_topic(topic))
        return {fqn(i) for i in subs + pubs if not _unnamed(i.node_name)}

    def unconfirmed_of(self, topic: str, expected: set[str]) -> list[str]:
        """The nodes of ``expected`` (and any that confirmed) that have not confirmed
        receiving every measurement sent on ``topic``, each with what it said. A node that
        left the graph after it was expected (killed; its restart confirms in turn) is still
        expected: success needs every node that subscribed to have all of it."""
        sent, seen = self.sent[topic], self.done[topic]
        out = []
        for name in sorted(expected | set(seen)):
            got = seen.get(name)
            if got is None:
                out.append(f'{name} did not confirm it processed the input (no message on '
                           f'{topics.input_done_topic(topic)})')
            elif got < sent:
                out.append(f'{name} confirmed only {got} of the {sent} measurements sent')
        return out

    def undelivered(self, step_s: float = 0.5) -> list[str]:
        """What is not delivered now: a measurement topic without a subscriber, or a topic
        not acknowledged by every matched subscriber within ``step_s``."""
        step = Duration(seconds=step_s)
        missing = []
        for name, p in self.publishers.items():
            if name in self.kept and p.get_subscription_count() == 0:
                missing.append(f'{name}: no subscriber')
            elif not p.wait_for_all_acked(step):
                missing.append(f'{name}: not acknowledged by every subscriber')
        return missing

    def asks_history(self, topic: str) -> bool:
        """True when a subscriber of ``topic`` asks for the history (transient local, as the
        alignment node by default): it is there to process the input, so play expects its
        confirmation. Known with the subscription itself, whatever the order in which DDS
        discovers the node's other endpoints (its input-done publisher may come later)."""
        return any(info.qos_profile.durability == DurabilityPolicy.TRANSIENT_LOCAL
                   for info in self.node.get_subscriptions_info_by_topic(topic))

    def _wait_delivered(self, patience_s: float) -> list[str]:
        """Before exiting: wait until :meth:`undelivered` is empty and every end topic with a
        confirming subscriber (one asking for the history, :meth:`asks_history`, or a node
        publishing the input-done topic) got a confirmation that the end of input was
        processed. A node killed meanwhile stays matched until DDS notices it is gone; its
        restart gets the whole history again and confirms in turn. Gives up after
        ``patience_s`` without any subscriber acknowledging or node processing, and in any
        case after ``AT_WORK_PATIENCE`` times ``patience_s`` (a confirmation lost on its
        volatile topic must not make the player wait forever). Returns what is still
        undelivered (with an error line naming it)."""
        end = time.monotonic() + patience_s
        last = time.monotonic() + AT_WORK_PATIENCE * patience_s
        expected: dict[str, set[str]] = {t: set() for t in self.end_topics}  # nodes ever seen
        while True:
            now = time.monotonic()
            missing = self.undelivered()
            for t in self.end_topics:
                expected[t] |= self.confirmers(t)
                at_work = self.node.count_publishers(topics.input_done_topic(t)) > 0
                pending = [n for n in expected[t] if self.done[t].get(n, -1) < self.sent[t]]
                if at_work and pending:
                    end = min(max(end, now + patience_s), last)   # a node is at work
                missing += [f'{t}: {text}' for text in self.unconfirmed_of(t, expected[t])]
            if not missing or now > end:
                break
            rclpy.spin_once(self.node, timeout_sec=0.05)
        if missing:
            self.node.get_logger().error(
                f'after {patience_s:g} s, NOT DELIVERED: ' + '; '.join(missing))
        return missing

    def play(self) -> PlayStats:
        """Publish the whole bag; returns what was published.

        Raises
        ------
        FormatError
            If the bag turns out truncated or corrupt (the messages before it were published).
        """
        c = self.config
        stats = PlayStats(counts={t: 0 for t in self.topics})
        if c.wait_for_subscribers_s > 0 and not self.wait_for_subscribers(
                c.wait_for_subscribers_s):
            self.node.get_logger().warning(
                f'no subscriber on any topic after {c.wait_for_subscribers_s:g} s; playing '
                'anyway (measurement topics keep their history for a late subscriber)')
        if c.delay_s > 0:
            time.sleep(c.delay_s)
        t0 = time.monotonic()
        bag_t0: int | None = None
        next_clock = -1
        clock_step = max(int(c.clock_period_s * 1e9), 1)
        since_ack = 0
        last = 0
        for m in self.bag.messages(self.topics, raw=True):
            if bag_t0 is None:
                bag_t0 = m.log_ns
            if c.rate > 0:
                due = t0 + (m.log_ns - bag_t0) * 1e-9 / c.rate
                while True:
                    now = time.monotonic()
                    if now >= due:
                        break
                    # keep /clock ticking through long gaps
                    if self.clock_pub is not None and next_clock >= 0:
                        bag_now = bag_t0 + int((now - t0) * c.rate * 1e9)
                        if bag_now >= next_clock:
                            self._clock(bag_now, stats)
                            next_clock = bag_now + clock_step
                    time.sleep(min(due - now, 0.005))
            if m.log_ns >= next_clock:
                self._clock(m.log_ns, stats)
                next_clock = m.log_ns + clock_step
            self.publishers[m.topic].publish(m.data)
            stats.counts[m.topic] += 1
            if m.topic in self.sent:
                self.sent[m.topic] += 1
            last = m.log_ns
            if c.rate == 0:
                since_ack += 1
                if since_ack >= c.ack_every:
                    self._wait_acked()
                    since_ack = 0
        if bag_t0 is not None:  # /clock ends at the bag's last message, sent before the
            self._clock(last, stats)  # end signals and the wait for their delivery below
            stats.bag_seconds = (last - bag_t0) * 1e-9
        # reliable delivery of the tail before the process (and its DDS writers) goes away
        self._wait_acked()
        for topic in self.end_topics:
            end = Odometry()
            end.child_frame_id = TRACK_END_FRAME
            self.publishers[topic].publish(end)
            stats.end_signals += 1
        stats.undelivered = self._wait_delivered(c.delivery_timeout_s)
        stats.seconds = time.monotonic() - t0
        return stats


#: Fast DDS profile of the player's writers: a 5 ms heartbeat, so subscribers acknowledge within
#: milliseconds (the default is 3 s) when acknowledgements pace the player or end it.
FAST_HEARTBEAT_PROFILE = """<?xml version="1.0" encoding="UTF-8" ?>
<profiles xmlns="http://www.eprosima.com/XMLSchemas/fastRTPS_Profiles">
  <data_writer profile_name="ga_play_writer" is_default_profile="true">
    <times><heartbeatPeriod><sec>0</sec><nanosec>5000000</nanosec></heartbeatPeriod></times>
  </data_writer>
</profiles>
"""
_PROFILE_VARS = ('FASTRTPS_DEFAULT_PROFILES_FILE', 'FASTDDS_DEFAULT_PROFILES_FILE')


def play_bag(bag_path: str | Path, config: PlayConfig = PlayConfig(),
             ros_args: Sequence[str] | None = None, verbose: bool = True) -> PlayStats:
    """Init rclpy, play ``bag_path`` with a node named ``ga_play``, shut down; returns stats.

    With Fast DDS (the default RMW) and no user profile file, the player's own process gets
    :data:`FAST_HEARTBEAT_PROFILE` (environment of this process only), so that waiting for
    acknowledgements (``rate = 0``, and before exiting) costs milliseconds instead of Fast DDS's
    3 s heartbeat.
    """
    profile = None
    if (not any(os.environ.get(v) for v in _PROFILE_VARS)
            and os.environ.get('RMW_IMPLEMENTATION', 'rmw_fastrtps_cpp') == 'rmw_fastrtps_cpp'):
        fd, profile = tempfile.mkstemp(prefix='ga_play_', suffix='.xml')
        with os.fdopen(fd, 'w') as f:
            f.write(FAST_HEARTBEAT_PROFILE)
        os.environ['FASTRTPS_DEFAULT_PROFILES_FILE'] = profile
    try:
        rclpy.init(args=list(ros_args) if ros_args else None)
        node = Node('ga_play')
    finally:
        if profile is not None:
            os.environ.pop('FASTRTPS_DEFAULT_PROFILES_FILE', None)
    player = None
    try:
        player = BagPlayer(node, bag_path, config)
        if verbose:
            print(f'playing {bag_path}: {", ".join(player.topics)} at '
                  + (f'rate {config.rate:g}' if config.rate > 0 else 'full speed (acked)'),
                  flush=True)
        return player.play()
    finally:
        if player is not None:
            player.close()
        node.destroy_node()
        rclpy.try_shutdown()
        if profile is not None:
            os.unlink(profile)


def build_parser(parser: argparse.ArgumentParser | None = None) -> argparse.ArgumentParser:
    """Arguments of ``ga-ros play`` (also ``python -m ga_ros.ros.play``)."""
    return add_arguments(parser or argparse.ArgumentParser(prog='ga-ros play',
                                                           description=__doc__,
                                                           allow_abbrev=False))


def run(args: argparse.Namespace) -> int:
    """Entry of ``ga-ros play``: play the bag and print what was published."""
    config = PlayConfig(rate=args.rate, topics=tuple(args.topics), clock=not args.no_clock,
                        delay_s=args.delay, wait_for_subscribers_s=args.wait_for_subscribers,
                        end_signal=not args.no_end_signal,
                        delivery_timeout_s=args.delivery_timeout,
                        sensor_reliability=args.sensor_qos)
    stats = play_bag(args.bag, config)
    total = sum(stats.counts.values())
    print(f'published {total} messages ({stats.bag_seconds:.1f} s of bag time) in '
          f'{stats.seconds:.2f} s, {stats.clock_messages} /clock messages, '
          f'{stats.end_signals} end-of-input messages')
    for topic, n in sorted(stats.counts.items()):
        print(f'  {topic:<40} {n}')
    if stats.undelivered:
        print(f'ga-ros play: error: not delivered after {args.delivery_timeout:g} s: '
              + '; '.join(stats.undelivered), file=sys.stderr)
        return EXIT_NOT_DELIVERED
    return 0


def main(args: Sequence[str] | None = None) -> int:
    """``python -m ga_ros.ros.play BAG [--rate R]``."""
    argv = list(sys.argv[1:] if args is None else args)
    if '--ros-args' in argv:
        argv = argv[:argv.index('--ros-args')]
    parsed = build_parser().parse_args(argv)
    try:
        return run(parsed)
    except GaError as exc:
        print(f'ga-ros play: error: {exc}', file=sys.stderr)
        return 1
    except (KeyboardInterrupt, ExternalShutdownException):
        return 130


if __name__ == '__main__':
    sys.exit(main())
