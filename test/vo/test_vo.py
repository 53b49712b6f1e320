"""Stereo VO core: motion refinement (Jacobian, covariance consistency), calibration and
rectification, and the odometry on simulated pairs with known motion and on bad input."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from scipy import stats

from ga_ros.core.tracks import TrackRules
from ga_ros.errors import DegenerateGeometryError, InputError
from ga_ros.geometry import se3
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene
from ga_ros.vo.calibration import CameraModel, StereoCalibration
from ga_ros.vo.evaluate import motion_errors
from ga_ros.vo.motion import _residuals, point_covariance, project, refine_motion, triangulate
from ga_ros.vo.odometry import StereoFrame, StereoOdometry, VoConfig, VoState

K = np.array([[240.0, 0.0, 159.5], [0.0, 240.0, 119.5], [0.0, 0.0, 1.0]])
BASELINE = 10.0


def random_motion(rng: np.random.Generator) -> np.ndarray:
    return se3.exp(np.concatenate([rng.normal(0, 5.0, 3), rng.normal(0, 0.05, 3)]))


def synthetic_pair(rng: np.random.Generator, T_src_dst: np.ndarray, n: int = 150,
                   sigma_px: float = 0.3, sigma_d: float = 0.2):
    """Stereo points at src (noisy disparity) and their noisy pixels at dst."""
    uv = np.column_stack([rng.uniform(0, 319, n), rng.uniform(0, 239, n)])
    depth = rng.uniform(45, 105, n)
    X_true = triangulate(uv, K[0, 0] * BASELINE / depth, K, BASELINE)
    d_noisy = K[0, 0] * BASELINE / depth + rng.normal(0, sigma_d, n)
    X = triangulate(uv, d_noisy, K, BASELINE)
    cov_X = point_covariance(uv, d_noisy, K, BASELINE, 0.0, sigma_d)
    T_dst_src = se3.inverse(T_src_dst)
    Xd = X_true @ T_dst_src[:3, :3].T + T_dst_src[:3, 3]
    uv_dst = project(Xd, K) + rng.normal(0, sigma_px, (n, 2))
    return X, uv_dst, cov_X


def test_triangulate_inverts_projection(rng):
    X = np.column_stack([rng.uniform(-30, 30, 50), rng.uniform(-20, 20, 50),
                         rng.uniform(40, 100, 50)])
    uv = project(X, K)
    d = K[0, 0] * BASELINE / X[:, 2]
    np.testing.assert_allclose(triangulate(uv, d, K, BASELINE), X, rtol=1e-12)


def test_point_covariance_matches_finite_differences(rng):
    uv = np.array([[30.0, 200.0]])
    d = np.array([40.0])
    s_uv, s_d = 0.5, 0.3
    C = point_covariance(uv, d, K, BASELINE, s_uv, s_d)[0]
    J = np.zeros((3, 3))
    h = 1e-5
    for k in range(3):
        e = np.zeros(3)
        e[k] = h
        plus = triangulate(uv + e[:2], d + e[2], K, BASELINE)[0]
        minus = triangulate(uv - e[:2], d - e[2], K, BASELINE)[0]
        J[:, k] = (plus - minus) / (2 * h)
    np.testing.assert_allclose(C, J @ np.diag([s_uv ** 2, s_uv ** 2, s_d ** 2]) @ J.T,
                               rtol=1e-6)


def test_residual_jacobian_matches_finite_differences(rng):
    T = random_motion(rng)
    X, uv, cov_X = synthetic_pair(rng, T, n=10)
    r0, J, _, _ = _residuals(T, X, uv, K, cov_X, np.full(10, 0.3))
    h = 1e-6
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        rp = _residuals(T @ se3.exp(e), X, uv, K, cov_X, np.full(10, 0.3))[0]
        rm = _residuals(T @ se3.exp(-e), X, uv, K, cov_X, np.full(10, 0.3))[0]
        np.testing.assert_allclose(J[:, :, k], (rp - rm) / (2 * h), rtol=1e-5, atol=1e-5)


def test_refine_recovers_the_motion_exactly_without_noise(rng):
    T = random_motion(rng)
    X, uv, cov_X = synthetic_pair(rng, T, sigma_px=0.0, sigma_d=0.0)
    cov_X = cov_X + 1e-6 * np.eye(3)
    start = T @ se3.exp(np.array([0.5, -0.3, 0.2, 0.01, -0.02, 0.01]))
    est = refine_motion(X, uv, K, start, cov_X, 0.3)
    np.testing.assert_allclose(se3.log(se3.inverse(T) @ est.T_src_dst), 0, atol=1e-7)
    assert est.n_inliers == len(X)


def test_refine_gates_gross_outliers(rng):
    T = random_motion(rng)
    X, uv, cov_X = synthetic_pair(rng, T)
    uv[:10] += rng.uniform(20, 40, (10, 2))
    est = refine_motion(X, uv, K, T, cov_X, 0.3)
    assert not est.inliers[:10].any()
    assert est.inliers[10:].mean() > 0.98
    with pytest.raises(DegenerateGeometryError):
        refine_motion(X[:4], uv[:4], K, T, cov_X[:4], 0.3)


def test_covariance_is_consistent_monte_carlo():
    """NEES of the refined motion over many noisy pairs: chi-square with 6 dof (mean 6)."""
    rng = np.random.default_rng(11)
    nees = []
    for _ in range(300):
        T = random_motion(rng)
        X, uv, cov_X = synthetic_pair(rng, T, sigma_px=0.4, sigma_d=0.25)
        # Prior sigmas too small by a common factor: the variance factor s^2 must absorb it
        # (it is floored at 1, so a too large prior is not scaled down).
        est = refine_motion(X, uv, K, T, cov_X * 0.25, 0.2)
        e = se3.log(se3.inverse(T) @ est.T_src_dst)
        nees.append(e @ np.linalg.solve(est.cov, e))
        assert np.all(np.linalg.eigvalsh(est.cov) > 0)
    nees = np.asarray(nees)
    assert 5.4 < nees.mean() < 6.6
    # Distribution check against chi-square(6).
    assert stats.kstest(nees, 'chi2', args=(6,)).pvalue > 1e-3


# ----------------------------------------------------------------------------- calibration
def test_calibration_from_rectified_camera_infos():
    P_r = np.hstack([K, [[-K[0, 0] * BASELINE], [0], [0]]])
    left = CameraModel(320, 240, K, np.zeros(5), np.eye(3), np.hstack([K, np.zeros((3, 1))]))
    right = CameraModel(320, 240, K, np.zeros(5), np.eye(3), P_r)
    cal = StereoCalibration.from_camera_models(left, right)
    assert not cal.needs_rectification
    assert cal.baseline_m == pytest.approx(BASELINE)
    with pytest.raises(InputError):
        StereoCalibration.from_camera_models(left, left)  # zero baseline
    with pytest.raises(InputError):
        StereoCalibration.from_camera_models(left, CameraModel(640, 480, K, P=P_r))


def test_rectification_undoes_lens_distortion():
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=3))
    scene = make_scene(survey, StereoRig(), seed=2)
    left, right = scene.render_pair(survey.T_world_cam[1])
    D = np.array([-0.12, 0.03, 0.0005, -0.0003, 0.0])
    K_raw = K.copy()
    K_raw[0, 2] += 3.0
    # Raw (distorted) images: raw pixel -> undistorted normalised -> rectified pixel.
    u, v = np.meshgrid(np.arange(320, dtype=np.float64), np.arange(240, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    rect = cv2.undistortPoints(pts, K_raw, D, P=K).reshape(240, 320, 2).astype(np.float32)
    raw_l = cv2.remap(left, rect[..., 0], rect[..., 1], cv2.INTER_LINEAR)
    raw_r = cv2.remap(right, rect[..., 0], rect[..., 1], cv2.INTER_LINEAR)
    P_l = np.hstack([K, np.zeros((3, 1))])
    P_r = np.hstack([K, [[-K[0, 0] * BASELINE], [0], [0]]])
    cal = StereoCalibration.from_camera_models(CameraModel(320, 240, K_raw, D, np.eye(3), P_l),
                                               CameraModel(320, 240, K_raw, D, np.eye(3), P_r))
    assert cal.needs_rectification
    out_l, out_r = cal.rectify(raw_l, raw_r)
    c = (slice(30, 210), slice(40, 280))
    err = np.abs(out_l[c].astype(float) - left[c].astype(float))
    raw_err = np.abs(raw_l[c].astype(float) - left[c].astype(float))
    assert np.median(err) < 3.0 < np.median(raw_err)
    assert np.median(np.abs(out_r[c].astype(float) - right[c].astype(float))) < 3.0


# ----------------------------------------------------------------------------- odometry
@pytest.fixture(scope='module')
def swath():
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=16, seed=4))
    rig = StereoRig()
    scene = make_scene(survey, rig, seed=4)
    rng = np.random.default_rng(4)
    frames = [scene.render_pair(T, rng) for T in survey.T_world_cam[:16]]
    cal = StereoCalibration.rectified(rig.width, rig.height, rig.K, rig.baseline_m)
    return survey, frames, cal


def run(vo, survey, frames, start=0):
    results, kf_frame = [], {}
    for i, (left, right) in enumerate(frames):
        res = vo.process(StereoFrame(left, right, int(survey.stamps_ns[start + i])))
        if res.keyframe is not None or res.status in ('initialised', 'keyframe'):
            kf_frame[res.keyframe_id] = start + i
        results.append(res)
    return results, kf_frame


def test_odometry_measures_known_motion(swath):
    survey, frames, cal = swath
    vo = StereoOdometry(cal, VoConfig())
    results, kf_frame = run(vo, survey, frames)
    assert results[0].status == 'initialised' and results[0].measurement is None
    meas = [r.measurement for r in results if r.measurement is not None]
    assert len(meas) >= 4
    rel, rot = [], []
    for k, m in enumerate(meas):
        assert m.kind == 'consecutive' and m.src_track == m.dst_track == 0
        assert m.dst_id == m.src_id + 1 == meas[0].src_id + k + 1  # a chain of keyframes
        T_true = se3.relative(survey.T_world_cam[kf_frame[m.src_id]],
                              survey.T_world_cam[kf_frame[m.dst_id]])
        dt, dr, _ = motion_errors(T_true, m)
        rel.append(dt / np.linalg.norm(T_true[:3, 3]))
        rot.append(dr)
        np.testing.assert_allclose(m.cov, m.cov.T)
        assert np.all(np.linalg.eigvalsh(m.cov) > 0)
        assert m.stamp_ns == survey.stamps_ns[kf_frame[m.dst_id]]
    assert np.median(rel) < 0.01
    assert np.median(rot) < 0.1
    # The integrated pose follows the truth (first camera = VO world).
    T_rel = se3.relative(survey.T_world_cam[0], survey.T_world_cam[len(frames) - 1])
    drift = np.linalg.norm(results[-1].T_world_cam[:3, 3] - T_rel[:3, 3])
    assert drift < 0.02 * np.linalg.norm(T_rel[:3, 3])


def test_bad_input_raises_and_changes_nothing(swath):
    survey, frames, cal = swath
    vo = StereoOdometry(cal, VoConfig())
    vo.process(StereoFrame(*frames[0], 0))
    state = (vo.state, vo._kf_id, vo._T_kf_prev.copy())
    left, right = frames[1]
    for bad in (StereoFrame(left[:, :300], right, 1), StereoFrame(left, right[:200], 1),
                StereoFrame(left.astype(np.float32), right, 1),
                StereoFrame(left[None], right, 1)):
        with pytest.raises(InputError):
            vo.process(bad)
    assert (vo.state, vo._kf_id) == state[:2]
    np.testing.assert_array_equal(vo._T_kf_prev, state[2])
    res = vo.process(StereoFrame(cv2.cvtColor(left, cv2.COLOR_GRAY2BGR), right, 1))
    assert res.status in ('tracked', 'keyframe')  # colour input is accepted


def test_black_frame_and_lost_track_reinitialise(swath):
    survey, frames, cal = swath
    vo = StereoOdometry(cal, VoConfig())
    r0 = vo.process(StereoFrame(*frames[0], 0))
    vo.process(StereoFrame(*frames[1], 1))
    black = np.zeros_like(frames[0][0])
    res = vo.process(StereoFrame(black, black, 2))
    assert res.status == 'rejected' and 'textureless' in res.reason
    assert res.measurement is None and vo.state == VoState.LOST
    res = vo.process(StereoFrame(*frames[3], 3))
    assert res.status == 'initialised' and res.measurement is None
    assert res.keyframe_id > r0.keyframe_id
    # A frame from elsewhere (no overlap): lost, no measurement, re-initialised on it.
    res = vo.process(StereoFrame(*frames[15], 4))
    assert res.status == 'lost' and res.measurement is None
    assert vo.state == VoState.TRACKING
    res = vo.process(StereoFrame(*frames[14], 5))
    assert res.status in ('tracked', 'keyframe')


def test_track_boundary_by_keyframe_count(swath):
    survey, frames, cal = swath
    vo = StereoOdometry(cal, VoConfig(track=TrackRules('frames', keyframes=3)))
    results, _ = run(vo, survey, frames)
    meas = [r.measurement for r in results if r.measurement is not None]
    tracks = [m.dst_track for m in meas]
    assert tracks == sorted(tracks) and tracks[-1] >= 1
    assert any(m.src_track + 1 == m.dst_track for m in meas)  # a track-crossing motion
    with pytest.raises(InputError):
        VoConfig(track=TrackRules('frames', keyframes=0))
    with pytest.raises(InputError):
        VoConfig(track=TrackRules('sometimes'))


def test_external_track_boundary(swath):
    survey, frames, cal = swath
    vo = StereoOdometry(cal, VoConfig(track=TrackRules('external')))
    tracks = []
    for i, (left, right) in enumerate(frames):
        if i == 6:
            vo.request_track_boundary()
        res = vo.process(StereoFrame(left, right, i))
        if res.measurement is not None:
            tracks.append((res.measurement.src_track, res.measurement.dst_track))
    assert tracks[0] == (0, 0) and tracks[-1] == (1, 1)
    assert (0, 1) in tracks  # the motion across the boundary links the two tracks


def test_covariance_on_rendered_pairs_is_not_overconfident():
    """Loose statistical check on simulated images (the bench reports the precise NEES): the
    mean NEES of the consecutive motions of one track stays within a factor 2 of 6."""
    from ga_ros.vo.evaluate import BenchConfig, run_benchmark

    out = run_benchmark(BenchConfig(n_tracks=1, positions_per_swath=30, seed=5, cross=False))
    nees = out['consecutive']['nees']
    assert nees['n'] >= 25
    assert 3.0 < nees['mean'] < 12.0
    assert out['consecutive']['translation_error_pct']['median'] < 1.0
    assert out['consecutive']['rotation_error_deg']['median'] < 0.1
