"""A point-cloud map that follows the alignment's corrections (ROS-free):
:class:`KeyframeCloudMap`.

Each keyframe's cloud is kept in the keyframe's own frame ``kf`` (the frame its points are
given in; :mod:`ga_ros.pipeline.cloud_map` gives them in the keyframe's ``base_link``),
decimated once, when it arrives (a voxel grid of ``keyframe_voxel_m`` in that frame, then at
most ``max_points_per_keyframe`` points, evenly strided), together with its pose ``T_map_kf``
(``p_map = T_map_kf @ p_kf``).
The map is a voxel grid of ``voxel_m`` in ``map`` (:class:`ga_ros.mapping.voxels.
VoxelAccumulator`): every placed keyframe adds its points' per-voxel sums and remembers the
slots they went to, so that re-anchoring a keyframe (:meth:`KeyframeCloudMap.set_poses`)
subtracts its old contribution (recomputed from its points and old pose: the same arrays, bit
for bit, as when it was added) and adds the new one. An update therefore costs time proportional
to the points of the keyframes it moves, not to the size of the map; a keyframe whose pose is
unchanged costs nothing. The map's points (:meth:`KeyframeCloudMap.cloud`) are the voxels'
centroids, each with its mean intensity: the same, up to float rounding, as a map built from
scratch from the same poses.

Memory is bounded: at most ``max_live_keyframes`` keyframes keep their points; beyond, the most
settled keyframe joins the **static layer**: its contribution stays in the voxel grid, its
points and per-voxel sums are dropped, and later corrections of it are counted
(``static_moves_ignored``) and not applied. The most settled is the one whose last move by more
than ``settle_voxels`` voxels (the largest shift of its points: translation plus rotation angle
times its farthest point's range) is the oldest, counted in pose updates
(:meth:`KeyframeCloudMap.set_poses` calls: one per corrections message); placing a keyframe or
replacing its cloud counts as a move, smaller corrections are applied but do not count. A
keyframe that keeps moving (a track a background refinement, a loop closure or a fix still
corrects, however old) therefore stays live while others have settled. The voxel sums do not
depend on the order of the keyframes, so any order of merging gives the same map. A merge of a
keyframe that moved within the last ``settle_updates`` updates (none had settled) keeps the
bound all the same and is counted (``static_forced``; ``static_settled`` the others).

Clouds without a pose yet wait (at most ``max_unplaced_clouds``, oldest dropped first, counted),
as do poses without a cloud yet (at most ``max_pending_poses``).

Keyframes are named by an integer key chosen by the caller (the keyframe's stamp in ns, for
``ga/keyframe_cloud`` and ``ga/corrections`` alike: :mod:`ga_ros.pipeline.cloud_map`).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.core.config_ranges import check_ranges, ranged
from ga_ros.errors import InputError
from ga_ros.mapping.voxels import Contribution, VoxelAccumulator, contribution, downsample


@dataclass(frozen=True)
class CloudMapConfig:
    """Settings of :class:`KeyframeCloudMap` (``map_node`` parameters of the same names).

    Attributes
    ----------
    voxel_m : edge of the map's voxels in ``map`` (m); one point (the centroid) per voxel.
    keyframe_voxel_m : edge of the voxels that decimate each keyframe's cloud in its own frame
        when it arrives (m; 0: no voxel decimation).
    max_points_per_keyframe : points kept per keyframe after that (evenly strided; 0: all).
    max_range_m : points of a keyframe farther than this from its frame's origin are dropped
        (m; 0: no limit).
    max_live_keyframes : keyframes that keep their points and can be re-anchored; beyond, the
        most settled joins the static layer (module docstring; 0: no limit).
    settle_updates : pose updates a keyframe must go without moving by more than
        ``settle_voxels`` to count as settled when it is merged (``static_settled``, else
        ``static_forced``).
    settle_voxels : a move smaller than this (voxels of ``voxel_m``: the largest shift of the
        keyframe's points) does not unsettle a keyframe; it is applied all the same.
    max_unplaced_clouds : clouds waiting for their keyframe's pose; beyond, the oldest is
        dropped (counted).
    max_pending_poses : poses waiting for their keyframe's cloud; beyond, the oldest is dropped.
    """

    voxel_m: float = ranged(0.2, 1e-4, 1e4)
    keyframe_voxel_m: float = ranged(0.1, 0.0, 1e4)
    max_points_per_keyframe: int = ranged(20000, 0, 10**8)
    max_range_m: float = ranged(0.0, 0.0, 1e6)
    max_live_keyframes: int = ranged(5000, 0, 10**8)
    settle_updates: int = ranged(5, 0, 10**8)
    settle_voxels: float = ranged(0.25, 0.0, 1e6)
    max_unplaced_clouds: int = ranged(200, 1, 10**7)
    max_pending_poses: int = ranged(100000, 1, 10**8)

    def __post_init__(self) -> None:
        check_ranges(self)


@dataclass(frozen=True)
class MapCloud:
    """Points of a map.

    Attributes
    ----------
    points : (n, 3) float32 ``x y z`` (m) in ``map``.
    intensity : (n,) float32 mean intensity of each point's voxel.
    """

    points: np.ndarray
    intensity: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])


@dataclass(frozen=True)
class MapUpdate:
    """What one :meth:`KeyframeCloudMap.set_poses` did.

    Attributes
    ----------
    moved : keyframes already placed whose pose changed (re-anchored).
    placed : keyframes placed for the first time (their cloud was waiting).
    unchanged : keyframes named with the pose they had (nothing done).
    pending : poses of keyframes without a cloud yet (kept for when it comes).
    static_ignored : keyframes of the static layer named (not moved).
    points : points whose contribution was subtracted or added (the work done).
    """

    moved: int = 0
    placed: int = 0
    unchanged: int = 0
    pending: int = 0
    static_ignored: int = 0
    points: int = 0


@dataclass
class _Keyframe:
    """One keyframe: its decimated cloud in its own frame, its pose and, once placed, the
    slots of the voxel grid its contribution went to (in key order)."""

    points: np.ndarray
    intensity: np.ndarray
    T_map_kf: FloatArray | None = None
    slots: IntArray | None = None
    #: the pose update of its last move beyond ``settle_voxels`` and its pose then
    moved_at: int = 0
    settled_pose: FloatArray | None = None
    #: the farthest point's range from the keyframe's origin (m)
    radius: float = 0.0

    def __post_init__(self) -> None:
        if len(self.points):
            self.radius = float(np.sqrt(np.max(np.einsum('ij,ij->i', self.points,
                                                         self.points, dtype=float))))


def transform_points(T_map_kf: FloatArray, points_kf: np.ndarray) -> FloatArray:
    """(n, 3) float64 ``p_map = R p_kf + t`` of (n, 3) points (m) and a (4, 4) pose."""
    T = np.asarray(T_map_kf, float)
    return np.asarray(points_kf, float) @ T[:3, :3].T + T[:3, 3]


class KeyframeCloudMap:
    """Keyframe clouds in their own frames, re-anchored by corrections (module docstring).

    Parameters
    ----------
    config : the settings.
    """

    def __init__(self, config: CloudMapConfig = CloudMapConfig()) -> None:
        self.config = config
        self.voxels = VoxelAccumulator()
        self._live: OrderedDict[int, _Keyframe] = OrderedDict()   # placed, by last move
        self._unplaced: OrderedDict[int, _Keyframe] = OrderedDict()
        self._pending: OrderedDict[int, FloatArray] = OrderedDict()
        self._static: set[int] = set()
        self.clouds_dropped = 0
        self.static_moves_ignored = 0
        #: pose updates so far (:meth:`set_poses` calls), the clock of settledness
        self.updates = 0
        #: keyframes merged into the static layer settled, and merged while still moving
        self.static_settled = 0
        self.static_forced = 0

    # ------------------------------------------------------------------ state
    @property
    def n_live(self) -> int:
        """Placed keyframes that keep their points."""
        return len(self._live)

    @property
    def n_static(self) -> int:
        """Keyframes merged into the static layer."""
        return len(self._static)

    @property
    def n_unplaced(self) -> int:
        """Clouds waiting for their pose."""
        return len(self._unplaced)

    @property
    def n_pending_poses(self) -> int:
        """Poses waiting for their cloud."""
        return len(self._pending)

    def keys(self) -> list[int]:
        """Keys of the placed keyframes that keep their points (most settled first: oldest last
        move beyond ``settle_voxels``)."""
        return list(self._live)

    def unplaced_keys(self) -> list[int]:
        """Keys of the clouds waiting for their pose (oldest arrival first)."""
        return list(self._unplaced)

    def keyframe_cloud(self, key: int) -> tuple[np.ndarray, np.ndarray] | None:
        """``(points, intensity)`` of a keyframe as kept (decimated, in its own frame), placed
        or waiting; None for an unknown or static keyframe."""
        kf = self._live.get(int(key)) or self._unplaced.get(int(key))
        return None if kf is None else (kf.points, kf.intensity)

    def pose(self, key: int) -> FloatArray | None:
        """``T_map_kf`` of a placed live keyframe (None otherwise)."""
        kf = self._live.get(int(key))
        return None if kf is None else kf.T_map_kf

    def nbytes(self) -> int:
        """Bytes of the points kept and of the voxel grid (Python objects not counted)."""
        n = self.voxels.nbytes
        for kf in list(self._live.values()) + list(self._unplaced.values()):
            n += kf.points.nbytes + kf.intensity.nbytes
            if kf.slots is not None:
                n += kf.slots.nbytes
        return n

    # ------------------------------------------------------------------ input
    def decimate(self, points_kf: np.ndarray, intensity: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
        """``(points, intensity)`` float32 of a keyframe's cloud as kept: finite points within
        ``max_range_m``, on the ``keyframe_voxel_m`` grid, at most ``max_points_per_keyframe``.

        Raises
        ------
        InputError
            Points that are not (n, 3), or a count of intensities that differs.
        """
        P = np.asarray(points_kf)
        inten = np.asarray(intensity).reshape(-1)
        if P.ndim != 2 or P.shape[1] != 3 or inten.shape[0] != P.shape[0]:
            raise InputError(f'a keyframe cloud needs (n, 3) points and (n,) intensities, got '
                             f'{P.shape} and {inten.shape}')
        c = self.config
        ok = np.all(np.isfinite(P), axis=1) & np.isfinite(inten)
        if c.max_range_m > 0:
            ok &= np.einsum('ij,ij->i', P, P, dtype=float) <= c.max_range_m ** 2
        P, inten = P[ok], inten[ok]
        if c.keyframe_voxel_m > 0 and len(P):
            P, inten = downsample(P, inten, c.keyframe_voxel_m)
        n_max = c.max_points_per_keyframe
        if n_max and len(P) > n_max:
            keep = np.linspace(0, len(P) - 1, n_max).round().astype(np.int64)
            P, inten = P[keep], inten[keep]
        return np.ascontiguousarray(P, np.float32), np.ascontiguousarray(inten, np.float32)

    def add_cloud(self, key: int, points_kf: np.ndarray, intensity: np.ndarray) -> bool:
        """A keyframe's cloud, (n, 3) in its own frame ``kf`` (m), with (n,) intensities.

        Placed at once if its pose came before, else kept until it comes. A second cloud of a
        keyframe replaces the first. Returns True when the map changed (placed).

        Raises
        ------
        InputError
            Bad shapes (:meth:`decimate`); nothing is changed.
        """
        key = int(key)
        P, inten = self.decimate(points_kf, intensity)
        kf = _Keyframe(P, inten)
        if key in self._static:
            self.static_moves_ignored += 1
            return False
        old = self._live.pop(key, None)
        if old is not None:
            self._unplace(old)
            kf.T_map_kf = old.T_map_kf
        self._unplaced.pop(key, None)
        T = self._pending.pop(key, None) if kf.T_map_kf is None else kf.T_map_kf
        if T is None:
            self._unplaced[key] = kf
            while len(self._unplaced) > self.config.max_unplaced_clouds:
                self._unplaced.popitem(last=False)
                self.clouds_dropped += 1
            return False
        self._place(key, kf, T)
        self._bound_live()
        return True

    def set_poses(self, keys: IntArray | list[int], T_map_kf: FloatArray) -> MapUpdate:
        """Re-anchor the keyframes named (and only them): ``T_map_kf`` (k, 4, 4) their new
        poses, in order (a key named twice: the last pose wins).

        Raises
        ------
        InputError
            Shapes that do not match, or a pose that is not finite (nothing is changed).
        """
        keys = np.asarray(keys, np.int64).reshape(-1)
        T = np.asarray(T_map_kf, float).reshape(-1, 4, 4)
        if T.shape[0] != keys.size:
            raise InputError(f'{keys.size} keyframes but {T.shape[0]} poses')
        if not np.all(np.isfinite(T)):
            raise InputError('a keyframe pose holds NaN or infinity')
        moved = placed = unchanged = pending = static = points = 0
        self.updates += 1
        last = {int(k): i for i, k in enumerate(keys.tolist())}
        for key, i in last.items():
            Ti = T[i]
            kf = self._live.get(key)
            if kf is not None:
                if np.array_equal(kf.T_map_kf, Ti):
                    unchanged += 1
                    continue
                points += 2 * len(kf.points)
                self._unplace(kf)
                settled_pose, moved_at = kf.settled_pose, kf.moved_at
                self._place(key, kf, Ti)
                if self._shift_m(kf, settled_pose, Ti) <= \
                        self.config.settle_voxels * self.config.voxel_m:
                    kf.settled_pose, kf.moved_at = settled_pose, moved_at
                else:
                    self._live.move_to_end(key)
                moved += 1
            elif key in self._unplaced:
                kf = self._unplaced.pop(key)
                self._place(key, kf, Ti)
                points += len(kf.points)
                placed += 1
            elif key in self._static:
                static += 1
            else:
                self._pending[key] = Ti.copy()
                self._pending.move_to_end(key)
                while len(self._pending) > self.config.max_pending_poses:
                    self._pending.popitem(last=False)
                pending += 1
        self.static_moves_ignored += static
        self._bound_live()
        return MapUpdate(moved, placed, unchanged, pending, static, points)

    def unplace_all(self) -> None:
        """Every live keyframe loses its pose (its cloud waits for a new one) and the poses
        waiting are forgotten: what a full corrections message starts with. The static layer
        stays (:meth:`clear_static` removes it)."""
        for key, kf in list(self._live.items()):
            self._unplace(kf)
            kf.T_map_kf = None
            self._unplaced[key] = kf
        self._live.clear()
        self._pending.clear()
        while len(self._unplaced) > self.config.max_unplaced_clouds:
            self._unplaced.popitem(last=False)
            self.clouds_dropped += 1

    def clear_static(self) -> None:
        """Drop the static layer (after a reset of the alignment: a new survey). Live keyframes
        are put back on a fresh grid."""
        self._static.clear()
        self.voxels.clear()
        for kf in self._live.values():
            assert kf.T_map_kf is not None
            kf.slots = self.voxels.add(self._contribution(kf, kf.T_map_kf)).astype(np.int32)

    def freeze(self, keys: IntArray | list[int]) -> int:
        """Merge these placed keyframes into the static layer now; returns how many."""
        n = 0
        for key in np.asarray(keys, np.int64).reshape(-1).tolist():
            kf = self._live.pop(int(key), None)
            if kf is not None:
                self._static.add(int(key))
                n += 1
        return n

    # ------------------------------------------------------------------ output
    def cloud(self) -> MapCloud:
        """The map: one point per occupied voxel (centroid, m, in ``map``) with its mean
        intensity, in voxel-key order."""
        P, inten = self.voxels.centroids()
        return MapCloud(P, inten)

    # ------------------------------------------------------------------ internals
    def _contribution(self, kf: _Keyframe, T_map_kf: FloatArray) -> Contribution:
        return contribution(transform_points(T_map_kf, kf.points), kf.intensity,
                            self.config.voxel_m)

    def _place(self, key: int, kf: _Keyframe, T_map_kf: FloatArray) -> None:
        """Add the keyframe's contribution at this pose; it counts as a move (settledness)."""
        kf.T_map_kf = np.array(T_map_kf, float)
        kf.slots = self.voxels.add(self._contribution(kf, kf.T_map_kf)).astype(np.int32)
        kf.settled_pose, kf.moved_at = kf.T_map_kf, self.updates
        self._live[key] = kf

    @staticmethod
    def _shift_m(kf: _Keyframe, T_old: FloatArray | None, T_new: FloatArray) -> float:
        """An upper bound of how far any point of the keyframe moves between two poses (m):
        the translation plus the rotation angle times the farthest point's range (infinite
        without an old pose)."""
        if T_old is None:
            return float('inf')
        dR = T_old[:3, :3].T @ T_new[:3, :3]
        angle = float(np.arccos(np.clip((np.trace(dR) - 1.0) / 2.0, -1.0, 1.0)))
        return float(np.linalg.norm(T_new[:3, 3] - T_old[:3, 3])) + angle * kf.radius

    def _unplace(self, kf: _Keyframe) -> None:
        if kf.slots is not None and kf.T_map_kf is not None:
            self.voxels.remove(self._contribution(kf, kf.T_map_kf), kf.slots)
        kf.slots = None

    def _bound_live(self) -> None:
        n_max = self.config.max_live_keyframes
        while n_max and len(self._live) > n_max:
            key, kf = self._live.popitem(last=False)   # moved longest ago
            self._static.add(key)
            if self.updates - kf.moved_at >= self.config.settle_updates:
                self.static_settled += 1
            else:
                self.static_forced += 1


def map_from_poses(config: CloudMapConfig, keys: IntArray | list[int],
                   T_map_kf: FloatArray, clouds: dict[int, tuple[np.ndarray, np.ndarray]]
                   ) -> KeyframeCloudMap:
    """A map built at once from poses and clouds (``clouds[key] = (points_kf, intensity)``;
    keyframes without a cloud are skipped)."""
    m = KeyframeCloudMap(config)
    keys = np.asarray(keys, np.int64).reshape(-1)
    T = np.asarray(T_map_kf, float).reshape(-1, 4, 4)
    for i, key in enumerate(keys.tolist()):   # one at a time: nothing waits, nothing dropped
        if key in clouds:
            m.add_cloud(key, *clouds[key])
            m.set_poses([key], T[i:i + 1])
    return m
