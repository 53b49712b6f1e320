"""The photomosaic: geometry against the simulator's orthophoto, the seam metric against known
shifts, the georeference and the message fields (:mod:`ga_ros.mapping`)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.geometry import se3
from ga_ros.mapping.mosaic import (
    CameraView,
    Georeference,
    MosaicConfig,
    build_mosaic,
    image_fields,
    map_metadata_fields,
    plan_georeference,
    save_mosaic,
)
from ga_ros.mapping.seams import image_offset, seam_misregistration
from ga_ros.mapping.surface import GroundPlane, SurfaceConfig, ground_from_keyframe_points

sim = pytest.importorskip('ga_ros.sim.stereo')


def flat_scene(seed: int = 1) -> sim.StereoScene:
    """A flat textured ground at z = 20 m seen by the default 320x240 rig."""
    cfg = sim.TerrainConfig(-80.0, 160.0, -80.0, 180.0, texture_resolution_m=0.15,
                            min_height_m=20.0, max_height_m=20.0, seed=seed)
    return sim.StereoScene(sim.Terrain(cfg), sim.StereoRig(), noise_std=0.0)


def nadir(x: float, y: float, z: float = 110.0, heading: float = np.pi / 2) -> np.ndarray:
    return se3.from_rt(sim.nadir_rotation(heading), np.array([x, y, z]))


def registration_px(mosaic_img: np.ndarray, valid: np.ndarray, truth: np.ndarray,
                    tile: int = 64) -> np.ndarray:
    """Offset length (px) of every fully covered ``tile`` x ``tile`` block of the mosaic
    against the same block of the truth raster."""
    out = []
    for r in range(0, valid.shape[0] - tile + 1, tile):
        for c in range(0, valid.shape[1] - tile + 1, tile):
            if valid[r:r + tile, c:c + tile].all():
                dx, dy = image_offset(truth[r:r + tile, c:c + tile],
                                      mosaic_img[r:r + tile, c:c + tile])
                out.append(np.hypot(dx, dy))
    return np.asarray(out)


def truth_raster(scene: sim.StereoScene, georef: Georeference) -> np.ndarray:
    """The simulator's orthophoto on the mosaic grid (pixel centres, filtered to the pixel)."""
    x, y = georef.pixel_centres(0, 0, georef.height, georef.width)
    return scene.terrain.texture_at(x, y, np.full(x.shape, georef.metres_per_pixel,
                                                  np.float32))


def test_image_offset_finds_a_known_subpixel_shift() -> None:
    scene = flat_scene()
    x, y = np.meshgrid(np.arange(160) * 0.3, np.arange(128) * 0.3)
    a = scene.terrain.texture_at(x.astype(np.float32), y.astype(np.float32))
    for dx, dy in ((1.3, -0.7), (-4.25, 2.5), (0.0, 0.0)):
        # b(x, y) = a(x - dx, y - dy): the texture sampled dx, dy pixels back
        b = scene.terrain.texture_at((x - 0.3 * dx).astype(np.float32),
                                     (y - 0.3 * dy).astype(np.float32))
        got = image_offset(a, b)
        assert got == pytest.approx((dx, dy), abs=0.05)


def test_flat_ground_mosaic_is_the_orthophoto_and_the_seams_see_a_known_pose_shift() -> None:
    scene = flat_scene()
    K = scene.rig.K
    poses = [nadir(0.0, y) for y in (0.0, 12.0, 24.0)] + \
            [nadir(20.0, y, heading=-np.pi / 2) for y in (24.0, 12.0, 0.0)]
    views = [CameraView(scene.render(T), T, K) for T in poses]
    tracks = np.array([0, 0, 0, 1, 1, 1])
    plane = GroundPlane(20.0)
    cfg = MosaicConfig(metres_per_pixel=0.4)
    mosaic = build_mosaic(views, plane, cfg)
    reg = registration_px(mosaic.image.astype(np.float32), mosaic.valid,
                          truth_raster(scene, mosaic.georef))
    assert reg.size >= 20
    assert np.median(reg) < 0.1
    exact = seam_misregistration(views, tracks, plane, mosaic.georef)
    assert exact.measured >= 3 and exact.max_px < 0.1
    # track 1 placed 1.0 m east and 0.6 m north of where it was: its image lands 2.5 px right
    # and 1.5 px up on the 0.4 m grid (a horizontal shift of a camera over a plane moves its
    # projection rigidly)
    moved = [v if t == 0 else CameraView(v.image, se3.from_rt(
        v.T_map_cam[:3, :3], v.T_map_cam[:3, 3] + [1.0, 0.6, 0.0]), K)
        for v, t in zip(views, tracks)]
    shifted = seam_misregistration(moved, tracks, plane, mosaic.georef)
    assert shifted.measured == exact.measured
    for o in shifted.offsets:
        assert (o.dx_px, o.dy_px) == pytest.approx((2.5, -1.5), abs=0.1)
    assert shifted.median_px == pytest.approx(np.hypot(2.5, 1.5), abs=0.1)


