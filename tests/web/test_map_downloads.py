"""Map downloads: each file of one snapshot, under a dated name, the zip's PGM and YAML consistent."""

from __future__ import annotations

import io
import re
import zipfile

import numpy as np

from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.map_export import read_ros_map
from mazebot.state import SharedState
from mazebot.web import map_images
from mazebot.web.app import WebSettings, create_app

TOKEN = "2468"
STEM = re.compile(r"mazebot-map-\d{8}-\d{6}")


def _grid() -> OccupancyGrid:
    grid = OccupancyGrid(resolution_m=0.05, margin_m=0.1)
    angles = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    grid.integrate(np.array([0.1, -0.05, 0.3]), 0.8 * np.column_stack((np.cos(angles), np.sin(angles))),
                   np.ones(90, bool))
    return grid


async def test_the_zip_holds_a_pgm_and_the_yaml_that_places_it_and_map_server_reads_back_the_grid(
        aiohttp_client, tmp_path) -> None:
    state = SharedState()
    client = await aiohttp_client(create_app(state, settings=WebSettings(control_token=TOKEN, broadcast_hz=0)))
    resp = await client.get("/map.zip")
    assert resp.status == 404 and "no map yet" in (await resp.json())["error"]
    state.map = grid = _grid()
    resp = await client.get("/map.zip")
    assert resp.status == 200 and resp.content_type == "application/zip"
    name = re.fullmatch(r'attachment; filename="(.+)"', resp.headers["Content-Disposition"]).group(1)
    assert STEM.fullmatch(name.removesuffix(".zip")), name
    stem = name.removesuffix(".zip")
    with zipfile.ZipFile(io.BytesIO(await resp.read())) as zf:
        assert sorted(zf.namelist()) == [f"{stem}.pgm", f"{stem}.yaml"]
        zf.extractall(tmp_path)
    back = read_ros_map(tmp_path / f"{stem}.yaml")
    assert back.image == f"{stem}.pgm"
    np.testing.assert_array_equal(back.three_state, grid.three_state())
    assert back.origin[:2] == tuple(grid.origin_m) and back.resolution_m == grid.resolution_m


async def test_png_download_is_named_and_saved_and_plain_png_stays_inline(aiohttp_client) -> None:
    state = SharedState()
    state.map = grid = _grid()
    client = await aiohttp_client(create_app(state, settings=WebSettings(control_token=TOKEN, broadcast_hz=0)))
    saved = await client.get("/map.png?download")
    name = re.fullmatch(r'attachment; filename="(.+)"', saved.headers["Content-Disposition"]).group(1)
    assert STEM.fullmatch(name.removesuffix(".png")), name
    assert await saved.read() == map_images.encode_map_png(grid.three_state())
    plain = await client.get("/map.png")
    assert plain.headers["Content-Disposition"].startswith("inline;")
    assert (await client.get("/map.pgm")).headers["Content-Disposition"] == 'inline; filename="map.pgm"'


async def test_a_closed_page_wants_the_pin_for_downloads_too(aiohttp_client) -> None:
    state = SharedState()
    state.map = _grid()
    client = await aiohttp_client(
        create_app(state, settings=WebSettings(control_token=TOKEN, broadcast_hz=0, view_open=False)))
    assert (await client.get("/map.zip")).status == 401
    assert (await client.get("/map.zip", headers={"X-Mazebot-Token": TOKEN})).status == 200


def test_a_snapshot_is_a_copy_the_growing_map_cannot_change() -> None:
    grid = _grid()
    snap = map_images.take_snapshot(grid, now_unix_s=1_800_000_000.0)
    before = snap.three_state.copy()
    grid.integrate(np.array([2.0, 2.0, 0.0]), np.array([[0.5, 0.0]]), np.ones(1, bool))  # grows and moves
    np.testing.assert_array_equal(snap.three_state, before)
    assert STEM.fullmatch(snap.stem)
