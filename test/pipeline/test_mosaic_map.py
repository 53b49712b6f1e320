"""The live mosaic (ga_ros.pipeline.mosaic_map.LiveMosaic): after corrections it equals a mosaic
built from scratch from the final poses by ga_ros.mapping.mosaic.build_mosaic; a correction
re-warps only the keyframes it moved; memory bounds; bad input refused with nothing changed."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.mapping.mosaic import (
    CameraView,
    Mosaic,
    MosaicConfig,
    build_mosaic,
    map_metadata_fields,
)
from ga_ros.mapping.seams import seam_misregistration
from ga_ros.mapping.surface import GroundPlane, ground_from_keyframe_points
from ga_ros.pipeline import mosaic_map
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
    assert live.mosaic() is None and live.counts.warps == 0  # no ground known yet
    T_cam = T_true[0] @ T_BASE_CAM
    ground = np.array([[x, y, GROUND_Z] for x in np.arange(-60.0, 61.0, 0.5)
                       for y in np.arange(-60.0, 61.0, 0.5)])
    pts_cam = (ground - T_cam[:3, 3]) @ T_cam[:3, :3]
    assert live.add_cloud(int(stamps[0]), pts_cam, T_BASE_CAM) == 1
    assert live.mosaic() is not None and live.surface.z_range == pytest.approx((GROUND_Z,) * 2)
    # automatic resolution: height above the ground over the focal length
    h = T_cam[2, 3] - GROUND_Z
    assert live.metres_per_pixel == pytest.approx(h / K[0, 0])


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


# ---------------------------------------------------------------- relief: the height grid
@pytest.fixture(scope='module')
def relief():
    """Two 275 m swaths over relief: stamps, images, true ``T_map_base`` and each keyframe's
    ground points in its camera frame (the scene's true ground, as a keyframe cloud)."""
    survey = sim.lawnmower(sim.LawnmowerConfig(n_tracks=1, positions_per_swath=12, step_m=25.0,
                                               turn_positions=0, seed=2))
    scene = sim.make_scene(survey, seed=2, noise_std=0.0)
    T_cam = np.asarray(survey.T_world_cam)
    images = [scene.render(T) for T in T_cam]
    clouds = [(scene.ground_points(T, 8) - T[:3, 3]) @ T[:3, :3] for T in T_cam]
    stamps = 1_000_000_000 + np.arange(len(T_cam), dtype=np.int64) * 500_000_000
    return (scene.rig.K, stamps, images, T_cam @ se3.inverse(T_BASE_CAM), clouds,
            np.asarray(survey.swath))


def offline(images, clouds, T_map_base, K, georef):
    """The offline mosaic (build_mosaic on the height grid of the same clouds at the same
    poses) on the live grid, with its views and surface."""
    T_cam = T_map_base @ T_BASE_CAM
    views = [CameraView(img, T, K) for img, T in zip(images, T_cam)]
    surface = ground_from_keyframe_points(clouds, T_cam)
    return build_mosaic(views, surface, MosaicConfig(MPP, 'last'), georef), views, surface


def assert_close(live, ref) -> None:
    """The same mosaic within what a ground stale by ``ground_tolerance_m`` (2 cm: under
    0.02 px of parallax here) gives: coverage equal but for 0.2 % of the pixels, grey levels
    within 2 for 99 % of the common ones."""
    both = live.valid & ref.valid
    diff = np.abs(live.image.astype(int) - ref.image.astype(int))[both]
    print(f'live vs offline: coverage differs at {np.mean(live.valid != ref.valid):.2e} of the '
          f'pixels, grey > 2 apart at {np.mean(diff > 2):.2e}, mean {diff.mean():.3f}')
    assert live.valid.sum() > 0.3 * live.valid.size
    assert np.mean(live.valid != ref.valid) < 2e-3 and np.mean(diff > 2) < 1e-2


@pytest.mark.parametrize('tolerance_m', [0.0, 0.02])
def test_live_mosaic_over_relief_is_the_offline_orthomosaic_of_the_final_poses(
        relief, tolerance_m: float) -> None:
    """Pixel for pixel with ``ground_tolerance_m`` 0; within :func:`assert_close` with the
    default 2 cm."""
    K, stamps, images, T_true, clouds, tracks = relief
    T_f2f = drifted(T_true, seed=1)
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, tile_px=64,
                                      ground_tolerance_m=tolerance_m))
    same = assert_same if tolerance_m == 0 else assert_close
    # clouds, images and poses interleaved as a live run delivers them
    for k, s in enumerate(stamps):
        live.add_cloud(int(s), clouds[k], T_BASE_CAM)
        live.add_image(int(s), images[k], K, T_BASE_CAM)
        live.set_poses(stamps[k:k + 1], T_f2f[k:k + 1])
    before = live.mosaic()
    ref, _, _ = offline(images, clouds, T_f2f, K, before.georef)
    same(before, ref)
    assert live.counts.ground_rewarps > 0  # later clouds changed earlier keyframes' ground
    print(f'tolerance {tolerance_m} m: {live.counts.warps} warps for {len(stamps)} keyframes '
          f'arriving one by one ({live.counts.ground_rewarps} for their ground)')
    for track in np.unique(tracks):  # the alignment's corrections, track by track
        sel = tracks >= track
        live.set_poses(stamps[sel], T_true[sel])
    after = live.mosaic()
    ref, views, surface = offline(images, clouds, T_true, K, after.georef)
    same(after, ref)
    # orthorectified: the seams of the live mosaic are those of the height grid, and a plane
    # at the middle height (the flat mosaic) misregisters them by the parallax
    on_grid = seam_misregistration(views, tracks, surface, after.georef)
    lo, hi = surface.z_range
    on_plane = seam_misregistration(views, tracks, GroundPlane(0.5 * (lo + hi)), after.georef)
    print(f'live mosaic seams: height grid {on_grid.median_px:.3f} px, plane '
          f'{on_plane.median_px:.3f} px ({on_grid.measured} pairs)')
    assert hi - lo > 5.0 and on_grid.measured >= 3
    assert on_grid.median_px < 0.3 and on_plane.median_px > 3 * on_grid.median_px + 1.0


