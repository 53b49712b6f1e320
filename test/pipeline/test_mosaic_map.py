"""The live mosaic (ga_ros.pipeline.mosaic_map.LiveMosaic): after corrections it equals a mosaic
built from scratch from the final poses by ga_ros.mapping.mosaic.build_mosaic; a correction
re-warps only the keyframes it moved; memory bounds; bad input refused with nothing changed."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.mapping.mosaic import CameraView, MosaicConfig, build_mosaic
from ga_ros.mapping.surface import GroundPlane
from ga_ros.pipeline.mosaic_map import LiveMosaic, MosaicMapConfig

sim = pytest.importorskip('ga_ros.sim.stereo')

GROUND_Z = 20.0
MPP = 0.4
#: the camera 0.2 m ahead of and 0.5 m below base_link, looking down (optical axes)
T_BASE_CAM = se3.from_rt(np.eye(3), np.array([0.2, 0.0, -0.5]))


def flat_scene() -> sim.StereoScene:
    cfg = sim.TerrainConfig(-80.0, 160.0, -80.0, 180.0, texture_resolution_m=0.15,
                            min_height_m=GROUND_Z, max_height_m=GROUND_Z, seed=3)
    return sim.StereoScene(sim.Terrain(cfg), sim.StereoRig(), noise_std=0.0)


def survey(scene: sim.StereoScene) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """Stamps, images and true ``T_map_base`` of a 3-track lawnmower (8 keyframes a track)."""
    T_cam, tracks = [], []
    for t, x in enumerate((0.0, 20.0, 40.0)):
        ys = np.arange(8) * 10.0
        heading = np.pi / 2 if t % 2 == 0 else -np.pi / 2
        for y in (ys if t % 2 == 0 else ys[::-1]):
            T_cam.append(se3.from_rt(sim.nadir_rotation(heading), np.array([x, y, 110.0])))
            tracks.append(t)
    T_cam = np.asarray(T_cam)
    images = [scene.render(T) for T in T_cam]
    T_map_base = T_cam @ se3.inverse(T_BASE_CAM)
    stamps = 1_000_000_000 + np.arange(len(T_cam), dtype=np.int64) * 500_000_000
    return stamps, images, T_map_base


def drifted(T_true: np.ndarray, seed: int = 0) -> np.ndarray:
    """Poses off by a growing drift (m, rad), as frame-to-frame odometry would be."""
    rng = np.random.default_rng(seed)
    out = T_true.copy()
    for k in range(len(out)):
        d = np.r_[rng.normal(0, 0.05 * k, 2), 0.0, 0.0, 0.0, rng.normal(0, 0.002 * k)]
        out[k] = out[k] @ se3.exp(d)
    return out


def scratch(images, T_map_base, K, georef) -> np.ndarray:
    """The independent mosaic: build_mosaic of the views in stamp order on the live grid."""
    views = [CameraView(img, T @ T_BASE_CAM, K) for img, T in zip(images, T_map_base)]
    return build_mosaic(views, GroundPlane(GROUND_Z), MosaicConfig(MPP, 'last'), georef)


def assert_same(live, ref) -> None:
    """The same mosaic, pixel for pixel (same coverage, same grey levels)."""
    assert live.valid.sum() > 0.3 * live.valid.size
    assert np.array_equal(live.valid, ref.valid)
    assert np.array_equal(live.image, ref.image)


@pytest.fixture(scope='module')
def data():
    scene = flat_scene()
    return scene.rig.K, *survey(scene)


def test_live_mosaic_after_corrections_equals_one_built_from_the_final_poses(data) -> None:
    K, stamps, images, T_true = data
    T_f2f = drifted(T_true)
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                      ground_from_clouds=False, tile_px=64))
    # poses before images for half of them, images before poses for the rest
    half = len(stamps) // 2
    live.set_poses(stamps[:half], T_f2f[:half])
    for s, img in zip(stamps, images):
        live.add_image(int(s), img, K, T_BASE_CAM)
    live.set_poses(stamps[half:], T_f2f[half:])
    before = live.mosaic()
    assert_same(before, scratch(images, T_f2f, K, before.georef))
    # the alignment's corrections, track by track
    for track in range(3):
        sel = np.arange(len(stamps)) >= 8 * track
        live.set_poses(stamps[sel], T_true[sel])
    after = live.mosaic()
    assert after.georef.metres_per_pixel == MPP
    assert_same(after, scratch(images, T_true, K, after.georef))
    # the test can fail: the drifted mosaic is not the aligned one
    ref_f2f = scratch(images, T_f2f, K, after.georef)
    both = after.valid & ref_f2f.valid
    assert np.mean(np.abs(after.image.astype(int) - ref_f2f.image.astype(int))[both] > 8) > 0.2


def test_a_correction_rewarps_only_the_keyframes_it_moved(data) -> None:
    K, stamps, images, T_true = data
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                      ground_from_clouds=False, tile_px=64))
    for s, img in zip(stamps, images):
        live.add_image(int(s), img, K, T_BASE_CAM)
    assert live.counts.warps == 0  # no pose yet
    live.set_poses(stamps, T_true)
    assert live.counts.warps == len(stamps)
    all_tiles = len(live.tiles)
    # the same poses again: nothing to do
    assert live.set_poses(stamps, T_true) == 0 and live.counts.warps == len(stamps)
    live.take_changed()
    for moved in ([3], [0, 9, 17], list(range(5, 12))):
        warps, tiles = live.counts.warps, live.counts.tiles_composited
        T = T_true.copy()
        T[moved, 0, 3] += 0.7
        assert live.set_poses(stamps, T) == len(moved)
        assert live.counts.warps - warps == len(moved)
        assert 0 < live.counts.tiles_composited - tiles < all_tiles
        assert live.take_changed()
        live.set_poses(stamps, T_true)
    assert_same(live.mosaic(), scratch(images, T_true, K, live.mosaic().georef))


def test_memory_bounds_freeze_old_keyframes_and_refuse_an_oversized_mosaic(data) -> None:
    K, stamps, images, T_true = data
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                      ground_from_clouds=False, tile_px=64,
                                      max_live_keyframes=5))
    for s, img, T in zip(stamps, images, T_true):
        live.add_image(int(s), img, K, T_BASE_CAM)
        live.set_poses([int(s)], T[None])
    assert live.n_placed == 5 and live.counts.frozen == len(stamps) - 5
    assert len(live.keyframes) == 5  # the frozen ones' images released
    assert_same(live.mosaic(), scratch(images, T_true, K, live.mosaic().georef))
    # a pixel cap below one keyframe's footprint: refused, with what to change
    small = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                       ground_from_clouds=False, tile_px=64,
                                       max_pixels=64 * 64 * 4))
    small.add_image(int(stamps[0]), images[0], K, T_BASE_CAM)
    assert small.set_poses(stamps[:1], T_true[:1]) == 1
    assert small.counts.refused == 1 and small.mosaic() is None
    assert 'mosaic_max_pixels' in small.last_error
    # images waiting for their pose are bounded
    waiting = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                         ground_from_clouds=False, max_waiting=3))
    for s, img in zip(stamps[:6], images[:6]):
        waiting.add_image(int(s), img, K, T_BASE_CAM)
    assert len(waiting.keyframes) == 3 and waiting.counts.dropped == 3
    assert sorted(waiting.keyframes) == stamps[3:6].tolist()  # the newest kept


def test_ground_from_clouds_waits_then_places(data) -> None:
    K, stamps, images, T_true = data
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=0.0, tile_px=64))
    live.add_image(int(stamps[0]), images[0], K, T_BASE_CAM)
    live.set_poses(stamps[:1], T_true[:1])
    assert live.mosaic() is None and live.counts.warps == 0
    assert live.set_ground(GROUND_Z) == 1 and live.mosaic() is not None
    # automatic resolution: height above the ground over the focal length
    h = (T_true[0] @ T_BASE_CAM)[2, 3] - GROUND_Z
    assert live.metres_per_pixel == pytest.approx(h / K[0, 0])
    assert live.set_ground(0.0) == 0 and live.ground.z_m == GROUND_Z  # fixed once


def test_bad_input_is_refused_and_changes_nothing(data) -> None:
    K, stamps, images, T_true = data
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                      ground_from_clouds=False))
    live.add_image(int(stamps[0]), images[0], K, T_BASE_CAM)
    live.set_poses(stamps[:1], T_true[:1])
    ref = live.mosaic()
    bad_T = T_true[:2].copy()
    bad_T[1, 0, 3] = np.nan
    with pytest.raises(InputError):
        live.set_poses(stamps[:2], bad_T)
    with pytest.raises(InputError):
        live.set_poses(stamps[:3], T_true[:2])
    with pytest.raises(InputError):
        live.add_image(5, images[1].astype(np.float32), K, T_BASE_CAM)
    with pytest.raises(InputError):
        live.add_image(5, images[1], np.zeros((3, 3)), T_BASE_CAM)
    with pytest.raises(InputError):
        live.add_image(5, np.dstack([images[1]] * 3), K, T_BASE_CAM)  # colour after grey
    with pytest.raises(InputError):
        MosaicMapConfig(tile_px=2)
    now = live.mosaic()
    assert np.array_equal(now.image, ref.image) and now.georef == ref.georef
    # a camera looking up sees no ground: refused, not raised
    up = se3.from_rt(np.diag([1.0, -1.0, -1.0]), np.zeros(3))
    live.add_image(7, images[1], K, up)
    live.set_poses([7], T_true[1:2])
    assert live.counts.refused == 1 and 'downward' in live.last_error
