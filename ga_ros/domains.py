"""ROS domain ids claimed machine-wide for the tests and the benchmarks (ROS-free, imports
nothing of ROS).

Processes that start ROS graphs side by side on one machine (two test runs, a test run beside
``ga-ros bench faults``) must never share a ``ROS_DOMAIN_ID``: nodes of one would hear the
other's measurements, services and transforms. A domain id is claimed by an exclusive
``flock`` on ``<tmp>/ga_ros_domains/<id>.lock``: a claim is refused while another process holds
it, and the kernel releases it when the process that holds it exits (killed too), so nothing
is left stale. The lock's file descriptor is not inherited by child processes.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ga_ros.errors import GaError

#: Domain ids handed out: 1..232 (0 is ROS's default, used by anything started by hand; Fast
#: DDS's port arithmetic stops at 232).
FIRST, LAST = 1, 232
#: Folder of the lock files (environment variable ``GA_ROS_DOMAIN_LOCKS``).
LOCK_DIR = Path(os.environ.get('GA_ROS_DOMAIN_LOCKS',
                               Path(tempfile.gettempdir()) / 'ga_ros_domains'))


class DomainsExhausted(GaError):
    """Every domain id is claimed by a running process."""


class DomainClaim:
    """One claimed domain id (:attr:`domain`), held until :meth:`release` or process exit."""

    def __init__(self, domain: int, fd: int) -> None:
        self.domain = domain
        self._fd: int | None = fd

    def release(self) -> None:
        """Give the id back (closing the lock's descriptor releases the ``flock``)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None


def claim(start: int | None = None) -> DomainClaim:
    """Claim the first free domain id from ``start`` on (wrapping around; default: from this
    process's pid, which spreads concurrent processes).

    Raises
    ------
    DomainsExhausted
        All ids in ``FIRST..LAST`` are held by running processes.
    """
    LOCK_DIR.mkdir(parents=True, exist_ok=True)
    n = LAST - FIRST + 1
    first = (os.getpid() * 7 if start is None else start - FIRST) % n
    for k in range(n):
        domain = FIRST + (first + k) % n
        fd = os.open(LOCK_DIR / f'{domain}.lock', os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            continue
        return DomainClaim(domain, fd)
    raise DomainsExhausted(f'all ROS domain ids {FIRST}-{LAST} are claimed by running processes '
                           f'(locks in {LOCK_DIR}); stop some ROS test runs or benchmarks')


@contextmanager
def claimed() -> Iterator[int]:
    """A domain id of our own for the duration of the ``with`` block."""
    c = claim()
    try:
        yield c.domain
    finally:
        c.release()


class DomainBook:
    """Domain ids by key, each claimed on first use and held for the life of the process (the
    tests of one run take different keys, so a test never hears the processes of another)."""

    def __init__(self) -> None:
        self._claims: dict[object, DomainClaim] = {}

    def domain(self, key: object) -> int:
        if key not in self._claims:
            self._claims[key] = claim()
        return self._claims[key].domain


#: The process's domain ids by key (:func:`domain_id`).
BOOK = DomainBook()


def domain_id(key: object = 0) -> int:
    """This process's domain id for ``key``: claimed machine-wide on first use, the same id on
    every later call with that key, different for different keys."""
    return BOOK.domain(key)