def test_a_move_rewarps_the_keyframe_and_those_whose_ground_it_changed(relief) -> None:
    K, stamps, images, T_true, clouds, _ = relief
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, tile_px=64, ground_tolerance_m=0))
    for k, s in enumerate(stamps):
        live.add_cloud(int(s), clouds[k], T_BASE_CAM)
        live.add_image(int(s), images[k], K, T_BASE_CAM)
    live.set_poses(stamps, T_true)
    assert live.counts.warps == len(stamps)  # all clouds came first: one warp each
    cells = live.surface.cells_computed
    warps, ground = live.counts.warps, live.counts.ground_rewarps
    T = T_true.copy()
    T[0, 1, 3] += 0.9  # the first keyframe, at a corner of the survey
    assert live.set_poses(stamps, T) > 1
    rewarped = live.counts.warps - warps
    assert rewarped == 1 + live.counts.ground_rewarps - ground < len(stamps)
    assert live.surface.cells_computed - cells < live.surface.heights.size
    ref, _, _ = offline(images, clouds, T, K, live.mosaic().georef)
    assert_same(live.mosaic(), ref)


# ---------------------------------------------------------------- orientation
L_GROUND_Z = 0.0


def l_pattern(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """An L on the ground (z up, x east, y north): a long bar up y, a short one along x."""
    bar = ((0 <= x) & (x <= 20) & (0 <= y) & (y <= 5)) | ((0 <= x) & (x <= 5) & (0 <= y)
                                                            & (y <= 35))
    return np.where(bar, 220, 30).astype(np.uint8)


def render_l(T_world_cam: np.ndarray, K: np.ndarray, w: int = 320, h: int = 240) -> np.ndarray:
    """What a camera at ``T_world_cam`` (world z up) sees of the L on the plane z = 0."""
    u, v = np.meshgrid(np.arange(w) + 0.0, np.arange(h) + 0.0)
    rays = np.linalg.solve(K, np.stack([u.ravel(), v.ravel(), np.ones(u.size)]))
    d = T_world_cam[:3, :3] @ rays
    s = (L_GROUND_Z - T_world_cam[2, 3]) / d[2]
    X = T_world_cam[:3, 3, None] + s * d
    return l_pattern(X[0], X[1]).reshape(h, w)


def assert_unmirrored_l(image: np.ndarray, valid: np.ndarray) -> None:
    """The L as seen from above with x right: its corner bottom-left, its long bar up."""
    rows, cols = np.nonzero(valid & (image > 128))
    assert rows.size > 100
    r_mid, c_mid = 0.5 * (rows.min() + rows.max()), 0.5 * (cols.min() + cols.max())
    assert rows.mean() > r_mid + 2  # mass at the bottom (the short bar, y small)
    assert cols.mean() < c_mid - 2  # and at the left (the long bar, x small)
    assert rows.max() - rows.min() > 1.4 * (cols.max() - cols.min())  # tall: y is vertical


@pytest.mark.parametrize('z_up', [True, False])
def test_mosaic_is_seen_from_above_whichever_way_z_points(z_up: bool) -> None:
    K = np.array([[300.0, 0, 160], [0, 300.0, 120], [0, 0, 1]])
    T_world = np.array([se3.from_rt(sim.nadir_rotation(np.pi / 2), np.array([10.0, y, 60.0]))
                        for y in (0.0, 30.0)])
    images = [render_l(T, K) for T in T_world]
    # map = world (z up), or map with z down: x the same, y and z reversed
    F = np.eye(4) if z_up else np.diag([1.0, -1.0, -1.0, 1.0])
    T_map_cam = F @ T_world
    ground = np.array([[x, y, L_GROUND_Z, 1.0] for x in np.arange(-40.0, 60.0, 0.5)
                       for y in np.arange(-30.0, 70.0, 0.5)])
    clouds = [(np.linalg.inv(T) @ ground.T).T[:, :3] for T in T_world]  # camera frame
    stamps = np.array([1, 2], dtype=np.int64) * 1_000_000_000
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=0.25, tile_px=64))
    for k, s in enumerate(stamps):
        live.add_cloud(int(s), clouds[k], np.eye(4))
        live.add_image(int(s), images[k], K, np.eye(4))
    live.set_poses(stamps, T_map_cam)
    mos = live.mosaic()
    assert mos.georef.z_up == z_up
    assert_unmirrored_l(mos.image, mos.valid)
    # the offline mosaic follows the same convention
    views = [CameraView(img, T, K) for img, T in zip(images, T_map_cam)]
    surface = ground_from_keyframe_points(clouds, T_map_cam)
    off = build_mosaic(views, surface, MosaicConfig(0.25))
    assert off.georef.z_up == z_up
    assert_unmirrored_l(off.image, off.valid)
    ref = build_mosaic(views, surface, MosaicConfig(0.25), mos.georef)
    assert_same_pixels(mos, ref)
    # the georeference says where a pixel lies: the L's corner (x, y) = (0, 0) in the world
    rows, cols = np.nonzero(mos.valid & (mos.image > 128))
    corner = (rows.max(), cols.min())  # bottom-left bright pixel
    x, y = mos.georef.pixel_centres(int(corner[0]), int(corner[1]), 1, 1)
    assert (float(x[0, 0]), float(F[1, 1] * y[0, 0])) == pytest.approx((0.0, 0.0), abs=0.5)
    # the MapMetaData: grid row i is image row height - 1 - i from the origin along its y
    f = map_metadata_fields(mos.georef)
    origin = np.array(f['origin']['position'])
    q = f['origin']['orientation']
    R = se3.from_pos_quat(np.zeros(3), np.array(q))[:3, :3]
    assert R[2, 2] * (1 if z_up else -1) > 0  # the grid's z points up: towards the cameras
    i, j = mos.georef.height - 1 - int(corner[0]), int(corner[1])
    cell = origin + R @ np.array([(j + 0.5) * 0.25, (i + 0.5) * 0.25, 0.0])
    assert cell[:2] == pytest.approx([float(x[0, 0]), float(y[0, 0])], abs=1e-6)


