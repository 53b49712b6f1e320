"""Message <-> core conversions (ga_ros.ros.conversions): round trips, rejection of bad input."""

from __future__ import annotations

import math

import numpy as np
import pytest

pytest.importorskip('rclpy')

from ga_ros.core import encoding
from ga_ros.core.measurement import Measurement  # noqa: E402
from ga_ros.errors import InputError  # noqa: E402
from ga_ros.geometry import se3  # noqa: E402
from ga_ros.ros import conversions as conv  # noqa: E402


def random_spd(rng: np.random.Generator, d: int = 6) -> np.ndarray:
    A = rng.normal(size=(d, d))
    return A @ A.T + 0.1 * np.eye(d)


def random_measurement(rng: np.random.Generator, kind: str = 'consecutive') -> Measurement:
    z = np.concatenate([rng.normal(size=3) * 5.0, rng.normal(size=3) * 0.5])
    return Measurement(int(rng.integers(0, 10**9)), int(rng.integers(10**9, 2 * 10**9)),
                       int(rng.integers(0, 100)), int(rng.integers(0, 100)), z,
                       random_spd(rng), int(rng.integers(0, 2**62)), kind)


@pytest.mark.parametrize('kind', ['consecutive', 'cross'])
def test_measurement_round_trip(rng, kind):
    for _ in range(20):
        m = random_measurement(rng, kind)
        msg = conv.measurement_to_odometry(m)
        assert msg.header.frame_id == f'ga/{m.src_track}/{m.src_id}'
        assert msg.child_frame_id == f'ga/{m.dst_track}/{m.dst_id}'
        assert msg.twist.twist.linear.x == (1.0 if kind == 'cross' else 0.0)
        back = conv.odometry_to_measurement(msg)
        assert (back.src_id, back.dst_id, back.src_track, back.dst_track, back.stamp_ns,
                back.kind) == (m.src_id, m.dst_id, m.src_track, m.dst_track, m.stamp_ns, m.kind)
        np.testing.assert_allclose(back.T_src_dst, m.T_src_dst, atol=1e-12)
        np.testing.assert_allclose(back.cov, m.cov, rtol=0, atol=0)


def test_encoding_fields_by_hand():
    """The encoding written out by hand: 90 deg about z, 1 m along x, row-major covariance."""
    cov = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    cov[0, 1] = cov[1, 0] = 0.5
    m = Measurement(7, 8, 2, 2, np.array([1.0, 0, 0, 0, 0, math.pi / 2]), cov,
                    3 * 10**9 + 25, 'consecutive')
    msg = conv.measurement_to_odometry(m)
    assert (msg.header.stamp.sec, msg.header.stamp.nanosec) == (3, 25)
    assert msg.pose.pose.position.x == pytest.approx(1.0)
    assert msg.pose.pose.orientation.z == pytest.approx(math.sqrt(0.5))
    assert msg.pose.pose.orientation.w == pytest.approx(math.sqrt(0.5))
    assert list(msg.pose.covariance[:8]) == [1.0, 0.5, 0, 0, 0, 0, 0.5, 2.0]


def _valid_msg(rng):
    return conv.measurement_to_odometry(random_measurement(rng))


@pytest.mark.parametrize('mutate', [
    lambda m: setattr(m.header, 'frame_id', 'odom'),
    lambda m: setattr(m.header, 'frame_id', 'ga/1/-3'),
    lambda m: setattr(m, 'child_frame_id', 'ga/1/2/3'),
    lambda m: setattr(m, 'child_frame_id', f'ga/1/{2**60}'),
    lambda m: setattr(m, 'child_frame_id', m.header.frame_id),
    lambda m: setattr(m.pose.pose.position, 'x', float('nan')),
    lambda m: setattr(m.pose.pose.orientation, 'w', float('inf')),
    lambda m: setattr(m.pose.pose.orientation, 'w', m.pose.pose.orientation.w + 0.5),
    lambda m: m.pose.covariance.__setitem__(0, -1.0),
    lambda m: m.pose.covariance.__setitem__(7, float('nan')),
    lambda m: m.pose.covariance.__setitem__(1, m.pose.covariance[1] + 10.0),
    lambda m: setattr(m.pose, 'covariance', np.zeros(36)),
    lambda m: setattr(m.twist.twist.linear, 'x', 0.5),
], ids=['frame', 'negative-id', 'extra-part', 'absurd-id', 'self-loop', 'nan-pos', 'inf-quat',
        'non-unit-quat', 'neg-variance', 'nan-cov', 'asym-cov', 'zero-cov', 'kind-flag'])
