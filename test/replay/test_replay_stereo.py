"""Replay of stereo image bags: VO in the replay == VO run directly on the same images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from ga_ros.io.bag import BagReader
from ga_ros.io.bag_messages import CAMERA_INFO, IMAGE, header, typestore
from ga_ros.io.bag_writer import BagWriter
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.pipeline import replay
from ga_ros.replay.samples import (
    LEFT_IMAGE_TOPIC,
    RIGHT_IMAGE_TOPIC,
    StereoSampleConfig,
    make_stereo_bag,
)

pytest.importorskip('ga_ros.vo.odometry')
pytest.importorskip('ga_ros.sim.stereo')

from test_replay import DeadReckoning, mcap_counts  # noqa: E402

SMALL = StereoSampleConfig(n_tracks=1, positions_per_swath=14, turn_positions=16, seed=4)


@pytest.fixture(scope='module')
def stereo_bag(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return make_stereo_bag(tmp_path_factory.mktemp('stereo') / 'bag', SMALL)


def direct_vo(bag: Path) -> list:
    """Measurements of StereoOdometry + CrossTrackMatcher on the bag's images, read and decoded
    with the mcap library and OpenCV (not the replay's reader)."""
    import cv2
    from mcap.reader import make_reader

    from ga_ros.sim.stereo import StereoRig
    from ga_ros.vo.calibration import StereoCalibration
    from ga_ros.vo.crosstrack import CrossTrackMatcher
    from ga_ros.vo.odometry import StereoFrame, StereoOdometry

    rig = StereoRig.for_size(SMALL.width, SMALL.height)
    calib = StereoCalibration.rectified(rig.width, rig.height, rig.K, rig.baseline_m)
    vo = StereoOdometry(calib)
    matcher = CrossTrackMatcher(calib.K, calib.width, calib.height)
    images: dict[str, list] = {LEFT_IMAGE_TOPIC: [], RIGHT_IMAGE_TOPIC: []}
    (f,) = bag.glob('*.mcap')
    with open(f, 'rb') as fh:
        for _, ch, msg in make_reader(fh).iter_messages(topics=list(images)):
            m = typestore().deserialize_cdr(msg.data, 'sensor_msgs/msg/CompressedImage')
            images[ch.topic].append((m.header.stamp.sec * 10**9 + m.header.stamp.nanosec,
                                     cv2.imdecode(np.asarray(m.data), cv2.IMREAD_GRAYSCALE)))
    out = []
    for (s, left), (s2, right) in zip(images[LEFT_IMAGE_TOPIC], images[RIGHT_IMAGE_TOPIC]):
        assert s == s2
        res = vo.process(StereoFrame(left, right, s))
        if res.measurement is not None:
            out.append(res.measurement)
        if res.keyframe is not None:
            out.extend(a.measurement for a in matcher.add(res.keyframe)
                       if a.accepted and a.measurement is not None)
    return out


def test_stereo_replay_equals_direct_vo(tmp_path: Path, stereo_bag: Path) -> None:
    from ga_ros.io.bag_messages import odometry_to_measurement
    from ga_ros.pipeline.stereo import FrontEndConfig

    config = ReplayConfig(vo=FrontEndConfig(feedback=False), plot=False)
    r = replay(stereo_bag, tmp_path / 'out', config, aligner_factory=DeadReckoning)
    assert r.source == 'stereo' and r.n_inputs == r.source_stats['pairs'] > 0
    want = direct_vo(stereo_bag)
    with BagReader(tmp_path / 'out' / 'replay_bag') as out:
        got = [odometry_to_measurement(m.msg) for m in out.messages(['/ga/measurements'])]
    assert len(want) > 5 and len(got) == len(want) == r.n_measurements
    for a, b in zip(got, want):
        assert (a.src_id, a.dst_id, a.kind, a.stamp_ns) == (b.src_id, b.dst_id, b.kind,
                                                           b.stamp_ns)
        np.testing.assert_allclose(a.z, b.z, atol=1e-9)
    counts = mcap_counts(tmp_path / 'out' / 'replay_bag')
    assert counts['/ga/corrected_pose'] == r.n_nodes and counts['/ga/ground_truth'] == 1
    # keyframes matched to ground truth by stamp; VO is accurate to well under a metre here
    assert r.errors['f2f'].n == r.n_nodes
    assert r.errors['f2f'].ate_raw < 2.0


def test_raw_images_and_missing_calibration(tmp_path: Path, stereo_bag: Path) -> None:
    """A bag with raw mono8 Images replays like the compressed one; images before any
    CameraInfo wait for it."""
    from ga_ros.errors import FormatError

    with BagReader(stereo_bag) as src, BagWriter(tmp_path / 'raw') as dst:
        from ga_ros.vo.messages import image_to_grey

        first = True
        for m in src.messages():
            if m.msgtype == CAMERA_INFO and first:
                continue  # the first frame has no calibration yet
            if m.msgtype == 'sensor_msgs/msg/CompressedImage':
                img = image_to_grey(m.msg)
                msg = typestore().types[IMAGE](
                    header=header(m.msg.header.frame_id,
                                  m.msg.header.stamp.sec * 10**9 + m.msg.header.stamp.nanosec),
                    height=img.shape[0], width=img.shape[1], encoding='mono8', is_bigendian=0,
                    step=img.shape[1], data=img.reshape(-1))
                dst.write(m.topic.replace('/compressed', ''), IMAGE, msg, m.log_ns)
                if 'right' in m.topic:
                    first = False
            else:
                dst.write_raw(m.topic, m.msgtype, m.data, m.log_ns)
    r = replay(tmp_path / 'raw', tmp_path / 'out', ReplayConfig(plot=False),
               aligner_factory=DeadReckoning)
    # the first pair waits for the first CameraInfo (of the next stamp): none is lost
    assert r.rejected == {}
    assert 'no CameraInfo yet' not in r.source_stats['reasons']
    assert r.n_inputs == r.source_stats['pairs']
    assert r.n_measurements > 5
    with BagWriter(tmp_path / 'noinfo') as dst, BagReader(tmp_path / 'raw') as src:
        for m in src.messages():
            if m.msgtype != CAMERA_INFO:
                dst.write_raw(m.topic, m.msgtype, m.data, m.log_ns)
    with pytest.raises(FormatError, match='no CameraInfo'):
        replay(tmp_path / 'noinfo', tmp_path / 'out2', ReplayConfig(),
               aligner_factory=DeadReckoning)
    assert not (tmp_path / 'out2').exists()


def test_sample_bag_generation_is_deterministic(tmp_path: Path) -> None:
    from ga_ros.replay.samples import make_measurements_bag

    tiny = StereoSampleConfig(n_tracks=1, positions_per_swath=3, turn_positions=2, seed=9)
    a = make_stereo_bag(tmp_path / 'a' / 's', tiny)
    b = make_stereo_bag(tmp_path / 'b' / 's', tiny)
    assert (a / 's.mcap').read_bytes() == (b / 's.mcap').read_bytes()
    a = make_measurements_bag(tmp_path / 'a' / 'm', n_tracks=1)
    b = make_measurements_bag(tmp_path / 'b' / 'm', n_tracks=1)
    assert (a / 'm.mcap').read_bytes() == (b / 'm.mcap').read_bytes()


def test_committed_stereo_bag_tracks_without_loss(tmp_path: Path) -> None:
    """bags/stereo_sample: every pair is tracked, VO alone stays close to the ground truth."""
    from test_replay import REPO

    bag = REPO / 'bags' / 'stereo_sample'
    if not bag.exists():
        pytest.skip('sample bag not generated')
    r = replay(bag, tmp_path / 'out', ReplayConfig(plot=False), aligner_factory=DeadReckoning)
    assert r.n_inputs == 200 and r.source_stats['lost'] == 0 and not r.rejected
    assert r.source_stats['cross_accepted'] > 0
    assert r.errors['f2f'].n == r.n_nodes and r.errors['f2f'].ate_raw < 5.0
