"""Fixtures of the package tests: the colcon workspace, built once per session."""

from __future__ import annotations

import pytest
from colcon_workspace import Workspace, build_workspace, colcon_executable


@pytest.fixture(scope='session')
def colcon_workspace(tmp_path_factory: pytest.TempPathFactory) -> Workspace:
    """The package built by ``colcon build`` in a temporary workspace (skips without colcon)."""
    pytest.importorskip('colcon_core')
    pytest.importorskip('colcon_ros')
    if colcon_executable() is None:
        pytest.skip('no colcon executable beside the interpreter')
    return build_workspace(tmp_path_factory.mktemp('ws'))
