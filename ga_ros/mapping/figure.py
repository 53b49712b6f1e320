"""The mosaic before and after the alignment in one small PNG (ROS-free).

Top: the F2F (before) and GA (after) mosaics side by side, scaled to ``panel_px`` wide. Bottom,
for each: a zoom on one seam (the pair of keyframes on neighbouring tracks that F2F misregisters
most), the two keyframes' images overlaid in colour -- red the earlier track's keyframe, cyan
the later one's: where they agree the zoom is grey, a misregistration shows as red / cyan
fringes.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from ga_ros.mapping.mosaic import (
    CameraView,
    Georeference,
    Mosaic,
    Surface,
    warp_view,
    write_png,
)


@dataclass
class MosaicPanel:
    """One trajectory's mosaic and what the seam zoom needs.

    Attributes
    ----------
    label : the caption (e.g. ``'F2F (before): seams 0.53 px'``).
    mosaic : the mosaic.
    views, surface : the keyframes and ground it was built from.
    """

    label: str
    mosaic: Mosaic
    views: list[CameraView]
    surface: Surface


def _grey_to_bgr(img: np.ndarray) -> np.ndarray:
    return img if img.ndim == 3 else cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)


def _caption(img: np.ndarray, text: str) -> np.ndarray:
    bar = np.full((22, img.shape[1], 3), 255, np.uint8)
    cv2.putText(bar, text, (4, 16), cv2.FONT_HERSHEY_SIMPLEX, 0.45, (0, 0, 0), 1, cv2.LINE_AA)
    return np.vstack([bar, img])


def seam_zoom(panel: MosaicPanel, a: int, b: int, centre_xy: tuple[float, float],
              size_px: int = 40, zoom: int = 8) -> np.ndarray:
    """(size_px * zoom)^2 BGR overlay of views ``a`` (red) and ``b`` (cyan) of the panel around
    map point ``centre_xy`` (m), on the panel's mosaic grid, nearest-neighbour zoomed."""
    g: Georeference = panel.mosaic.georef
    m = g.metres_per_pixel
    col = int(round((centre_xy[0] - g.x_min) / m)) - size_px // 2
    row = int(round(float(g.row_of(centre_xy[1])))) - size_px // 2
    layers = []
    for k in (a, b):
        out = np.zeros((size_px, size_px), np.float32)
        wv = warp_view(panel.views[k], panel.surface, g)
        if wv is not None:
            img = np.where(wv.valid, wv.image if wv.image.ndim == 2 else wv.image.mean(axis=2), 0)
            r0, c0 = row - wv.row0, col - wv.col0
            rs = slice(max(r0, 0), max(min(r0 + size_px, img.shape[0]), 0))
            cs = slice(max(c0, 0), max(min(c0 + size_px, img.shape[1]), 0))
            part = img[rs, cs]
            out[rs.start - r0:rs.start - r0 + part.shape[0],
                cs.start - c0:cs.start - c0 + part.shape[1]] = part
        layers.append(np.clip(out, 0, 255).astype(np.uint8))
    bgr = np.dstack([layers[1], layers[1], layers[0]])  # B, G from b (cyan); R from a
    return cv2.resize(bgr, None, fx=zoom, fy=zoom, interpolation=cv2.INTER_NEAREST)


def write_compare_figure(path: str | Path, before: MosaicPanel, after: MosaicPanel,
                         pair: tuple[int, int] | None, centre_xy: tuple[float, float] | None,
                         panel_px: int = 320) -> str:
    """Write the before / after figure (module docstring) as PNG; returns its path.

    ``pair`` indexes both panels' ``views`` (the same keyframes), ``centre_xy`` is the seam's
    map point (m); None: no zoom row."""
    cols = []
    for p in (before, after):
        img = _grey_to_bgr(p.mosaic.image)
        scale = panel_px / img.shape[1]
        small = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA)
        col = [_caption(small, p.label)]
        if pair is not None and centre_xy is not None:
            z = seam_zoom(p, pair[0], pair[1], centre_xy)
            z = cv2.resize(z, (panel_px, panel_px), interpolation=cv2.INTER_NEAREST)
            col.append(_caption(z, 'seam zoom: red / cyan = the two tracks'))
        cols.append(col)
    h = max(sum(c.shape[0] for c in col) for col in cols)
    panels = []
    for col in cols:
        stack = np.vstack(col)
        pad = np.full((h - stack.shape[0], panel_px, 3), 255, np.uint8)
        panels.append(np.vstack([stack, pad]))
    gap = np.full((h, 8, 3), 255, np.uint8)
    fig = np.hstack([panels[0], gap, panels[1]])
    return str(write_png(path, fig, compression=9))
