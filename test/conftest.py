"""Shared fixtures: seeded random generators and the path to the shared benchmark data."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
TEST = Path(__file__).resolve().parent

# The tests mirror the package's folders (test/core/window/ tests ga_ros/core/window/, ...).
# Shared helpers (solver_problems.py here, fixtures builders of one test module used by
# another) are imported by module name: every test folder is on sys.path, whichever test
# runs first or alone.
for _d in sorted({p.parent for p in TEST.rglob('test_*.py')} | {TEST}):
    if str(_d) not in sys.path:
        sys.path.insert(0, str(_d))
SHARED_DATA = Path(os.environ.get('GA_ROS_SHARED_DATA', REPO.parent / 'shared' / 'data'))


@pytest.fixture(scope='session', autouse=True)
def _single_blas_thread():
    """As the entry points do (see ga_ros.runtime): small dense blocks, shared cores."""
    from ga_ros.runtime import limit_blas_threads
    with limit_blas_threads():
        yield


@pytest.fixture(autouse=True)
def _ros_home(tmp_path_factory, monkeypatch):
    """Each test its own ``ROS_HOME`` (the alignment node keeps its state there by default):
    nothing is written to ``~/.ros``, no state is shared between tests."""
    monkeypatch.setenv('ROS_HOME', str(tmp_path_factory.mktemp('ros_home')))


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20051101)


@pytest.fixture
def pose_graph_dir() -> Path:
    d = SHARED_DATA / 'pose-graphs'
    if not d.is_dir():
        pytest.skip(f'shared pose-graph data not found at {d} (set GA_ROS_SHARED_DATA)')
    return d