def test_relief_needs_the_height_grid() -> None:
    """Over relief a plane misregisters neighbouring tracks by the parallax; the height grid of
    the (here: true) ground points removes it."""
    survey = sim.lawnmower(sim.LawnmowerConfig(n_tracks=1, positions_per_swath=6, step_m=12.0,
                                               turn_positions=0, seed=2))
    scene = sim.make_scene(survey, seed=2, noise_std=0.0)
    views = [CameraView(scene.render(T), T, scene.rig.K) for T in survey.T_world_cam]
    # the true ground points of each view, in its camera frame (as a keyframe cloud)
    pts_cam = [(scene.ground_points(T, 8) - T[:3, 3]) @ T[:3, :3] for T in survey.T_world_cam]
    grid = ground_from_keyframe_points(pts_cam, survey.T_world_cam, SurfaceConfig(cell_m=2.0))
    pts = np.concatenate([scene.ground_points(T, 8) for T in survey.T_world_cam])
    err = np.abs(grid.heights(pts[:, :1], pts[:, 1:2]).ravel() - pts[:, 2])
    print(f'height grid error: median {np.median(err):.3f} m, p95 {np.percentile(err, 95):.3f} m')
    assert np.median(err) < 0.2 and np.percentile(err, 95) < 1.0  # 2 m cells, smoothed
    lo, hi = grid.z_range
    georef = plan_georeference(views, grid, MosaicConfig(metres_per_pixel=0.4))
    on_grid = seam_misregistration(views, survey.swath, grid, georef)
    on_plane = seam_misregistration(views, survey.swath, GroundPlane(0.5 * (lo + hi)), georef)
    assert on_grid.measured >= 3 and on_plane.measured == on_grid.measured
    assert hi - lo > 5.0  # there is relief
    assert on_grid.median_px < 0.3
    assert on_plane.median_px > 3 * on_grid.median_px + 1.0


def test_mosaic_too_large_is_refused_with_the_resolution_that_fits() -> None:
    scene = flat_scene()
    T = nadir(0.0, 0.0)
    view = CameraView(scene.render(T), T, scene.rig.K)
    with pytest.raises(InputError, match='metres_per_pixel >='):
        plan_georeference([view], GroundPlane(20.0),
                          MosaicConfig(metres_per_pixel=0.01, max_pixels=1_000_000))
    with pytest.raises(InputError, match='blend'):
        MosaicConfig(blend='median')


def test_saved_georeference_and_message_fields(tmp_path) -> None:
    scene = flat_scene()
    poses = [nadir(0.0, 0.0), nadir(0.0, 15.0)]
    views = [CameraView(scene.render(T), T, scene.rig.K) for T in poses]
    for blend in ('last', 'average'):
        mosaic = build_mosaic(views, GroundPlane(20.0), MosaicConfig(0.5, blend=blend))
        assert mosaic.valid.mean() > 0.5
    g = mosaic.georef
    files = save_mosaic(tmp_path / 'mosaic.png', mosaic)
    png = cv2.imread(files['png'], cv2.IMREAD_UNCHANGED)
    assert png.shape == (g.height, g.width, 4)
    assert np.array_equal(png[..., 0], mosaic.image)
    assert np.array_equal(png[..., 3] > 0, mosaic.valid)
    meta = json.loads((tmp_path / 'mosaic.json').read_text())
    assert meta['metres_per_pixel'] == g.metres_per_pixel and meta['x_min'] == g.x_min
    world = [float(v) for v in (tmp_path / 'mosaic.pgw').read_text().split()]
    # ESRI world file: x = A * col + B * row + C, y = D * col + E * row + F (pixel centres)
    col, row = 17, 9
    x = world[0] * col + world[2] * row + world[4]
    y = world[1] * col + world[3] * row + world[5]
    px, py = g.pixel_centres(row, col, 1, 1)
    assert (x, y) == pytest.approx((float(px[0, 0]), float(py[0, 0])), abs=1e-4)

    # sensor_msgs/Image and nav_msgs/MapMetaData as ROS tools read them (CDR round trip)
    from ga_ros.io.bag_messages import header, typestore
    from ga_ros.vo.messages import image_to_grey

    ts = typestore()
    f = image_fields(mosaic)
    msg = ts.types['sensor_msgs/msg/Image'](header=header('map', 5), **f)
    back = ts.deserialize_cdr(ts.serialize_cdr(msg, 'sensor_msgs/msg/Image'),
                              'sensor_msgs/msg/Image')
    assert back.encoding == 'mono8' and back.step == back.width == g.width
    assert len(back.data) == back.step * back.height
    assert np.array_equal(image_to_grey(back), mosaic.image)
    colour = build_mosaic([CameraView(cv2.cvtColor(v.image, cv2.COLOR_GRAY2BGR), v.T_map_cam,
                                      v.K) for v in views], GroundPlane(20.0),
                          MosaicConfig(0.5))
    fc = image_fields(colour)
    assert fc['encoding'] == 'rgb8' and fc['step'] == 3 * g.width
    m = map_metadata_fields(g)
    Pose = ts.types['geometry_msgs/msg/Pose']
    origin = Pose(position=ts.types['geometry_msgs/msg/Point'](*m['origin']['position']),
                  orientation=ts.types['geometry_msgs/msg/Quaternion'](
                      *m['origin']['orientation']))
    info = ts.types['nav_msgs/msg/MapMetaData'](
        map_load_time=ts.types['builtin_interfaces/msg/Time'](sec=0, nanosec=5),
        resolution=m['resolution'], width=m['width'], height=m['height'], origin=origin)
    # OccupancyGrid convention: cell (i, j) centre = origin + ((j + 0.5), (i + 0.5)) * res,
    # grid row i = image row height - 1 - i
    i, j = 3, 11
    cx = info.origin.position.x + (j + 0.5) * info.resolution
    cy = info.origin.position.y + (i + 0.5) * info.resolution
    px, py = g.pixel_centres(g.height - 1 - i, j, 1, 1)
    assert (cx, cy) == pytest.approx((float(px[0, 0]), float(py[0, 0])), abs=1e-4)
