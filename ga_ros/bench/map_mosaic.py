"""Benchmark: the live mosaic of ``map_node`` (:class:`ga_ros.pipeline.mosaic_map.LiveMosaic`)
against the keyframes moved and the keyframes fed, and the bytes it holds.

A synthetic survey: a downward camera (``--mosaic-image`` px wide, 4:3, focal length = width,
so a 20 m high camera sees 20 m x 15 m) over a plane with 0.5 m of relief, keyframes 4 m apart
on a lawnmower grid (neighbours overlap), each with a random-texture grey image and a cloud of
``--mosaic-points`` ground points in its camera's frame; orthorectified on the clouds' height
model (the node's default) at 0.1 m per pixel. N keyframes (each of ``--mosaic-sizes``) arrive
one by one (cloud, image, pose), with ``mosaic_max_live_keyframes`` = ``--mosaic-live`` (the
older ones are merged into the static layers). Then, per k of ``--moved``, ``--mosaic-repeats``
corrections each move k keyframes drawn at random among the newest ``--mosaic-live`` (the live
ones: what the alignment still corrects; a few cm, a few mrad). Printed per N: the keyframes live
and merged (of which forced: merged before they settled, ``mosaic_settle_updates`` at its
default), the bytes held in all, per live keyframe (image, patch, points) and per merged one
(its pose plus its share of the static layers, which grow with the area, not the keyframes), the
CPU time of one update moving k keyframes (mean over the repeats) with the warps it did (the moved
keyframes and the neighbours whose ground it changed), and the CPU time of placing the N
keyframes one by one (what rebuilding the mosaic from the corrected path after every update would
cost at least). With ``--mosaic-live 0`` nothing is merged (the memory without the bound).

CPU: ``time.process_time`` (this process, every thread; nothing else runs in it).

Run: ``ga-ros bench map --mosaic-sizes 1000,5000 [--mosaic-live 500] [--moved 1,10,100]``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np

from ga_ros.geometry import se3
from ga_ros.pipeline.mosaic_map import LiveMosaic, MosaicMapConfig

#: camera height above the ground (m) and keyframe spacing (m)
HEIGHT_M = 20.0
STEP_M = 4.0


@dataclass(frozen=True)
class MosaicBenchRow:
    """One size's figures (CPU s, bytes)."""

    keyframes: int
    live: int
    merged: int
    forced: int
    bytes_total: int
    bytes_per_live: float
    bytes_per_merged: float
    update_s: list[float]
    warps: list[float]
    build_s: float


def _survey_pose(k: int, side: int, rng: np.random.Generator) -> np.ndarray:
    """``T_map_base`` of keyframe k (the base is the camera's optical frame looking down)."""
    row, col = divmod(k, side)
    x = STEP_M * (col if row % 2 == 0 else side - 1 - col)
    down = se3.from_rt(np.diag([1.0, -1.0, -1.0]), np.array([x, STEP_M * row, HEIGHT_M]))
    return down @ se3.from_translation_rotvec(np.zeros(3), rng.normal(0, 0.01, 3))


