"""Dense stereo keyframe clouds (ga_ros.vo.dense, StereoFrontEnd.keyframe_cloud): the points of
simulated pairs lie on the simulator's terrain, decimation and range limits, bad input, and the
front end's VO outputs unchanged by computing clouds."""

from __future__ import annotations

import numpy as np
import pytest

from ga_ros.errors import InputError
from ga_ros.pipeline.stereo import FrontEndConfig, StereoFrontEnd, front_end_config_from_params
from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene
from ga_ros.vo.calibration import CameraModel, StereoCalibration
from ga_ros.vo.dense import DenseStereo, DenseStereoConfig


@pytest.fixture(scope='module')
def rendered():
    """A simulated rectified pair (noisy), the true z-depth of every left pixel, the rig."""
    rig = StereoRig()
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=4, seed=3))
    scene = make_scene(survey, rig, seed=3)
    rng = np.random.default_rng(3)
    T = survey.T_world_cam[1]
    left, depth = scene.render(T, rng, with_depth=True)
    right = scene.render(T @ rig.T_left_right, rng)
    return left, right, depth, rig


def _pixels(points: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Integer pixels of optical-frame points under the pinhole ``K`` (independent of the
    triangulation's formula: a forward projection)."""
    u = K[0, 0] * points[:, 0] / points[:, 2] + K[0, 2]
    v = K[1, 1] * points[:, 1] / points[:, 2] + K[1, 2]
    return np.rint(u).astype(int), np.rint(v).astype(int)


def test_points_lie_on_the_simulated_terrain(rendered):
    left, right, depth, rig = rendered
    cal = StereoCalibration.rectified(rig.width, rig.height, rig.K, rig.baseline_m)
    cloud = DenseStereo(DenseStereoConfig(pixel_stride=1)).cloud(left, right, cal)
    assert cloud.points.dtype == np.float32 and cloud.intensity.dtype == np.float32
    assert cloud.points.shape == (len(cloud), 3) and cloud.intensity.shape == (len(cloud),)
    # most pixels right of the search range get a point
    searchable = rig.height * (rig.width - 64)
    assert len(cloud) > 0.8 * searchable
    u, v = _pixels(cloud.points.astype(float), rig.K)
    assert u.min() >= 0 and v.min() >= 0 and u.max() < rig.width and v.max() < rig.height
    true_z = depth[v, u]
    rel = np.abs(cloud.points[:, 2] - true_z) / true_z
    assert np.median(rel) < 0.02, np.median(rel)
    assert np.percentile(rel, 90) < 0.05
    # optical frame: z forward (the terrain below a nadir camera at ~50-100 m)
    assert np.all(cloud.points[:, 2] > 0.5 * depth.min())
    # x right, y down: pixels right of / below the principal point have x > 0 / y > 0
    np.testing.assert_array_equal(cloud.points[:, 0] > 0, u > rig.K[0, 2])
    np.testing.assert_array_equal(np.sign(cloud.points[:, 1]),
                                  np.sign(v - rig.K[1, 2]))
    # intensity: the grey level of the left pixel
    np.testing.assert_array_equal(cloud.intensity, left[v, u].astype(np.float32))


def test_stride_and_range_decimate(rendered):
    left, right, depth, rig = rendered
    cal = StereoCalibration.rectified(rig.width, rig.height, rig.K, rig.baseline_m)
    full = DenseStereo(DenseStereoConfig(pixel_stride=1)).cloud(left, right, cal)
    third = DenseStereo(DenseStereoConfig(pixel_stride=3)).cloud(left, right, cal)
    u, v = _pixels(third.points.astype(float), rig.K)
    assert np.all(u % 3 == 0) and np.all(v % 3 == 0)
    assert 0.08 * len(full) < len(third) < 0.14 * len(full)
    # the strided points are the full cloud's points at those pixels (one disparity map)
    uf, vf = _pixels(full.points.astype(float), rig.K)
    on_grid = (uf % 3 == 0) & (vf % 3 == 0)
    np.testing.assert_array_equal(third.points, full.points[on_grid])
    np.testing.assert_array_equal(third.intensity, full.intensity[on_grid])
    fb = rig.focal_px * rig.baseline_m
    max_range = float(np.median(depth))
    for cfg in (DenseStereoConfig(pixel_stride=1, max_range_m=max_range),
                DenseStereoConfig(pixel_stride=1, min_disparity_px=fb / max_range)):
        near = DenseStereo(cfg).cloud(left, right, cal)
        assert np.all(near.points[:, 2] <= max_range * (1 + 1e-6))
        assert 0.3 * len(full) < len(near) < 0.7 * len(full)


def test_bad_input_and_settings(rendered):
    left, right, _, rig = rendered
    cal = StereoCalibration.rectified(rig.width, rig.height, rig.K, rig.baseline_m)
    dense = DenseStereo()
    with pytest.raises(InputError):
        dense.cloud(left[:, :100], right[:, :100], cal)
    with pytest.raises(InputError):
        dense.disparity(left, right.astype(np.float32))
    with pytest.raises(InputError):
        dense.disparity(np.dstack([left] * 3), np.dstack([right] * 3))
    for bad in ({'num_disparities': 40}, {'block_size': 4}, {'mode': 'fast'},
                {'pixel_stride': 0}, {'min_disparity_px': 0.0}, {'max_range_m': -1.0}):
        with pytest.raises(InputError):
            DenseStereoConfig(**bad)
    # a textureless pair gives no point (and no error)
    flat = np.full_like(left, 128)
    assert len(dense.cloud(flat, flat, cal)) < 0.01 * left.size


def test_cloud_parameters_of_the_front_end():
    c = front_end_config_from_params({'cloud_pixel_stride': 4, 'cloud_max_range_m': 150,
                                      'cloud_mode': '3way'})
    assert c.cloud == DenseStereoConfig(pixel_stride=4, max_range_m=150.0, mode='3way')
    with pytest.raises(InputError, match='multiple of 16'):
        front_end_config_from_params({'cloud_num_disparities': 10})


def _drive(front: StereoFrontEnd, pairs, clouds: bool):
    out = []
    for stamp, left, right in pairs:
        frame = front.process_pair(_pair(stamp, left, right))
        cloud = front.keyframe_cloud(frame) if clouds else None
        out.append((frame, cloud))
    return out


class _Msg:
    """A minimal ``sensor_msgs/Image`` (mono8) read by field name."""

    def __init__(self, img: np.ndarray, stamp_ns: int) -> None:
        self.height, self.width = img.shape
        self.encoding, self.step, self.is_bigendian = 'mono8', img.shape[1], 0
        self.data = img.tobytes()
        self.header = type('H', (), {'stamp': type('S', (), {
            'sec': stamp_ns // 10**9, 'nanosec': stamp_ns % 10**9})(), 'frame_id': 'l'})()


def _pair(stamp: int, left: np.ndarray, right: np.ndarray):
    from ga_ros.pipeline.stereo import ImagePair
    return ImagePair(_Msg(left, stamp), _Msg(right, stamp), stamp)


def test_front_end_clouds_at_keyframes_and_vo_unchanged():
    rig = StereoRig()
    survey = lawnmower(LawnmowerConfig(n_tracks=1, positions_per_swath=8, seed=5))
    scene = make_scene(survey, rig, seed=5)
    rng = np.random.default_rng(5)
    pairs = [(int(survey.stamps_ns[i]), *scene.render_pair(survey.T_world_cam[i], rng))
             for i in range(8)]
    P_right = np.hstack([rig.K, [[-rig.focal_px * rig.baseline_m], [0.0], [0.0]]])
    models = (CameraModel(rig.width, rig.height, rig.K, P=np.hstack([rig.K, np.zeros((3, 1))])),
              CameraModel(rig.width, rig.height, rig.K, P=P_right))
    runs = []
    for clouds in (False, True):
        front = StereoFrontEnd(FrontEndConfig(cross_track=False))
        front.set_camera_models(*models)
        runs.append(_drive(front, pairs, clouds))
    n_kf = 0
    for (f0, _), (f1, cloud) in zip(*runs, strict=True):
        assert f0.reason == f1.reason and f0.result.status == f1.result.status
        np.testing.assert_array_equal(f0.result.T_world_cam, f1.result.T_world_cam)
        if f0.measurement is not None:
            np.testing.assert_array_equal(f0.measurement.z, f1.measurement.z)
            np.testing.assert_array_equal(f0.measurement.cov, f1.measurement.cov)
        assert (cloud is not None) == (f1.result.keyframe is not None)
        if cloud is not None:
            n_kf += 1
            assert len(cloud) > 0.1 * rig.width * rig.height / 4  # stride 2 by default
            assert np.all(np.isfinite(cloud.points)) and np.all(cloud.points[:, 2] > 0)
    assert n_kf >= 2
