"""A sensor's extrinsic: motions and poses of a camera expressed for the robot's ``base_link``.

The stereo VO measures the motion of the left camera's optical frame (z forward, x right,
y down); REP 103/105 want the robot's ``base_link`` (x forward, z up). With the fixed extrinsic
``T_base_cam`` (the camera's pose in ``base_link``, as ``/tf_static`` gives it), a camera motion
``T_c1_c2`` is the base motion::

    T_b1_b2 = T_base_cam @ T_c1_c2 @ inv(T_base_cam)

and a right perturbation ``xi_c`` of the camera motion is ``xi_b = Ad(T_base_cam) xi_c`` of the
base motion (``T_bc exp(xi) T_cb = exp(Ad(T_bc) xi)``), so the covariance, order
``[x y z rx ry rz]``, is ``Ad cov Ad^T`` (:func:`ga_ros.geometry.se3.adjoint`). The camera's
integrated pose ``T_world_cam`` (world = the first camera frame) becomes ``T_odom_base`` with
``odom`` = the first base frame: ``T_odom_base = T_base_cam @ T_world_cam @ inv(T_base_cam)``.

The one place where this conversion is done: ``vo_node`` and the replay both use it (through
:class:`ga_ros.pipeline.stereo.StereoFrontEnd`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace

import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.core.measurement import Measurement
from ga_ros.errors import InputError, UnknownExtrinsicError
from ga_ros.geometry import se3, so3

#: Where an extrinsic came from (:attr:`Extrinsic.source`).
FROM_TF = 'tf_static'
FROM_PARAMETERS = 'parameters'
IDENTITY_ASSUMED = 'identity (assume_identity_extrinsic)'


@dataclass(frozen=True)
class Extrinsic:
    """The camera's pose in the robot's base frame.

    Attributes
    ----------
    T_base_cam : (4, 4) pose of the camera frame in ``base_frame`` (``p_base = T @ p_cam``).
    base_frame, camera_frame : the frame ids.
    source : :data:`FROM_TF`, :data:`FROM_PARAMETERS` or :data:`IDENTITY_ASSUMED`.
    """

    T_base_cam: FloatArray
    base_frame: str = 'base_link'
    camera_frame: str = ''
    source: str = FROM_PARAMETERS

    @property
    def is_identity(self) -> bool:
        """True when the camera frame is the base frame (the conversions change nothing)."""
        return bool(np.array_equal(self.T_base_cam, np.eye(4)))

    def motion(self, m: Measurement) -> Measurement:
        """A camera motion measurement as the base's (:func:`motion_to_base`; ``m`` itself
        for the identity)."""
        return m if self.is_identity else motion_to_base(m, self.T_base_cam)

    def pose(self, T_world_cam: FloatArray) -> FloatArray:
        """``T_odom_base`` of an integrated camera pose (:func:`pose_to_base`)."""
        if self.is_identity:
            return np.asarray(T_world_cam, float)
        return pose_to_base(T_world_cam, self.T_base_cam)

    def camera_pose(self, T_map_base: FloatArray) -> FloatArray:
        """The inverse of :meth:`pose`: ``T_world_cam`` of base poses (..., 4, 4)."""
        if self.is_identity:
            return np.asarray(T_map_base, float)
        return se3.inverse(self.T_base_cam) @ np.asarray(T_map_base, float) @ self.T_base_cam


def motion_to_base(m: Measurement, T_base_cam: FloatArray) -> Measurement:
    """The base motion and covariance of a camera motion measurement (module docstring).

    Parameters
    ----------
    m : motion ``T_c1_c2`` of the camera, covariance of its right perturbation.
    T_base_cam : (4, 4) the camera's pose in the base frame.

    Returns
    -------
    Measurement
        Same nodes, tracks, stamp and kind; ``T_b1_b2`` and ``Ad cov Ad^T``.
    """
    T_bc = np.asarray(T_base_cam, dtype=float)
    T = T_bc @ m.T_src_dst @ se3.inverse(T_bc)
    Ad = se3.adjoint(T_bc)
    cov = Ad @ np.asarray(m.cov, dtype=float) @ Ad.T
    return replace(m, z=se3.to_translation_rotvec(T), cov=0.5 * (cov + cov.T))


def pose_to_base(T_world_cam: FloatArray, T_base_cam: FloatArray) -> FloatArray:
    """``T_odom_base = T_base_cam @ T_world_cam @ inv(T_base_cam)`` (..., 4, 4): the camera's
    integrated pose (world = first camera frame) as the base's in ``odom`` (= first base)."""
    T_bc = np.asarray(T_base_cam, dtype=float)
    return T_bc @ np.asarray(T_world_cam, dtype=float) @ se3.inverse(T_bc)


