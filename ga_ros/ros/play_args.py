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
    p.add_argument('--delay', type=float, default=0.0,
                   help='extra seconds to wait before publishing (default 0)')
    p.add_argument('--wait-for-subscribers', type=float, default=10.0, metavar='SEC',
                   help='wait up to SEC seconds (default 10; 0: no wait) for a matched '
                        'subscriber before playing, and before exiting if none is left; a '
                        'warning if none came')
    p.add_argument('--delivery-timeout', type=float, default=60.0, metavar='SEC',
                   help='after the bag, wait up to SEC seconds (default 60) until every '
                        'measurement topic has a subscriber and every subscriber acknowledged '
                        'everything (a node restarted meanwhile gets the whole history again); '
                        'exit code 3, naming the topics, if not')
    p.add_argument('--no-end-signal', action='store_true',
                   help='do not send the end-of-input message on the measurements topic '
                        '(child_frame_id ga/track_end: the alignment node ends the last track)')
    p.add_argument('--sensor-qos', choices=('reliable', 'best_effort'), default='reliable',
                   help='QoS reliability of the image and camera-info publishers (default '
                        'reliable; best_effort as most camera drivers)')
    return p
