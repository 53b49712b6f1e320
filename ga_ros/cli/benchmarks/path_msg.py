"""Size and cost of the alignment node's path messages at survey scale (issue 14 item 3).

Builds the ``nav_msgs/Path`` the node publishes (``conversions.path_to_msg``) for the full
path of ``--poses`` nodes and for a window of ``--window-poses`` movable nodes
(``ga/window_path``), and prints the serialized size (CDR, what DDS sends), the time to build
the rclpy message and serialize it, and the time of :func:`ga_ros.io.cdr.path_cdr` (the bytes
the node publishes for the full path)::

    ga-ros bench path-msg --poses 100000 --window-poses 5000
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ga_ros.geometry import se3
from ga_ros.io.cdr import path_cdr


def figures(n: int, frame_id: str) -> tuple[float, float, float, int]:
    """(build s, serialize s, path_cdr s, bytes) of a Path of ``n`` poses."""
    from rclpy.serialization import serialize_message  # ROS only when this benchmark runs

    from ga_ros.ros import conversions as conv
    rng = np.random.default_rng(0)
    T = se3.exp(rng.normal(size=(n, 6)))
    stamps = 1_700_000_000 * 10**9 + 500_000_000 * np.arange(n, dtype=np.int64)
    t0 = time.perf_counter()
    msg = conv.path_to_msg(T, stamps, frame_id)
    t1 = time.perf_counter()
    data = serialize_message(msg)
    t2 = time.perf_counter()
    raw = path_cdr(T, stamps, frame_id)
    t3 = time.perf_counter()
    assert len(raw) == len(data)
    return t1 - t0, t2 - t1, t3 - t2, len(data)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog='ga-ros bench path-msg', description=__doc__.split('\n\n')[0], allow_abbrev=False)
    p.add_argument('--poses', type=int, default=100_000)
    p.add_argument('--window-poses', type=int, default=5_000)
    p.add_argument('--frame-id', default='map')
    a = p.parse_args(argv)
    print('| path | poses | CDR bytes | bytes/pose | path_to_msg s | serialize s | path_cdr s |')
    print('|---|---:|---:|---:|---:|---:|---:|')
    for name, n in (('full (ga/corrected_path)', a.poses),
                    ('window (ga/window_path)', a.window_poses)):
        build, ser, raw, size = figures(n, a.frame_id)
        print(f'| {name} | {n:,} | {size:,} | {size / max(n, 1):.1f} | {build:.2f} | '
              f'{ser:.3f} | {raw:.3f} |')
    return 0

