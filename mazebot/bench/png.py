"""Line drawing for the benchmark figures, written as PNG (no plotting library).

The encoder is :func:`mazebot.png.encode_png`, the one the map exports use too.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from mazebot.files import write_atomic
from mazebot.png import encode_png


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write atomically (:func:`mazebot.files.write_atomic`): a half-written figure never replaces a good one."""
    write_atomic(path, encode_png(rgb))


class Canvas:
    """An RGB raster over a world rectangle: metres in, pixels out (north up)."""

    def __init__(self, bounds_m: tuple[float, float, float, float], pixels_per_m: float, margin_m: float = 0.05):
        xmin, ymin, xmax, ymax = bounds_m
        self.x0, self.y0 = xmin - margin_m, ymin - margin_m
        self.scale = pixels_per_m
        self.w = int(np.ceil((xmax - xmin + 2 * margin_m) * pixels_per_m))
        self.h = int(np.ceil((ymax - ymin + 2 * margin_m) * pixels_per_m))
        self.rgb = np.full((self.h, self.w, 3), 255, np.uint8)

    def to_px(self, xy_m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        xy = np.asarray(xy_m, dtype=float).reshape(-1, 2)
        cols = np.floor((xy[:, 0] - self.x0) * self.scale).astype(int)
        rows = self.h - 1 - np.floor((xy[:, 1] - self.y0) * self.scale).astype(int)
        return rows, cols

    def paint_mask(self, mask: np.ndarray, origin_m: tuple[float, float], resolution_m: float,
                   color: tuple[int, int, int]) -> None:
        """Paint the cells of a grid mask (row 0 south) in ``color``."""
        rows, cols = np.nonzero(mask)
        centres = np.column_stack(
            [origin_m[0] + (cols + 0.5) * resolution_m, origin_m[1] + (rows + 0.5) * resolution_m]
        )
        half = max(1, round(resolution_m * self.scale / 2))
        r, c = self.to_px(centres)
        for dr in range(-half + 1, half):
            for dc in range(-half + 1, half):
                self._set(r + dr, c + dc, color)
        if half == 1:
            self._set(r, c, color)

    def polyline(self, xy_m: np.ndarray, color: tuple[int, int, int], width_px: int = 1) -> None:
        xy = np.asarray(xy_m, dtype=float).reshape(-1, 2)
        if len(xy) < 2:
            return
        seg_len = np.hypot(*np.diff(xy, axis=0).T)
        steps = np.maximum(1, np.ceil(seg_len * self.scale * 2).astype(int))
        pieces = [
            a + np.outer(np.linspace(0, 1, n, endpoint=False), b - a)
            for a, b, n in zip(xy[:-1], xy[1:], steps, strict=True)
        ]
        pts = np.concatenate([*pieces, xy[-1:]])
        r, c = self.to_px(pts)
        for d in range(-(width_px // 2), width_px - width_px // 2):
            self._set(r + d, c, color)
            self._set(r, c + d, color)

    def _set(self, rows: np.ndarray, cols: np.ndarray, color: tuple[int, int, int]) -> None:
        ok = (rows >= 0) & (rows < self.h) & (cols >= 0) & (cols < self.w)
        self.rgb[rows[ok], cols[ok]] = color