def assert_same_pixels(live, ref) -> None:
    assert np.array_equal(live.valid, ref.valid)
    assert np.array_equal(live.image, ref.image)


# ---------------------------------------------------------------- memory: merged keyframes
def live_bytes(m: LiveMosaic) -> int:
    """Bytes the live keyframes hold (images, patches, points)."""
    parts = m.nbytes_by_part()
    return parts['images'] + parts['patches'] + parts['points']


def test_memory_stays_bounded_while_keyframes_arrive(relief) -> None:
    K, stamps, images, T_true, clouds, _ = relief
    limit = 6
    bounded = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, tile_px=64,
                                         max_live_keyframes=limit))
    unbounded = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, tile_px=64,
                                           max_live_keyframes=0))
    held = []
    for k, s in enumerate(stamps):
        for m in (bounded, unbounded):
            m.add_cloud(int(s), clouds[k], T_BASE_CAM)
            m.add_image(int(s), images[k], K, T_BASE_CAM)
            m.set_poses(stamps[k:k + 1], T_true[k:k + 1])
        assert bounded.n_placed <= limit and len(bounded.keyframes) <= limit
        assert len(bounded.surface.keyframes) <= limit
        held.append(live_bytes(bounded))
    assert bounded.counts.frozen == len(stamps) - limit == len(bounded.merged)
    # what one keyframe holds, from the unbounded mosaic (an independent count of the arrays)
    one = sorted(kf.image.nbytes + kf.patch.image.nbytes + kf.patch.valid.nbytes
                 + kf.patch.ground.nbytes + unbounded.surface.keyframes[key].points.nbytes
                 + 2 * unbounded.surface.keyframes[key].z.nbytes
                 for key, kf in unbounded.keyframes.items())
    assert max(held) <= sum(one[-limit:])
    assert live_bytes(unbounded) == sum(one) > 3 * held[-1]  # can fail: 24 against 6
    parts = bounded.nbytes_by_part()
    assert parts['merged_poses'] == 128 * (len(stamps) - limit)
    print(f'bytes held: {held[-1] / limit / 1e3:.0f} kB per live keyframe, bounded mosaic '
          f'{bounded.nbytes() / 1e6:.2f} MB, unbounded {unbounded.nbytes() / 1e6:.2f} MB')


