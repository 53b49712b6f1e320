"""The live photomosaic of a downward camera as ``map_node`` drives it (ROS-free):
:class:`LiveMosaic`.

Inputs, in any order: keyframe images (the rectified left image, its intrinsics ``K`` and the
camera's extrinsic ``T_base_cam``, under the keyframe's stamp), keyframe clouds (points in the
camera's frame, with the same extrinsic) and keyframe poses ``T_map_base`` (from the
corrections or the corrected path, by stamp). Frames and the pixel convention are those of
:mod:`ga_ros.mapping.mosaic`: ``T_map_cam = T_map_base @ T_base_cam`` in the optical convention;
the mosaic is seen from above with ``x`` to the right, whichever way ``map``'s ``z`` points
(decided by the first keyframe placed, :func:`ga_ros.mapping.mosaic.looks_along_minus_z`).

The mosaic lives on one unbounded grid of ``metres_per_pixel`` whose pixel ``(row, col)`` has
its centre at ``x = (col + 0.5) * m`` and ``y = -(row + 0.5) * m`` (``z`` up) or
``y = (row + 0.5) * m`` (``z`` down); rows and columns may be negative. It is cut into square
tiles of ``tile_px``. Each placed keyframe keeps its warped patch
(:func:`ga_ros.mapping.mosaic.warp_view`, the offline mosaic's warp, rounded to ``uint8`` as
:func:`ga_ros.mapping.mosaic.build_mosaic` rounds it) and the tiles it touches. A keyframe is
re-warped when its pose changes or when the ground under it changes, and the tiles its old and
new patches touch are recomposited (``'last'`` blending: a later stamp covers an earlier one);
an update therefore costs in proportion to the keyframes it moved or whose ground it changed
(:attr:`MosaicCounts.warps`), not to the mosaic's size. :meth:`LiveMosaic.mosaic` assembles the
tiles over their bounding box (:class:`ga_ros.mapping.mosaic.Mosaic`, whose georeference is the
published one).

The ground, with ``ground_from_clouds`` (the default), is the offline mosaic's height model
(:mod:`ga_ros.mapping.surface`, cells of ``ground_cell_m``) of the keyframe clouds at their
current poses, kept by :class:`ga_ros.mapping.live_surface.LiveHeightGrid`: each image is
orthorectified, so the mosaic equals :func:`ga_ros.mapping.mosaic.build_mosaic` on
:func:`ga_ros.mapping.surface.ground_from_keyframe_points` of the same clouds and poses.
Keyframes wait until ground under them is known; pixels whose ground is unknown are left
uncovered. Without it the ground is the plane ``z = ground_z``.

Memory is bounded: the tiles' bounding box may not exceed ``max_pixels`` (a keyframe that would
grow it beyond is refused: :attr:`LiveMosaic.last_error` says what to change). Beyond
``max_live_keyframes`` placed keyframes, **settled** keyframes are **merged**, oldest (by stamp)
first: its pixels are pasted into the tiles' static base layer, its cloud's points into the
height model's static layer (:meth:`ga_ros.mapping.live_surface.LiveHeightGrid.merge`, which
changes no height), and its image, patch and points are released; so are the points of settled
older keyframes whose image never came. A keyframe is settled when its pose has not moved by
more than ``settle_px`` pixels on the ground (the largest shift of its footprint's border, at the
ground's lowest and highest heights) over the last ``settle_updates`` pose updates
(:meth:`LiveMosaic.set_poses` calls: one per corrections message); a keyframe without an image
yet, or whose footprint is unknown, counts any change of pose as a move. Keyframes that keep
moving (a track that a background refinement, a loop closure or a fix still corrects, however
old) stay live. When fewer keyframes are settled than must go, the bound is kept all the same:
the most settled (moved longest ago, then oldest) are merged and counted
(:attr:`MosaicCounts.merged_forced`; :attr:`MosaicCounts.merged_settled` the others).
``settle_updates`` 0 makes every keyframe settled: the oldest are merged.

The static layer keeps, per pixel, the stamp of the keyframe it shows, so that ``'last'``
blending holds whatever the order of the merges: a live keyframe covers a static pixel only where
its stamp is later than the pixel's, and a merge pastes only over earlier stamps. The mosaic is
therefore the one of every keyframe in stamp order, merged or live, and a merge changes no
pixel of the mosaic. What a keyframe holds while live, and a merged one
(its pose at the merge, 128 bytes), is :meth:`LiveMosaic.nbytes_by_part`; the static layers grow
with the area covered, not with the keyframes. A merged keyframe no longer moves: a later pose
of it that differs from its pose at the merge is ignored and counted
(:attr:`MosaicCounts.merged_moves_ignored`, the largest shift in
:attr:`MosaicCounts.merged_max_shift_m`); the mosaic keeps it where it was merged. Its ground
stays in the height model as it was at the merge, so a live keyframe over it is orthorectified
on it as before; the height of a cell shared with live points is then approximate
(:mod:`ga_ros.mapping.live_surface`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.errors import InputError
from ga_ros.mapping.live_surface import LiveHeightGrid
from ga_ros.mapping.mosaic import (
    CameraView,
    Georeference,
    Mosaic,
    footprint,
    looks_along_minus_z,
    warp_view,
)
from ga_ros.mapping.surface import GroundPlane, HeightGrid, SurfaceConfig


@dataclass(frozen=True)
class MosaicMapConfig:
    """Settings of :class:`LiveMosaic` (``map_node`` declares them with the prefix
    ``mosaic_``).

    Attributes
    ----------
    enabled : build and publish the mosaic (needs keyframe images).
    metres_per_pixel : resolution (m/px); 0: the first keyframe's ground sample distance
        (height above the ground over the focal length), then fixed.
    ground_z : height of the ground plane in ``map`` (m), when not ``ground_from_clouds``.
    ground_from_clouds : orthorectify on the height model of the keyframe clouds (module
        docstring); else on the plane ``ground_z``.
    ground_cell_m : cell of that height model (m).
    ground_tolerance_m : a keyframe is re-warped for its ground only when a height under it
        moved by more than this since its warp, or a cell there became known or unknown (m;
        0: on any change, so the mosaic equals the offline one exactly).
    tile_px : edge of the tiles recomposited when a keyframe moves (px).
    max_pixels : largest mosaic (bounding box of the tiles, px); a keyframe that would exceed
        it is refused.
    max_live_keyframes : keyframes that keep their image, patch and points and can move;
        beyond, settled ones are merged into the static layers, oldest first (module
        docstring; 0: no limit). A hard cap: when too few are settled, the most settled are
        merged all the same (counted).
    settle_updates : pose updates (``set_poses`` calls) a keyframe must go without moving by
        more than ``settle_px`` before it may be merged (0: every keyframe may: oldest first).
    settle_px : a move smaller than this (pixels of the mosaic: the largest shift of the
        keyframe's footprint on the ground) does not unsettle a keyframe; the move is applied
        all the same while it is live.
    max_waiting : keyframe images kept while their pose or the ground is unknown (oldest
        dropped beyond).
    """

    enabled: bool = True
    metres_per_pixel: float = 0.0
    ground_z: float = 0.0
    ground_from_clouds: bool = True
    ground_cell_m: float = 2.0
    ground_tolerance_m: float = 0.02
    tile_px: int = 256
    max_pixels: int = 25_000_000
    max_live_keyframes: int = 2000
    settle_updates: int = 5
    settle_px: float = 0.25
    max_waiting: int = 200

    def __post_init__(self) -> None:
        if self.metres_per_pixel < 0 or self.tile_px < 8 or self.max_pixels < 1 \
                or not self.ground_cell_m > 0 or not self.ground_tolerance_m >= 0 \
                or self.settle_updates < 0 or not self.settle_px >= 0:
            raise InputError('mosaic_metres_per_pixel must be >= 0 (0: automatic), '
                             'mosaic_tile_px >= 8, mosaic_max_pixels >= 1, '
                             'mosaic_ground_cell_m > 0, mosaic_ground_tolerance_m >= 0, '
                             'mosaic_settle_updates >= 0 and mosaic_settle_px >= 0')


@dataclass
class MosaicCounts:
    """What a :class:`LiveMosaic` received and did.

    Attributes
    ----------
    images : keyframe images taken.
    clouds : keyframe clouds taken.
    ground_rewarps : of the warps, those of keyframes whose ground changed (not their pose).
    warps : keyframe warps done (the work: one per placed or moved keyframe).
    tiles_composited : tile recompositions done.
    refused : keyframes refused (mosaic over ``max_pixels``, or no view of the ground).
    dropped : keyframe images dropped while waiting (``max_waiting``).
    frozen : keyframes merged into the static layers.
    merged_settled : of those, keyframes that were settled (module docstring).
    merged_forced : of those, keyframes merged while still moving, because fewer were settled
        than ``max_live_keyframes`` required.
    merged_moves_ignored : poses of merged keyframes that differed from their pose at the
        merge (ignored).
    merged_max_shift_m : the largest translation between such a pose and the pose at the
        merge (m).
    """

    images: int = 0
    clouds: int = 0
    ground_rewarps: int = 0
    warps: int = 0
    tiles_composited: int = 0
    refused: int = 0
    dropped: int = 0
    frozen: int = 0
    merged_settled: int = 0
    merged_forced: int = 0
    merged_moves_ignored: int = 0
    merged_max_shift_m: float = 0.0


@dataclass
class _Patch:
    """A keyframe's warped pixels on the global grid: ``image`` uint8 (rows, cols) and
    ``valid`` bool, top-left at global pixel ``(row0, col0)``."""

    image: np.ndarray
    valid: np.ndarray
    row0: int
    col0: int
    #: the ground cells (i_lo, i_hi, j_lo, j_hi) its warp read, their heights (float32, NaN:
    #: unknown; None on a plane) and the height range it assumed
    cells: tuple[int, int, int, int] = (0, -1, 0, -1)
    ground: np.ndarray | None = None
    z_range: tuple[float, float] = (0.0, 0.0)

    def tiles(self, t: int) -> set[tuple[int, int]]:
        """Tiles (tile row, tile column) the patch touches."""
        r, c = self.valid.shape
        return {(i, j) for i in range(self.row0 // t, (self.row0 + r - 1) // t + 1)
                for j in range(self.col0 // t, (self.col0 + c - 1) // t + 1)}


@dataclass
class _Keyframe:
    image: np.ndarray
    K: FloatArray
    T_base_cam: FloatArray
    T_map_base: FloatArray | None = None
    patch: _Patch | None = None
    refused: bool = False
    #: the pose update (:attr:`LiveMosaic.updates`) of its last move beyond ``settle_px``, and
    #: its pose then (None: no pose yet)
    moved_at: int = 0
    settled_pose: FloatArray | None = None


@dataclass(frozen=True)
class _Heights:
    """A height range, what :func:`ga_ros.mapping.mosaic.footprint` reads of a surface."""

    z_range: tuple[float, float]


@dataclass
class _Tile:
    image: np.ndarray
    valid: np.ndarray
    keys: set[int] = field(default_factory=set)


#: Stamps a static tile lists before it is compacted to those its pixels show (fewer when its
#: owner indices' type holds fewer).
STATIC_TILE_STAMPS = 2 ** 16 - 1


@dataclass
class _StaticTile:
    """A tile of the static layer: the merged keyframes' pixels and, per pixel, which stamp it
    shows (``owner``: 0 none, else ``stamps[owner - 1]``). ``owner`` is uint8 and widens to
    uint16, then uint32, when a tile shows more stamps; ``stamps`` only grows until it is
    compacted to the stamps still shown."""

    image: np.ndarray
    owner: np.ndarray
    stamps: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """The pixels some merged keyframe covers."""
        return self.owner != 0

    @property
    def newest(self) -> int:
        """The latest stamp listed (at least the latest shown)."""
        return int(self.stamps.max()) if self.stamps.size else -(2 ** 63)

    def nbytes(self) -> int:
        return self.image.nbytes + self.owner.nbytes + self.stamps.nbytes

    def compact(self) -> None:
        """Keep only the stamps some pixel shows (owner indices renumbered)."""
        v = self.owner != 0
        shown, inverse = np.unique(self.owner[v], return_inverse=True)
        self.owner[v] = (inverse + 1).astype(self.owner.dtype)
        self.stamps = self.stamps[shown.astype(np.int64) - 1]

    def take(self, key: int, pasted: np.ndarray) -> None:
        """The pixels of ``pasted`` (bool, tile-sized) now show stamp ``key``."""
        top = int(np.iinfo(self.owner.dtype).max)
        if self.stamps.size >= min(STATIC_TILE_STAMPS, top):
            self.compact()
            if self.stamps.size >= top:
                self.owner = self.owner.astype(np.uint16 if top < 2 ** 16 - 1 else np.uint32)
        self.owner[pasted] = self.stamps.size + 1
        self.stamps = np.r_[self.stamps, np.int64(key)]

    def pixel_stamps(self) -> np.ndarray:
        """(t, t) int64 stamp of each pixel (the smallest int64 where none is shown)."""
        out = np.full(self.owner.shape, -(2 ** 63), np.int64)
        v = self.owner != 0
        out[v] = self.stamps[self.owner[v].astype(np.int64) - 1]
        return out


class LiveMosaic:
    """Keyframe images + poses -> a tiled mosaic that re-warps only what moved (module
    docstring)."""

    def __init__(self, config: MosaicMapConfig = MosaicMapConfig()) -> None:
        self.config = config
        self.counts = MosaicCounts()
        self.keyframes: dict[int, _Keyframe] = {}
        self.tiles: dict[tuple[int, int], _Tile] = {}
        #: static layer: tile -> the merged keyframes' pixels and their stamps
        self.static: dict[tuple[int, int], _StaticTile] = {}
        #: merged keyframes: stamp -> T_map_base at the merge
        self.merged: dict[int, FloatArray] = {}
        self.ground: GroundPlane | None = (None if config.ground_from_clouds
                                           else GroundPlane(float(config.ground_z)))
        self.surface: LiveHeightGrid | None = (
            LiveHeightGrid(SurfaceConfig(cell_m=config.ground_cell_m))
            if config.ground_from_clouds else None)
        #: map's z points up (None until the first keyframe is placed)
        self.z_up: bool | None = None
        self.metres_per_pixel = float(config.metres_per_pixel)
        #: poses that came before their image: stamp -> T_map_base
        self.pending_poses: dict[int, FloatArray] = {}
        #: pose updates so far (:meth:`set_poses` calls), the clock of settledness
        self.updates = 0
        #: the height model's keyframes without an image: the update of their last move
        self._orphan_moved: dict[int, int] = {}
        #: the height model's keyframes without an image merged into its static layer: their
        #: later poses are ignored (counted as merged keyframes' moves are not: no pose kept)
        self._merged_orphans: set[int] = set()
        #: why the last keyframe was refused ('' when none was)
        self.last_error = ''
        #: the mosaic changed since :meth:`take_changed` last said so
        self.changed = False
        self._colour: bool | None = None

    # ------------------------------------------------------------------ inputs
    def add_cloud(self, stamp_ns: int, points_cam: np.ndarray, T_base_cam: FloatArray) -> int:
        """A keyframe's cloud ((k, 3) points in its camera's frame, m) and the camera's
        extrinsic ``T_base_cam`` (4, 4), for the ground (ignored on a ground plane); returns the
        keyframes warped because the ground under them changed.

        Raises
        ------
        InputError
            Points that are not (k, 3) or an extrinsic that is not a finite 4x4 transform.
        """
        if self.surface is None:
            return 0
        P = np.asarray(points_cam)
        T_bc = np.asarray(T_base_cam, float)
        if P.ndim != 2 or P.shape[1] != 3 or T_bc.shape != (4, 4) \
                or not np.all(np.isfinite(T_bc)):
            raise InputError('mosaic: a keyframe cloud needs (k, 3) points and a finite 4x4 '
                             'camera extrinsic')
        self.counts.clouds += 1
        if int(stamp_ns) in self.merged or int(stamp_ns) in self._merged_orphans:
            return 0  # its points are in the static layer already
        self.surface.add_points(int(stamp_ns), P, T_bc)
        if int(stamp_ns) not in self.keyframes:
            self._orphan_moved[int(stamp_ns)] = self.updates
        return self._update([])

    def add_image(self, stamp_ns: int, image: np.ndarray, K: FloatArray,
                  T_base_cam: FloatArray) -> bool:
        """A keyframe's rectified image (uint8 grey or BGR), intrinsics ``K`` (3, 3, px) and
        camera extrinsic ``T_base_cam`` (4, 4); True when it was placed at once (its pose and
        the ground known).

        Raises
        ------
        InputError
            A malformed image, ``K`` or extrinsic, or grey and colour images mixed.
        """
        img = np.asarray(image)
        K = np.asarray(K, float)
        T_bc = np.asarray(T_base_cam, float)
        if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
            raise InputError(f'mosaic: keyframe images must be uint8 grey or BGR, got '
                             f'{img.dtype}{img.shape}')
        if min(img.shape[:2]) < 2 or K.shape != (3, 3) or not np.all(np.isfinite(K)) \
                or K[0, 0] <= 0 or T_bc.shape != (4, 4) or not np.all(np.isfinite(T_bc)):
            raise InputError('mosaic: a keyframe image needs a finite 3x3 K with fx > 0 and a '
                             'finite 4x4 camera extrinsic')
        colour = img.ndim == 3
        if self._colour is None:
            self._colour = colour
        elif colour != self._colour:
            raise InputError('mosaic: grey and colour keyframe images mixed')
        key = int(stamp_ns)
        self.counts.images += 1
        if key in self.merged:  # its pixels are in the static layer already
            return False
        old = self.keyframes.get(key)
        T = self.pending_poses.pop(key, None)
        if T is None and old is not None:   # a new image of a placed keyframe keeps its pose
            T = old.T_map_base
        self._orphan_moved.pop(key, None)
        self.keyframes[key] = _Keyframe(img, K, T_bc, T, moved_at=self.updates, settled_pose=T)
        if old is not None and old.patch is not None:
            self._recomposite(self._remove_patch(key, old.patch))
        self._bound_waiting()
        self._update([key])
        return self.keyframes.get(key) is not None and self.keyframes[key].patch is not None

    def set_poses(self, stamps_ns: IntArray, T_map_base: FloatArray) -> int:
        """Poses of keyframes by stamp; those whose pose changed are re-warped and their tiles
        recomposited. Returns the keyframes warped. One call is one pose update of
        settledness (module docstring).

        Raises
        ------
        InputError
            Shapes that do not match or a pose that is not finite: nothing is changed.
        """
        keys = np.asarray(stamps_ns, np.int64).reshape(-1)
        T = np.asarray(T_map_base, float).reshape(-1, 4, 4)
        if T.shape[0] != keys.size or not np.all(np.isfinite(T)):
            raise InputError(f'mosaic: {keys.size} stamps and {T.shape[0]} poses, or a pose '
                             'that is not finite')
        moved = []
        self.updates += 1
        for k, Tk in zip(keys.tolist(), T):
            at_merge = self.merged.get(k)
            if at_merge is not None:
                if not np.array_equal(at_merge, Tk):
                    self.counts.merged_moves_ignored += 1
                    shift = float(np.linalg.norm(Tk[:3, 3] - at_merge[:3, 3]))
                    self.counts.merged_max_shift_m = max(self.counts.merged_max_shift_m, shift)
                continue
            kf = self.keyframes.get(k)
            if kf is None and k in self._merged_orphans:  # its points are static already
                continue
            if self.surface is not None and self.surface.set_pose(k, Tk) and kf is None:
                self._orphan_moved[k] = self.updates
            if kf is None:
                self.pending_poses[k] = Tk.copy()
                continue
            if kf.T_map_base is not None and np.array_equal(kf.T_map_base, Tk):
                continue
            if self._shift_px(kf, Tk) > self.config.settle_px:
                kf.moved_at, kf.settled_pose = self.updates, Tk.copy()
            kf.T_map_base = Tk.copy()
            kf.refused = False
            moved.append(k)
        while len(self.pending_poses) > 100_000:
            self.pending_poses.pop(next(iter(self.pending_poses)))
        return self._update(moved)

    def unplace_all(self) -> None:
        """Forget every keyframe's pose (a full corrections message follows with the new
        ones); the mosaic is emptied but the images are kept."""
        for kf in self.keyframes.values():
            kf.T_map_base = None
            kf.patch = None
        if self.surface is not None:
            self.surface.unplace_all()
            self.surface.commit()
        self.tiles.clear()
        self.pending_poses.clear()
        self.changed = True

    def clear_static(self) -> None:
        """Drop the merged keyframes' layers (a reset)."""
        self.static.clear()
        self.merged.clear()
        self._merged_orphans.clear()
        if self.surface is not None:
            self.surface.clear_static()
        self.changed = True

    # ------------------------------------------------------------------ work
    def _bound_waiting(self) -> None:
        waiting = [k for k, kf in self.keyframes.items() if kf.patch is None]
        over = len(waiting) - max(1, self.config.max_waiting)
        for k in sorted(waiting)[:max(over, 0)]:
            del self.keyframes[k]
            self.counts.dropped += 1

    def _shift_px(self, kf: _Keyframe, T_map_base: FloatArray) -> float:
        """How far (mosaic pixels) the keyframe's footprint on the ground moves from its pose at
        its last move to ``T_map_base``: the largest shift of its border's points at the
        ground's lowest and highest heights; infinite when not known (no pose then, no
        resolution or ground yet, or a view that does not see the ground)."""
        z_range = self._z_range()
        if kf.settled_pose is None or not self.metres_per_pixel \
                or not np.all(np.isfinite(z_range)):
            return float('inf')
        heights = _Heights(z_range)
        old = footprint(CameraView(kf.image, kf.settled_pose @ kf.T_base_cam, kf.K),
                        heights)  # type: ignore[arg-type]
        new = footprint(CameraView(kf.image, T_map_base @ kf.T_base_cam, kf.K),
                        heights)  # type: ignore[arg-type]
        if old is None or new is None:
            return float('inf')
        return float(np.sqrt(np.max(np.sum((new - old) ** 2, axis=1)))) / self.metres_per_pixel

    def settled(self, key: int) -> bool:
        """A live keyframe has not moved beyond ``settle_px`` over the last ``settle_updates``
        pose updates (module docstring)."""
        kf = self.keyframes[key]
        return self.updates - kf.moved_at >= self.config.settle_updates

    def _orphan_settled(self, key: int) -> bool:
        """The height model's keyframe without an image has not moved for ``settle_updates``
        pose updates."""
        return self.updates - self._orphan_moved.get(key, 0) >= self.config.settle_updates

    def _view(self, kf: _Keyframe) -> CameraView:
        assert kf.T_map_base is not None
        return CameraView(kf.image, kf.T_map_base @ kf.T_base_cam, kf.K)

    def _z_range(self) -> tuple[float, float]:
        return self.ground.z_range if self.ground is not None else self.surface.z_range

    def _warp(self, kf: _Keyframe) -> _Patch | str | None:
        """The keyframe warped on the global grid; ``'refused'`` when it does not see the
        ground, None when it sees no known ground yet."""
        view = self._view(kf)
        z_range = self._z_range()
        if not np.all(np.isfinite(z_range)):
            return None
        if self.z_up is None:
            self.z_up = looks_along_minus_z([view])
        if not self.metres_per_pixel:
            gsd = abs(float(view.T_map_cam[2, 3]) - 0.5 * sum(z_range)) / float(kf.K[0, 0])
            if not gsd > 0:
                return 'refused'
            self.metres_per_pixel = gsd
        window = self._window(view, z_range)
        if window is None:
            return 'refused'
        georef, cells = window
        r0 = int(round(-georef.y_max / georef.metres_per_pixel)) if self.z_up \
            else int(round(georef.y_min / georef.metres_per_pixel))
        c0 = int(round(georef.x_min / georef.metres_per_pixel))
        surface: GroundPlane | HeightGrid = (self.ground if self.ground is not None
                                             else self.surface.window(*cells))
        wv = warp_view(view, surface, georef)
        self.counts.warps += 1
        if wv is None:
            return None
        img = np.where(wv.valid[..., None] if wv.image.ndim == 3 else wv.valid,
                       np.clip(wv.image + 0.5, 0, 255), 0).astype(np.uint8)
        heights = None if isinstance(surface, GroundPlane) else surface.z.astype(np.float32)
        return _Patch(img, wv.valid, r0 + wv.row0, c0 + wv.col0, cells, heights, z_range)

    def _window(self, view: CameraView, z_range: tuple[float, float]
                ) -> tuple[Georeference, tuple[int, int, int, int]] | None:
        """The window of the global grid over the view's footprint for ground heights in
        ``z_range`` (None when it does not see them), and the ground cells a warp on it reads
        (i_lo, i_hi, j_lo, j_hi; empty on a plane)."""
        m = self.metres_per_pixel
        foot = footprint(view, _Heights(z_range))  # type: ignore[arg-type]
        if foot is None:
            return None
        c0 = int(np.floor(foot[:, 0].min() / m)) - 1
        c1 = int(np.ceil(foot[:, 0].max() / m)) + 1
        sign = -1.0 if self.z_up else 1.0  # map y = sign * (row + 0.5) * m
        rows_at = sign * foot[:, 1] / m
        r0 = int(np.floor(rows_at.min())) - 1
        r1 = int(np.ceil(rows_at.max())) + 1
        y_max = -r0 * m if self.z_up else r1 * m
        georef = Georeference(c0 * m, y_max, m, c1 - c0, r1 - r0, z_up=bool(self.z_up))
        if self.surface is None:
            return georef, (0, -1, 0, -1)
        c = self.surface.config.cell_m
        return georef, (int(np.floor(-y_max / c)) - 2, int(np.floor(-georef.y_min / c)) + 2,
                        int(np.floor(c0 * m / c)) - 2, int(np.floor(c1 * m / c)) + 2)

    def _ground_moved(self, patch: _Patch) -> bool:
        """The ground under a patch changed beyond ``ground_tolerance_m`` since its warp."""
        tol = self.config.ground_tolerance_m
        if tol <= 0 or patch.ground is None:
            return True
        now = self.surface.window(*patch.cells).z
        known = np.isfinite(now)
        if not np.array_equal(known, np.isfinite(patch.ground)):
            return True
        return bool(known.any() and np.max(np.abs(now[known] - patch.ground[known])) > tol)

    def _update(self, keys: list[int]) -> int:
        """The ground's changes committed, then (re-)warp these keyframes, those whose ground
        changed and those waiting for ground; returns the keyframes warped."""
        todo = set(keys)
        if self.surface is not None:
            ci, cj = self.surface.commit()
            ground = self._ground_changed(ci, cj) - todo
            self.counts.ground_rewarps += len(ground)
            todo |= ground
            if ci.size:  # new ground: the keyframes that saw none yet try again
                todo |= {k for k, kf in self.keyframes.items()
                         if kf.T_map_base is not None and kf.patch is None and not kf.refused}
        return self._place(sorted(todo))

    def _ground_changed(self, ci: np.ndarray, cj: np.ndarray) -> set[int]:
        """Placed keyframes whose warp read a ground cell that changed (beyond
        ``ground_tolerance_m``: :meth:`_ground_moved`). A keyframe warped when the heights spanned
        less than they do now (by more than the tolerance) reads the cells of its footprint at
        the present span (a cell outside its old window can only have come into view by
        changing to a height outside the old span)."""
        out: set[int] = set()
        if ci.size == 0:
            return out
        lo, hi = self._z_range()
        tol = self.config.ground_tolerance_m
        i0, j0 = int(ci.min()), int(cj.min())
        hit = np.zeros((int(ci.max()) - i0 + 2, int(cj.max()) - j0 + 2), np.int64)
        hit[ci - i0 + 1, cj - j0 + 1] = 1
        sat = hit.cumsum(0).cumsum(1)  # summed-area table, row/column 0 zero
        n_i, n_j = sat.shape[0] - 2, sat.shape[1] - 2
        for k, kf in self.keyframes.items():
            if kf.patch is None or k in out:
                continue
            a, b, c, d = kf.patch.cells
            widened = lo < kf.patch.z_range[0] - tol or hi > kf.patch.z_range[1] + tol
            if widened:
                window = self._window(self._view(kf), (lo, hi))
                if window is not None:
                    a, b, c, d = window[1]
            a, b = max(a - i0, 0), min(b - i0, n_i)
            c, d = max(c - j0, 0), min(d - j0, n_j)
            if a <= b and c <= d and \
                    sat[b + 1, d + 1] - sat[a, d + 1] - sat[b + 1, c] + sat[a, c] > 0 \
                    and (widened or self._ground_moved(kf.patch)):
                out.add(k)
        return out

    def _place(self, keys: list[int]) -> int:
        """(Re-)warp these keyframes (pose known) and recomposite the tiles touched."""
        dirty: set[tuple[int, int]] = set()
        warped = 0
        t = self.config.tile_px
        for k in keys:
            kf = self.keyframes.get(k)
            if kf is None or kf.T_map_base is None:
                continue
            if kf.patch is not None:
                dirty |= self._remove_patch(k, kf.patch)
                kf.patch = None
            patch = self._warp(kf)
            warped += 1
            if patch is None:
                continue
            if isinstance(patch, str):
                kf.refused = True
                self.counts.refused += 1
                lo, hi = self._z_range()
                self.last_error = (f'keyframe {k} does not see the ground at z = {lo:.3g} to '
                                   f'{hi:.3g} m (a mosaic needs a downward camera; check the '
                                   'camera extrinsic)')
                continue
            new = patch.tiles(t)
            if not self._fits(new):
                kf.refused = True
                self.counts.refused += 1
                self.last_error = (f'mosaic: keyframe {k} would grow the mosaic beyond '
                                   f'mosaic_max_pixels {self.config.max_pixels}: raise it or '
                                   'mosaic_metres_per_pixel')
                continue
            kf.patch = patch
            for tile in new:
                self._tile(tile).keys.add(k)
            dirty |= new
        self._recomposite(dirty)
        self._freeze()
        return warped

    def _fits(self, new: set[tuple[int, int]]) -> bool:
        keys = set(self.tiles) | set(self.static) | new
        rows = [i for i, _ in keys]
        cols = [j for _, j in keys]
        t = self.config.tile_px
        return (max(rows) - min(rows) + 1) * (max(cols) - min(cols) + 1) * t * t \
            <= self.config.max_pixels

    def _tile(self, tile: tuple[int, int]) -> _Tile:
        got = self.tiles.get(tile)
        if got is None:
            t = self.config.tile_px
            shape = (t, t, 3) if self._colour else (t, t)
            got = self.tiles[tile] = _Tile(np.zeros(shape, np.uint8), np.zeros((t, t), bool))
        return got

    def _remove_patch(self, key: int, patch: _Patch) -> set[tuple[int, int]]:
        tiles = patch.tiles(self.config.tile_px)
        for tile in tiles:
            got = self.tiles.get(tile)
            if got is not None:
                got.keys.discard(key)
        return tiles

    def _recomposite(self, tiles: set[tuple[int, int]]) -> None:
        """Each tile again: the static layer, then its keyframes' patches by stamp."""
        t = self.config.tile_px
        for tile in tiles:
            got = self.tiles.get(tile)
            if got is None:
                continue
            base = self.static.get(tile)
            if base is None:
                got.image[:] = 0
                got.valid[:] = False
            else:
                got.image[:], got.valid[:] = base.image, base.valid
            newest = None if base is None else base.newest
            under = None  # the static pixels' stamps, while a live keyframe is older than some
            for k in sorted(got.keys):
                p = self.keyframes[k].patch
                assert p is not None
                older = newest is not None and k < newest
                if older and under is None:
                    under = base.pixel_stamps()
                _paste(got, p, tile[0] * t, tile[1] * t, under < k if older else None)
            if not got.keys and base is None:
                del self.tiles[tile]
            self.counts.tiles_composited += 1
        self.changed |= bool(tiles)

    def _freeze(self) -> None:
        """Beyond ``max_live_keyframes`` placed keyframes, merge the settled ones, oldest
        first, then if need be the most settled (module docstring)."""
        limit = self.config.max_live_keyframes
        if limit <= 0:
            return
        placed = [k for k, kf in self.keyframes.items() if kf.patch is not None]
        over = len(placed) - limit
        if over <= 0:
            return
        settled = sorted(k for k in placed if self.settled(k))[:over]
        forced = []
        if len(settled) < over:
            done = set(settled)
            forced = sorted((k for k in placed if k not in done),
                            key=lambda k: (self.keyframes[k].moved_at, k))[:over - len(settled)]
        self.merge(settled + forced)
        self.counts.merged_settled += len(settled)
        self.counts.merged_forced += len(forced)

    def merge(self, keys: list[int]) -> int:
        """Merge these placed keyframes into the static layers (module docstring), and the
        height model's keyframes older than the newest of them that have no image here and
        have settled (no pose update for ``settle_updates``; all of them when a keyframe
        named has not settled); returns the keyframes merged. The mosaic is unchanged."""
        keys = sorted(k for k in keys if k in self.keyframes
                      and self.keyframes[k].patch is not None)
        if not keys:
            return 0
        if self.surface is not None:
            if all(self.settled(k) for k in keys):
                orphans = [k for k in self.surface.keyframes if k <= keys[-1]
                           and k not in self.keyframes and self._orphan_settled(k)]
            else:
                orphans = [k for k in self.surface.keyframes
                           if k <= keys[-1] and k not in self.keyframes]
            self.surface.merge(keys + orphans)
            for k in orphans:
                self._orphan_moved.pop(k, None)
                self.pending_poses.pop(k, None)
            self._merged_orphans.update(orphans)
        t = self.config.tile_px
        for k in keys:
            kf = self.keyframes.pop(k)
            patch = kf.patch
            assert patch is not None and kf.T_map_base is not None
            self.merged[k] = kf.T_map_base
            for tile in patch.tiles(t):
                got = self._tile(tile)
                got.keys.discard(k)
                self._paste_static(tile, k, patch)
            self.counts.frozen += 1
        return len(keys)

    def _paste_static(self, tile: tuple[int, int], key: int, patch: _Patch) -> None:
        """Paste a merged keyframe's pixels into a static tile over the pixels of earlier
        stamps (and the empty ones)."""
        t = self.config.tile_px
        layer = self.static.get(tile)
        if layer is None:
            got = self.tiles[tile]
            layer = self.static[tile] = _StaticTile(
                np.zeros_like(got.image), np.zeros(got.valid.shape, np.uint8),
                np.zeros(0, np.int64))
        where = None if key > layer.newest else layer.pixel_stamps() < key
        pasted = np.zeros(layer.owner.shape, bool)
        _paste(_Tile(layer.image, pasted), patch, tile[0] * t, tile[1] * t, where)
        if pasted.any():
            layer.take(key, pasted)

    # ------------------------------------------------------------------ outputs
    def take_changed(self) -> bool:
        """True once after each change of the mosaic (what a periodic publisher asks)."""
        out, self.changed = self.changed, False
        return out

    @property
    def n_placed(self) -> int:
        """Keyframes in the mosaic that can still move."""
        return sum(kf.patch is not None for kf in self.keyframes.values())

    def nbytes(self) -> int:
        """Bytes held by the images, patches, points, tiles and static layers."""
        return sum(self.nbytes_by_part().values())

    def nbytes_by_part(self) -> dict[str, int]:
        """Bytes held, by what holds them: per live keyframe ``images``, ``patches`` (warped
        pixels, mask and the ground read) and ``points`` (the height model's), per merged
        keyframe ``merged_poses``; per area ``tiles``, ``static_tiles`` and ``ground`` (the
        height model's per-cell arrays)."""
        kfs = self.keyframes.values()
        patches = [kf.patch for kf in kfs if kf.patch is not None]
        return {
            'images': sum(kf.image.nbytes for kf in kfs),
            'patches': sum(p.image.nbytes + p.valid.nbytes
                           + (0 if p.ground is None else p.ground.nbytes) for p in patches),
            'points': 0 if self.surface is None else self.surface.points_nbytes(),
            'merged_poses': sum(T.nbytes for T in self.merged.values()),
            'tiles': sum(tl.image.nbytes + tl.valid.nbytes for tl in self.tiles.values()),
            'static_tiles': sum(layer.nbytes() for layer in self.static.values()),
            'ground': 0 if self.surface is None else self.surface.grid_nbytes(),
        }

    def mosaic(self) -> Mosaic | None:
        """The tiles assembled over their bounding box (None when empty); its georeference
        places it in ``map`` (module docstring's grid)."""
        if not self.tiles:
            return None
        t, m = self.config.tile_px, self.metres_per_pixel
        rows = [i for i, _ in self.tiles]
        cols = [j for _, j in self.tiles]
        i0, j0 = min(rows), min(cols)
        h, w = (max(rows) - i0 + 1) * t, (max(cols) - j0 + 1) * t
        image = np.zeros((h, w, 3) if self._colour else (h, w), np.uint8)
        valid = np.zeros((h, w), bool)
        for (i, j), tl in self.tiles.items():
            win = (slice((i - i0) * t, (i - i0 + 1) * t), slice((j - j0) * t, (j - j0 + 1) * t))
            image[win] = tl.image
            valid[win] = tl.valid
        y_max = -i0 * t * m if self.z_up is not False else i0 * t * m + h * m
        return Mosaic(image, valid, Georeference(j0 * t * m, y_max, m, w, h,
                                                 z_up=self.z_up is not False))


def _paste(tile: _Tile, patch: _Patch, top: int, left: int,
           where: np.ndarray | None = None) -> None:
    """Copy the patch's valid pixels that fall in the tile whose top-left global pixel is
    ``(top, left)`` (and where ``where``, a tile-sized bool array, is true)."""
    t = tile.valid.shape[0]
    r, c = patch.valid.shape
    r0, r1 = max(patch.row0, top), min(patch.row0 + r, top + t)
    c0, c1 = max(patch.col0, left), min(patch.col0 + c, left + t)
    if r1 <= r0 or c1 <= c0:
        return
    src = (slice(r0 - patch.row0, r1 - patch.row0), slice(c0 - patch.col0, c1 - patch.col0))
    dst = (slice(r0 - top, r1 - top), slice(c0 - left, c1 - left))
    v = patch.valid[src]
    if where is not None:
        v = v & where[dst]
    tile.image[dst][v] = patch.image[src][v]
    tile.valid[dst] |= v
