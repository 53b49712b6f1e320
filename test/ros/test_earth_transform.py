"""REP 105 ``earth -> map`` from a NavSatFix input's ENU origin, published by the node on
``/tf_static`` (latched). The expected ECEF origin and ENU axes are written out here."""

from __future__ import annotations

import time

import numpy as np
import pytest

pytest.importorskip('rclpy')
pytest.importorskip('tf2_msgs.msg')

from rclpy.executors import SingleThreadedExecutor  # noqa: E402
from rclpy.parameter import Parameter  # noqa: E402
from tf2_msgs.msg import TFMessage  # noqa: E402

from ga_ros.geometry import se3  # noqa: E402
from ga_ros.ros.alignment_node import AlignmentNode  # noqa: E402
from ga_ros.ros.deadlines import patience  # noqa: E402
from ga_ros.ros.harness import domain_id, ros_context  # noqa: E402
from ga_ros.ros.qos import latched_qos  # noqa: E402

DATUM = (-33.8688, 151.2093, 58.0)  # lat, lon (deg), alt (m): southern, eastern hemisphere
A_WGS84, F_WGS84 = 6378137.0, 1.0 / 298.257223563


def _ecef(lat_deg: float, lon_deg: float, alt_m: float) -> np.ndarray:
    """WGS84 geodetic -> ECEF (m), written out (test's own)."""
    e2 = F_WGS84 * (2 - F_WGS84)
    lat, lon = np.deg2rad(lat_deg), np.deg2rad(lon_deg)
    N = A_WGS84 / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    return np.array([(N + alt_m) * np.cos(lat) * np.cos(lon),
                     (N + alt_m) * np.cos(lat) * np.sin(lon),
                     (N * (1 - e2) + alt_m) * np.sin(lat)])


@pytest.fixture
def ctx():
    with ros_context(domain_id(57)) as c:
        yield c


def _node(ctx, **extra) -> AlignmentNode:
    params = {'inputs': 'odom0', 'odom0.topic': 'odom', 'publish_markers': False,
              'diagnostics_period_sec': 0.0, 'transform_publish_period_sec': 0.0,
              'absolutes': 'fix0', 'fix0.topic': 'fix', 'fix0.type': 'navsatfix',
              'fix0.use_datum': True, 'fix0.datum': list(DATUM), 'datum': 'fixes', **extra}
    return AlignmentNode(context=ctx, parameter_overrides=[Parameter(k, value=v)
                                                           for k, v in params.items()])


def _navsatfix():
    from sensor_msgs.msg import NavSatFix, NavSatStatus

    msg = NavSatFix()
    msg.header.frame_id = 'gps'
    msg.header.stamp.sec = 1_700_000_000
    msg.latitude, msg.longitude, msg.altitude = DATUM[0] + 1e-5, DATUM[1], DATUM[2]
    msg.position_covariance = [4.0, 0.0, 0.0, 0.0, 4.0, 0.0, 0.0, 0.0, 9.0]
    msg.position_covariance_type = NavSatFix.COVARIANCE_TYPE_DIAGONAL_KNOWN
    msg.status.status = NavSatStatus.STATUS_FIX
    return msg


def test_node_publishes_earth_to_map_latched(ctx) -> None:
    node = _node(ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ex.add_node(node)
    got: list[TFMessage] = []
    try:
        node._on_absolute('fix0', _navsatfix())
        node._on_absolute('fix0', _navsatfix())  # once only
        # a late subscriber (latched) still gets it
        node.create_subscription(TFMessage, '/tf_static', got.append, latched_qos())
        end = time.monotonic() + patience(30)
        while time.monotonic() < end and not got:
            ex.spin_once(timeout_sec=0.05)
        earth = [t for m in got for t in m.transforms if t.header.frame_id == 'earth']
        assert len(earth) == 1 and earth[0].child_frame_id == 'map'
        tr = earth[0].transform
        T = se3.from_pos_quat(np.array([tr.translation.x, tr.translation.y, tr.translation.z]),
                              np.array([tr.rotation.x, tr.rotation.y, tr.rotation.z,
                                        tr.rotation.w]))
        # the map origin is the datum's ECEF point
        np.testing.assert_allclose(T[:3, 3], _ecef(*DATUM), atol=1e-6)
        # the map axes are East, North, Up at the datum: east along the parallel, up along the
        # ellipsoid normal, north completing them; checked by points 1 m away along each
        lat, lon = np.deg2rad(DATUM[0]), np.deg2rad(DATUM[1])
        up = np.array([np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)])
        d_east = _ecef(DATUM[0], DATUM[1] + 1e-6, DATUM[2]) - _ecef(*DATUM)
        d_north = _ecef(DATUM[0] + 1e-6, DATUM[1], DATUM[2]) - _ecef(*DATUM)
        np.testing.assert_allclose(T[:3, 0], d_east / np.linalg.norm(d_east), atol=1e-6)
        np.testing.assert_allclose(T[:3, 1], d_north / np.linalg.norm(d_north), atol=1e-6)
        np.testing.assert_allclose(T[:3, 2], up, atol=1e-9)
        np.testing.assert_allclose(np.linalg.det(T[:3, :3]), 1.0, atol=1e-12)
    finally:
        ex.shutdown()
        node.destroy_node()


def test_switched_off_or_without_the_fixes_frame_nothing_is_published(ctx) -> None:
    for extra in ({'publish_earth_transform': False}, {'datum': 'first_node'}):
        node = _node(ctx, **extra)
        try:
            node._on_absolute('fix0', _navsatfix())
            assert node._pub_earth is None
        finally:
            node.destroy_node()


@pytest.mark.parametrize('lose_datum_file', [False, True])
def test_a_restart_keeps_the_map_origin_of_the_saved_state(ctx, tmp_path,
                                                           lose_datum_file) -> None:
    """Without ``use_datum`` the first fix sets the ENU origin; it is saved beside the state
    file and journaled, so after a restart (also with the datum file lost: from the journal) a
    fix elsewhere lands where it is relative to that origin (not at the new first fix), in the
    frame of the restored poses."""
    from ga_ros.pipeline.journal import datum_path

    state = str(tmp_path / 'state.npz')
    first = _node(ctx, **{'fix0.use_datum': False, 'state_file': state})
    try:
        first._on_absolute('fix0', _navsatfix())  # at DATUM + 1e-5 deg north: the origin
        saved = first.absolute.earth_datum()
    finally:
        first.destroy_node()
    assert datum_path(state).exists()
    np.testing.assert_allclose(saved, (DATUM[0] + 1e-5, DATUM[1], DATUM[2]))
    if lose_datum_file:
        datum_path(state).unlink()

    again = _node(ctx, **{'fix0.use_datum': False, 'state_file': state})
    try:
        assert again.absolute.earth_datum() == saved  # before any fix
        msg = _navsatfix()
        msg.latitude = DATUM[0]  # 1e-5 deg south of the origin
        again._on_absolute('fix0', msg)
        (_, fix, _), = again.absolute._pending
        p = np.asarray(fix.T_map_sensor)[:3, 3]
    finally:
        again.destroy_node()
    expected = np.linalg.norm(_ecef(*DATUM) - _ecef(*saved))
    assert expected > 1.0
    assert p[1] < 0 and abs(np.linalg.norm(p) - expected) < 1e-3 and abs(p[0]) < 1e-6
