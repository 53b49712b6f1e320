"""The maps of ``ga-ros replay BAG --map``: the keyframe clouds collected during the replay and
the map files written at the end.

While the replay runs, :class:`KeyframeClouds` takes each new keyframe of the stereo front end
(the same :meth:`ga_ros.pipeline.stereo.StereoFrontEnd.keyframe_cloud` as ``vo_node``'s
``ga/keyframe_cloud``), moves its points into the keyframe's ``base_link`` with the camera's
extrinsic, and keeps them decimated as the map node does (:meth:`ga_ros.mapping.cloud_map.
KeyframeCloudMap.decimate`), under the keyframe's stamp. At the end, :func:`write_map_outputs`
builds two maps of the same clouds (:func:`ga_ros.mapping.cloud_map.map_from_poses`):

* ``map_ga.ply`` from GA's final poses (``trajectory_ga.tum``);
* ``map_f2f.ply`` from the frame-to-frame poses anchored as GA (``trajectory_f2f.tum``);

binary little-endian PLY, ``x y z intensity`` float32, in the map frame
(:mod:`ga_ros.mapping.ply`), and puts their figures in ``summary.json``'s ``map``
(:mod:`ga_ros.mapping.figures`: points, covered area, spread of heights per x-y cell in the
map and between the tracks; GA's against F2F's).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ga_ros.errors import GaError
from ga_ros.io.trajectory import Trajectory
from ga_ros.mapping.cloud_map import (
    CloudMapConfig,
    KeyframeCloudMap,
    map_from_poses,
    transform_points,
)
from ga_ros.mapping.figures import group_height_spread, map_figures
from ga_ros.mapping.ply import write_ply
from ga_ros.safe_write import check_destinations

#: The files ``--map`` writes (the photomosaic's are added by its writer).
MAP_FILES = ('map_ga.ply', 'map_f2f.ply')


@dataclass(frozen=True)
class MapOutputConfig:
    """Settings of the replay's maps.

    Attributes
    ----------
    cloud : the map's voxels and the per-keyframe decimation (as ``map_node``'s parameters).
    cell_m : edge of the x-y cells of the figures (covered area, spread of heights), m.
    keep_images : keep each keyframe's rectified left image too (for the photomosaic).
    """

    cloud: CloudMapConfig = CloudMapConfig()
    cell_m: float = 2.0
    keep_images: bool = False


@dataclass
class KeyframeClouds:
    """The clouds (and images) of the keyframes, collected while the replay runs.

    Attributes
    ----------
    front : the stereo front end of the replay (its calibration and extrinsic).
    config : the settings.
    clouds : keyframe stamp (ns) -> ``(points, intensity)`` in the keyframe's ``base_link``,
        decimated.
    images : keyframe stamp (ns) -> rectified left image (uint8), with ``keep_images``.
    errors : keyframes whose cloud failed, with why (the first ten).
    """

    front: Any
    config: MapOutputConfig = MapOutputConfig()
    clouds: dict[int, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    images: dict[int, np.ndarray] = field(default_factory=dict)
    errors: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._map = KeyframeCloudMap(self.config.cloud)   # its decimation only

    def __call__(self, frame: Any) -> None:
        """Take a processed pair that made a keyframe (the front end's ``FrameOutput``)."""
        res = frame.result
        if res is None or res.keyframe is None:
            return
        try:
            cloud = self.front.keyframe_cloud(frame)
        except GaError as exc:
            if len(self.errors) < 10:
                self.errors.append(f'keyframe {res.keyframe.stamp_ns}: {exc}')
            return
        if cloud is None:
            return
        P = cloud.points
        ext = self.front.extrinsic
        if ext is not None and not ext.is_identity:
            P = transform_points(ext.T_base_cam, P)
        stamp = int(res.keyframe.stamp_ns)
        self.clouds[stamp] = self._map.decimate(P, cloud.intensity)
        if self.config.keep_images and self.front.calibration is not None:
            self.images[stamp] = self.front.calibration.rectify(frame.left, frame.right)[0]


def attach(run: Any, config: MapOutputConfig) -> KeyframeClouds | None:
    """A :class:`KeyframeClouds` fed by the replay's stereo source (None when the source is
    not a stereo bag: the result says why), after the destinations were checked."""
    check_destinations(*(run.out.dir / name for name in MAP_FILES))
    source = run.source
    front = getattr(source, 'front', None)
    if front is None or not hasattr(source, 'on_keyframe'):
        run.result.warnings.append('--map needs a stereo bag (the keyframe clouds come from '
                                   'its images): no map written')
        return None
    collector = KeyframeClouds(front, config)
    source.on_keyframe = collector
    return collector


def _placed_points(clouds: dict, traj: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """(n, 3) every kept keyframe point at its pose in ``traj`` (m, map) and (n,) the track
    of its keyframe."""
    P, tracks = [np.zeros((0, 3))], [np.zeros(0, np.int64)]
    for stamp, T, track in zip(traj.stamps_ns.tolist(), traj.T_world_node, traj.track_ids):
        c = clouds.get(int(stamp))
        if c is not None:
            P.append(transform_points(T, c[0]))
            tracks.append(np.full(len(c[0]), int(track), np.int64))
    return np.concatenate(P), np.concatenate(tracks)


def _build(config: MapOutputConfig, clouds: dict, traj: Trajectory) -> Any:
    """The map of the clouds at the poses of ``traj`` (already decimated: no second pass)."""
    cfg = replace(config.cloud, keyframe_voxel_m=0.0, max_points_per_keyframe=0,
                  max_live_keyframes=0, max_range_m=0.0)
    return map_from_poses(cfg, traj.stamps_ns, traj.T_world_node, clouds).cloud()


def write_map_outputs(run: Any, collector: KeyframeClouds, ga: Trajectory,
                      f2f: Trajectory) -> dict[str, Any]:
    """Write ``map_ga.ply`` and ``map_f2f.ply`` (module docstring) and return the summary's
    ``map`` block: per map its figures and file, the keyframes with a cloud and how many of
    them the path placed, and the GA / F2F ratio of the median spread of heights."""
    cfg = collector.config
    out: dict[str, Any] = {'keyframes_with_cloud': len(collector.clouds),
                           'voxel_m': cfg.cloud.voxel_m,
                           'keyframe_voxel_m': cfg.cloud.keyframe_voxel_m}
    if collector.errors:
        out['cloud_errors'] = collector.errors
    frame = ga.frame_id or 'map'
    for name, traj in (('ga', ga), ('f2f', f2f)):
        cloud = _build(cfg, collector.clouds, traj)
        path = write_ply(run.out.dir / f'map_{name}.ply', cloud.points, cloud.intensity,
                         comments=(f'ga_ros map ({name} poses), frame {frame}',))
        run.out.files[f'map_{name}'] = path
        figures = map_figures(cloud.points, cfg.cell_m).as_dict()
        placed, tracks = _placed_points(collector.clouds, traj)
        figures['track_height_spread_m'] = group_height_spread(placed, tracks,
                                                               cfg.cell_m).as_dict()
        figures['keyframes_placed'] = int(np.isin(traj.stamps_ns,
                                                  list(collector.clouds)).sum())
        out[name] = {**figures, 'file': str(path)}
    for key in ('height_spread_m', 'track_height_spread_m'):
        ga_s, f2f_s = out['ga'][key]['median'], out['f2f'][key]['median']
        out[f'{key[:-2]}_ga_over_f2f'] = (ga_s / f2f_s if f2f_s and np.isfinite(f2f_s)
                                          else float('nan'))
    mosaic = mosaic_outputs(run, collector, ga, f2f)
    if mosaic:
        out['mosaic'] = mosaic
    return out


def mosaic_outputs(run: Any, collector: KeyframeClouds, ga: Trajectory,
                   f2f: Trajectory) -> dict[str, Any]:
    """The photomosaic's files and figures (``mosaic_ga.png``, ``mosaic_f2f.png``, seams): the
    call site of the mosaic writer, given the keyframes' rectified images
    (``collector.images``, with ``keep_images``), the same poses as the clouds and the
    front end's calibration. Returns ``{}`` while no writer is connected."""
    return {}
