"""The replay's mosaic step (ROS-free): keyframe images read back from the bag, then one mosaic
per trajectory (GA's final poses, the frame-to-frame odometry) with its seam misregistration.

:func:`write_mosaics` is what the replay's map step calls (``ga-ros replay BAG --mosaic``,
through :func:`replay_mosaics`): it writes ``mosaic_<name>.png`` (+ ``.json`` / ``.pgw``
georeference, :func:`ga_ros.mapping.mosaic.save_mosaic`) and returns the figures for
``summary.json``. The keyframe images and stereo points held are bounded
(:data:`MAX_KEYFRAME_BYTES`, a clear error beyond).
The ground is the keyframes' dense stereo points
(:class:`ga_ros.vo.dense.DenseStereo`) placed with the same trajectory's poses
(:func:`ga_ros.mapping.surface.height_grid_from_points`), so each mosaic is orthorectified with
its own poses; without right images, a given plane height.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import InputError
from ga_ros.io.bag_messages import stamp_to_ns
from ga_ros.io.trajectory import Trajectory
from ga_ros.mapping.figure import MosaicPanel, write_compare_figure
from ga_ros.mapping.mosaic import (
    CameraView,
    MosaicConfig,
    Surface,
    build_mosaic,
    plan_georeference,
    save_mosaic,
)
from ga_ros.mapping.seams import SeamStats, seam_misregistration
from ga_ros.mapping.surface import GroundPlane, SurfaceConfig, ground_from_keyframe_points

#: Default limit of the keyframe data a replay's mosaic step holds (bytes).
MAX_KEYFRAME_BYTES = 1 << 30


@dataclass
class KeyframeImages:
    """Rectified keyframe images read back from a bag, with their dense stereo points.

    Attributes
    ----------
    stamps_ns : (n,) keyframe stamps (ns), the images' header stamps.
    left : n (h, w) uint8 rectified left images.
    points : per keyframe its dense stereo points (:class:`ga_ros.vo.dense.DenseStereo`),
        (k, 3) float32 in the left camera's optical frame (m); None without a right image.
    K : (3, 3) rectified intrinsics (px).
    """

    stamps_ns: IntArray
    left: list[np.ndarray]
    points: list[np.ndarray | None]
    K: FloatArray


def read_keyframe_images(bag: Any, left_topic: str, right_topic: str, calibration: Any,
                         stamps_ns: IntArray, pixel_stride: int = 4,
                         max_bytes: int = MAX_KEYFRAME_BYTES) -> KeyframeImages:
    """The keyframes ``stamps_ns`` (header stamps, ns) of an open bag
    (:class:`ga_ros.io.bag.BagReader`): left images rectified with ``calibration``
    (:class:`ga_ros.vo.calibration.StereoCalibration`) and the pair's dense stereo points (every
    ``pixel_stride``-th pixel); the right images are not kept. Keyframes whose left image is not
    found are dropped (their stamps are not in the result).

    Raises
    ------
    InputError
        The images and points held would exceed ``max_bytes``.
    """
    from ga_ros.vo.dense import DenseStereo, DenseStereoConfig
    from ga_ros.vo.messages import image_to_grey

    dense = DenseStereo(DenseStereoConfig(pixel_stride=pixel_stride))
    want = {int(s) for s in np.asarray(stamps_ns)}
    left: dict[int, np.ndarray] = {}
    points: dict[int, np.ndarray] = {}
    early_right: dict[int, np.ndarray] = {}  # right images whose left has not come yet
    sides = {left_topic: 'left', right_topic: 'right'}
    held = 0
    for bm in bag.messages([left_topic, right_topic]):
        s = stamp_to_ns(bm.msg.header.stamp)
        side = sides.get(bm.topic)
        if side is None or s not in want or s in points or (side == 'left' and s in left):
            continue
        img = calibration.rectify_one(image_to_grey(bm.msg), side)
        if side == 'left':
            left[s] = img
            held += img.nbytes
            right = early_right.pop(s, None)
            if right is None:
                continue
            held -= right.nbytes
        elif s in left:
            right = img
        else:
            early_right[s] = img
            held += img.nbytes
            continue
        pts = dense.cloud(left[s], right, calibration).points
        points[s] = pts
        held += pts.nbytes
        if held > max_bytes:
            raise InputError(f"mosaic: the keyframes' images and stereo points exceed "
                             f'{max_bytes / 2 ** 20:.0f} MiB after {len(left)} of {len(want)} '
                             'keyframes; raise the limit (max_bytes) or mosaic a part of the '
                             'survey')
    stamps = np.array(sorted(left), dtype=np.int64)
    return KeyframeImages(stamps, [left[int(s)] for s in stamps],
                          [points.get(int(s)) for s in stamps], np.asarray(calibration.K, float))


def poses_at(traj: Trajectory, stamps_ns: IntArray) -> tuple[IntArray, FloatArray, IntArray]:
    """Indices into ``stamps_ns`` found in ``traj`` (exact stamps), their poses and track ids."""
    index = {int(s): i for i, s in enumerate(np.asarray(traj.stamps_ns))}
    rows = [(k, index[int(s)]) for k, s in enumerate(np.asarray(stamps_ns)) if int(s) in index]
    keep = np.array([k for k, _ in rows], dtype=np.int64)
    at = np.array([i for _, i in rows], dtype=np.int64)
    if at.size == 0:
        return keep, np.zeros((0, 4, 4)), keep
    return keep, np.asarray(traj.T_world_node)[at], np.asarray(traj.track_ids)[at]


def write_mosaics(out_dir: str | Path, images: KeyframeImages,
                  trajectories: dict[str, Trajectory], T_base_cam: FloatArray | None = None,
                  config: MosaicConfig = MosaicConfig(), ground_z: float | None = None,
                  ground_cell_m: float = 2.0) -> dict[str, dict[str, Any]]:
    """One mosaic per trajectory (``mosaic_<name>.png`` in ``out_dir``) and its figures.

    Parameters
    ----------
    images : the keyframes' rectified images (:func:`read_keyframe_images`).
    trajectories : name (e.g. ``'ga'``, ``'f2f'``) -> poses ``T_map_base`` of the keyframes
        (matched to the images by exact stamp) with their track ids.
    T_base_cam : (4, 4) the camera's pose in ``base_link`` (default: the identity).
    config : resolution, blending and size limit (0 m/px: the first trajectory's ground sample
        distance, then the same grid size for all, so they compare pixel for pixel).
    ground_z : a ground plane height (m in ``map``) instead of the stereo ground.
    ground_cell_m : cell of the stereo ground's height grid (m).

    Returns
    -------
    name -> ``{'png', 'georeference', 'world_file', 'keyframes', 'covered_area_m2',
    'metres_per_pixel', 'seams': {'pairs', 'measured', 'median_px', 'p95_px', ...}}``; with
    both ``'ga'`` and ``'f2f'`` also ``'compare': {'png'}``, the before / after figure
    ``mosaic_compare.png`` (:func:`ga_ros.mapping.figure.write_compare_figure`).

    Raises
    ------
    InputError
        No keyframe image, no pose for them, or a mosaic over the size limit.
    """
    if not images.left:
        raise InputError('mosaic: no keyframe image was read back from the bag')
    T_bc = np.eye(4) if T_base_cam is None else np.asarray(T_base_cam, float)
    out: dict[str, dict[str, Any]] = {}
    panels: dict[str, tuple[MosaicPanel, SeamStats]] = {}
    mpp = config.metres_per_pixel
    points_cam = images.points
    for name, traj in trajectories.items():
        keep, T_map_base, tracks = poses_at(traj, images.stamps_ns)
        if keep.size == 0:
            raise InputError(f"mosaic {name}: no keyframe pose at the images' stamps")
        T_map_cam = T_map_base @ T_bc
        views = [CameraView(images.left[int(k)], T, images.K) for k, T in zip(keep, T_map_cam)]
        surface: Surface = (GroundPlane(float(ground_z)) if ground_z is not None
                            else ground_from_keyframe_points([points_cam[int(k)] for k in keep],
                                                            T_map_cam,
                                                            SurfaceConfig(cell_m=ground_cell_m)))
        cfg = MosaicConfig(mpp, config.blend, config.max_pixels, config.margin_m)
        georef = plan_georeference(views, surface, cfg)
        mpp = georef.metres_per_pixel
        mosaic = build_mosaic(views, surface, cfg, georef)
        files = save_mosaic(Path(out_dir) / f'mosaic_{name}.png', mosaic)
        seams = seam_misregistration(views, tracks, surface, georef)
        out[name] = {**files, 'keyframes': len(views),
                     'covered_area_m2': float(mosaic.valid.sum()) * mpp * mpp,
                     'metres_per_pixel': mpp, 'seams': seams.as_dict()}
        if len(keep) == len(images.left):  # every keyframe: the panels index the same views
            label = {'f2f': 'F2F (before)', 'ga': 'GA (after)'}.get(name, name)
            panels[name] = (MosaicPanel(f'{label}: seams {seams.median_px:.2f} px median',
                                        mosaic, views, surface), seams)
    if 'f2f' in panels and 'ga' in panels:
        out['compare'] = {'png': _compare(Path(out_dir) / 'mosaic_compare.png', panels)}
    return out


def _compare(path: Path, panels: dict[str, tuple[MosaicPanel, SeamStats]]) -> str:
    """The before / after figure, zoomed on the seam F2F misregisters most."""
    before, seams = panels['f2f']
    pair = centre = None
    if seams.offsets:
        worst = max(seams.offsets, key=lambda o: o.length_px)
        pair, centre = (worst.a, worst.b), worst.centre_xy
    return write_compare_figure(path, before, panels['ga'][0], pair, centre)


def replay_mosaics(source: Any, out_dir: str | Path,
                   trajectories: dict[str, Trajectory]) -> dict[str, dict[str, Any]]:
    """The replay's mosaics from its stereo source (:class:`ga_ros.replay.stereo.StereoSource`:
    its open bag, topic plan, front end's calibration and extrinsic): the keyframe images read
    back, then :func:`write_mosaics`.

    Raises
    ------
    InputError
        The source is not a stereo camera's, or has no calibration or keyframe image.
    """
    front = getattr(source, 'front', None)
    if front is None or getattr(front, 'calibration', None) is None:
        raise InputError('a mosaic needs a stereo image bag (a downward camera); this source '
                         'has no calibrated camera')
    plan = source.plan
    stamps = np.unique(np.concatenate([np.asarray(t.stamps_ns) for t in trajectories.values()]))
    images = read_keyframe_images(source.bag, plan.left_image, plan.right_image,
                                  front.calibration, stamps)
    ext = getattr(front, 'extrinsic', None)
    return write_mosaics(out_dir, images, trajectories,
                         None if ext is None else np.asarray(ext.T_base_cam, float))
