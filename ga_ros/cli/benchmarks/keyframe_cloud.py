"""CPU cost of the keyframe clouds (``vo_node``'s ``ga/keyframe_cloud``) on the stereo sample bag.

Reads ``bags/stereo_sample`` (320x240 JPEG pairs with ``CameraInfo``), runs the stereo front end
over every pair as ``vo_node`` does, and at each new keyframe times
:meth:`ga_ros.pipeline.stereo.StereoFrontEnd.keyframe_cloud` (rectification + semi-global
matching + triangulation) and :func:`ga_ros.ros.conversions.cloud_to_pointcloud2` separately.
Prints the CPU time per keyframe (process CPU, every thread: OpenCV may run SGBM on several),
the VO's CPU per pair beside it (the work the cloud adds to), points and bytes per cloud.
Usage::

    ga-ros bench keyframe-cloud [--bag bags/stereo_sample] [--stride 2] [--repeat 3]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from ga_ros.cli.commands.demo import find_bags_dir
from ga_ros.io.bag.reader import BagReader
from ga_ros.pipeline.stereo import FrontEndConfig, StereoFrontEnd
from ga_ros.runtime import limit_blas_threads
from ga_ros.vo.dense import DenseStereoConfig

STEREO_BAG = 'stereo_sample'


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog='ga-ros bench keyframe-cloud', description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter,
                                 allow_abbrev=False)
    ap.add_argument('--bag', type=Path, help='stereo bag (default: bags/stereo_sample)')
    ap.add_argument('--stride', type=int, default=DenseStereoConfig().pixel_stride,
                    help='cloud_pixel_stride (default: that of config/vo.yaml)')
    ap.add_argument('--repeat', type=int, default=3,
                    help='clouds computed per keyframe (the CPU figure is their mean)')
    args = ap.parse_args(argv)
    from ga_ros.ros import conversions as conv  # ROS only when this benchmark runs

    bag = args.bag
    if bag is None:
        bags = find_bags_dir()
        if bags is None:
            print('sample bags not found: give --bag')
            return 2
        bag = bags / STEREO_BAG
    _limits = limit_blas_threads()  # noqa: F841 (kept alive)
    front = StereoFrontEnd(FrontEndConfig(cloud=DenseStereoConfig(pixel_stride=args.stride)))
    vo_cpu = cloud_cpu = msg_cpu = 0.0
    points: list[int] = []
    n_bytes: list[int] = []
    size = ''
    with BagReader(bag) as reader:
        for m in reader.messages():
            side = 'left' if '/left/' in m.topic else 'right' if '/right/' in m.topic else ''
            if not side:
                continue
            if m.topic.endswith('camera_info'):
                front.set_camera_info(side, m.msg)
                continue
            t = time.process_time()
            frames = front.add_image(side, m.msg)
            for frame in frames:
                front.match(frame)
            vo_cpu += time.process_time() - t
            for frame in frames:
                if frame.result is None or frame.result.keyframe is None:
                    continue
                t = time.process_time()
                for _ in range(max(1, args.repeat)):
                    cloud = front.keyframe_cloud(frame)
                cloud_cpu += (time.process_time() - t) / max(1, args.repeat)
                t = time.process_time()
                msg = conv.cloud_to_pointcloud2(cloud.points, cloud.intensity, 'camera',
                                                frame.stamp_ns)
                msg_cpu += time.process_time() - t
                points.append(len(cloud))
                n_bytes.append(len(msg.data))
                size = f'{frame.left.shape[1]}x{frame.left.shape[0]}'
    k, pairs = len(points), front.stats.pairs
    if not k:
        print(f'{bag}: no keyframe ({front.stats.summary()})')
        return 1
    print(f'{bag}: {pairs} pairs {size}, {k} keyframes; OpenCV threads {cv2.getNumThreads()}; '
          f'cloud_pixel_stride {args.stride}, num_disparities '
          f'{front.config.cloud.num_disparities}')
    print(f'keyframe cloud: {1e3 * cloud_cpu / k:.1f} ms CPU per keyframe (rectify + SGBM + '
          f'points), + {1e3 * msg_cpu / k:.2f} ms CPU for the PointCloud2; '
          f'{np.mean(points):.0f} points = {np.mean(n_bytes) / 1e3:.0f} kB per cloud')
    print(f'VO + cross-track matching for comparison: {1e3 * vo_cpu / pairs:.1f} ms CPU per pair '
          f'({1e3 * vo_cpu / k:.1f} ms per keyframe interval)')
    return 0
