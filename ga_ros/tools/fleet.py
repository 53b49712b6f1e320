"""Several robots in one ROS graph (issue 14 item 2): each its own VO and alignment, one domain.

Each robot ``/robotN`` runs, as separate processes on one DDS domain:

* ``ga-ros play`` of its own stereo bag, its topics remapped into the namespace
  (``/stereo/...`` -> ``/robotN/stereo/...``; ``/clock`` -> ``/robotN/clock``: each robot has
  its own simulated time);
* ``vo_node`` and ``alignment_node`` with ``__ns:=/robotN``: their topics are relative
  (``ga/measurements``, ``ga/corrected_path``, ...), so they resolve inside the namespace; the
  TF frames get the robot's prefix (``robotN/map``, ``robotN/odom``, ...) since ``/tf`` is shared;
* ``python -m ga_ros.ros.mapping_node`` in the namespace, which records the measurements and
  corrected path of that robot and calls its ``alignment_node/finish_track`` once the
  measurements stop.

Afterwards each robot's last path is compared with the aligner fed, in-process, the measurements
its own mapping node recorded (same input, same deterministic aligner: identical). The robots'
bags carry disjoint stamp ranges, so a measurement or pose that crossed from one robot to the
other would be seen by its stamp.

This module never imports ROS: it starts processes.
"""

from __future__ import annotations

import json
import os
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from ga_ros import domains
from ga_ros.errors import GaError
from ga_ros.safe_write import check_destinations, open_log, write_json
from ga_ros.tools.multihost import REPO, _stop_all, _wait_line, compare_paths

#: The stereo topics of the sample bags (``ga_ros.replay.samples``), remapped per robot.
STEREO_TOPICS = ('/stereo/left/image_raw/compressed', '/stereo/right/image_raw/compressed',
                 '/stereo/left/camera_info', '/stereo/right/camera_info')


@dataclass
class RobotResult:
    """What one robot's mapping node received, and the check against its own replay.

    Attributes
    ----------
    name : namespace without the slash (``robot1``).
    bag : the stereo bag it was fed.
    measurements : measurements its mapping node recorded.
    stamp_range_ns : ``[first, last]`` stamp of those measurements (ns).
    path_poses : poses of the last corrected path.
    path_stamp_range_ns : ``[first, last]`` stamp of that path's poses (ns).
    replay_poses : poses of ``ga-ros replay`` of the recorded measurements.
    max_diff_vs_replay_m, max_rot_diff_vs_replay_rad : largest difference path vs replay.
    """

    name: str
    bag: str
    measurements: int = 0
    stamp_range_ns: list[int] = field(default_factory=list)
    path_poses: int = 0
    path_stamp_range_ns: list[int] = field(default_factory=list)
    replay_poses: int = 0
    max_diff_vs_replay_m: float | None = None
    max_rot_diff_vs_replay_rad: float | None = None


@dataclass
class FleetResult:
    """Outcome of :func:`run_fleet` (also written to ``summary.json``)."""

    ok: bool = False
    seconds: float = 0.0
    domain_id: int = 0
    robots: list[RobotResult] = field(default_factory=list)
    errors: list[str] = field(default_factory=list)


def robot_commands(name: str, bag: Path, out: Path, rate: float,
                   idle_s: float, timeout_s: float) -> dict[str, list[str]]:
    """The command lines of one robot's processes (``play``, ``vo``, ``alignment``,
    ``mapping``), all in namespace ``/name``. The mapping node's idle finish is armed by the
    file ``out / 'player_done'`` (created once the robot's player has exited)."""
    py, ns = sys.executable, f'/{name}'
    common = ['-r', f'__ns:={ns}', '-r', f'/clock:={ns}/clock']
    remap = [a for t in STEREO_TOPICS for a in ('-r', f'{t}:={ns}{t}')]
    frames = [f'{k}:={name}/{v}' for k, v in (('map_frame', 'map'), ('odom_frame', 'odom'),
                                                ('base_frame', 'base_link'))]
    return {
        'mapping': [py, '-m', 'ga_ros.ros.mapping_node', '--out', str(out / 'mapping'),
                    '--finish-after-idle', str(idle_s), '--timeout', str(timeout_s),
                    '--finish-armed-by', str(out / 'player_done'),
                    '--ros-args', '-r', f'__ns:={ns}'],
        'alignment': [py, '-m', 'ga_ros.ros.alignment_node', '--ros-args', *common,
                      '--params-file', str(REPO / 'config' / 'alignment.yaml'),
                      '-p', 'use_sim_time:=true', '-p', 'autosave:=false',
                      '-p', 'measurement_durability:=transient_local',
                      '-p', 'allow_finish_track:=true',  # the mapping node ends the survey
                      *[a for f in frames for a in ('-p', f)]],
        'vo': [py, '-m', 'ga_ros.ros.vo_node', '--ros-args', *common,
               '--params-file', str(REPO / 'config' / 'vo.yaml'), '-p', 'use_sim_time:=true',
               '-p', 'compressed:=true', '-p', 'image_queue:=200', '-p', 'pair_queue:=1000',
               # the sample cameras are their robots' base frames (play sends no /tf_static)
               '-p', 'assume_identity_extrinsic:=true',
               '-p', 'left_image_topic:=stereo/left/image_raw/compressed',
               '-p', 'right_image_topic:=stereo/right/image_raw/compressed',
               '-p', 'left_info_topic:=stereo/left/camera_info',
               '-p', 'right_info_topic:=stereo/right/camera_info'],
        'play': [py, '-m', 'ga_ros.ros.play', str(bag), '--rate', str(rate),
                 '--wait-for-subscribers', '30', '--topics', *STEREO_TOPICS,
                 '--ros-args', *common, *remap],
    }


