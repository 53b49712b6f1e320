"""Standard odometry / pose inputs -> Measurements (ga_ros.inputs.odometry), with synthetic
odometry whose ground truth and noise are known."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pytest
import yaml

from ga_ros.core.tracks import TrackRules, TrackSegmenter
from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.inputs.odometry import OdometryInput, OdometryInputConfig, usable_covariance

NS = 1_000_000_000


@dataclass
class Stream:
    """A synthetic odometry stream: truth, measured poses and their covariances."""

    stamps: np.ndarray
    T_true: np.ndarray
    T_odom: np.ndarray
    pose_cov_parent: np.ndarray
    twist_cov: np.ndarray


def _twists(n: int, dt: float) -> np.ndarray:
    """Body twists (n, 6): a planar robot driving curves at ~1 m/s with some 3-D wobble."""
    k = np.arange(n) * dt
    v = np.zeros((n, 6))
    v[:, 0] = 1.0 + 0.3 * np.sin(0.2 * k)
    v[:, 1] = 0.05 * np.cos(0.7 * k)
    v[:, 2] = 0.02 * np.sin(1.3 * k)
    v[:, 3] = 0.02 * np.sin(0.9 * k)
    v[:, 4] = 0.02 * np.cos(1.1 * k)
    v[:, 5] = 0.25 * np.sin(0.1 * k)
    return v


def _stream(rng: np.random.Generator, n: int = 1000, dt: float = 0.1) -> Stream:
    """Integrate true and noisy twists; the pose covariance is propagated as a random walk."""
    sig_v = np.array([0.05, 0.03, 0.02, 0.01, 0.01, 0.03])
    Sv = np.diag(sig_v ** 2)
    v = _twists(n, dt)
    D_true = se3.exp(v * dt)
    D_meas = se3.exp((v + sig_v * rng.standard_normal((n, 6))) * dt)
    A = se3.adjoint(se3.inverse(D_meas))
    T_true = se3.integrate(np.eye(4), D_true)
    T_odom = se3.integrate(np.eye(4), D_meas)
    C = np.empty((n + 1, 6, 6))
    C[0] = np.diag([1e-4] * 3 + [1e-6] * 3)
    for k in range(n):
        C[k + 1] = A[k] @ C[k] @ A[k].T + dt * dt * Sv
    B = np.zeros((n + 1, 6, 6))
    B[:, :3, :3] = B[:, 3:, 3:] = T_odom[:, :3, :3]
    C_parent = B @ C @ B.transpose(0, 2, 1)
    stamps = (np.arange(n + 1) * dt * NS).astype(np.int64) + 10 * NS
    return Stream(stamps, T_true, T_odom, C_parent, np.broadcast_to(Sv, (n + 1, 6, 6)))


def _feed(inp: OdometryInput, s: Stream, pose: bool = True, twist: bool = True) -> list:
    out = []
    for k in range(len(s.stamps)):
        up = inp.add_sample(int(s.stamps[k]), s.T_odom[k], s.pose_cov_parent[k] if pose else None,
                            s.twist_cov[k] if twist and k > 0 else None)
        out.append(up)
    return out


def _nees(inp: OdometryInput, ups: list, s: Stream) -> np.ndarray:
    idx = {int(t): k for k, t in enumerate(s.stamps)}
    kf_k = {ups[0].keyframe_id: 0}
    out = []
    for up in ups:
        if up.measurement is None:
            continue
        m = up.measurement
        kf_k[m.dst_id] = idx[m.stamp_ns]
        a, b = kf_k[m.src_id], kf_k[m.dst_id]
        T_true = se3.relative(s.T_true[a], s.T_true[b])
        xi = se3.log(se3.inverse(T_true) @ m.T_src_dst)
        out.append(float(xi @ np.linalg.solve(m.cov, xi)))
    return np.asarray(out)


@pytest.mark.parametrize('source', ['twist', 'pose_difference'])
def test_motion_covariance_is_consistent_with_the_truth(source: str) -> None:
    """Monte-Carlo NEES of the keyframe motions under both documented covariance models."""
    rng = np.random.default_rng(11)
    nees = []
    for _ in range(3):
        s = _stream(rng)
        inp = OdometryInput(OdometryInputConfig(covariance_source=source, keyframe_travel_m=1.0,
                                                keyframe_rotation_deg=0.0))
        ups = _feed(inp, s, pose=source != 'twist', twist=source == 'twist')
        assert all(u.covariance_source == source for u in ups if u.measurement)
        assert inp.stats.default_covariances == 0
        nees.append(_nees(inp, ups, s))
    nees = np.concatenate(nees)
    assert len(nees) > 250
    # mean of n chi2(6) variables: sd sqrt(12 / n) ~ 0.2
    assert abs(nees.mean() - 6.0) < 0.8, nees.mean()


def test_twist_and_pose_difference_agree() -> None:
    """Both readings of one random-walk stream give the same covariance (batch vs recursion)."""
    s = _stream(np.random.default_rng(3), n=200)
    a = _feed(OdometryInput(OdometryInputConfig(covariance_source='twist')), s, pose=False)
    b = _feed(OdometryInput(OdometryInputConfig(covariance_source='pose_difference')), s,
              twist=False)
    ma = [u.measurement for u in a if u.measurement]
    mb = [u.measurement for u in b if u.measurement]
    assert len(ma) == len(mb) > 10
    for x, y in zip(ma, mb):
        np.testing.assert_allclose(x.cov, y.cov, rtol=1e-6, atol=1e-14)
        np.testing.assert_allclose(x.z, y.z, atol=1e-12)


def test_pose_independent_is_the_sum() -> None:
    s = _stream(np.random.default_rng(4), n=100)
    ups = _feed(OdometryInput(OdometryInputConfig(covariance_source='pose_independent')), s,
                twist=False)
    kf = [0] + [int(np.searchsorted(s.stamps, u.stamp_ns)) for u in ups if u.measurement]
    m = [u.measurement for u in ups if u.measurement][1]
    a, b = kf[1], kf[2]
    Ca, Cb = (_body(s, a), _body(s, b))
    A = se3.adjoint(se3.relative(s.T_odom[b], s.T_odom[a]))
    np.testing.assert_allclose(m.cov, A @ Ca @ A.T + Cb, rtol=1e-9, atol=1e-15)


def _body(s: Stream, k: int) -> np.ndarray:
    B = np.zeros((6, 6))
    B[:3, :3] = B[3:, 3:] = s.T_odom[k, :3, :3]
    return B.T @ s.pose_cov_parent[k] @ B


@pytest.mark.parametrize('cov', [np.zeros((6, 6)), -np.ones((6, 6)), None,
                                 np.diag([-1.0, 1, 1, 1, 1, 1]), np.full((6, 6), np.nan)])
def test_missing_covariances_get_the_documented_default(cov) -> None:
    cfg = OdometryInputConfig(default_noise_percent=10.0, default_depth_m=5.0,
                              keyframe_travel_m=2.0)
    inp = OdometryInput(cfg)
    T = se3.from_translation_rotvec(np.array([0.0, 0, 0]), np.zeros(3))
    inp.add_sample(NS, T, cov, cov)
    T2 = se3.from_translation_rotvec(np.array([3.0, 4.0, 0]), np.array([0, 0, 0.1]))
    up = inp.add_sample(2 * NS, T2, cov, cov)
    assert up.default_covariance and up.covariance_source == 'default'
    assert inp.stats.default_covariances == 1
    # paper model written out: 10 % of |t| = 5 m per axis; rotation 10 % of max(0.1, 5 / 5)
    expected = np.diag([0.5 ** 2] * 3 + [0.1 ** 2] * 3)
    np.testing.assert_allclose(up.measurement.cov, expected, rtol=1e-12)
    assert not usable_covariance(cov)


def test_default_is_floored_for_a_still_robot() -> None:
    cfg = OdometryInputConfig(keyframe_interval_s=1.0, default_sigma_floor_m=0.02,
                              default_sigma_floor_rad=0.003)
    inp = OdometryInput(cfg)
    inp.add_sample(0, np.eye(4))
    up = inp.add_sample(2 * NS, np.eye(4))
    np.testing.assert_allclose(np.diag(up.measurement.cov), [4e-4] * 3 + [9e-6] * 3)
    assert np.linalg.eigvalsh(up.measurement.cov).min() > 0


def test_constant_covariance_falls_back_to_the_default() -> None:
    """A driver publishing one fixed covariance: the difference is not PD -> default, flagged."""
    inp = OdometryInput(OdometryInputConfig(keyframe_travel_m=1.0))
    C = np.diag([0.1, 0.1, 0.1, 0.01, 0.01, 0.01])
    for k in range(30):
        T = se3.from_translation_rotvec(np.array([0.1 * k, 0, 0]), np.array([0, 0, 0.02 * k]))
        up = inp.add_sample(k * NS // 10, T, C)
    assert inp.stats.measurements >= 2
    assert inp.stats.default_covariances == inp.stats.measurements
    assert up.keyframe_id >= 2


def test_keyframe_rules() -> None:
    # travel: 1 m/s at 10 Hz, 1 m rule -> a keyframe every 10 samples
    inp = OdometryInput(OdometryInputConfig(keyframe_travel_m=0.99, keyframe_rotation_deg=0))
    kf = [k for k in range(101) if inp.add_sample(
        k * NS // 10, se3.from_translation_rotvec(np.array([0.1 * k, 0, 0]), np.zeros(3))
    ).new_keyframe]
    assert kf == list(range(0, 101, 10))
    # rotation in place at 30 deg/s, 15 deg rule -> every 0.5 s
    inp = OdometryInput(OdometryInputConfig(keyframe_travel_m=1.0, keyframe_rotation_deg=14.9))
    kf = [k for k in range(41) if inp.add_sample(
        k * NS // 10, se3.from_translation_rotvec(np.zeros(3), np.deg2rad([0, 0, 3.0 * k]))
    ).new_keyframe]
    assert kf == list(range(0, 41, 5))
    # time: still robot, 2 s rule
    inp = OdometryInput(OdometryInputConfig(keyframe_interval_s=2.0))
    kf = [k for k in range(51) if inp.add_sample(k * NS // 10, np.eye(4)).new_keyframe]
    assert kf == [0, 20, 40]


def test_bad_samples_change_nothing() -> None:
    inp = OdometryInput()
    inp.add_sample(NS, np.eye(4))
    with pytest.raises(InputError, match='not after'):
        inp.add_sample(NS, np.eye(4))
    bad = np.eye(4)
    bad[:3, :3] *= 2
    with pytest.raises(InputError, match='rotation'):
        inp.add_sample(2 * NS, bad)
    with pytest.raises(InputError, match='covariance_source'):
        OdometryInputConfig(covariance_source='magic')
    assert inp.stats.samples == 1


def _lawnmower(n_legs: int = 4, leg_m: float = 20.0, step_m: float = 0.5) -> list[np.ndarray]:
    """Poses of back-and-forth legs along x, 5 m apart in y, turning at each end."""
    poses = []
    for leg in range(n_legs):
        xs = np.arange(0, leg_m, step_m)
        if leg % 2:
            xs = xs[::-1]
        yaw = 0.0 if leg % 2 == 0 else np.pi
        for x in xs:
            poses.append(se3.from_translation_rotvec(np.array([x, 5.0 * leg, 0]),
                                                     np.array([0, 0, yaw])))
    return poses


def test_heading_reversals_make_tracks() -> None:
    inp = OdometryInput(OdometryInputConfig(track=TrackRules('heading', swaths=2),
                                            keyframe_travel_m=2.0, keyframe_rotation_deg=0))
    tracks = [inp.add_sample(k * NS, T) for k, T in enumerate(_lawnmower(6))]
    ms = [u.measurement for u in tracks if u.measurement]
    assert sorted({m.dst_track for m in ms}) == [0, 1, 2]
    assert all(m.dst_track - m.src_track in (0, 1) for m in ms)


def test_segmenter_distance_time_and_requests() -> None:
    seg = TrackSegmenter(TrackRules('distance', length_m=10.0))
    ids = []
    for k in range(25):
        seg.update(se3.from_translation_rotvec(np.array([float(k), 0, 0]), np.zeros(3)))
        ids.append(seg.track_id)
    assert ids[10] == 0 and ids[11] == 1 and ids[22] == 2
    seg = TrackSegmenter(TrackRules('time', duration_s=5.0))
    starts = [k for k in range(20) if seg.update(np.eye(4), k * NS)]
    assert starts == [6, 12, 18]
    seg = TrackSegmenter(TrackRules('external'))
    assert not seg.update(np.eye(4))
    seg.request_boundary()
    assert seg.update(np.eye(4)) and seg.track_id == 1
    with pytest.raises(InputError):
        TrackRules('distance')


def _noise_free_circle(n: int = 400, dt: float = 0.1) -> tuple[np.ndarray, np.ndarray]:
    """Constant-twist motion (a helix): geodesic interpolation between samples is exact."""
    v = np.array([1.0, 0, 0.05, 0, 0, 0.1])
    stamps = (np.arange(n) * dt * NS).astype(np.int64)
    poses = np.stack([se3.exp(v * dt * k) for k in range(n)])
    return stamps, poses


def test_constraint_from_stamps_maps_onto_keyframes() -> None:
    stamps, poses = _noise_free_circle()
    inp = OdometryInput(OdometryInputConfig(keyframe_travel_m=2.0, constraint_tolerance_s=1.0))
    ups = [inp.add_sample(int(t), T) for t, T in zip(stamps, poses)]
    kf_stamps = np.array([u.stamp_ns for u in ups if u.new_keyframe])
    ta, tb = int(stamps[33] + 0.04 * NS), int(stamps[301] + 0.07 * NS)
    T_true_a = se3.exp(np.array([1.0, 0, 0.05, 0, 0, 0.1]) * ta * 1e-9)
    T_true_b = se3.exp(np.array([1.0, 0, 0.05, 0, 0, 0.1]) * tb * 1e-9)
    C = np.diag([0.01, 0.02, 0.03, 1e-4, 2e-4, 3e-4])
    m = inp.constraint_from_stamps(ta, tb, se3.relative(T_true_a, T_true_b), C)
    assert m.kind == 'cross'
    assert (m.src_id, m.dst_id) == tuple(int(np.argmin(np.abs(kf_stamps - t))) for t in (ta, tb))
    T_expected = se3.relative(inp.keyframe_pose(m.src_id), inp.keyframe_pose(m.dst_id))
    np.testing.assert_allclose(m.T_src_dst, T_expected, atol=1e-9)
    assert np.linalg.eigvalsh(m.cov).min() > 0
    # at a keyframe's own stamps the offsets vanish and the covariance is the constraint's
    ka, kb = inp.keyframe_pose(2), inp.keyframe_pose(5)
    i2, i5 = (int(np.argmin([np.abs(p - k).max() for p in poses])) for k in (ka, kb))
    m = inp.constraint_from_stamps(int(stamps[i2]), int(stamps[i5]), se3.relative(ka, kb), C)
    assert (m.src_id, m.dst_id) == (2, 5)
    np.testing.assert_allclose(m.cov, C, rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(m.T_src_dst, se3.relative(ka, kb), atol=1e-12)


def test_constraint_errors_and_node_ids() -> None:
    stamps, poses = _noise_free_circle(100)
    inp = OdometryInput(OdometryInputConfig(keyframe_travel_m=2.0, constraint_tolerance_s=0.3))
    for t, T in zip(stamps, poses):
        inp.add_sample(int(t), T)
    C = np.eye(6) * 1e-3
    with pytest.raises(InputError, match='outside the odometry'):
        inp.constraint_from_stamps(int(stamps[-1]) + NS, int(stamps[3]), np.eye(4), C)
    with pytest.raises(InputError, match='no keyframe within'):
        inp.constraint_from_stamps(int(stamps[10]), int(stamps[50]), np.eye(4), C)
    with pytest.raises(InputError, match='both constraint stamps'):
        inp.constraint_from_stamps(int(stamps[0]), int(stamps[1]), np.eye(4), C)
    with pytest.raises(InputError, match='unknown node id'):
        inp.constraint_from_nodes(0, 99, np.eye(4), C)
    before = inp.stats.default_covariances
    m = inp.constraint_from_nodes(0, 3, np.eye(4), None)
    assert m.kind == 'cross' and inp.stats.default_covariances == before + 1
    assert inp.stats.constraints == 1


def test_yaml_mirrors_config_defaults() -> None:
    path = Path(__file__).resolve().parents[2] / 'config' / 'inputs.yaml'
    section = yaml.safe_load(path.read_text())['odom0']
    expected = {k: v for k, v in asdict(OdometryInputConfig()).items() if k != 'name'}
    assert section == expected
    assert OdometryInputConfig.from_mapping('odom0', section) == OdometryInputConfig()
    with pytest.raises(InputError, match='unknown input settings'):
        OdometryInputConfig.from_mapping('odom1', {'keyframe_travle_m': 2.0})


def test_a_restarted_input_numbers_on_from_the_given_node_and_track() -> None:
    """``continue_from``: keyframes numbered from the given node on the given track (the
    keyframe poses found by those ids); after samples, a fresh chain from the next sample (the
    former keyframes forgotten, no motion from them); negative ids refused."""
    inp = OdometryInput(OdometryInputConfig(keyframe_travel_m=0.99, keyframe_rotation_deg=0))
    inp.continue_from(40, 3)
    ups = [inp.add_sample(k * NS // 10, se3.from_translation_rotvec(np.array([0.1 * k, 0, 0]),
                                                                  np.zeros(3)))
           for k in range(31)]
    ms = [u.measurement for u in ups if u.measurement is not None]
    assert [(m.src_id, m.dst_id, m.src_track, m.dst_track) for m in ms] == [
        (40, 41, 3, 3), (41, 42, 3, 3), (42, 43, 3, 3)]
    np.testing.assert_allclose(inp.keyframe_pose(42)[:3, 3], [2.0, 0, 0], atol=1e-12)
    with pytest.raises(InputError, match='unknown node id 39'):
        inp.keyframe_pose(39)
    inp.continue_from(50, 4)
    with pytest.raises(InputError, match='unknown node id 42'):
        inp.keyframe_pose(42)
    with pytest.raises(InputError, match='no keyframe yet'):
        inp.constraint_from_stamps(NS, 2 * NS, np.eye(4), None)
    up = inp.add_sample(31 * NS // 10, se3.from_translation_rotvec(np.array([3.1, 0, 0]),
                                                                   np.zeros(3)))
    assert (up.keyframe_id, up.track_id, up.new_keyframe, up.measurement) == (50, 4, True, None)
    up = inp.add_sample(42 * NS // 10, se3.from_translation_rotvec(np.array([4.2, 0, 0]),
                                                                   np.zeros(3)))
    m = up.measurement
    assert (m.src_id, m.dst_id, m.src_track, m.dst_track) == (50, 51, 4, 4)
    np.testing.assert_allclose(m.z[:3], [1.1, 0, 0], atol=1e-12)
    assert inp.keyframe_ids == (50, 52)
    with pytest.raises(InputError, match='>= 0'):
        inp.continue_from(-1, 4)
