"""An alignment node process with a client, killed and restarted on its state file.

Shared by the restart tests of ``test_alignment_node.py`` and ``test_gaps_node.py``: the node's
log is printed when the test fails, the client closed and the process stopped in any case.
"""

from __future__ import annotations

import signal
import subprocess
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from ga_ros.ros.deadlines import patience
from ga_ros.ros.harness import NodeClient, start_node_process, stop_process


@dataclass
class LiveNode:
    """A running node process (``proc``, replaced by a restart) and the client that talks to
    it on ``domain_id``; ``params`` and ``log`` are what a restart starts it with again."""

    domain_id: int
    params: dict[str, object]
    log: Path
    proc: subprocess.Popen
    client: NodeClient

    def kill_and_restart(self, while_down: Callable[[], None] | None = None) -> None:
        """``kill -9`` the node (it can save nothing), call ``while_down`` (e.g. publish what
        nobody hears), start it again with the same parameters and wait for its first
        diagnostics (it has restored its state by then)."""
        before = self.client.subscription_gids()
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(timeout=patience(10))
        if while_down is not None:
            while_down()
        self.proc = start_node_process(self.domain_id, self.params, log_path=self.log)
        self.client.diagnostics = {}
        self.client.wait_for_node(proc=self.proc, replacing=before)
        self.client.spin_until(lambda: self.client.diag_int('nodes') >= 0, 20, 'diagnostics',
                               self.proc)


@contextmanager
def live_node(domain_id: int, params: dict[str, object], log: Path) -> Iterator[LiveNode]:
    """Start the node process and a client, wait until they see each other; on a failure print
    the node's log; finally close the client and stop the process."""
    proc = start_node_process(domain_id, params, log_path=log)
    client = None
    node = None
    try:
        client = NodeClient(domain_id)
        client.wait_for_node(proc=proc)
        node = LiveNode(domain_id, params, log, proc, client)
        yield node
    except Exception:
        print(log.read_text() if log.exists() else '(no log)')
        raise
    finally:
        if client is not None:
            client.close()
        stop_process(node.proc if node is not None else proc)
