"""The harness of the fault cases: a live alignment node process with its client, ``ga-ros play``
as a process, tmpfs mounts, and what a node's log says."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from nav_msgs.msg import Odometry
from rclpy.duration import Duration

from ga_ros import topics
from ga_ros.core.measurement import Measurement
from ga_ros.ros import conversions as conv
from ga_ros.ros.deadlines import patience
from ga_ros.ros.fault_catalogue.survey import Ctx
from ga_ros.ros.harness import HarnessTimeout, NodeClient, start_node_process, stop_process

#: Names of the diagnostics levels.
LEVELS = {0: 'OK', 1: 'WARN', 2: 'ERROR', 3: 'STALE'}
#: Diagnostics often enough for the waits; everything else at the node's defaults.
BASE_PARAMS: dict[str, object] = {'diagnostics_period_sec': 0.2}


def traceback_in(log: Path) -> bool:
    return log.exists() and 'Traceback' in log.read_text(errors='replace')


class Live:
    """One alignment node process and a client whose transient-local publisher keeps the
    whole history (a restarted node gets it again)."""

    def __init__(self, ctx: Ctx, params: dict[str, object] | None = None) -> None:
        self.ctx = ctx
        self.params = {**BASE_PARAMS, **(params or {})}
        self.log = ctx.work / 'node.log'
        self.proc = start_node_process(ctx.dom, self.params, log_path=self.log)
        try:
            self.client = NodeClient(ctx.dom)
        except BaseException:
            stop_process(self.proc)
            raise
        self.client.deadline = ctx.deadline
        self.client.diag_seq_drops_allowed = 0      # cross-talk is an error
        self.pub = self.client.pub
        try:
            self.wait()
            self.alone()
        except BaseException:    # the case's try/finally does not hold this Live yet
            self.close()
            raise

    def alone(self) -> None:
        """Raise :class:`HarnessTimeout` if the domain holds another alignment node (another
        process uses this domain id: its measurements, services and diagnostics would mix with
        this case's)."""
        names = [n for n, _ in self.client.node.get_node_names_and_namespaces()
                 if n == 'alignment_node']
        if len(names) > 1:
            raise HarnessTimeout(f'cross-talk: {len(names)} alignment nodes on ROS domain '
                                 f'{self.ctx.dom}; another process uses this domain id')

    def wait(self, timeout: float = 60.0) -> None:
        c = self.client
        c.spin_until(lambda: self.pub.get_subscription_count() > 0
                     and all(s.service_is_ready() for s in c.services.values()), timeout,
                     'the node', self.proc)

    def kill(self, sig: int = signal.SIGKILL) -> int:
        self.proc.send_signal(sig)
        return self.proc.wait(timeout=self.ctx.remaining(patience(60)))

    def restart(self) -> float:
        """Start the node again; returns the seconds until it holds every node it held when
        the last diagnostics before the restart were received."""
        end = time.monotonic() + 0.5   # take what the stopped node sent before it stopped
        while time.monotonic() < end:
            self.client.executor.spin_once(timeout_sec=0.05)
        before = max(self.client.diag_int('nodes'), 0)
        t0 = time.monotonic()
        self.proc = start_node_process(self.ctx.dom, self.params, log_path=self.log)
        self.client.expect_restart()
        self.client.diagnostics = {}
        self.wait()
        self.client.spin_until(lambda: self.client.diag_int('nodes') >= before, 1800,
                               'the recovered nodes', self.proc)
        return time.monotonic() - t0

    def send(self, msgs: list[Odometry], wait: bool = True) -> None:
        """Publish ``msgs``; ``wait``: until every matched reader acknowledged them (a killed
        node's reader counts until its lease ends).

        Raises
        ------
        HarnessTimeout
            The readers did not acknowledge them within the deadline: delivery stalled.
        """
        for k, msg in enumerate(msgs):
            self.pub.publish(msg)
            if k % 500 == 499:
                self.client.executor.spin_once(timeout_sec=0.0)
        if wait:
            timeout = self.ctx.remaining(patience(60))
            t0 = time.monotonic()
            if not self.pub.wait_for_all_acked(Duration(seconds=timeout)):
                raise HarnessTimeout(f'{len(msgs)} messages not acknowledged by the node after '
                                     f'{time.monotonic() - t0:.0f} s: DDS delivery stalled')

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
        """The last path received once it holds ``n`` adjusted nodes (after ``timeout``: the
        last one received, the row then counts what it lacks; the case's time budget spent:
        :class:`HarnessTimeout`)."""
        c = self.client
        try:
            c.spin_until(lambda: c.paths and len(c.paths[-1][1].poses) >= n
                         and c.diag_int('dead_reckoned_nodes') == 0
                         and c.diag_int('nodes') >= n, timeout, 'final path')
        except HarnessTimeout:
            if time.monotonic() > self.ctx.deadline:
                raise
        return conv.path_msg_to_poses(c.paths[-1][1]) if c.paths else np.zeros((0, 4, 4))

    def survived(self) -> str:
        if traceback_in(self.log):
            return 'TRACEBACK'
        return 'yes' if self.proc.poll() is None else f'NO (exit {self.proc.returncode})'

    def close(self) -> None:
        self.client.close()
        stop_process(self.proc)


def start_play(ctx: Ctx, *args: str) -> subprocess.Popen:
    env = dict(os.environ, ROS_DOMAIN_ID=str(ctx.dom))
    return subprocess.Popen([sys.executable, '-m', 'ga_ros.ros.play', str(ctx.survey.bag),
                             '--rate', '0', *args], env=env, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)


def recovery_note(log: Path) -> str:
    """How the restarted node resumed (its log line)."""
    found = re.findall(r'\(((?:snapshot|journal)[^)]*replayed in [0-9.]+ s)',
                       log.read_text(errors='replace') if log.exists() else '')
    return found[-1] if found else ''


def mount_tmpfs(where: Path, options: str) -> bool:
    """Mount a tmpfs (needs root); False if that is not possible here."""
    where.mkdir(parents=True, exist_ok=True)
    res = subprocess.run(['mount', '-t', 'tmpfs', '-o', options, 'tmpfs', str(where)],
                         capture_output=True)
    return res.returncode == 0


def umount(where: Path) -> None:
    subprocess.run(['umount', '-l', str(where)], capture_output=True)
