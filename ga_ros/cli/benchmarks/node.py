"""``ga-ros bench node``: latency and sustained measurement rate of the alignment node.

Starts the alignment node as a separate process (own ``ROS_DOMAIN_ID``), streams the measurements
of a simulated aerial survey to it, and prints, per track:

* the measurement-to-corrected-path latency at the end of the track: the time from publishing the
  first measurement of the next track (which ends the track) to receiving the new
  ``nav_msgs/Path``; the node has absorbed every earlier measurement before the clock starts;
* the rate at which the node absorbs the track's measurements between updates, when they are
  published at ``--rate`` per second: measurements / (time the node reports the last one received
  - time the first was published), the lag of the node behind the publisher at the end of the
  track (it stays at a few diagnostics periods, 20 ms each, if the node keeps up), and whether
  any were dropped (the node's ``measurements_received`` counter vs. the number published);
* the node's own time per measurement callback (decode, validate, add to the network);
* the drain rate (``--capacity``, on by default): an ``AlignmentNode`` in this process with a
  publisher beside it; the first track's measurements are published at once into the node's
  reliable queue, then the executor is spun and the time to absorb them all is measured. This is
  the sustained rate the node absorbs between updates, including rclpy's take and deserialise
  overhead, independent of how fast one Python publisher can send.

A benchmark, not a test: it prints figures and asserts nothing (exit code 1 only on a failure to
run). ROS is imported lazily inside the functions that need it so the CLI works without it.
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import dataclass
from typing import Any


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``ga-ros bench node``."""
    p = argparse.ArgumentParser(
        prog='ga-ros bench node',
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter,
        allow_abbrev=False)
    p.add_argument('--tracks', type=int, default=6, help='double tracks in the survey (6)')
    p.add_argument('--per-swath', type=int, default=102,
                   help='nodes per swath (102: the paper aerial scenario)')
    p.add_argument('--noise', type=float, default=5.0, help='motion noise, percent (5)')
    p.add_argument('--rate', type=float, default=2000.0,
                   help='publish rate, measurements/s (2000; 0: as fast as possible)')
    p.add_argument('--window', type=int, default=5, help='window size in tracks (5)')
    p.add_argument('--markers', action='store_true', help='also publish the network markers')
    p.add_argument('--seed', type=int, default=0)
    p.add_argument('--domain-id', type=int, default=None,
                   help='ROS_DOMAIN_ID for the node and the benchmark (default: one claimed '
                        'machine-wide, never one a concurrent run holds)')
    p.add_argument('--log', default=None, help='file for the node process output')
    p.add_argument('--no-capacity', dest='capacity', action='store_false',
                   help='skip the in-process drain-rate measurement')
    return p


@dataclass(frozen=True)
class TrackFigures:
    """Figures of one track streamed to the node.

    Attributes
    ----------
    track : track id.
    n : measurements streamed between the updates.
    published_per_s : publish rate achieved, measurements/s.
    absorbed_per_s : rate the node absorbed them, measurements/s.
    lag_ms : time from the last publish to the node's report of the last one, ms.
    latency_ms : end-of-track latency (measurement -> corrected path), ms (NaN: first track).
    update_ms : the node's update time of the track end, ms (NaN: first track).
    """

    track: int
    n: int
    published_per_s: float
    absorbed_per_s: float
    lag_ms: float
    latency_ms: float
    update_ms: float


@dataclass(frozen=True)
class NodeFigures:
    """Figures of a whole survey streamed to the node: per track, the final ``finish_track``
    latency (ms), the node's counters and its time per measurement callback (us)."""

    rows: list[TrackFigures]
    sent: int
    final_ms: float
    received: int
    accepted: int
    callback_us: float


