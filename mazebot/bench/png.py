"""A minimal PNG writer and line drawing for the benchmark figures (no plotting library).

PNG: signature, IHDR, one zlib-compressed IDAT of filter-0 scanlines, IEND, each chunk
with its CRC-32 (PNG specification, ISO/IEC 15948, sections 5 and 11).
"""

from __future__ import annotations

import os
import struct
import tempfile
import zlib
from pathlib import Path

import numpy as np


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png(rgb: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) uint8 image, row 0 at the top."""
    if rgb.ndim != 3 or rgb.shape[2] != 3 or rgb.dtype != np.uint8:
        raise ValueError(f"expected an (H, W, 3) uint8 image, got {rgb.shape} {rgb.dtype}")
    h, w, _ = rgb.shape
    raw = np.concatenate([np.zeros((h, 1), np.uint8), rgb.reshape(h, w * 3)], axis=1).tobytes()
    ihdr = struct.pack(">IIBBBBB", w, h, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", ihdr) + _chunk(b"IDAT", zlib.compress(raw, 6)) + _chunk(b"IEND", b"")


def write_png(path: str | Path, rgb: np.ndarray) -> None:
    """Write atomically: a half-written figure never replaces a good one."""
    path = Path(path)
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(encode_png(rgb))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
