"""Formatting and lint (STYLE habit 12): ``ruff check`` with the repository's ``ruff.toml`` over
the package, the tests and the scripts, so style is never a review topic."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]


def _ruff() -> list[str]:
    exe = Path(sys.executable).with_name('ruff')
    if exe.exists():
        return [str(exe)]
    found = shutil.which('ruff')
    if found is None:
        pytest.skip('ruff not installed (pip install -r requirements.txt)')
    return [found]


def test_ruff_is_clean():
    proc = subprocess.run([*_ruff(), 'check', 'ga_ros', 'test', 'scripts'], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
