"""The stereo image simulator: geometry of the rendered pairs against the exact ground truth."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.geometry import se3, so3
from ga_ros.sim.stereo import (
    LawnmowerConfig,
    StereoRig,
    StereoScene,
    Terrain,
    TerrainConfig,
    lawnmower,
    make_scene,
    nadir_rotation,
)


@pytest.fixture(scope='module')
def small():
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=8, turn_positions=6))
    return survey, make_scene(survey, StereoRig(), seed=3)


def test_terrain_is_seeded_and_in_range():
    cfg = TerrainConfig(0, 100, 0, 80, texture_resolution_m=0.5, seed=7)
    a, b = Terrain(cfg), Terrain(cfg)
    np.testing.assert_array_equal(a.texture, b.texture)
    assert a.heights.min() == pytest.approx(5.0, abs=1e-3)
    assert a.heights.max() == pytest.approx(65.0, abs=1e-3)
    c = Terrain(TerrainConfig(0, 100, 0, 80, texture_resolution_m=0.5, seed=8))
    assert not np.array_equal(a.texture, c.texture)
    assert a.texture.std() > 20  # textured, corner-rich
    with pytest.raises(InputError):
        Terrain(TerrainConfig(10, 0, 0, 10))


def test_nadir_rotation_is_a_rotation_looking_down():
    for h in np.linspace(-np.pi, np.pi, 7):
        R = nadir_rotation(h)
        np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-12)  # optical axis down
        np.testing.assert_allclose(-R[:2, 1], [np.cos(h), np.sin(h)], atol=1e-12)  # image up


def test_lawnmower_layout():
    cfg = LawnmowerConfig(n_tracks=2, positions_per_swath=10, turn_positions=8,
                          attitude_jitter_deg=0.0, position_jitter_m=0.0)
    s = lawnmower(cfg)
    assert len(s.T_world_cam) == 4 * 10 + 3 * 8
    np.testing.assert_array_equal(np.unique(s.swath), [0, 1, 2, 3])
    np.testing.assert_array_equal(s.track, s.swath // 2)
    assert np.all(np.diff(s.stamps_ns) > 0)
    assert np.allclose(s.T_world_cam[:, 2, 3], cfg.altitude_m)
    # Smooth flight: no jump in heading or position between frames (also through the turns).
    for a, b in zip(s.T_world_cam[:-1], s.T_world_cam[1:]):
        d = se3.relative(a, b)
        assert np.linalg.norm(d[:3, 3]) <= cfg.step_m + 1e-9
        assert np.rad2deg(np.linalg.norm(so3.log(d[:3, :3]))) < 180 / (cfg.turn_positions + 1) + 1
    # Swaths alternate direction along +y / -y at x = k * spacing.
    for k in range(4):
        p = s.T_world_cam[(s.swath == k) & ~s.in_turn][:, :3, 3]
        np.testing.assert_allclose(p[:, 0], k * cfg.swath_spacing_m, atol=1e-9)
        assert np.sign(p[-1, 1] - p[0, 1]) == (1 if k % 2 == 0 else -1)


def test_depth_is_the_terrain_intersection(small):
    survey, scene = small
    T = survey.T_world_cam[2]
    img, depth = scene.render(T, with_depth=True)
    assert img.dtype == np.uint8 and img.shape == (240, 320)
    rng = np.random.default_rng(0)
    K = scene.rig.K
    for _ in range(20):
        u, v = rng.integers(0, 320), rng.integers(0, 240)
        p_cam = depth[v, u] * np.linalg.solve(K, [u, v, 1.0])
        p = T[:3, :3] @ p_cam + T[:3, 3]
        assert p[2] == pytest.approx(scene.terrain.height_at(np.array([p[0]]),
                                                             np.array([p[1]]))[0], abs=0.02)
    assert 110 - 65 - 5 < depth.min() and depth.max() < 110 - 5 + 5


def test_stereo_pair_is_rectified_and_consistent(small):
    survey, scene = small
    T = survey.T_world_cam[3]
    left, right = scene.render_pair(T)
    _, depth = scene.render(T, with_depth=True)
    f, b = scene.rig.focal_px, scene.rig.baseline_m
    # A left pixel shows the same ground point as the right pixel u - f b / Z on the same row.
    rng = np.random.default_rng(1)
    diffs = []
    for _ in range(200):
        u, v = rng.integers(80, 300), rng.integers(10, 230)
        ur = u - f * b / depth[v, u]
        u0 = int(np.floor(ur))
        a = ur - u0
        val = (1 - a) * float(right[v, u0]) + a * float(right[v, u0 + 1])
        diffs.append(abs(val - float(left[v, u])))
    assert np.median(diffs) < 3.0  # grey levels (bilinear interpolation only)
    disp = f * b / depth
    assert 15 < disp.min() and disp.max() < 60


def test_render_is_deterministic_with_seeded_noise(small):
    survey, scene = small
    a = scene.render_pair(survey.T_world_cam[0], np.random.default_rng(5))
    b = scene.render_pair(survey.T_world_cam[0], np.random.default_rng(5))
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    with pytest.raises(InputError):
        scene.render(np.eye(3))


def test_overlap(small):
    survey, scene = small
    T = survey.T_world_cam[1]
    assert scene.overlap(T, T) == pytest.approx(1.0)
    near = T @ se3.from_rt(np.eye(3), [0.0, -10.0, 0.0])
    far = T @ se3.from_rt(np.eye(3), [0.0, -300.0, 0.0])
    assert 0.6 < scene.overlap(T, near) < 1.0
    assert scene.overlap(T, far) == 0.0


def test_rig_for_size():
    rig = StereoRig.for_size(640, 480)
    assert rig.focal_px == 480.0 and rig.K[0, 2] == pytest.approx(319.5)
    scene = StereoScene(Terrain(TerrainConfig(-150, 150, -150, 150, texture_resolution_m=0.3)),
                        rig)
    T = np.eye(4)
    T[:3, :3] = nadir_rotation(np.pi / 2)
    T[2, 3] = 110.0
    left, right = scene.render_pair(T)
    assert left.shape == right.shape == (480, 640)