def _spawn(argv: list[str], env: dict[str, str], log: Path):
    import subprocess

    out = open_log(log)  # closed with the process
    return subprocess.Popen(argv, env=env, stdout=out, stderr=subprocess.STDOUT,
                            start_new_session=True)


def run_fleet(out_dir: str | Path, bags: dict[str, Path], rate: float = 5.0,
              timeout_s: float = 180.0, domain_id: int | None = None,
              log=print) -> FleetResult:
    """Run every robot of ``bags`` (``{'robot1': bag, ...}``) at once on one domain, then
    compare each robot's path with the replay of its own recorded measurements.

    Parameters
    ----------
    out_dir : logs, each robot's mapping outputs (``<robot>/mapping``), replays, summary.json.
    bags : stereo bag of each robot (with the topics of :data:`STEREO_TOPICS`); give them
        disjoint stamp ranges for the crossing check to mean something.
    rate : ``ga-ros play --rate``.
    timeout_s : longest wait for all robots to finish.
    domain_id : ``ROS_DOMAIN_ID`` (default: one claimed machine-wide, :mod:`ga_ros.domains`).
    """
    out = Path(out_dir).resolve()
    out.mkdir(parents=True, exist_ok=True)
    check_destinations(out / 'summary.json')
    dom = int(domain_id if domain_id is not None else domains.domain_id('fleet'))
    res = FleetResult(domain_id=dom)
    env = {**os.environ, 'ROS_DOMAIN_ID': str(dom), 'PYTHONUNBUFFERED': '1'}
    t0 = time.monotonic()
    procs: dict[tuple[str, str], object] = {}
    cmds = {r: robot_commands(r, Path(b), out / r, rate, 3.0, timeout_s)
            for r, b in bags.items()}
    try:
        for r in bags:
            (out / r).mkdir(exist_ok=True)
            for role in ('mapping', 'alignment', 'vo'):
                procs[r, role] = _spawn(cmds[r][role], env, out / r / f'{role}.log')
        for r in bags:
            if not _wait_line(out / r / 'mapping.log', 'mapping_node: ready',
                              procs[r, 'mapping'], 90.0):
                raise GaError(f'{r}: the mapping node did not see its VO and alignment node '
                              f'within 90 s (see {out / r})')
        log(f'{len(bags)} robots up after {time.monotonic() - t0:.1f} s (domain {dom})')
        for r in bags:
            procs[r, 'play'] = _spawn(cmds[r]['play'], env, out / r / 'play.log')
        end = time.monotonic() + timeout_s
        mappers = [procs[r, 'mapping'] for r in bags]
        while any(p.poll() is None for p in mappers) and time.monotonic() < end:
            for r in bags:  # a robot's player has exited: arm its mapping node's idle finish
                if procs[r, 'play'].poll() is not None:
                    (out / r / 'player_done').touch()
            time.sleep(0.2)
        log(f'robots through after {time.monotonic() - t0:.1f} s')
        for r in bags:
            if procs[r, 'mapping'].poll() is None:
                res.errors.append(f'{r}: the mapping node did not finish within '
                                  f'{timeout_s:.0f} s')
    except GaError as exc:
        res.errors.append(str(exc))
    finally:
        _stop_all(list(procs.values()))
    for r, bag in bags.items():
        res.robots.append(_check_robot(r, Path(bag), out / r, res.errors))
    res.seconds = time.monotonic() - t0
    res.ok = not res.errors
    write_json(out / 'summary.json', asdict(res), indent=1)
    return res