def _ground_z(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return 0.5 * np.sin(0.3 * x) * np.cos(0.2 * y)


def _keyframe(T: np.ndarray, width: int, points: int, rng: np.random.Generator
              ) -> tuple[np.ndarray, np.ndarray]:
    """A random-texture image (height 3/4 width) and ground points in the camera frame."""
    image = rng.integers(0, 256, (width * 3 // 4, width), dtype=np.uint8)
    xy = T[:2, 3] + rng.uniform(-0.5, 0.5, (points, 2)) * np.array([HEIGHT_M, 0.75 * HEIGHT_M])
    p = np.c_[xy, _ground_z(xy[:, 0], xy[:, 1])]
    return image, ((p - T[:3, 3]) @ T[:3, :3]).astype(np.float32)


def run(n: int, moved: list[int], live_limit: int, width: int, points: int, repeats: int,
        seed: int = 0) -> MosaicBenchRow:
    """Feed n keyframes, then time corrections moving each k of ``moved`` (module
    docstring)."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    K = np.array([[width, 0.0, width / 2], [0.0, width, width * 3 / 8], [0.0, 0.0, 1.0]])
    eye = np.eye(4)
    mosaic = LiveMosaic(MosaicMapConfig(metres_per_pixel=0.1, max_live_keyframes=live_limit,
                                        max_pixels=10**9))
    T = np.empty((n, 4, 4))
    build = 0.0
    for k in range(n):
        T[k] = _survey_pose(k, side, rng)
        image, cloud = _keyframe(T[k], width, points, rng)
        t0 = time.process_time()
        mosaic.add_cloud(k, cloud, eye)
        mosaic.add_image(k, image, K, eye)
        mosaic.set_poses([k], T[k:k + 1])
        build += time.process_time() - t0
    live_keys = np.arange(max(0, n - live_limit) if live_limit else 0, n)
    update_s, warps = [], []
    for m in moved:
        m = min(m, live_keys.size)
        total, done = 0.0, 0
        for _ in range(repeats):
            keys = rng.choice(live_keys, size=m, replace=False)
            dT = se3.from_translation_rotvec(rng.normal(0, 0.03, (m, 3)),
                                             rng.normal(0, 0.003, (m, 3)))
            T[keys] = T[keys] @ dT
            t0 = time.process_time()
            done += mosaic.set_poses(keys, T[keys])
            total += time.process_time() - t0
        update_s.append(total / repeats)
        warps.append(done / repeats)
    parts = mosaic.nbytes_by_part()
    live = mosaic.n_placed
    merged = len(mosaic.merged)
    forced = mosaic.counts.merged_forced
    per_live = parts['images'] + parts['patches'] + parts['points']
    per_merged = parts['merged_poses'] + parts['static_tiles'] + parts['ground']
    return MosaicBenchRow(n, live, merged, forced, sum(parts.values()), per_live / max(live, 1),
                          per_merged / merged if merged else float('nan'), update_s, warps,
                          build)


def print_table(sizes: list[int], moved: list[int], live_limit: int, width: int, points: int,
                repeats: int) -> None:
    """Run each size and print the table of the module docstring."""
    print(f'\nlive mosaic (map_node): {width}x{width * 3 // 4} px grey keyframe images, '
          f'{points} cloud points each, 0.1 m/px, mosaic_max_live_keyframes {live_limit}; CPU = '
          f'time.process_time (this process, all threads), mean over {repeats} updates per cell')
    head = ' | '.join(f'update, {k} moved (warps)' for k in moved)
    print(f'| keyframes fed | live / merged (forced) | MB held | kB per live keyframe | kB per '
          f'merged keyframe (pose + static layers) | {head} | placing all one by one |')
    print('|---:|---:|---:|---:|---:|' + '---:|' * len(moved) + '---:|')
    rows = []
    for n in sizes:
        r = run(n, moved, live_limit, width, points, repeats)
        rows.append(r)
        cells = ' | '.join(f'{1e3 * s:.1f} ms ({w:.0f})' for s, w in zip(r.update_s, r.warps))
        print(f'| {n:,} | {r.live:,} / {r.merged:,} ({r.forced:,}) | {r.bytes_total / 1e6:.1f} | '
              f'{r.bytes_per_live / 1e3:.0f} | {r.bytes_per_merged / 1e3:.2f} | {cells} | '
              f'{r.build_s:.1f} s |', flush=True)
    print('mosaic update CPU per warp (ms), by keyframes fed ' + ', '.join(f'{n:,}' for n in sizes)
          + ':')
    for i, k in enumerate(moved):
        per = [1e3 * r.update_s[i] / max(r.warps[i], 1) for r in rows]
        print(f'  {k:>4} moved: ' + ', '.join(f'{v:.2f}' for v in per)
              + f'   (largest / smallest: {per[-1] / per[0]:.2f})')