def extrinsic_from_parameters(xyz: Sequence[float], rpy: Sequence[float] = (),
                              quat_xyzw: Sequence[float] = ()) -> FloatArray:
    """``T_base_cam`` from a translation (m) and either roll-pitch-yaw (rad, fixed axes x-y-z as
    ``tf2``'s ``setRPY``: ``R = Rz(yaw) Ry(pitch) Rx(roll)``) or a quaternion ``[x y z w]``.

    Raises
    ------
    InputError
        Not three translation values, not exactly one of three angles / four quaternion
        values, or a zero quaternion.
    """
    xyz = [float(v) for v in xyz]
    if len(xyz) != 3:
        raise InputError(f'T_base_camera xyz needs 3 values (m), got {xyz}')
    if bool(len(rpy)) == bool(len(quat_xyzw)):
        raise InputError('give the camera rotation as rpy (3 values, rad) or as a quaternion '
                         '(4 values, x y z w), not both or neither')
    if len(rpy):
        if len(rpy) != 3:
            raise InputError(f'T_base_camera rpy needs 3 values (rad), got {list(rpy)}')
        r, p, y = (float(v) for v in rpy)
        R = (so3.exp(np.array([0.0, 0.0, y])) @ so3.exp(np.array([0.0, p, 0.0]))
             @ so3.exp(np.array([r, 0.0, 0.0])))
        return se3.from_rt(R, np.array(xyz))
    q = np.asarray(quat_xyzw, dtype=float)
    if q.shape != (4,) or not np.linalg.norm(q) > 0:
        raise InputError(f'T_base_camera quaternion needs 4 values (x y z w), got {list(q)}')
    return se3.from_pos_quat(np.array(xyz), q / np.linalg.norm(q))


#: A REP 103 optical frame (z forward, x right, y down) in its body frame (x forward, y left,
#: z up): the rotation of ``camera_link -> camera_optical_frame`` (rpy -pi/2, 0, -pi/2).
R_BODY_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


@dataclass(frozen=True)
class ExtrinsicConfig:
    """Where the camera's extrinsic comes from (``vo_node`` parameters, ``config/vo.yaml``).

    Attributes
    ----------
    base_frame : the robot's base frame (REP 105 ``base_link``): the child of ``odom``.
    camera_frame : the left camera's (optical) frame; '' = the left image's
        ``header.frame_id``.
    T_base_camera : the camera's pose in ``base_frame`` when no ``/tf_static`` has it, in the
        convention of every ``T_base_<sensor>`` parameter: ``'x y z qx qy qz qw'`` (m,
        quaternion x y z w, as ``static_transform_publisher``), or ``'x y z roll pitch yaw'``
        (m, rad, ``R = Rz(yaw) Ry(pitch) Rx(roll)``); '' = from ``/tf_static`` only.
    assume_identity_extrinsic : with neither ``/tf_static`` nor ``T_base_camera``, take the
        camera frame as the base frame (poses are then the optical frame's: z forward);
        without it such a camera is refused (:meth:`resolve`).
    """

    base_frame: str = 'base_link'
    camera_frame: str = ''
    T_base_camera: str = ''
    assume_identity_extrinsic: bool = False

    def from_parameters(self, camera_frame: str = '') -> Extrinsic | None:
        """The extrinsic of ``T_base_camera`` (None when it is empty).

        Raises
        ------
        InputError
            ``T_base_camera`` is not 6 or 7 numbers.
        """
        text = self.T_base_camera.replace(',', ' ').split()
        if not text:
            return None
        try:
            v = [float(x) for x in text]
        except ValueError:
            raise InputError(f'T_base_camera must be numbers, got {self.T_base_camera!r}'
                             ) from None
        if len(v) == 6:
            T = extrinsic_from_parameters(v[:3], rpy=v[3:])
        elif len(v) == 7:
            T = extrinsic_from_parameters(v[:3], quat_xyzw=v[3:])
        else:
            raise InputError(f"T_base_camera needs 'x y z roll pitch yaw' or 'x y z qx qy qz qw'"
                             f', got {len(v)} numbers')
        return Extrinsic(T, self.base_frame, self.camera_frame or camera_frame, FROM_PARAMETERS)

    def resolve(self, T_base_cam_tf: FloatArray | None, camera_frame: str = '',
                parameter: str = 'T_base_camera',
                identity: str = 'assume_identity_extrinsic: true', in_bag: bool = False
                ) -> Extrinsic:
        """The extrinsic to use: ``/tf_static``'s (``T_base_cam_tf``, None when it has none),
        else the parameters', else the identity when said so (``assume_identity_extrinsic``).

        Parameters
        ----------
        T_base_cam_tf : (4, 4) ``base_frame -> camera`` from ``/tf_static``, or None.
        camera_frame : the camera's frame id (used unless :attr:`camera_frame` is set).
        parameter, identity : how the caller's user sets ``T_base_camera`` and
            ``assume_identity_extrinsic`` (named in the refusal; node parameters by default).
        in_bag : the ``/tf_static`` is a bag's (the refusal says to record it there).

        Raises
        ------
        UnknownExtrinsicError
            Neither ``/tf_static`` nor ``T_base_camera`` gives it and the identity was not
            asked for: the camera's poses would be published as the base's.
        InputError
            A malformed ``T_base_camera``.
        """
        cam = self.camera_frame or camera_frame
        if T_base_cam_tf is not None:
            return Extrinsic(np.asarray(T_base_cam_tf, float), self.base_frame, cam, FROM_TF)
        from_params = self.from_parameters(cam)
        if from_params is not None:
            return from_params
        if self.assume_identity_extrinsic:
            return Extrinsic(np.eye(4), self.base_frame, cam, IDENTITY_ASSUMED)
        raise unknown_extrinsic_error('camera', parameter, identity,
                                      frames=(self.base_frame, cam), in_bag=in_bag)


