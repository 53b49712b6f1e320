"""The maps of ``ga-ros replay BAG --map``: the map that follows the corrections during the
replay, and the map files written at the end.

The replay drives the same :class:`ga_ros.pipeline.cloud_map.CloudMapBuilder` as ``map_node``:
:class:`ReplayMap` takes each new keyframe's dense stereo cloud (the same
:meth:`ga_ros.pipeline.stereo.StereoFrontEnd.keyframe_cloud` as ``vo_node``'s
``ga/keyframe_cloud``, in the camera's frame, with the extrinsic the front end resolved) and
every corrections message the replay writes (``ga/corrections``), as the node would receive
them. At the end, :func:`write_map_outputs` re-anchors the keyframes to GA's final poses (only
those that differ from what the corrections left cost anything) and writes:

* ``map_ga.ply``: that map, at GA's final poses (``trajectory_ga.tum``);
* ``map_f2f.ply``: the same keyframe clouds at the frame-to-frame poses anchored as GA
  (``trajectory_f2f.tum``), built at once (:func:`ga_ros.mapping.cloud_map.map_from_poses`);

binary little-endian PLY, ``x y z intensity`` float32, in the map frame
(:mod:`ga_ros.mapping.ply`), and puts their figures in ``summary.json``'s ``map``
(:mod:`ga_ros.mapping.figures`: points, covered area, spread of heights per x-y cell in the
map and between the tracks; GA's against F2F's; and what the corrections moved on the way).
Offline, every keyframe keeps its points (no static layer: ``max_live_keyframes`` 0), so that
the F2F map has them all.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ga_ros.errors import GaError
from ga_ros.io.trajectory import Trajectory
from ga_ros.mapping.cloud_map import CloudMapConfig, map_from_poses, transform_points
from ga_ros.mapping.figures import group_height_spread, map_figures
from ga_ros.mapping.ply import write_ply
from ga_ros.pipeline.cloud_map import CloudMapBuilder
from ga_ros.pipeline.corrections import Corrections
from ga_ros.safe_write import check_destinations

#: The files ``--map`` writes (the photomosaic's: :mod:`ga_ros.mapping.replay_mosaic`).
MAP_FILES = ('map_ga.ply', 'map_f2f.ply')


@dataclass(frozen=True)
class MapOutputConfig:
    """Settings of the replay's maps.

    Attributes
    ----------
    cloud : the map's voxels and the per-keyframe decimation (as ``map_node``'s parameters;
        ``max_live_keyframes`` is not used offline).
    cell_m : edge of the x-y cells of the figures (covered area, spread of heights), m.
    """

    cloud: CloudMapConfig = CloudMapConfig()
    cell_m: float = 2.0


@dataclass
class ReplayMap:
    """The map of a replay, fed as ``map_node`` is (module docstring).

    Attributes
    ----------
    front : the stereo front end of the replay (its calibration and extrinsic).
    config : the settings.
    builder : the map (``map_node``'s pipeline object).
    errors : keyframes whose cloud failed, with why (the first ten).
    """

    front: Any
    config: MapOutputConfig = MapOutputConfig()
    builder: CloudMapBuilder = field(init=False)
    errors: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        self.builder = CloudMapBuilder(replace(self.config.cloud, max_live_keyframes=0))

    def on_keyframe(self, frame: Any) -> None:
        """A processed pair that made a keyframe (the front end's ``FrameOutput``): its cloud,
        as ``vo_node`` publishes it and ``map_node`` takes it."""
        res = frame.result
        ext = self.front.extrinsic
        if res is None or res.keyframe is None or ext is None:
            return
        try:
            cloud = self.front.keyframe_cloud(frame)
        except GaError as exc:
            if len(self.errors) < 10:
                self.errors.append(f'keyframe {res.keyframe.stamp_ns}: {exc}')
            return
        if cloud is None:
            return
        stamp = int(res.keyframe.stamp_ns)
        self.builder.set_extrinsic(ext)
        self.builder.add_cloud(stamp, ext.camera_frame, cloud.points, cloud.intensity)

    def on_corrections(self, c: Corrections) -> None:
        """A corrections message of the replay (``ga/corrections``), as ``map_node`` takes it."""
        self.builder.on_corrections(c.message())

    def clouds(self, stamps_ns: np.ndarray) -> dict[int, tuple[np.ndarray, np.ndarray]]:
        """Keyframe stamp -> ``(points, intensity)`` in the keyframe's ``base_link`` (as kept),
        for the stamps that have one."""
        out = {}
        for s in np.asarray(stamps_ns).tolist():
            c = self.builder.map.keyframe_cloud(int(s))
            if c is not None:
                out[int(s)] = c
        return out


def attach(run: Any, config: MapOutputConfig) -> ReplayMap | None:
    """A :class:`ReplayMap` fed by the replay's stereo source and its corrections (None when
    the source is not a stereo bag: the result says why), after the destinations were
    checked."""
    check_destinations(*(run.out.dir / name for name in MAP_FILES))
    source = run.source
    front = getattr(source, 'front', None)
    if front is None or not hasattr(source, 'on_keyframe'):
        run.result.warnings.append('--map needs a stereo bag (the keyframe clouds come from '
                                   'its images): no map written')
        return None
    replay_map = ReplayMap(front, config)
    source.on_keyframe = replay_map.on_keyframe
    run.on_corrections = replay_map.on_corrections
    return replay_map


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


def write_map_outputs(run: Any, replay_map: ReplayMap, ga: Trajectory,
                      f2f: Trajectory) -> dict[str, Any]:
    """Write ``map_ga.ply`` and ``map_f2f.ply`` (module docstring) and return the summary's
    ``map`` block: per map its figures and file, the keyframes with a cloud and how many of
    them the path placed, what the corrections did during the replay, and the GA / F2F ratios
    of the median spreads."""
    cfg = replay_map.config
    builder = replay_map.builder
    counts = builder.counts
    out: dict[str, Any] = {'keyframes_with_cloud': counts.clouds, 'voxel_m': cfg.cloud.voxel_m,
                           'keyframe_voxel_m': cfg.cloud.keyframe_voxel_m,
                           'online': {'corrections': counts.corrections,
                                      'keyframes_moved': counts.moved,
                                      'points_moved': counts.points_moved}}
    if replay_map.errors:
        out['cloud_errors'] = replay_map.errors
    final = builder.set_poses(ga.stamps_ns, ga.T_world_node)   # GA's final poses
    out['online']['moved_to_final'] = final.moved
    clouds = replay_map.clouds(ga.stamps_ns)
    frame = ga.frame_id or 'map'
    for name, traj in (('ga', ga), ('f2f', f2f)):
        cloud = (builder.cloud() if name == 'ga' else
                 _build(cfg, clouds, traj))
        path = write_ply(run.out.dir / f'map_{name}.ply', cloud.points, cloud.intensity,
                         comments=(f'ga_ros map ({name} poses), frame {frame}',))
        run.out.files[f'map_{name}'] = path
        figures = map_figures(cloud.points, cfg.cell_m).as_dict()
        placed, tracks = _placed_points(clouds, traj)
        figures['track_height_spread_m'] = group_height_spread(placed, tracks,
                                                               cfg.cell_m).as_dict()
        figures['keyframes_placed'] = int(np.isin(traj.stamps_ns, list(clouds)).sum())
        out[name] = {**figures, 'file': str(path)}
    for key in ('height_spread_m', 'track_height_spread_m'):
        ga_s, f2f_s = out['ga'][key]['median'], out['f2f'][key]['median']
        out[f'{key[:-2]}_ga_over_f2f'] = (ga_s / f2f_s if f2f_s and np.isfinite(f2f_s)
                                          else float('nan'))
    return out
