"""Fault catalogue of issue 12: bad inputs, kills, corrupt files and races against LIVE nodes.

Each case starts ``alignment_node`` as a process (own ``ROS_DOMAIN_ID``), feeds it a small
simulated survey with the fault injected, ends the input with the end-of-input message and
compares the final published path with :class:`TrackWindowAligner` fed the clean measurements.
Prints one row per case: survived (the node process is alive, or exited cleanly where that is
the case), counted (rejections or events the node reported, against the expected ones), nodes
lost (reference nodes missing from, or misplaced in, the final path).

Run: ``.venv/bin/python scripts/fault_catalogue.py [--only NAME ...]`` (about a minute).
"""

from __future__ import annotations

import argparse
import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.duration import Duration

from ga_ros import topics
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import InputError
from ga_ros.pipeline.journal import journal_path
from ga_ros.replay.samples import aerial_sample, write_measurement_bag
from ga_ros.ros import conversions as conv
from ga_ros.ros.harness import HarnessTimeout, NodeClient, start_node_process, stop_process
from ga_ros.ros.qos import measurement_qos

SAMPLE = aerial_sample(n_tracks=3, positions_per_swath=8, seed=12)
MS: list[Measurement] = SAMPLE.measurements


def reference() -> np.ndarray:
    aligner = TrackWindowAligner(AlignerConfig())
    for m in MS:
        aligner.add_measurement(m)
    aligner.finish_track()
    return aligner.corrected_path().T_world_node


@dataclass
class Row:
    name: str
    survived: str
    counted: str
    lost: int | str
    note: str = ''


class Live:
    """One alignment node process and a client that publishes (transient local) to it."""

    def __init__(self, work: Path, dom: int, params: dict[str, object]) -> None:
        self.work, self.dom = work, dom
        self.params = {'diagnostics_period_sec': 0.2, 'warn_throttle_sec': 0.5,
                       'measurement_durability': 'transient_local', **params}
        self.log = work / 'node.log'
        self.proc = start_node_process(dom, self.params, log_path=self.log)
        self.client = NodeClient(dom)
        self.pub = self.client.node.create_publisher(
            Odometry, '/' + topics.MEASUREMENTS, measurement_qos(transient_local=True))
        self._wait()

    def _wait(self) -> None:
        c = self.client
        c.spin_until(lambda: self.pub.get_subscription_count() > 0
                     and all(s.service_is_ready() for s in c.services.values()), 30,
                     'the node', self.proc)

    def restart(self) -> None:
        self.proc = start_node_process(self.dom, self.params, log_path=self.log)
        self.client.diagnostics = {}
        self._wait()

    def send(self, msgs: list[Odometry], wait: bool = True) -> None:
        for msg in msgs:
            self.pub.publish(msg)
        if wait:
            self.pub.wait_for_all_acked(Duration(seconds=10))

    def send_ms(self, ms: list[Measurement], wait: bool = True) -> None:
        self.send([conv.measurement_to_odometry(m) for m in ms], wait)

    def end(self) -> None:
        msg = Odometry()
        msg.child_frame_id = topics.TRACK_END_FRAME
        self.send([msg])

    def final_path(self, n: int, timeout: float = 20.0) -> np.ndarray:
        c = self.client
        try:
            c.spin_until(lambda: c.paths and len(c.paths[-1][1].poses) >= n
                         and c.diag_int('dead_reckoned_nodes') == 0
                         and c.diag_int('nodes') >= n, timeout, 'final path')
        except HarnessTimeout:
            pass
        c.spin_until(lambda: False or True, 1, '')
        return conv.path_msg_to_poses(c.paths[-1][1]) if c.paths else np.zeros((0, 4, 4))

    def rejected(self) -> int:
        return max(self.client.diag_int('rejected'), 0)

    def close(self) -> None:
        self.client.close()
        stop_process(self.proc)


