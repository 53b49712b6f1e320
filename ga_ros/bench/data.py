"""Where the benchmarks find the shared data (public pose graphs, real odometry): the directory
``$GA_ROS_SHARED_DATA``, else ``shared/data`` beside the repository's folder (a checkout's
layout; set the variable when the package is installed elsewhere)."""

from __future__ import annotations

import os
from pathlib import Path

#: the shared data directory (``README.md``, ``pose-graphs/``, ``real/``)
SHARED_DATA = Path(os.environ.get('GA_ROS_SHARED_DATA',
                                  Path(__file__).resolve().parents[2].parent / 'shared' / 'data'))
#: the public g2o benchmarks with their reference optima
POSE_GRAPHS = SHARED_DATA / 'pose-graphs'
