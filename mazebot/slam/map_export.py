"""Maps as files: ROS ``map_server`` PGM + YAML, and PNG; written atomically, read back.

The format of ROS ``map_server``/``map_saver`` (wiki.ros.org/map_server, "Map format"):

- the image is a binary PGM (P5, maxval 255), one pixel per cell, **north up**: image
  row 0 is the grid's northmost row (the grid's row 0 is south);
- ``map_saver`` values: 254 free, 0 occupied, 205 unknown;
- the YAML gives ``image``, ``resolution`` (m/pixel), ``origin`` ``[x, y, yaw]`` (the
  pose of the image's **bottom-left** pixel's corner in the map frame), ``negate``,
  ``occupied_thresh``, ``free_thresh`` and ``mode: trinary``. A reader computes
  ``p = (255 − v) / 255`` (``negate: 0``) and calls a cell occupied above
  ``occupied_thresh``, free below ``free_thresh``: 0 → 1.0 occupied, 254 → 0.004 free,
  205 → 0.196 unknown (not below 0.196).

The PNG is the same grey image (8-bit greyscale). Every file is written to a temporary
name in its directory and renamed into place, so a reader never sees half a map.

Example::

    write_ros_map(grid, "out/map")            # out/map.pgm and out/map.yaml
    write_map_png(grid.three_state(), "out/map.png")
    ros = read_ros_map("out/map.yaml")        # ros.three_state == grid.three_state()
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mazebot.errors import UsageError
from mazebot.files import write_atomic
from mazebot.png import encode_png
from mazebot.slam.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid

FREE_PIXEL = 254
OCCUPIED_PIXEL = 0
UNKNOWN_PIXEL = 205
OCCUPIED_THRESH = 0.65
FREE_THRESH = 0.196


class MapFileError(UsageError):
    """A map file is missing or not in the map_server format; the message names the file."""


@dataclass(frozen=True)
class RosMap:
    """A map read back: three-state grid (row 0 south, -1/0/100), cell size and origin (x, y, yaw)."""

    three_state: np.ndarray
    resolution_m: float
    origin: tuple[float, float, float]
    image: str


def map_pixels(three_state: np.ndarray) -> np.ndarray:
    """uint8 image, north up, of a three-state grid (-1 unknown, 0 free, 100 occupied; row 0 south)."""
    t = np.asarray(three_state)
    img = np.full(t.shape, UNKNOWN_PIXEL, dtype=np.uint8)
    img[t == FREE] = FREE_PIXEL
    img[t == OCCUPIED] = OCCUPIED_PIXEL
    return np.ascontiguousarray(img[::-1])


def encode_pgm(three_state: np.ndarray) -> bytes:
    """Binary PGM (P5, maxval 255) of the map."""
    img = map_pixels(three_state)
    rows, cols = img.shape
    return f"P5\n# mazebot map\n{cols} {rows}\n255\n".encode() + img.tobytes()


def encode_yaml(resolution_m: float, origin_m: tuple[float, float], image: str) -> str:
    """The map_server YAML describing ``image``."""
    return (
        f"image: {image}\n"
        f"resolution: {resolution_m:.9g}\n"
        f"origin: [{origin_m[0]:.9g}, {origin_m[1]:.9g}, 0.0]\n"
        "negate: 0\n"
        f"occupied_thresh: {OCCUPIED_THRESH}\n"
        f"free_thresh: {FREE_THRESH}\n"
        "mode: trinary\n"
    )


def write_map_png(three_state: np.ndarray, path: str | os.PathLike[str]) -> Path:
    """The map as a greyscale PNG (map_saver grey levels, north up), atomically."""
    path = Path(path)
    write_atomic(path, encode_png(map_pixels(three_state)))
    return path


def write_ros_map(grid: OccupancyGrid, stem: str | os.PathLike[str]) -> tuple[Path, Path]:
    """``STEM.pgm`` and ``STEM.yaml`` for ROS ``map_server``, atomically (image first)."""
    stem = Path(stem)
    pgm = stem.with_name(stem.name + ".pgm")
    yaml = stem.with_name(stem.name + ".yaml")
    write_atomic(pgm, encode_pgm(grid.three_state()))
    write_atomic(yaml, encode_yaml(grid.resolution_m, grid.origin_m, pgm.name).encode())
    return pgm, yaml


def read_ros_map(yaml_path: str | os.PathLike[str]) -> RosMap:
    """Read a map_server YAML and its PGM back into a three-state grid (row 0 south)."""
    yaml_path = Path(yaml_path)
    try:
        text = yaml_path.read_text(encoding="utf-8")
    except OSError as exc:
        raise MapFileError(f"map file {yaml_path} cannot be read ({exc.strerror or exc})") from None
    meta = _parse_yaml(text, yaml_path)
    try:
        image = str(meta["image"])
        resolution = float(meta["resolution"])
        origin = tuple(float(v) for v in _parse_list(meta["origin"]))
        negate = int(meta.get("negate", "0"))
        occupied = float(meta.get("occupied_thresh", OCCUPIED_THRESH))
        free = float(meta.get("free_thresh", FREE_THRESH))
    except (KeyError, ValueError) as exc:
        raise MapFileError(f"{yaml_path}: expected image, resolution and origin [x, y, yaw] ({exc})") from None
    if len(origin) != 3:
        raise MapFileError(f"{yaml_path}: origin must be [x, y, yaw], got {meta['origin']}")
    pgm_path = Path(image) if Path(image).is_absolute() else yaml_path.parent / image
    pixels = _read_pgm(pgm_path)
    p = pixels.astype(np.float64) / 255.0 if negate else (255.0 - pixels.astype(np.float64)) / 255.0
    three = np.full(pixels.shape, UNKNOWN, dtype=np.int8)
    three[p > occupied] = OCCUPIED
    three[p < free] = FREE
    return RosMap(three[::-1].copy(), resolution, (origin[0], origin[1], origin[2]), image)


def _parse_yaml(text: str, source: Path) -> dict[str, str]:
    """The flat ``key: value`` YAML map_server uses (no nesting beyond the origin list)."""
    out: dict[str, str] = {}
    for number, line in enumerate(text.splitlines(), start=1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        key, sep, value = line.partition(":")
        if not sep:
            raise MapFileError(f"{source} line {number}: expected 'key: value', got {line!r}")
        out[key.strip()] = value.strip().strip("'\"")
    return out


def _parse_list(text: str) -> list[str]:
    text = text.strip()
    if not (text.startswith("[") and text.endswith("]")):
        raise ValueError(f"expected a list like [x, y, yaw], got {text!r}")
    return [v.strip() for v in text[1:-1].split(",") if v.strip()]


def _read_pgm(path: Path) -> np.ndarray:
    """A binary (P5) or plain (P2) 8-bit PGM as uint8 (rows, cols), row 0 at the top."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise MapFileError(f"map image {path} cannot be read ({exc.strerror or exc})") from None
    fields: list[bytes] = []
    pos = 0
    while len(fields) < 4:  # magic, width, height, maxval; comments start with '#'
        while pos < len(data) and data[pos : pos + 1].isspace():
            pos += 1
        if data[pos : pos + 1] == b"#":
            pos = data.find(b"\n", pos) + 1 or len(data)
            continue
        start = pos
        while pos < len(data) and not data[pos : pos + 1].isspace():
            pos += 1
        if start == pos:
            raise MapFileError(f"{path}: truncated PGM header")
        fields.append(data[start:pos])
    magic, width, height, maxval = fields[0], int(fields[1]), int(fields[2]), int(fields[3])
    if maxval != 255 or magic not in (b"P5", b"P2"):
        raise MapFileError(f"{path}: expected an 8-bit PGM (P5 or P2, maxval 255), got {magic!r} maxval {maxval}")
    if magic == b"P5":
        body = data[pos + 1 : pos + 1 + width * height]
        if len(body) != width * height:
            raise MapFileError(f"{path}: expected {width * height} pixels, found {len(body)}")
        return np.frombuffer(body, dtype=np.uint8).reshape(height, width).copy()
    values = np.array(data[pos:].split(), dtype=np.int64)
    if values.size != width * height:
        raise MapFileError(f"{path}: expected {width * height} pixels, found {values.size}")
    return values.astype(np.uint8).reshape(height, width)