def nodes_lost(ref: np.ndarray, got: np.ndarray) -> int:
    """Reference nodes missing from the path or more than 1 mm away from their reference."""
    k = min(len(ref), len(got))
    err = np.linalg.norm(ref[:k, :3, 3] - got[:k, :3, 3], axis=1) if k else np.zeros(0)
    return len(ref) - k + int(np.count_nonzero(err > 1e-3))


def _msg(m: Measurement, **change) -> Odometry:
    fields = dict(src_id=m.src_id, dst_id=m.dst_id, src_track=m.src_track,
                  dst_track=m.dst_track, z=m.z, cov=m.cov, stamp_ns=m.stamp_ns, kind=m.kind)
    fields.update(change)
    return conv.measurement_to_odometry(Measurement(**fields))


def bad_inputs(at: int) -> list[tuple[str, Odometry]]:
    """(case, message) of bad inputs, each to be sent after MS[:at]."""
    m, last = MS[3], MS[at - 1]
    nan = conv.measurement_to_odometry(m)
    nan.pose.pose.position.x = float('nan')
    neg = conv.measurement_to_odometry(m)
    neg.pose.covariance = list(-np.eye(6).reshape(36))
    frame = conv.measurement_to_odometry(m)
    frame.header.frame_id = 'base_link'
    return [
        ('NaN pose', nan),
        ('negative covariance', neg),
        ('tiny covariance 1e-20 I', _msg(m, cov=1e-20 * np.eye(6))),
        ('huge covariance 1e308', _msg(m, cov=1e308 * np.eye(6))),
        ('self-loop', _msg(m, dst_id=m.src_id, dst_track=m.src_track)),
        ('foreign frame id', frame),
        ('duplicate', conv.measurement_to_odometry(m)),
        ('out of order', _msg(last, src_id=last.dst_id, dst_id=10**9,
                              src_track=last.dst_track, dst_track=last.dst_track - 1,
                              kind='consecutive')),
        ('track id jump 1e6', _msg(last, src_id=last.dst_id, dst_id=last.dst_id + 1,
                                   src_track=last.dst_track, dst_track=1_000_000,
                                   kind='consecutive')),
        ('node id 2^53', _msg(last, src_id=last.dst_id, dst_id=2**53,
                              src_track=last.dst_track, dst_track=last.dst_track,
                              kind='consecutive')),
    ]


def mid() -> int:
    return next(k for k, m in enumerate(MS) if m.dst_track == 1) + 5


# ------------------------------------------------------------------ cases
def case_bad_input(name: str, msg: Odometry) -> Callable[[Path, int, np.ndarray], Row]:
    def run(work: Path, dom: int, ref: np.ndarray) -> Row:
        live = Live(work, dom, {})
        try:
            k = mid()
            live.send_ms(MS[:k])
            live.send([msg])
            live.send_ms(MS[k:])
            live.end()
            got = live.final_path(len(ref))
            counted = live.rejected()
            return Row(name, _alive(live), f'{counted}/1 rejected', nodes_lost(ref, got),
                       live.client.diagnostics.get('last_error', '')[:40])
        finally:
            live.close()
    return run


def _alive(live: Live) -> str:
    return 'yes' if live.proc.poll() is None else f'NO (exit {live.proc.returncode})'


def case_finish_race(work: Path, dom: int, ref: np.ndarray) -> Row:
    live = Live(work, dom, {})
    try:
        k = next(k for k, m in enumerate(MS) if m.dst_track == 2) + 3
        live.send_ms(MS[:k])                        # delivered (acknowledged), still queued
        resp = live.client.call('finish_track')   # must not overtake the queue
        live.send_ms(MS[k:])
        live.end()
        # the service ends track 2 after MS[:k] (as asked): the rest of track 2 is refused
        want = finish_after(k)
        got = live.final_path(len(want))
        return Row('finish_track while measurements are queued', _alive(live),
                   f'{live.rejected()} rejected',
                   nodes_lost(want, got), f'service: {resp.message[:30]}')
    finally:
        live.close()


