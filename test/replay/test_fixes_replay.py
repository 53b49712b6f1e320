"""Absolute fixes in the replay: bags written here with rosbags, shaped like other robots' data.

* Nav2-like: ``/odom`` with all-zero covariance and a heading drift, ``/amcl_pose``
  (``PoseWithCovarianceStamped`` in ``map``: x, y, yaw variances, zeros elsewhere as AMCL sends).
* A lawnmower run with a drifting odometry and ``sensor_msgs/NavSatFix`` at 1 Hz (WGS84, ENU
  datum given or the first fix), a few fixes 30 m off (multipath), the antenna 1.5 m beside and
  0.8 m above the base (``/tf_static`` ``base_link -> gps``: ignored, the swaths would be 3 m
  apart in alternate directions).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from bag_fixtures import (
    NAV_SAT_FIX,
    ODOMETRY,
    POSE_COV_STAMPED,
    nav_sat_fix_msg,
    odometry_msg,
    pose_cov_stamped_msg,
    write_tf_static,
)

from ga_ros.core.window import AlignerConfig
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.inputs.absolute import (
    AbsoluteInputConfig,
    enu_rotation,
    geodetic_to_ecef,
    geodetic_to_enu,
)
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.io.bag import BagReader
from ga_ros.io.bag_writer import BagWriter
from ga_ros.io.trajectory import read_tum
from ga_ros.pipeline.absolute import AbsoluteSpec
from ga_ros.pipeline.inputs import InputSpec
from ga_ros.replay.config import ReplayConfig
from ga_ros.replay.inputs import InputTopics
from ga_ros.replay.pipeline import replay
from ga_ros.replay.text import result_text

RATE_HZ = 10.0
T0_NS = 1_700_000_000_000_000_000
DATUM = (47.3977, 8.5456, 488.0)  # lat, lon (deg), alt (m)


def _path(waypoints: np.ndarray, speed: float) -> np.ndarray:
    """Ground truth (n, 4, 4) along straight legs between waypoints at ``speed`` m/s, 10 Hz."""
    out = []
    for a, b in zip(waypoints[:-1], waypoints[1:]):
        d = b - a
        yaw = np.arctan2(d[1], d[0])
        n = max(1, int(round(np.linalg.norm(d) / speed * RATE_HZ)))
        for k in range(n):
            p = a + d * k / n
            out.append(se3.from_translation_rotvec(np.array([p[0], p[1], 0.0]),
                                                   np.array([0.0, 0.0, yaw])))
    return np.array(out)


def _drifting(gt: np.ndarray, rng: np.random.Generator, yaw_bias: float = 6e-4,
              scale: float = 1.02) -> np.ndarray:
    """Odometry poses (odom frame = start pose): the true increments with a heading bias per
    step, a scale error and small noise."""
    odom = [np.eye(4)]
    for k in range(1, len(gt)):
        d = se3.relative(gt[k - 1], gt[k])
        d[:3, 3] *= scale
        e = se3.from_translation_rotvec(rng.normal(0, 0.002, 3) * [1, 1, 0],
                                        np.array([0.0, 0.0, yaw_bias + rng.normal(0, 2e-4)]))
        odom.append(odom[-1] @ d @ e)
    return np.array(odom)


def _rmse(p: np.ndarray, q: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.sum((p[:, :2] - q[:, :2]) ** 2, axis=1))))


def _evaluate(res, stamps: np.ndarray, gt: np.ndarray, odom: np.ndarray,
              trajectory: str = 'trajectory_ga') -> tuple[float, float]:
    """(RMSE of the corrected trajectory, or of the output file ``trajectory``, RMSE of the
    odometry) over the keyframes (2-D)."""
    ga = read_tum(res.files[trajectory])
    idx = np.searchsorted(stamps, ga.stamps_ns)
    assert np.array_equal(stamps[idx], ga.stamps_ns)
    T_odom = gt[0] @ odom[idx]
    return (_rmse(ga.T_world_node[:, :3, 3], gt[idx, :3, 3]),
            _rmse(T_odom[:, :3, 3], gt[idx, :3, 3]))


def test_nav2_odom_with_zero_covariance_and_amcl_pose(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    square = np.array([[0, 0], [20, 0], [20, 12], [0, 12], [0, 0], [20, 0], [20, 12],
                       [0, 12], [0, 0]], float)
    gt = _path(square, 0.5)
    odom = _drifting(gt, rng)
    stamps = T0_NS + (np.arange(len(gt)) * 1e9 / RATE_HZ).astype(np.int64)
    amcl_err = []
    sig_xy, sig_yaw = 0.25, 0.05
    with BagWriter(tmp_path / 'in') as bag:
        for k, (s, T) in enumerate(zip(stamps, odom)):
            s = int(s)
            bag.write('/odom', ODOMETRY, odometry_msg(gt[0] @ T, s), s)
            if k % 10 == 5:  # AMCL at 1 Hz, between odometry keyframes
                noise = np.concatenate([rng.normal(0, sig_xy, 2), [0.0]])
                yaw = rng.normal(0, sig_yaw)
                T_m = gt[k] @ se3.from_translation_rotvec(np.zeros(3), np.array([0, 0, yaw]))
                T_m[:3, 3] += noise
                amcl_err.append(noise[:2])
                cov = np.zeros((6, 6))
                cov[0, 0] = cov[1, 1] = sig_xy ** 2
                cov[5, 5] = sig_yaw ** 2
                bag.write('/amcl_pose', POSE_COV_STAMPED,
                          pose_cov_stamped_msg(T_m, s, cov, 'map'), s)
    spec = InputSpec('/odom', 'odometry', OdometryInputConfig('odom0', keyframe_travel_m=0.5))
    amcl = AbsoluteSpec('/amcl_pose', 'pose_cov', AbsoluteInputConfig('amcl0', frame_id='map'))
    cfg = ReplayConfig(inputs=InputTopics((spec,), absolutes=(amcl,)), plot=False,
                       aligner=AlignerConfig(datum='fixes', refine_executor='inline'))
    res = replay(tmp_path / 'in', tmp_path / 'out', cfg)
    st = res.source_stats['absolute']
    assert st['amcl0']['fixes'] == len(amcl_err) and st['amcl0']['default_covariances'] == 0
    assert st['aligner']['added'] == len(amcl_err) and st['aligner']['outliers'] == 0
    rmse_ga, rmse_odom = _evaluate(res, stamps, gt, odom)
    rmse_fix = float(np.sqrt(np.mean(np.sum(np.array(amcl_err) ** 2, axis=1))))
    assert rmse_odom > 1.0  # the drift is real
    assert rmse_ga < 0.7 * rmse_fix and rmse_ga < 0.1 * rmse_odom, (rmse_ga, rmse_fix,
                                                                    rmse_odom)
    print(f'nav2: corrected {rmse_ga:.3f} m, AMCL {rmse_fix:.3f} m, odometry {rmse_odom:.3f} m')


def _enu_to_geodetic(p_enu: np.ndarray, datum) -> np.ndarray:
    """Inverse of ``geodetic_to_enu`` by Bowring's iteration (test helper)."""
    a, f = 6378137.0, 1.0 / 298.257223563
    e2 = f * (2 - f)
    x = geodetic_to_ecef(*datum) + p_enu @ enu_rotation(datum[0], datum[1])
    lon = np.arctan2(x[..., 1], x[..., 0])
    r = np.hypot(x[..., 0], x[..., 1])
    lat = np.arctan2(x[..., 2], r * (1 - e2))
    for _ in range(10):
        N = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
        h = r / np.cos(lat) - N
        lat = np.arctan2(x[..., 2], r * (1 - e2 * N / (N + h)))
    N = a / np.sqrt(1 - e2 * np.sin(lat) ** 2)
    return np.stack([np.rad2deg(lat), np.rad2deg(lon), r / np.cos(lat) - N], axis=-1)