def replay_recorded(bag: Path):
    """The corrected path of :class:`~ga_ros.core.window.TrackWindowAligner` (the node's
    defaults, ``config/alignment.yaml``) fed the measurements of a mapping node's bag in order,
    the last track finished: what the alignment node computes from the same input."""
    from ga_ros.core.window import AlignerConfig, TrackWindowAligner
    from ga_ros.io.bag import BagReader
    from ga_ros.replay.samples import MEASUREMENTS_TOPIC
    from ga_ros.replay.source import bag_measurements

    with BagReader(bag) as reader:
        ms = [it.measurement for it in bag_measurements(reader, MEASUREMENTS_TOPIC, [0])
              if it.measurement is not None]
    al = TrackWindowAligner(AlignerConfig())
    al.add_measurements(ms)
    al.finish_track()
    return al.corrected_path(), len(ms)


def _check_robot(name: str, bag: Path, out: Path, errors: list[str]) -> RobotResult:
    rr = RobotResult(name, str(bag))
    summary = out / 'mapping' / 'mapping.json'
    if not summary.exists() or not (out / 'mapping' / 'path.npz').exists():
        errors.append(f'{name}: the mapping node wrote no outputs')
        return rr
    summ = json.loads(summary.read_text())
    rr.measurements = int(summ['measurements'])
    if summ['status'] != 'finished':
        errors.append(f'{name}: mapping node status {summ["status"]!r}')
    got = np.load(out / 'mapping' / 'path.npz')
    T_live, stamps = got['T_world_node'], got['stamps_ns']
    rr.path_poses = len(T_live)
    if not rr.measurements or not rr.path_poses:
        errors.append(f'{name}: no measurement or no path recorded')
        return rr
    rr.path_stamp_range_ns = [int(stamps.min()), int(stamps.max())]
    ref, n = replay_recorded(out / 'mapping' / 'measurements')
    rr.replay_poses = len(ref.T_world_node)
    rr.stamp_range_ns = [int(ref.stamps_ns.min()), int(ref.stamps_ns.max())]
    if n != rr.measurements or not np.array_equal(ref.stamps_ns, stamps):
        errors.append(f'{name}: path of {rr.path_poses} poses, the replay of its {n} recorded '
                      f'measurements {rr.replay_poses} (or other stamps)')
        return rr
    rr.max_diff_vs_replay_m, rr.max_rot_diff_vs_replay_rad = compare_paths(T_live,
                                                                           ref.T_world_node)
    if rr.max_diff_vs_replay_m > 1e-6 or rr.max_rot_diff_vs_replay_rad > 1e-8:
        errors.append(f'{name}: path differs from the replay of its measurements by '
                      f'{rr.max_diff_vs_replay_m:.3g} m')
    return rr


def format_result(res: FleetResult) -> str:
    """A short human-readable report of a run."""
    lines = [f'fleet run on domain {res.domain_id}: {"OK" if res.ok else "FAILED"} in '
             f'{res.seconds:.0f} s']
    for r in res.robots:
        lines.append(f'  /{r.name}: {r.measurements} measurements (stamps {r.stamp_range_ns}), '
                     f'path {r.path_poses} poses, replay {r.replay_poses} poses, max difference '
                     f'{r.max_diff_vs_replay_m} m / {r.max_rot_diff_vs_replay_rad} rad')
    lines += [f'  error: {e}' for e in res.errors]
    return '\n'.join(lines)


def make_second_bag(path: str | Path, stamp_offset_s: float = 10_000.0,
                    positions_per_swath: int = 12, seed: int = 5) -> Path:
    """A second stereo survey, different from the sample (2 double tracks of
    ``positions_per_swath`` frames a swath, shorter turns, terrain of ``seed``), with stamps
    ``stamp_offset_s`` after the sample's; returns its path."""
    from ga_ros.replay import samples

    base = samples.BASE_STAMP_NS
    samples.BASE_STAMP_NS = base + int(stamp_offset_s * 1e9)
    try:
        return samples.make_stereo_bag(path, samples.StereoSampleConfig(
            n_tracks=2, positions_per_swath=positions_per_swath, turn_positions=8, seed=seed),
            overwrite=True)
    finally:
        samples.BASE_STAMP_NS = base


def main(argv: list[str] | None = None) -> int:
    """``python -m ga_ros.tools.fleet [--out DIR] [--rate R]``: two robots, the stereo sample
    and a second survey (:func:`make_second_bag`)."""
    import argparse

    p = argparse.ArgumentParser(description='Two namespaced robots (VO + alignment each) on '
                                            'one DDS domain.', allow_abbrev=False)
    p.add_argument('--out', default='out/fleet')
    p.add_argument('--rate', type=float, default=5.0)
    p.add_argument('--timeout', type=float, default=240.0)
    a = p.parse_args(argv)
    out = Path(a.out)
    try:
        second = make_second_bag(out / 'robot2_bag')
        res = run_fleet(out, {'robot1': REPO / 'bags' / 'stereo_sample', 'robot2': second},
                        a.rate, a.timeout)
    except GaError as exc:
        print(f'fleet: {exc}', file=sys.stderr)
        return 1
    print(format_result(res))
    return 0 if res.ok else 1


if __name__ == '__main__':
    sys.exit(main())
