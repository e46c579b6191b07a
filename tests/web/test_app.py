"""The web application through aiohttp's test client: routes, auth, websocket sequences, backpressure."""

from __future__ import annotations

import asyncio
import json
import socket
import struct
import zlib
from typing import Any

import aiohttp
import numpy as np
import pytest
from aiohttp import WSMsgType, web
from aiohttp.test_utils import TestClient, TestServer

from mazebot.clock import RealClock
from mazebot.png import encode_png
from mazebot.slam.grid import OccupancyGrid
from mazebot.slam.map_export import map_pixels, read_ros_map, write_ros_map
from mazebot.state import SharedState
from mazebot.web.app import BROADCASTER_KEY, WebSettings, create_app
from mazebot.web.protocol import KIND_DELTA, KIND_FULL, decode_packet

TOKEN = "2468"


@pytest.fixture
def state() -> SharedState:
    return SharedState()


def _app(state: SharedState, **settings: Any) -> web.Application:
    return create_app(state, settings=WebSettings(control_token=TOKEN, broadcast_hz=0, **settings))


async def _receive_packet(ws) -> Any:
    """The next binary packet, skipping text frames (hello, heartbeat)."""
    while True:
        msg = await asyncio.wait_for(ws.receive(), 5)
        if msg.type == WSMsgType.BINARY:
            return decode_packet(msg.data)
        assert msg.type == WSMsgType.TEXT, msg


async def _receive_text(ws, kind: str) -> dict:
    while True:
        msg = await asyncio.wait_for(ws.receive(), 5)
        if msg.type == WSMsgType.TEXT and json.loads(msg.data)["type"] == kind:
            return json.loads(msg.data)
        assert msg.type in (WSMsgType.TEXT, WSMsgType.BINARY), msg


# -- plain routes -------------------------------------------------------------------------