def run(args: argparse.Namespace) -> int:
    from ga_ros.domains import domain_id
    from ga_ros.errors import InputError

    if args.tracks < 2 or args.per_swath < 2:
        raise InputError('need --tracks >= 2 and --per-swath >= 2')
    by_track, n_nodes, n_measurements = survey_by_track(args.tracks, args.per_swath,
                                                        args.noise, args.seed)
    dom = args.domain_id if args.domain_id is not None else domain_id('bench node')
    print(f'aerial survey: {args.tracks} tracks x {2 * args.per_swath} nodes, '
          f'{n_nodes} nodes, {n_measurements} measurements; window {args.window} tracks; '
          f'ROS_DOMAIN_ID {dom}')
    params = {'window_tracks': args.window, 'state_file': '', 'autosave': False,
              'diagnostics_period_sec': 0.02, 'publish_markers': bool(args.markers),
              'allow_finish_track': True}
    if args.capacity:
        n, drain_s, n_got = drain_rate(by_track[min(by_track)], dom, params)
        print(f'drain rate (in-process node, {n} queued measurements of track 0): '
              f'{n_got / drain_s:.0f} measurements/s ({n_got}/{n} absorbed in {drain_s:.2f} s)')
    figures = stream_survey(by_track, dom, params, args.rate, args.log)
    print_figures(figures)
    return 0


def survey_by_track(n_tracks: int, per_swath: int, noise_percent: float,
                    seed: int) -> tuple[dict[int, list], int, int]:
    """The noisy measurements of a simulated aerial survey grouped by destination track;
    ``(by_track, n_nodes, n_measurements)``."""
    import numpy as np

    from ga_ros.sim.aerial import aerial_scenario
    from ga_ros.sim.noise import NoiseModel, perturb

    rng = np.random.default_rng(seed)
    sc = aerial_scenario(n_tracks=n_tracks, positions_per_swath=per_swath)
    noisy = perturb(sc.true_motions(), NoiseModel(noise_percent, sc.depth_m), rng)
    ms = sc.measurements(noisy.z, noisy.cov)
    by_track: dict[int, list] = {}
    for m in ms:
        by_track.setdefault(m.dst_track, []).append(m)
    return by_track, sc.n_nodes, len(ms)


def stream_survey(by_track: dict[int, list], domain_id: int, params: dict, rate_hz: float,
                  log: str | None) -> NodeFigures:
    """Start the node as a process, stream the survey track by track at ``rate_hz``
    measurements/s (0: as fast as possible), end the last track by ``~/finish_track``."""
    from ga_ros.ros.harness import NodeClient, start_node_process, stop_process

    proc = start_node_process(domain_id, params, log_path=log)
    client = None
    rows = []
    try:
        client = NodeClient(domain_id)
        client.wait_for_node(timeout=60.0, proc=proc)
        sent = 0
        for track in sorted(by_track):
            row = _stream_track(client, proc, track, by_track[track], sent, rate_hz)
            sent += row.n + (1 if sent else 0)
            rows.append(row)
        client.spin_until(lambda: client.diag_int('measurements_received') >= sent, 60.0,
                          'the last measurements', proc)
        n_paths = len(client.paths)
        t0 = time.perf_counter()
        client.call('finish_track', timeout=120.0)
        client.spin_until(lambda: len(client.paths) > n_paths, 120.0, 'the final path', proc)
        final_ms = 1e3 * (client.paths[-1][0] - t0)
        return NodeFigures(rows, sent, final_ms, client.diag_int('measurements_received'),
                           client.diag_int('measurements_accepted'),
                           float(client.diagnostics.get('measurement_callback_us', 'nan')))
    finally:
        if client is not None:
            client.close()
        stop_process(proc)


def _stream_track(client: Any, proc: Any, track: int, group: list, sent: int,
                  rate_hz: float) -> TrackFigures:
    """Stream one track: its first measurement ends the previous track (the latency is timed
    from it to the new path) unless it is the first; then the rest at ``rate_hz``."""
    latency_ms = update_ms = float('nan')
    if sent:                        # the first measurement of this track ends the last
        client.wait_received(sent, timeout=120.0, proc=proc)
        n_paths = len(client.paths)
        n_updates = client.diag_int('updates', 0)
        t0 = time.perf_counter()
        client.publish(group[:1])
        client.spin_until(lambda n=n_paths: len(client.paths) > n, 120.0,
                          'the corrected path', proc)
        latency_ms = 1e3 * (client.paths[-1][0] - t0)
        client.spin_until(lambda u=n_updates: client.diag_int('updates') > u, 30.0,
                          'the update diagnostics', proc)
        update_ms = float(client.diagnostics.get('update_ms', 'nan'))
        group = group[1:]
        sent += 1
    client.wait_received(sent, timeout=120.0, proc=proc)
    t_start = time.perf_counter()
    pub_s = client.publish(group, rate_hz=rate_hz)
    t_published = time.perf_counter()
    sent += len(group)
    client.spin_until(lambda s=sent: client.diag_int('measurements_received') >= s,
                      120.0, 'the measurements', proc)
    t_done = time.perf_counter()
    return TrackFigures(track, len(group), len(group) / max(pub_s, 1e-9),
                        len(group) / max(t_done - t_start, 1e-9),
                        1e3 * (t_done - t_published), latency_ms, update_ms)