def test_enu_against_local_radii_of_curvature() -> None:
    """Small offsets: east = (N + h) cos(lat) dlon, north = (M + h) dlat with the meridian and
    prime-vertical radii (an independent formula), to millimetres over 100 m."""
    a, f = 6378137.0, 1.0 / 298.257223563
    e2 = f * (2 - f)
    lat0, lon0, h0 = DATUM
    s = np.sin(np.deg2rad(lat0))
    N = a / np.sqrt(1 - e2 * s * s)
    M = a * (1 - e2) / (1 - e2 * s * s) ** 1.5
    dlat, dlon = 50.0 / (M + h0), 80.0 / ((N + h0) * np.cos(np.deg2rad(lat0)))
    p = geodetic_to_enu(lat0 + np.rad2deg(dlat), lon0 + np.rad2deg(dlon), h0, DATUM)
    np.testing.assert_allclose(p[:2], [80.0, 50.0], atol=2e-3)
    assert abs(p[2]) < 2e-3 + (50 ** 2 + 80 ** 2) / (2 * N)  # the curvature drop
    back = _enu_to_geodetic(np.array([123.0, -45.0, 6.0]), DATUM)
    np.testing.assert_allclose(geodetic_to_enu(*back, DATUM), [123.0, -45.0, 6.0], atol=1e-6)


