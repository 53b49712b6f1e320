"""The map placed before the aligner's first update (ga_ros.pipeline.map_placement) and the
``map -> odom`` state that drives it (ga_ros.pipeline.map_to_odom.MapToOdom): the identity
from the first odometry message, the fixes' placement checked against the truth and against
an independent least-squares fit, the jump warning, stamps that never step back."""

from __future__ import annotations

import numpy as np
import pytest
from bag_fixtures import odometry_msg
from scipy.optimize import least_squares

from ga_ros.core.fixes import AbsoluteFix, FixTerm
from ga_ros.geometry import se3
from ga_ros.inputs.odometry import OdometryInputConfig
from ga_ros.pipeline.absolute import ResolvedFix
from ga_ros.pipeline.inputs import InputFrontEnd, InputSpec
from ga_ros.pipeline.map_placement import FixPlacement, PlacementConfig
from ga_ros.pipeline.map_to_odom import MapToOdom

T_MAP_ODOM = se3.from_translation_rotvec(np.array([7.4, -3.2, 0.0]), np.array([0, 0, 2.1]))


def _pose(x: float, y: float, yaw: float, z: float = 0.0) -> np.ndarray:
    return se3.from_translation_rotvec(np.array([x, y, z]), np.array([0.0, 0.0, yaw]))


def _fix(T_map_sensor: np.ndarray, sigma_xy: float, sigma_yaw: float | None = None,
         stamp_ns: int = 0) -> AbsoluteFix:
    """AMCL-like (x, y and optionally yaw known, the rest unknown: -1)."""
    cov = -np.eye(6)
    cov[0, 0] = cov[1, 1] = sigma_xy ** 2
    if sigma_yaw is not None:
        cov[5, 5] = sigma_yaw ** 2
    return AbsoluteFix.from_covariance(stamp_ns, T_map_sensor, cov, 'amcl0')


def test_one_oriented_fix_places_the_map_at_it():
    T_odom_sensor = _pose(1.5, 0.4, 0.3, z=0.2)
    T_map_sensor = T_MAP_ODOM @ T_odom_sensor
    p = FixPlacement().add(T_odom_sensor, _fix(T_map_sensor, 0.2, 0.05))
    assert p is not None and p.heading == 'orientation' and p.n_fixes == 1
    T = p.T_map_odom @ T_odom_sensor
    np.testing.assert_allclose(T[:2, 3], T_map_sensor[:2, 3], atol=1e-9)
    np.testing.assert_allclose(T[:3, :3], T_map_sensor[:3, :3], atol=1e-9)
    assert p.T_map_odom[2, 3] == pytest.approx(0.0)   # z unknown: odom's
    assert p.fix_sigma_m == pytest.approx(0.2)
    assert p.heading_sigma_rad == pytest.approx(0.05)


def test_position_fixes_without_motion_keep_odoms_heading_and_follow_the_newest_fix():
    place = FixPlacement(PlacementConfig(heading_sigma_max_rad=0.1))
    p = place.add(_pose(0, 0, 0), _fix(T_MAP_ODOM @ _pose(0, 0, 0), 1.0))
    assert p.heading == 'odom' and np.isinf(p.heading_sigma_rad)
    np.testing.assert_allclose(p.T_map_odom[:3, :3], np.eye(3))
    np.testing.assert_allclose(p.T_map_odom[:2, 3], T_MAP_ODOM[:2, 3], atol=1e-9)
    # 2 m of travel against 1 m fixes: heading sigma 1/sqrt(2) rad, not determined yet; the
    # sensor is put at the newest fix
    T_o = _pose(2.0, 0, 0)
    T_m = T_MAP_ODOM @ T_o
    p = place.add(T_o, _fix(T_m, 1.0))
    assert p.heading == 'odom' and p.n_fixes == 2
    np.testing.assert_allclose((p.T_map_odom @ T_o)[:2, 3], T_m[:2, 3], atol=1e-9)


