"""Arguments of ``ga-ros play`` and ``python -m ga_ros.ros.play`` (no rclpy import here, so the
CLI can register the command without loading ROS)."""

from __future__ import annotations

import argparse
from pathlib import Path


def add_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the play options to ``p`` and return it."""
    p.add_argument('bag', type=Path, help='rosbag2 directory, or a .mcap / .db3 file')
    p.add_argument('--rate', type=float, default=1.0,
                   help='speed factor (1 = real time); 0 = as fast as subscribers keep up')
    p.add_argument('--topics', nargs='+', default=[], help='only these topics')
    p.add_argument('--no-clock', action='store_true', help='do not publish /clock')
    p.add_argument('--delay', type=float, default=1.0,
                   help='seconds to wait for discovery before publishing (default 1)')
    p.add_argument('--wait-for-subscribers', type=float, default=0.0, metavar='SEC',
                   help='wait up to SEC seconds for a first subscriber')
    return p
