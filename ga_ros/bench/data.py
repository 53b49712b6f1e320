"""Where the benchmarks find the shared data (public pose graphs, real odometry).

The directory ``$GA_ROS_SHARED_DATA`` when set; else ``shared/data`` beside the repository's
folder (a checkout's layout: ``<dir>/main`` and ``<dir>/shared/data``), or beside the main
checkout's folder when the repository is a git worktree elsewhere (its ``.git`` file names the
main checkout's ``.git`` directory). :data:`SHARED_DATA` is the first of these that exists (the
first candidate if none does: tests skip, saying where they looked); :func:`shared_data` raises
an error that says what to do when none exists.
"""

from __future__ import annotations

import os
from pathlib import Path

from ga_ros.errors import InputError

#: The environment variable that names the shared data directory.
SHARED_DATA_ENV = 'GA_ROS_SHARED_DATA'
#: The repository's folder (a checkout or a git worktree) holding this package.
REPO = Path(__file__).resolve().parents[2]


def main_checkout(repo: Path) -> Path | None:
    """The main checkout's folder of the git worktree ``repo`` (its ``.git`` is a file
    ``gitdir: <main>/.git/worktrees/<name>``, whose ``commondir`` names ``<main>/.git``);
    ``None`` when ``repo`` is not a worktree or its files cannot be read. Reads the files only
    (no ``git`` process)."""
    dot_git = repo / '.git'
    try:
        if not dot_git.is_file():
            return None
        text = dot_git.read_text(encoding='utf-8').strip()
        if not text.startswith('gitdir:'):
            return None
        gitdir = Path(text[len('gitdir:'):].strip())
        gitdir = gitdir if gitdir.is_absolute() else repo / gitdir
        common_file = gitdir / 'commondir'
        common = (gitdir / common_file.read_text(encoding='utf-8').strip()
                  if common_file.is_file() else gitdir.parent.parent)
        common = common.resolve()
    except OSError:
        return None
    return common.parent if common.name == '.git' else None


def candidates(repo: Path = REPO, env: dict[str, str] | None = None) -> list[Path]:
    """The shared data directories to try, in order (module doc): ``$GA_ROS_SHARED_DATA``
    alone when set, else ``shared/data`` beside ``repo`` and beside its main checkout."""
    env = os.environ if env is None else env
    given = env.get(SHARED_DATA_ENV, '')
    if given:
        return [Path(given)]
    out = [repo.parent / 'shared' / 'data']
    main = main_checkout(repo)
    if main is not None and main.parent / 'shared' / 'data' not in out:
        out.append(main.parent / 'shared' / 'data')
    return out


def find_shared_data(repo: Path = REPO, env: dict[str, str] | None = None) -> Path | None:
    """The first of :func:`candidates` that is a directory, or ``None``."""
    return next((p for p in candidates(repo, env) if p.is_dir()), None)


def shared_data(repo: Path = REPO, env: dict[str, str] | None = None) -> Path:
    """The shared data directory (:func:`find_shared_data`).

    Raises
    ------
    InputError
        None of the candidates exists: the message lists them and says to set
        ``GA_ROS_SHARED_DATA``.
    """
    found = find_shared_data(repo, env)
    if found is None:
        looked = ', '.join(str(p) for p in candidates(repo, env))
        raise InputError(f'shared data directory not found (looked in {looked}): set '
                         f'{SHARED_DATA_ENV} to the folder holding pose-graphs/ and real/')
    return found


#: the shared data directory (``README.md``, ``pose-graphs/``, ``real/``)
SHARED_DATA = find_shared_data() or candidates()[0]
#: the public g2o benchmarks with their reference optima
POSE_GRAPHS = SHARED_DATA / 'pose-graphs'
