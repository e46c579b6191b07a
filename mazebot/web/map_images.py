"""The live map as files: ROS ``map_server`` PGM + YAML, and PNG.

The same files the exporter writes (:mod:`mazebot.slam.map_export`: 254 free, 0 occupied,
205 unknown, north up, ``mode: trinary``), so what a browser downloads from the robot and
what ``mazebot map export`` writes load the same in ``map_server``; this module only turns
them into bytes for a response.

A download is made of one :class:`MapSnapshot`: the cells, the cell size and the origin
read together on the event loop (the map's only writer runs there too), so a PGM and the
YAML that places it can never come from two different versions of a growing map.
"""

from __future__ import annotations

import io
import time
import zipfile
from dataclasses import dataclass
from typing import Any

import numpy as np

from mazebot.png import encode_png
from mazebot.slam import map_export
from mazebot.slam.map_export import map_pixels

#: Download names: ``mazebot-map-20261203-153012`` (the robot's local time the map was read).
FILENAME_PREFIX = "mazebot-map"


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


@dataclass(frozen=True)
class MapSnapshot:
    """One version of the live map, copied: everything a download needs, nothing shared with SLAM."""

    three_state: np.ndarray
    resolution_m: float
    origin_m: tuple[float, float]
    generation: int
    taken_at_unix_s: float

    @property
    def stem(self) -> str:
        """The file name without suffix, e.g. ``mazebot-map-20261203-153012``."""
        return f"{FILENAME_PREFIX}-{time.strftime('%Y%m%d-%H%M%S', time.localtime(self.taken_at_unix_s))}"


def take_snapshot(grid: Any, now_unix_s: float | None = None) -> MapSnapshot:
    """Copy the live grid (an :class:`~mazebot.slam.grid.OccupancyGrid`). Call it on the loop,
    with no ``await`` in between, so cells and geometry are of the same moment."""
    return MapSnapshot(
        three_state=grid.three_state(),
        resolution_m=float(grid.resolution_m),
        origin_m=(float(grid.origin_m[0]), float(grid.origin_m[1])),
        generation=int(getattr(grid, "generation", 0)),
        taken_at_unix_s=time.time() if now_unix_s is None else now_unix_s,
    )


def encode_ros_zip(snap: MapSnapshot) -> bytes:
    """A zip of ``STEM.pgm`` and ``STEM.yaml`` (its ``image:`` names that PGM): the map as
    ``map_server`` loads it once unpacked, both files of ``snap``."""
    pgm_name, yaml_name = f"{snap.stem}.pgm", f"{snap.stem}.yaml"
    stamp = time.localtime(snap.taken_at_unix_s)[:6]
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in ((pgm_name, encode_pgm(snap.three_state)),
                           (yaml_name, encode_yaml(snap.resolution_m, snap.origin_m, pgm_name))):
            info = zipfile.ZipInfo(name, date_time=stamp)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16  # rw-r--r-- when unpacked
            zf.writestr(info, data)
    return out.getvalue()
