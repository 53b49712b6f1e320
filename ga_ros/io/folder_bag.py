"""A stereo dataset folder (EuRoC ASL, KITTI odometry) read as a bag.

:func:`open_recording` opens what ``ga-ros replay`` is given: such a folder
(:class:`FolderReader`), else a bag (:class:`ga_ros.io.bag.BagReader`). :class:`FolderBag`
shows a :class:`ga_ros.io.stereo_folder.StereoFolder` to the replay as the bag a conversion would
make, so that the one stereo path (topic plan, ``StereoSource``, the ground truth by stamp,
``/tf_static`` for the camera's extrinsic) reads it unchanged:

* ``/cam0/camera_info``, ``/cam1/camera_info`` (``sensor_msgs/msg/CameraInfo``): the left and
  right models, once, before the images;
* ``/cam0/image_raw``, ``/cam1/image_raw`` (``sensor_msgs/msg/CompressedImage``): each PNG file
  as it is;
* ``/tf_static`` (``tf2_msgs/msg/TFMessage``): ``base_link -> cam0`` and ``base_link -> cam1``;
* ``/ga/ground_truth`` (``geometry_msgs/msg/PoseStamped``): ``T_world_base``, when the folder
  has a ground truth.

Log times are the stamps; at one time the calibration and ``/tf_static`` come first, then the left
image, then the right. An image file is read when its message is.
"""

from __future__ import annotations

import heapq
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from ga_ros import topics
from ga_ros.errors import FormatError
from ga_ros.io.bag import BagReader
from ga_ros.io.bag.summary import BagInfo, BagMessage, BagTopic
from ga_ros.io.bag_messages import (
    CAMERA_INFO,
    COMPRESSED_IMAGE,
    POSE_STAMPED,
    header,
    matrix_to_pose_msg,
    typestore,
)
from ga_ros.io.stereo_folder import StereoFolder, read_stereo_folder

if TYPE_CHECKING:
    from ga_ros.vo.calibration import CameraModel

TF_MESSAGE = 'tf2_msgs/msg/TFMessage'
#: The base frame of a folder's ``/tf_static`` (the robot's, REP 105).
BASE_FRAME = 'base_link'


def folder_topics(folder: StereoFolder) -> dict[str, tuple[str, str]]:
    """``{role: (topic, type)}`` of a folder's bag (module doc); ``ground_truth`` only when the
    folder has it."""
    left, right = folder.frames
    out = {'left_info': (f'/{left}/camera_info', CAMERA_INFO),
           'right_info': (f'/{right}/camera_info', CAMERA_INFO),
           'left_image': (f'/{left}/image_raw', COMPRESSED_IMAGE),
           'right_image': (f'/{right}/image_raw', COMPRESSED_IMAGE),
           'tf_static': ('/tf_static', TF_MESSAGE)}
    if len(folder.ground_truth_stamps_ns):
        out['ground_truth'] = (topics.resolve(topics.GROUND_TRUTH), POSE_STAMPED)
    return out


def camera_info(model: CameraModel, frame: str, stamp_ns: int) -> Any:
    """``sensor_msgs/CameraInfo`` (rosbags) of a camera model."""
    types = typestore().types
    return types[CAMERA_INFO](
        header=header(frame, stamp_ns), height=int(model.height), width=int(model.width),
        distortion_model=model.distortion_model,
        d=np.asarray(model.D, float).reshape(-1).copy(),
        k=np.asarray(model.K, float).reshape(9).copy(),
        r=np.asarray(model.R, float).reshape(9).copy(),
        p=model.projection().reshape(12).copy(), binning_x=0, binning_y=0,
        roi=types['sensor_msgs/msg/RegionOfInterest'](x_offset=0, y_offset=0, height=0, width=0,
                                                      do_rectify=False))


def _png(path: Path, frame: str, stamp_ns: int) -> Any:
    try:
        data = np.frombuffer(path.read_bytes(), dtype=np.uint8)
    except OSError as exc:
        raise FormatError(f'cannot read image: {exc.strerror or exc}', str(path)) from None
    fmt = 'png' if path.suffix.lower() == '.png' else path.suffix.lstrip('.').lower()
    return typestore().types[COMPRESSED_IMAGE](header=header(frame, stamp_ns), format=fmt,
                                               data=data)


