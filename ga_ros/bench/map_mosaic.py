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


@dataclass(frozen=True)
class DriftRow:
    """One merge rule's figures in the drift run (:func:`run_drift`)."""

    rule: str
    merged_settled: int
    merged_forced: int
    moves_ignored: int
    max_ignored_shift_m: float
    differing: float
    update_s: float


def _aligned(a, b) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Two mosaics on the same global grid cut to their common box: images and masks."""
    m = a.georef.metres_per_pixel
    dc = int(round((b.georef.x_min - a.georef.x_min) / m))
    dr = int(round((a.georef.y_max - b.georef.y_max) / m))
    r0, c0 = max(0, dr), max(0, dc)
    r1 = min(a.image.shape[0], dr + b.image.shape[0])
    c1 = min(a.image.shape[1], dc + b.image.shape[1])
    return (a.image[r0:r1, c0:c1], a.valid[r0:r1, c0:c1],
            b.image[r0 - dr:r1 - dr, c0 - dc:c1 - dc], b.valid[r0 - dr:r1 - dr, c0 - dc:c1 - dc])


def run_drift(n: int, live_limit: int, width: int, points: int, sigma0_m: float,
              decay: float, seed: int = 0) -> tuple[list[DriftRow], float]:
    """Old keyframes that keep moving: the survey of :func:`run` fed row by row (a row is a
    track), each keyframe placed off its true pose by an error ``e_k`` (``sigma0_m`` per axis
    in m, a hundredth of it in rad); after each row one corrections update shrinks every error
    to ``decay ** age`` of it (age: rows since the keyframe's own) and sends the keyframes that
    moved by more than 1 cm (the corrections topic's default threshold): corrections that go on
    for ``log(0.01 / sigma0_m) / log(decay)`` rows, beyond the live keyframes. The last update
    sends the true poses (the final batch). Run once merging when settled (the default
    ``mosaic_settle_updates``) and once by age (0), on the same data. Returns, per rule, the
    merges settled / forced, the corrections of merged keyframes ignored and the largest of
    them (m), the share of the pixels of the final mosaic whose grey level differs by more than
    2 from the mosaic of every keyframe placed at its final pose without merging (of the pixels
    both cover), the CPU per update; and that reference's CPU (s)."""
    rng = np.random.default_rng(seed)
    side = int(np.ceil(np.sqrt(n)))
    K = np.array([[width, 0.0, width / 2], [0.0, width, width * 3 / 8], [0.0, 0.0, 1.0]])
    eye = np.eye(4)
    T_true = np.array([_survey_pose(k, side, rng) for k in range(n)])
    frames = [_keyframe(T, width, points, rng) for T in T_true]
    rows = np.arange(n) // side
    error = np.c_[rng.normal(0, sigma0_m, (n, 3)), rng.normal(0, sigma0_m / 100, (n, 3))]
    # one schedule for both rules: (new keys, keys sent, their poses) per update
    schedule = []
    sent = np.full(n, np.nan)
    for row in range(rows[-1] + 1):
        new = np.flatnonzero(rows == row)
        seen = np.flatnonzero(rows <= row)
        shrink = decay ** (row - rows[seen])
        moved = np.isnan(sent[seen]) | (np.abs(shrink - sent[seen])
                                        * np.linalg.norm(error[seen, :3], axis=1) > 0.01)
        keys = seen[moved]
        sent[keys] = shrink[moved]
        T = T_true[keys] @ se3.from_translation_rotvec(error[keys, :3] * shrink[moved, None],
                                                       error[keys, 3:] * shrink[moved, None])
        schedule.append((new, keys, T))
    out = []
    for rule, settle in (('merged when settled', MosaicMapConfig.settle_updates),
                         ('merged by age', 0)):
        mosaic = LiveMosaic(MosaicMapConfig(metres_per_pixel=0.1, max_live_keyframes=live_limit,
                                            max_pixels=10**9, settle_updates=settle))
        cpu = 0.0
        for new, keys, T in schedule:
            for k in new.tolist():
                mosaic.add_cloud(k, frames[k][1], eye)
                mosaic.add_image(k, frames[k][0], K, eye)
            t0 = time.process_time()
            mosaic.set_poses(keys, T)
            cpu += time.process_time() - t0
        mosaic.set_poses(np.arange(n), T_true)
        out.append((rule, mosaic, cpu / len(schedule)))
    t0 = time.process_time()
    reference = LiveMosaic(MosaicMapConfig(metres_per_pixel=0.1, max_live_keyframes=0,
                                           max_pixels=10**9))
    for k in range(n):
        reference.add_cloud(k, frames[k][1], eye)
        reference.add_image(k, frames[k][0], K, eye)
    reference.set_poses(np.arange(n), T_true)
    ref_cpu = time.process_time() - t0
    ref = reference.mosaic()
    rows_out = []
    for rule, mosaic, cpu in out:
        a, va, b, vb = _aligned(mosaic.mosaic(), ref)
        both = va & vb
        diff = np.abs(a.astype(int) - b.astype(int))[both] > 2
        c = mosaic.counts
        rows_out.append(DriftRow(rule, c.merged_settled, c.merged_forced, c.merged_moves_ignored,
                                 c.merged_max_shift_m, float(diff.mean()), cpu))
    return rows_out, ref_cpu


def print_drift(n: int, live_limit: int, width: int, points: int, sigma0_m: float,
                decay: float) -> None:
    """Run :func:`run_drift` and print its table."""
    side = int(np.ceil(np.sqrt(n)))
    print(f'\nlive mosaic with old keyframes that keep moving: {n:,} keyframes in rows (tracks) '
          f'of {side}, mosaic_max_live_keyframes {live_limit}, 0.1 m/px; each keyframe placed '
          f'{100 * sigma0_m:.0f} cm off (per axis), the error shrunk to {decay} of it per row '
          'after (corrections above 1 cm sent), the last update sends the true poses. '
          '"differing": share of the '
          'pixels of the final live mosaic whose grey differs by > 2 from the mosaic of every '
          'keyframe placed at its final pose without merging (pixels both cover). CPU = '
          'time.process_time per update')
    rows, ref_cpu = run_drift(n, live_limit, width, points, sigma0_m, decay)
    print('| merge rule | merged settled / forced | corrections of merged keyframes ignored '
          '(largest, m) | pixels differing from the reference | CPU per update |')
    print('|---|---:|---:|---:|---:|')
    for r in rows:
        print(f'| {r.rule} | {r.merged_settled:,} / {r.merged_forced:,} | {r.moves_ignored:,} '
              f'({r.max_ignored_shift_m:.3f}) | {100 * r.differing:.2f} % | '
              f'{1e3 * r.update_s:.0f} ms |')
    print(f'reference (all {n:,} placed at their final poses, nothing merged): {ref_cpu:.1f} s '
          'CPU')
