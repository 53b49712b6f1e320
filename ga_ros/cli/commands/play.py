"""``ga-ros play BAG [--rate R]``: publish a bag into a running ROS 2 graph, with ``/clock``.

For users without ``ros2 bag play`` (the ros2 CLI is not packaged here). The ROS side lives in
:mod:`ga_ros.ros.play`, imported only when the command runs.
"""

from __future__ import annotations

import argparse
from pathlib import Path


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        'play', help='publish a bag live (with /clock) into a running ROS 2 graph',
        description='Publish every message of a rosbag2 bag (mcap or sqlite3) with /clock at a '
                    'chosen rate, or as fast as the subscribers keep up (--rate 0); exits when '
                    'the bag is done. Nodes should run with use_sim_time:=true.')
    add_arguments(p)
    p.set_defaults(func=run)


def add_arguments(p: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Arguments of ``ga-ros play`` (shared with ``python -m ga_ros.ros.play``)."""
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


def run(args: argparse.Namespace) -> int:
    from ga_ros.ros.play import run as run_play

    return run_play(args)
