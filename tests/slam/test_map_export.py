"""Map files: ROS map_server PGM + YAML and PNG, parsed back to the same grid."""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from mazebot.slam.grid import FREE, OCCUPIED, UNKNOWN, OccupancyGrid
from mazebot.slam.map_export import (
    FREE_PIXEL,
    OCCUPIED_PIXEL,
    UNKNOWN_PIXEL,
    MapFileError,
    encode_pgm,
    read_ros_map,
    write_map_png,
    write_ros_map,
)


@pytest.fixture
def grid() -> OccupancyGrid:
    """A room seen from inside: free floor, occupied walls, unknown beyond; not square."""
    g = OccupancyGrid(resolution_m=0.05, margin_m=0.2)
    g.integrate(np.zeros(3), np.array([[0.0, -1.0]]), np.array([False]))  # a free ray south: not symmetric
    angles = np.linspace(-np.pi, np.pi, 720, endpoint=False)
    # a 1.0 x 0.6 m box around (0.3, -0.1): hits on its walls
    half_x, half_y = 0.5, 0.3
    t = np.minimum(half_x / np.maximum(np.abs(np.cos(angles)), 1e-9), half_y / np.maximum(np.abs(np.sin(angles)), 1e-9))
    centre = np.array([0.3, -0.1])
    ends = centre + np.column_stack((t * np.cos(angles), t * np.sin(angles)))
    for _ in range(3):
        g.integrate(np.array([*centre, 0.0]), ends, np.ones(len(ends), dtype=bool))
    return g


def test_pgm_and_yaml_parse_back_to_the_same_grid(grid: OccupancyGrid, tmp_path: Path) -> None:
    pgm, yaml = write_ros_map(grid, tmp_path / "map")
    assert (pgm.name, yaml.name) == ("map.pgm", "map.yaml")
    back = read_ros_map(yaml)
    three = grid.three_state()
    assert {int(v) for v in np.unique(three)} == {UNKNOWN, FREE, OCCUPIED}  # the test covers every value
    np.testing.assert_array_equal(back.three_state, three)
    assert back.resolution_m == pytest.approx(grid.resolution_m)
    assert back.origin[:2] == pytest.approx(grid.origin_m) and back.origin[2] == 0.0
    assert back.image == "map.pgm"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["map.pgm", "map.yaml"]  # no temporary files left


def test_pgm_is_map_saver_format_north_up(grid: OccupancyGrid) -> None:
    three = grid.three_state()
    data = encode_pgm(three)
    header = data.split(b"\n", 4)
    assert header[0] == b"P5" and header[2] == f"{three.shape[1]} {three.shape[0]}".encode() and header[3] == b"255"
    pixels = np.frombuffer(header[4], dtype=np.uint8).reshape(three.shape)
    assert set(np.unique(pixels).tolist()) == {OCCUPIED_PIXEL, UNKNOWN_PIXEL, FREE_PIXEL}
    # image row 0 is the northmost grid row (map_server: origin at the bottom-left pixel)
    assert not np.array_equal(three, three[::-1])  # so the orientation shows
    np.testing.assert_array_equal(pixels == FREE_PIXEL, three[::-1] == FREE)
    np.testing.assert_array_equal(pixels == OCCUPIED_PIXEL, three[::-1] == OCCUPIED)


def test_yaml_has_every_map_server_key(grid: OccupancyGrid, tmp_path: Path) -> None:
    _, yaml = write_ros_map(grid, tmp_path / "m")
    text = yaml.read_text()
    for key in ("image: m.pgm", "resolution: 0.05", "origin: [", "negate: 0", "occupied_thresh: 0.65",
                "free_thresh: 0.196"):
        assert key in text
    # map_server's reading of the three grey levels with those thresholds
    p = (255 - np.array([FREE_PIXEL, OCCUPIED_PIXEL, UNKNOWN_PIXEL])) / 255.0
    assert p[0] < 0.196 and p[1] > 0.65 and 0.196 <= p[2] <= 0.65


def test_png_is_the_same_grey_image(grid: OccupancyGrid, tmp_path: Path) -> None:
    path = write_map_png(grid.three_state(), tmp_path / "map.png")
    data = path.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    width, height, depth, colour = struct.unpack(">IIBB", data[16:26])
    three = grid.three_state()
    assert (width, height, depth, colour) == (three.shape[1], three.shape[0], 8, 0)
    idat_len = struct.unpack(">I", data[33:37])[0]
    raw = np.frombuffer(zlib.decompress(data[41 : 41 + idat_len]), dtype=np.uint8).reshape(height, width + 1)
    assert not raw[:, 0].any()  # filter type 0 on every row
    np.testing.assert_array_equal(raw[:, 1:], np.frombuffer(encode_pgm(three).split(b"\n", 4)[4], np.uint8).reshape(
        three.shape))


def test_reading_a_broken_map_says_which_file(tmp_path: Path) -> None:
    (tmp_path / "bad.yaml").write_text("image: missing.pgm\nresolution: 0.05\norigin: [0, 0, 0]\n")
    with pytest.raises(MapFileError, match=r"missing\.pgm"):
        read_ros_map(tmp_path / "bad.yaml")
    (tmp_path / "worse.yaml").write_text("resolution: 0.05\n")
    with pytest.raises(MapFileError, match=r"worse\.yaml"):
        read_ros_map(tmp_path / "worse.yaml")
