"""The page can be added to a phone's home screen: a web-app manifest and PNG icons, served and valid."""

from __future__ import annotations

import importlib.util
import json
import re
import struct
import zlib
from pathlib import Path

import pytest

from mazebot.state import SharedState
from mazebot.web.app import WebSettings, create_app

REPO = Path(__file__).resolve().parents[2]


def _png_size(data: bytes) -> tuple[int, int]:
    """(width, height) of a PNG, after checking every chunk's CRC and that the pixels inflate."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat, size = 8, b"", None
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        assert struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])[0] == zlib.crc32(kind + body)
        if kind == b"IHDR":
            w, h, depth, colour = struct.unpack(">IIBB", body[:10])
            size, channels = (w, h), {0: 1, 2: 3, 6: 4}[colour]
            assert depth == 8
        elif kind == b"IDAT":
            idat += body
        pos += 12 + length
    assert size is not None and len(zlib.decompress(idat)) == size[1] * (1 + size[0] * channels)
    return size


@pytest.fixture
async def client(aiohttp_client):
    return await aiohttp_client(create_app(SharedState(), settings=WebSettings(control_token="2468", broadcast_hz=0)))


async def test_the_page_links_a_manifest_whose_icons_are_served_at_their_sizes(client) -> None:
    html = await (await client.get("/")).text()
    (href,) = re.findall(r'<link rel="manifest" href="([^"]+)"', html)
    resp = await client.get(href)
    assert resp.status == 200 and resp.content_type == "application/manifest+json"
    manifest = json.loads(await resp.text())
    assert manifest["name"] == "mazebot" and manifest["start_url"] == "/" and manifest["display"] == "standalone"
    sizes = set()
    for icon in manifest["icons"]:
        data = await (await client.get(icon["src"])).read()
        w, h = _png_size(data)
        assert icon["sizes"] == f"{w}x{h}" and icon["type"] == "image/png"
        sizes.add(w)
    assert {192, 512} <= sizes  # what Chrome asks of an installable app
    (touch,) = re.findall(r'<link rel="apple-touch-icon" href="([^"]+)"', html)  # iOS' home screen
    assert _png_size(await (await client.get(touch)).read()) == (180, 180)


def test_the_committed_icons_are_what_tools_make_icons_draws() -> None:
    spec = importlib.util.spec_from_file_location("make_icons", REPO / "tools" / "make_icons.py")
    make_icons = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(make_icons)
    for size in make_icons.SIZES:
        assert make_icons.icon_path(size).read_bytes() == make_icons.icon_png(size), size