def test_a_merge_changes_no_pixel_and_later_moves_of_merged_keyframes_are_ignored(
        relief) -> None:
    K, stamps, images, T_true, clouds, tracks = relief
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, tile_px=64, ground_tolerance_m=0,
                                      max_live_keyframes=0))
    for k, s in enumerate(stamps):
        live.add_cloud(int(s), clouds[k], T_BASE_CAM)
        live.add_image(int(s), images[k], K, T_BASE_CAM)
    live.set_poses(stamps, T_true)
    before, heights = live.mosaic(), live.surface.heights.copy()
    warps, points = live.counts.warps, live.nbytes_by_part()['points']
    first = stamps[tracks == tracks[0]].tolist()
    assert live.merge(first) == len(first) == live.counts.frozen
    assert_same_pixels(live.mosaic(), before)
    assert live.counts.warps == warps  # nothing re-warped
    live.surface.commit()
    assert np.array_equal(live.surface.heights, heights, equal_nan=True)
    assert live.nbytes_by_part()['points'] < 0.6 * points
    # a correction of a merged keyframe: ignored and counted, the mosaic unchanged
    T = T_true.copy()
    T[0, 0, 3] += 0.9
    assert live.set_poses(stamps[:1], T[:1]) == 0
    assert live.set_poses(stamps[1:2], T[1:2]) == 0  # its pose at the merge: not counted
    assert live.counts.merged_moves_ignored == 1
    assert live.counts.merged_max_shift_m == pytest.approx(0.9)
    assert_same_pixels(live.mosaic(), before)
    # the live swath moved: re-warped over the ground the merged clouds left, where it lies on
    # top as close to the offline mosaic of every keyframe (the merged ones at their merge
    # poses) as a ground stale by 2 cm gives; the merged keyframes are not re-warped
    sel = tracks != tracks[0]
    T = T_true.copy()
    T[sel, 0, 3] += 0.6
    assert live.set_poses(stamps[sel], T[sel]) == sel.sum()
    now = live.mosaic()
    ref, views, surface = offline(images, clouds, T, K, now.georef)
    top = build_mosaic([v for v, s in zip(views, sel) if s], surface, MosaicConfig(MPP, 'last'),
                       now.georef).valid
    assert top.mean() > 0.2
    assert_close(Mosaic(now.image, now.valid & top, now.georef),
                 Mosaic(ref.image, ref.valid & top, now.georef))


