"""``ga-ros bench outputs``: what the replay's outputs cost per update, early against late in a
long run with fixes (issue 36: no per-update step reads the whole history).

The bag (written into a temporary folder): a ground robot drives ``--laps`` laps of a 20 x 10 m
rectangle at 1 m/s, wheel odometry (``nav_msgs/Odometry``, no covariance: the default noise)
at ``--rate`` Hz drifting in heading by 2e-4 rad per message, and a position fix
(``PoseWithCovarianceStamped`` in ``map``, 0.3 m per axis, yaw unknown) every ``--fix-every``
messages; each used fix ends a track. It is replayed as ``ga-ros replay BAG --odom-topic /odom
--absolute-topic /fix`` does (default settings, final batch included).

Printed, per quarter of the run's track updates (mean):

* ``outputs_cpu_ms`` of ``summary.json`` (the CPU of the replay's thread writing the outputs of
  one update: the corrected path message, the corrections, the network markers,
  ``map -> odom``);
* ``update_ms`` (the aligner's update, wall time, including the wait for a background
  refinement);

and the CPU seconds of all processes (this one and its children) over the whole replay. The
machine's load enters every wall time; the CPU figures are the ones to compare across runs.
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import resource
import tempfile
from pathlib import Path

import numpy as np

from ga_ros.geometry import se3
from ga_ros.io.bag_writer import BagWriter, odometry_msg, pose_with_covariance_msg

LAP_M = 60.0   # the rectangle's perimeter (m), driven at 1 m/s


def rectangle_poses(t_s: np.ndarray) -> np.ndarray:
    """(n, 4, 4) true poses at ``t_s`` (s): a 20 x 10 m rectangle at 1 m/s, heading along."""
    d = np.mod(t_s, LAP_M)
    legs = [(0, 20, (0, 0), (1, 0), 0.0), (20, 30, (20, 0), (0, 1), np.pi / 2),
            (30, 50, (20, 10), (-1, 0), np.pi), (50, 60, (0, 10), (0, -1), -np.pi / 2)]
    xy, yaw = np.zeros((d.size, 2)), np.zeros(d.size)
    for a, b, start, direction, heading in legs:
        on = (d >= a) & (d < b)
        xy[on] = np.asarray(start) + (d[on, None] - a) * np.asarray(direction)
        yaw[on] = heading
    return se3.from_translation_rotvec(np.c_[xy, np.zeros(d.size)],
                                       np.c_[np.zeros((d.size, 2)), yaw])


def write_bag(path: Path, laps: float, rate_hz: float, fix_every: int, seed: int = 1) -> int:
    """The bag of the module docstring; returns the number of odometry messages."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, laps * LAP_M, 1.0 / rate_hz)
    T_true = rectangle_poses(t)
    drift = se3.from_translation_rotvec(np.zeros(3), np.array([0.0, 0.0, 2e-4]))
    stamps = 1_765_000_000_000_000_000 + np.round(t * 1e9).astype(np.int64)
    fix_cov = np.zeros((6, 6))
    fix_cov[0, 0] = fix_cov[1, 1] = 0.3 ** 2
    fix_cov[2, 2] = 1.0
    T_odom = T_true[0].copy()
    with BagWriter(path) as bag:
        for k, s in enumerate(stamps.tolist()):
            if k:
                T_odom = T_odom @ se3.relative(T_true[k - 1], T_true[k]) @ drift
            bag.write('/odom', 'nav_msgs/msg/Odometry',
                      odometry_msg(T_odom, np.zeros((6, 6)), 'odom', 'base_link', s), s)
            if k % fix_every == 7:
                T = T_true[k].copy()
                T[:2, 3] += rng.normal(0, 0.3, 2)
                bag.write('/fix', 'geometry_msgs/msg/PoseWithCovarianceStamped',
                          pose_with_covariance_msg(T, fix_cov, 'map', s), s + 1000)
    return len(stamps)


def _cpu_s() -> float:
    a, b = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return a.ru_utime + a.ru_stime + b.ru_utime + b.ru_stime


def quarters(values: list[float]) -> list[float]:
    """Mean of each quarter of ``values`` (in order)."""
    return [float(np.mean(q)) if q.size else float('nan')
            for q in np.array_split(np.asarray(values, float), 4)]


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``ga-ros bench outputs``."""
    p = argparse.ArgumentParser(prog='ga-ros bench outputs', description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter,
                                allow_abbrev=False)
    p.add_argument('--laps', type=float, default=80.0, help='laps of the rectangle (default 80)')
    p.add_argument('--rate', type=float, default=5.0, help='odometry rate, Hz (default 5)')
    p.add_argument('--fix-every', type=int, default=50,
                   help='odometry messages between fixes (default 50: 10 s at 5 Hz)')
    p.add_argument('--json', action='store_true', help='print one JSON object')
    return p


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``ga-ros bench outputs``."""
    args = build_parser().parse_args(argv)
    from ga_ros.cli.main import main as ga_ros_main

    with tempfile.TemporaryDirectory(prefix='ga_bench_outputs_') as tmp:
        bag = Path(tmp) / 'bag'
        n = write_bag(bag, args.laps, args.rate, args.fix_every)
        cpu0 = _cpu_s()
        with contextlib.redirect_stdout(io.StringIO()):
            rc = ga_ros_main(['replay', str(bag), '--odom-topic', '/odom', '--absolute-topic',
                              '/fix', '--out', str(Path(tmp) / 'out'), '--no-plot',
                              '--no-progress'])
        cpu = _cpu_s() - cpu0
        if rc != 0:
            print(f'ga-ros bench outputs: the replay failed (exit {rc})')
            return rc
        summary = json.loads((Path(tmp) / 'out' / 'summary.json').read_text())
    ups = summary['updates']
    out = {'odometry_messages': n, 'nodes': summary.get('n_nodes'), 'updates': len(ups),
           'outputs_cpu_ms_per_quarter': quarters([u['outputs_cpu_ms'] for u in ups]),
           'update_ms_per_quarter': quarters([u['update_ms'] for u in ups]),
           'replay_cpu_s_all_processes': cpu}
    if args.json:
        print(json.dumps(out))
        return 0
    fmt = ' / '.join
    print(f'replay of {n} odometry messages, a fix every {args.fix_every}: {out["nodes"]} '
          f'nodes, {len(ups)} track updates')
    print('per update, mean over each quarter of the run (first / second / third / last):')
    print('  outputs CPU (replay thread: path, corrections, markers, map -> odom): '
          + fmt(f'{v:.2f}' for v in out['outputs_cpu_ms_per_quarter']) + ' ms')
    print('  aligner update_ms (wall, incl. refinement wait):                     '
          + fmt(f'{v:.1f}' for v in out['update_ms_per_quarter']) + ' ms')
    print(f'CPU of all processes over the replay: {cpu:.1f} s')
    return 0
