"""Fault catalogue: bad inputs, kills, full disks, damaged files, hostile peers and floods,
injected into LIVE alignment nodes started with their default settings (``ga-ros bench faults``).

Each case starts ``alignment_node`` as a process (own ``ROS_DOMAIN_ID``), feeds it a survey
(a small simulated one, or a measurements bag such as ``bags/aerial_measurements``) with the
fault injected, by a transient-local publisher or by ``ga-ros play``, ends the input with the
end-of-input message and compares the final published path with :class:`TrackWindowAligner`
fed the clean measurements. One :class:`Row` per case: the node survived (alive, or exited
cleanly where the fault stops it; no traceback in its log), what it counted, the nodes
expected and the nodes kept (within 1 mm of the reference), and the time to recover (restart
until the node holds again every node it held before the fault).

Nodes lost because a measurement never arrives at all (a gap) are not caught here: the
publishers keep their history, so a restarted node gets everything again.
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.duration import Duration

from ga_ros import topics
from ga_ros.core.measurement import Measurement
from ga_ros.core.window import AlignerConfig, TrackWindowAligner
from ga_ros.errors import InputError
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import odometry_to_measurement
from ga_ros.pipeline.journal import journal_path
from ga_ros.replay.samples import aerial_sample, write_measurement_bag
from ga_ros.ros import conversions as conv
from ga_ros.ros.harness import HarnessTimeout, NodeClient, start_node_process, stop_process

#: Names of the diagnostics levels.
LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
#: Diagnostics often enough for the waits; everything else at the node's defaults.
BASE_PARAMS: dict[str, object] = {'diagnostics_period_sec': 0.2}


@dataclass
class Survey:
    """The measurements of a case, the bag that holds them and the reference path.

    Attributes
    ----------
    measurements : in publication order.
    bag : a measurements bag of them (for the cases that play it).
    T_ref : ``(n, 4, 4)`` reference path, ``T_world_node``: the aligner fed every measurement,
        then a track end.
    """

    measurements: list[Measurement]
    bag: Path
    T_ref: np.ndarray = field(repr=False)

    @property
    def n_nodes(self) -> int:
        return len(self.T_ref)


def reference(ms: list[Measurement]) -> np.ndarray:
    """The path of an aligner (defaults) fed ``ms`` then a track end."""
    aligner = TrackWindowAligner(AlignerConfig())
    aligner.add_measurements(ms)
    aligner.finish_track()
    return aligner.corrected_path().T_world_node


def small_survey(work: Path) -> Survey:
    """A simulated survey of 3 tracks (48 nodes, about 220 measurements)."""
    ms = aerial_sample(n_tracks=3, positions_per_swath=8, seed=12).measurements
    return Survey(ms, write_measurement_bag(work / 'small_bag', ms, None), reference(ms))


def bag_survey(bag: Path) -> Survey:
    """The measurements of a bag's ``/ga/measurements`` topic."""
    with BagReader(bag) as reader:
        ms = [odometry_to_measurement(bm.msg)
              for bm in reader.messages(['/' + topics.MEASUREMENTS])]
    return Survey(ms, Path(bag), reference(ms))


@dataclass
class Row:
    """One case: survived, counted, nodes expected / kept, time to recover (s), note."""

    name: str
    survived: str
    counted: str
    expected: int
    kept: int
    recover_s: float | None = None
    note: str = ''

    @property
    def lost(self) -> int:
        return self.expected - self.kept


@dataclass
class Ctx:
    """What a case gets: its work directory, ROS domain and survey."""

    work: Path
    dom: int
    survey: Survey

    @property
    def ms(self) -> list[Measurement]:
        return self.survey.measurements


def nodes_kept(ref: np.ndarray, got: np.ndarray) -> int:
    """Reference nodes present in the path within 1 mm of their reference position."""
    k = min(len(ref), len(got))
    if not k:
        return 0
    err = np.linalg.norm(ref[:k, :3, 3] - got[:k, :3, 3], axis=1)
    return int(np.count_nonzero(err <= 1e-3))


def _traceback(log: Path) -> bool:
    return log.exists() and 'Traceback' in log.read_text(errors='replace')