def test_malformed_measurements_rejected(rng, mutate):
    msg = _valid_msg(rng)
    conv.odometry_to_measurement(msg)      # valid before the mutation
    mutate(msg)
    with pytest.raises(InputError):
        conv.odometry_to_measurement(msg)


def test_rank_deficient_covariance_rejected(rng):
    msg = _valid_msg(rng)
    v = rng.normal(size=(6, 5))
    msg.pose.covariance = (v @ v.T).reshape(36)     # PSD, rank 5
    with pytest.raises(InputError, match='positive definite'):
        conv.odometry_to_measurement(msg)


def test_frame_id_helpers():
    assert conv.node_frame_id(3, 12) == 'ga/3/12'
    assert conv.parse_node_frame_id('ga/3/12') == (3, 12)
    assert conv.parse_node_frame_id('/ga/3/12') == (3, 12)
    for bad in ['', 'ga/3', 'ga/x/1', 'ga/1/1.5', 'map', 'ga//1']:
        with pytest.raises(InputError):
            conv.parse_node_frame_id(bad)
    with pytest.raises(InputError):
        conv.node_frame_id(-1, 0)


def test_stamp_round_trip():
    for ns in [0, 1, 999_999_999, 1_000_000_000, 1_700_000_000_123_456_789]:
        assert conv.stamp_to_ns(conv.ns_to_stamp(ns)) == ns
    with pytest.raises(InputError):
        conv.ns_to_stamp(-1)


def test_path_round_trip(rng):
    xi = rng.normal(size=(30, 6))
    T = se3.exp(xi)
    stamps = np.arange(30) * 10**8
    msg = conv.path_to_msg(T, stamps, 'map')
    assert msg.header.frame_id == 'map'
    assert len(msg.poses) == 30
    assert conv.stamp_to_ns(msg.header.stamp) == stamps[-1]
    assert conv.stamp_to_ns(msg.poses[4].header.stamp) == stamps[4]
    np.testing.assert_allclose(conv.path_msg_to_poses(msg), T, atol=1e-12)
    empty = conv.path_to_msg(np.zeros((0, 4, 4)), [], 'map')
    assert empty.poses == [] and conv.path_msg_to_poses(empty).shape == (0, 4, 4)
    with pytest.raises(InputError):
        conv.path_to_msg(T, stamps[:-1], 'map')


def test_pose_covariance_and_odometry(rng):
    T = se3.exp(rng.normal(size=6))
    cov = random_spd(rng)
    pc = conv.pose_with_covariance_msg(T, cov, 'map', 5)
    np.testing.assert_allclose(conv.msg_to_pose(pc.pose.pose), T, atol=1e-12)
    np.testing.assert_array_equal(conv.msg_to_covariance(pc.pose.covariance), cov)
    od = conv.odometry_msg(T, cov, 'map', 'ga/1/2', 5)
    assert (od.header.frame_id, od.child_frame_id) == ('map', 'ga/1/2')
    np.testing.assert_allclose(conv.msg_to_pose(od.pose.pose), T, atol=1e-12)


def test_network_markers_and_colours():
    p = np.array([[0.0, 0, 0], [1, 0, 0], [1, 1, 0]])
    arr = conv.network_markers(p, [0, 1], [1, 2], [0.0, 10.0], 'map', 0)
    clear, nodes, lines = arr.markers
    assert clear.action == clear.DELETEALL
    assert len(nodes.points) == 3
    assert len(lines.points) == 4 and len(lines.colors) == 4
    assert (lines.points[2].x, lines.points[3].y) == (1.0, 1.0)
    # residual 0 -> green, residual >= scale -> red
    assert (lines.colors[0].r, lines.colors[0].g) == (0.0, 1.0)
    assert (lines.colors[2].r, lines.colors[2].g) == (1.0, 0.0)
    np.testing.assert_allclose(conv.residual_color([1.5], scale=3.0)[0], [1, 1, 0, 1])
    with pytest.raises(InputError):
        conv.network_markers(p, [0], [3], [1.0], 'map', 0)


