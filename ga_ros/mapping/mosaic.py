"""Photomosaic of a downward-looking camera from its corrected poses (ROS-free).

Each keyframe's image is projected onto the ground (:mod:`ga_ros.mapping.surface`) and resampled
on a grid of ``metres_per_pixel`` in ``map``: for a :class:`GroundPlane` by one homography
(``cv2.warpPerspective``), for a :class:`HeightGrid` (relief) by orthorectification (every
mosaic pixel's ground point projected into the image, ``cv2.remap``). ``T_map_cam`` is the
camera's pose in ``map`` with the OpenCV optical convention (``z`` forward, ``x`` right, ``y``
down); ``K`` the (3, 3) intrinsics of the (rectified, undistorted) image in px.

Orientation: the mosaic is the ground **as seen from above** (from the cameras' side), with
``map``'s ``x`` to the right, whichever way ``map``'s ``z`` points. With ``z`` up (REP 103:
``x`` east, ``y`` north) row 0 is the largest ``y`` (north up); with ``z`` down (e.g. ``map``
anchored at a camera's optical frame looking down) row 0 is the smallest ``y``, so the image is
not mirrored. :func:`plan_georeference` tells which from the cameras' viewing direction
(:attr:`Georeference.z_up`).

Georeference (:class:`Georeference`): pixel ``(row, col)`` of the mosaic has its centre at map
``x = x_min + (col + 0.5) * metres_per_pixel`` and, with ``z`` up,
``y = y_max - (row + 0.5) * metres_per_pixel``; with ``z`` down,
``y = y_min + (row + 0.5) * metres_per_pixel``. :func:`save_mosaic` writes it beside the PNG as
JSON and as an ESRI world file (``.pgw``); :func:`image_fields` and :func:`map_metadata_fields`
give it as ``sensor_msgs/Image`` plus ``nav_msgs/MapMetaData`` fields.

Blending: ``'last'`` (a later keyframe covers an earlier one) or ``'average'`` (the mean of the
keyframes that see a pixel). Memory is bounded: a mosaic larger than ``max_pixels`` is refused
with the resolution that would fit.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from ga_ros.arrays import FloatArray
from ga_ros.errors import InputError
from ga_ros.mapping.surface import GroundPlane, HeightGrid
from ga_ros.safe_write import write_bytes, write_json, write_text

#: Blending modes of :class:`MosaicConfig`.
BLEND_MODES = ('last', 'average')

Surface = GroundPlane | HeightGrid


@dataclass(frozen=True)
class CameraView:
    """One keyframe image and where it was taken.

    Attributes
    ----------
    image : (h, w) uint8 grey or (h, w, 3) uint8 BGR, rectified and undistorted.
    T_map_cam : (4, 4) pose of the camera (optical frame) in ``map`` (m).
    K : (3, 3) intrinsics of ``image`` (px).
    """

    image: np.ndarray
    T_map_cam: FloatArray
    K: FloatArray


@dataclass(frozen=True)
class Georeference:
    """Where a raster seen from above lies in ``map`` (module docstring).

    Attributes
    ----------
    x_min, y_max : map coordinates of the raster's smallest ``x`` and largest ``y`` edges (m).
    metres_per_pixel : pixel size on the ground (m).
    width, height : raster size (px).
    frame_id : the frame of ``x_min, y_max``.
    z_up : ``map``'s ``z`` points up (row 0 is the largest ``y``); False: ``z`` points down (row
        0 is the smallest ``y``).
    """

    x_min: float
    y_max: float
    metres_per_pixel: float
    width: int
    height: int
    frame_id: str = 'map'
    z_up: bool = True

    @property
    def y_min(self) -> float:
        """Map ``y`` of the edge of smallest ``y`` (m)."""
        return self.y_max - self.height * self.metres_per_pixel

    @property
    def row_step(self) -> float:
        """Map ``y`` from one row to the next (m): ``-metres_per_pixel`` with ``z`` up."""
        return -self.metres_per_pixel if self.z_up else self.metres_per_pixel

    @property
    def y_top(self) -> float:
        """Map ``y`` of row 0's outer edge (m)."""
        return self.y_max if self.z_up else self.y_min

    def row_of(self, y: FloatArray) -> FloatArray:
        """Fractional row (pixel edges at integers) of map ``y`` (m)."""
        return (np.asarray(y, float) - self.y_top) / self.row_step

    def pixel_centres(self, row0: int, col0: int, rows: int,
                      cols: int) -> tuple[np.ndarray, np.ndarray]:
        """Map ``x, y`` (m) of the pixel centres of a window, two (rows, cols) float32 arrays."""
        m = self.metres_per_pixel
        x = self.x_min + (np.arange(col0, col0 + cols) + 0.5) * m
        y = self.y_top + (np.arange(row0, row0 + rows) + 0.5) * self.row_step
        xx, yy = np.meshgrid(x, y)
        return xx.astype(np.float32), yy.astype(np.float32)

    def as_dict(self) -> dict[str, Any]:
        """JSON-able fields plus the convention in words."""
        rows = ('y = y_max - (row + 0.5) * metres_per_pixel (map z up: north up)' if self.z_up
                else 'y = y_max - (height - row - 0.5) * metres_per_pixel (map z down)')
        return {'frame_id': self.frame_id, 'metres_per_pixel': self.metres_per_pixel,
                'x_min': self.x_min, 'y_max': self.y_max, 'width': self.width,
                'height': self.height, 'z_up': self.z_up,
                'convention': 'seen from above with x to the right; pixel (row, col) centre at '
                              f'x = x_min + (col + 0.5) * metres_per_pixel, {rows}'}