# ---------------------------------------------------------------- merging settled keyframes
def late_loop_closure(live: LiveMosaic, K, stamps, images, T_true, clouds=None) -> list[int]:
    """Feed a survey whose first keyframes are corrected last; returns the keyframes placed
    after each update.

    Seven updates: update u < 6 adds keyframes 4u .. 4u + 3 (group u) 1.5 m off their true
    poses and corrects group u - 1 to its true poses (group 0 excepted); group 0 is still being
    corrected at every update (1 m off, +- 0.3 m: a background refinement at work, 2.5 px at
    0.4 m/px), and the last update moves it and group 5 to their true poses (a loop closure)."""
    groups = np.arange(len(stamps)) // 4
    off = np.eye(4)
    placed = []
    for u in range(7):
        T = T_true.copy()
        T[groups == u, 0, 3] += 1.5
        if u < 6:
            T[groups == 0, 0, 3] += 1.0 + 0.3 * (-1) ** u
        for k in np.flatnonzero(groups == u):
            if clouds is not None:
                live.add_cloud(int(stamps[k]), clouds[k], T_BASE_CAM)
            live.add_image(int(stamps[k]), images[k], K, T_BASE_CAM)
        sel = (groups == u) | (groups == u - 1) | (groups == 0) if u < 6 \
            else (groups == 0) | (groups == 5)
        live.set_poses(stamps[sel], T[sel] @ off)
        placed.append(live.n_placed)
    return placed


def test_merging_settled_keyframes_keeps_late_corrected_ones_live(data) -> None:
    """A loop closure corrects the first keyframes after many later ones: merged by age they
    are merged while still moving (their last corrections ignored, the mosaic wrong); merged
    when settled they stay live, newer keyframes over them are merged instead, and the live
    mosaic is the one built from scratch from the final poses, with memory bounded."""
    K, stamps, images, T_true = data
    limit = 12

    def mosaic(settle_updates: int) -> LiveMosaic:
        return LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                          ground_from_clouds=False, tile_px=64,
                                          max_live_keyframes=limit,
                                          settle_updates=settle_updates))

    by_age, settled = mosaic(0), mosaic(1)
    assert max(late_loop_closure(by_age, K, stamps, images, T_true)) <= limit
    assert max(late_loop_closure(settled, K, stamps, images, T_true)) <= limit
    first = stamps[:4].tolist()
    # by age: the first keyframes were merged while moving; their loop closure is ignored
    assert set(first) <= set(by_age.merged)
    assert by_age.counts.merged_moves_ignored >= 4
    assert by_age.counts.merged_max_shift_m == pytest.approx(0.7)  # merged at 0.7 m off
    now = by_age.mosaic()
    ref = scratch(images, T_true, K, now.georef)
    both = now.valid & ref.valid
    assert np.mean(np.abs(now.image.astype(int) - ref.image.astype(int))[both] > 8) > 0.01
    # by settledness: the first keyframes stayed live, later ones were merged (settled)
    assert not set(first) & set(settled.merged)
    assert set(settled.merged) == set(stamps[4:16].tolist())
    assert settled.counts.merged_settled == settled.counts.frozen == len(stamps) - limit
    assert settled.counts.merged_forced == 0 and settled.counts.merged_moves_ignored == 0
    now = settled.mosaic()
    ref = scratch(images, T_true, K, now.georef)
    assert_same(now, ref)
    # the stamp order mattered: newer merged keyframes lie under the live first ones, which
    # a static layer pasted under every live keyframe would have got wrong
    newer = scratch(images[4:16], T_true[4:16], K, now.georef).valid
    older = scratch(images[:4], T_true[:4], K, now.georef).valid
    assert np.mean(newer & older) > 0.02


def test_the_bound_holds_when_nothing_settles(data) -> None:
    """Keyframes that never settle are merged all the same beyond the bound (the most settled
    first), counted as forced; the mosaic is still the one of the poses at the merges."""
    K, stamps, images, T_true = data
    limit = 6
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                      ground_from_clouds=False, tile_px=64,
                                      max_live_keyframes=limit, settle_updates=100))
    placed = late_loop_closure(live, K, stamps, images, T_true)
    assert max(placed) <= limit and len(live.keyframes) <= limit
    assert live.counts.merged_forced == live.counts.frozen == len(stamps) - limit
    assert live.counts.merged_settled == 0
    # the most settled went first: group 0 moved at every update, so it was merged last of
    # the groups already corrected
    assert set(stamps[4:8].tolist()) <= set(live.merged)
    T = np.array([live.merged.get(int(s), live.keyframes.get(int(s)) and
                                  live.keyframes[int(s)].T_map_base) for s in stamps])
    now = live.mosaic()
    assert_same(now, scratch(images, T, K, now.georef))


