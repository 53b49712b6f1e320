"""ROS domain ids claimed machine-wide (ga_ros.domains): a running process's id is never
handed to another one, and is free again once that process has exited (killed too)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys

import pytest

from ga_ros import domains
from ga_ros.ros.deadlines import patience


@pytest.fixture
def lock_dir(tmp_path, monkeypatch):
    monkeypatch.setattr(domains, 'LOCK_DIR', tmp_path)
    monkeypatch.setenv('GA_ROS_DOMAIN_LOCKS', str(tmp_path))
    return tmp_path


HOLDER = ('import sys\nfrom ga_ros import domains\nc = domains.claim(int(sys.argv[1]))\n'
          'print(c.domain, flush=True)\nsys.stdin.read()\n')


def holder(start: int) -> tuple[subprocess.Popen, int]:
    """A process that claims the first free id from ``start`` and holds it until killed."""
    proc = subprocess.Popen([sys.executable, '-c', HOLDER, str(start)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env=dict(os.environ))
    line = proc.stdout.readline()   # (blocks until the child has claimed; EOF if it died)
    assert line.strip(), proc.communicate(timeout=patience(10))
    return proc, int(line)


def test_an_id_held_by_another_process_is_never_handed_out(lock_dir) -> None:
    proc, held = holder(100)
    try:
        assert held == 100
        mine = domains.claim(100)
        assert mine.domain == 101                     # the next free one
        other, second = holder(100)                   # a third process: neither 100 nor 101
        try:
            assert second == 102
        finally:
            other.kill()
            other.wait(timeout=patience(10))
        mine.release()
        again = domains.claim(101)
        assert again.domain == 101                    # released: free again
        again.release()
    finally:
        proc.send_signal(signal.SIGKILL)              # a killed holder frees its id too
        proc.wait(timeout=patience(10))
    freed = domains.claim(100)
    assert freed.domain == 100
    freed.release()


def test_one_id_per_key_for_the_life_of_the_process(lock_dir) -> None:
    book = domains.DomainBook()
    a, b = book.domain('a'), book.domain('b')
    assert a != b and book.domain('a') == a and domains.FIRST <= a <= domains.LAST
    with domains.claimed() as c:
        assert c not in (a, b)


def test_all_ids_claimed_is_a_clear_error(lock_dir, monkeypatch) -> None:
    monkeypatch.setattr(domains, 'LAST', domains.FIRST + 1)
    held = [domains.claim(), domains.claim()]
    with pytest.raises(domains.DomainsExhausted, match='stop some ROS test runs'):
        domains.claim()
    for c in held:
        c.release()
