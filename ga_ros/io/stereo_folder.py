"""Stereo datasets stored as folders: a EuRoC ASL folder and a KITTI odometry sequence.

:func:`read_stereo_folder` recognises the folder and reads what the replay needs from it into a
:class:`StereoFolder`: the stamps and files of the left and right images, the two camera models
(rectified, as ``CameraInfo`` gives them), the cameras' poses in the robot's base frame and the
ground truth when present. :class:`ga_ros.io.bag.folder.FolderBag` then shows it to the replay as
a bag. Images are never decoded here (their files are read when their message is).

EuRoC ASL (``MH_01_easy/`` or its ``mav0/``)
    ``mav0/cam0/data.csv`` (``#timestamp [ns],filename``) and ``mav0/cam0/data/*.png`` (left),
    the same under ``cam1`` (right); ``cam0/sensor.yaml``, ``cam1/sensor.yaml`` (pinhole,
    radial-tangential intrinsics, ``T_BS`` = the camera's pose in the body frame ``B``, the
    IMU); ``mav0/state_groundtruth_estimate0/data.csv`` (optional): ``T_world_B`` at 200 Hz. The
    base frame is ``B``: ``T_base_cam0`` is cam0's ``T_BS``.

KITTI odometry (``sequences/NN/``)
    ``image_0/*.png`` (left grey), ``image_1/*.png`` (right grey), ``calib.txt`` (``P0:`` and
    ``P1:``, the rectified 3x4 projections, ``P1[0, 3] = -fx * baseline``), ``times.txt`` (s,
    one a line); ground truth (optional): ``NN.txt`` in ``../../poses/`` (the dataset's layout)
    or ``poses.txt`` in the sequence folder, ``T_cam0(0)_cam0(k)`` of the left camera. The base
    frame is the left camera (``T_base_cam0`` = identity): KITTI's poses are the left camera's.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import FormatError, InputError
from ga_ros.geometry import se3
from ga_ros.io.groundtruth import read_euroc_csv, read_kitti_ground_truth

if TYPE_CHECKING:
    from ga_ros.vo.calibration import CameraModel


@dataclass(frozen=True)
class StereoFolder:
    """A stereo dataset folder, read (images by file name only).

    Attributes
    ----------
    kind : ``'EuRoC'`` or ``'KITTI'``.
    path : the folder given.
    stamps_ns : (n,) acquisition times of the pairs (ns, increasing).
    left_files, right_files : the n image files of each pair.
    left, right : the rectified camera models (``CameraInfo`` fields).
    frames : the left and right camera frame ids (``cam0``, ``cam1``).
    T_base_left, T_base_right : (4, 4) the cameras' poses in the base frame.
    ground_truth_stamps_ns, T_world_base : the ground truth ((m,) ns, (m, 4, 4)), empty arrays
        when the folder has none.
    ground_truth_file : the file the ground truth was read from ('' = none).
    """

    kind: str
    path: Path
    stamps_ns: IntArray
    left_files: tuple[Path, ...]
    right_files: tuple[Path, ...]
    left: CameraModel
    right: CameraModel
    frames: tuple[str, str]
    T_base_left: FloatArray
    T_base_right: FloatArray
    ground_truth_stamps_ns: IntArray
    T_world_base: FloatArray
    ground_truth_file: str = ''


def euroc_root(path: Path) -> Path | None:
    """The ``mav0`` folder of a EuRoC ASL folder (``path`` or ``path/mav0``), else None."""
    for root in (path / 'mav0', path):
        if (root / 'cam0' / 'data.csv').is_file() and (root / 'cam1' / 'data.csv').is_file():
            return root
    return None


def is_kitti_sequence(path: Path) -> bool:
    """True for a KITTI odometry sequence folder (``image_0``, ``image_1``, ``calib.txt``)."""
    return all((path / n).exists() for n in ('image_0', 'image_1', 'calib.txt'))


def read_stereo_folder(path: str | Path) -> StereoFolder | None:
    """The EuRoC or KITTI folder at ``path`` (module doc), or None when it is neither.

    Raises
    ------
    FormatError
        A recognised folder with a missing or malformed file (the message names it).
    """
    path = Path(path)
    if not path.is_dir():
        return None
    root = euroc_root(path)
    if root is not None:
        return read_euroc(path, root)
    if is_kitti_sequence(path):
        return read_kitti(path)
    return None


def _euroc_images(cam: Path) -> tuple[IntArray, list[Path]]:
    stamps: list[int] = []
    files: list[Path] = []
    name = str(cam / 'data.csv')
    for k, line in enumerate((cam / 'data.csv').read_text().splitlines(), start=1):
        text = line.strip()
        if not text or text.startswith('#'):
            continue
        fields = [f.strip() for f in text.split(',')]
        if len(fields) < 2 or not fields[0].isdigit() or len(fields[0]) > 19:
            raise FormatError('expected "timestamp [ns],filename"', name, k)
        stamps.append(int(fields[0]))
        files.append(cam / 'data' / fields[1])
    if not files:
        raise FormatError('no images listed', name)
    return np.asarray(stamps, np.int64), files


def read_euroc(path: Path, root: Path) -> StereoFolder:
    """A EuRoC ASL folder whose ``mav0`` is ``root`` (module doc); pairs are the stamps both
    cameras list."""
    import yaml

    from ga_ros.vo.calibration import read_stereo_calibration

    sl, fl = _euroc_images(root / 'cam0')
    sr, fr = _euroc_images(root / 'cam1')
    right = dict(zip(sr.tolist(), fr))
    keep = [k for k, s in enumerate(sl.tolist()) if s in right]
    if not keep:
        raise FormatError('cam0 and cam1 share no timestamp: no stereo pair', str(root))
    order = sorted(keep, key=lambda k: int(sl[k]))
    stamps = sl[order]
    yamls = [root / c / 'sensor.yaml' for c in ('cam0', 'cam1')]
    for y in yamls:
        if not y.is_file():
            raise FormatError('missing sensor.yaml (the camera calibration)', str(y))
    try:
        models = read_stereo_calibration([str(y) for y in yamls])
    except InputError as exc:
        raise FormatError(str(exc), str(root)) from None
    T_bs = []
    for y in yamls:
        text = y.read_text()
        doc = yaml.safe_load(text.split('\n', 1)[1] if text.startswith('%YAML') else text)
        T_bs.append(np.asarray(doc['T_BS']['data'], float).reshape(4, 4))
    gt_file = root / 'state_groundtruth_estimate0' / 'data.csv'
    gt_stamps, T_gt = np.zeros(0, np.int64), np.zeros((0, 4, 4))
    if gt_file.is_file():
        traj = read_euroc_csv(gt_file)
        gt_stamps, T_gt = traj.stamps_ns, traj.T_world_node
    return StereoFolder('EuRoC', path, stamps, tuple(fl[k] for k in order),
                        tuple(right[int(s)] for s in stamps), models.left, models.right,
                        ('cam0', 'cam1'), T_bs[0], T_bs[1], gt_stamps, T_gt,
                        str(gt_file) if gt_file.is_file() else '')


def _kitti_calibration(path: Path) -> dict[str, FloatArray]:
    out: dict[str, FloatArray] = {}
    for k, line in enumerate(path.read_text().splitlines(), start=1):
        key, sep, rest = line.partition(':')
        if not sep:
            continue
        try:
            values = np.asarray([float(v) for v in rest.split()], float)
        except ValueError:
            raise FormatError(f'not a number in {line[:60]!r}', str(path), k) from None
        if values.size == 12:
            out[key.strip()] = values.reshape(3, 4)
    for key in ('P0', 'P1'):
        if key not in out:
            raise FormatError(f'no {key}: line of 12 numbers (the rectified projection)',
                              str(path))
    return out


def _kitti_model(P: FloatArray, width: int, height: int) -> CameraModel:
    from ga_ros.vo.calibration import CameraModel

    return CameraModel(width, height, P[:, :3].copy(), np.zeros(5), np.eye(3), P.copy())


def read_kitti(path: Path) -> StereoFolder:
    """A KITTI odometry sequence folder (module doc)."""
    import cv2

    left = sorted((path / 'image_0').glob('*.png'))
    right = sorted((path / 'image_1').glob('*.png'))
    if not left or len(left) != len(right):
        raise FormatError(f'image_0 has {len(left)} and image_1 {len(right)} PNG images: '
                          'expected the same positive number', str(path))
    times = path / 'times.txt'
    if not times.is_file():
        raise FormatError('missing times.txt (the image times, s)', str(path))
    t = np.asarray([float(x.split()[0]) for x in times.read_text().splitlines() if x.strip()])
    if t.size != len(left):
        raise FormatError(f'{t.size} times for {len(left)} images', str(times))
    stamps = np.round(t * 1e9).astype(np.int64)
    first = cv2.imread(str(left[0]), cv2.IMREAD_GRAYSCALE)
    if first is None:
        raise FormatError('cannot read the image', str(left[0]))
    h, w = first.shape
    P = _kitti_calibration(path / 'calib.txt')
    baseline = -P['P1'][0, 3] / P['P1'][0, 0]
    if not baseline > 0:
        raise FormatError(f'P1 gives a baseline of {baseline:.3g} m: expected the right camera '
                          'right of the left one (P1[0, 3] < 0)', str(path / 'calib.txt'))
    T_right = se3.from_rt(np.eye(3), np.array([baseline, 0.0, 0.0]))
    gt_stamps, T_gt, gt_name = np.zeros(0, np.int64), np.zeros((0, 4, 4)), ''
    for cand in (path.parent.parent / 'poses' / f'{path.name}.txt', path / 'poses.txt'):
        if cand.is_file():
            T_gt = read_kitti_ground_truth(cand, times)
            gt_stamps, T_gt, gt_name = T_gt.stamps_ns, T_gt.T_world_node, str(cand)
            break
    return StereoFolder('KITTI', path, stamps, tuple(left), tuple(right),
                        _kitti_model(P['P0'], w, h), _kitti_model(P['P1'], w, h),
                        ('cam0', 'cam1'), np.eye(4), T_right, gt_stamps, T_gt, gt_name)
