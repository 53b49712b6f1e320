"""Benchmark: ``map_node``'s update cost against the keyframes moved and the map's size.

A synthetic survey (a downward camera over a plane with relief, keyframes 4 m apart on a
lawnmower grid, each cloud ``--points`` points over a 10 m x 10 m footprint, so neighbours
overlap) fills a :class:`~ga_ros.mapping.cloud_map.KeyframeCloudMap` of ``--voxel`` m voxels with
N keyframes, for each N of ``--sizes`` (up to 5,000). Then, per N and per k of ``--moved``,
``--repeats`` corrections each move k keyframes drawn at random from the whole map (a few cm,
a few mrad: what a correction does) and :meth:`~ga_ros.mapping.cloud_map.KeyframeCloudMap.
set_poses` re-anchors them. Printed per N: the voxels and bytes held, the CPU time of one
update of k moved keyframes (mean over the repeats), the CPU time to build the whole map from
scratch from the same poses (what a consumer of the whole path would do after every update),
and the CPU time of :meth:`~ga_ros.mapping.cloud_map.KeyframeCloudMap.cloud` (the points to
publish, proportional to the voxels, paid once per ``publish_period_sec``, not per update).

Then the live mosaic's table (:mod:`ga_ros.bench.map_mosaic`: update cost for the same ``--moved``
counts and bytes held per keyframe, at ``--mosaic-sizes`` keyframes fed; ``--mosaic-sizes ''``
skips it, ``--sizes ''`` skips the cloud map's). With ``--drift N``, the live mosaic whose old
keyframes keep moving (:func:`ga_ros.bench.map_mosaic.run_drift`: merged when settled against
merged by age, the final mosaic against the one of the final poses).

CPU: ``time.process_time`` (this process, every thread; nothing else runs in it).

Run: ``ga-ros bench map [--sizes 500,1000,2000,5000] [--moved 1,10,100] [--points 500]
[--voxel 0.2] [--repeats 20] [--mosaic-sizes 1000,5000] [--mosaic-live 500]
[--mosaic-points 1000] [--mosaic-image 320] [--mosaic-repeats 5] [--drift 600 --drift-live 300
--drift-sigma 0.3 --drift-decay 0.7]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from ga_ros.bench import map_mosaic
from ga_ros.geometry import se3
from ga_ros.mapping.cloud_map import CloudMapConfig, map_from_poses


def survey(n: int, points: int, seed: int = 0) -> tuple[np.ndarray, dict]:
    """``(T_map_kf (n, 4, 4), clouds {key: (points, intensity)})`` of the synthetic survey
    (module docstring); keys 0..n-1."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    T = np.empty((n, 4, 4))
    clouds = {}
    for k in range(n):
        row, col = divmod(k, side)
        x = 4.0 * (col if row % 2 == 0 else side - 1 - col)
        T[k] = se3.from_translation_rotvec(np.array([x, 4.0 * row, 0.0]),
                                           rng.normal(0, 0.01, 3))
        xy = rng.uniform(-5, 5, (points, 2))
        z = 0.5 * np.sin(0.3 * (xy[:, 0] + x)) + rng.normal(0, 0.05, points)
        clouds[k] = (np.c_[xy, z].astype(np.float32),
                     rng.uniform(0, 255, points).astype(np.float32))
    return T, clouds