@dataclass(frozen=True)
class MosaicConfig:
    """Settings of :func:`build_mosaic`.

    Attributes
    ----------
    metres_per_pixel : mosaic resolution (m/px); 0: the keyframes' median ground sample distance.
    blend : one of :data:`BLEND_MODES`.
    max_pixels : largest mosaic (pixels); a larger one is an :class:`InputError`.
    margin_m : border added around the keyframes' footprints (m).
    """

    metres_per_pixel: float = 0.0
    blend: str = 'last'
    max_pixels: int = 40_000_000
    margin_m: float = 0.0

    def __post_init__(self) -> None:
        if self.blend not in BLEND_MODES:
            raise InputError(f'mosaic blend must be one of {BLEND_MODES}, got {self.blend!r}')
        if self.metres_per_pixel < 0 or self.max_pixels < 1:
            raise InputError('mosaic metres_per_pixel must be >= 0 (0: automatic) and '
                             'max_pixels >= 1')


@dataclass
class Mosaic:
    """A mosaic: pixels, which of them are covered, and where it lies.

    Attributes
    ----------
    image : (height, width) uint8 grey or (height, width, 3) uint8 BGR; 0 where not covered.
    valid : (height, width) bool, True where a keyframe covers the pixel.
    georef : where it lies in ``map``.
    """

    image: np.ndarray
    valid: np.ndarray
    georef: Georeference


@dataclass
class WarpedView:
    """A view resampled on a window of the mosaic grid: ``image`` (rows, cols[, 3]) float32 and
    ``valid`` (rows, cols) bool, whose top-left pixel is mosaic pixel ``(row0, col0)``."""

    image: np.ndarray
    valid: np.ndarray
    row0: int
    col0: int


def _check_view(view: CameraView) -> None:
    T, K = np.asarray(view.T_map_cam, float), np.asarray(view.K, float)
    img = np.asarray(view.image)
    if T.shape != (4, 4) or not np.all(np.isfinite(T)) or K.shape != (3, 3):
        raise InputError('mosaic: each view needs a finite 4x4 T_map_cam and a 3x3 K')
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise InputError(f'mosaic: images must be uint8 grey or BGR, got {img.dtype}{img.shape}')


