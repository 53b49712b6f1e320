"""Stereo calibration: rectified intrinsics and baseline, with rectification of raw images.

A :class:`CameraModel` mirrors ``sensor_msgs/CameraInfo`` (``K``, ``D``, ``R``, ``P``) without
importing ROS. :meth:`StereoCalibration.from_camera_models` decides whether the images need
rectifying: a camera is rectified when its distortion is zero and ``R`` is the identity
(then ``P[:3, :3]`` is used as is); otherwise undistort-rectify maps are built from
``K, D, R, P`` (``cv2.initUndistortRectifyMap``), as for real cameras with lens distortion.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError
from ga_ros.runtime import lazy_import

cv2 = lazy_import('cv2')  # only rectification needs it (start-up of the command line)


@dataclass(frozen=True)
class CameraModel:
    """One camera's calibration, field for field as in ``sensor_msgs/CameraInfo``.

    Attributes
    ----------
    width, height : image size (px).
    K : (3, 3) raw intrinsics.
    D : (k,) distortion coefficients (``plumb_bob``: k1 k2 t1 t2 k3); empty or zeros: none.
    R : (3, 3) rectification rotation.
    P : (3, 4) projection of the rectified camera; ``P[0, 3] = -fx' * baseline`` on the right.
    distortion_model : ``'plumb_bob'``, ``'rational_polynomial'`` or ``'equidistant'``.
    """

    width: int
    height: int
    K: FloatArray
    D: FloatArray = field(default_factory=lambda: np.zeros(0))
    R: FloatArray = field(default_factory=lambda: np.eye(3))
    P: FloatArray | None = None
    distortion_model: str = 'plumb_bob'

    def projection(self) -> FloatArray:
        """(3, 4) ``P``, defaulting to ``[K | 0]``."""
        if self.P is None:
            return np.hstack([np.asarray(self.K, float), np.zeros((3, 1))])
        return np.asarray(self.P, float).reshape(3, 4)

    def is_rectified(self) -> bool:
        """True when the images need no undistortion or rectification."""
        D = np.asarray(self.D, float).ravel()
        R = np.asarray(self.R, float).reshape(3, 3)
        same_k = np.allclose(self.projection()[:3, :3], np.asarray(self.K, float).reshape(3, 3),
                             rtol=1e-6, atol=1e-6)
        return (D.size == 0 or not np.any(D)) and np.allclose(R, np.eye(3)) and same_k


@dataclass(frozen=True)
class StereoCalibration:
    """Rectified stereo geometry plus (optional) rectification maps.

    Attributes
    ----------
    width, height : image size (px).
    K : (3, 3) intrinsics of the rectified left (and right) image.
    baseline_m : baseline (m).
    maps_left, maps_right : ``cv2.remap`` tables in fixed point (``cv2.convertMaps`` to
        ``CV_16SC2``: 1/32 px interpolation), or None when the input is already rectified.
    """

    width: int
    height: int
    K: FloatArray
    baseline_m: float
    maps_left: tuple[np.ndarray, np.ndarray] | None = None
    maps_right: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def needs_rectification(self) -> bool:
        """True when :meth:`rectify` remaps the images."""
        return self.maps_left is not None

    @staticmethod
    def rectified(width: int, height: int, K: FloatArray, baseline_m: float) -> StereoCalibration:
        """Calibration of an already rectified pair."""
        K = np.asarray(K, float).reshape(3, 3)
        if width <= 0 or height <= 0 or baseline_m <= 0 or K[0, 0] <= 0 or K[1, 1] <= 0:
            raise InputError('stereo calibration needs positive size, focal length and baseline')
        return StereoCalibration(int(width), int(height), K, float(baseline_m))

    @staticmethod
    def from_camera_models(left: CameraModel, right: CameraModel) -> StereoCalibration:
        """Calibration from the two CameraInfo-like models (see module doc).

        Raises
        ------
        InputError
            Sizes differ, the baseline is not positive, or the matrices are malformed.
        """
        if (left.width, left.height) != (right.width, right.height):
            raise InputError(f'left camera is {left.width}x{left.height}, '
                             f'right camera is {right.width}x{right.height}')
        try:
            Pl, Pr = left.projection(), right.projection()
        except ValueError as exc:
            raise InputError(f'malformed projection matrix: {exc}') from exc
        if not (np.all(np.isfinite(Pl)) and np.all(np.isfinite(Pr))):
            raise InputError('camera matrices must be finite')
        if Pr[0, 0] <= 0:
            raise InputError('right projection has a non-positive focal length')
        baseline = -Pr[0, 3] / Pr[0, 0]
        if not baseline > 0:
            raise InputError(f'stereo baseline from P_right[0, 3] is {baseline:g} m; '
                             'expected a positive baseline (right camera to the right)')
        K = Pl[:3, :3].copy()
        if left.is_rectified() and right.is_rectified():
            return StereoCalibration.rectified(left.width, left.height, K, baseline)
        size = (int(left.width), int(left.height))
        maps = []
        for cam, P in ((left, Pl), (right, Pr)):
            Kc = np.asarray(cam.K, float).reshape(3, 3)
            D = np.asarray(cam.D, float).ravel()
            R = np.asarray(cam.R, float).reshape(3, 3)
            if cam.distortion_model == 'equidistant':
                mx, my = cv2.fisheye.initUndistortRectifyMap(Kc, D[:4], R, P[:3, :3], size,
                                                             cv2.CV_32FC1)
            else:
                mx, my = cv2.initUndistortRectifyMap(Kc, D if D.size else None, R, P[:3, :3],
                                                     size, cv2.CV_32FC1)
            maps.append(cv2.convertMaps(mx, my, cv2.CV_16SC2))  # fixed point: ~2x faster remap
        return StereoCalibration(size[0], size[1], K, float(baseline), maps[0], maps[1])

    def rectify(self, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Undistort and rectify a raw pair (identity when already rectified)."""
        return self.rectify_one(left, 'left'), self.rectify_one(right, 'right')

    def rectify_one(self, image: np.ndarray, side: str) -> np.ndarray:
        """Undistort and rectify one raw image of ``side`` (``'left'``/``'right'``); the VO
        rectifies the right image only at keyframes, where it matches stereo."""
        maps = self.maps_left if side == 'left' else self.maps_right
        return image if maps is None else cv2.remap(image, *maps, cv2.INTER_LINEAR)


