"""Safe file writing for the whole package: atomic replacement, no symlinks, no foreign files.

Every file ga_ros writes goes through this module: aligner snapshots, their sidecar and the
measurement journal, and every output of the commands and tools (JSON with
:func:`write_json`, text, CSV and TUM with :func:`write_text`, PNG plots with
:func:`save_figure`, bags with :func:`staging_directory` and :func:`commit_directory`, the logs
of child processes with :func:`open_log`):

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
* a damaged file is moved aside (``<name>.corrupt-<UTC timestamp>``), never deleted;
* a directory output (a rosbag2 bag) is written under ``<name>.partial/`` and renamed to
  ``<name>`` when complete, so a killed run leaves ``<name>.partial`` (replaced by the next
  run), never a file that looks complete.

The ``write_*`` helpers and :func:`save_figure` turn an ``OSError`` into a
:class:`~ga_ros.errors.FormatError` naming the file, so a command exits with one line.
"""

from __future__ import annotations

import io
import os
import stat
import time
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import IO, Any

from ga_ros.errors import ForeignFileError, FormatError, UnsafePathError

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


# --------------------------------------------------------------------------- command outputs
def check_destinations(*paths: str | os.PathLike) -> None:
    """Refuse, before any work, output files that are symbolic links or not regular files.

    Raises :class:`UnsafePathError` naming the first such path; missing paths are fine.
    """
    for p in paths:
        check_regular(p)


def write_bytes(path: str | os.PathLike, data: Chunk | Iterable[Chunk], mode: int = 0o644
                ) -> Path:
    """:func:`atomic_write` of an output file; an ``OSError`` becomes a :class:`FormatError`
    naming ``path`` (a link or a non-regular file: :class:`UnsafePathError`)."""
    try:
        return atomic_write(path, data, mode=mode)
    except OSError as exc:
        raise FormatError(f'cannot write: {exc.strerror or exc}', str(path)) from None


def write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` atomically (:func:`write_bytes`)."""
    return write_bytes(path, text.encode())


def write_json(path: str | os.PathLike, data: Any, **dumps: Any) -> Path:
    """Write ``json.dumps(data, **dumps)`` and a newline to ``path`` atomically."""
    import json  # lazy, as tempfile above: start-up of the commands that never write JSON

    return write_text(path, json.dumps(data, **dumps) + '\n')


def write_npz(path: str | os.PathLike, compressed: bool = False, **arrays: Any) -> Path:
    """Write ``arrays`` as a NumPy ``.npz`` archive (``np.savez``, or ``np.savez_compressed``
    with ``compressed``) built in memory, then atomically (:func:`write_bytes`)."""
    import numpy as np

    buf = io.BytesIO()
    (np.savez_compressed if compressed else np.savez)(buf, **arrays)
    return write_bytes(path, buf.getbuffer())


def save_figure(fig: Any, path: str | os.PathLike, **savefig: Any) -> Path:
    """Render a matplotlib figure into memory (format from the suffix) and write it
    atomically; the figure is not closed."""
    path = Path(path)
    check_regular(path)
    buf = io.BytesIO()
    fig.savefig(buf, format=savefig.pop('format', path.suffix.lstrip('.') or 'png'), **savefig)
    return write_bytes(path, buf.getbuffer())


def open_log(path: str | os.PathLike, append: bool = False) -> IO[bytes]:
    """A binary file for a child process's output (written as it runs, so not atomic):
    created or truncated (``append``: appended to), never through a symbolic link."""
    flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if append else os.O_TRUNC)
    try:
        return os.fdopen(open_nofollow(path, flags), 'ab' if append else 'wb')
    except OSError as exc:
        raise FormatError(f'cannot write: {exc.strerror or exc}', str(path)) from None


# --------------------------------------------------------------------------- directory outputs
PARTIAL_SUFFIX = '.partial'
#: The file that marks a ``<name>.partial`` directory as ga_ros's own staging directory: only
#: a directory holding it is ever removed.
PARTIAL_MARKER = '.ga_ros-partial'


def staging_directory(final: str | os.PathLike, is_ours: Callable[[Path], bool]) -> Path:
    """An empty directory ``<final>.partial`` to build the directory output ``final`` in.

    ``final`` is checked first: a symbolic link is refused (:class:`UnsafePathError`), an
    existing path that ``is_ours`` does not accept is refused (:class:`ForeignFileError`); both
    are left untouched. The staging directory holds :data:`PARTIAL_MARKER`; a
    ``<final>.partial`` left by a killed run is removed only if it holds that marker (anything
    else there, a link included, is refused and left untouched). Call :func:`commit_directory`
    when the output is complete.
    """
    final = Path(final)
    _check_replaceable_directory(final, is_ours)
    staging = final.with_name(final.name + PARTIAL_SUFFIX)
    _remove_tree(staging)
    try:
        staging.mkdir(parents=True)
        atomic_write(staging / PARTIAL_MARKER, b'a staging directory of ga_ros: removed by '
                     b'the next run\n')
    except OSError as exc:
        raise FormatError(f'cannot create: {exc.strerror or exc}', str(staging)) from None
    return staging


def commit_directory(staging: str | os.PathLike, final: str | os.PathLike,
                     is_ours: Callable[[Path], bool]) -> Path:
    """Rename the complete directory ``staging`` to ``final`` (replacing an older output that
    ``is_ours`` accepts), and sync the parent directory. Returns ``final``."""
    staging, final = Path(staging), Path(final)
    _check_replaceable_directory(final, is_ours)
    old = None
    if os.path.lexists(final):
        old = final.with_name(f'.{final.name}.old-{os.urandom(4).hex()}')
        os.rename(final, old)
    os.rename(staging, final)
    sync_directory(final.parent)
    if old is not None:
        import shutil

        shutil.rmtree(old, ignore_errors=True)
    return final


def remove_staging(staging: str | os.PathLike) -> None:
    """Remove an emptied staging directory of :func:`staging_directory` (its marker and the
    directory; anything else left in it makes this fail with ``OSError``)."""
    staging = Path(staging)
    (staging / PARTIAL_MARKER).unlink(missing_ok=True)
    staging.rmdir()


def _check_replaceable_directory(path: Path, is_ours: Callable[[Path], bool]) -> None:
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(st.st_mode):
        raise UnsafePathError(f'{path} is a symbolic link: ga_ros never writes through links; '
                              'remove it or choose another path')
    if not stat.S_ISDIR(st.st_mode) or not is_ours(path):
        raise ForeignFileError(f'{path} exists and is not an output ga_ros may replace: it is '
                               'left untouched; choose another path or move it away')


def _remove_tree(path: Path) -> None:
    """Remove a leftover staging directory: never through a symbolic link, and only one
    that holds :data:`PARTIAL_MARKER` (a directory of the user's with that name is refused)."""
    try:
        st = os.lstat(path)
    except FileNotFoundError:
        return
    if stat.S_ISLNK(st.st_mode) or not stat.S_ISDIR(st.st_mode):
        raise UnsafePathError(f'{path} is in the way and is not a leftover directory of '
                              'ga_ros; remove it or choose another path')
    try:
        marked = stat.S_ISREG(os.lstat(path / PARTIAL_MARKER).st_mode)
    except OSError:
        marked = False
    if not marked:
        raise ForeignFileError(f'{path} is in the way and has no {PARTIAL_MARKER} marker, so it '
                               'is not a staging directory of ga_ros: it is left untouched; '
                               'move it away or choose another path')
    import shutil

    shutil.rmtree(path)
