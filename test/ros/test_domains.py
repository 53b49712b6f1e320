"""ROS domain ids claimed machine-wide (ga_ros.domains): a running process's id is never
handed to another one, and is free again once that process has exited (killed too)."""

from __future__ import annotations

import os
import pathlib
import shutil
import signal
import stat
import subprocess
import sys
import tempfile

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


# ------------------------------------------------------------------------- several users
NOBODY = 65534
REPO = pathlib.Path(__file__).resolve().parents[2]


def _as_nobody() -> None:
    os.setgroups([])
    os.setgid(NOBODY)
    os.setuid(NOBODY)


def _python_for_nobody() -> str:
    """An interpreter that user ``nobody`` can run and that imports ``ga_ros.domains`` from
    this checkout (skips the test without one, or when not root: no other user to become)."""
    if not hasattr(os, 'geteuid') or os.geteuid() != 0:
        pytest.skip('needs root, to run a claim as another user (nobody)')
    for exe in (sys.executable, shutil.which('python3'), '/usr/bin/python3'):
        if not exe:
            continue
        try:
            ok = subprocess.run([exe, '-c', 'import ga_ros.domains'], preexec_fn=_as_nobody,
                                env={'PYTHONPATH': str(REPO), 'PATH': os.environ['PATH']},
                                capture_output=True, timeout=patience(30)).returncode == 0
        except OSError:
            ok = False
        if ok:
            return exe
    pytest.skip(f'no Python that user nobody can run imports ga_ros from {REPO}')


@pytest.fixture
def shared_base():
    """A folder every user can reach (the tests' own tmp folders are root's, 0700)."""
    base = pathlib.Path(tempfile.mkdtemp(prefix='ga_ros_domain_users_'))
    os.chmod(base, 0o755)
    yield base
    shutil.rmtree(base, ignore_errors=True)


def nobody_holder(exe: str, folder: pathlib.Path, start: int) -> subprocess.Popen:
    """User nobody claiming the first free id from ``start`` in ``folder`` (printed) and
    holding it until its stdin closes; a refused claim prints the error."""
    code = ('import sys\nfrom ga_ros import domains\ntry:\n'
            '    c = domains.claim(int(sys.argv[1]))\n'
            'except domains.DomainLockFolderError as exc:\n'
            '    print("error:", exc, flush=True)\n    sys.exit(3)\n'
            'print(c.domain, flush=True)\nsys.stdin.read()\n')
    return subprocess.Popen([exe, '-c', code, str(start)], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=_as_nobody,
                            env={'PYTHONPATH': str(REPO), 'PATH': os.environ['PATH'],
                                 'GA_ROS_DOMAIN_LOCKS': str(folder)})


def test_claims_of_different_users_exclude_each_other(shared_base, monkeypatch) -> None:
    """The default folder is made shared (mode 1777, lock files 0644): an id root holds is
    not handed to user nobody, nor the id nobody holds to root."""
    exe = _python_for_nobody()
    folder = shared_base / 'ga_ros_domains'
    monkeypatch.delenv('GA_ROS_DOMAIN_LOCKS', raising=False)
    monkeypatch.setattr(domains, 'LOCK_DIR', folder)
    mine = domains.claim(100)
    assert mine.domain == 100
    assert stat.S_IMODE(os.stat(folder).st_mode) == domains.SHARED_MODE
    assert stat.S_IMODE(os.stat(folder / '100.lock').st_mode) == domains.LOCK_MODE
    proc = nobody_holder(exe, folder, 100)
    try:
        line = proc.stdout.readline()
        assert line.strip() == '101', (line, proc.stderr.read() if proc.poll() else '')
        assert os.stat(folder / '101.lock').st_uid == NOBODY
        again = domains.claim(100)
        assert again.domain == 102            # 100 is ours, 101 nobody's
        again.release()
    finally:
        proc.stdin.close()
        proc.wait(timeout=patience(10))
        mine.release()


def test_a_folder_another_user_made_private_is_a_clear_error(shared_base) -> None:
    """A lock folder of another user that this user cannot create files in (root's, 0755,
    as an older ga_ros left it) is refused with what to do, not an OSError."""
    exe = _python_for_nobody()
    folder = shared_base / 'ga_ros_domains'
    folder.mkdir(mode=0o755)
    proc = nobody_holder(exe, folder, 100)
    out, err = proc.communicate(timeout=patience(30))
    assert proc.returncode == 3, (out, err)
    assert 'belongs to user root (uid 0) with mode 755' in out
    assert f'chmod 1777 {folder}' in out and 'GA_ROS_DOMAIN_LOCKS' in out
    assert not list(folder.iterdir())


def test_a_linked_folder_is_refused_and_a_linked_lock_skipped(lock_dir, monkeypatch) -> None:
    """A lock folder that is a symbolic link is refused (it could point anywhere); a lock file
    that is a link counts as claimed (never followed)."""
    target = lock_dir / 'elsewhere'
    target.mkdir()
    link = lock_dir / 'link'
    link.symlink_to(target)
    monkeypatch.setattr(domains, 'LOCK_DIR', link)
    with pytest.raises(domains.DomainLockFolderError, match='is a symbolic link'):
        domains.claim(100)
    folder = lock_dir / 'locks'
    folder.mkdir()
    (folder / '100.lock').symlink_to(target / 'victim')
    monkeypatch.setattr(domains, 'LOCK_DIR', folder)
    c = domains.claim(100)
    assert c.domain == 101 and not (target / 'victim').exists()
    c.release()


def test_the_default_folder_is_the_machines_whatever_tmpdir_says(tmp_path) -> None:
    """Two runs with their own ``TMPDIR`` share the machine's DDS ports, so they share the
    claims: the default folder does not follow ``TMPDIR``."""
    if not domains.MACHINE_TMP.is_dir():
        pytest.skip('no /tmp on this platform: the platform temporary folder is used')
    code = 'from ga_ros import domains; print(domains.lock_folder())'
    folders = set()
    for name in ('a', 'b'):
        own = tmp_path / name
        own.mkdir()
        env = {k: v for k, v in os.environ.items() if k != 'GA_ROS_DOMAIN_LOCKS'}
        env['TMPDIR'] = str(own)
        out = subprocess.run([sys.executable, '-c', code], env=env, capture_output=True,
                             text=True, timeout=patience(30), check=True)
        folders.add(out.stdout.strip())
    assert folders == {str(domains.MACHINE_TMP / 'ga_ros_domains')}
