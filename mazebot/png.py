"""PNG encoding without an imaging library: greyscale maps and colour figures.

Signature, IHDR, one zlib-compressed IDAT of filter-0 scanlines, IEND, each chunk with
its CRC-32 (PNG specification, ISO/IEC 15948, sections 5 and 11); 8 bits per sample,
colour type 0 (greyscale) for an (H, W) image and 2 (RGB) for an (H, W, 3) one.
"""

from __future__ import annotations

import struct
import zlib

import numpy as np

_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an (H, W) greyscale or (H, W, 3) RGB uint8 image, row 0 at the top.

    >>> encode_png(np.zeros((2, 3), np.uint8))[:8] == _SIGNATURE
    True
    """
    img = np.asarray(image)
    if img.dtype != np.uint8 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] == 3)):
        raise ValueError(f"expected an (H, W) or (H, W, 3) uint8 image, got {img.shape} {img.dtype}")
    h, w = img.shape[:2]
    colour_type = 0 if img.ndim == 2 else 2
    rows = np.ascontiguousarray(img).reshape(h, -1)
    raw = np.concatenate((np.zeros((h, 1), np.uint8), rows), axis=1).tobytes()
    header = struct.pack(">IIBBBBB", w, h, 8, colour_type, 0, 0, 0)
    return _SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", zlib.compress(raw, 6)) + _chunk(b"IEND", b"")