@dataclass(frozen=True)
class StereoModels:
    """The two camera models of a stereo rig (read from calibration files)."""

    left: CameraModel
    right: CameraModel


def _matrix(value: object, rows: int, cols: int, what: str) -> FloatArray:
    """A YAML matrix (a flat or nested list, or ``{rows, cols, data}``) -> (rows, cols)."""
    if isinstance(value, dict):
        value = value.get('data')
    try:
        out = np.asarray(value, float).reshape(rows, cols)
    except (TypeError, ValueError) as exc:
        raise InputError(f'calibration: {what} is not a {rows}x{cols} matrix: {exc}') from exc
    if not np.all(np.isfinite(out)):
        raise InputError(f'calibration: {what} holds NaN or infinity')
    return out


def _camera_info_fields(d: dict, what: str) -> CameraModel:
    """A ``sensor_msgs/CameraInfo``-like mapping (``width height k d r p distortion_model``,
    or camera_calibration's ``image_width camera_matrix ...``) -> model."""
    w = d.get('width', d.get('image_width'))
    h = d.get('height', d.get('image_height'))
    K = _matrix(d.get('k', d.get('camera_matrix')), 3, 3, f'{what} k')
    D_value = d.get('d', d.get('distortion_coefficients')) or []
    if isinstance(D_value, dict):
        D_value = D_value.get('data') or []
    D = np.asarray(D_value, float).ravel()
    R = d.get('r', d.get('rectification_matrix'))
    P = d.get('p', d.get('projection_matrix'))
    if not isinstance(w, int) or not isinstance(h, int) or w <= 0 or h <= 0:
        raise InputError(f'calibration: {what} needs a positive integer width and height')
    return CameraModel(w, h, K, D, np.eye(3) if R is None else _matrix(R, 3, 3, f'{what} r'),
                       None if P is None else _matrix(P, 3, 4, f'{what} p'),
                       str(d.get('distortion_model', 'plumb_bob')))


