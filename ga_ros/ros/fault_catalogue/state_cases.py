"""Fault cases of the default state (``$ROS_HOME/ga_ros/<namespace>/<name>/state``): a publisher
whose history is shorter than the survey, two nodes configured onto one state, a full disk that
gets space again, and another survey played into a node holding a finished one."""

from __future__ import annotations

import signal
import subprocess
import time

from nav_msgs.msg import Odometry

from ga_ros.ros.deadlines import patience
from ga_ros.ros.fault_catalogue.harness import Live, mount_tmpfs, recovery_note, start_play, umount
from ga_ros.ros.fault_catalogue.survey import Ctx, Row, nodes_kept, small_survey
from ga_ros.ros.harness import HarnessTimeout, start_node_process, stop_process
from ga_ros.ros.qos import measurement_qos


def bounded_publisher(live: Live, depth: int) -> None:
    """Replace the client's measurement publisher by one keeping only its last ``depth``
    messages for a late or restarted subscriber (as ``vo_node``'s bounded history)."""
    node, topic = live.client.node, live.pub.topic_name
    node.destroy_publisher(live.pub)
    live.pub = live.client.pub = node.create_publisher(
        Odometry, topic, measurement_qos(depth, transient_local=True))
    live.wait()


def persistence(live: Live) -> str:
    """The node's ``persistence`` diagnostic value, its first word."""
    return live.client.diagnostics.get('persistence', '?').split(':')[0]


