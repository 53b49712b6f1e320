"""Seam misregistration of a mosaic (ROS-free): how far apart the images of two overlapping
keyframes on neighbouring tracks land on the mosaic grid.

For each keyframe of a track, its partner is the keyframe of the previous track (in track id
order) whose footprint overlaps it most (at least ``min_overlap`` of the smaller footprint's
bounding box). Both are warped alone onto the mosaic grid
(:func:`ga_ros.mapping.mosaic.warp_view`);
on the largest rectangle that both cover, the translation between them is measured by phase
correlation (``cv2.phaseCorrelate``, Hann window) refined by ECC (``cv2.findTransformECC``,
translation). With exact poses and ground the two images agree up to noise and the offset is ~0;
a pose error shows as an offset in mosaic pixels. Figures: median and 95th percentile of the
offset's length over the pairs (px and m).
"""

from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass, field

import cv2
import numpy as np

from ga_ros.arrays import FloatArray, IntArray
from ga_ros.mapping.mosaic import (
    CameraView,
    Georeference,
    Surface,
    WarpedView,
    footprint,
    warp_view,
)


@dataclass(frozen=True)
class SeamOffset:
    """The offset of view ``b`` against view ``a`` on the mosaic grid.

    Attributes
    ----------
    a, b : indices of the two views.
    dx_px, dy_px : translation of ``b``'s content relative to ``a``'s (px; ``x`` right = east,
        ``y`` down = south): ``b(col, row) ~ a(col - dx, row - dy)``.
    size_px : (rows, cols) of the compared rectangle.
    centre_xy : map ``x, y`` (m) of the compared rectangle's centre.
    """

    a: int
    b: int
    dx_px: float
    dy_px: float
    size_px: tuple[int, int]
    centre_xy: tuple[float, float] = (float('nan'), float('nan'))

    @property
    def length_px(self) -> float:
        """Length of the offset (px)."""
        return float(np.hypot(self.dx_px, self.dy_px))


@dataclass
class SeamStats:
    """Seam misregistration of one mosaic.

    Attributes
    ----------
    pairs : keyframe pairs on neighbouring tracks found overlapping.
    measured : pairs whose common rectangle was large enough to measure.
    median_px, p95_px, max_px : of the offsets' lengths (px; NaN when none measured).
    metres_per_pixel : the mosaic's pixel size (m).
    offsets : every measured offset.
    """

    pairs: int
    measured: int
    median_px: float
    p95_px: float
    max_px: float
    metres_per_pixel: float
    offsets: list[SeamOffset] = field(default_factory=list)

    def as_dict(self) -> dict[str, float | int]:
        """JSON-able figures (px and m)."""
        m = self.metres_per_pixel
        return {'pairs': self.pairs, 'measured': self.measured, 'median_px': self.median_px,
                'p95_px': self.p95_px, 'max_px': self.max_px, 'median_m': self.median_px * m,
                'p95_m': self.p95_px * m, 'metres_per_pixel': m}


def _box(points: FloatArray) -> FloatArray:
    return np.r_[points.min(axis=0), points.max(axis=0)]  # x0 y0 x1 y1


def seam_pairs(views: list[CameraView], tracks: IntArray, surface: Surface,
               min_overlap: float = 0.5) -> list[tuple[int, int]]:
    """Pairs ``(a, b)`` of view indices: ``b`` on a track, ``a`` its most overlapping view on the
    previous track (track ids in increasing order), overlap of the footprints' bounding boxes
    at least ``min_overlap`` of the smaller box."""
    tracks = np.asarray(tracks)
    boxes: list[FloatArray | None] = []
    for v in views:
        f = footprint(v, surface)
        boxes.append(None if f is None else _box(f))
    order = np.unique(tracks)
    pairs = []
    for prev, cur in zip(order[:-1], order[1:]):
        cand = [i for i in np.flatnonzero(tracks == prev) if boxes[i] is not None]
        for b in np.flatnonzero(tracks == cur):
            bb = boxes[b]
            if bb is None or not cand:
                continue
            best, best_ov = -1, 0.0
            for a in cand:
                ba = boxes[a]
                assert ba is not None
                w = min(ba[2], bb[2]) - max(ba[0], bb[0])
                h = min(ba[3], bb[3]) - max(ba[1], bb[1])
                if w <= 0 or h <= 0:
                    continue
                small = min((ba[2] - ba[0]) * (ba[3] - ba[1]), (bb[2] - bb[0]) * (bb[3] - bb[1]))
                ov = w * h / small
                if ov > best_ov:
                    best, best_ov = int(a), ov
            if best >= 0 and best_ov >= min_overlap:
                pairs.append((best, int(b)))
    return pairs


