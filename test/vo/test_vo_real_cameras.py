"""The VO with real cameras: the variance factor floored at 1, keyframe and track rules that scale
with the scene depth (1 m to 150 m without tuning), and an EuRoC-like 752x480 pair with
radial-tangential distortion that gives measurements with default settings."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from ga_ros.core.tracks import TrackRules
from ga_ros.geometry import se3
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene
from ga_ros.vo.calibration import CameraModel, StereoCalibration
from ga_ros.vo.motion import _residuals, point_covariance, project, refine_motion, triangulate
from ga_ros.vo.odometry import StereoFrame, StereoOdometry, VoConfig

K = np.array([[240.0, 0.0, 159.5], [0.0, 240.0, 119.5], [0.0, 0.0, 1.0]])


def _points(rng: np.random.Generator, T_src_dst: np.ndarray, n: int, sigma_px: float):
    """Stereo points at ``src`` (exact) and their pixels at ``dst`` with noise ``sigma_px``."""
    uv = np.column_stack([rng.uniform(0, 319, n), rng.uniform(0, 239, n)])
    d = K[0, 0] * 10.0 / rng.uniform(45, 105, n)
    X = triangulate(uv, d, K, 10.0)
    cov_X = point_covariance(uv, d, K, 10.0, 0.0, 0.2)
    T_dst_src = se3.inverse(T_src_dst)
    uv_dst = project(X @ T_dst_src[:3, :3].T + T_dst_src[:3, 3], K)
    return X, uv_dst + rng.normal(0, sigma_px, uv_dst.shape), cov_X


def _information(T: np.ndarray, X: np.ndarray, uv: np.ndarray, cov_X: np.ndarray,
                 sigma_px: float) -> np.ndarray:
    """``sum J_i^T C_i^-1 J_i`` with ``J`` by central differences on the manifold."""
    n = len(X)
    sig = np.full(n, sigma_px)
    _, _, W, _ = _residuals(T, X, uv, K, cov_X, sig)
    J = np.zeros((n, 2, 6))
    h = 1e-6
    for k in range(6):
        e = np.zeros(6)
        e[k] = h
        J[:, :, k] = (_residuals(T @ se3.exp(e), X, uv, K, cov_X, sig)[0]
                      - _residuals(T @ se3.exp(-e), X, uv, K, cov_X, sig)[0]) / (2 * h)
    return np.einsum('nai,nab,nbj->ij', J, W, J)


def test_still_camera_covariance_is_not_shrunk_by_a_small_variance_factor() -> None:
    """Residuals far below the prior noise (a still camera) leave the prior covariance; larger
    residuals scale it by s^2 as before."""
    rng = np.random.default_rng(7)
    T = np.eye(4)  # still camera
    X, uv, cov_X = _points(rng, T, 120, sigma_px=0.01)
    est = refine_motion(X, uv, K, T, cov_X, 0.3)
    assert est.sigma0_sq < 0.05  # the unfloored covariance would be > 20x too small
    N = _information(est.T_src_dst, X[est.inliers], uv[est.inliers], cov_X[est.inliers], 0.3)
    np.testing.assert_allclose(est.cov, np.linalg.inv(N), rtol=1e-4)
    # Noisier than the prior: the covariance is s^2 (J^T C^-1 J)^-1, s^2 > 1.
    T = se3.exp(np.array([3.0, -2.0, 0.5, 0.01, 0.02, -0.03]))
    X, uv, cov_X = _points(rng, T, 120, sigma_px=0.9)
    est = refine_motion(X, uv, K, T, cov_X, 0.3)
    assert est.sigma0_sq > 2.0
    N = _information(est.T_src_dst, X[est.inliers], uv[est.inliers], cov_X[est.inliers], 0.3)
    np.testing.assert_allclose(est.cov, est.sigma0_sq * np.linalg.inv(N), rtol=1e-4)


@pytest.fixture(scope='module')
def three_swaths():
    """Rendered pairs of three swaths with two turns (aerial scene, depth 45-105 m)."""
    survey = lawnmower(LawnmowerConfig(n_tracks=2, positions_per_swath=6, step_m=6.0,
                                       turn_positions=12, seed=3))
    n = 3 * 6 + 2 * 12
    rig = StereoRig()
    scene = make_scene(survey, rig, seed=3)
    rng = np.random.default_rng(3)
    frames = [scene.render_pair(T, rng) for T in survey.T_world_cam[:n]]
    return survey, frames, rig, _run(frames, survey, rig, 1.0)


def _run(frames, survey, rig: StereoRig, scale: float) -> list:
    """The VO on the same images with the calibration of a world scaled by ``scale``."""
    cal = StereoCalibration.rectified(rig.width, rig.height, rig.K, rig.baseline_m * scale)
    vo = StereoOdometry(cal, VoConfig(track=TrackRules('heading', swaths=2)))
    return [vo.process(StereoFrame(left, right, int(survey.stamps_ns[i])))
            for i, (left, right) in enumerate(frames)]


@pytest.mark.parametrize('scale', [0.02, 1.6])
def test_keyframe_and_track_rules_scale_with_depth(three_swaths, scale: float) -> None:
    """The same images seen as a scene 50x smaller (depth 1-2 m) or 1.6x larger (70-170 m):
    the same keyframes, tracks and rotations, and translations scaled by the factor."""
    survey, frames, rig, ref = three_swaths
    out = _run(frames, survey, rig, scale)
    assert [r.status for r in out] == [r.status for r in ref]
    m_ref = [r.measurement for r in ref if r.measurement is not None]
    m_out = [r.measurement for r in out if r.measurement is not None]
    assert len(m_out) == len(m_ref) >= 8
    assert [(m.src_track, m.dst_track) for m in m_out] == [
        (m.src_track, m.dst_track) for m in m_ref]
    assert m_ref[-1].dst_track >= 1  # the heading rule found a track boundary
    depth = np.array([r.median_depth_m for r in out if r.status == 'keyframe'])
    assert np.all((depth > 40 * scale) & (depth < 110 * scale))
    for a, b in zip(m_out, m_ref):
        np.testing.assert_allclose(a.z[:3], scale * b.z[:3], rtol=1e-3, atol=1e-4 * scale)
        np.testing.assert_allclose(a.z[3:], b.z[3:], atol=1e-5)


# EuRoC MAV cam0 (752x480, radial-tangential) intrinsics, distortion and a small rectifying
# rotation per camera.
EUROC_K = np.array([[458.654, 0.0, 367.215], [0.0, 457.296, 248.375], [0.0, 0.0, 1.0]])
EUROC_D = np.array([-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05, 0.0])


def _raw_maps(K_rect: np.ndarray, R: np.ndarray, w: int, h: int) -> tuple:
    """Remap tables making the raw image of a camera (``EUROC_K``, ``EUROC_D``, rectifying
    rotation ``R``) from its rectified image."""
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pts = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    rect = cv2.undistortPoints(pts, EUROC_K, EUROC_D, R=R, P=K_rect).reshape(h, w, 2)
    return rect[..., 0].astype(np.float32), rect[..., 1].astype(np.float32)


def test_euroc_like_distorted_752x480_pairs_give_measurements() -> None:
    """A 752x480 pair sequence with EuRoC's lens distortion, 11 cm baseline and 2-5 m depth
    (the aerial scene scaled by 1/20), 20 Hz at 1.6 m/s: default VoConfig, raw images and
    CameraInfo-like models in, measurements close to the truth out."""
    scale = 0.05
    n = 32
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=n, step_m=1.6,
                                       turn_positions=0, frame_period_s=0.05, seed=6))
    rig = StereoRig(752, 480, 458.0, 0.11 / scale)
    scene = make_scene(survey, rig, seed=6)
    rng = np.random.default_rng(6)
    R_l = cv2.Rodrigues(np.array([0.004, -0.006, 0.002]))[0]
    R_r = cv2.Rodrigues(np.array([-0.003, 0.005, -0.001]))[0]
    P_l = np.hstack([rig.K, np.zeros((3, 1))])
    P_r = np.hstack([rig.K, [[-rig.K[0, 0] * 0.11], [0.0], [0.0]]])
    cal = StereoCalibration.from_camera_models(
        CameraModel(752, 480, EUROC_K, EUROC_D, R_l, P_l),
        CameraModel(752, 480, EUROC_K, EUROC_D, R_r, P_r))
    assert cal.needs_rectification and cal.baseline_m == pytest.approx(0.11)
    vo = StereoOdometry(cal, VoConfig())
    maps_l, maps_r = _raw_maps(rig.K, R_l, 752, 480), _raw_maps(rig.K, R_r, 752, 480)
    meas, kf_frame = [], {}
    for i in range(n):
        left, right = scene.render_pair(survey.T_world_cam[i], rng)
        res = vo.process(StereoFrame(cv2.remap(left, *maps_l, cv2.INTER_LINEAR),
                                     cv2.remap(right, *maps_r, cv2.INTER_LINEAR),
                                     int(survey.stamps_ns[i])))
        assert res.status in ('initialised', 'tracked', 'keyframe'), res.reason
        if res.status in ('initialised', 'keyframe'):
            kf_frame[res.keyframe_id] = i
        if res.measurement is not None:
            meas.append(res.measurement)
    assert len(meas) >= 3
    errs = []
    for m in meas:
        T_true = se3.relative(survey.T_world_cam[kf_frame[m.src_id]],
                              survey.T_world_cam[kf_frame[m.dst_id]])
        t_true = scale * T_true[:3, 3]
        errs.append(np.linalg.norm(m.z[:3] - t_true) / np.linalg.norm(t_true))
    assert np.median(errs) < 0.05, errs
    assert all(np.all(np.linalg.eigvalsh(m.cov) > 0) for m in meas)