def unknown_extrinsic_error(sensor: str, parameter: str, identity: str,
                            tf_static: bool = True, frames: tuple[str, str] = ('', ''),
                            in_bag: bool = False) -> UnknownExtrinsicError:
    """The one-line refusal when a sensor's extrinsic is unknown: it names the ways to give it
    (``/tf_static`` when the caller reads it, the ``parameter`` ``T_base_<sensor>`` as
    ``'x y z qx qy qz qw'``, or ``identity`` to take the sensor frame as the base frame).

    ``frames`` (base frame, sensor frame) name the missing transform when known; ``in_bag``:
    the ``/tf_static`` read is a bag's."""
    base, child = frames
    edge = f'{base} -> {child}' if base and child else f'base_frame -> {sensor} frame'
    ways = ([f'publish {edge} on /tf_static' + (' (recorded in the bag)' if in_bag else '')]
            if tf_static else []) + [
        f"set {parameter} ('x y z qx qy qz qw': m, quaternion x y z w)",
        f'say {identity} (the {sensor} frame is the base frame)']
    return UnknownExtrinsicError(f'{sensor} extrinsic unknown: ' + ', or '.join(ways))


def renamed_parameter_error(old: str, new: str) -> InputError:
    """A parameter of the old extrinsic convention was given: say the new name."""
    return InputError(f"{old} is now {new} ('x y z qx qy qz qw': m, quaternion x y z w)")


def pose_text(T: FloatArray) -> str:
    """``'x y z qx qy qz qw'`` of a (4, 4) pose: the ``T_base_<sensor>`` parameter text."""
    p, q = se3.to_pos_quat(np.asarray(T, float))
    return ' '.join(f'{float(v):.12g}' for v in (*p, *q))


class TransformTree:
    """Static transforms (``/tf_static``) and the lookup of one frame in another (a tree: each
    child has one parent). The one reader of ``/tf_static`` messages: the camera's extrinsic
    (``vo_node``, the stereo replay) and the absolute sensors' lever arms
    (:mod:`ga_ros.inputs.absolute`) all look their ``base_frame -> sensor_frame`` chain up
    here."""

    def __init__(self) -> None:
        self._parent: dict[str, tuple[str, FloatArray]] = {}

    def add(self, parent: str, child: str, T_parent_child: FloatArray) -> None:
        """Record ``parent -> child`` (a later one for the same child replaces it)."""
        self._parent[child.lstrip('/')] = (parent.lstrip('/'), np.asarray(T_parent_child, float))

    def add_message(self, msg: object) -> int:
        """Record every transform of a ``tf2_msgs/TFMessage`` (rclpy or rosbags message, read by
        field name; quaternions normalised); returns how many. A transform with a non-finite
        value or a zero quaternion is skipped (not counted)."""
        n = 0
        for t in getattr(msg, 'transforms', ()):
            tr, q = t.transform.translation, t.transform.rotation
            p = np.array([tr.x, tr.y, tr.z], float)
            quat = np.array([q.x, q.y, q.z, q.w], float)
            if not (np.isfinite(p).all() and np.isfinite(quat).all()
                    and np.linalg.norm(quat) > 1e-9):
                continue
            self.add(str(t.header.frame_id), str(t.child_frame_id), se3.from_pos_quat(p, quat))
            n += 1
        return n

    def __len__(self) -> int:
        return len(self._parent)

    def _to_root(self, frame: str) -> tuple[str, FloatArray]:
        T = np.eye(4)
        seen = {frame}
        while frame in self._parent:
            parent, T_pc = self._parent[frame]
            T = T_pc @ T
            frame = parent
            if frame in seen:
                raise InputError(f'/tf_static has a loop through {frame!r}')
            seen.add(frame)
        return frame, T

    def lookup(self, target: str, source: str) -> FloatArray | None:
        """``T_target_source`` (pose of ``source`` in ``target``), None if not connected."""
        target, source = target.lstrip('/'), source.lstrip('/')
        if not target or not source:
            return None
        root_t, T_root_target = self._to_root(target)
        root_s, T_root_source = self._to_root(source)
        if root_t != root_s:
            return None
        return se3.inverse(T_root_target) @ T_root_source
