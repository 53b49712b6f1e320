"""The point-cloud map as ``map_node`` and the replay drive it (ROS-free):
:class:`CloudMapBuilder`.

Inputs, in any order:

* **keyframe clouds** (``ga/keyframe_cloud``: points in the camera's frame, stamped with the
  keyframe's stamp): turned into the keyframe's ``base_link`` frame with the camera's extrinsic
  (``base_frame -> header.frame_id`` from ``/tf_static``, else ``T_base_camera``, else the
  identity when ``assume_identity_extrinsic``: :class:`ga_ros.core.extrinsic.ExtrinsicConfig`,
  as ``vo_node`` resolves it) and kept under the keyframe's stamp; a cloud that comes before
  the extrinsic is known waits (at most ``max_waiting``, oldest dropped) and is taken when a
  ``/tf_static`` message brings it;
* **corrections** (``ga/corrections``, :mod:`ga_ros.pipeline.corrections`): applied to the
  poses held (:class:`~ga_ros.pipeline.corrections.HeldPoses`, the shared convention: entries
  and the keyframes interpolated inside spans), each ``T_map_base`` under its stamp; a full
  message (opened by the ``ga/full_path`` marker) first unplaces every keyframe (an empty one, a
  reset, also drops the static layer);
* **the corrected path** (``ga/corrected_path``, every keyframe): used until the first
  corrections message (a map node started after the alignment node gets the transient-local
  path, not the corrections sent before it joined); from then on the corrections alone move the
  map.

Keyframes are named by their stamp (ns): the key the clouds and the poses share. The first two
keyframes of a survey share one stamp in the path and the corrections (the measurement encoding
stamps a motion at its destination: the first keyframe gets the second's stamp): when a message
names a stamp twice, its first pose is the keyframe before, and it goes to the newest cloud
waiting with an older stamp (the first keyframe's own), remembered for later messages.

The map (:class:`ga_ros.mapping.cloud_map.KeyframeCloudMap`) re-anchors only the keyframes
named; :meth:`CloudMapBuilder.cloud` is the voxel map in ``map``.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.extrinsic import Extrinsic, ExtrinsicConfig, TransformTree
from ga_ros.errors import InputError, UnknownExtrinsicError
from ga_ros.mapping.cloud_map import (
    CloudMapConfig,
    KeyframeCloudMap,
    MapCloud,
    MapUpdate,
    transform_points,
)
from ga_ros.pipeline.corrections import CorrectionMessage, HeldPoses


@dataclass
class BuilderCounts:
    """What a :class:`CloudMapBuilder` received and did (the node's diagnostics).

    Attributes
    ----------
    clouds : keyframe clouds taken.
    clouds_dropped : clouds dropped while waiting for the camera's extrinsic.
    corrections : corrections messages taken.
    full : of them, full messages.
    paths : corrected paths taken (only before the first corrections message).
    moved : keyframe re-anchorings done.
    points_moved : points whose contribution was moved (the work).
    """

    clouds: int = 0
    clouds_dropped: int = 0
    corrections: int = 0
    full: int = 0
    paths: int = 0
    moved: int = 0
    points_moved: int = 0


@dataclass(frozen=True)
class Reanchored:
    """What a corrections message set: the keyframes' stamps (ns, sorted) and poses
    ``T_map_base`` (k, 4, 4) (its entries and the keyframes interpolated in its spans: what
    other consumers of the message, such as the mosaic, take), and the map's update."""

    stamps_ns: IntArray
    T_map_base: FloatArray
    update: MapUpdate


class CloudMapBuilder:
    """Keyframe clouds + corrections -> the voxel map in ``map`` (module docstring).

    Parameters
    ----------
    config : the map's settings.
    extrinsic : where the camera's pose in ``base_link`` comes from.
    max_waiting : clouds kept while the camera's extrinsic is unknown.
    """

    def __init__(self, config: CloudMapConfig = CloudMapConfig(),
                 extrinsic: ExtrinsicConfig = ExtrinsicConfig(), max_waiting: int = 50
                 ) -> None:
        self.map = KeyframeCloudMap(config)
        self.extrinsic_config = extrinsic
        self.tf_static = TransformTree()
        self._extrinsics: dict[str, Extrinsic] = {}
        self.counts = BuilderCounts()
        self.corrections_seen = False
        #: clouds waiting for the camera's extrinsic: (stamp, frame, points, intensity)
        self.waiting: deque[tuple[int, str, np.ndarray, np.ndarray]] = deque()
        self.max_waiting = max(1, int(max_waiting))
        #: why clouds wait ('' once the extrinsic is known)
        self.extrinsic_error = ''
        #: the map changed since :meth:`take_changed` last said so
        self.changed = False
        #: a stamp named twice -> the stamp of the keyframe its first pose is (module doc)
        self._alias: dict[int, int] = {}
        #: the poses held, as the corrections convention keeps them
        self.held = HeldPoses()

    def add_tf_static(self, msg: object) -> int:
        """Record a ``tf2_msgs/TFMessage`` of ``/tf_static`` and take the clouds that waited
        for it; returns the transforms taken."""
        n = self.tf_static.add_message(msg)
        waiting, self.waiting = self.waiting, deque()
        for item in waiting:
            self.add_cloud(*item)
        return n

    def set_extrinsic(self, extrinsic: Extrinsic) -> None:
        """Use this extrinsic for clouds in its ``camera_frame`` (one resolved elsewhere, e.g.
        by the replay's stereo front end)."""
        self._extrinsics[extrinsic.camera_frame] = extrinsic

    def extrinsic(self, camera_frame: str) -> Extrinsic:
        """The camera's extrinsic for clouds in ``camera_frame`` (resolved once, then kept).

        Raises
        ------
        UnknownExtrinsicError
            Neither ``/tf_static``, ``T_base_camera`` nor the identity (when asked for) gives it.
        """
        ext = self._extrinsics.get(camera_frame)
        if ext is None:
            cfg = self.extrinsic_config
            ext = cfg.resolve(self.tf_static.lookup(cfg.base_frame, camera_frame), camera_frame)
            self._extrinsics[camera_frame] = ext
        return ext

    def add_cloud(self, stamp_ns: int, camera_frame: str, points_cam: np.ndarray,
                  intensity: np.ndarray) -> bool:
        """A keyframe's cloud in ``camera_frame`` (m); True when the map changed.

        A cloud whose camera extrinsic is unknown waits (:attr:`extrinsic_error` says why)
        until :meth:`add_tf_static` brings it.

        Raises
        ------
        InputError
            Bad shapes, or a malformed ``T_base_camera``.
        """
        try:
            ext = self.extrinsic(camera_frame)
        except UnknownExtrinsicError as exc:
            self.extrinsic_error = str(exc)
            self.waiting.append((int(stamp_ns), camera_frame, np.asarray(points_cam),
                                 np.asarray(intensity)))
            while len(self.waiting) > self.max_waiting:
                self.waiting.popleft()
                self.counts.clouds_dropped += 1
            return False
        self.extrinsic_error = ''
        P = np.asarray(points_cam)
        if not ext.is_identity:
            P = transform_points(ext.T_base_cam, P)
        placed = self.map.add_cloud(int(stamp_ns), P, intensity)
        self.counts.clouds += 1
        self.changed |= placed
        return placed

    def on_corrections(self, msg: CorrectionMessage) -> Reanchored:
        """A corrections message, applied to the poses held
        (:meth:`~ga_ros.pipeline.corrections.HeldPoses.apply`: its entries and the keyframes
        inside its spans) and the keyframes it set re-anchored.

        Raises
        ------
        InputError
            A span the poses held cannot anchor: nothing is changed.
        """
        stamps, T = self.held.apply(msg)     # raises before changing anything
        self.corrections_seen = True
        self.counts.corrections += 1
        if msg.full:
            self.counts.full += 1
            self.map.unplace_all()
            if len(msg.stamps_ns) == 0:
                self.map.clear_static()
            self.changed = True
        return Reanchored(stamps, T, self._apply(stamps, T))

    def on_path(self, stamps_ns: IntArray, T_map_base: FloatArray) -> MapUpdate | None:
        """A corrected path (every keyframe, now the poses held); ignored (None) once
        corrections came.

        Raises
        ------
        InputError
            Shapes that do not match or a pose that is not finite: nothing is changed.
        """
        if self.corrections_seen:
            return None
        T = np.asarray(T_map_base, float).reshape(-1, 4, 4)
        if T.shape[0] != np.size(stamps_ns) or not np.all(np.isfinite(T)):
            raise InputError(f'a path of {np.size(stamps_ns)} stamps and {T.shape[0]} poses, '
                             'or a pose that is not finite: path dropped')
        self.counts.paths += 1
        self.held.set_poses(stamps_ns, T)
        return self._apply(stamps_ns, T)

    def set_poses(self, stamps_ns: IntArray, T_map_base: FloatArray) -> MapUpdate:
        """Re-anchor the keyframes named to these poses, whatever came before (e.g. the final
        poses at the end of a replay: only those that differ cost anything)."""
        return self._apply(stamps_ns, T_map_base)

    def _apply(self, stamps_ns: IntArray, T_map_base: FloatArray) -> MapUpdate:
        up = self.map.set_poses(self._unshared(stamps_ns), T_map_base)
        self.counts.moved += up.moved
        self.counts.points_moved += up.points
        self.changed |= bool(up.moved or up.placed)
        return up

    def keys(self, stamps_ns: IntArray) -> IntArray:
        """The keyframe keys of a message's poses as the map took them (a stamp named twice
        names, at its first pose, the keyframe before: module docstring), for other consumers
        of the same message (the mosaic)."""
        return self._unshared(stamps_ns)

    def _unshared(self, stamps_ns: IntArray) -> IntArray:
        """The keys of a message's poses: a stamp named twice names, at its first pose, the
        keyframe before (module docstring)."""
        keys = np.asarray(stamps_ns, np.int64).reshape(-1)
        if keys.size < 2:
            return keys
        uniq, counts = np.unique(keys, return_counts=True)
        shared = uniq[counts > 1]
        if shared.size == 0:
            return keys
        keys = keys.copy()
        for s in shared.tolist():
            alias = self._alias.get(s)
            if alias is None:
                older = [k for k in self.map.unplaced_keys() if k < s]
                if not older:
                    continue
                alias = self._alias[s] = max(older)
            keys[int(np.flatnonzero(keys == s)[0])] = alias
        return keys

    def take_changed(self) -> bool:
        """True once after each change of the map (what a periodic publisher asks)."""
        out, self.changed = self.changed, False
        return out

    def cloud(self) -> MapCloud:
        """The voxel map in ``map``."""
        return self.map.cloud()
