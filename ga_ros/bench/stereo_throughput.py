"""Throughput of the stereo front end (vo_node's worker) at 752x480, EuRoC-like raw images.

Renders ``--pairs`` pairs (aerial scene seen as a 2-5 m room, radial-tangential distortion and a
small rectifying rotation per camera, 20 Hz at 1.6 m/s scaled), builds mono8 ``Image``-like
messages and times :meth:`ga_ros.pipeline.stereo.StereoFrontEnd.process_pair` (decoding,
rectification, VO, cross-track matching) over them. Prints pairs/s (wall clock: depends on the
machine's load) and the CPU time per pair (this process only), and the top of a profile with
``--profile``. Target: >= 20 pairs/s (a 20 Hz camera). Usage::

    ga-ros bench stereo-throughput [--pairs 120] [--profile]
"""

from __future__ import annotations

import argparse
import cProfile
import pstats
import time
from types import SimpleNamespace

import cv2
import numpy as np

from ga_ros.pipeline.stereo import FrontEndConfig, ImagePair, StereoFrontEnd
from ga_ros.runtime import limit_blas_threads
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene
from ga_ros.vo.calibration import CameraModel

K_RAW = np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])
D_RAW = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])


def _image(img: np.ndarray, stamp_ns: int) -> SimpleNamespace:
    stamp = SimpleNamespace(sec=stamp_ns // 10**9, nanosec=stamp_ns % 10**9)
    return SimpleNamespace(header=SimpleNamespace(stamp=stamp), height=480, width=752,
                           encoding='mono8', is_bigendian=0, step=752, data=img.tobytes())


def make_pairs(n: int, seed: int = 6) -> tuple[list[ImagePair], CameraModel, CameraModel]:
    """``n`` raw 752x480 pairs (rendered at 376x240, upscaled, distorted) and the two models."""
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=n, step_m=1.6,
                                       turn_positions=0, frame_period_s=0.05, seed=seed))
    small = StereoRig(376, 240, 229.0, 2.2)
    scene = make_scene(survey, small, seed=seed)
    rng = np.random.default_rng(seed)
    K = StereoRig(752, 480, 458.0, 2.2).K
    models, maps = [], []
    for k, rv in enumerate(([0.004, -0.006, 0.002], [-0.003, 0.005, -0.001])):
        R = cv2.Rodrigues(np.array(rv))[0]
        P = np.hstack([K, [[-K[0, 0] * 0.11 * k], [0.0], [0.0]]])
        models.append(CameraModel(752, 480, K_RAW, D_RAW, R, P))
        u, v = np.meshgrid(np.arange(752.0), np.arange(480.0))
        pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
        rect = cv2.undistortPoints(pts, K_RAW, D_RAW, R=R, P=K).reshape(480, 752, 2)
        maps.append((rect[..., 0].astype(np.float32), rect[..., 1].astype(np.float32)))
    pairs = []
    for i in range(n):
        s = int(survey.stamps_ns[i]) + 1
        imgs = [cv2.remap(cv2.resize(im, (752, 480)), *m, cv2.INTER_LINEAR)
                for im, m in zip(scene.render_pair(survey.T_world_cam[i], rng), maps)]
        pairs.append(ImagePair(_image(imgs[0], s), _image(imgs[1], s), s))
    return pairs, models[0], models[1]


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='ga-ros bench stereo-throughput', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 allow_abbrev=False)
    ap.add_argument('--pairs', type=int, default=120)
    ap.add_argument('--no-cross', action='store_true', help='without cross-track matching')
    ap.add_argument('--profile', action='store_true', help='print the top of a profile')
    args = ap.parse_args(argv)
    _limits = limit_blas_threads()  # noqa: F841 (kept alive)
    t = time.perf_counter()
    pairs, left, right = make_pairs(args.pairs)
    print(f'rendered {len(pairs)} pairs 752x480 in {time.perf_counter() - t:.1f} s; '
          f'OpenCV threads {cv2.getNumThreads()}')
    front = StereoFrontEnd(FrontEndConfig(cross_track=not args.no_cross))
    front.set_camera_models(left, right)
    prof = cProfile.Profile() if args.profile else None
    wall, cpu = time.perf_counter(), time.process_time()
    if prof is not None:
        prof.enable()
    for p in pairs:
        front.stats.pairs += 1  # (counted by the pairing, which the benchmark skips)
        out = front.process_pair(p)
        front.match(out)
    if prof is not None:
        prof.disable()
    wall, cpu = time.perf_counter() - wall, time.process_time() - cpu
    n = len(pairs)
    print(f'{n} pairs in {wall:.2f} s wall = {n / wall:.1f} pairs/s; CPU {1e3 * cpu / n:.1f} ms '
          f'per pair (= {n / cpu:.1f} pairs/s of CPU); {front.stats.summary()}')
    if prof is not None:
        pstats.Stats(prof).sort_stats('cumulative').print_stats(18)
    return 0