def test_heading_from_motion_matches_the_truth_and_an_independent_fit(rng):
    """Noise-free: the truth; noisy (isotropic sigmas differing per fix): the weighted least
    squares minimum of sum |p_map - Rz(psi) p_odom - t|^2 / sigma^2 found by scipy."""
    T_odom = [_pose(0.8 * k, 0.3 * k ** 1.3, 0.1 * k) for k in range(12)]
    place = FixPlacement()
    for T in T_odom:
        p = place.add(T, _fix(T_MAP_ODOM @ T, 0.3))
    assert p.heading == 'motion'
    np.testing.assert_allclose(p.T_map_odom, T_MAP_ODOM, atol=1e-9)

    sig = rng.uniform(0.1, 0.5, len(T_odom))
    po = np.array([T[:2, 3] for T in T_odom])
    pm = np.array([(T_MAP_ODOM @ T)[:2, 3] for T in T_odom]) + rng.normal(0, 1, po.shape) * sig[
        :, None]
    place = FixPlacement()
    for T, q, s in zip(T_odom, pm, sig):
        p = place.add(T, _fix(_pose(q[0], q[1], 0.0), s))

    def residuals(x):
        c, s_ = np.cos(x[0]), np.sin(x[0])
        R = np.array([[c, -s_], [s_, c]])
        return ((pm - po @ R.T - x[1:]) / sig[:, None]).ravel()

    ref = least_squares(residuals, np.zeros(3), xtol=1e-14, ftol=1e-14, gtol=1e-14).x
    assert np.arctan2(p.T_map_odom[1, 0], p.T_map_odom[0, 0]) == pytest.approx(ref[0], abs=1e-7)
    np.testing.assert_allclose(p.T_map_odom[:2, 3], ref[1:], atol=1e-6)


def test_oriented_fixes_weighted_by_their_variance():
    """Two oriented fixes at one place: the heading is their inverse-variance mean (small
    angles: the circular mean equals the linear one up to third-order terms)."""
    T_o = _pose(1.0, 2.0, 0.5)
    yaw = [0.02, -0.03]
    var = [0.01 ** 2, 0.03 ** 2]
    place = FixPlacement()
    for y, v in zip(yaw, var):
        p = place.add(T_o, _fix(T_MAP_ODOM @ T_o @ _pose(0, 0, y), 0.2, np.sqrt(v)))
    expected = (yaw[0] / var[0] + yaw[1] / var[1]) / (1 / var[0] + 1 / var[1])
    got = np.arctan2(p.T_map_odom[1, 0], p.T_map_odom[0, 0]) - 2.1
    assert got == pytest.approx(expected, abs=1e-5)   # third order: 1.5e-6
    assert p.heading_sigma_rad == pytest.approx(1 / np.sqrt(1 / var[0] + 1 / var[1]))


# --------------------------------------------------------------------------- MapToOdom
def _front() -> InputFrontEnd:
    return InputFrontEnd([InputSpec('/odom', 'odometry',
                                    OdometryInputConfig('odom0', keyframe_travel_m=1.0))])


def _drive(front: InputFrontEnd, poses: list[np.ndarray], t0_ns: int = 10**9) -> list[int]:
    stamps = []
    for k, T in enumerate(poses):
        s = t0_ns + k * 100_000_000
        step = front.sample('odom0', odometry_msg(T, s))
        assert not step.error, step.error
        stamps.append(s)
    return stamps


def _resolved(front: InputFrontEnd, T_map_sensor: np.ndarray, sigma: float,
              sigma_yaw: float | None = None) -> ResolvedFix:
    """A fix at the newest odometry pose, tied to keyframe 0 (as AbsoluteFrontEnd does)."""
    odo = front.inputs[front.primary]
    T_k = odo.keyframe_pose(0)
    term = FixTerm(0, se3.inverse(T_k) @ front.latest_pose(),
                   _fix(T_map_sensor, sigma, sigma_yaw))
    return ResolvedFix(term, np.zeros((6, 6)))