def _euroc_sensor(d: dict, what: str) -> tuple[dict, FloatArray]:
    """An EuRoC ``sensor.yaml`` (pinhole, radial-tangential) -> CameraInfo-like fields and
    ``T_body_cam`` (4, 4)."""
    if d.get('camera_model', 'pinhole') != 'pinhole':
        raise InputError(f'calibration: {what}: camera_model {d.get("camera_model")!r} is not '
                         'supported (pinhole only)')
    if d.get('distortion_model', 'radial-tangential') != 'radial-tangential':
        raise InputError(f'calibration: {what}: unsupported distortion_model '
                         f'{d.get("distortion_model")!r} (radial-tangential only; give the '
                         'CameraInfo fields instead)')
    model = 'plumb_bob'
    fu, fv, cu, cv = (float(x) for x in d['intrinsics'])
    w, h = (int(x) for x in d['resolution'])
    fields_ = {'width': w, 'height': h, 'k': [fu, 0, cu, 0, fv, cv, 0, 0, 1],
               'd': list(d.get('distortion_coefficients', [])), 'distortion_model': model}
    return fields_, _matrix(d['T_BS'], 4, 4, f'{what} T_BS')


def read_stereo_calibration(paths: list[str]) -> StereoModels:
    """Stereo camera models from calibration files, for bags without ``CameraInfo``.

    Accepted forms:

    * two EuRoC ``sensor.yaml`` files (left then right camera: ``intrinsics``, ``resolution``,
      ``distortion_coefficients``, ``T_BS``); the rectification (``R``, ``P`` of each camera)
      is computed with ``cv2.stereoRectify`` from the two body-to-camera poses;
    * one YAML with ``left`` and ``right`` mappings of ``sensor_msgs/CameraInfo`` fields
      (``width height k d r p distortion_model``; camera_calibration's ``image_width
      camera_matrix distortion_coefficients rectification_matrix projection_matrix`` too);
    * two such CameraInfo-like YAML files (left then right).

    Raises
    ------
    InputError
        Unreadable files, missing fields, or an inconsistent rig.
    """
    import yaml

    docs = []
    for p in paths:
        try:
            with open(p) as fh:
                text = fh.read()
            if text.startswith('%YAML'):  # EuRoC files start with an OpenCV-style directive
                text = text.split('\n', 1)[1]
            docs.append(yaml.safe_load(text))
        except (OSError, yaml.YAMLError) as exc:
            raise InputError(f'cannot read calibration file {p}: {exc}') from exc
    try:
        if len(docs) == 1 and isinstance(docs[0], dict) and {'left', 'right'} <= set(docs[0]):
            return StereoModels(_camera_info_fields(docs[0]['left'], 'left'),
                                _camera_info_fields(docs[0]['right'], 'right'))
        if len(docs) != 2 or not all(isinstance(d, dict) for d in docs):
            raise InputError('calibration: expected two files (left, right camera) or one YAML '
                             'with left and right CameraInfo fields')
        if all('T_BS' in d for d in docs):
            return _rectify_euroc(*docs)
        return StereoModels(_camera_info_fields(docs[0], paths[0]),
                            _camera_info_fields(docs[1], paths[1]))
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(f'calibration: missing or malformed field {exc}') from exc


def _rectify_euroc(d_left: dict, d_right: dict) -> StereoModels:
    (fl, T_b_l), (fr, T_b_r) = _euroc_sensor(d_left, 'left'), _euroc_sensor(d_right, 'right')
    if (fl['width'], fl['height']) != (fr['width'], fr['height']):
        raise InputError('calibration: the two cameras have different resolutions')
    T_r_l = np.linalg.inv(T_b_r) @ T_b_l  # x_right = T_r_l x_left
    K_l, K_r = (np.asarray(f['k'], float).reshape(3, 3) for f in (fl, fr))
    D_l, D_r = (np.asarray(f['d'], float) for f in (fl, fr))
    size = (fl['width'], fl['height'])
    R1, R2, P1, P2, *_ = cv2.stereoRectify(K_l, D_l, K_r, D_r, size,
                                           np.ascontiguousarray(T_r_l[:3, :3]),
                                           T_r_l[:3, 3].reshape(3, 1).copy(),
                                           flags=cv2.CALIB_ZERO_DISPARITY, alpha=0)
    if P2[0, 3] > 0:
        raise InputError('calibration: the second camera is left of the first; pass the left '
                         'camera first')
    return StereoModels(CameraModel(size[0], size[1], K_l, D_l, R1, P1, fl['distortion_model']),
                        CameraModel(size[0], size[1], K_r, D_r, R2, P2, fr['distortion_model']))
