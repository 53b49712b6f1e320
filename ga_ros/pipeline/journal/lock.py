"""One writer per state file: an advisory lock (``fcntl.flock``) on ``<state_file>.lock``, held
while a session writes the state, so that two nodes never share a state file.

The lock file holds who has it (``pid``, host, owner: e.g. the node's full name) for the error
the second one gets. It is never deleted (deleting a lock file lets a third process lock a new
file while the second still holds the old one); the operating system releases the lock when the
holder closes it or dies, ``kill -9`` included.
"""

from __future__ import annotations

import fcntl
import os
import socket
from pathlib import Path

from ga_ros.errors import PersistenceError
from ga_ros.safe_write import open_nofollow


def lock_path(state_file: str | os.PathLike) -> Path:
    """The lock file of a state file: ``<state_file>.lock``."""
    return Path(str(state_file) + '.lock')


class StateLock:
    """The exclusive lock of a state file, taken at construction.

    Parameters
    ----------
    state_file : the state file (the lock is ``<state_file>.lock``; its directory is created).
    owner : who takes it (e.g. ``/robot1/alignment_node``), written into the lock file.

    Raises
    ------
    PersistenceError
        Another process (or another session of this one) holds it: the message names the holder
        and the path, and what to do.
    OSError, UnsafePathError
        The lock file cannot be created or is a symbolic link.
    """

    def __init__(self, state_file: str | os.PathLike, owner: str) -> None:
        self._fd: int | None = None
        self.path = lock_path(state_file)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd = open_nofollow(self.path, os.O_RDWR | os.O_CREAT)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 512, 0).decode('utf-8', 'replace').strip() or 'unknown'
            os.close(fd)
            raise PersistenceError(
                f'in use by {holder} (lock {self.path}): two nodes never share a state file; '
                'give this node another name or namespace (the default state_file follows '
                'them) or another state_file') from None
        except BaseException:
            os.close(fd)
            raise
        text = f'pid {os.getpid()} on {socket.gethostname()}: {owner}\n'.encode()
        os.ftruncate(fd, 0)
        os.pwrite(fd, text, 0)
        self._fd = fd

    def release(self) -> None:
        """Give the lock up (the file stays)."""
        if self._fd is not None:
            os.close(self._fd)  # closing the only descriptor releases the flock
            self._fd = None

    def __del__(self) -> None:  # a lock whose holder was dropped (e.g. a failed start)
        self.release()
