"""The live map as files: ROS ``map_server`` PGM + YAML, and PNG.

PGM and PNG hold the map_saver values (254 free, 0 occupied, 205 unknown), north up:
image row 0 is the grid's northmost row. The YAML's ``origin`` is the world pose of the
image's bottom-left pixel, as map_server expects.
"""

from __future__ import annotations

import numpy as np

from mazebot.bench.png import encode_png

FREE_PIXEL = 254
OCCUPIED_PIXEL = 0
UNKNOWN_PIXEL = 205


def map_pixels(three_state: np.ndarray) -> np.ndarray:
    """uint8 image (north up) of a three-state grid (-1 unknown, 0 free, 100 occupied; row 0 south)."""
    t = np.asarray(three_state)
    img = np.full(t.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    img[t == 0] = FREE_PIXEL
    img[t == 100] = OCCUPIED_PIXEL
    return np.ascontiguousarray(img[::-1])


def encode_pgm(three_state: np.ndarray) -> bytes:
    """Binary PGM (P5, maxval 255)."""
    img = map_pixels(three_state)
    rows, cols = img.shape
    return f"P5\n# mazebot map\n{cols} {rows}\n255\n".encode() + img.tobytes()


def encode_map_png(three_state: np.ndarray) -> bytes:
    """PNG of the same grey levels as the PGM."""
    img = map_pixels(three_state)
    return encode_png(np.repeat(img[:, :, None], 3, axis=2))


def encode_yaml(resolution_m: float, origin_m: tuple[float, float], image: str = "map.pgm") -> bytes:
    """The map_server YAML next to ``image``."""
    return (
        f"image: {image}\n"
        f"resolution: {resolution_m:.6g}\n"
        f"origin: [{origin_m[0]:.6g}, {origin_m[1]:.6g}, 0.0]\n"
        "negate: 0\n"
        "occupied_thresh: 0.65\n"
        "free_thresh: 0.196\n"
    ).encode()