def test_a_small_move_does_not_unsettle_a_keyframe(data) -> None:
    """Moves below settle_px (on the ground, in pixels) leave a keyframe settled; a larger one
    unsettles it for settle_updates updates."""
    K, stamps, images, T_true = data
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                      ground_from_clouds=False, tile_px=64,
                                      settle_updates=2, settle_px=0.25))
    key = int(stamps[0])
    live.add_image(key, images[0], K, T_BASE_CAM)
    T = T_true[:1].copy()
    live.set_poses([key], T)
    assert not live.settled(key)
    live.set_poses([], np.zeros((0, 4, 4)))
    live.set_poses([], np.zeros((0, 4, 4)))
    assert live.settled(key)
    for dx in (0.04, 0.04, 0.04):   # 0.1 px each: 0.2 px, then 0.3 px from where it settled
        T[0, 0, 3] += dx
        warps = live.counts.warps
        live.set_poses([key], T)
        assert live.counts.warps == warps + 1   # applied all the same
    assert not live.settled(key)       # the third one took it beyond 0.25 px
    live.set_poses([], np.zeros((0, 4, 4)))
    assert not live.settled(key)
    live.set_poses([], np.zeros((0, 4, 4)))
    assert live.settled(key)
    # a rotation moves the footprint too: 1 mrad at 90 m above the ground is 0.09 m
    R = se3.from_translation_rotvec(np.zeros(3), np.array([0.0, 0.0, 0.003]))
    live.set_poses([key], T @ R)
    assert not live.settled(key)


@pytest.mark.parametrize('compact_at', [2 ** 16 - 1, 3])
def test_merges_in_any_order_change_no_pixel(data, monkeypatch, compact_at: int) -> None:
    """Newer keyframes merged before older ones that overlap them: the static layer keeps the
    newer pixels on top, so each merge leaves the mosaic as built from scratch (also when the
    static tiles' lists of stamps are compacted at every third merge)."""
    monkeypatch.setattr(mosaic_map, 'STATIC_TILE_STAMPS', compact_at)
    K, stamps, images, T_true = data
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                      ground_from_clouds=False, tile_px=64,
                                      max_live_keyframes=0))
    for s, img in zip(stamps, images):
        live.add_image(int(s), img, K, T_BASE_CAM)
    live.set_poses(stamps, T_true)
    ref = scratch(images, T_true, K, live.mosaic().georef)
    assert_same(live.mosaic(), ref)
    for group in (5, 1, 3, 0, 4):
        assert live.merge(stamps[4 * group:4 * group + 4].tolist()) == 4
        assert_same(live.mosaic(), ref)
    # stamps no pixel shows any more: listed until the tile is compacted
    hidden = [layer.stamps.size - np.unique(layer.owner[layer.valid]).size
              for layer in live.static.values()]
    assert max(hidden) <= 1 if compact_at == 3 else max(hidden) > 1
    # and once recomposited from the static layer (a live keyframe moved and back)
    T = T_true.copy()
    T[8:12, 0, 3] += 2.0
    live.set_poses(stamps, T)
    live.set_poses(stamps, T_true)
    assert_same(live.mosaic(), ref)


def test_merging_settled_keyframes_over_relief(relief) -> None:
    """The same late loop closure orthorectified on the keyframe clouds' height model: the
    first keyframes stay live, and the mosaic is the offline orthomosaic of the final poses
    (within :func:`assert_close`); merged by age it is not."""
    K, stamps, images, T_true, clouds, _ = relief
    results = {}
    for settle in (0, 1):
        live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, tile_px=64,
                                          max_live_keyframes=12, settle_updates=settle))
        assert max(late_loop_closure(live, K, stamps, images, T_true, clouds)) <= 12
        assert len(live.surface.keyframes) <= 12
        now = live.mosaic()
        results[settle] = live, now, offline(images, clouds, T_true, K, now.georef)[0]
    live, now, ref = results[1]
    assert live.counts.merged_forced == 0 and live.counts.merged_moves_ignored == 0
    assert not set(stamps[:4].tolist()) & set(live.merged)
    assert_close(now, ref)
    live, now, ref = results[0]
    assert live.counts.merged_moves_ignored >= 4
    both = now.valid & ref.valid
    assert np.mean(np.abs(now.image.astype(int) - ref.image.astype(int))[both] > 8) > 0.01