class Live:
    """One alignment node process and a client whose transient-local publisher keeps the
    whole history (a restarted node gets it again)."""

    def __init__(self, ctx: Ctx, params: dict[str, object] | None = None) -> None:
        self.ctx = ctx
        self.params = {**BASE_PARAMS, **(params or {})}
        self.log = ctx.work / 'node.log'
        self.proc = start_node_process(ctx.dom, self.params, log_path=self.log)
        self.client = NodeClient(ctx.dom)
        self.pub = self.client.pub
        self.wait()

    def wait(self, timeout: float = 60.0) -> None:
        c = self.client
        c.spin_until(lambda: self.pub.get_subscription_count() > 0
                     and all(s.service_is_ready() for s in c.services.values()), timeout,
                     'the node', self.proc)

    def kill(self, sig: int = signal.SIGKILL) -> int:
        self.proc.send_signal(sig)
        return self.proc.wait(timeout=60)

    def restart(self) -> float:
        """Start the node again; returns the seconds until it holds every node it held when
        the last diagnostics before the restart were received."""
        end = time.monotonic() + 0.5   # take what the stopped node sent before it stopped
        while time.monotonic() < end:
            self.client.executor.spin_once(timeout_sec=0.05)
        before = max(self.client.diag_int('nodes'), 0)
        t0 = time.monotonic()
        self.proc = start_node_process(self.ctx.dom, self.params, log_path=self.log)
        self.client.diagnostics = {}
        self.wait()
        self.client.spin_until(lambda: self.client.diag_int('nodes') >= before, 1800,
                               'the recovered nodes', self.proc)
        return time.monotonic() - t0

    def send(self, msgs: list[Odometry], wait: bool = True) -> None:
        for k, msg in enumerate(msgs):
            self.pub.publish(msg)
            if k % 500 == 499:
                self.client.executor.spin_once(timeout_sec=0.0)
        if wait:
            self.pub.wait_for_all_acked(Duration(seconds=60))

    def send_ms(self, ms: list[Measurement], wait: bool = True) -> None:
        self.send([conv.measurement_to_odometry(m) for m in ms], wait)

    def end(self) -> None:
        msg = Odometry()
        msg.child_frame_id = topics.TRACK_END_FRAME
        self.send([msg])

    def wait_accepted(self, n: int, timeout: float = 300.0) -> None:
        c = self.client
        c.spin_until(lambda: c.diag_int('measurements_accepted') >= n, timeout,
                     f'{n} accepted', self.proc)

    def final_path(self, n: int, timeout: float = 120.0) -> np.ndarray:
        c = self.client
        try:
            c.spin_until(lambda: c.paths and len(c.paths[-1][1].poses) >= n
                         and c.diag_int('dead_reckoned_nodes') == 0
                         and c.diag_int('nodes') >= n, timeout, 'final path')
        except HarnessTimeout:
            pass
        return conv.path_msg_to_poses(c.paths[-1][1]) if c.paths else np.zeros((0, 4, 4))

    def survived(self) -> str:
        if _traceback(self.log):
            return 'TRACEBACK'
        return 'yes' if self.proc.poll() is None else f'NO (exit {self.proc.returncode})'

    def close(self) -> None:
        self.client.close()
        stop_process(self.proc)


def _msg(m: Measurement, **change) -> Odometry:
    fields = dict(src_id=m.src_id, dst_id=m.dst_id, src_track=m.src_track,
                  dst_track=m.dst_track, z=m.z, cov=m.cov, stamp_ns=m.stamp_ns, kind=m.kind)
    fields.update(change)
    return conv.measurement_to_odometry(Measurement(**fields))


def mid(ms: list[Measurement]) -> int:
    """An index inside track 1."""
    return next(k for k, m in enumerate(ms) if m.dst_track == 1) + 5


def bad_inputs(ms: list[Measurement]) -> list[tuple[str, Odometry]]:
    """(case, message) of bad inputs, each to be sent after ``ms[:mid(ms)]``."""
    m, last = ms[3], ms[mid(ms) - 1]
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


Case = Callable[[Ctx], Row]


# ------------------------------------------------------------------ bad inputs, races
def case_bad_input(name: str, pick: int) -> Case:
    def run(ctx: Ctx) -> Row:
        msg = bad_inputs(ctx.ms)[pick][1]
        live = Live(ctx)
        try:
            k = mid(ctx.ms)
            live.send_ms(ctx.ms[:k])
            live.send([msg])
            live.send_ms(ctx.ms[k:])
            live.end()
            got = live.final_path(ctx.survey.n_nodes)
            return Row(name, live.survived(), f'{max(live.client.diag_int("rejected"), 0)}/1 '
                       'rejected', ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got),
                       note=live.client.diagnostics.get('last_error', '')[:40])
        finally:
            live.close()
    return run