def main(argv: list[str] | None = None) -> int:
    """``ga-ros bench map``: print the table of the module docstring."""
    ap = argparse.ArgumentParser(prog='ga-ros bench map', description=__doc__.split('\n\n')[0],
                                 allow_abbrev=False)
    ap.add_argument('--sizes', default='500,1000,2000,5000',
                    help='keyframes in the map, comma-separated')
    ap.add_argument('--moved', default='1,10,100', help='keyframes moved per update')
    ap.add_argument('--points', type=int, default=500, help='points per keyframe cloud')
    ap.add_argument('--voxel', type=float, default=0.2, help='map voxel edge (m)')
    ap.add_argument('--repeats', type=int, default=20, help='updates timed per cell')
    ap.add_argument('--mosaic-sizes', default='1000,5000',
                    help="keyframes fed to the live mosaic, comma-separated ('': skip it)")
    ap.add_argument('--mosaic-live', type=int, default=500,
                    help='mosaic_max_live_keyframes (0: no merging)')
    ap.add_argument('--mosaic-points', type=int, default=1000,
                    help="cloud points per keyframe for the mosaic's ground")
    ap.add_argument('--mosaic-image', type=int, default=320,
                    help='keyframe image width (px; height 3/4 of it)')
    ap.add_argument('--mosaic-repeats', type=int, default=5,
                    help='mosaic updates timed per cell')
    ap.add_argument('--drift', type=int, default=0,
                    help='keyframes of the live mosaic run whose old keyframes keep moving '
                         '(0: skip it)')
    ap.add_argument('--drift-live', type=int, default=300,
                    help='mosaic_max_live_keyframes of that run')
    ap.add_argument('--drift-sigma', type=float, default=0.3,
                    help="that run's error of a keyframe when placed (m per axis)")
    ap.add_argument('--drift-decay', type=float, default=0.7,
                    help="that run's error left after each later track (fraction)")
    a = ap.parse_args(argv)
    sizes = [int(v) for v in a.sizes.split(',') if v]
    moved = [int(v) for v in a.moved.split(',')]
    mosaic_sizes = [int(v) for v in a.mosaic_sizes.split(',') if v]
    if sizes:
        _cloud_table(a, sizes, moved)
    if mosaic_sizes:
        map_mosaic.print_table(mosaic_sizes, moved, a.mosaic_live, a.mosaic_image,
                               a.mosaic_points, a.mosaic_repeats)
    if a.drift:
        map_mosaic.print_drift(a.drift, a.drift_live, a.mosaic_image, a.mosaic_points,
                               a.drift_sigma, a.drift_decay)
    return 0


def _cloud_table(a: argparse.Namespace, sizes: list[int], moved: list[int]) -> None:
    """The cloud map's table (module docstring)."""
    cfg = CloudMapConfig(voxel_m=a.voxel, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                         max_live_keyframes=0)
    rng = np.random.default_rng(1)
    T_all, clouds_all = survey(max(sizes), a.points)
    print(f'map_node update cost: {a.points} points per keyframe, voxel {a.voxel:g} m; CPU = '
          'time.process_time (this process, all threads), mean over '
          f'{a.repeats} updates per cell')
    head = ' | '.join(f'update, {k} moved' for k in moved)
    print(f'| keyframes in map | voxels | MB held | {head} | rebuild from scratch | '
          'cloud() (publish) |')
    print('|---:|---:|---:|' + '---:|' * len(moved) + '---:|---:|')
    per_kf: dict[int, list[float]] = {k: [] for k in moved}
    for n in sizes:
        T = T_all[:n].copy()
        clouds = {k: clouds_all[k] for k in range(n)}
        t0 = time.process_time()
        m = map_from_poses(cfg, np.arange(n), T, clouds)
        rebuild = time.process_time() - t0
        cells = []
        for k in moved:
            k = min(k, n)
            total = 0.0
            for _ in range(a.repeats):
                keys = rng.choice(n, size=k, replace=False)
                dT = se3.from_translation_rotvec(rng.normal(0, 0.03, (k, 3)),
                                                 rng.normal(0, 0.003, (k, 3)))
                T[keys] = T[keys] @ dT
                t0 = time.process_time()
                up = m.set_poses(keys, T[keys])
                total += time.process_time() - t0
                assert up.moved == k
            cells.append(total / a.repeats)
            per_kf[k].append(total / a.repeats / k)
        t0 = time.process_time()
        cloud = m.cloud()
        publish = time.process_time() - t0
        row = ' | '.join(f'{1e3 * c:.2f} ms' for c in cells)
        print(f'| {n:,} | {len(cloud):,} | {m.nbytes() / 1e6:.1f} | {row} | '
              f'{rebuild:.2f} s | {1e3 * publish:.0f} ms |')
    print('CPU per moved keyframe (ms), by map size ' + ', '.join(f'{n:,}' for n in sizes) + ':')
    for k in moved:
        print(f'  {k:>4} moved: ' + ', '.join(f'{1e3 * v:.3f}' for v in per_kf[k])
              + f'   (largest / smallest map: {per_kf[k][-1] / per_kf[k][0]:.2f})')
