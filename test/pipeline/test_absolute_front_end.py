"""Absolute front end (ROS-free): every NavSatFix input shares one ENU origin, so two GNSS
receivers on one robot give fixes in one map frame, whichever reports first."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from ga_ros.inputs.absolute import AbsoluteInputConfig
from ga_ros.pipeline.absolute import AbsoluteFrontEnd, AbsoluteSpec

LAT, LON, ALT = 48.1372, 11.5756, 519.0
M_PER_DEG_LAT = 111_132.954 - 559.822 * np.cos(2 * np.deg2rad(LAT))  # meridian arc, first terms


def _navsat(t_s: float, lat: float, lon: float = LON, alt: float = ALT) -> SimpleNamespace:
    stamp = SimpleNamespace(sec=int(t_s), nanosec=int(round((t_s % 1) * 1e9)))
    return SimpleNamespace(
        header=SimpleNamespace(stamp=stamp, frame_id='gps'), status=SimpleNamespace(status=0),
        latitude=lat, longitude=lon, altitude=alt, position_covariance_type=2,
        position_covariance=[1.0, 0, 0, 0, 1.0, 0, 0, 0, 4.0])


def _front(**b_settings) -> AbsoluteFrontEnd:
    return AbsoluteFrontEnd([
        AbsoluteSpec('gps_a', 'navsatfix', AbsoluteInputConfig(name='gps_a')),
        AbsoluteSpec('gps_b', 'navsatfix', AbsoluteInputConfig(name='gps_b', **b_settings))])


def _positions(front: AbsoluteFrontEnd) -> dict[str, list[np.ndarray]]:
    out: dict[str, list[np.ndarray]] = {'gps_a': [], 'gps_b': []}
    for name, fix, _ in front._pending:
        out[name].append(np.asarray(fix.T_map_sensor)[:3, 3])
    return out


def test_two_navsat_inputs_share_the_first_fix_as_origin() -> None:
    front = _front()
    north = 2e-4  # deg: about 22 m
    assert not front.message('gps_b', _navsat(10.0, LAT + north)).error  # B reports first
    assert not front.message('gps_a', _navsat(10.5, LAT)).error
    assert not front.message('gps_a', _navsat(11.0, LAT + north)).error
    pos = _positions(front)
    np.testing.assert_allclose(pos['gps_b'][0], 0.0, atol=1e-9)  # B's first fix is the origin
    # A's fix at the same place is at the origin too, its fix 22 m south is 22 m south
    np.testing.assert_allclose(pos['gps_a'][1], pos['gps_b'][0], atol=1e-6)
    np.testing.assert_allclose(pos['gps_a'][0][:2], [0.0, -north * M_PER_DEG_LAT], atol=0.05)
    assert front.datums() == {'gps_a': [LAT + north, LON, ALT], 'gps_b': [LAT + north, LON, ALT]}


def test_an_input_with_its_own_datum_is_the_origin_of_the_others() -> None:
    front = _front(use_datum=True, datum=(LAT, LON, ALT))
    assert not front.message('gps_a', _navsat(10.0, LAT)).error
    np.testing.assert_allclose(_positions(front)['gps_a'][0], 0.0, atol=1e-6)
    assert front.earth_datum() == (LAT, LON, ALT)