@pytest.mark.parametrize('datum_given', [True, False])
def test_lawnmower_with_navsatfix_outliers(tmp_path: Path, datum_given: bool) -> None:
    rng = np.random.default_rng(11)
    legs = []
    for k in range(6):  # 6 swaths of 40 m, 8 m apart
        y = 8.0 * k
        legs += [[0.0, y], [40.0, y]] if k % 2 == 0 else [[40.0, y], [0.0, y]]
    gt = _path(np.array(legs), 1.0)
    odom = _drifting(gt, rng, yaw_bias=4e-4)
    stamps = T0_NS + (np.arange(len(gt)) * 1e9 / RATE_HZ).astype(np.int64)
    sig = 1.0
    bad = set()
    fix_err = []
    T_base_gps = se3.from_translation_rotvec(np.array([0.0, 1.5, 0.8]), np.zeros(3))
    with BagWriter(tmp_path / 'in') as bag:
        write_tf_static(bag, [('base_link', 'gps', T_base_gps)], int(stamps[0]))
        for k, (s, T) in enumerate(zip(stamps, odom)):
            s = int(s)
            bag.write('/odom', ODOMETRY, odometry_msg(T, s), s)
            if k % 10 == 3:
                p = (gt[k] @ T_base_gps)[:3, 3] + rng.normal(0, sig, 3)
                if len(fix_err) % 37 == 20:  # multipath: 30 m off
                    p = p + np.array([30.0, 0.0, 0.0])
                    bad.add(len(fix_err))
                fix_err.append(p[:2] - (gt[k] @ T_base_gps)[:2, 3])
                lla = _enu_to_geodetic(p, DATUM)
                bag.write('/fix', NAV_SAT_FIX,
                          nav_sat_fix_msg(lla, s, np.diag([sig ** 2] * 3)), s)
        # a fix without a fix: dropped and counted
        s = int(stamps[-1])
        bag.write('/fix', NAV_SAT_FIX, nav_sat_fix_msg((0.0, 0.0, 0.0), s, None, status=-1),
                  s + 1)
    spec = InputSpec('/odom', 'odometry', OdometryInputConfig('odom0', keyframe_travel_m=1.0))
    # the ENU origin: given, or the first fix (then the map frame is offset by its error,
    # which the comparison below removes)
    gnss = AbsoluteSpec('/fix', 'navsatfix', AbsoluteInputConfig(
        'fix0', use_datum=datum_given, datum=DATUM))
    cfg = ReplayConfig(inputs=InputTopics((spec,), absolutes=(gnss,)), plot=False,
                       aligner=AlignerConfig(datum='fixes', refine_executor='inline'))
    res = replay(tmp_path / 'in', tmp_path / 'out', cfg)
    st = res.source_stats['absolute']
    assert st['fix0']['dropped'] == {'fix_no_fix': 1}
    assert st['fix0']['lever_arm_from_tf'] == st['fix0']['fixes'] == len(fix_err)
    assert st['aligner']['outliers'] == len(bad) >= 3
    ga = read_tum(res.files['trajectory_ga'])
    idx = np.searchsorted(stamps, ga.stamps_ns)
    shift = np.zeros(3)
    if not datum_given:
        shift = geodetic_to_enu(*st['datums']['fix0'], DATUM)
    p_ga = ga.T_world_node[:, :3, 3] + shift
    rmse_ga = _rmse(p_ga, gt[idx, :3, 3])
    good = np.array([e for k, e in enumerate(fix_err) if k not in bad])
    rmse_fix = float(np.sqrt(np.mean(np.sum(good ** 2, axis=1))))
    _, rmse_odom = _evaluate(res, stamps, gt, odom)
    assert rmse_odom > 3.0  # the drift is real
    assert rmse_ga < 0.6 * rmse_fix and rmse_ga < 0.2 * rmse_odom, (rmse_ga, rmse_fix,
                                                                    rmse_odom)
    print(f'lawnmower: corrected {rmse_ga:.3f} m, GNSS (without outliers) {rmse_fix:.3f} m, '
          f'odometry {rmse_odom:.3f} m')
    # REP 105 earth -> map on /tf_static: the map origin is the datum's ECEF point, the map axes
    # East, North, Up there (written once, before the input's own static transform is copied)
    datum = DATUM if datum_given else tuple(st['datums']['fix0'])
    with BagReader(Path(res.files['bag'])) as reader:
        earth = [t for bm in reader.messages(['/tf_static']) for t in bm.msg.transforms
                 if t.header.frame_id == 'earth']
    assert len(earth) == 1 and earth[0].child_frame_id == 'map'
    tr = earth[0].transform
    q = [tr.rotation.x, tr.rotation.y, tr.rotation.z, tr.rotation.w]
    T = se3.from_pos_quat(np.array([tr.translation.x, tr.translation.y, tr.translation.z]),
                          np.array(q))
    lat, lon = np.deg2rad(datum[0]), np.deg2rad(datum[1])
    east = [-np.sin(lon), np.cos(lon), 0.0]
    north = [-np.sin(lat) * np.cos(lon), -np.sin(lat) * np.sin(lon), np.cos(lat)]
    up = [np.cos(lat) * np.cos(lon), np.cos(lat) * np.sin(lon), np.sin(lat)]
    np.testing.assert_allclose(T[:3, :3], np.array([east, north, up]).T, atol=1e-9)
    np.testing.assert_allclose(T[:3, 3], geodetic_to_ecef(*datum), atol=1e-6)


