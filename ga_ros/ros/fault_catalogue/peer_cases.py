"""Fault cases of hostile or unlucky peers: a track end racing the queue, hostile service calls,
a peer reset, an idle timeout, play before the node, SIGTERM during start-up."""

from __future__ import annotations

import signal
import time

import numpy as np

from ga_ros.ros import conversions as conv
from ga_ros.ros.fault_catalogue.harness import BASE_PARAMS, Live, start_play, traceback_in
from ga_ros.ros.fault_catalogue.survey import Ctx, Row, finish_after, mid, nodes_kept
from ga_ros.ros.harness import HarnessTimeout, NodeClient, start_node_process, stop_process


def _final_path(c: NodeClient, n: int) -> np.ndarray:
    """The last corrected path the client received, (k, 4, 4), after waiting (up to 60 s
    nominal) for one of ``n`` poses with every node adjusted; whatever came if none did."""
    try:
        c.spin_until(lambda: c.paths and len(c.paths[-1][1].poses) >= n
                     and c.diag_int('dead_reckoned_nodes') == 0
                     and c.diag_int('nodes') >= n, 60, 'path')
    except HarnessTimeout:
        pass
    return conv.path_msg_to_poses(c.paths[-1][1]) if c.paths else np.zeros((0, 4, 4))


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


def case_play_early(ctx: Ctx) -> Row:
    log = ctx.work / 'node.log'
    proc = start_node_process(ctx.dom, BASE_PARAMS, log_path=log)
    time.sleep(0.1)
    play = start_play(ctx)
    out, _ = play.communicate(timeout=ctx.remaining(1800))
    client = NodeClient(ctx.dom)
    client.deadline = ctx.deadline
    try:
        c = client
        n = ctx.survey.n_nodes
        got = _final_path(c, n)
        return Row('ga-ros play into a node started 0.1 s before',
                   'yes' if proc.poll() is None and not traceback_in(log) else 'NO',
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
    return Row('SIGTERM during start-up', 'TRACEBACK' if traceback_in(log)
               else f'clean exit {code}', '-', 0, 0)


def case_play_clock_late_node(ctx: Ctx) -> Row:
    """``ga-ros play --rate 0`` (``/clock`` on) started first; a sim-time alignment node
    (``use_sim_time``) started once play publishes: play exits 0 only after the node confirmed
    what it processed, and the node keeps every node. Then play again, into a subscriber that
    asks for the history but never confirms: play must exit non-zero."""
    from nav_msgs.msg import Odometry

    from ga_ros.ros.qos import measurement_qos
    client = NodeClient(ctx.dom)
    client.deadline = ctx.deadline
    log = ctx.work / 'node.log'
    proc = None
    play = start_play(ctx, '--delay', '0')
    try:
        c = client
        c.spin_until(lambda: c.node.count_publishers('/ga/measurements') > 1, 60,
                     'play publishing')           # (the client's own publisher is one)
        proc = start_node_process(ctx.dom, {**BASE_PARAMS, 'use_sim_time': True},
                                  log_path=log)
        out, _ = play.communicate(timeout=ctx.remaining(1800))
        n = ctx.survey.n_nodes
        got = _final_path(c, n)
        survived = 'yes' if proc.poll() is None and not traceback_in(log) else 'NO'
        confirmed = f"{c.diag_int('measurements_received')}/{len(ctx.ms)} received"
        stop_process(proc)
        # nobody confirms: a subscriber asking for the history, no alignment node
        c.node.create_subscription(Odometry, '/ga/measurements', lambda msg: None,
                                   measurement_qos(transient_local=True))
        silent = start_play(ctx, '--delay', '0', '--delivery-timeout', '3')
        silent.communicate(timeout=ctx.remaining(1800))
        return Row('sim-time node started after ga-ros play --clock began', survived,
                   f'{confirmed}; play exit {play.returncode}; unconfirmed play exit '
                   f'{silent.returncode}', n, nodes_kept(ctx.survey.T_ref, got))
    finally:
        if play.poll() is None:
            play.kill()
            play.communicate()
        client.close()
        stop_process(proc)