def footprint(view: CameraView, surface: Surface) -> FloatArray | None:
    """(k, 2) map ``x, y`` (m) bounding the ground the view sees: its border's rays cut at the
    surface's lowest and highest heights; None when a border ray does not meet both heights in
    front of the camera (a camera looking at the surface from above, or from below when
    ``map``'s ``z`` points down, e.g. anchored at a ``base_link`` with ``z`` down)."""
    h, w = np.asarray(view.image).shape[:2]
    T = np.asarray(view.T_map_cam, float)
    u = np.r_[np.linspace(0, w - 1, 5), np.full(5, w - 1), np.linspace(0, w - 1, 5), np.zeros(5)]
    v = np.r_[np.zeros(5), np.linspace(0, h - 1, 5), np.full(5, h - 1), np.linspace(0, h - 1, 5)]
    rays = np.linalg.solve(np.asarray(view.K, float), np.stack([u, v, np.ones_like(u)]))
    d = T[:3, :3] @ rays
    if np.any(np.abs(d[2]) <= 1e-9):
        return None
    pts = []
    for z in surface.z_range:
        s = (z - T[2, 3]) / d[2]
        if np.any(s <= 0):
            return None
        pts.append((T[:2, 3, None] + s * d[:2]).T)
    return np.concatenate(pts)


def looks_along_minus_z(views: list[CameraView]) -> bool:
    """True when most cameras look along ``map``'s ``-z`` (``z`` up, a camera above the
    ground); False when they look along ``+z`` (``map``'s ``z`` points down)."""
    dz = [float(np.asarray(v.T_map_cam, float)[2, 2]) for v in views]
    return bool(np.median(dz) <= 0) if dz else True


def ground_sample_distance(views: list[CameraView], surface: Surface) -> float:
    """The views' median ground sample distance (m/px): height above the surface's middle
    height (along ``z`` or ``-z``, :func:`looks_along_minus_z`) over the focal length."""
    lo, hi = surface.z_range
    up = 1.0 if looks_along_minus_z(views) else -1.0
    gsd = [up * (float(v.T_map_cam[2, 3]) - 0.5 * (lo + hi)) / float(np.asarray(v.K)[0, 0])
           for v in views]
    gsd = [g for g in gsd if g > 0]
    if not gsd:
        raise InputError('mosaic: no camera is above the ground surface (is the camera looking '
                         'down at the ground?)')
    return float(np.median(gsd))


def plan_georeference(views: list[CameraView], surface: Surface,
                      config: MosaicConfig = MosaicConfig()) -> Georeference:
    """The grid covering every view's footprint.

    Raises
    ------
    InputError
        No view looks down at the surface, or the grid would exceed ``config.max_pixels`` (the
        message gives the resolution that fits).
    """
    for v in views:
        _check_view(v)
    feet = [f for f in (footprint(v, surface) for v in views) if f is not None]
    if not feet:
        raise InputError('mosaic: no view looks down at the ground (a mosaic needs a downward '
                         'camera; check the camera extrinsic)')
    pts = np.concatenate(feet)
    m = config.metres_per_pixel or ground_sample_distance(views, surface)
    x_min, y_min = pts.min(axis=0) - config.margin_m
    x_max, y_max = pts.max(axis=0) + config.margin_m
    width = int(np.ceil((x_max - x_min) / m))
    height = int(np.ceil((y_max - y_min) / m))
    if width * height > config.max_pixels:
        need = float(np.sqrt((x_max - x_min) * (y_max - y_min) / config.max_pixels))
        raise InputError(f'mosaic of {width}x{height} px at {m:.3g} m/px exceeds max_pixels '
                         f'{config.max_pixels}: use metres_per_pixel >= {need:.3g} or raise '
                         'max_pixels')
    return Georeference(float(x_min), float(y_max), float(m), width, height,
                        z_up=looks_along_minus_z(views))