class FolderBag:
    """A :class:`StereoFolder` as a bag (module doc): the reader interface of
    :class:`ga_ros.io.bag.BagReader` (``info``, ``messages``, ``close``)."""

    def __init__(self, folder: StereoFolder) -> None:
        self.folder = folder
        self.topics = folder_topics(folder)

    def info(self) -> BagInfo:
        f = self.folder
        n = len(f.stamps_ns)
        counts = {'left_info': 1, 'right_info': 1, 'left_image': n, 'right_image': n,
                  'tf_static': 1, 'ground_truth': len(f.ground_truth_stamps_ns)}
        topics_ = tuple(sorted((BagTopic(name, kind, counts[role])
                                for role, (name, kind) in self.topics.items()),
                               key=lambda t: t.name))
        stamps = np.concatenate([f.stamps_ns, f.ground_truth_stamps_ns])
        return BagInfo(f.path, f.kind, sum(t.count for t in topics_), int(stamps.min()),
                       int(stamps.max()), topics_)

    def _rows(self, role: str) -> Iterator[tuple[int, int, str, Any]]:
        """``(log ns, order at one time, role, payload)`` of one topic, in time order."""
        f = self.folder
        t0 = int(f.stamps_ns[0])
        if role in ('left_info', 'right_info', 'tf_static'):
            yield (t0, 0, role, None)
        elif role in ('left_image', 'right_image'):
            files = f.left_files if role == 'left_image' else f.right_files
            order = 1 if role == 'left_image' else 2
            for s, p in zip(f.stamps_ns.tolist(), files):
                yield (int(s), order, role, p)
        elif role == 'ground_truth':
            for k, s in enumerate(f.ground_truth_stamps_ns.tolist()):
                yield (int(s), 3, role, k)

    def _message(self, role: str, payload: Any, log_ns: int) -> tuple[Any, bytes | None]:
        f = self.folder
        left, right = f.frames
        if role == 'left_info':
            return camera_info(f.left, left, log_ns), None
        if role == 'right_info':
            return camera_info(f.right, right, log_ns), None
        if role == 'tf_static':
            from ga_ros.io.bag_writer import tf_message, transform_msg

            msg = tf_message([transform_msg(BASE_FRAME, left, f.T_base_left, log_ns),
                              transform_msg(BASE_FRAME, right, f.T_base_right, log_ns)])
            return msg, bytes(typestore().serialize_cdr(msg, TF_MESSAGE))
        if role == 'ground_truth':
            return typestore().types[POSE_STAMPED](
                header=header('world', log_ns),
                pose=matrix_to_pose_msg(f.T_world_base[payload])), None
        return _png(payload, left if role == 'left_image' else right, log_ns), None

    def messages(self, wanted: set[str] | None, raw: bool, name: str) -> Iterator[BagMessage]:
        if raw:
            raise FormatError(f'a {self.folder.kind} folder cannot be played raw: replay it '
                              '(ga-ros replay FOLDER)', name)
        roles = [r for r, (t, _) in self.topics.items() if wanted is None or t in wanted]
        for log_ns, _, role, payload in heapq.merge(*(self._rows(r) for r in roles)):
            msg, data = self._message(role, payload, log_ns)
            topic, kind = self.topics[role]
            yield BagMessage(topic, kind, log_ns, msg, data)

    def close(self) -> None:
        """Nothing to close (files are read one message at a time)."""


class FolderReader(BagReader):
    """A :class:`BagReader` of a stereo dataset folder (:class:`FolderBag`)."""

    def __init__(self, folder: StereoFolder) -> None:
        super().__init__(folder.path)
        self.folder = folder

    def open(self) -> None:
        """Show the folder as its bag (nothing is read but its lists and calibration)."""
        self._reader = FolderBag(self.folder)
        self.info = self._reader.info()


def open_recording(path: str | Path) -> BagReader:
    """The reader of what ``ga-ros replay`` is given (not opened yet): a EuRoC ASL folder or a
    KITTI odometry sequence (:func:`ga_ros.io.stereo_folder.read_stereo_folder`), else a bag.

    Raises
    ------
    FormatError
        A recognised folder with a missing or malformed file.
    """
    folder = read_stereo_folder(path)
    return BagReader(path) if folder is None else FolderReader(folder)


def recording_info(path: str | Path) -> BagInfo:
    """The summary of :func:`open_recording`'s recording (as :func:`ga_ros.io.bag.bag_info`)."""
    with open_recording(path) as rec:
        assert rec.info is not None
        return rec.info
