"""The shared data directory is found from a checkout, from a git worktree elsewhere (through
its main checkout) and through ``GA_ROS_SHARED_DATA``; else a clear error. Layouts built here
with the files git writes for ``git worktree add``."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest

from ga_ros.bench.data import candidates, find_shared_data, main_checkout, shared_data
from ga_ros.errors import InputError


def _layout(root: Path) -> tuple[Path, Path, Path]:
    """``root/main`` (a checkout), ``root/wt/hygiene`` (its worktree, as git writes it) and
    ``root/shared/data``."""
    main, wt, data = root / 'main', root / 'wt' / 'hygiene', root / 'shared' / 'data'
    (main / '.git' / 'worktrees' / 'hygiene').mkdir(parents=True)
    (main / '.git' / 'worktrees' / 'hygiene' / 'commondir').write_text('../..\n')
    wt.mkdir(parents=True)
    (wt / '.git').write_text(f'gitdir: {main}/.git/worktrees/hygiene\n')
    data.mkdir(parents=True)
    return main, wt, data


def test_found_beside_the_checkout_and_from_a_worktree(tmp_path: Path) -> None:
    main, wt, data = _layout(tmp_path)
    assert find_shared_data(main, env={}) == data
    assert main_checkout(wt) == main.resolve()
    assert find_shared_data(wt, env={}).resolve() == data.resolve()
    assert main_checkout(main) is None


def test_a_relative_gitdir(tmp_path: Path) -> None:
    main, wt, data = _layout(tmp_path)
    (wt / '.git').write_text('gitdir: ../../main/.git/worktrees/hygiene\n')
    assert find_shared_data(wt, env={}).resolve() == data.resolve()


def test_the_variable_wins_and_alone(tmp_path: Path) -> None:
    main, wt, data = _layout(tmp_path)
    other = tmp_path / 'elsewhere'
    other.mkdir()
    assert find_shared_data(wt, env={'GA_ROS_SHARED_DATA': str(other)}) == other
    assert candidates(wt, env={'GA_ROS_SHARED_DATA': str(tmp_path / 'none')}) == \
        [tmp_path / 'none']
    assert find_shared_data(wt, env={'GA_ROS_SHARED_DATA': str(tmp_path / 'none')}) is None


def test_a_clear_error_when_there_is_none(tmp_path: Path) -> None:
    main, wt, data = _layout(tmp_path)
    data.rmdir()
    with pytest.raises(InputError) as err:
        shared_data(wt, env={})
    text = str(err.value)
    assert 'GA_ROS_SHARED_DATA' in text and str(tmp_path / 'shared' / 'data') in text


def test_a_worktree_made_by_git(tmp_path: Path) -> None:
    """The same with the files of a real ``git worktree add``."""
    main, wt = tmp_path / 'repo', tmp_path / 'trees' / 'feature'
    (tmp_path / 'shared' / 'data').mkdir(parents=True)
    main.mkdir()
    try:
        for args in (['init', '-q'], ['-c', 'user.email=a@b', '-c', 'user.name=a', 'commit',
                                      '-q', '--allow-empty', '-m', 'x'],
                     ['worktree', 'add', '-q', str(wt)]):
            subprocess.run(['git', *args], cwd=main, check=True, capture_output=True)
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f'git not usable here: {exc}')
    assert find_shared_data(wt, env={}).resolve() == (tmp_path / 'shared' / 'data').resolve()
