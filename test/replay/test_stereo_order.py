"""Stereo pairs synchronised by stamp whatever the arrival order of image and CameraInfo.

A camera driver publishes each image and its CameraInfo with one stamp, but a recorder may log
the CameraInfo just after the images: the first pair must then wait for it, not be dropped
("no CameraInfo yet"). The replay of such a bag gives what the same bag with the CameraInfo
first gives, pair for pair.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import CAMERA_INFO
from ga_ros.io.bag_writer import BagWriter
from ga_ros.pipeline.stereo import NO_CAMERA_INFO, FrontEndConfig, StereoFrontEnd
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.pipeline import replay
from ga_ros.replay.samples import StereoSampleConfig, make_stereo_bag
from ga_ros.vo.odometry import VoConfig

SMALL = StereoSampleConfig(n_tracks=1, positions_per_swath=10, turn_positions=4)


def _info_after_images(src: Path, dst: Path) -> int:
    """Copy ``src`` with every CameraInfo logged 1 ns after the images of its stamp; returns
    how many CameraInfo moved."""
    moved = 0
    with BagReader(src) as bag, BagWriter(dst, compress=False) as out:
        rows = []
        for m in bag.messages():
            late = m.msgtype == CAMERA_INFO
            moved += late
            rows.append((m.log_ns + late, late, m))
        for _, _, m in sorted(rows, key=lambda r: (r[0], r[1])):
            out.write(m.topic, m.msgtype, m.msg, m.log_ns + (m.msgtype == CAMERA_INFO))
    return moved


def test_replay_with_camera_info_after_the_images(tmp_path: Path) -> None:
    bag = make_stereo_bag(tmp_path / 'first', SMALL)
    assert _info_after_images(bag, tmp_path / 'late') == 2 * 24
    with BagReader(tmp_path / 'late') as b:  # the order really is image, image, info, info
        first = [m.msgtype.rsplit('/', 1)[1] for _, m in zip(range(5), b.messages())]
    assert first[1:] == ['CompressedImage', 'CompressedImage', 'CameraInfo', 'CameraInfo']
    a = replay(bag, tmp_path / 'out_a', ReplayConfig(plot=False))
    b = replay(tmp_path / 'late', tmp_path / 'out_b', ReplayConfig(plot=False))
    assert NO_CAMERA_INFO not in b.source_stats['reasons'], b.source_stats
    assert b.n_inputs == a.n_inputs == 24
    assert b.source_stats['reasons'] == a.source_stats['reasons']
    assert (b.n_measurements, b.n_nodes) == (a.n_measurements, a.n_nodes)
    ta = np.loadtxt(a.files['trajectory_ga'])
    tb = np.loadtxt(b.files['trajectory_ga'])
    np.testing.assert_allclose(tb, ta, atol=1e-9)


def test_front_end_holds_a_pair_until_its_calibration(tmp_path: Path) -> None:
    """The front end alone: held while uncalibrated, released in stamp order, bounded (an
    older held pair is counted under "no CameraInfo yet"), all released at the end."""
    bag = make_stereo_bag(tmp_path / 'b', SMALL)
    front = StereoFrontEnd(FrontEndConfig(vo=VoConfig(), max_pending=3))
    infos: dict[str, object] = {}
    images = []
    with BagReader(bag) as b:
        for m in b.messages():
            if m.msgtype == CAMERA_INFO:
                infos.setdefault('left' if 'left' in m.topic else 'right', m.msg)
            elif 'image' in m.topic:
                images.append(('left' if 'left' in m.topic else 'right', m.msg))
    outputs = [front.add_image(side, msg) for side, msg in images[:10]]  # five pairs
    assert all(o == [] for o in outputs)
    assert front.stats.pairs == 5 and front.stats.reasons == {NO_CAMERA_INFO: 2}
    assert front.release_held() == []  # not calibrated yet
    front.set_camera_info('left', infos['left'])
    assert front.release_held() == []
    front.set_camera_info('right', infos['right'])
    held = front.release_held()
    assert [p.stamp_ns for p in held] == sorted(p.stamp_ns for p in held) and len(held) == 3
    assert front.release_held() == []
    frames = [front.process_pair(p) for p in held]
    assert all(f.result is not None for f in frames)
    end = StereoFrontEnd()
    end.add_image(*images[0])
    end.add_image(*images[1])
    last = end.release_held(final=True)
    assert len(last) == 1 and end.process_pair(last[0]).reason == NO_CAMERA_INFO
