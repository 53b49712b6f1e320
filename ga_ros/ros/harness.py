"""Drive an alignment node running in another process (integration tests, ``ga-ros bench node``).

:func:`start_node_process` launches ``python -m ga_ros.ros.alignment_node`` with its own
``ROS_DOMAIN_ID``; :class:`NodeClient` publishes measurements to it, listens to its outputs and
calls its services, spinning its own executor with timeouts (never forever).
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from nav_msgs.msg import Odometry
from nav_msgs.msg import Path as PathMsg
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from std_srvs.srv import Trigger

from ga_ros import domains, topics
from ga_ros.core.measurement import Measurement
from ga_ros.errors import GaError
from ga_ros.ros import conversions as conv
from ga_ros.ros.deadlines import patience
from ga_ros.ros.qos import latched_qos, measurement_qos, stream_qos
from ga_ros.safe_write import open_log

CONFIG = Path(__file__).resolve().parents[2] / 'config' / 'alignment.yaml'


class HarnessTimeout(GaError):
    """A condition was not met in time (the node is too slow, dead, or not discovered)."""


def domain_id(offset: object = 0) -> int:
    """A ``ROS_DOMAIN_ID`` of this process for ``offset`` (:func:`ga_ros.domains.domain_id`:
    claimed machine-wide, so concurrent runs never share one): the tests of one run take
    different offsets, so they never hear each other."""
    return domains.domain_id(offset)


@contextmanager
def ros_context(domain: int) -> Iterator[rclpy.Context]:
    """An rclpy context of its own, initialised on ``domain`` and shut down on exit."""
    context = rclpy.Context()
    rclpy.init(context=context, domain_id=domain)
    try:
        yield context
    finally:
        rclpy.try_shutdown(context=context)


def start_node_process(domain_id: int, params: dict[str, object] | None = None,
                       params_file: str | os.PathLike | None = CONFIG,
                       log_path: str | os.PathLike | None = None,
                       ros_args: Sequence[str] = (),
                       module: str = 'ga_ros.ros.alignment_node') -> subprocess.Popen:
    """Start the alignment node as a child process on ``domain_id``; ``params`` are ``-p
    name:=value`` overrides, ``ros_args`` more ROS arguments (e.g. ``['-r', '__ns:=/robot1']``).
    Stdout/stderr go to ``log_path`` (default: discarded)."""
    cmd = [sys.executable, '-m', module, '--ros-args', *ros_args]
    if params_file is not None and Path(params_file).exists():
        cmd += ['--params-file', str(params_file)]
    for key, value in (params or {}).items():
        if isinstance(value, bool):
            value = 'true' if value else 'false'
        elif isinstance(value, str) and value == '':
            value = "''"
        cmd += ['-p', f'{key}:={value}']
    env = dict(os.environ, ROS_DOMAIN_ID=str(int(domain_id)), PYTHONUNBUFFERED='1')
    out = open_log(log_path, append=True) if log_path else subprocess.DEVNULL
    return subprocess.Popen(cmd, env=env, stdout=out, stderr=subprocess.STDOUT,
                            start_new_session=True)


def stop_process(proc: subprocess.Popen | None, sig: int = signal.SIGINT,
                 timeout: float = 10.0) -> None:
    """Stop a child started by :func:`start_node_process` (``SIGINT``, then ``SIGKILL``)."""
    if proc is None or proc.poll() is not None:
        return
    try:
        proc.send_signal(sig)
        proc.wait(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait(timeout=timeout)


class NodeClient:
    """Test-side ROS node: publishes measurements, records the alignment node's outputs."""

    def __init__(self, domain_id: int, node_name: str = 'alignment_node',
                 measurements_topic: str = topics.MEASUREMENTS,
                 path_topic: str = topics.CORRECTED_PATH,
                 diagnostics_topic: str = topics.DIAGNOSTICS) -> None:
        self.context = rclpy.Context()
        rclpy.init(context=self.context, domain_id=int(domain_id))
        self.node = Node(f'ga_harness_{os.getpid()}', context=self.context)
        self.executor = SingleThreadedExecutor(context=self.context)
        self.executor.add_node(self.node)
        self.pub = self.node.create_publisher(Odometry, measurements_topic,
                                              measurement_qos(transient_local=True))
        self.path_topic = path_topic
        self.paths: list[tuple[float, PathMsg]] = []
        self.diagnostics: dict[str, str] = {}
        self.diag_count = 0
        #: ``time.monotonic()`` after which every wait fails at once (a caller's whole time
        #: budget, e.g. a fault case's; default none).
        self.deadline = math.inf
        #: Diagnostics whose publication sequence number fell below the previous one's: once
        #: per node (re)start, repeatedly when two nodes publish on this domain (cross-talk).
        self.diag_seq_drops = 0
        #: ``diag_seq_drops`` allowed before :meth:`spin_until` reports cross-talk (None: not
        #: checked); :meth:`expect_restart` raises it by one per restart.
        self.diag_seq_drops_allowed: int | None = None
        self._diag_seq = 0
        #: Level of the last diagnostics (0 OK, 1 WARN, 2 ERROR; -1 none yet).
        self.diag_level = -1
        self._path_sub = self.subscribe_path()
        self.node.create_subscription(DiagnosticArray, diagnostics_topic, self._on_diag,
                                      stream_qos(100))
        self.services = {name: self.node.create_client(Trigger, f'/{node_name}/{name}')
                         for name in ('finish_track', 'reset', 'save_state', 'load_state')}

    # ------------------------------------------------------------------ subscriptions
    def subscribe_path(self, sink: list | None = None):
        """A (new) transient-local subscription to the path; messages go to ``sink`` (default:
        :attr:`paths`) as ``(receive time, msg)``."""
        sink = self.paths if sink is None else sink
        return self.node.create_subscription(
            PathMsg, self.path_topic, lambda msg: sink.append((time.perf_counter(), msg)),
            latched_qos(100))  # a deep reader queue: every path, not only the newest

    def record(self, msg_type, topic: str, qos=None) -> list:
        """Subscribe to ``topic`` and return the list its messages are appended to."""
        sink: list = []
        self.node.create_subscription(msg_type, topic, sink.append,
                                      qos if qos is not None else stream_qos(100))
        return sink

    def _on_diag(self, msg: DiagnosticArray, info: dict) -> None:
        seq = info.get('publication_sequence_number') or 0
        if 0 < seq < self._diag_seq:
            self.diag_seq_drops += 1
        self._diag_seq = seq
        self.diagnostics = conv.diagnostics_to_dict(msg)
        if msg.status:
            level = msg.status[0].level
            self.diag_level = level[0] if isinstance(level, bytes) else int(level)
        self.diag_count += 1

    def diag_int(self, key: str, default: int = -1) -> int:
        try:
            return int(self.diagnostics[key])
        except (KeyError, ValueError):
            return default

    # ------------------------------------------------------------------ waiting
    def spin_until(self, predicate: Callable[[], bool], timeout: float, what: str = '',
                   proc: subprocess.Popen | None = None) -> None:
        """Spin until ``predicate()`` is true; :class:`HarnessTimeout` after ``timeout`` s or if
        ``proc`` exits, or at once when :attr:`deadline` has passed."""
        deadline = time.monotonic() + patience(timeout)
        while not predicate():
            if proc is not None and proc.poll() is not None:
                raise HarnessTimeout(f'node process exited ({proc.returncode}) while waiting '
                                     f'for {what}')
            now = time.monotonic()
            if now > deadline:
                raise HarnessTimeout(f'timed out after {patience(timeout):.0f} s waiting for '
                                     f'{what}')
            if now > self.deadline:
                raise HarnessTimeout(f'the time budget ran out waiting for {what}')
            allowed = self.diag_seq_drops_allowed
            if allowed is not None and self.diag_seq_drops > allowed:
                raise HarnessTimeout(f'cross-talk while waiting for {what}: diagnostics from '
                                     'more than one node on this ROS domain (another process '
                                     'uses this domain id)')
            self.executor.spin_once(timeout_sec=0.02)

    def expect_restart(self) -> None:
        """The node is restarted: its diagnostics start again from sequence number 1."""
        if self.diag_seq_drops_allowed is not None:
            self.diag_seq_drops_allowed += 1

    def subscription_gids(self) -> set[tuple[int, ...]]:
        """Endpoint ids of the subscriptions to the measurements topic in the graph (a killed
        node's stays until DDS notices it is gone)."""
        return {tuple(i.endpoint_gid)
                for i in self.node.get_subscriptions_info_by_topic(self.pub.topic_name)}

    def wait_for_node(self, timeout: float = 30.0, proc: subprocess.Popen | None = None,
                      replacing: set[tuple[int, ...]] | None = None) -> None:
        """Wait until the node's measurement subscription and services are discovered and the
        measurements publisher is matched with the subscription. ``replacing``: the
        subscriptions of a node that was killed (:meth:`subscription_gids` before the kill):
        wait for a new one, matched (a stale match of the dead one does not count), so that
        what is published next reaches the restarted node even when it is volatile."""
        def ready() -> bool:
            if self.pub.get_subscription_count() == 0 or not all(
                    c.service_is_ready() for c in self.services.values()):
                return False
            if replacing is None:
                return True
            gids = self.subscription_gids()
            return bool(gids - replacing) and self.pub.get_subscription_count() >= len(gids)

        self.spin_until(ready, timeout, 'the alignment node to appear', proc)

    def wait_received(self, n: int, timeout: float = 30.0,
                      proc: subprocess.Popen | None = None) -> None:
        """Wait until the node reports ``measurements_received >= n`` in its diagnostics."""
        self.spin_until(lambda: self.diag_int('measurements_received') >= n, timeout,
                        f'{n} measurements to be received', proc)

    # ------------------------------------------------------------------ actions
    def publish(self, measurements: Sequence[Measurement], rate_hz: float = 0.0,
                spin_every: int = 200) -> float:
        """Publish measurements (paced at ``rate_hz`` if > 0); returns the seconds it took."""
        t0 = time.perf_counter()
        for k, m in enumerate(measurements):
            if rate_hz > 0:
                delay = t0 + k / rate_hz - time.perf_counter()
                if delay > 0:
                    time.sleep(delay)
            self.pub.publish(conv.measurement_to_odometry(m))
            if spin_every and k % spin_every == spin_every - 1:
                self.executor.spin_once(timeout_sec=0.0)
        return time.perf_counter() - t0

    def publish_raw(self, msgs: Sequence[Odometry]) -> None:
        for msg in msgs:
            self.pub.publish(msg)

    def call(self, service: str, timeout: float = 30.0) -> Trigger.Response:
        """Call one of the node's Trigger services and return the response."""
        client = self.services[service]
        self.spin_until(client.service_is_ready, timeout, f'service {service}')
        future = client.call_async(Trigger.Request())
        self.spin_until(future.done, timeout, f'the response of {service}')
        return future.result()

    def close(self) -> None:
        try:
            self.executor.shutdown(timeout_sec=1.0)
            self.node.destroy_node()
        finally:
            rclpy.try_shutdown(context=self.context)

    def __enter__(self) -> NodeClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
