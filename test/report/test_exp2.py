"""Experiment 2 from rendered stereo (issue 15 item 4): VO motions -> window / batch, the
figures' data, the VO's NEES, the cache, and Fig. 12's ground-plane warp."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from ga_ros.geometry import se3
from ga_ros.report import preset
from ga_ros.report.experiments.survey import pose_error_profiles, survey_window
from ga_ros.report.stereo_survey import (
    StereoSurveyConfig,
    ground_homography,
    load_survey,
    register_pair,
    render_vo_survey,
)
from ga_ros.sim.stereo import StereoRig, StereoScene, Terrain, TerrainConfig, nadir_rotation

TINY = StereoSurveyConfig(n_tracks=1, positions_per_swath=10, fig12_pairs=1)


@pytest.fixture(scope='module')
def tiny(tmp_path_factory):
    cache = tmp_path_factory.mktemp('exp2') / 'survey.npz'
    return render_vo_survey(TINY, cache), cache


def test_vo_survey_has_truth_motions_and_cross_connections(tiny):
    vs, _ = tiny
    n = vs.n_nodes
    assert vs.T_true.shape == (n, 4, 4) and vs.track_ids.shape == (n,)
    assert np.all(vs.src < vs.dst) and vs.cross.any() and (~vs.cross).sum() == n - 1
    # the consecutive motions form the keyframe chain (k, k + 1)
    assert np.array_equal(vs.dst[~vs.cross], vs.src[~vs.cross] + 1)
    nees = vs.nees()
    # independent NEES of the first consecutive motion
    k = int(np.nonzero(~vs.cross)[0][0])
    T_rel = se3.inverse(vs.T_true[vs.src[k]]) @ vs.T_true[vs.dst[k]]
    e = se3.log(se3.inverse(T_rel) @ se3.from_translation_rotvec(vs.z[k, :3], vs.z[k, 3:]))
    one = float(e @ np.linalg.solve(vs.cov[k], e))
    assert nees['consecutive']['n'] == n - 1 and nees['cross']['n'] == int(vs.cross.sum())
    assert nees['consecutive']['nees_p90'] >= 0 and np.isfinite(one)
    assert 0 < nees['consecutive']['nees_mean'] < 30 and 0 < nees['cross']['nees_mean'] < 30


def test_cache_returns_the_same_survey_only_for_the_same_config(tiny):
    vs, cache = tiny
    again = load_survey(TINY, cache)
    assert again is not None
    np.testing.assert_array_equal(again.z, vs.z)
    np.testing.assert_array_equal(again.fig12['img_b'], vs.fig12['img_b'])
    np.testing.assert_array_equal(again.fig12['plane'], vs.fig12['plane'])
    assert vs.fig12['plane'].shape == (len(vs.fig12['a']), 4)
    assert load_survey(replace(TINY, seed=1), cache) is None


def test_vo_motions_window_and_batch_beat_f2f(tiny):
    vs, _ = tiny
    cfg = replace(preset('tiny'), policies=('weighted',), fig8_tracks=(1,))
    res = survey_window(cfg, vs.scenario(), vs.z, vs.cov)
    s = res.summary
    assert s['batch']['raw_rmse_m'] < s['f2f']['raw_rmse_m']
    assert s['policies']['weighted']['window']['raw_rmse_m'] < s['f2f']['raw_rmse_m']
    assert set(res.paths) == {'f2f', 'batch', 'window_weighted'}
    prof = pose_error_profiles(res.paths['batch'], res.T_true)
    assert all(v.shape == (vs.n_nodes,) for v in prof.values())
    np.testing.assert_allclose(prof['position'], res.errors['batch'])
    # quality control of the batch: redundancy numbers sum to r - u (no priors)
    q = s['quality']
    assert q['redundancy_numbers_sum'] == pytest.approx(q['redundancy'], rel=1e-6)


def test_ground_homography_maps_plane_points_as_the_cameras_project_them():
    rng = np.random.default_rng(3)
    K = StereoRig().K
    T_a = se3.from_rt(nadir_rotation(np.pi / 2), np.array([0.0, 0.0, 110.0]))
    T_b = se3.from_rt(nadir_rotation(-np.pi / 2 + 0.05), np.array([20.0, 3.0, 108.0]))
    h = 30.0
    X = np.column_stack([rng.uniform(-20, 20, 50), rng.uniform(-20, 20, 50), np.full(50, h)])

    def project(T, X):
        Xc = (X - T[:3, 3]) @ T[:3, :3]
        u = Xc @ K.T
        return u[:, :2] / u[:, 2:]

    ua, ub = project(T_a, X), project(T_b, X)
    H = ground_homography(K, T_a, T_b, h)
    m = np.column_stack([ua, np.ones(50)]) @ H.T
    np.testing.assert_allclose(m[:, :2] / m[:, 2:], ub, atol=1e-8)
    # a tilted plane n . X = c (10 deg slope)
    n = np.array([np.sin(np.radians(10.0)), 0.0, np.cos(np.radians(10.0))])
    X[:, 2] = (h - n[0] * X[:, 0]) / n[2]
    ua, ub = project(T_a, X), project(T_b, X)
    H = ground_homography(K, T_a, T_b, np.r_[n, h])
    m = np.column_stack([ua, np.ones(50)]) @ H.T
    np.testing.assert_allclose(m[:, :2] / m[:, 2:], ub, atol=1e-8)


def test_registration_error_falls_with_the_better_motion():
    """Flat ground (the homography is exact): b warped with the true motion registers; the
    same motion with a 3 m / 1 deg error (an F2F-sized drift) registers worse."""
    terrain = Terrain(TerrainConfig(-80, 120, -80, 120, texture_resolution_m=0.3,
                                    min_height_m=20.0, max_height_m=20.0))
    scene = StereoScene(terrain, StereoRig(), noise_std=0.0)
    T_a = se3.from_rt(nadir_rotation(np.pi / 2), np.array([0.0, 20.0, 110.0]))
    T_b = se3.from_rt(nadir_rotation(-np.pi / 2), np.array([20.0, 25.0, 110.0]))
    img_a, img_b = scene.render(T_a), scene.render(T_b)
    good = register_pair(img_a, img_b, ground_homography(scene.rig.K, T_a, T_b, 20.0))
    drift = T_b @ se3.exp(np.array([3.0, 0.0, 0.0, 0.0, 0.0, np.radians(1.0)]))
    bad = register_pair(img_a, img_b, ground_homography(scene.rig.K, T_a, drift, 20.0))
    assert good.overlap > 0.5 and good.ncc > 0.9
    assert bad.ncc < good.ncc - 0.2 and bad.mean_abs_diff > 1.5 * good.mean_abs_diff