def test_a_static_tile_widens_its_owner_indices_and_keeps_every_stamp() -> None:
    """A static tile that shows more stamps than uint8 indices hold widens them; compaction
    drops only the stamps no pixel shows; each pixel keeps the stamp last given it."""
    t = 32
    layer = mosaic_map._StaticTile(np.zeros((t, t), np.uint8), np.zeros((t, t), np.uint8),
                                   np.zeros(0, np.int64))
    want = np.full((t, t), -(2 ** 63), np.int64)
    rng = np.random.default_rng(0)
    for key in range(1000, 1700):
        # each key a random block in the lower rows; every second also a pixel of its own in
        # the upper rows that stays shown
        pasted = np.zeros((t, t), bool)
        r, c = rng.integers(12, t - 4), rng.integers(0, t - 4)
        pasted[r:r + 4, c:c + 4] = True
        if key % 2 == 0:
            own = (key - 1000) // 2
            pasted[own // t, own % t] = True
        layer.take(key, pasted)
        want[pasted] = key
    assert np.array_equal(layer.pixel_stamps(), want)
    assert np.array_equal(layer.valid, want > -(2 ** 63))
    assert layer.owner.dtype == np.uint16   # more than 255 stamps shown
    shown = np.unique(want[want > -(2 ** 63)]).size
    assert shown > 255 and layer.stamps.size < 700
    layer.compact()
    assert layer.stamps.size == shown and np.array_equal(layer.pixel_stamps(), want)


def test_a_new_image_of_a_placed_keyframe_keeps_its_pose(data) -> None:
    """A keyframe's image sent again (a re-published keyframe, a second camera message) after
    its pose came: the keyframe stays placed at that pose, and the mosaic is the one built from
    scratch."""
    K, stamps, images, T_true = data
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, ground_z=GROUND_Z,
                                      ground_from_clouds=False, tile_px=64))
    live.set_poses(stamps, T_true)
    for s, img in zip(stamps, images):
        assert live.add_image(int(s), img, K, T_BASE_CAM)
    assert live.add_image(int(stamps[3]), images[3], K, T_BASE_CAM)   # placed at once again
    mosaic = live.mosaic()
    assert_same(mosaic, scratch(images, T_true, K, mosaic.georef))


def test_merged_keyframes_without_an_image_keep_no_pose_waiting(relief) -> None:
    """Clouds for every keyframe, images for every other one (a decimated mosaic): the height
    model's keyframes without an image are merged with the imaged ones, and the poses that
    later corrections send for them are neither kept waiting (in the mosaic or its height
    model) nor placed again."""
    K, stamps, images, T_true, clouds, _ = relief
    live = LiveMosaic(MosaicMapConfig(metres_per_pixel=MPP, tile_px=64, max_live_keyframes=2,
                                      settle_updates=1))
    for k, s in enumerate(stamps):
        live.add_cloud(int(s), clouds[k], T_BASE_CAM)
        if k % 2 == 0:
            live.add_image(int(s), images[k], K, T_BASE_CAM)
        live.set_poses(stamps[:k + 1], T_true[:k + 1])  # every pose at every update
    live.set_poses(stamps, T_true)
    assert live.counts.frozen >= 2 and live._merged_orphans
    assert set(live.surface.keyframes) | live._merged_orphans | set(live.merged) \
        >= set(stamps.tolist())
    merged = live._merged_orphans | set(live.merged)
    waiting = [k for k in merged if k in live.pending_poses or k in live.surface.pending_poses]
    assert waiting == []
    # a cloud sent again for a merged keyframe without an image is not placed a second time
    orphan = min(live._merged_orphans)
    live.add_cloud(orphan, clouds[list(stamps).index(orphan)], T_BASE_CAM)
    assert orphan not in live.surface.keyframes
