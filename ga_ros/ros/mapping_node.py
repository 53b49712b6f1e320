"""A small, independent "mapping node": the consumer of the corrected path on another host.

It stands for a mapping or planning computer that uses the alignment's output (issue 14, the
third host of ``ga-ros multihost``). It builds no map (``map_node``, :mod:`ga_ros.ros.map_node`,
does); it only subscribes, records and reports:

* the corrected path (``nav_msgs/Path``, transient local), with the wall-clock time each message
  arrived;
* the measurements (``nav_msgs/Odometry`` in the measurement encoding, reliable, deep queue),
  with the publisher's source timestamp (``rmw`` message info): the time the VO published them
  on the first host.

With ``--finish-after-idle SEC`` it also ends the survey: once measurements have stopped for
``SEC`` seconds it calls the alignment node's ``finish_track`` service and waits for the path
that follows, then writes its outputs and exits. Outputs (``--out DIR``):

* ``path.npz``: the last path received: ``T_world_node`` (n, 4, 4), ``stamps_ns`` (n,);
* ``measurements/``: an mcap bag of the measurements received, in arrival order (replay it with
  ``ga-ros replay`` to get the in-process reference of the same input);
* ``mapping.json``: counts, every path message's arrival time and size, and the end-of-track
  latencies (see :func:`track_latencies`).

Times are ``CLOCK_REALTIME`` nanoseconds: comparable across hosts only when their clocks are
synchronised (network namespaces on one machine share one clock; real hosts need NTP/PTP).

Run as ``python -m ga_ros.ros.mapping_node --out DIR [--ros-args ...]``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np
import rclpy
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from ga_ros.core.measurement import Measurement
from ga_ros.errors import GaError
from ga_ros.ros import conversions as conv
from ga_ros.ros.qos import latched_qos, measurement_qos
from ga_ros.safe_write import check_destinations, write_json, write_npz

READY_LINE = 'mapping_node: ready'


@dataclass(frozen=True)
class MappingSettings:
    """Settings of the mapping node (command-line options).

    Attributes
    ----------
    out_dir : where the outputs are written.
    path_topic, measurements_topic : topic names (relative names resolve in the node's
        namespace: ``ga/corrected_path`` is ``/ga/corrected_path`` without one).
    finish_service : the alignment node's ``finish_track`` service (``std_srvs/Trigger``).
    finish_after_idle_s : call ``finish_service`` once no measurement came for this long (s),
        then exit after the next path; 0 = never (run until ``timeout_s`` or SIGINT).
    finish_armed_by : a file's path: the idle time counts only once this file exists (the
        orchestrator creates it when the player has exited, so a stall of the VO or of a loaded
        machine mid-survey does not end the survey); '' = counts from the start.
    timeout_s : give up after this long (s) in all; the outputs are written anyway (exit 1).
    ready_publishers : print :data:`READY_LINE` once this many publishers of the measurements
        and one of the path have been discovered.
    """

    out_dir: str
    path_topic: str = 'ga/corrected_path'
    measurements_topic: str = 'ga/measurements'
    finish_service: str = 'alignment_node/finish_track'
    finish_after_idle_s: float = 0.0
    finish_armed_by: str = ''
    timeout_s: float = 600.0
    ready_publishers: int = 1


@dataclass
class Received:
    """What arrived, with times in ``CLOCK_REALTIME`` ns."""

    measurements: list[Measurement] = field(default_factory=list)
    m_source_ns: list[int] = field(default_factory=list)
    m_receive_ns: list[int] = field(default_factory=list)
    m_dst_track: list[int] = field(default_factory=list)
    path_receive_ns: list[int] = field(default_factory=list)
    path_sizes: list[int] = field(default_factory=list)
    last_path: PathMsg | None = None
    bad_measurements: int = 0


@dataclass
class TrackLatency:
    """End-of-track latency of track ``track_id`` (s).

    ``from_trigger_s``: from the publication of the measurement that ended the track (the first
    one of the next track: the aligner cannot know the track is over before it) to the arrival
    of the next corrected path; ``from_last_s``: from the publication of the track's last
    measurement to the same arrival.
    """

    track_id: int
    from_trigger_s: float
    from_last_s: float


def track_latencies(m_source_ns: list[int], m_dst_track: list[int],
                    path_receive_ns: list[int]) -> list[TrackLatency]:
    """End-of-track latencies from the recorded times (see :class:`TrackLatency`).

    A track ends at the first measurement whose destination track id is larger than every
    earlier one; its latency is measured to the first path that arrived after that measurement
    was published. The final track (ended by the ``finish_track`` call) is not included.
    """
    out: list[TrackLatency] = []
    paths = np.asarray(path_receive_ns, dtype=np.int64)
    best = None
    for k, tr in enumerate(m_dst_track):
        if best is not None and tr > best and k > 0:
            t_trig = m_source_ns[k]
            after = paths[paths > t_trig]
            if after.size:
                out.append(TrackLatency(int(best), (int(after[0]) - t_trig) * 1e-9,
                                        (int(after[0]) - m_source_ns[k - 1]) * 1e-9))
        best = tr if best is None else max(best, tr)
    return out


class MappingNode(Node):
    """Records the corrected path and the measurements; optionally ends the survey."""

    def __init__(self, settings: MappingSettings, **kwargs) -> None:
        super().__init__('mapping_node', **kwargs)
        self.settings = settings
        self.rx = Received()
        self.create_subscription(PathMsg, settings.path_topic, self._on_path, latched_qos())
        self.create_subscription(Odometry, settings.measurements_topic, self._on_measurement,
                                 measurement_qos())
        self.finish_client = self.create_client(Trigger, settings.finish_service)
        self.finish_called_ns: int | None = None
        self.finish_reply: str | None = None
        self.ready = False

    def _on_path(self, msg: PathMsg) -> None:
        self.rx.path_receive_ns.append(time.time_ns())
        self.rx.path_sizes.append(len(msg.poses))
        self.rx.last_path = msg

    def _on_measurement(self, msg: Odometry, info) -> None:
        now = time.time_ns()
        try:
            m = conv.odometry_to_measurement(msg)
        except GaError:
            self.rx.bad_measurements += 1
            return
        self.rx.measurements.append(m)
        self.rx.m_receive_ns.append(now)
        self.rx.m_source_ns.append(int(info['source_timestamp']))
        self.rx.m_dst_track.append(int(m.dst_track))

    def check_ready(self) -> bool:
        """True (and print :data:`READY_LINE` once) when the publishers are discovered."""
        if not self.ready:
            n_meas = self.count_publishers(self.resolve_topic_name(
                self.settings.measurements_topic))
            n_path = self.count_publishers(self.resolve_topic_name(self.settings.path_topic))
            if n_meas >= self.settings.ready_publishers and n_path >= 1:
                self.ready = True
                print(READY_LINE, flush=True)
        return self.ready


#: The files the node writes in its output directory (besides the ``measurements/`` bag).
OUTPUT_FILES = ('path.npz', 'mapping.json')


def check_outputs(out_dir: str | os.PathLike) -> None:
    """Refuse (:class:`ga_ros.errors.UnsafePathError`) output files that are symbolic links or
    not regular files, before the node starts (the outputs are written when it ends)."""
    check_destinations(*(Path(out_dir) / name for name in OUTPUT_FILES))


def write_outputs(node: MappingNode, status: str) -> dict:
    """Write ``path.npz``, ``measurements/`` and ``mapping.json`` to the output directory
    (atomically, never through a symbolic link: :mod:`ga_ros.safe_write`)."""
    from ga_ros.replay.samples import write_measurement_bag

    s, rx = node.settings, node.rx
    out = Path(s.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    if rx.last_path is not None:
        stamps = np.array([p.header.stamp.sec * 10**9 + p.header.stamp.nanosec
                           for p in rx.last_path.poses], dtype=np.int64)
        write_npz(out / 'path.npz', T_world_node=conv.path_msg_to_poses(rx.last_path),
                  stamps_ns=stamps)
    if rx.measurements:
        write_measurement_bag(out / 'measurements', rx.measurements, None, overwrite=True)
    lat = track_latencies(rx.m_source_ns, rx.m_dst_track, rx.path_receive_ns)
    summary = {
        'status': status,
        'measurements': len(rx.measurements),
        'bad_measurements': rx.bad_measurements,
        'tracks': sorted(set(rx.m_dst_track)),
        'paths': len(rx.path_sizes),
        'path_sizes': rx.path_sizes,
        'path_receive_ns': rx.path_receive_ns,
        'last_path_poses': rx.path_sizes[-1] if rx.path_sizes else 0,
        'first_measurement_source_ns': rx.m_source_ns[0] if rx.m_source_ns else None,
        'last_measurement_source_ns': rx.m_source_ns[-1] if rx.m_source_ns else None,
        'finish_called_ns': node.finish_called_ns,
        'finish_reply': node.finish_reply,
        'track_latencies': [asdict(x) for x in lat],
        'settings': asdict(s),
    }
    write_json(out / 'mapping.json', summary, indent=1)
    return summary


def run(settings: MappingSettings, ros_args: list[str] | None = None) -> int:
    """Spin the node until the survey is finished (or ``timeout_s``); write the outputs."""
    try:
        check_outputs(settings.out_dir)
    except GaError as exc:
        print(f'mapping_node: error: {exc}', file=sys.stderr)
        return 1
    rclpy.init(args=ros_args)
    node = MappingNode(settings)
    ex = SingleThreadedExecutor()
    ex.add_node(node)
    status = 'timeout'
    t_end = time.monotonic() + settings.timeout_s
    future = None
    n_paths_at_finish = 0
    armed_ns = None if settings.finish_armed_by else 0
    try:
        while time.monotonic() < t_end:
            ex.spin_once(timeout_sec=0.05)
            node.check_ready()
            idle = settings.finish_after_idle_s
            rx = node.rx
            if armed_ns is None and os.path.exists(settings.finish_armed_by):
                armed_ns = time.time_ns()
            if future is None and idle > 0 and rx.measurements and armed_ns is not None:
                if (time.time_ns() - max(rx.m_receive_ns[-1], armed_ns)) * 1e-9 > idle:
                    if node.finish_client.service_is_ready():
                        n_paths_at_finish = len(rx.path_sizes)
                        node.finish_called_ns = time.time_ns()
                        future = node.finish_client.call_async(Trigger.Request())
            if future is not None and future.done():
                if node.finish_reply is None:
                    res = future.result()
                    node.finish_reply = f'{res.success}: {res.message}'
                if (len(rx.path_sizes) > n_paths_at_finish
                        or node.finish_reply.endswith('no open track')):
                    status = 'finished'
                    break
    except (KeyboardInterrupt, ExternalShutdownException):
        status = 'interrupted'
    summary = write_outputs(node, status)
    print(json.dumps({k: summary[k] for k in ('status', 'measurements', 'paths',
                                               'last_path_poses')}), flush=True)
    ex.shutdown()
    node.destroy_node()
    rclpy.try_shutdown()
    return 0 if status == 'finished' or settings.finish_after_idle_s <= 0 else 1


def main(args: list[str] | None = None) -> int:
    """Console entry: ``python -m ga_ros.ros.mapping_node --out DIR [options] [--ros-args]``."""
    argv = list(sys.argv[1:] if args is None else args)
    ros_args = []
    if '--ros-args' in argv:
        k = argv.index('--ros-args')
        argv, ros_args = argv[:k], argv[k:]
    p = argparse.ArgumentParser(prog='mapping_node', description=__doc__.split('\n\n')[0],
                                allow_abbrev=False)
    p.add_argument('--out', required=True, help='output directory')
    p.add_argument('--path-topic', default=MappingSettings.path_topic)
    p.add_argument('--measurements-topic', default=MappingSettings.measurements_topic)
    p.add_argument('--finish-service', default=MappingSettings.finish_service)
    p.add_argument('--finish-after-idle', type=float, default=0.0,
                   help='call finish_track once measurements stopped this long (s), then exit')
    p.add_argument('--finish-armed-by', default='', metavar='FILE',
                   help='count the idle time only once FILE exists (e.g. created when the '
                        'player has exited)')
    p.add_argument('--timeout', type=float, default=MappingSettings.timeout_s,
                   help='give up after this many seconds')
    a = p.parse_args(argv)
    settings = MappingSettings(a.out, a.path_topic, a.measurements_topic, a.finish_service,
                               a.finish_after_idle, a.finish_armed_by, a.timeout)
    return run(settings, ['mapping_node', *ros_args] if ros_args else None)


if __name__ == '__main__':
    sys.exit(main())