def test_identity_from_the_first_odometry_message_then_the_fixes_then_the_aligner():
    front = _front()
    m2o = MapToOdom(front, datum='fixes')
    assert m2o.latest() is None                      # nothing to send before any odometry
    _drive(front, [_pose(3.0, 4.0, 0.2)])
    assert m2o.latest() is not None and m2o.placed_by == 'identity'
    np.testing.assert_allclose(m2o.T_map_odom, np.eye(4))
    assert 'identity' in m2o.diagnostic_values()['map_to_odom/placed_by']
    # the aligner's provisional path (before any update) does not place the map: it would put
    # the map at the first keyframe
    m2o.update(np.array([0]), np.eye(4)[None], adjusted=False)
    assert m2o.placed_by == 'identity'
    T_truth = T_MAP_ODOM @ front.latest_pose()
    m2o.add_fixes([_resolved(front, T_truth, 0.2, 0.05)])
    assert m2o.placed_by == 'fixes' and m2o.jumps_warned == 0   # the first placement
    np.testing.assert_allclose(m2o.T_map_odom @ front.latest_pose(), T_truth, atol=1e-9)
    # the first window update: the aligner's path places it from then on, fixes ignored
    T_k0 = front.inputs[front.primary].keyframe_pose(0)
    m2o.update(np.array([0]), (T_MAP_ODOM @ T_k0)[None], adjusted=True)
    assert m2o.placed_by == 'aligner' and m2o.jumps_warned == 0
    m2o.add_fixes([_resolved(front, _pose(0, 0, 0), 0.2, 0.05)])
    np.testing.assert_allclose(m2o.T_map_odom, T_MAP_ODOM, atol=1e-9)


def test_first_node_datum_is_placed_by_the_provisional_path():
    front = _front()
    m2o = MapToOdom(front)
    _drive(front, [_pose(3.0, 4.0, 0.2)])
    T_k0 = front.inputs[front.primary].keyframe_pose(0)
    m2o.update(np.array([0]), np.eye(4)[None], adjusted=False)
    assert m2o.placed_by == 'aligner'
    np.testing.assert_allclose(m2o.T_map_odom, se3.inverse(T_k0), atol=1e-12)
    m2o.add_fixes([_resolved(front, _pose(0, 0, 0), 0.2, 0.05)])   # not the fixes' frame
    np.testing.assert_allclose(m2o.T_map_odom, se3.inverse(T_k0), atol=1e-12)


def test_a_jump_beyond_the_fixes_sigma_is_warned_and_a_small_one_is_not():
    front = _front()
    m2o = MapToOdom(front, datum='fixes', placement=PlacementConfig(jump_sigmas=3.0))
    _drive(front, [_pose(0.1 * k, 0, 0) for k in range(3)])
    T_base = front.latest_pose()
    m2o.add_fixes([_resolved(front, T_MAP_ODOM @ T_base, 0.2, 0.05)])
    T_k0 = front.inputs[front.primary].keyframe_pose(0)
    # the aligner's first update 0.5 m (< 0.6 m = 3 sigma) off at the robot: no warning
    small = _pose(0.5, 0, 0) @ T_MAP_ODOM
    m2o.update(np.array([0]), (small @ T_k0)[None])
    assert m2o.jumps_warned == 0 and m2o.warning == ''
    assert m2o.last_jump_m == pytest.approx(0.5)
    # then 0.7 m more: warned, in the diagnostics values and the text
    big = _pose(1.2, 0, 0) @ T_MAP_ODOM
    m2o.update(np.array([0]), (big @ T_k0)[None])
    assert m2o.jumps_warned == 1 and '0.70 m' in m2o.warning and '0.60 m' in m2o.warning
    assert m2o.diagnostic_values()['map_to_odom/jumps_warned'] == 1
    m2o.update(np.array([0]), (big @ T_k0)[None])     # no change: the warning stays
    assert m2o.warning
    m2o.update(np.array([0]), (_pose(1.3, 0, 0) @ T_MAP_ODOM @ T_k0)[None])
    assert m2o.warning == '' and m2o.last_warning and m2o.jumps_warned == 1
    # the newest fix's sigma is the unit, also after the aligner placed the map: 1 m fixes
    # let it move 2 m without a warning (and no longer place it)
    placed = m2o.T_map_odom.copy()
    m2o.add_fixes([_resolved(front, _pose(50.0, 0, 0), 1.0, 0.05)])
    np.testing.assert_allclose(m2o.T_map_odom, placed)
    assert m2o.fix_sigma_m == pytest.approx(1.0)
    m2o.update(np.array([0]), (_pose(3.3, 0, 0) @ T_MAP_ODOM @ T_k0)[None])
    assert m2o.last_jump_m == pytest.approx(2.0) and m2o.jumps_warned == 1


def test_stamps_never_step_back():
    m2o = MapToOdom(_front())
    assert [m2o.stamp(s) for s in (100, 90, 150, 150, 149, 200)] == [100, 100, 150, 150, 150,
                                                                     200]
