"""Shared fixtures: seeded random generators and the path to the shared benchmark data."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get('GA_ROS_SHARED_DATA', REPO.parent / 'shared' / 'data'))


@pytest.fixture(scope='session', autouse=True)
def _single_blas_thread():
    """As the entry points do (see ga_ros.runtime): small dense blocks, shared cores."""
    from ga_ros.runtime import limit_blas_threads
    with limit_blas_threads():
        yield


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(20051101)


@pytest.fixture
def pose_graph_dir() -> Path:
    d = SHARED_DATA / 'pose-graphs'
    if not d.is_dir():
        pytest.skip(f'shared pose-graph data not found at {d} (set GA_ROS_SHARED_DATA)')
    return d
