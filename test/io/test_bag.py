"""Bag reading/writing without ROS: frames, the measurement encoding, topic plans, bad bags."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import reference_network_markers, write_unknown_type_bag

from ga_ros.core.frames import node_frame, parse_node_frame
from ga_ros.core.measurement import Measurement
from ga_ros.errors import ForeignFileError, FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.io.bag import BagReader, bag_info
from ga_ros.io.bag_messages import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    ODOMETRY,
    PATH,
    measurement_to_odometry,
    odometry_to_measurement,
    trajectory_to_path_msg,
    typestore,
)
from ga_ros.io.bag_writer import BagWriter
from ga_ros.io.groundtruth import read_ground_truth_topic
from ga_ros.io.topic_plan import TopicConfig, plan_topics
from ga_ros.io.trajectory import Trajectory

STORAGES = ['mcap', 'sqlite3']


def random_measurements(rng: np.random.Generator, n: int = 30) -> list[Measurement]:
    out = []
    for i in range(n):
        A = rng.normal(size=(6, 6))
        cov = A @ A.T * 1e-3 + np.eye(6) * 1e-4
        kind = 'cross' if i % 5 == 4 else 'consecutive'
        src = i - 3 if kind == 'cross' else i
        out.append(Measurement.from_pose(src, i + 1, src // 10, (i + 1) // 10,
                                         se3.exp(rng.normal(size=6)), cov,
                                         1_000_000_000 + 100_000_000 * (i + 1), kind,
                                         ('', 'odom0', 'odom_ß1')[i % 3]))
    return out


def write_bag(path: Path, ms: list[Measurement], storage: str = 'mcap',
              gt: Trajectory | None = None) -> Path:
    with BagWriter(path, storage=storage) as bag:
        for m in ms:
            bag.write('/ga/measurements', ODOMETRY, measurement_to_odometry(m), m.stamp_ns)
        if gt is not None:
            bag.write('/ga/ground_truth', PATH, trajectory_to_path_msg(gt, node_frames=True),
                      int(gt.stamps_ns[-1]))
    return path


# --------------------------------------------------------------------------- frames
def test_node_frame_round_trip() -> None:
    for track, node in [(0, 0), (3, 412), (24, 5099), (2**53, 2**53)]:
        assert parse_node_frame(node_frame(track, node)) == (track, node)
    assert node_frame(np.int64(2), np.int64(7)) == 'ga/2/7'
    assert parse_node_frame('/ga/1/2') == (1, 2)  # same language as the rclpy conversions


@pytest.mark.parametrize('bad', ['', 'ga/1', 'ga/1/2/3', 'gb/1/2', 'ga/-1/2', 'ga/1/x',
                                 'ga/1/2 ', 'ga//2', f'ga/1/{2**53 + 1}', 'ga/1/' + '9' * 20])
def test_parse_node_frame_rejects(bad: str) -> None:
    with pytest.raises(InputError):
        parse_node_frame(bad)


def test_node_frame_rejects_bad_ids() -> None:
    for track, node in [(-1, 0), (0, -5), (0, 2**53 + 1), (1.5, 2), (True, 1)]:
        with pytest.raises(InputError):
            node_frame(track, node)


# --------------------------------------------------------------------------- measurements
@pytest.mark.parametrize('storage', STORAGES)
def test_measurement_bag_round_trip(tmp_path: Path, rng: np.random.Generator,
                                    storage: str) -> None:
    ms = random_measurements(rng)
    write_bag(tmp_path / 'b', ms, storage)
    info = bag_info(tmp_path / 'b')
    assert info.storage == storage
    assert info.topic('/ga/measurements').count == len(ms)
    with BagReader(tmp_path / 'b') as bag:
        got = [odometry_to_measurement(m.msg) for m in bag.messages(['/ga/measurements'])]
    assert len(got) == len(ms)
    for a, b in zip(ms, got):
        assert (a.src_id, a.dst_id, a.src_track, a.dst_track, a.kind, a.stamp_ns, a.source) == (
            b.src_id, b.dst_id, b.src_track, b.dst_track, b.kind, b.stamp_ns, b.source)
        np.testing.assert_allclose(b.T_src_dst, a.T_src_dst, atol=1e-12)
        np.testing.assert_allclose(b.cov, a.cov, rtol=1e-12, atol=1e-18)


def test_rosbags_and_rclpy_decoders_agree(rng: np.random.Generator) -> None:
    """rosbags-written CDR decodes with rclpy's conversions to the same measurement, and back."""
    pytest.importorskip('rclpy')
    from nav_msgs.msg import Odometry
    from rclpy.serialization import deserialize_message, serialize_message

    from ga_ros.ros import conversions

    for m in random_measurements(rng, 10):
        cdr = typestore().serialize_cdr(measurement_to_odometry(m), ODOMETRY)
        a = conversions.odometry_to_measurement(deserialize_message(bytes(cdr), Odometry))
        b = odometry_to_measurement(typestore().deserialize_cdr(
            serialize_message(conversions.measurement_to_odometry(m)), ODOMETRY))
        for x in (a, b):
            assert (x.src_id, x.dst_id, x.src_track, x.dst_track, x.kind, x.stamp_ns,
                    x.source) == (m.src_id, m.dst_id, m.src_track, m.dst_track, m.kind,
                                  m.stamp_ns, m.source)
            np.testing.assert_allclose(x.T_src_dst, m.T_src_dst, atol=1e-12)
            np.testing.assert_allclose(x.cov, m.cov, rtol=1e-12)