async def test_page_assets_and_status_are_served(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    resp = await client.get("/")
    assert resp.status == 200
    html = await resp.text()
    assert "/static/app.js" in html and "/static/vendor/d3.min.js" in html and "/static/style.css" in html
    for path in ("/static/app.js", "/static/style.css", "/static/vendor/d3.min.js", "/static/vendor/d3.LICENSE"):
        assert (await client.get(path)).status == 200, path
    assert "d3js.org v7" in await (await client.get("/static/vendor/d3.min.js")).text()
    status = await (await client.get("/api/status")).json()
    assert status["state"] == "idle" and status["map"] is None and status["coverage"] is None
    assert status["versions"]["protocol"] == 1 and status["versions"]["mazebot"] == status["version"]
    assert status["cpu"]["control tick"] == {"calls": 0, "cpu_ms_per_s": None, "p50_ms": None, "p99_ms": None}


async def test_status_says_where_the_cpu_goes(aiohttp_client, state) -> None:
    state.cpu.started_s = RealClock().now_s() - 10.0  # the daemon started ten seconds ago
    state.cpu.part("slam per revolution").add(0.004)
    state.cpu.part("slam per revolution").add(0.006)
    client = await aiohttp_client(_app(state))
    slam = (await (await client.get("/api/status")).json())["cpu"]["slam per revolution"]
    assert slam["calls"] == 2 and slam["p99_ms"] == pytest.approx(6.0, abs=0.05)
    assert slam["cpu_ms_per_s"] == pytest.approx(1.0, rel=0.05)  # 10 ms over ~10 s


async def test_the_page_weighs_under_350_kb_and_travels_compressed(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    raw = wire = 0
    for path in ("/", "/static/app.js", "/static/style.css", "/static/vendor/d3.min.js"):
        resp = await client.get(path, headers={"Accept-Encoding": "gzip, deflate"}, auto_decompress=False)
        assert resp.headers.get("Content-Encoding") in ("gzip", "deflate"), path
        wire += len(await resp.read())
        raw += len(await (await client.get(path)).read())
    assert raw <= 350_000 and wire <= 120_000, (raw, wire)


async def test_the_page_needs_nothing_from_the_internet(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    for path in ("/", "/static/app.js", "/static/style.css"):
        text = await (await client.get(path)).text()
        assert "http://" not in text.replace("http://www.w3.org", "") and "https://" not in text, path


async def test_map_files_404_without_a_map_then_png_pgm_yaml(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    for path in ("/map.png", "/map.pgm", "/map.yaml"):
        resp = await client.get(path)
        assert resp.status == 404 and "no map yet" in (await resp.json())["error"]
    grid = OccupancyGrid(resolution_m=0.05, margin_m=0.1)
    angles = np.linspace(0, 2 * np.pi, 60, endpoint=False)
    grid.integrate(np.zeros(3), np.column_stack((np.cos(angles), np.sin(angles))), np.ones(60, bool))
    state.map = grid
    png = await (await client.get("/map.png")).read()
    assert png.startswith(b"\x89PNG\r\n\x1a\n")
    pgm = await (await client.get("/map.pgm")).read()
    rows, cols = grid.shape
    header = f"P5\n# mazebot map\n{cols} {rows}\n255\n".encode()
    assert pgm.startswith(header)
    pixels = np.frombuffer(pgm[len(header) :], np.uint8).reshape(rows, cols)
    # the PNG is greyscale (IHDR colour type 0, 8 bits) with the PGM's pixels, as the exporter writes it
    assert struct.unpack(">IIBB", png[16:26]) == (cols, rows, 8, 0)
    idat_len = struct.unpack(">I", png[33:37])[0]
    raw = np.frombuffer(zlib.decompress(png[41 : 41 + idat_len]), np.uint8).reshape(rows, cols + 1)
    np.testing.assert_array_equal(raw[:, 1:], pixels)
    assert png == encode_png(map_pixels(grid.three_state()))
    three = grid.three_state()[::-1]  # PGM row 0 is north
    assert set(np.unique(pixels)) <= {0, 205, 254}
    np.testing.assert_array_equal(pixels == 0, three == 100)
    np.testing.assert_array_equal(pixels == 254, three == 0)
    yaml = await (await client.get("/map.yaml")).text()
    assert "image: map.pgm" in yaml and "resolution: 0.05" in yaml
    assert f"origin: [{grid.origin_m[0]:.9g}, {grid.origin_m[1]:.9g}, 0.0]" in yaml


async def test_the_served_map_files_are_the_exporters_and_load_back(aiohttp_client, state, tmp_path) -> None:
    """What a browser downloads from /map.pgm and /map.yaml is what ``write_ros_map`` writes
    (``mode: trinary`` included), and map_server's reading of it gives back the live grid."""
    client = await aiohttp_client(_app(state))
    grid = OccupancyGrid(resolution_m=0.05, margin_m=0.1)
    angles = np.linspace(0, 2 * np.pi, 90, endpoint=False)
    grid.integrate(np.array([0.1, -0.05, 0.3]), 0.8 * np.column_stack((np.cos(angles), np.sin(angles))),
                   np.ones(90, bool))
    state.map = grid
    served = tmp_path / "served"
    served.mkdir()
    (served / "map.pgm").write_bytes(await (await client.get("/map.pgm")).read())
    (served / "map.yaml").write_bytes(await (await client.get("/map.yaml")).read())
    (tmp_path / "exported").mkdir()
    exported_pgm, exported_yaml = write_ros_map(grid, tmp_path / "exported" / "map")
    assert "mode: trinary" in (served / "map.yaml").read_text()
    assert (served / "map.yaml").read_bytes() == exported_yaml.read_bytes()
    assert (served / "map.pgm").read_bytes() == exported_pgm.read_bytes()
    back = read_ros_map(served / "map.yaml")
    np.testing.assert_array_equal(back.three_state, grid.three_state())
    assert back.resolution_m == pytest.approx(0.05)
    assert back.origin[:2] == pytest.approx(tuple(grid.origin_m))


# -- control over HTTP ------------------------------------------------------------------------


async def test_http_start_stop_refuse_missing_and_wrong_tokens_and_nothing_is_queued(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    resp = await client.post("/api/start")
    assert resp.status == 401 and "WWW-Authenticate" in resp.headers
    resp = await client.post("/api/start", headers={"X-Mazebot-Token": "1111"})
    assert resp.status == 403
    resp = await client.post("/api/stop", headers={"Authorization": "Bearer 9999"})
    assert resp.status == 403
    assert state.commands.empty()
    resp = await client.post("/api/start", headers={"X-Mazebot-Token": TOKEN})
    assert resp.status == 200 and await resp.json() == {"accepted": "start"}
    resp = await client.post("/api/stop", headers={"Authorization": f"Bearer {TOKEN}"})
    assert resp.status == 200
    assert [state.commands.get_nowait(), state.commands.get_nowait()] == ["start", "stop"]


async def test_repeated_wrong_pins_lock_the_client_out(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    for _ in range(5):
        assert (await client.post("/api/start", headers={"X-Mazebot-Token": "0000"})).status == 403
    assert (await client.post("/api/start", headers={"X-Mazebot-Token": TOKEN})).status == 429
    assert state.commands.empty()


async def test_foreign_origins_cannot_control_or_open_the_websocket(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    evil = {"Origin": "http://evil.example", "X-Mazebot-Token": TOKEN}
    assert (await client.post("/api/start", headers=evil)).status == 403
    assert state.commands.empty()
    with pytest.raises(aiohttp.WSServerHandshakeError) as err:
        await client.ws_connect("/ws", headers={"Origin": "http://evil.example"})
    assert err.value.status == 403
    own = f"http://{client.server.host}:{client.server.port}"
    ws = await client.ws_connect("/ws", headers={"Origin": own})
    assert (await _receive_packet(ws)).kind == KIND_FULL
    await ws.close()


async def test_viewing_can_require_the_token(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state, view_open=False))
    assert (await client.get("/api/status")).status == 401
    assert (await client.get("/map.png")).status == 401
    assert (await client.get("/api/status", headers={"X-Mazebot-Token": TOKEN})).status == 200
    ws = await client.ws_connect("/ws")
    error = await _receive_text(ws, "error")
    assert error["status"] == 401
    msg = await ws.receive()
    assert msg.type == WSMsgType.CLOSE and ws.close_code == 4401
    ws = await client.ws_connect(f"/ws?token={TOKEN}")
    assert (await _receive_packet(ws)).kind == KIND_FULL
    await ws.close()


# -- the websocket -------------------------------------------------------------------------------


async def test_connect_full_then_deltas_in_sequence_and_a_gap_answered_by_resync(aiohttp_client, state, fake_grid,
                                                                                 mirror) -> None:
    grid = fake_grid()
    state.map = grid
    app = _app(state)
    client = await aiohttp_client(app)
    broadcaster = app[BROADCASTER_KEY]
    ws = await client.ws_connect("/ws")
    hello = await _receive_text(ws, "hello")
    assert hello["protocol"] == 1 and hello["resync_every"] == 50
    page = mirror()
    first = await _receive_packet(ws)
    assert first.kind == KIND_FULL and first.map is not None
    page.apply(encode_again(first))
    for step in range(3):
        grid.cells[step, step] = 100
        broadcaster.tick()
        delta = await _receive_packet(ws)
        assert delta.kind == KIND_DELTA and delta.seq == first.seq + step + 1
        assert len(delta.map) == 1
    # the page misses a packet (pretend: skip one) and asks for a resync
    grid.cells[5, 5] = 0
    broadcaster.tick()
    await _receive_packet(ws)  # "lost"
    grid.cells[6, 6] = 0
    broadcaster.tick()
    after_gap = await _receive_packet(ws)
    assert after_gap.seq == first.seq + 5
    await ws.send_json({"type": "resync"})
    full = await _receive_packet(ws)
    assert full.kind == KIND_FULL and full.seq == after_gap.seq
    np.testing.assert_array_equal(full.map.codes, (grid.cells == 0) * 1 + (grid.cells == 100) * 2)
    await ws.close()


def encode_again(packet) -> bytes:
    from mazebot.web.protocol import encode_packet

    return encode_packet(packet)


async def test_every_50th_packet_over_the_socket_is_full(aiohttp_client, state) -> None:
    app = _app(state, send_queue_packets=200)
    client = await aiohttp_client(app)
    ws = await client.ws_connect("/ws")
    first = await _receive_packet(ws)
    for step in range(100):
        state.pose.x_m = 0.001 * (step + 1)
        app[BROADCASTER_KEY].tick()
    packets = [await _receive_packet(ws) for _ in range(100)]
    assert [p.seq for p in packets] == list(range(first.seq + 1, first.seq + 101))
    assert [p.seq for p in packets if p.kind == KIND_FULL] == [50, 100]
    await ws.close()


async def test_start_and_stop_over_the_websocket_need_the_token(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    ws = await client.ws_connect("/ws")
    await ws.send_json({"type": "start"})
    reply = await _receive_text(ws, "reply")
    assert (reply["ok"], reply["status"]) == (False, 401)
    await ws.send_json({"type": "start", "token": "1357"})
    assert (await _receive_text(ws, "reply"))["status"] == 403
    assert state.commands.empty()
    await ws.send_json({"type": "start", "token": TOKEN})
    assert (await _receive_text(ws, "reply")) == {"type": "reply", "command": "start", "ok": True, "status": 200,
                                                   "message": "accepted"}
    await ws.send_json({"type": "stop", "token": TOKEN})
    await _receive_text(ws, "reply")
    assert [state.commands.get_nowait(), state.commands.get_nowait()] == ["start", "stop"]
    await ws.send_str("hello robot")
    assert (await _receive_text(ws, "error"))["status"] == 400
    await ws.close()


async def test_shutdown_closes_every_socket_with_going_away(state) -> None:
    server = TestServer(_app(state))
    client = TestClient(server)
    await client.start_server()
    sockets = [await client.ws_connect("/ws") for _ in range(3)]
    for ws in sockets:
        await _receive_packet(ws)
    closing = asyncio.create_task(server.close())
    for ws in sockets:
        while (msg := await asyncio.wait_for(ws.receive(), 5)).type is not WSMsgType.CLOSE:
            assert msg.type in (WSMsgType.TEXT, WSMsgType.BINARY), msg
        assert msg.data == aiohttp.WSCloseCode.GOING_AWAY and msg.extra == "server shutting down"
    await asyncio.wait_for(closing, 5)
    await client.close()


def _small_buffer_socket(addr_info) -> socket.socket:
    """A client socket with a tiny receive buffer, set before connecting: a phone on bad Wi-Fi."""
    family, kind, proto, _, _ = addr_info
    sock = socket.socket(family=family, type=kind, proto=proto)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    return sock


async def test_a_viewer_that_stops_reading_is_dropped_to_full_maps_and_never_stalls_the_others(
    aiohttp_client, state, fake_grid, mirror
) -> None:
    rng = np.random.default_rng(7)
    grid = fake_grid(rows=400, cols=400)
    state.map = grid
    app = _app(state, send_queue_packets=4)

    @web.middleware
    async def small_send_buffer(request: web.Request, handler):
        if request.headers.get("X-Test-Slow"):  # the server side of a phone on bad Wi-Fi
            request.transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 8192)
        return await handler(request)

    app.middlewares.append(small_send_buffer)
    client = await aiohttp_client(app)
    broadcaster = app[BROADCASTER_KEY]
    async with aiohttp.ClientSession(connector=aiohttp.TCPConnector(socket_factory=_small_buffer_socket)) as session:
        slow = await session.ws_connect(client.make_url("/ws"), max_msg_size=0, headers={"X-Test-Slow": "1"})
        # ... and never reads again
        fast = await client.ws_connect("/ws", max_msg_size=0)
        page = mirror()
        for _ in range(60):
            flip = rng.random(grid.cells.shape) < 0.12  # big deltas
            grid.cells[flip] = rng.choice(np.array([-1, 0, 100], np.int8), int(flip.sum()))
            broadcaster.tick()
            while True:  # the fast one keeps up, in sequence
                p = await _receive_packet(fast)
                assert page.apply(encode_again(p)), "the fast viewer saw a gap"
                if p.seq == broadcaster.seq:
                    break
            for v in broadcaster.viewers:
                assert v.queued <= 4  # the bound, never growing
        assert page.matches(grid)
        dropped = sorted(v.dropped for v in broadcaster.viewers)
        assert dropped[0] == 0 and dropped[1] > 0, dropped
        slow_viewer = max(broadcaster.viewers, key=lambda v: v.dropped)
        assert isinstance(slow_viewer.pending()[0], bytes)
        assert decode_packet(slow_viewer.pending()[0]).kind == KIND_FULL  # what it gets next
        await fast.close()
        assert not slow.closed