def finish_after(k: int) -> np.ndarray:
    """The path of an aligner fed MS[:k], then a track end, then the rest (refused ones
    dropped), then the last track end."""
    aligner = TrackWindowAligner(AlignerConfig())
    for j, m in enumerate(MS):
        if j == k:
            aligner.finish_track()
        try:
            aligner.add_measurement(m)
        except InputError:
            pass
    aligner.finish_track()
    return aligner.corrected_path().T_world_node


def case_kill(work: Path, dom: int, ref: np.ndarray) -> Row:
    live = Live(work, dom, {'state_file': str(work / 'state.npz')})
    try:
        k = mid()
        live.send_ms(MS[:k])
        live.send_ms(MS[k:k + 20], wait=False)
        live.proc.send_signal(signal.SIGKILL)
        live.proc.wait(timeout=10)
        live.send_ms(MS[k + 20:], wait=False)          # the publisher keeps going
        live.restart()
        live.end()
        got = live.final_path(len(ref))
        return Row('kill -9 mid-track, publisher continues', _alive(live),
                   f'{live.rejected()} re-deliveries rejected', nodes_lost(ref, got),
                   _recovery_note(live.log))
    finally:
        live.close()


def _recovery_note(log: Path) -> str:
    """The recovery time the restarted node logged."""
    found = re.findall(r'replayed in ([0-9.]+) s', log.read_text() if log.exists() else '')
    return f'recovered in {found[-1]} s' if found else ''