def test_diagnostics():
    msg = conv.diagnostics_msg('ga', 'alignment', {'nodes': 10, 'sigma0_sq': 1.23456789}, 7,
                               level=1, message='warn')
    assert msg.status[0].level == bytes([1])
    assert conv.diagnostics_to_dict(msg) == {'nodes': '10', 'sigma0_sq': '1.23457'}


@pytest.mark.parametrize('angle', [0.0, 1e-10, 1e-5, 0.3, 2.0, np.pi - 1e-6, np.pi])
def test_quaternion_to_rotvec_matches_se3(rng, angle):
    """The scalar decoder agrees with the vectorised se3 helpers, including the small-angle branch,
    angles near pi, and quaternions given with w < 0 (same rotation)."""
    for sign in (1.0, -1.0):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        T = se3.from_translation_rotvec(rng.normal(size=3), angle * axis)
        p, q = se3.to_pos_quat(T)
        w = encoding.quat_to_rotvec(*(sign * q))
        np.testing.assert_allclose(se3.from_translation_rotvec(p, np.array(w)), T, atol=1e-12)


def _read_pointcloud2(msg) -> dict[str, np.ndarray]:
    """A PointCloud2 reader written from the message definition (sensor_msgs/PointField
    datatypes, offsets, point_step, row_step, is_bigendian), as RViz and Foxglove read it."""
    sizes = {1: 'i1', 2: 'u1', 3: 'i2', 4: 'u2', 5: 'i4', 6: 'u4', 7: 'f4', 8: 'f8'}
    order = '>' if msg.is_bigendian else '<'
    raw = bytes(msg.data)
    assert len(raw) == msg.row_step * msg.height
    out = {}
    for f in msg.fields:
        dt = np.dtype(order + sizes[f.datatype])
        values = []
        for row in range(msg.height):
            for col in range(msg.width):
                start = row * msg.row_step + col * msg.point_step + f.offset
                values.append(np.frombuffer(raw, dt, f.count, start))
        out[f.name] = np.concatenate(values) if values else np.zeros(0, dt)
    return out


def test_cloud_to_pointcloud2_as_viewers_read_it(rng):
    from sensor_msgs.msg import PointField

    n = 257
    points = rng.normal(0, 50, (n, 3)).astype(np.float32)
    intensity = rng.integers(0, 256, n).astype(np.float32)
    msg = conv.cloud_to_pointcloud2(points, intensity, 'cam_optical', 1_700_000_000_123_456_789)
    assert msg.header.frame_id == 'cam_optical'
    assert conv.stamp_to_ns(msg.header.stamp) == 1_700_000_000_123_456_789
    assert (msg.height, msg.width, msg.point_step, msg.row_step) == (1, n, 16, 16 * n)
    assert not msg.is_bigendian and msg.is_dense
    assert [(f.name, f.offset, f.datatype, f.count) for f in msg.fields] == [
        ('x', 0, PointField.FLOAT32, 1), ('y', 4, PointField.FLOAT32, 1),
        ('z', 8, PointField.FLOAT32, 1), ('intensity', 12, PointField.FLOAT32, 1)]
    got = _read_pointcloud2(msg)
    for k, name in enumerate('xyz'):
        np.testing.assert_array_equal(got[name], points[:, k])
    np.testing.assert_array_equal(got['intensity'], intensity)
    # float64 input is stored as float32; an empty cloud is a valid message
    msg64 = conv.cloud_to_pointcloud2(points.astype(float), intensity.astype(float), 'c', 0)
    assert bytes(msg64.data) == bytes(msg.data)
    empty = conv.cloud_to_pointcloud2(np.zeros((0, 3)), np.zeros(0), 'c', 0)
    assert empty.width == 0 and empty.row_step == 0 and len(empty.data) == 0
    with pytest.raises(InputError):
        conv.cloud_to_pointcloud2(points[:, :2], intensity, 'c', 0)
    with pytest.raises(InputError):
        conv.cloud_to_pointcloud2(points, intensity[:-1], 'c', 0)
    bad = points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError):
        conv.cloud_to_pointcloud2(bad, intensity, 'c', 0)
