"""Shared fixtures: seeded random generators and the shared benchmark data, found only through
:data:`ga_ros.bench.data.SHARED_DATA` (its one definition: ``$GA_ROS_SHARED_DATA``, else
``shared/data`` beside the checkout or its main checkout); a test that needs it skips, saying
where it looked, when it is absent."""

from __future__ import annotations

import os
import sys
from pathlib import Path

import numpy as np
import pytest

from ga_ros.bench.data import SHARED_DATA

REPO = Path(__file__).resolve().parents[1]
TEST = Path(__file__).resolve().parent

# The tests mirror the package's folders (test/core/window/ tests ga_ros/core/window/, ...).
# Shared helpers (solver_problems.py here, fixtures builders of one test module used by
# another) are imported by module name: every test folder is on sys.path, whichever test
# runs first or alone.
for _d in sorted({p.parent for p in TEST.rglob('test_*.py')} | {TEST}):
    if str(_d) not in sys.path:
        sys.path.insert(0, str(_d))


# A window update failing with anything but a GaError is a bug: it raises in tests (and in the
# nodes they start) instead of being reported in the update's result only. Tests that inject
# such a failure on purpose set ``aligner.strict = False``.
os.environ.setdefault('GA_ROS_STRICT_UPDATES', '1')


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


#: Test modules that take more than a few seconds on a 2-core machine (multi-process ROS
#: graphs, whole replays, Monte-Carlo runs): marked ``slow`` with every ``ros`` test, so that
#: ``-m "not slow"`` is the quick subset for everyday work. CI runs everything.
SLOW_MODULES = {
    'test/ros/test_fault_catalogue.py', 'test/ros/test_alignment_node.py',
    'test/core/window/test_window.py', 'test/core/window/test_aligner_guards.py',
    'test/pipeline/test_recovery.py', 'test/inputs/test_multiple_sources.py',
    'test/replay/test_replay_inputs.py', 'test/replay/test_fixes_replay.py',
    'test/pipeline/test_persistence_failures.py', 'test/report/test_reproduce.py',
    'test/core/test_gaps.py', 'test/core/window/test_honest_covariances.py',
    'test/package/test_packaging.py', 'test/package/test_launch_files.py',
    'test/core/window/test_refinement.py', 'test/core/window/test_persistence.py',
    'test/replay/test_replay_stereo.py', 'test/core/window/test_quality_wiring.py',
    'test/replay/test_replay.py', 'test/io/test_groundtruth.py',
    'test/pipeline/test_map_to_odom.py', 'test/bench/test_bench_scale.py',
    'test/core/test_frames.py', 'test/pipeline/test_camera_beside_odometry.py',
    'test/core/window/test_refinement_horizon.py', 'test/replay/test_replay_live.py',
    'test/replay/test_real_camera_bags.py', 'test/mapping/test_mosaic_replay.py',
    'test/core/window/test_refinement_relinearize.py',
}


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark ``slow`` the tests of :data:`SLOW_MODULES` and every ``ros`` test."""
    for item in items:
        rel = Path(str(item.path)).resolve().relative_to(REPO).as_posix()
        if rel in SLOW_MODULES or item.get_closest_marker('ros') is not None:
            item.add_marker(pytest.mark.slow)


def test_slow_modules_exist() -> None:
    """Every module named slow is there (a renamed one would silently join the quick set)."""
    missing = sorted(m for m in SLOW_MODULES if not (REPO / m).is_file())
    assert not missing, missing