def case_corrupt(what: str) -> Callable[[Path, int, np.ndarray], Row]:
    def run(work: Path, dom: int, ref: np.ndarray) -> Row:
        state = work / 'state.npz'
        live = Live(work, dom, {'state_file': str(state)})
        try:
            k = next(k for k, m in enumerate(MS) if m.dst_track == 2) + 4
            live.send_ms(MS[:k])
            c = live.client
            c.spin_until(lambda: c.diag_int('measurements_accepted') >= k, 20, 'processing')
            live.proc.send_signal(signal.SIGKILL)
            live.proc.wait(timeout=10)
            target = journal_path(state) if what == 'journal header' else state
            data = bytearray(target.read_bytes())
            if what == 'journal header':
                data[:4] = b'XXXX'
            else:
                data[len(data) // 2] ^= 0xFF
            target.write_bytes(bytes(data))
            live.restart()
            live.send_ms(MS[k:])
            live.end()
            got = live.final_path(len(ref))
            aside = [p.name for p in work.iterdir() if '.corrupt-' in p.name]
            return Row(f'corrupt {what}, restart', _alive(live), f'{len(aside)} moved aside',
                       nodes_lost(ref, got))
        finally:
            live.close()
    return run


def case_foreign(kind: str) -> Callable[[Path, int, np.ndarray], Row]:
    def run(work: Path, dom: int, ref: np.ndarray) -> Row:
        victim = work / 'notes.txt'
        victim.write_text('precious\n')
        state = victim
        if kind == 'symlink':
            state = work / 'state.npz'
            state.symlink_to(victim)
        live = Live(work, dom, {'state_file': str(state), 'allow_reset': True})
        try:
            live.send_ms(MS)
            live.client.call('save_state')
            live.client.call('reset')
            live.send_ms([])
            intact = victim.read_text() == 'precious\n'
            return Row(f'state_file is a {kind}', _alive(live),
                       'file intact' if intact else 'FILE CHANGED', 0 if intact else 'file',
                       'persistence off, warned')
        finally:
            live.close()
    return run


def case_reset_by_peer(work: Path, dom: int, ref: np.ndarray) -> Row:
    live = Live(work, dom, {'state_file': str(work / 'state.npz')})
    try:
        live.send_ms(MS)
        resp = live.client.call('reset')
        live.end()
        got = live.final_path(len(ref))
        return Row('~/reset called by a peer', _alive(live),
                   'refused' if not resp.success else 'ACCEPTED', nodes_lost(ref, got))
    finally:
        live.close()


def case_idle_timeout(work: Path, dom: int, ref: np.ndarray) -> Row:
    live = Live(work, dom, {'track_idle_timeout_sec': 1.0})
    try:
        live.send_ms(MS)                               # no end message, no service call
        got = live.final_path(len(ref), timeout=10)
        return Row('last track, no end signal (idle 1 s)', _alive(live), '-',
                   nodes_lost(ref, got))
    finally:
        live.close()


def case_play_early(work: Path, dom: int, ref: np.ndarray) -> Row:
    bag = write_measurement_bag(work / 'bag', MS, None)
    params = {'diagnostics_period_sec': 0.2}
    proc = start_node_process(dom, params, log_path=work / 'node.log')
    time.sleep(0.1)
    env = dict(os.environ, ROS_DOMAIN_ID=str(dom))
    play = subprocess.run([sys.executable, '-m', 'ga_ros.ros.play', str(bag), '--rate', '0'],
                          env=env, capture_output=True, text=True, timeout=120)
    client = NodeClient(dom)
    try:
        c = client
        try:
            c.spin_until(lambda: c.paths and len(c.paths[-1][1].poses) >= len(ref)
                         and c.diag_int('dead_reckoned_nodes') == 0
                         and c.diag_int('nodes') >= len(ref), 20, 'path')
        except HarnessTimeout:
            pass
        got = conv.path_msg_to_poses(c.paths[-1][1]) if c.paths else np.zeros((0, 4, 4))
        return Row('ga-ros play into a node started 0.1 s before',
                   'yes' if proc.poll() is None else 'NO',
                   f"{c.diag_int('measurements_received')}/{len(MS)} received",
                   nodes_lost(ref, got), f'play exit {play.returncode}')
    finally:
        client.close()
        stop_process(proc)


def case_sigterm_startup(work: Path, dom: int, ref: np.ndarray) -> Row:
    log = work / 'node.log'
    proc = start_node_process(dom, {}, log_path=log)
    time.sleep(0.8)
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(timeout=20)
    text = log.read_text() if log.exists() else ''
    return Row('SIGTERM during start-up', f'clean exit {code}' if 'Traceback' not in text
               else 'TRACEBACK', '-', 0)


CASES: dict[str, Callable[[Path, int, np.ndarray], Row]] = {}


def _register() -> None:
    for name, msg in bad_inputs(mid()):
        CASES[name] = case_bad_input(name, msg)
    CASES.update({
        'finish race': case_finish_race,
        'kill': case_kill,
        'corrupt journal': case_corrupt('journal header'),
        'corrupt snapshot': case_corrupt('snapshot'),
        'foreign state': case_foreign('foreign text file'),
        'symlink state': case_foreign('symlink'),
        'reset by peer': case_reset_by_peer,
        'idle timeout': case_idle_timeout,
        'play early': case_play_early,
        'sigterm': case_sigterm_startup,
    })


def main(argv: list[str] | None = None) -> int:
    _register()
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument('--only', nargs='+', default=[], choices=sorted(CASES), metavar='CASE')
    args = p.parse_args(argv)
    ref = reference()
    rows = []
    base = 200 + os.getpid() % 10  # above the 40..189 the test suites use
    t0 = time.monotonic()
    for k, (name, run) in enumerate(CASES.items()):
        if args.only and name not in args.only:
            continue
        with tempfile.TemporaryDirectory(prefix='ga_fault_') as tmp:
            try:
                row = run(Path(tmp), base + k, ref)
            except Exception as exc:  # noqa: BLE001 - a failed case is a row, not a crash
                row = Row(name, 'ERROR', '-', '?', f'{type(exc).__name__}: {exc}'[:60])
        rows.append(row)
        print(f'  {row.name}: {row.survived}, {row.counted}, lost {row.lost}', flush=True)
    print(f'\n{len(MS)} measurements, {len(ref)} nodes per run; '
          f'{time.monotonic() - t0:.0f} s\n')
    print('| case | survived | counted | nodes lost | note |')
    print('|---|---|---|---|---|')
    for r in rows:
        print(f'| {r.name} | {r.survived} | {r.counted} | {r.lost} | {r.note} |')
    return 0 if all(r.lost == 0 for r in rows) else 1


if __name__ == '__main__':
    sys.exit(main())