def warp_view(view: CameraView, surface: Surface, georef: Georeference) -> WarpedView | None:
    """The view resampled on the mosaic grid over its footprint (bilinear); None when it does
    not see the grid."""
    _check_view(view)
    foot = footprint(view, surface)
    if foot is None:
        return None
    m = georef.metres_per_pixel
    col0 = max(int(np.floor((foot[:, 0].min() - georef.x_min) / m)), 0)
    col1 = min(int(np.ceil((foot[:, 0].max() - georef.x_min) / m)) + 1, georef.width)
    rows_at = georef.row_of(foot[:, 1])
    row0 = max(int(np.floor(rows_at.min())), 0)
    row1 = min(int(np.ceil(rows_at.max())) + 1, georef.height)
    if col1 <= col0 or row1 <= row0:
        return None
    rows, cols = row1 - row0, col1 - col0
    img = np.asarray(view.image)
    h, w = img.shape[:2]
    T = np.asarray(view.T_map_cam, float)
    R, t = T[:3, :3], T[:3, 3]
    P = np.asarray(view.K, float) @ np.hstack([R.T, (-R.T @ t)[:, None]])  # map -> pixel
    src = img.astype(np.float32)
    m0 = georef.x_min + (col0 + 0.5) * m
    dy = georef.row_step
    n0 = georef.y_top + (row0 + 0.5) * dy
    if isinstance(surface, GroundPlane):
        # mosaic window pixel (c, r, 1) -> map (x, y, z, 1) -> image: one homography
        A = np.array([[m, 0.0, m0], [0.0, dy, n0], [0.0, 0.0, surface.z_m], [0.0, 0.0, 1.0]])
        out = cv2.warpPerspective(src, P @ A, (cols, rows),
                                  flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                                  borderMode=cv2.BORDER_CONSTANT)
        z: np.ndarray | float = float(surface.z_m)
    else:
        x, y = georef.pixel_centres(row0, col0, rows, cols)
        z = surface.heights(x, y)
    # image coordinates of every window pixel's ground point, separably: x varies along the
    # columns, y along the rows
    xs = (m0 + m * np.arange(cols, dtype=np.float64))[None, :]
    ys = (n0 + dy * np.arange(rows, dtype=np.float64))[:, None]
    q = [(P[k, 0] * xs + (P[k, 1] * ys + P[k, 3])).astype(np.float32) + np.float32(P[k, 2]) * z
         for k in range(3)]
    depth = q[2]
    with np.errstate(divide='ignore', invalid='ignore'):
        u = q[0] / depth
        v = q[1] / depth
    if not isinstance(surface, GroundPlane):
        out = cv2.remap(src, np.nan_to_num(u, nan=-1.0, posinf=-1.0, neginf=-1.0),
                        np.nan_to_num(v, nan=-1.0, posinf=-1.0, neginf=-1.0),
                        cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    with np.errstate(invalid='ignore'):
        valid = (depth > 0) & (u >= 0) & (u <= w - 1) & (v >= 0) & (v <= h - 1)
    if not valid.any():
        return None
    return WarpedView(out, valid, row0, col0)


def build_mosaic(views: list[CameraView], surface: Surface,
                 config: MosaicConfig = MosaicConfig(),
                 georef: Georeference | None = None) -> Mosaic:
    """The mosaic of ``views`` (in the order given: ``'last'`` lets later ones cover earlier
    ones) on ``georef`` (default: :func:`plan_georeference`).

    Raises
    ------
    InputError
        No view, a malformed view, or a mosaic over ``config.max_pixels``.
    """
    if not views:
        raise InputError('mosaic: no keyframe image')
    georef = georef or plan_georeference(views, surface, config)
    colour = np.asarray(views[0].image).ndim == 3
    shape = (georef.height, georef.width) + ((3,) if colour else ())
    if georef.width * georef.height > config.max_pixels:
        raise InputError(f'mosaic of {georef.width}x{georef.height} px exceeds max_pixels '
                         f'{config.max_pixels}')
    if config.blend == 'average':
        acc = np.zeros(shape, np.float32)
        count = np.zeros(shape[:2], np.float32)
    else:
        acc = np.zeros(shape, np.uint8)
        count = np.zeros(shape[:2], np.float32)
    for view in views:
        if (np.asarray(view.image).ndim == 3) != colour:
            raise InputError('mosaic: mixed grey and colour images')
        wv = warp_view(view, surface, georef)
        if wv is None:
            continue
        r, c = wv.valid.shape
        win = (slice(wv.row0, wv.row0 + r), slice(wv.col0, wv.col0 + c))
        if config.blend == 'average':
            acc[win][wv.valid] += wv.image[wv.valid]
        else:
            acc[win][wv.valid] = np.clip(wv.image[wv.valid] + 0.5, 0, 255).astype(np.uint8)
        count[win][wv.valid] += 1.0
    valid = count > 0
    if config.blend == 'average':
        den = np.maximum(count, 1.0)
        img = acc / (den[..., None] if colour else den)
        image = np.clip(img + 0.5, 0, 255).astype(np.uint8)
    else:
        image = acc
    return Mosaic(image, valid, georef)


def write_png(path: str | Path, image: np.ndarray, compression: int = 3) -> Path:
    """Encode ``image`` (grey, BGR or BGRA, uint8) as PNG and write it through
    :mod:`ga_ros.safe_write` (atomic, no symbolic link followed); ``compression`` 0-9."""
    ok, buf = cv2.imencode('.png', image, [cv2.IMWRITE_PNG_COMPRESSION, int(compression)])
    if not ok:
        raise InputError(f'could not encode {path} as PNG ({image.shape}, {image.dtype})')
    return write_bytes(path, buf.tobytes())


def save_mosaic(path: str | Path, mosaic: Mosaic) -> dict[str, str]:
    """Write the mosaic as PNG (grey or colour; an alpha channel marks the covered pixels), its
    georeference as JSON (``<name>.json``) and as an ESRI world file (``<name>.pgw``: pixel
    size, rotation terms 0, the ``y`` step of a row, pixel (0, 0)'s centre), each atomically
    through :mod:`ga_ros.safe_write` (links refused). Returns the paths by kind.

    Raises
    ------
    InputError
        The PNG cannot be encoded.
    FormatError
        A file cannot be written.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    img = mosaic.image if mosaic.image.ndim == 3 else cv2.cvtColor(mosaic.image,
                                                                    cv2.COLOR_GRAY2BGR)
    bgra = np.concatenate([img, (mosaic.valid * 255).astype(np.uint8)[..., None]], axis=2)
    write_png(path, bgra)
    g = mosaic.georef
    meta = write_json(path.with_suffix('.json'), g.as_dict(), indent=1)
    world = path.with_suffix('.pgw')
    m = g.metres_per_pixel
    dy = g.row_step
    write_text(world, f'{m!r}\n0.0\n0.0\n{dy!r}\n{g.x_min + 0.5 * m!r}\n{g.y_top + 0.5 * dy!r}\n')
    return {'png': str(path), 'georeference': str(meta), 'world_file': str(world)}


def image_fields(mosaic: Mosaic) -> dict[str, Any]:
    """``sensor_msgs/Image`` fields of the mosaic (without the header): ``mono8`` for grey,
    ``rgb8`` for colour, rows as seen from above (module docstring), uncovered pixels 0.
    Publish it with ``header.frame_id`` = the georeference's frame (``map``) beside
    :func:`map_metadata_fields` (same stamp)."""
    img = mosaic.image
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
        encoding, channels = 'rgb8', 3
    else:
        encoding, channels = 'mono8', 1
    img = np.ascontiguousarray(img)
    h, w = img.shape[:2]
    return {'height': h, 'width': w, 'encoding': encoding, 'is_bigendian': 0,
            'step': w * channels, 'data': img.reshape(-1)}


def map_metadata_fields(georef: Georeference) -> dict[str, Any]:
    """The georeference as ``nav_msgs/MapMetaData`` fields (``resolution`` m/px, ``width``,
    ``height``, ``origin`` = position ``[x, y, z]`` and quaternion ``[x, y, z, w]`` of grid cell
    (0, 0)'s outer corner), the convention of ``nav_msgs/OccupancyGrid``: grid row ``i``
    (counted from ``origin`` along the origin's ``y`` axis) is row ``height - 1 - i`` of the
    ``sensor_msgs/Image`` of :func:`image_fields`. With ``map``'s ``z`` up the origin is the
    corner ``(x_min, y_min)`` with no rotation; with ``z`` down it is ``(x_min, y_max)`` turned
    half a turn about ``x`` (quaternion ``[1, 0, 0, 0]``: the grid's ``y`` is ``map``'s ``-y``,
    its ``z`` points up)."""
    corner = georef.y_min if georef.z_up else georef.y_max
    return {'resolution': float(georef.metres_per_pixel), 'width': int(georef.width),
            'height': int(georef.height),
            'origin': {'position': [float(georef.x_min), float(corner), 0.0],
                       'orientation': ([0.0, 0.0, 0.0, 1.0] if georef.z_up
                                       else [1.0, 0.0, 0.0, 0.0])}}
