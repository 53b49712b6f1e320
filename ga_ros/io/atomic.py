"""Safe file writing for the whole package: atomic replacement, no symlinks, no foreign files.

Every file ga_ros writes (aligner snapshots, their sidecar, the measurement journal) goes through
this module:

* a new file is written to a temporary file created in the target's own directory as
  :func:`tempfile.mkstemp` does (``O_CREAT | O_EXCL | O_NOFOLLOW``, a random name, mode ``0600``
  then the final mode; :func:`_temporary_file`, without importing :mod:`tempfile`), flushed
  with ``fsync``, renamed over the target with :func:`os.replace` (atomic on POSIX) and the
  directory entry is synced, so a reader sees the old or the new file, never a mix, even after
  a power cut;
* an existing target that is a symbolic link or not a regular file is refused
  (:class:`~ga_ros.errors.UnsafePathError`); one that is not ours (the caller's ``is_ours`` test
  says so) is refused too (:class:`~ga_ros.errors.ForeignFileError`): never overwritten, never
  deleted;
* files kept open for appending are opened with ``O_NOFOLLOW``;
* a damaged file is moved aside (``<name>.corrupt-<UTC timestamp>``), never deleted.
"""

from __future__ import annotations

import os
import stat
import time
from collections.abc import Callable, Iterable
from pathlib import Path

from ga_ros.errors import ForeignFileError, UnsafePathError

Chunk = bytes | bytearray | memoryview
_NOFOLLOW = getattr(os, 'O_NOFOLLOW', 0)
_CLOEXEC = getattr(os, 'O_CLOEXEC', 0)


def check_regular(path: str | os.PathLike) -> bool:
    """``True`` if ``path`` is an existing regular file, ``False`` if nothing is there.

    Raises :class:`UnsafePathError` for a symbolic link (even a dangling one) or anything that is
    not a regular file (a directory, a FIFO, a device).
    """
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return False
    if stat.S_ISLNK(st.st_mode):
        raise UnsafePathError(f'{path} is a symbolic link: ga_ros never writes through links; '
                              'remove it or choose another path')
    if not stat.S_ISREG(st.st_mode):
        raise UnsafePathError(f'{path} exists and is not a regular file; choose another path')
    return True


def _temporary_file(directory: Path, prefix: str, suffix: str) -> tuple[int, str]:
    """``(fd, path)`` of a new file ``directory/<prefix><random><suffix>``, opened for writing,
    mode ``0600``: what :func:`tempfile.mkstemp` does (``O_CREAT | O_EXCL``, so an existing
    name, link or not, is never opened), without importing :mod:`tempfile` (with ``random``
    and ``shutil``, ~5-15 ms of a command's start-up)."""
    flags = os.O_RDWR | os.O_CREAT | os.O_EXCL | _NOFOLLOW | _CLOEXEC
    for _ in range(100):
        name = os.path.join(directory, f'{prefix}{os.urandom(6).hex()}{suffix}')
        try:
            return os.open(name, flags, 0o600), name
        except FileExistsError:
            continue
    raise FileExistsError(f'no free temporary name in {directory}')


def atomic_write(path: str | os.PathLike, data: Chunk | Iterable[Chunk], *,
                 is_ours: Callable[[Path], bool] | None = None, mode: int = 0o644) -> Path:
    """Write ``data`` to ``path`` atomically (temporary file in the same directory, fsync,
    rename).

    Parameters
    ----------
    path : target file; its directory is created if missing.
    data : the bytes, or an iterable of bytes-like chunks (e.g. ``memoryview`` of arrays,
        written without a copy).
    is_ours : called with ``path`` if a file is already there; if it returns ``False`` the file
        is refused (:class:`ForeignFileError`) and left as it was. ``None`` replaces any regular
        file.
    mode : permission bits of the new file.

    Returns
    -------
    The target path. On any error the target is unchanged and the temporary file is removed.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    if check_regular(path) and is_ours is not None and not is_ours(path):
        raise ForeignFileError(f'{path} exists and is not a ga_ros file: it is left untouched; '
                               'choose another path or move that file away')
    fd, tmp = _temporary_file(path.parent, f'.{path.name}.', '.tmp')
    try:
        with os.fdopen(fd, 'wb') as f:
            for chunk in ([data] if isinstance(data, bytes | bytearray | memoryview) else data):
                f.write(chunk)
            f.flush()
            os.fchmod(f.fileno(), mode)
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise
    sync_directory(path.parent)
    return path


def sync_directory(directory: str | os.PathLike) -> None:
    """``fsync`` a directory so a rename or a new entry in it survives a power cut (best
    effort: some file systems refuse it)."""
    try:
        fd = os.open(directory, os.O_RDONLY | _CLOEXEC)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def open_nofollow(path: str | os.PathLike, flags: int, mode: int = 0o644) -> int:
    """``os.open`` that refuses symbolic links (``O_NOFOLLOW``) and anything but a regular file.

    Returns a file descriptor. Raises :class:`UnsafePathError` if ``path`` is a link or not a
    regular file, ``OSError`` otherwise.
    """
    check_regular(path)
    try:
        fd = os.open(path, flags | _NOFOLLOW | _CLOEXEC, mode)
    except OSError as exc:
        if os.path.islink(path):
            raise UnsafePathError(f'{path} is a symbolic link: refused') from None
        raise exc
    if not stat.S_ISREG(os.fstat(fd).st_mode):
        os.close(fd)
        raise UnsafePathError(f'{path} is not a regular file; choose another path')
    return fd


def read_bytes(path: str | os.PathLike) -> bytes:
    """The whole content of a regular file, never read through a symbolic link."""
    fd = open_nofollow(path, os.O_RDONLY)
    with os.fdopen(fd, 'rb') as f:
        return f.read()


def move_aside(path: str | os.PathLike, tag: str = 'corrupt') -> Path:
    """Rename ``path`` to ``<name>.<tag>-<UTC timestamp>`` in the same directory (never over an
    existing file) and return the new path. The content is kept as it was."""
    path = Path(path)
    stamp = time.strftime('%Y%m%dT%H%M%SZ', time.gmtime())
    for k in range(1000):
        new = path.with_name(f'{path.name}.{tag}-{stamp}' + (f'.{k}' if k else ''))
        try:
            os.link(path, new)          # fails if ``new`` exists: nothing is overwritten
        except FileExistsError:
            continue
        except OSError:                 # no hard links here: check, then rename
            if os.path.lexists(new):
                continue
            os.rename(path, new)
            return new
        os.unlink(path)
        sync_directory(path.parent)
        return new
    raise FileExistsError(f'cannot find a free name to move {path} aside')
