"""The live map as files: ROS ``map_server`` PGM + YAML, and PNG.

The same files the exporter writes (:mod:`mazebot.slam.map_export`: 254 free, 0 occupied,
205 unknown, north up, ``mode: trinary``), so what a browser downloads from the robot and
what ``mazebot map export`` writes load the same in ``map_server``; this module only turns
them into bytes for a response.
"""

from __future__ import annotations

import numpy as np

from mazebot.png import encode_png
from mazebot.slam import map_export
from mazebot.slam.map_export import map_pixels


def encode_pgm(three_state: np.ndarray) -> bytes:
    """Binary PGM (P5, maxval 255), byte for byte the exporter's."""
    return map_export.encode_pgm(three_state)


def encode_map_png(three_state: np.ndarray) -> bytes:
    """Greyscale PNG of the same grey levels as the PGM, byte for byte the exporter's ``map.png``
    (one channel where an RGB copy of the same grey had three)."""
    return encode_png(map_pixels(three_state))


def encode_yaml(resolution_m: float, origin_m: tuple[float, float], image: str = "map.pgm") -> bytes:
    """The map_server YAML next to ``image``, the exporter's text (``mode: trinary`` included)."""
    return map_export.encode_yaml(resolution_m, origin_m, image).encode()