def finish_after(ms: list[Measurement], k: int) -> np.ndarray:
    """The path of an aligner fed ms[:k], a track end, the rest (refused ones dropped), then
    the last track end."""
    aligner = TrackWindowAligner(AlignerConfig())
    for j, m in enumerate(ms):
        if j == k:
            aligner.finish_track()
        try:
            aligner.add_measurement(m)
        except InputError:
            pass
    aligner.finish_track()
    return aligner.corrected_path().T_world_node


def case_finish_race(ctx: Ctx) -> Row:
    """Allowed ``~/finish_track`` while the measurements before it are still queued: it
    applies after them (the rest of the track is then refused, as asked)."""
    live = Live(ctx, {'allow_finish_track': True})
    try:
        k = next(k for k, m in enumerate(ctx.ms) if m.dst_track == 2) + 3
        live.send_ms(ctx.ms[:k])
        resp = live.client.call('finish_track')
        live.send_ms(ctx.ms[k:])
        live.end()
        want = finish_after(ctx.ms, k)
        got = live.final_path(len(want))
        return Row('allowed finish_track while measurements are queued', live.survived(),
                   f'{max(live.client.diag_int("rejected"), 0)} rejected', len(want),
                   nodes_kept(want, got), note=f'service: {resp.message[:30]}')
    finally:
        live.close()


def case_hostile_services(ctx: Ctx) -> Row:
    """A peer calls ``~/finish_track`` mid-track and ``~/load_state`` (defaults: refused)."""
    live = Live(ctx, {'state_file': str(ctx.work / 'state'), 'autosave': False})
    try:
        k = mid(ctx.ms)
        live.send_ms(ctx.ms[:k])
        saved = live.client.call('save_state')
        live.send_ms(ctx.ms[k:k + 10])
        fin = live.client.call('finish_track')
        load = live.client.call('load_state')
        live.send_ms(ctx.ms[k + 10:])
        live.end()
        got = live.final_path(ctx.survey.n_nodes)
        refused = sum(not r.success for r in (fin, load))
        return Row('peer calls ~/finish_track mid-track and ~/load_state', live.survived(),
                   f'{refused}/2 refused', ctx.survey.n_nodes,
                   nodes_kept(ctx.survey.T_ref, got), note=f'save {saved.success}')
    finally:
        live.close()


def case_reset_by_peer(ctx: Ctx) -> Row:
    live = Live(ctx, {'state_file': str(ctx.work / 'state.npz')})
    try:
        live.send_ms(ctx.ms)
        resp = live.client.call('reset')
        live.end()
        got = live.final_path(ctx.survey.n_nodes)
        return Row('~/reset called by a peer', live.survived(),
                   'refused' if not resp.success else 'ACCEPTED', ctx.survey.n_nodes,
                   nodes_kept(ctx.survey.T_ref, got))
    finally:
        live.close()


def case_idle_timeout(ctx: Ctx) -> Row:
    live = Live(ctx, {'track_idle_timeout_sec': 1.0})
    try:
        live.send_ms(ctx.ms)                          # no end message, no service call
        got = live.final_path(ctx.survey.n_nodes, timeout=30)
        return Row('last track, no end signal (idle 1 s)', live.survived(), '-',
                   ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got))
    finally:
        live.close()


# ------------------------------------------------------------------ kills and restarts
def _play(ctx: Ctx, *args: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(ctx.dom))
    return subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.play', str(ctx.survey.bag),
                             '--rate', '0', *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def _killed_during_play(ctx: Ctx, name: str, params: dict[str, object], sig: int,
                        again_during_recovery: bool = False) -> Row:
    """Play the bag into the node, stop it with ``sig`` a third of the way in, restart it
    (optionally killed once more as soon as it logs that it restores the state), let play
    deliver the rest."""
    live = Live(ctx, params)
    player = _play(ctx, '--delivery-timeout', '300')
    try:
        live.wait_accepted(len(ctx.ms) // 3)
        code = live.kill(sig)
        clean = 'clean exit' if sig != signal.SIGKILL and code == 0 else f'exit {code}'
        if again_during_recovery:
            n_lines = live.log.read_text(errors='replace').count('restoring the state')
            live.proc = start_node_process(ctx.dom, live.params, log_path=live.log)
            end = time.monotonic() + 120
            while (live.log.read_text(errors='replace').count('restoring the state') == n_lines
                   and time.monotonic() < end):
                time.sleep(0.01)
            live.kill()                                   # while it restores
        recover_s = live.restart()
        out, _ = player.communicate(timeout=1800)
        got = live.final_path(ctx.survey.n_nodes)
        return Row(name, f'{live.survived()}; {clean}', f'play exit {player.returncode}',
                   ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got), recover_s,
                   _recovery_note(live.log))
    finally:
        if player.poll() is None:
            player.kill()
            player.communicate()
        live.close()


