"""Fault cases of crashes and state files: kills and SIGTERM during play, kills during recovery,
damaged snapshots and journals, a full disk, unusable and foreign state paths."""

from __future__ import annotations

import signal

import numpy as np
from nav_msgs.msg import Odometry

from ga_ros.pipeline.journal import default_state_file, journal_path
from ga_ros.ros.fault_catalogue.harness import (
    LEVELS,
    Live,
    mount_tmpfs,
    recovery_note,
    start_play,
    umount,
)
from ga_ros.ros.fault_catalogue.survey import Case, Ctx, Row, nodes_kept
from ga_ros.ros.harness import start_node_process
from ga_ros.ros.qos import measurement_qos


def killed_during_play(ctx: Ctx, name: str, params: dict[str, object], sig: int,
                        again_during_recovery: bool = False) -> Row:
    """Play the bag into the node, stop it with ``sig`` a third of the way in, restart it
    (optionally killed once more as soon as it logs that it restores the state), let play
    deliver the rest."""
    live = Live(ctx, params)
    player = start_play(ctx, '--delivery-timeout', '300')
    try:
        live.wait_accepted(len(ctx.ms) // 3)
        code = live.kill(sig)
        clean = 'clean exit' if sig != signal.SIGKILL and code == 0 else f'exit {code}'
        if again_during_recovery:
            n_lines = live.log.read_text(errors='replace').count('restoring the state')
            live.proc = start_node_process(ctx.dom, live.params, log_path=live.log)
            live.client.expect_restart()
            live.client.spin_until(
                lambda: live.log.read_text(errors='replace').count('restoring the state')
                > n_lines, 120, 'the restarted node to log that it restores the state',
                live.proc)
            live.kill()                                   # while it restores
        recover_s = live.restart()
        out, _ = player.communicate(timeout=ctx.remaining(1800))
        got = live.final_path(ctx.survey.n_nodes)
        return Row(name, f'{live.survived()}; {clean}', f'play exit {player.returncode}',
                   ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got), recover_s,
                   recovery_note(live.log))
    finally:
        if player.poll() is None:
            player.kill()
            player.communicate()
        live.close()


def case_kill_defaults(ctx: Ctx) -> Row:
    return killed_during_play(ctx, 'kill -9 during play, defaults (state under ROS_HOME)', {},
                               signal.SIGKILL)


def case_kill_state(ctx: Ctx) -> Row:
    return killed_during_play(ctx, 'kill -9 during play, state file',
                               {'state_file': str(ctx.work / 'state')}, signal.SIGKILL)


def case_kill_recovery(ctx: Ctx) -> Row:
    return killed_during_play(ctx, 'kill -9 during play and again during recovery',
                               {'state_file': str(ctx.work / 'state')}, signal.SIGKILL,
                               again_during_recovery=True)


def case_sigterm(ctx: Ctx) -> Row:
    return killed_during_play(ctx, 'SIGTERM during play (updates running), defaults', {},
                               signal.SIGTERM)


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
                       recovery_note(live.log))
        finally:
            live.close()
    return run


def case_disk_full(ctx: Ctx) -> Row:
    """The state file on a tmpfs too small for the journal: writes fail, counted (ERROR
    diagnostics); the estimate stays complete; a restart on the full disk recovers the
    journal's records and gets the rest again from the publisher's history."""
    disk = ctx.work / 'disk'
    size_kb = max(64, len(ctx.ms) * 381 // 1024 // 3)   # about a third of the journal
    if not mount_tmpfs(disk, f'size={size_kb}k'):
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
                       nodes_kept(ctx.survey.T_ref, got), recover_s, recovery_note(live.log))
        finally:
            live.close()
    finally:
        umount(disk)


def case_state_path(kind: str) -> Case:
    def run(ctx: Ctx) -> Row:
        if kind == 'read-only directory':
            where = ctx.work / 'ro'
            if not mount_tmpfs(where, 'ro,size=64k'):
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
                umount(ctx.work / 'ro')
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


def case_ended_snapshot_lost(ctx: Ctx) -> Row:
    """Defaults (the state under ``$ROS_HOME``): the whole survey and the end of input, then
    ``kill -9``, the snapshot emptied and the publisher gone (no history to re-deliver): the
    restarted node has only its journal, which holds the track end of the end of input."""
    live = Live(ctx, {})
    try:
        live.send_ms(ctx.ms)
        live.end()
        live.wait_accepted(len(ctx.ms), timeout=1800)
        before = nodes_kept(ctx.survey.T_ref, live.final_path(ctx.survey.n_nodes, 600))
        live.kill()
        state = default_state_file('/', 'alignment_node')  # ROS_HOME: the case's (run_case)
        state.write_bytes(b'')
        node, topic = live.client.node, live.pub.topic_name  # nothing is re-delivered: a
        node.destroy_publisher(live.pub)                      # new publisher, no history
        live.pub = live.client.pub = node.create_publisher(
            Odometry, topic, measurement_qos(transient_local=True))
        live.client.paths.clear()
        recover_s = live.restart()
        got = live.final_path(ctx.survey.n_nodes)
        return Row('kill -9 after the end of input, snapshot emptied, no history, defaults',
                   live.survived(), f'persistence '
                   f'{live.client.diagnostics.get("persistence", "?").split(":")[0]}',
                   ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got), recover_s,
                   f'{before} kept before the kill; {recovery_note(live.log)}')
    finally:
        live.close()
