"""The package built with ``colcon build`` in a temporary workspace (once per test session):
what a ROS user gets from ``colcon build && source install/setup.bash``."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


@dataclass(frozen=True)
class Workspace:
    """A built colcon workspace: its ``install`` folder and the environment to run it in
    (``PATH`` with colcon's folder; source ``install/setup.bash`` on top)."""

    install: Path
    env: dict[str, str]

    def sourced(self, command: str) -> list[str]:
        """``bash -c`` of ``command`` after ``source install/setup.bash``."""
        return ['bash', '-c', f'source "{self.install}/setup.bash" && {command}']


def copy_package(dst: Path) -> None:
    """The package's sources (without build products and local data) into ``dst``."""
    shutil.copytree(REPO, dst, dirs_exist_ok=True, ignore=shutil.ignore_patterns(
        '.venv', '.git', 'out', 'build', 'install', 'log', '__pycache__', '*.egg-info',
        '.pytest_cache', 'bags'))


def colcon_executable() -> Path | None:
    """colcon beside the interpreter (the venv's), or None."""
    colcon = Path(sys.executable).parent / 'colcon'
    return colcon if colcon.exists() else None


def build_workspace(root: Path) -> Workspace:
    """Copy the package into ``root/src/ga_ros`` and ``colcon build`` it there. Raises
    RuntimeError with colcon's output if the build fails."""
    colcon = colcon_executable()
    if colcon is None:
        raise RuntimeError('no colcon executable beside the interpreter')
    src = root / 'src' / 'ga_ros'
    src.mkdir(parents=True)
    copy_package(src)
    env = dict(os.environ, PATH=f'{colcon.parent}{os.pathsep}{os.environ.get("PATH", "")}')
    build = subprocess.run([str(colcon), 'build'], cwd=root, env=env, capture_output=True,
                           text=True, timeout=600)
    if build.returncode != 0:
        raise RuntimeError(f'colcon build failed:\n{build.stdout}\n{build.stderr}')
    return Workspace(root / 'install', env)
