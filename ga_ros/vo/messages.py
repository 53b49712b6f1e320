"""Image and CameraInfo messages -> numpy, for rclpy and rosbags messages alike (ROS-free).

The one decoder of the stereo front end (``vo_node`` and the replay both use it): the functions
read message fields by name (``encoding``, ``height``, ``data``, ``k``, ...), which rclpy and
rosbags messages share, and never import ROS.
"""

from __future__ import annotations

import array
from typing import Any

import numpy as np

from ga_ros.errors import InputError
from ga_ros.runtime import lazy_import
from ga_ros.vo.calibration import CameraModel

cv2 = lazy_import('cv2')  # imported on first use (start-up of the command line)

#: Supported ``sensor_msgs/Image`` encodings -> bytes per pixel.
BYTES_PER_PIXEL = {'mono8': 1, '8uc1': 1, 'bgr8': 3, '8uc3': 3, 'rgb8': 3, 'bgra8': 4,
                   'rgba8': 4, 'mono16': 2, '16uc1': 2}
#: Colour encodings -> the name of OpenCV's conversion to grey in ``cv2``.
_TO_GREY = {'bgr8': 'COLOR_BGR2GRAY', '8uc3': 'COLOR_BGR2GRAY', 'rgb8': 'COLOR_RGB2GRAY',
            'bgra8': 'COLOR_BGRA2GRAY', 'rgba8': 'COLOR_RGBA2GRAY'}


def message_bytes(data: Any) -> np.ndarray:
    """Message ``data`` (bytes, array.array, numpy array or list) -> flat uint8 array."""
    if isinstance(data, np.ndarray):
        return data.astype(np.uint8, copy=False).ravel()
    if isinstance(data, (bytes, bytearray, memoryview, array.array)):
        return np.frombuffer(data, np.uint8)
    return np.asarray(data, dtype=np.uint8).ravel()


def is_compressed(msg: Any) -> bool:
    """True for a ``sensor_msgs/CompressedImage`` (it has ``format``, not ``encoding``)."""
    return not hasattr(msg, 'encoding') and hasattr(msg, 'format')


def image_to_grey(msg: Any) -> np.ndarray:
    """``sensor_msgs/Image`` or ``CompressedImage`` -> grey ``uint8`` (height, width) array.

    Raw encodings: ``mono8``/``8UC1``, ``bgr8``/``8UC3``, ``rgb8``, ``bgra8``, ``rgba8`` and
    ``mono16``/``16UC1`` (the high byte); compressed: anything OpenCV decodes (jpeg, png).

    Raises
    ------
    InputError
        Undecodable data, an unsupported encoding, or a data size that disagrees with
        ``height`` and ``step``.
    """
    if is_compressed(msg):
        buf = message_bytes(msg.data)
        img = cv2.imdecode(buf, cv2.IMREAD_GRAYSCALE) if buf.size else None
        if img is None:
            raise InputError(f'could not decode compressed image (format {msg.format!r})')
        return img
    enc = str(msg.encoding).lower()
    c = BYTES_PER_PIXEL.get(enc)
    if c is None:
        raise InputError(f'unsupported image encoding {msg.encoding!r} (use mono8, bgr8, rgb8, '
                         'bgra8, rgba8 or mono16)')
    h, w, step = int(msg.height), int(msg.width), int(msg.step)
    data = message_bytes(msg.data)
    if h <= 0 or w <= 0 or step < w * c or data.size < h * step:
        raise InputError(f'image data of {data.size} bytes does not match {w}x{h}, step {step}')
    rows = data[:h * step].reshape(h, step)[:, :w * c]
    if c == 2:
        dt = '>u2' if msg.is_bigendian else '<u2'
        return (rows.copy().view(dt).reshape(h, w) >> 8).astype(np.uint8)
    if c == 1:
        return np.ascontiguousarray(rows.reshape(h, w))
    return cv2.cvtColor(np.ascontiguousarray(rows.reshape(h, w, c)), getattr(cv2, _TO_GREY[enc]))


def camera_info_to_model(msg: Any) -> CameraModel:
    """``sensor_msgs/CameraInfo`` -> :class:`CameraModel`.

    A zero ``R`` means identity and a zero ``P`` means ``[K | 0]`` (uncalibrated drivers).

    Raises
    ------
    InputError
        If ``K`` is zero (no intrinsics), the image size is zero, a matrix has the wrong
        size, or ``K``, ``D``, ``R`` or ``P`` holds NaN or infinity.
    """
    try:
        K = np.asarray(msg.k, float).reshape(3, 3)
        P = np.asarray(msg.p, float).reshape(3, 4)
        R = np.asarray(msg.r, float).reshape(3, 3)
        D = np.asarray(msg.d, float).ravel()
    except ValueError as exc:
        raise InputError(f'malformed CameraInfo: {exc}') from exc
    for name, arr in (('K', K), ('D', D), ('R', R), ('P', P)):
        if not np.all(np.isfinite(arr)):
            raise InputError(f'CameraInfo {name} holds NaN or infinity; publish a calibrated '
                             'CameraInfo (camera_calibration) or pass a calibration file')
    if K[0, 0] <= 0 or K[1, 1] <= 0 or msg.width <= 0 or msg.height <= 0:
        raise InputError('CameraInfo has no intrinsics (K is zero) or no image size')
    if not np.any(R):
        R = np.eye(3)
    return CameraModel(int(msg.width), int(msg.height), K, D, R,
                       P if np.any(P) else None, str(msg.distortion_model or 'plumb_bob'))


def same_model(a: CameraModel, b: CameraModel) -> bool:
    """True if two camera models describe the same calibration."""
    return ((a.width, a.height) == (b.width, b.height)
            and np.array_equal(np.asarray(a.K), np.asarray(b.K))
            and np.array_equal(np.asarray(a.D), np.asarray(b.D))
            and np.array_equal(a.projection(), b.projection()))
