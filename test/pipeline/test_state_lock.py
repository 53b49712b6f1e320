"""The default state path (under ``$ROS_HOME``, named by the node's namespace and name) and the
lock that keeps two writers off one state file (ROS-free)."""

from __future__ import annotations

import subprocess
import sys

import pytest

from ga_ros.errors import FormatError, PersistenceError
from ga_ros.pipeline.journal import StateLock, default_state_file, lock_path
from ga_ros.pipeline.session import AlignmentSession, SessionConfig


def test_the_default_state_file_is_under_ros_home_by_namespace_and_name(tmp_path, monkeypatch):
    monkeypatch.setenv('ROS_HOME', str(tmp_path))
    assert default_state_file('/', 'alignment_node') == tmp_path / 'ga_ros/alignment_node/state'
    assert (default_state_file('/robot1/nav', 'align') ==
            tmp_path / 'ga_ros/robot1/nav/align/state')
    monkeypatch.delenv('ROS_HOME')
    monkeypatch.setenv('HOME', str(tmp_path / 'home'))
    assert default_state_file('/', 'n') == tmp_path / 'home/.ros/ga_ros/n/state'
    with pytest.raises(FormatError):
        default_state_file('/../x', 'n')


def test_a_second_lock_is_refused_naming_the_holder(tmp_path):
    state = tmp_path / 'a' / 'state'
    first = StateLock(state, '/robot1/alignment_node')
    assert lock_path(state).exists()
    with pytest.raises(PersistenceError) as err:
        StateLock(state, '/robot2/alignment_node')
    text = str(err.value)
    assert '/robot1/alignment_node' in text and str(lock_path(state)) in text
    assert 'state_file' in text and 'namespace' in text
    first.release()
    StateLock(state, '/robot2/alignment_node').release()  # free again


def test_a_lock_held_by_another_process_is_refused_and_freed_when_it_dies(tmp_path):
    state = tmp_path / 'state'
    code = ('import sys; from ga_ros.pipeline.journal import StateLock; '
            f'lock = StateLock({str(state)!r}, "/other"); print("locked", flush=True); '
            'sys.stdin.readline()')
    proc = subprocess.Popen([sys.executable, '-c', code], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == 'locked'
        with pytest.raises(PersistenceError, match='/other'):
            StateLock(state, '/me')
    finally:
        proc.kill()
        proc.wait(timeout=60)
    StateLock(state, '/me').release()  # the OS released the dead holder's lock


def test_a_session_on_a_locked_state_file_runs_without_persistence(tmp_path):
    state = str(tmp_path / 'state')
    first = AlignmentSession(session=SessionConfig(state, lock_owner='/first'))
    assert first.resume() is None and first.lock is not None
    warnings: list[str] = []
    second = AlignmentSession(session=SessionConfig(state, lock_owner='/second'),
                              warn=warnings.append)
    how = second.resume()
    assert how.startswith('failed') and second.journal is None
    assert '/first' in second.persistence_off and any('WITHOUT' in w for w in warnings)
    with pytest.raises(PersistenceError, match='/first'):
        AlignmentSession(session=SessionConfig(state, lock_owner='/third',
                                               state_required=True)).resume()
    first.close()
    third = AlignmentSession(session=SessionConfig(state, lock_owner='/third'))
    assert third.resume() is None and third.journal is not None
    third.close()


@pytest.mark.parametrize('kind', ['foreign', 'symlink'])
def test_no_lock_file_beside_a_refused_state_path(tmp_path, kind):
    """A foreign or linked state path is refused before the lock: nothing is created."""
    victim = tmp_path / 'notes.txt'
    victim.write_text('precious\n')
    state = victim if kind == 'foreign' else tmp_path / 'state'
    if kind == 'symlink':
        state.symlink_to(victim)
    session = AlignmentSession(session=SessionConfig(str(state), lock_owner='/me'))
    assert session.resume().startswith('failed')
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(
        ['notes.txt'] + (['state'] if kind == 'symlink' else []))
    assert victim.read_text() == 'precious\n'