def case_bounded_history(ctx: Ctx) -> Row:
    """Defaults; the publisher keeps only the last half of the survey; ``kill -9`` at two
    thirds; the rest is published while the node is down; the restarted node gets the last
    half again: what is older lives only in the node's default state."""
    n = len(ctx.ms)
    depth, k = n // 2, 2 * n // 3
    live = Live(ctx, {})
    try:
        bounded_publisher(live, depth)
        for a in range(0, k, depth // 2):        # acknowledged in chunks within the history
            live.send_ms(ctx.ms[a:min(a + depth // 2, k)])
        live.wait_accepted(k)
        live.kill()
        live.send_ms(ctx.ms[k:], wait=False)     # nobody listens: kept in the history
        recover_s = live.restart()
        live.end()
        got = live.final_path(ctx.survey.n_nodes)
        c = live.client
        return Row(f'publisher history {depth} of {n} measurements, kill -9 at {k}, defaults',
                   live.survived(), f'{max(c.diag_int("rejected/duplicate"), 0)} duplicates; '
                   f'persistence {persistence(live)}', ctx.survey.n_nodes,
                   nodes_kept(ctx.survey.T_ref, got), recover_s, recovery_note(live.log))
    finally:
        live.close()


def case_two_nodes_one_state(ctx: Ctx) -> Row:
    """Two alignment nodes of the same name and ``ROS_HOME`` (so the same default state): the
    second is refused the state's lock (one error line naming the holder) and runs without
    persistence; the first keeps every node, through a ``kill -9`` and restart too."""
    live = Live(ctx, {})
    second_log = ctx.work / 'second.log'
    live.client.diag_seq_drops_allowed = None    # two nodes on the domain: the point here
    second = start_node_process(ctx.dom, {'diagnostics_period_sec': 0.2},
                                log_path=second_log)
    try:
        end = time.monotonic() + patience(60)
        text = ''
        while second.poll() is None and time.monotonic() < end:
            text = second_log.read_text(errors='replace') if second_log.exists() else ''
            if 'listening on' in text:
                break
            live.client.executor.spin_once(timeout_sec=0.05)
        refused = 'in use by pid' in text and 'WITHOUT persistence' in text
        stop_process(second)
        live.client.diag_seq_drops_allowed = live.client.diag_seq_drops
        clean = second.returncode == 0 and 'Traceback' not in second_log.read_text(
            errors='replace')
        k = len(ctx.ms) // 2
        live.send_ms(ctx.ms[:k])
        live.wait_accepted(k)
        live.kill()
        recover_s = live.restart()
        live.send_ms(ctx.ms[k:])
        live.end()
        got = live.final_path(ctx.survey.n_nodes)
        return Row('two nodes, same name and ROS_HOME: second refused the lock, kill -9 of '
                   'the first', live.survived(),
                   f'second: {"lock refused, no persistence" if refused else "NOT REFUSED"}, '
                   f'{"clean exit" if clean else "exit " + str(second.returncode)}',
                   ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got), recover_s,
                   recovery_note(live.log))
    finally:
        stop_process(second)
        live.close()


def case_disk_full_then_space(ctx: Ctx) -> Row:
    """The default state's folder on a tmpfs too small for the journal: writes fail
    (``persistence`` says ``failing``); the tmpfs is then made larger: the next writes succeed
    (``persistence`` ``on`` again). Then ``kill -9`` and a restart without any publisher
    history: the state alone holds every node."""
    from ga_ros.pipeline.journal import default_state_file
    disk = default_state_file('/', 'alignment_node').parent
    size_kb = max(64, len(ctx.ms) * 381 // 1024 // 3)
    if not mount_tmpfs(disk, f'size={size_kb}k'):
        return Row('disk full then space again', 'skipped', 'mount failed (needs root)', 0, 0)
    try:
        live = Live(ctx, {})
        try:
            c = live.client
            k = 3 * len(ctx.ms) // 4
            live.send_ms(ctx.ms[:k])
            live.wait_accepted(k)
            seen: set[str] = set()

            def failing_counted() -> bool:
                seen.add(persistence(live))
                return c.diag_int('persistence_errors') > 0 and 'failing' in seen
            try:
                c.spin_until(failing_counted, 30, 'persistence failing')
            except HarnessTimeout:
                pass
            errors = max(c.diag_int('persistence_errors'), 0)
            said = 'failing' if 'failing' in seen else 'NOT failing'
            grown = subprocess.run(['mount', '-o', 'remount,size=64m', str(disk)],
                                   capture_output=True).returncode == 0
            live.send_ms(ctx.ms[k:])
            live.end()
            got = live.final_path(ctx.survey.n_nodes)
            try:
                c.spin_until(lambda: persistence(live) == 'on'
                             and c.diag_int('persistence_unsaved') == 0, 30, 'persistence on')
            except HarnessTimeout:
                pass
            after = persistence(live)
            kept_live = nodes_kept(ctx.survey.T_ref, got)
            live.kill()
            no_history(live)
            recover_s = live.restart()
            got = live.final_path(ctx.survey.n_nodes)
            return Row(f'disk full ({size_kb} kB tmpfs) then space again, kill -9, restart '
                       'without history', live.survived(),
                       f'{errors} write errors, persistence {said} -> {after}'
                       f'{"" if grown else " (remount FAILED)"}; {kept_live} nodes before the '
                       'kill', ctx.survey.n_nodes, nodes_kept(ctx.survey.T_ref, got), recover_s,
                       recovery_note(live.log))
        finally:
            live.close()
    finally:
        umount(disk)


def no_history(live: Live) -> None:
    """A new measurement publisher: nothing is re-delivered to a restarted node."""
    node, topic = live.client.node, live.pub.topic_name
    node.destroy_publisher(live.pub)
    live.pub = live.client.pub = node.create_publisher(
        Odometry, topic, measurement_qos(transient_local=True))
    live.client.paths.clear()


def case_another_survey(ctx: Ctx) -> Row:
    """Defaults: ``ga-ros play`` of one survey into the node, the node stopped, started again
    (it resumes that survey) and another survey played into it (``play_bag.launch.py`` run on
    another bag): the first survey's state moves to a dated folder with a WARN line, the second
    starts afresh and keeps every node; play exits 0 both times."""
    from ga_ros.pipeline.journal import default_state_file
    (ctx.work / 'first').mkdir()
    first = Ctx(ctx.work, ctx.dom, small_survey(ctx.work / 'first', seed=13), ctx.deadline)
    live = Live(first, {})
    player = None
    try:
        player = start_play(first)
        out, _ = player.communicate(timeout=ctx.remaining(1800))
        first_exit = player.returncode
        first_kept = nodes_kept(first.survey.T_ref, live.final_path(first.survey.n_nodes))
        live.kill(signal.SIGINT)
        live.client.paths.clear()
        live.ctx = ctx
        recover_s = live.restart()
        c = live.client                          # the resumed survey's path, then forget it
        c.spin_until(lambda: c.paths and len(c.paths[-1][1].poses) >= first.survey.n_nodes,
                     60, "the resumed first survey's path", live.proc)
        c.paths.clear()
        player = start_play(ctx)
        out, _ = player.communicate(timeout=ctx.remaining(1800))
        live.wait_accepted(len(ctx.ms))          # counted afresh by the new survey
        got = live.final_path(ctx.survey.n_nodes)
        folders = list(default_state_file('/', 'alignment_node').parent.glob('state.survey-*'))
        warned = live.log.read_text(errors='replace').count('a different survey')
        return Row('another survey played into a node holding a finished one, defaults',
                   live.survived(), f'{len(folders)} moved aside, {warned} WARN line; play exit '
                   f'{first_exit}, {player.returncode}', ctx.survey.n_nodes,
                   nodes_kept(ctx.survey.T_ref, got), recover_s,
                   f'first survey: {first_kept}/{first.survey.n_nodes} kept')
    finally:
        if player is not None and player.poll() is None:
            player.kill()
            player.communicate()
        live.close()