def case_kill_defaults(ctx: Ctx) -> Row:
    return _killed_during_play(ctx, 'kill -9 during play, defaults (no state file)', {},
                               signal.SIGKILL)


def case_kill_state(ctx: Ctx) -> Row:
    return _killed_during_play(ctx, 'kill -9 during play, state file',
                               {'state_file': str(ctx.work / 'state')}, signal.SIGKILL)


def case_kill_recovery(ctx: Ctx) -> Row:
    return _killed_during_play(ctx, 'kill -9 during play and again during recovery',
                               {'state_file': str(ctx.work / 'state')}, signal.SIGKILL,
                               again_during_recovery=True)


def case_sigterm(ctx: Ctx) -> Row:
    return _killed_during_play(ctx, 'SIGTERM during play (updates running), defaults', {},
                               signal.SIGTERM)


def _recovery_note(log: Path) -> str:
    """How the restarted node resumed (its log line)."""
    found = re.findall(r'\(((?:snapshot|journal)[^)]*replayed in [0-9.]+ s)',
                       log.read_text(errors='replace') if log.exists() else '')
    return found[-1] if found else ''


def case_damaged_snapshot(what: str) -> Case:
    def run(ctx: Ctx) -> Row:
        state = ctx.work / 'state'
        live = Live(ctx, {'state_file': str(state)})
        try:
            k = 2 * len(ctx.ms) // 3
            live.send_ms(ctx.ms[:k])
            live.wait_accepted(k)
            live.kill()
            size = state.stat().st_size
            if what == 'empty':
                state.write_bytes(b'')
            elif what == 'random':
                state.write_bytes(np.random.default_rng(1).bytes(size))
            elif what == 'truncated':
                state.write_bytes(state.read_bytes()[:size // 2])
            else:                                        # the journal's header
                data = bytearray(journal_path(state).read_bytes())
                data[:4] = b'XXXX'
                journal_path(state).write_bytes(bytes(data))
            recover_s = live.restart()
            live.send_ms(ctx.ms[k:])
            live.end()
            got = live.final_path(ctx.survey.n_nodes)
            aside = [p.name for p in ctx.work.iterdir() if '.corrupt-' in p.name]
            label = ('damaged journal header, intact snapshot' if what == 'header'
                     else f'{what} snapshot, intact journal')
            return Row(f'{label}, restart', live.survived(),
                       f'{len(aside)} moved aside; persistence '
                       f'{live.client.diagnostics.get("persistence", "?").split(":")[0]}',
                       ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got), recover_s,
                       _recovery_note(live.log))
        finally:
            live.close()
    return run


# ------------------------------------------------------------------ state paths
def _mount_tmpfs(where: Path, options: str) -> bool:
    """Mount a tmpfs (needs root); False if that is not possible here."""
    where.mkdir(parents=True, exist_ok=True)
    res = subprocess.run(['mount', '-t', 'tmpfs', '-o', options, 'tmpfs', str(where)],
                         capture_output=True)
    return res.returncode == 0


def _umount(where: Path) -> None:
    subprocess.run(['umount', '-l', str(where)], capture_output=True)


def case_disk_full(ctx: Ctx) -> Row:
    """The state file on a tmpfs too small for the journal: writes fail, counted (ERROR
    diagnostics); the estimate stays complete; a restart on the full disk recovers the
    journal's records and gets the rest again from the publisher's history."""
    disk = ctx.work / 'disk'
    size_kb = max(64, len(ctx.ms) * 381 // 1024 // 3)   # about a third of the journal
    if not _mount_tmpfs(disk, f'size={size_kb}k'):
        return Row('disk full (tmpfs)', 'skipped', 'mount failed (needs root)', 0, 0)
    try:
        live = Live(ctx, {'state_file': str(disk / 'state')})
        try:
            live.send_ms(ctx.ms)
            live.end()
            got = live.final_path(ctx.survey.n_nodes)
            kept_live = nodes_kept(ctx.survey.T_ref, got)
            c = live.client
            c.spin_until(lambda: c.diag_int('persistence_errors') > 0, 10, 'errors counted')
            errors, level = c.diag_int('persistence_errors'), LEVELS.get(c.diag_level, '?')
            live.kill()
            recover_s = live.restart()
            live.end()
            got = live.final_path(ctx.survey.n_nodes)
            return Row(f'disk full ({size_kb} kB tmpfs), kill -9, restart on the full disk',
                       live.survived(), f'{errors} write errors {level}; '
                       f'{kept_live} nodes before the kill', ctx.survey.n_nodes,
                       nodes_kept(ctx.survey.T_ref, got), recover_s, _recovery_note(live.log))
        finally:
            live.close()
    finally:
        _umount(disk)


def case_state_path(kind: str) -> Case:
    def run(ctx: Ctx) -> Row:
        if kind == 'read-only directory':
            where = ctx.work / 'ro'
            if not _mount_tmpfs(where, 'ro,size=64k'):
                return Row(f'state file in a {kind}', 'skipped', 'mount failed', 0, 0)
            state = where / 'state'
        else:
            (ctx.work / 'file').write_text('x')
            state = ctx.work / 'file' / 'state'
        try:
            live = Live(ctx, {'state_file': str(state)})
            try:
                live.send_ms(ctx.ms)
                live.end()
                got = live.final_path(ctx.survey.n_nodes)
                log = live.log.read_text(errors='replace')
                lines = log.count('WITHOUT persistence')
                return Row(f'state file in a {kind}', live.survived(),
                           f'{lines} log line; persistence '
                           f'{live.client.diagnostics.get("persistence", "?").split(":")[0]}',
                           ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got))
            finally:
                live.close()
        finally:
            if kind == 'read-only directory':
                _umount(ctx.work / 'ro')
    return run


def case_foreign(kind: str) -> Case:
    def run(ctx: Ctx) -> Row:
        victim = ctx.work / 'notes.txt'
        victim.write_text('precious\n')
        state = victim
        if kind == 'symlink':
            state = ctx.work / 'state.npz'
            state.symlink_to(victim)
        live = Live(ctx, {'state_file': str(state), 'allow_reset': True})
        try:
            live.send_ms(ctx.ms)
            live.client.call('save_state')
            live.client.call('reset')
            intact = victim.read_text() == 'precious\n'
            return Row(f'state_file is a {kind}', live.survived(),
                       'file intact' if intact else 'FILE CHANGED', 1, int(intact),
                       note='persistence off, warned')
        finally:
            live.close()
    return run


# ------------------------------------------------------------------ floods, start-up
def case_flood_frame_ids(ctx: Ctx) -> Row:
    """50 messages with a 1 MB frame id between the survey's: rejected, the error text in
    ``/diagnostics`` bounded."""
    live = Live(ctx)
    try:
        k = mid(ctx.ms)
        bad = conv.measurement_to_odometry(ctx.ms[3])
        bad.header.frame_id = 'x' * 1_000_000
        live.send_ms(ctx.ms[:k])
        live.send([bad] * 50)
        live.send_ms(ctx.ms[k:])
        live.end()
        got = live.final_path(ctx.survey.n_nodes)
        err = live.client.diagnostics.get('last_error', '')
        return Row('50 messages with a 1 MB frame id', live.survived(),
                   f'{max(live.client.diag_int("rejected"), 0)}/50 rejected, last_error '
                   f'{len(err)} chars', ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got))
    finally:
        live.close()