def _odometry(rng: np.random.Generator) -> object:
    return measurement_to_odometry(random_measurements(rng, 1)[0])


@pytest.mark.parametrize('corrupt', ['frame', 'child', 'self_loop', 'nan', 'quat', 'cov_asym',
                                     'cov_neg', 'flag'])
def test_bad_odometry_rejected(rng: np.random.Generator, corrupt: str) -> None:
    msg = _odometry(rng)
    if corrupt == 'frame':
        msg.header.frame_id = 'odom'
    elif corrupt == 'child':
        msg.child_frame_id = 'ga/0/x'
    elif corrupt == 'self_loop':
        msg.child_frame_id = msg.header.frame_id
    elif corrupt == 'nan':
        msg.pose.pose.position.x = float('nan')
    elif corrupt == 'quat':
        msg.pose.pose.orientation.w = 3.0
    elif corrupt == 'cov_asym':
        msg.pose.covariance[1] += 1.0
    elif corrupt == 'cov_neg':
        msg.pose.covariance[:] = -np.eye(6).reshape(36)
    elif corrupt == 'flag':
        msg.twist.twist.linear.x = 0.5
    with pytest.raises(InputError):
        odometry_to_measurement(msg)


def test_ground_truth_round_trip(tmp_path: Path, rng: np.random.Generator) -> None:
    n = 12
    T = se3.exp(rng.normal(size=(n, 6)))
    gt = Trajectory(np.arange(n, dtype=np.int64) * 10 + 5, T, np.arange(n, dtype=np.int64) + 100,
                    np.arange(n, dtype=np.int64) // 4)
    write_bag(tmp_path / 'b', random_measurements(rng, 3), gt=gt)
    with BagReader(tmp_path / 'b') as bag:
        got = read_ground_truth_topic(bag, '/ga/ground_truth').trajectory
        assert read_ground_truth_topic(bag, '/nothing') is None
    np.testing.assert_array_equal(got.node_ids, gt.node_ids)
    np.testing.assert_array_equal(got.track_ids, gt.track_ids)
    np.testing.assert_array_equal(got.stamps_ns, gt.stamps_ns)
    np.testing.assert_allclose(got.T_world_node, T, atol=1e-12)


# --------------------------------------------------------------------------- output bags
def test_output_bag_reads_with_mcap_library(tmp_path: Path, rng: np.random.Generator) -> None:
    from mcap.reader import make_reader

    ms = random_measurements(rng, 7)
    with BagWriter(tmp_path / 'o') as bag:
        for m in ms:
            bag.write('/ga/measurements', ODOMETRY, measurement_to_odometry(m), m.stamp_ns)
        p = rng.normal(size=(5, 3))
        markers = reference_network_markers(p, [0, 1, 2], [1, 2, 4], [0.1, 2.0, np.nan],
                                            'map', 9)
        bag.write('/ga/markers', 'visualization_msgs/msg/MarkerArray', markers, 9)
    files = list((tmp_path / 'o').glob('*.mcap'))
    assert len(files) == 1 and (tmp_path / 'o' / 'metadata.yaml').exists()
    with open(files[0], 'rb') as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        counts = {c.topic: summary.statistics.channel_message_counts[cid]
                  for cid, c in summary.channels.items()}
        schemas = {c.topic: summary.schemas[c.schema_id].name
                   for c in summary.channels.values()}
        data = [msg.data for _, ch, msg in reader.iter_messages(topics=['/ga/markers'])]
    assert counts == {'/ga/measurements': 7, '/ga/markers': 1}
    assert schemas['/ga/markers'] == 'visualization_msgs/msg/MarkerArray'
    markers = typestore().deserialize_cdr(data[0], 'visualization_msgs/msg/MarkerArray').markers
    assert [mk.type for mk in markers[1:]] == [7, 5]  # SPHERE_LIST, LINE_LIST
    assert len(markers[2].points) == 6 and len(markers[2].colors) == 6
    ends = np.array([[q.x, q.y, q.z] for q in markers[2].points])
    np.testing.assert_allclose(ends[2:4], p[[1, 2]])


def test_writer_refuses_to_overwrite_non_bag(tmp_path: Path) -> None:
    (tmp_path / 'x').mkdir()
    (tmp_path / 'x' / 'notes.txt').write_text('keep me')
    with pytest.raises(ForeignFileError, match='left untouched'):
        BagWriter(tmp_path / 'x', overwrite=True).open()
    assert (tmp_path / 'x' / 'notes.txt').read_text() == 'keep me'


# --------------------------------------------------------------------------- topic plans
def _stereo_topics_bag(path: Path, with_info: bool = True, extra: str = '') -> Path:
    from ga_ros.replay.samples import camera_info_msg, compressed_image_msg

    img = np.zeros((8, 8), np.uint8)
    with BagWriter(path) as bag:
        for side in ('left', 'right'):
            bag.write(f'/cam/{side}/image_raw/compressed', COMPRESSED_IMAGE,
                      compressed_image_msg(img, side, 5), 5)
            if with_info:
                bag.write(f'/cam/{side}/camera_info', CAMERA_INFO,
                          camera_info_msg(np.eye(3), 8, 8, side, 5), 5)
        if extra:
            bag.write(extra, COMPRESSED_IMAGE, compressed_image_msg(img, 'x', 5), 5)
    return path


def test_plan_measurements_and_stereo(tmp_path: Path, rng: np.random.Generator) -> None:
    write_bag(tmp_path / 'm', random_measurements(rng, 3))
    plan = plan_topics(bag_info(tmp_path / 'm'))
    assert plan.source == 'measurements' and plan.measurements == '/ga/measurements'
    plan = plan_topics(bag_info(_stereo_topics_bag(tmp_path / 's')))
    assert plan.source == 'stereo'
    assert plan.left_image == '/cam/left/image_raw/compressed'
    assert plan.right_info == '/cam/right/camera_info'


def test_plan_errors_name_the_problem(tmp_path: Path, rng: np.random.Generator) -> None:
    write_bag(tmp_path / 'm', random_measurements(rng, 3))
    info = bag_info(tmp_path / 'm')
    with pytest.raises(FormatError, match='missing topic /nope'):
        plan_topics(info, TopicConfig(measurements='/nope', source='measurements'))
    with pytest.raises(FormatError, match='neither a measurements topic'):
        plan_topics(info, TopicConfig(measurements='/nope'))
    info = bag_info(_stereo_topics_bag(tmp_path / 's', with_info=False))
    with pytest.raises(FormatError, match='has type sensor_msgs/msg/CompressedImage; expected '
                       'one of geometry_msgs/msg/PoseStamped'):
        plan_topics(info, TopicConfig(ground_truth='/cam/left/image_raw/compressed'))
    with pytest.raises(FormatError, match='no CameraInfo'):
        plan_topics(info)


def test_missing_and_corrupt_bags(tmp_path: Path, rng: np.random.Generator) -> None:
    with pytest.raises(FormatError, match='not found'):
        bag_info(tmp_path / 'nothing')
    (tmp_path / 'garbage.mcap').write_bytes(b'not a bag at all' * 10)
    with pytest.raises(FormatError, match='cannot open bag'):
        bag_info(tmp_path / 'garbage.mcap')
    (tmp_path / 'garbage.db3').write_bytes(b'SQLite format 3\x00' + b'\x00' * 50)
    with pytest.raises(FormatError):
        bag_info(tmp_path / 'garbage.db3')
    (tmp_path / 'empty_dir').mkdir()
    with pytest.raises(FormatError, match='not a rosbag2 bag'):
        bag_info(tmp_path / 'empty_dir')


def test_truncated_mcap_reads_up_to_the_cut(tmp_path: Path, rng: np.random.Generator) -> None:
    """A recording cut short: the complete chunks are read, then a FormatError names the cut."""
    ms = random_measurements(rng, 3000)
    write_bag(tmp_path / 'b', ms)
    data = (tmp_path / 'b' / 'b.mcap').read_bytes()
    (tmp_path / 't').mkdir()
    (tmp_path / 't' / 't.mcap').write_bytes(data[:int(len(data) * 0.6)])
    with BagReader(tmp_path / 't' / 't.mcap') as bag:
        assert bag.truncated is not None
        n_info = bag.info.n_messages
        got = []
        with pytest.raises(FormatError, match='truncated or corrupt after'):
            for m in bag.messages(['/ga/measurements']):
                got.append(odometry_to_measurement(m.msg))
    assert 0 < len(got) == n_info < len(ms)
    for a, b in zip(ms, got):  # what was read is exactly the start of the bag
        assert (a.src_id, a.dst_id) == (b.src_id, b.dst_id)


def test_corrupt_message_is_reported_with_topic(tmp_path: Path, rng: np.random.Generator
                                                ) -> None:
    ms = random_measurements(rng, 5)
    with BagWriter(tmp_path / 'b') as bag:
        for i, m in enumerate(ms):
            if i == 3:
                bag.write_raw('/ga/measurements', ODOMETRY, b'\x00\x01\x00\x00garbage', 10)
            bag.write('/ga/measurements', ODOMETRY, measurement_to_odometry(m), m.stamp_ns)
    with BagReader(tmp_path / 'b') as bag:
        with pytest.raises(FormatError, match=r'/ga/measurements \(nav_msgs/msg/Odometry\)'):
            list(bag.messages())


def test_unknown_message_type(tmp_path: Path) -> None:
    """A bag with a type outside the standard set: a clear error naming the type."""
    path = write_unknown_type_bag(tmp_path / 'u')
    with BagReader(path) as bag:
        assert bag.info.topic('/custom').msgtype == 'my_pkg/msg/Thing'
        with pytest.raises(FormatError, match="unknown message type 'my_pkg/msg/Thing'"):
            list(bag.messages(['/custom']))
    with pytest.raises(FormatError, match='neither a measurements topic'):
        plan_topics(bag_info(path))


def test_bag_dir_without_metadata_but_one_mcap(tmp_path: Path, rng: np.random.Generator) -> None:
    write_bag(tmp_path / 'b', random_measurements(rng, 4))
    os.remove(tmp_path / 'b' / 'metadata.yaml')
    assert bag_info(tmp_path / 'b').topic('/ga/measurements').count == 4
    shutil.copy(tmp_path / 'b' / 'b.mcap', tmp_path / 'b' / 'c.mcap')
    with pytest.raises(FormatError, match='not a rosbag2 bag'):
        bag_info(tmp_path / 'b')


def test_source_values_that_are_not_a_name_leave_the_source_unknown(
        rng: np.random.Generator) -> None:
    """A publisher that fills the twist's covariance with numbers: the measurement is kept,
    its source unknown; a name too long for the field is refused with what to do."""
    msg = _odometry(rng)
    msg.twist.covariance = np.full(36, 0.25)
    assert odometry_to_measurement(msg).source == ''
    msg.twist.covariance = np.eye(6).reshape(36) * 300.0
    assert odometry_to_measurement(msg).source == ''
    m = random_measurements(rng, 1)[0]
    with pytest.raises(InputError, match='shorter input name'):
        measurement_to_odometry(Measurement(m.src_id, m.dst_id, m.src_track, m.dst_track, m.z,
                                            m.cov, m.stamp_ns, m.kind, 'x' * 37))
