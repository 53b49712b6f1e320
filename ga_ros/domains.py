"""ROS domain ids claimed machine-wide for the tests and the benchmarks (ROS-free, imports
nothing of ROS).

Processes that start ROS graphs side by side on one machine (two test runs, a test run beside
``ga-ros bench faults``, runs of different users) must never share a ``ROS_DOMAIN_ID``: nodes of
one would hear the other's measurements, services and transforms (DDS ports are the machine's,
whoever runs the nodes). A domain id is claimed by an exclusive ``flock`` on
``<folder>/<id>.lock``: a claim is refused while another process holds it, and the kernel releases
it when the process that holds it exits (killed too), so nothing is left stale. The lock's file
descriptor is not inherited by child processes.

The folder (:func:`lock_folder`) is ``$GA_ROS_DOMAIN_LOCKS`` if set, else ``/tmp/ga_ros_domains``
(``/tmp`` whatever ``TMPDIR`` says: a run with its own ``TMPDIR`` still shares the machine's
ports, so it must share the claims; the platform's temporary folder where there is no ``/tmp``),
one for every user of the machine: made like ``/tmp`` (mode ``1777``: everyone creates lock
files, nobody removes another's), each lock file readable by all (mode ``0644``; ``flock`` needs
only a descriptor opened for reading), so a user's claims hold against every other user's. A
lock file that cannot be opened (another user's, made unreadable) counts as claimed. A folder
that is a symbolic link, not a folder, or one this user cannot create lock files in (e.g. made
``0755`` by another user) is refused with :class:`DomainLockFolderError`, which says whom to ask
or what to set.
"""

from __future__ import annotations

import fcntl
import os
import stat
import tempfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

from ga_ros.errors import GaError

#: Domain ids handed out: 1..232 (0 is ROS's default, used by anything started by hand; Fast
#: DDS's port arithmetic stops at 232).
FIRST, LAST = 1, 232
#: Mode of the shared lock folder this module makes: every user creates lock files in it, only
#: their owner removes them (the sticky bit, as ``/tmp``).
SHARED_MODE = 0o1777
#: Mode of a lock file: readable by every user (enough for ``flock``).
LOCK_MODE = 0o644


#: The machine's temporary folder, shared by every user and every ``TMPDIR``.
MACHINE_TMP = Path('/tmp')


def lock_folder() -> Path:
    """The folder of the lock files: ``$GA_ROS_DOMAIN_LOCKS`` if set, else
    ``/tmp/ga_ros_domains`` (one for every user and every ``TMPDIR`` of the machine; the
    platform's temporary folder where there is no ``/tmp``)."""
    env = os.environ.get('GA_ROS_DOMAIN_LOCKS')
    if env:
        return Path(env)
    base = MACHINE_TMP if MACHINE_TMP.is_dir() else Path(tempfile.gettempdir())
    return base / 'ga_ros_domains'


#: Folder of the lock files (:func:`lock_folder`, read at import).
LOCK_DIR = lock_folder()


class DomainsExhausted(GaError):
    """Every domain id is claimed by a running process."""


class DomainLockFolderError(GaError):
    """The lock folder cannot be used (a link, not a folder, or another user's that does not let
    this user create lock files); the message says whom to ask or what to set."""


def _user(uid: int) -> str:
    """``name (uid)`` of a user id (the uid alone if it has no name)."""
    try:
        import pwd
        return f'{pwd.getpwuid(uid).pw_name} (uid {uid})'
    except (ImportError, KeyError):
        return f'uid {uid}'


def prepare_folder(folder: Path) -> None:
    """Make ``folder`` (as :data:`SHARED_MODE` when it is the default shared one) or check the
    existing one: a real folder this user can create lock files in.

    Raises
    ------
    DomainLockFolderError
        A symbolic link, not a folder, or not writable for this user (names its owner and what
        to do).
    """
    if not os.path.lexists(folder):
        folder.parent.mkdir(parents=True, exist_ok=True)
        try:
            folder.mkdir(mode=0o700)
        except FileExistsError:
            pass          # another process made it meanwhile: checked below
        else:
            if 'GA_ROS_DOMAIN_LOCKS' not in os.environ:
                os.chmod(folder, SHARED_MODE)   # (not lowered by the umask)
    st = os.lstat(folder)
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        what = 'a symbolic link' if stat.S_ISLNK(st.st_mode) else 'not a folder'
        raise DomainLockFolderError(
            f'the ROS domain lock folder {folder} is {what}; remove it (it is remade as a '
            'folder), or set GA_ROS_DOMAIN_LOCKS to another folder')
    if not os.access(folder, os.W_OK | os.X_OK):
        raise DomainLockFolderError(
            f'the ROS domain lock folder {folder} belongs to user {_user(st.st_uid)} with mode '
            f'{stat.S_IMODE(st.st_mode):o}: user {_user(os.geteuid())} cannot create lock files '
            f'in it. Ask its owner to run `chmod 1777 {folder}` (shared by every user, as /tmp '
            'is: the ids stay unique machine-wide), or set GA_ROS_DOMAIN_LOCKS to a folder of '
            "your own (then other users' runs may take the same ids and hear your nodes)")


def _open_lock(path: Path) -> int | None:
    """A descriptor of the lock file ``path`` (made :data:`LOCK_MODE` if new), or ``None`` if
    it cannot be opened (another user's, unreadable; a symbolic link): counted as claimed."""
    flags = os.O_NOFOLLOW | os.O_CLOEXEC
    try:
        fd = os.open(path, os.O_RDONLY | os.O_CREAT | os.O_EXCL | flags, LOCK_MODE)
    except FileExistsError:
        try:
            return os.open(path, os.O_RDONLY | flags)
        except OSError:
            return None
    except OSError:
        return None
    try:
        os.fchmod(fd, LOCK_MODE)   # (not lowered by the umask)
    except OSError:
        pass
    return fd


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
    DomainLockFolderError
        The lock folder cannot be used (:func:`prepare_folder`).
    """
    prepare_folder(LOCK_DIR)
    n = LAST - FIRST + 1
    first = (os.getpid() * 7 if start is None else start - FIRST) % n
    for k in range(n):
        domain = FIRST + (first + k) % n
        fd = _open_lock(LOCK_DIR / f'{domain}.lock')
        if fd is None:
            continue
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