def case_flood_queue(ctx: Ctx) -> Row:
    """20,000 copies of one measurement into a 1,000-deep subscription queue, then the
    survey: what the full queue dropped is counted (received + lost = sent)."""
    n_flood = 20_000
    live = Live(ctx, {'measurement_queue_depth': 1000})
    try:
        k = mid(ctx.ms)
        live.send_ms(ctx.ms[:k])
        live.wait_accepted(k)
        dup = conv.measurement_to_odometry(ctx.ms[3])
        live.send([dup] * n_flood)
        live.send_ms(ctx.ms[k:])
        live.end()
        got = live.final_path(ctx.survey.n_nodes)
        c = live.client
        sent = len(ctx.ms) + n_flood + 1
        c.spin_until(lambda: c.diag_int('measurements_received') > 0, 5, 'diagnostics')
        received = c.diag_int('measurements_received') + 1            # + the end message
        lost = c.diag_int('measurements_lost_in_queue')
        return Row(f'flood: {n_flood} duplicates into a 1,000-deep queue', live.survived(),
                   f'{received} received + {lost} counted lost of {sent} sent',
                   ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got))
    finally:
        live.close()


def case_play_early(ctx: Ctx) -> Row:
    log = ctx.work / 'node.log'
    proc = start_node_process(ctx.dom, BASE_PARAMS, log_path=log)
    time.sleep(0.1)
    play = _play(ctx)
    out, _ = play.communicate(timeout=1800)
    client = NodeClient(ctx.dom)
    try:
        c = client
        n = ctx.survey.n_nodes
        try:
            c.spin_until(lambda: c.paths and len(c.paths[-1][1].poses) >= n
                         and c.diag_int('dead_reckoned_nodes') == 0
                         and c.diag_int('nodes') >= n, 60, 'path')
        except HarnessTimeout:
            pass
        got = conv.path_msg_to_poses(c.paths[-1][1]) if c.paths else np.zeros((0, 4, 4))
        return Row('ga-ros play into a node started 0.1 s before',
                   'yes' if proc.poll() is None and not _traceback(log) else 'NO',
                   f"{c.diag_int('measurements_received')}/{len(ctx.ms)} received", n,
                   nodes_kept(ctx.survey.T_ref, got), note=f'play exit {play.returncode}')
    finally:
        client.close()
        stop_process(proc)