def _valid_rectangle(mask: np.ndarray) -> tuple[int, int, int, int] | None:
    """A large rectangle ``(r0, r1, c0, c1)`` (end exclusive) inside ``mask``: its bounding box,
    shrunk from the side with the most uncovered pixels until none is left."""
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    if rows.size == 0:
        return None
    r0, r1, c0, c1 = int(rows[0]), int(rows[-1]) + 1, int(cols[0]), int(cols[-1]) + 1
    while r1 - r0 > 1 and c1 - c0 > 1:
        sub = mask[r0:r1, c0:c1]
        bad = [(~sub[0]).sum() / sub.shape[1], (~sub[-1]).sum() / sub.shape[1],
               (~sub[:, 0]).sum() / sub.shape[0], (~sub[:, -1]).sum() / sub.shape[0]]
        k = int(np.argmax(bad))
        if bad[k] == 0:
            return r0, r1, c0, c1
        if k == 0:
            r0 += 1
        elif k == 1:
            r1 -= 1
        elif k == 2:
            c0 += 1
        else:
            c1 -= 1
    return None


def image_offset(a: np.ndarray, b: np.ndarray) -> tuple[float, float]:
    """Translation ``(dx, dy)`` (px) of image ``b``'s content relative to ``a``'s
    (``b(x, y) ~ a(x - dx, y - dy)``): phase correlation refined by ECC; two same-shape 2-D
    arrays."""
    a = np.asarray(a, np.float32)
    b = np.asarray(b, np.float32)
    a = a - a.mean()
    b = b - b.mean()
    win = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(a, b, win)
    warp = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy]], np.float32)
    try:
        _, warp = cv2.findTransformECC(a, b, warp, cv2.MOTION_TRANSLATION,
                                       (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 100,
                                        1e-5), None, 1)
    except cv2.error:
        return float(dx), float(dy)
    if abs(warp[0, 2] - dx) > 2.0 or abs(warp[1, 2] - dy) > 2.0:  # ECC wandered off
        return float(dx), float(dy)
    return float(warp[0, 2]), float(warp[1, 2])


def view_offset(wa: WarpedView, wb: WarpedView,
                min_side_px: int = 32) -> tuple[float, float, tuple[int, int, int, int]] | None:
    """Offset ``(dx, dy, (row0, row1, col0, col1))`` of warped view ``b`` against ``a`` (px)
    on the largest rectangle both cover (:func:`image_offset`; the rectangle in mosaic pixels,
    ends exclusive); None when the rectangle is smaller than ``min_side_px`` on a side."""
    r0 = max(wa.row0, wb.row0)
    c0 = max(wa.col0, wb.col0)
    r1 = min(wa.row0 + wa.valid.shape[0], wb.row0 + wb.valid.shape[0])
    c1 = min(wa.col0 + wa.valid.shape[1], wb.col0 + wb.valid.shape[1])
    if r1 - r0 < min_side_px or c1 - c0 < min_side_px:
        return None

    def crop(w: WarpedView, what: np.ndarray) -> np.ndarray:
        return what[r0 - w.row0:r1 - w.row0, c0 - w.col0:c1 - w.col0]

    both = crop(wa, wa.valid) & crop(wb, wb.valid)
    # one pixel in from the covered edge: bilinear samples there mix in the border
    both = cv2.erode(both.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    rect = _valid_rectangle(both)
    if rect is None or rect[1] - rect[0] < min_side_px or rect[3] - rect[2] < min_side_px:
        return None
    ia, ib = crop(wa, wa.image), crop(wb, wb.image)
    if ia.ndim == 3:
        ia, ib = ia.mean(axis=2), ib.mean(axis=2)
    sl = (slice(rect[0], rect[1]), slice(rect[2], rect[3]))
    dx, dy = image_offset(ia[sl], ib[sl])
    return dx, dy, (r0 + rect[0], r0 + rect[1], c0 + rect[2], c0 + rect[3])


def seam_misregistration(views: list[CameraView], tracks: IntArray, surface: Surface,
                         georef: Georeference, min_overlap: float = 0.5) -> SeamStats:
    """Seam misregistration of the mosaic of ``views`` on ``georef`` (module docstring)."""
    pairs = seam_pairs(views, tracks, surface, min_overlap)
    offsets: list[SeamOffset] = []
    cache: OrderedDict[int, WarpedView | None] = OrderedDict()  # bounded: 64 warped views

    def warped(k: int) -> WarpedView | None:
        if k in cache:
            cache.move_to_end(k)
            return cache[k]
        cache[k] = warp_view(views[k], surface, georef)
        if len(cache) > 64:
            cache.popitem(last=False)
        return cache[k]

    for a, b in pairs:
        wa, wb = warped(a), warped(b)
        if wa is None or wb is None:
            continue
        got = view_offset(wa, wb)
        if got is not None:
            q0, q1, p0, p1 = got[2]
            x, y = georef.pixel_centres(0, 0, 1, 1)
            m = georef.metres_per_pixel
            centre = (float(x[0, 0]) + 0.5 * (p0 + p1 - 1) * m,
                      float(y[0, 0]) + 0.5 * (q0 + q1 - 1) * georef.row_step)
            offsets.append(SeamOffset(a, b, got[0], got[1], (q1 - q0, p1 - p0), centre))
    lengths = np.array([o.length_px for o in offsets])
    nan = float('nan')
    return SeamStats(len(pairs), len(offsets),
                     float(np.median(lengths)) if lengths.size else nan,
                     float(np.percentile(lengths, 95)) if lengths.size else nan,
                     float(lengths.max()) if lengths.size else nan,
                     georef.metres_per_pixel, offsets)
