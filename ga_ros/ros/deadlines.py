"""Deadlines of the waits in the test harness and the tests (ROS-free, imports nothing of ROS).

A deadline only ends a wait that has already failed, so a generous one costs nothing when the
awaited event comes and keeps a loaded 2-core machine (a parallel build, other test runs)
from failing the suite. Every deadline of :mod:`ga_ros.ros.harness` and of the ROS tests is
``patience(seconds)``.
"""

from __future__ import annotations

import os

#: Factor on every deadline (environment variable ``GA_ROS_TEST_PATIENCE``, default 4).
PATIENCE = float(os.environ.get('GA_ROS_TEST_PATIENCE', '4'))


def patience(seconds: float) -> float:
    """``seconds`` of waiting as a deadline: times :data:`PATIENCE`."""
    return seconds * PATIENCE