def print_figures(figures: NodeFigures) -> None:
    """The per-track table and the summary lines of ``ga-ros bench node``."""
    import math

    rows, sent, final_ms = figures.rows, figures.sent, figures.final_ms
    print(f'{"track":>5} {"meas":>6} {"published/s":>12} {"absorbed/s":>11} {"lag ms":>7} '
          f'{"latency ms":>11} {"update ms":>10}')
    for r in rows:
        print(f'{r.track:5d} {r.n:6d} {r.published_per_s:12.0f} {r.absorbed_per_s:11.0f} '
              f'{r.lag_ms:7.0f} {r.latency_ms:11.1f} {r.update_ms:10.1f}')
    lats = [r.latency_ms for r in rows if math.isfinite(r.latency_ms)] + [final_ms]
    print(f'end-of-track latency (measurement -> corrected path): median '
          f'{statistics.median(lats):.1f} ms, max {max(lats):.1f} ms over {len(lats)} track ends '
          f'(last one via ~/finish_track: {final_ms:.1f} ms)')
    print(f'sustained rate absorbed between updates: min '
          f'{min(r.absorbed_per_s for r in rows):.0f}, '
          f'median {statistics.median(r.absorbed_per_s for r in rows):.0f} measurements/s '
          f'(target >= 2000)')
    print(f'end-of-track lag behind the publisher: max {max(r.lag_ms for r in rows):.0f} ms')
    print(f'node time per measurement callback: {figures.callback_us:.1f} us '
          f'(callback-bound capacity ~{1e6 / figures.callback_us:.0f} measurements/s)')
    print(f'measurements published {sent}, received {figures.received}, accepted '
          f'{figures.accepted}, dropped {sent - figures.received}')


def drain_rate(measurements, domain_id: int, params: dict) -> tuple[int, float, int]:
    """Queue ``measurements`` into an in-process :class:`AlignmentNode` and time how fast its
    executor absorbs them. Returns ``(published, seconds, absorbed)``."""
    import rclpy
    from nav_msgs.msg import Odometry
    from rclpy.executors import SingleThreadedExecutor
    from rclpy.parameter import Parameter

    from ga_ros.ros import conversions as conv
    from ga_ros.ros.alignment_node import AlignmentNode
    from ga_ros.ros.qos import measurement_qos

    ctx = rclpy.Context()
    rclpy.init(context=ctx, domain_id=domain_id)
    node = AlignmentNode(context=ctx, parameter_overrides=[
        Parameter(k, value=v) for k, v in params.items()])
    pub_node = rclpy.create_node('ga_bench_publisher', context=ctx)
    executor = SingleThreadedExecutor(context=ctx)
    executor.add_node(node)
    try:
        pub = pub_node.create_publisher(Odometry, node.settings.measurements_topic,
                                        measurement_qos(max(len(measurements), 10),
                                                        transient_local=True))
        deadline = time.monotonic() + 30.0
        while pub.get_subscription_count() == 0 and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.05)
        msgs = [conv.measurement_to_odometry(m) for m in measurements]
        for msg in msgs:
            pub.publish(msg)
        time.sleep(0.5)                       # let DDS deliver everything into the queue
        t0 = time.perf_counter()
        deadline = time.monotonic() + 60.0
        while node.n_received < len(msgs) and time.monotonic() < deadline:
            executor.spin_once(timeout_sec=0.1)
        seconds = max(time.perf_counter() - t0, 1e-9)
        return len(msgs), seconds, node.n_received
    finally:
        executor.shutdown(timeout_sec=1.0)
        pub_node.destroy_node()
        node.destroy_node()
        rclpy.try_shutdown(context=ctx)


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench node [options]``."""
    return run(build_parser().parse_args(argv))