def case_sigterm_startup(ctx: Ctx) -> Row:
    log = ctx.work / 'node.log'
    proc = start_node_process(ctx.dom, {}, log_path=log)
    time.sleep(0.8)
    proc.send_signal(signal.SIGTERM)
    code = proc.wait(timeout=20)
    return Row('SIGTERM during start-up', 'TRACEBACK' if _traceback(log)
               else f'clean exit {code}', '-', 0, 0)


def catalogue() -> dict[str, Case]:
    """Every case by its short name, in the order of the table."""
    cases: dict[str, Case] = {}
    names = ['nan', 'negative-cov', 'tiny-cov', 'huge-cov', 'self-loop', 'foreign-frame',
             'duplicate', 'out-of-order', 'track-jump', 'node-id-2^53']
    labels = ['NaN pose', 'negative covariance', 'tiny covariance 1e-20 I',
              'huge covariance 1e308', 'self-loop', 'foreign frame id', 'duplicate',
              'out of order', 'track id jump 1e6', 'node id 2^53']
    for k, (name, label) in enumerate(zip(names, labels)):
        cases[name] = case_bad_input(label, k)
    cases.update({
        'kill-defaults': case_kill_defaults,
        'kill-state': case_kill_state,
        'kill-recovery': case_kill_recovery,
        'sigterm-update': case_sigterm,
        'snapshot-empty': case_damaged_snapshot('empty'),
        'snapshot-random': case_damaged_snapshot('random'),
        'snapshot-truncated': case_damaged_snapshot('truncated'),
        'journal-header': case_damaged_snapshot('header'),
        'disk-full': case_disk_full,
        'read-only-dir': case_state_path('read-only directory'),
        'bogus-path': case_state_path('path under a regular file'),
        'foreign-state': case_foreign('foreign text file'),
        'symlink-state': case_foreign('symlink'),
        'hostile-services': case_hostile_services,
        'reset-by-peer': case_reset_by_peer,
        'finish-race': case_finish_race,
        'idle-timeout': case_idle_timeout,
        'flood-frame-ids': case_flood_frame_ids,
        'flood-queue': case_flood_queue,
        'play-early': case_play_early,
        'sigterm-startup': case_sigterm_startup,
    })
    return cases


def run_case(name: str, case: Case, survey: Survey | None, dom: int,
             bag: Path | None = None) -> Row:
    """Run one case in a fresh temporary directory (a failing case is a row, not a crash);
    ``survey`` None: the small simulated one, written in that directory."""
    with tempfile.TemporaryDirectory(prefix='ga_fault_') as tmp:
        work = Path(tmp)
        try:
            return case(Ctx(work, dom, survey or small_survey(work)))
        except Exception as exc:  # noqa: BLE001 - a failed case is a row
            return Row(name, 'ERROR', '-', 0, 0, note=f'{type(exc).__name__}: {exc}'[:80])


def table(rows: list[Row]) -> str:
    """The Markdown table of the rows."""
    lines = ['| case | survived | counted | nodes expected | nodes kept | lost | '
             'recover (s) | note |', '|---|---|---|---:|---:|---:|---:|---|']
    for r in rows:
        rec = f'{r.recover_s:.1f}' if r.recover_s is not None else '-'
        lines.append(f'| {r.name} | {r.survived} | {r.counted} | {r.expected} | {r.kept} | '
                     f'{r.lost} | {rec} | {r.note} |')
    return '\n'.join(lines)
