"""The sample bags in ``bags/``: deterministic generators (seeded simulators, fixed stamps).

Two bags, each with ground truth on ``/ga/ground_truth`` (``nav_msgs/Path``, written once at the
end; see :mod:`ga_ros.io.topic_plan`):

* ``aerial_measurements`` -- the measurement encoding (``/ga/measurements``) of the paper's
  full aerial scenario (Sec. IV; :func:`ga_ros.sim.aerial.aerial_scenario`: 25 double tracks x
  204 positions, ~30,000 connections; 2.4 MB with zstd-compressed mcap chunks), Gaussian noise of
  :mod:`ga_ros.sim.noise` at 5 %. Ground-truth poses carry their node frame
  ``'ga/<track>/<node>'``.
* ``stereo_sample`` -- JPEG-compressed 320x240 stereo pairs of the stereo simulator
  (:mod:`ga_ros.sim.stereo`) flying a small lawnmower (3 tracks = 6 swaths of 20 frames 6 m
  apart, 16-frame turns: 200 pairs), with ``CameraInfo`` per image. Ground
  truth is the left camera pose per frame (frame id ``map``; the replay matches it to VO
  keyframes by stamp).

All stamps start at :data:`BASE_STAMP_NS` so the bags look like real recordings.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros import topics
from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError
from ga_ros.io.bag_messages import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    ODOMETRY,
    PATH,
    header,
    measurement_to_odometry,
    trajectory_to_path_msg,
    typestore,
)
from ga_ros.io.bag_writer import BagWriter, tf_message, transform_msg
from ga_ros.io.trajectory import Trajectory

#: Stamp of the first frame of the sample bags (2023-11-14T22:13:20Z), ns.
BASE_STAMP_NS = 1_700_000_000 * 1_000_000_000

#: Topic names of the sample bags.
MEASUREMENTS_TOPIC = topics.resolve(topics.MEASUREMENTS)
GROUND_TRUTH_TOPIC = topics.resolve(topics.GROUND_TRUTH)
LEFT_IMAGE_TOPIC = '/stereo/left/image_raw/compressed'
RIGHT_IMAGE_TOPIC = '/stereo/right/image_raw/compressed'
LEFT_INFO_TOPIC = '/stereo/left/camera_info'
RIGHT_INFO_TOPIC = '/stereo/right/camera_info'

MEASUREMENTS_BAG = 'aerial_measurements'
STEREO_BAG = 'stereo_sample'


def write_measurement_bag(path: str | Path, measurements: list[Measurement],
                          ground_truth: Trajectory | None, storage: str = 'mcap',
                          overwrite: bool = False) -> Path:
    """Write measurements (bag time = their stamp) and, at the end, the ground-truth path.

    Parameters
    ----------
    path : output bag directory.
    measurements : in acquisition order.
    ground_truth : poses with node and track ids (written with node frame ids), or None.
    storage : ``'mcap'`` or ``'sqlite3'``.
    """
    with BagWriter(path, overwrite=overwrite, storage=storage) as bag:
        last = 0
        for m in measurements:
            bag.write(MEASUREMENTS_TOPIC, ODOMETRY, measurement_to_odometry(m), m.stamp_ns)
            last = max(last, int(m.stamp_ns))
        if ground_truth is not None:
            node_frames = bool((ground_truth.node_ids >= 0).all())
            bag.write(GROUND_TRUTH_TOPIC, PATH,
                      trajectory_to_path_msg(ground_truth, stamp_ns=last,
                                             node_frames=node_frames), last)
    return Path(path)


@dataclass(frozen=True)
class MeasurementSample:
    """An aerial measurement survey: measurements in acquisition order and ground truth."""

    measurements: list[Measurement]
    ground_truth: Trajectory


def aerial_sample(n_tracks: int = 6, positions_per_swath: int = 102, noise_pct: float = 5.0,
                  seed: int = 7) -> MeasurementSample:
    """The reduced aerial scenario with noisy measurements (deterministic for a seed).

    Parameters
    ----------
    n_tracks : double tracks (paper: 25; sample bag: 6).
    positions_per_swath : nodes per swath (paper: 102).
    noise_pct : noise level of :class:`ga_ros.sim.noise.NoiseModel` (percent of the motion).
    seed : seed of the noise.
    """
    from ga_ros.sim.aerial import aerial_scenario
    from ga_ros.sim.noise import NoiseModel, perturb

    sc = aerial_scenario(n_tracks=n_tracks, positions_per_swath=positions_per_swath)
    noisy = perturb(sc.true_motions('se3'), NoiseModel(noise_pct, sc.depth_m),
                    np.random.default_rng(seed))
    ms = [Measurement(m.src_id, m.dst_id, m.src_track, m.dst_track, m.z, m.cov,
                      m.stamp_ns + BASE_STAMP_NS, m.kind)
          for m in sc.measurements(noisy.z, noisy.cov)]
    gt = Trajectory(sc.stamps_ns + BASE_STAMP_NS, sc.T_world_node.copy(),
                    sc.node_ids.copy(), np.asarray(sc.track_ids, dtype=np.int64), 'map')
    return MeasurementSample(ms, gt)


def make_measurements_bag(path: str | Path, n_tracks: int = 6, noise_pct: float = 5.0,
                          seed: int = 7, storage: str = 'mcap',
                          overwrite: bool = False) -> Path:
    """Write the aerial measurements sample bag (see :func:`aerial_sample`)."""
    s = aerial_sample(n_tracks=n_tracks, noise_pct=noise_pct, seed=seed)
    return write_measurement_bag(path, s.measurements, s.ground_truth, storage, overwrite)


# --------------------------------------------------------------------------- stereo
def camera_info_msg(K: FloatArray, width: int, height: int, frame_id: str, stamp_ns: int,
                    Tx: float = 0.0) -> Any:
    """Rectified ``sensor_msgs/CameraInfo`` (rosbags): no distortion, ``R = I``,
    ``P = [K | (Tx, 0, 0)]`` with ``Tx = -f * baseline`` for the right camera."""
    types = typestore().types
    P = np.zeros((3, 4))
    P[:, :3] = K
    P[0, 3] = Tx
    return types[CAMERA_INFO](
        header=header(frame_id, stamp_ns), height=int(height), width=int(width),
        distortion_model='plumb_bob', d=np.zeros(5), k=np.asarray(K, float).reshape(9).copy(),
        r=np.eye(3).reshape(9), p=P.reshape(12),
        binning_x=0, binning_y=0,
        roi=types['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0,
                                                      do_rectify=False))


def compressed_image_msg(image: np.ndarray, frame_id: str, stamp_ns: int,
                         quality: int = 80) -> Any:
    """JPEG ``sensor_msgs/CompressedImage`` (rosbags) of a ``uint8`` mono image."""
    import cv2

    ok, buf = cv2.imencode('.jpg', image, [cv2.IMWRITE_JPEG_QUALITY, int(quality)])
    if not ok:
        raise InputError('JPEG encoding failed')
    return typestore().types[COMPRESSED_IMAGE](header=header(frame_id, stamp_ns), format='jpeg',
                                               data=np.asarray(buf, dtype=np.uint8).reshape(-1))


@dataclass(frozen=True)
class StereoSampleConfig:
    """The stereo sample survey.

    Attributes
    ----------
    n_tracks : double swaths.
    positions_per_swath : frames per swath.
    step_m : travel between frames (m).
    turn_positions : frames in each turn.
    width, height : image size (px).
    jpeg_quality : JPEG quality (0-100).
    seed : seed of the terrain, the flight wobble and the image noise.
    """

    n_tracks: int = 3
    positions_per_swath: int = 20
    step_m: float = 6.0
    turn_positions: int = 16
    width: int = 320
    height: int = 240
    jpeg_quality: int = 60
    seed: int = 3


def make_stereo_bag(path: str | Path, config: StereoSampleConfig = StereoSampleConfig(),
                    storage: str = 'mcap', overwrite: bool = False) -> Path:
    """Render the stereo sample survey into a bag (compressed images, CameraInfo, ground truth,
    and on ``/tf_static`` the camera's extrinsic: ``base_link -> stereo_left`` the identity, the
    survey's vehicle frame being its left camera's).

    Returns the bag path. Deterministic for a config (seeded terrain, flight and image noise).
    """
    from ga_ros.sim.stereo import LawnmowerConfig, StereoRig, lawnmower, make_scene

    c = config
    survey = lawnmower(LawnmowerConfig(n_tracks=c.n_tracks,
                                       positions_per_swath=c.positions_per_swath,
                                       step_m=c.step_m, turn_positions=c.turn_positions,
                                       seed=c.seed))
    rig = StereoRig.for_size(c.width, c.height)
    scene = make_scene(survey, rig, seed=c.seed)
    rng = np.random.default_rng(c.seed)
    stamps = survey.stamps_ns + BASE_STAMP_NS
    K = rig.K
    with BagWriter(path, overwrite=overwrite, storage=storage) as bag:
        bag.write('/tf_static', 'tf2_msgs/msg/TFMessage', tf_message([transform_msg(
            'base_link', 'stereo_left', np.eye(4), int(stamps[0]))]), int(stamps[0]))
        for T, s in zip(survey.T_world_cam, stamps):
            left, right = scene.render_pair(T, rng)
            s = int(s)
            bag.write(LEFT_INFO_TOPIC, CAMERA_INFO,
                      camera_info_msg(K, rig.width, rig.height, 'stereo_left', s), s)
            bag.write(RIGHT_INFO_TOPIC, CAMERA_INFO,
                      camera_info_msg(K, rig.width, rig.height, 'stereo_right', s,
                                      -rig.focal_px * rig.baseline_m), s)
            bag.write(LEFT_IMAGE_TOPIC, COMPRESSED_IMAGE,
                      compressed_image_msg(left, 'stereo_left', s, c.jpeg_quality), s)
            bag.write(RIGHT_IMAGE_TOPIC, COMPRESSED_IMAGE,
                      compressed_image_msg(right, 'stereo_right', s, c.jpeg_quality), s)
        n = len(stamps)
        gt = Trajectory(stamps.astype(np.int64), survey.T_world_cam.copy(),
                        np.full(n, -1, dtype=np.int64),
                        np.asarray(survey.track, dtype=np.int64), 'map')
        bag.write(GROUND_TRUTH_TOPIC, PATH, trajectory_to_path_msg(gt, stamp_ns=int(stamps[-1])),
                  int(stamps[-1]))
    return Path(path)



def make_sample_bags(out_dir: str | Path, which: tuple[str, ...] = ('measurements', 'stereo'),
                     overwrite: bool = True) -> dict[str, Path]:
    """Regenerate the sample bags into ``out_dir`` (``bags/`` in the repository).

    Parameters
    ----------
    which : ``'measurements'`` (:data:`MEASUREMENTS_BAG`) and/or ``'stereo'``
        (:data:`STEREO_BAG`).
    overwrite : replace existing bags of the same name.
    """
    out = Path(out_dir)
    made: dict[str, Path] = {}
    for kind in which:
        if kind == 'measurements':
            made[kind] = make_measurements_bag(out / MEASUREMENTS_BAG, n_tracks=25,
                                               overwrite=overwrite)
        elif kind == 'stereo':
            made[kind] = make_stereo_bag(out / STEREO_BAG, overwrite=overwrite)
        else:
            raise InputError(f"sample bag must be 'measurements' or 'stereo', got {kind!r}")
    return made
