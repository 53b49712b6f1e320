"""``ga-ros play BAG [--rate R]``: publish a bag into a running ROS 2 graph, with ``/clock``.

For users without ``ros2 bag play`` (the ros2 CLI is not packaged here). The ROS side lives in
:mod:`ga_ros.ros.play`, imported only when the command runs.
"""

from __future__ import annotations

import argparse

from ga_ros.cli.commands import SUMMARIES
from ga_ros.ros.play_args import add_arguments


def register(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        'play', help=SUMMARIES['play'],
        description='Publish every message of a rosbag2 bag (mcap or sqlite3) with /clock at a '
                    'chosen rate, or as fast as the subscribers keep up (--rate 0); exits when '
                    'the bag is done. Nodes should run with use_sim_time:=true.',
        allow_abbrev=False)
    add_arguments(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ga_ros.ros.play import run as run_play

    return run_play(args)