def test_inputs_yaml_mirrors_the_absolute_defaults() -> None:
    from dataclasses import fields

    import yaml

    path = Path(__file__).resolve().parents[2] / 'config' / 'inputs.yaml'
    section = yaml.safe_load(path.read_text())['absolutes']['fix0']
    expected = {f.name: getattr(AbsoluteInputConfig(), f.name)
                for f in fields(AbsoluteInputConfig) if f.name != 'name'}
    assert {k: tuple(v) if isinstance(v, list) else v for k, v in section.items()} == expected


def test_lever_arm_parameter_is_t_base_sensor_and_the_old_name_says_so(rng) -> None:
    """``T_base_sensor`` ``[x y z qx qy qz qw]`` (the ``T_base_<sensor>`` convention) is the
    pose ``from_pos_quat`` builds; the old ``lever_arm_m`` is refused naming the new one; a
    non-unit quaternion is refused."""
    T = se3.exp(rng.normal(size=6))
    p, q = se3.to_pos_quat(T)
    cfg = AbsoluteInputConfig.from_mapping('fix0', {'T_base_sensor': [*p, *q]})
    np.testing.assert_allclose(cfg.T_base_sensor_matrix, T, atol=1e-12)
    with pytest.raises(InputError, match=r'fix0\.lever_arm_m is now fix0\.T_base_sensor'):
        AbsoluteInputConfig.from_mapping('fix0', {'lever_arm_m': [0.0, 0.0, 1.0]})
    with pytest.raises(InputError, match='T_base_sensor'):
        AbsoluteInputConfig.from_mapping('fix0', {'T_base_sensor': [0.0] * 7})


def test_gnss_stating_too_small_a_covariance_is_named(tmp_path: Path) -> None:
    """A NavSatFix stating 0.5 m where its errors are 2 m (true factor 16), online variance
    components applied: the fix source's factor in summary.json's
    ``online_variance_components``, in the printout and a WARN naming it."""
    rng = np.random.default_rng(5)
    legs = []
    for k in range(6):
        y = 8.0 * k
        legs += [[0.0, y], [40.0, y]] if k % 2 == 0 else [[40.0, y], [0.0, y]]
    gt = _path(np.array(legs), 1.0)
    odom = _drifting(gt, rng, yaw_bias=0.0)
    stamps = T0_NS + (np.arange(len(gt)) * 1e9 / RATE_HZ).astype(np.int64)
    with BagWriter(tmp_path / 'in') as bag:
        for k, (s, T) in enumerate(zip(stamps, odom)):
            s = int(s)
            bag.write('/odom', ODOMETRY, odometry_msg(T, s), s)
            if k % 10 == 3:
                p = gt[k][:3, 3] + rng.normal(0, 2.0, 3)
                bag.write('/fix', NAV_SAT_FIX, nav_sat_fix_msg(_enu_to_geodetic(p, DATUM), s,
                                                               np.diag([0.5 ** 2] * 3)), s)
    spec = InputSpec('/odom', 'odometry', OdometryInputConfig('odom0', keyframe_travel_m=1.0))
    gnss = AbsoluteSpec('/fix', 'navsatfix', AbsoluteInputConfig('fix0', use_datum=True,
                                                                 datum=DATUM))
    cfg = ReplayConfig(inputs=InputTopics((spec,), absolutes=(gnss,)), plot=False,
                       aligner=AlignerConfig(datum='fixes', refine_executor='inline',
                                             variance_components='apply'))
    res = replay(tmp_path / 'in', tmp_path / 'out', cfg)
    fix = res.online_variance_components['fix0']
    assert fix['estimated'] and fix['applied'] and fix['factor'] > 4.0, fix
    summary = json.loads((tmp_path / 'out' / 'summary.json').read_text())
    assert summary['online_variance_components']['fix0']['factor'] == fix['factor']
    text = result_text(res)
    assert 'variance components (online' in text and '  fix0' in text, text
    assert any(w.startswith("online: fix0's stated covariance is") for w in res.warnings), \
        res.warnings
