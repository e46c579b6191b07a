"""Bad input from the network, against the real aiohttp server: each misbehaving client gets a
one-line error (and is closed when it must be), the others and the robot's state are untouched,
and nothing lands in the server log as an exception."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import gc
import json
import logging
import os
import socket
import struct
import tracemalloc
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
import pytest
from aiohttp import WSMsgType, web

from mazebot.state import RunState, SharedState
from mazebot.web import app as web_app
from mazebot.web import auth
from mazebot.web.app import BROADCASTER_KEY, WebSettings, create_app
from mazebot.web.protocol import KIND_FULL, decode_packet

TOKEN = "246810"
ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture
def state() -> SharedState:
    return SharedState()


@pytest.fixture
def server_log(caplog: pytest.LogCaptureFixture) -> pytest.LogCaptureFixture:
    """Every record of the server (mazebot and aiohttp), at DEBUG."""
    caplog.set_level(logging.DEBUG)
    return caplog


def assert_no_exception_logged(caplog: pytest.LogCaptureFixture) -> None:
    """Nothing at WARNING or above carries a traceback, nothing at ERROR at all (aiohttp's own DEBUG
    records of refused requests are below the daemon's log level)."""
    bad = [r for r in caplog.records if r.levelno >= logging.ERROR or (r.exc_info and r.levelno >= logging.INFO)]
    assert not bad, [f"{r.name}: {r.getMessage()}" for r in bad]


def _app(state: SharedState, **settings: Any) -> web.Application:
    return create_app(state, settings=WebSettings(control_token=TOKEN, broadcast_hz=0, **settings))


async def _next(ws: aiohttp.ClientWebSocketResponse) -> aiohttp.WSMessage:
    return await asyncio.wait_for(ws.receive(), 10)


async def _text(ws: aiohttp.ClientWebSocketResponse, kind: str) -> dict[str, Any]:
    """The next text message of ``kind``, skipping packets and other text."""
    while True:
        msg = await _next(ws)
        assert msg.type in (WSMsgType.TEXT, WSMsgType.BINARY), msg
        if msg.type == WSMsgType.TEXT and json.loads(msg.data)["type"] == kind:
            return json.loads(msg.data)


async def _packet(ws: aiohttp.ClientWebSocketResponse) -> Any:
    while True:
        msg = await _next(ws)
        assert msg.type in (WSMsgType.TEXT, WSMsgType.BINARY), msg
        if msg.type == WSMsgType.BINARY:
            return decode_packet(msg.data)


async def _close_of(ws: aiohttp.ClientWebSocketResponse) -> tuple[list[dict[str, Any]], aiohttp.WSMessage]:
    """The text messages up to the close, and the close."""
    texts = []
    while True:
        msg = await _next(ws)
        if msg.type == WSMsgType.TEXT:
            texts.append(json.loads(msg.data))
        elif msg.type != WSMsgType.BINARY:
            return texts, msg


# -- a raw websocket client (RFC 6455 by hand: junk the aiohttp client would refuse to send) -----------


class RawWebSocket:
    """A non-blocking TCP socket that does the websocket handshake and then whatever the test wants."""

    def __init__(self, sock: socket.socket) -> None:
        self.sock = sock
        self.buffer = b""

    @classmethod
    async def connect(cls, host: str, port: int, path: str = "/ws", rcvbuf: int | None = None,
                      handshake: bool = True, headers: str = "") -> RawWebSocket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        if rcvbuf:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)  # before connect: the window stays small
        sock.setblocking(False)
        await asyncio.get_running_loop().sock_connect(sock, (host, port))
        raw = cls(sock)
        if handshake:
            await raw.handshake(host, port, path, headers)
        return raw

    async def send(self, data: bytes) -> None:
        await asyncio.get_running_loop().sock_sendall(self.sock, data)

    async def _read(self, n: int) -> bytes:
        loop = asyncio.get_running_loop()
        while len(self.buffer) < n:
            chunk = await asyncio.wait_for(loop.sock_recv(self.sock, 65536), 10)
            if not chunk:
                raise ConnectionError("server closed the connection")
            self.buffer += chunk
        data, self.buffer = self.buffer[:n], self.buffer[n:]
        return data

    async def handshake(self, host: str, port: int, path: str, headers: str = "") -> None:
        key = base64.b64encode(os.urandom(16)).decode()
        await self.send(
            f"GET {path} HTTP/1.1\r\nHost: {host}:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n{headers}\r\n".encode()
        )
        loop = asyncio.get_running_loop()
        while b"\r\n\r\n" not in self.buffer:
            chunk = await asyncio.wait_for(loop.sock_recv(self.sock, 65536), 10)
            if not chunk:
                raise ConnectionError("server closed the connection during the handshake")
            self.buffer += chunk
        head, self.buffer = self.buffer.split(b"\r\n\r\n", 1)
        assert head.startswith(b"HTTP/1.1 101"), head

    async def http(self, request: bytes) -> tuple[int, bytes]:
        """Send a raw HTTP request; the status and everything until the server closes."""
        await self.send(request)
        loop = asyncio.get_running_loop()
        data = self.buffer
        while chunk := await asyncio.wait_for(loop.sock_recv(self.sock, 65536), 10):
            data += chunk
        return int(data.split(b" ", 2)[1]), data

    @staticmethod
    def frame(opcode: int, payload: bytes, mask: bool = True, fin: bool = True) -> bytes:
        head = bytes([(0x80 if fin else 0) | opcode])
        n = len(payload)
        bit = 0x80 if mask else 0
        if n < 126:
            head += bytes([bit | n])
        elif n < 65536:
            head += bytes([bit | 126]) + struct.pack("!H", n)
        else:
            head += bytes([bit | 127]) + struct.pack("!Q", n)
        if not mask:
            return head + payload
        key = os.urandom(4)
        return head + key + bytes(b ^ key[i % 4] for i, b in enumerate(payload))

    async def receive(self) -> tuple[int, bytes]:
        """The next frame from the server (unmasked): opcode, payload."""
        b0, b1 = await self._read(2)
        n = b1 & 0x7F
        if n == 126:
            (n,) = struct.unpack("!H", await self._read(2))
        elif n == 127:
            (n,) = struct.unpack("!Q", await self._read(8))
        return b0 & 0x0F, await self._read(n)

    async def until_close(self) -> tuple[list[dict[str, Any]], int, str]:
        """The text messages up to the server's close frame, and its code and reason."""
        texts = []
        while True:
            opcode, payload = await self.receive()
            if opcode == 0x1:
                texts.append(json.loads(payload))
            elif opcode == 0x8:
                (code,) = struct.unpack("!H", payload[:2])
                return texts, code, payload[2:].decode()

    def close(self) -> None:
        self.sock.close()


# -- malformed messages ----------------------------------------------------------------------------------


BAD_MESSAGES = [
    ("hello robot", "not JSON"),
    ('{"type": "start", "token": ', "not JSON"),
    ("[1, 2, 3]", "must be a JSON object, got list"),
    ('{"type": "launch"}', "unknown message type 'launch'"),
    ('{"kind": "start"}', "unknown message type None"),
    ('{"type": "start", "token": 246810}', "token must be a string"),
    ("\u0000\u00ff\ufffd", "not JSON"),
]


async def test_malformed_json_unknown_types_and_binary_junk_get_one_line_errors_and_change_nothing(
    aiohttp_client, state, server_log
) -> None:
    app = _app(state)
    client = await aiohttp_client(app)
    ws = await client.ws_connect("/ws")
    bystander = await client.ws_connect("/ws")
    await _packet(ws)
    await _packet(bystander)
    for text, expected in BAD_MESSAGES:
        await ws.send_str(text)
        error = await _text(ws, "error")
        assert error["status"] == 400 and expected in error["message"], (text, error)
        assert "\n" not in error["message"]
    for junk in (b"\x00\xffjunk", os.urandom(1000)):
        await ws.send_bytes(junk)
        error = await _text(ws, "error")
        assert error == {"type": "error", "status": 400,
                         "message": "binary frames are not part of the protocol; send JSON text"}
    # still connected, still served; nobody else heard anything; nothing queued or changed
    await ws.send_json({"type": "resync"})
    assert (await _packet(ws)).kind == KIND_FULL
    state.pose.x_m = 0.5
    app[BROADCASTER_KEY].tick()
    assert (await _packet(bystander)).status["pose"][0] == 0.5
    assert state.commands.empty() and state.run_state is RunState.IDLE
    network = (await (await client.get("/api/status")).json())["network"]
    assert network["bad_messages"] == len(BAD_MESSAGES) + 2
    assert network["last_problem"] == "127.0.0.1 sent a binary frame"
    await ws.close()
    await bystander.close()
    assert_no_exception_logged(server_log)


async def test_an_oversized_message_is_answered_in_words_and_closed_with_1009(aiohttp_client, state,
                                                                             server_log) -> None:
    app = _app(state, max_message_bytes=4096)
    client = await aiohttp_client(app)
    bystander = await client.ws_connect("/ws")
    await _packet(bystander)
    ws = await client.ws_connect("/ws")
    await _packet(ws)
    await ws.send_str(json.dumps({"type": "start", "token": "x" * 5000}))
    texts, close = await _close_of(ws)
    assert texts[-1] == {"type": "error", "status": 1009, "message": "message larger than 4096 bytes"}
    assert close.type == WSMsgType.CLOSE and close.data == 1009 and close.extra == "message larger than 4096 bytes"
    assert state.commands.empty()
    state.pose.y_m = 0.25
    app[BROADCASTER_KEY].tick()
    assert (await _packet(bystander)).status["pose"][1] == 0.25
    status = await (await client.get("/api/status")).json()
    assert status["network"]["broken_frames"] == 1 and status["viewers"] == 1
    assert "message larger than 4096 bytes; closed (1009)" in status["network"]["last_problem"]
    await bystander.close()
    assert_no_exception_logged(server_log)


@pytest.mark.parametrize(
    ("junk", "code", "reason"),
    [
        (RawWebSocket.frame(0x9, b"ping", fin=False), 1002, "broken websocket frame"),  # fragmented ping
        (bytes([0xF1, 0x82]) + os.urandom(6), 1002, "broken websocket frame"),  # reserved bits set
        (RawWebSocket.frame(0x3, b"??"), 1002, "broken websocket frame"),  # reserved opcode
        (b"\xff" * 64, 1002, "broken websocket frame"),  # not a frame at all
        (RawWebSocket.frame(0x1, b"\xc3\x28 not utf-8"), 1007, "text frame is not valid UTF-8"),
        (RawWebSocket.frame(0x2, b"x" * 70000), 1009, "message larger than 4096 bytes"),
    ],
    ids=["fragmented-ping", "reserved-bits", "reserved-opcode", "garbage", "bad-utf8", "oversized-binary"],
)
async def test_raw_junk_frames_are_answered_and_closed_without_a_server_exception(
    aiohttp_client, state, server_log, junk: bytes, code: int, reason: str
) -> None:
    client = await aiohttp_client(_app(state))
    bystander = await client.ws_connect("/ws")
    await _packet(bystander)
    raw = await RawWebSocket.connect(client.server.host, client.server.port)
    try:
        await raw.send(junk)
        texts, close_code, close_reason = await raw.until_close()
    finally:
        raw.close()
    assert (close_code, close_reason) == (code, reason)
    assert texts[-1] == {"type": "error", "status": code, "message": reason}
    await bystander.send_json({"type": "resync"})
    assert (await _packet(bystander)).kind == KIND_FULL
    assert state.commands.empty()
    assert_no_exception_logged(server_log)


async def test_junk_instead_of_http_is_refused_and_the_server_serves_on(aiohttp_client, state, server_log) -> None:
    client = await aiohttp_client(_app(state))
    for junk in (os.urandom(2000), b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03" + os.urandom(200),  # a TLS hello
                 b"GET /ws HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n\r\n"):
        raw = await RawWebSocket.connect(client.server.host, client.server.port, handshake=False)
        try:
            await raw.send(junk)
            loop = asyncio.get_running_loop()
            reply = await asyncio.wait_for(loop.sock_recv(raw.sock, 65536), 10)
        finally:
            raw.close()
        assert reply.split(b"\r\n", 1)[0] in (b"HTTP/1.0 400 Bad Request", b"HTTP/1.1 400 Bad Request"), reply[:80]
    assert (await client.get("/api/status")).status == 200
    assert_no_exception_logged(server_log)


# -- flooding -----------------------------------------------------------------------------------------


async def test_a_flooding_client_is_warned_once_then_closed_with_1008_and_others_are_untouched(
    aiohttp_client, state, server_log, fake_grid, mirror
) -> None:
    grid = fake_grid()
    state.map = grid
    app = _app(state, message_rate_per_s=20, message_burst=40, send_queue_packets=64)
    broadcaster = app[BROADCASTER_KEY]
    client = await aiohttp_client(app)
    steady = await client.ws_connect("/ws")
    page = mirror()
    first = await _packet(steady)
    page.seq, page.epoch, page.codes = first.seq, first.map.epoch, first.map.codes.copy()
    flooder = await client.ws_connect("/ws")
    await _packet(flooder)
    for _ in range(600):  # resync: each one the server honours costs it a full map
        await flooder.send_str('{"type":"resync"}')
    # meanwhile the map changes and the steady viewer gets every delta, in sequence
    for step in range(20):
        grid.cells[step, step] = 100
        broadcaster.tick()
    while page.seq != broadcaster.seq:
        msg = await _next(steady)
        if msg.type == WSMsgType.BINARY:
            assert page.apply(msg.data), "the steady viewer saw a gap"
    assert page.matches(grid)
    texts, close = await _close_of(flooder)
    warnings = [t for t in texts if t["type"] == "error"]
    assert warnings == [{"type": "error", "status": 429, "message": "too many messages: at most 20 a second "
                         "(bursts of 40); slow down or be disconnected"}]
    assert close.data == aiohttp.WSCloseCode.POLICY_VIOLATION and close.extra == "too many messages (over 20/s)"
    network = (await (await client.get("/api/status")).json())["network"]
    assert network["flood_warnings"] == 1 and network["flood_closes"] == 1
    assert len(broadcaster.viewers) == 1 and not steady.closed
    assert state.commands.empty()
    await steady.close()
    assert_no_exception_logged(server_log)


async def test_a_flooder_that_goes_on_after_its_close_frame_is_cut_off_not_read_for_the_handshake(
    aiohttp_client, state, server_log, monkeypatch
) -> None:
    """A flooder never answers the close frame and keeps sending: the server must not sit reading
    (parsing) its flood for the close handshake, it hangs up. The polite close wait is made
    a minute long here, so a server that waited for this client's close frame would not hang up;
    and no close handshake may start while the flooder's socket is still read (even a 0.1 s one
    kept the loop parsing the flood for 0.1 s)."""
    monkeypatch.setattr(web_app, "CLOSE_HANDSHAKE_S", 60.0)
    handshakes: list[tuple[int, bool]] = []  # (close code, the socket still read when it began)
    prepare, close = web_app.GuardedWebSocket.prepare, web_app.GuardedWebSocket.close

    async def remembering_prepare(self: Any, request: web.Request) -> Any:
        self.request_for_test = request
        return await prepare(self, request)

    async def recorded_close(self: Any, **kwargs: Any) -> bool:
        transport = self.request_for_test.transport
        handshakes.append((int(kwargs.get("code", 1000)), transport is not None and not transport.is_closing()))
        return await close(self, **kwargs)

    monkeypatch.setattr(web_app.GuardedWebSocket, "prepare", remembering_prepare)
    monkeypatch.setattr(web_app.GuardedWebSocket, "close", recorded_close)
    app = _app(state, message_rate_per_s=20, message_burst=40)
    client = await aiohttp_client(app)
    steady = await client.ws_connect("/ws")
    raw = await RawWebSocket.connect(client.server.host, client.server.port)
    loop = asyncio.get_running_loop()
    resync = RawWebSocket.frame(0x1, b'{"type":"resync"}')

    async def flood() -> None:
        with contextlib.suppress(OSError):  # ends when the server hangs up
            while True:
                await raw.send(resync * 200)

    flooding = asyncio.ensure_future(flood())
    try:
        _, code, reason = await raw.until_close()
        assert code == aiohttp.WSCloseCode.POLICY_VIOLATION and reason == "too many messages (over 20/s)"
        # the server hangs up on its own: EOF (or a reset) while the client still sends and never closes
        while True:
            chunk = await asyncio.wait_for(loop.sock_recv(raw.sock, 65536), 10)
            if not chunk:
                break
    except ConnectionResetError:
        pass
    finally:
        flooding.cancel()
        raw.close()
    network = (await (await client.get("/api/status")).json())["network"]
    assert network["flood_closes"] == 1
    assert (aiohttp.WSCloseCode.POLICY_VIOLATION, True) not in handshakes, handshakes
    assert not steady.closed and state.commands.empty()
    await steady.close()
    assert_no_exception_logged(server_log)


async def test_a_client_sending_at_the_limit_is_never_cut_off(aiohttp_client, state) -> None:
    """The limiter forgives: bursts that fit, spaced out, never close a well-behaved page."""
    app = _app(state, message_rate_per_s=1000, message_burst=5)  # a fast refill keeps the test short
    client = await aiohttp_client(app)
    ws = await client.ws_connect("/ws")
    await _packet(ws)
    for _ in range(10):
        for _ in range(5):
            await ws.send_json({"type": "resync"})
        for _ in range(5):
            assert (await _packet(ws)).kind == KIND_FULL
        await asyncio.sleep(0.02)  # >= 5 tokens back at 1000/s
    assert not ws.closed
    await ws.close()


# -- churn -------------------------------------------------------------------------------------------------


async def _churn_round(host: str, port: int, session: aiohttp.ClientSession, n: int = 50) -> None:
    """``n`` clients connect and drop at once: a third close politely, a third vanish, a third never finish."""

    async def one(i: int) -> None:
        if i % 3 == 0:
            ws = await session.ws_connect(f"http://{host}:{port}/ws")
            await ws.receive()
            await ws.close()
        elif i % 3 == 1:
            raw = await RawWebSocket.connect(host, port)  # connected, then the TCP connection just goes
            raw.close()
        else:
            raw = await RawWebSocket.connect(host, port, handshake=False)
            await raw.send(b"GET /ws HTTP/1.1\r\nHost: x\r\nUpgrade: websocket\r\n")  # half a request
            raw.close()

    await asyncio.gather(*(one(i) for i in range(n)))


async def _until(predicate, timeout_s: float = 10.0) -> None:
    loop = asyncio.get_running_loop()
    end = loop.time() + timeout_s
    while not predicate():
        assert loop.time() < end, "condition not reached"
        await asyncio.sleep(0.02)


class _Problems(logging.Handler):
    """Keeps only WARNING and above (pytest's caplog keeps every record, which the memory figure would count)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.records: list[logging.LogRecord] = []

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


async def test_fifty_clients_connecting_and_dropping_in_a_loop_leak_nothing(aiohttp_client, state,
                                                                            fake_grid, mirror) -> None:
    problems = _Problems()
    logging.getLogger().addHandler(problems)
    grid = fake_grid()
    state.map = grid
    app = _app(state, connect_rate_per_s=10000, connect_burst=100000)  # 50 clients, one address: let all in
    broadcaster = app[BROADCASTER_KEY]
    client = await aiohttp_client(app)
    host, port = client.server.host, client.server.port
    steady = await client.ws_connect("/ws")
    page = mirror()
    first = await _packet(steady)
    page.seq, page.epoch, page.codes = first.seq, first.map.epoch, first.map.codes.copy()
    rng = np.random.default_rng(3)
    sizes = []
    tracemalloc.start()
    try:
        async with aiohttp.ClientSession() as session:
            for _ in range(12):
                await _churn_round(host, port, session)
                grid.cells[rng.integers(0, 40), rng.integers(0, 60)] = 100
                broadcaster.tick()
                while page.seq != broadcaster.seq:  # the steady viewer is served all along
                    msg = await _next(steady)
                    if msg.type == WSMsgType.BINARY:
                        assert page.apply(msg.data), "the steady viewer saw a gap"
                await _until(lambda: len(broadcaster.viewers) == 1)
                gc.collect()
                sizes.append(tracemalloc.get_traced_memory()[0])
    finally:
        tracemalloc.stop()
    assert page.matches(grid) and not steady.closed
    assert len(broadcaster.viewers) == 1
    growth = sizes[-1] - sizes[1]  # round 0 warms caches up
    print(f"\ntraced memory after each round of 50 (KiB): {[s // 1024 for s in sizes]}; "
          f"growth over 10 rounds = 500 connections: {growth / 1024:.1f} KiB")
    # each dead socket used to stay alive until its heartbeat fired (~3 KiB each): closing it frees it at once
    assert growth < 100 * 1024, f"{growth / 1024:.0f} KiB more after 500 connections: a leak"
    await steady.close()
    await _until(lambda: not broadcaster.viewers)
    logging.getLogger().removeHandler(problems)
    assert_no_exception_logged(problems)  # type: ignore[arg-type]


async def test_an_address_opening_connections_too_fast_is_refused_with_429_before_any_work(
    aiohttp_client, state, server_log
) -> None:
    """Reconnecting as soon as it is closed, a flooder would cost a handshake, a hello and a full
    map each time; past its burst an address is refused before the upgrade, the open sockets
    are served on, and a token later it may connect again."""
    app = _app(state, connect_rate_per_s=2, connect_burst=5)
    broadcaster = app[BROADCASTER_KEY]
    client = await aiohttp_client(app)
    sockets = [await client.ws_connect("/ws") for _ in range(5)]
    for ws in sockets:
        assert (await _packet(ws)).kind == KIND_FULL  # what every viewer gets on connecting
    with pytest.raises(aiohttp.WSServerHandshakeError) as err:
        await client.ws_connect("/ws")
    assert err.value.status == 429 and err.value.headers["Retry-After"] == "1"
    resp = await client.get("/ws")
    assert resp.status == 429
    assert await resp.text() == ("too many connections from 127.0.0.1: at most 2 a second (bursts of 5); "
                                 "try again in 1 s")
    assert len(broadcaster.viewers) == 5 and broadcaster.packets_built == 2  # the refused cost no packet
    state.pose.x_m = 0.3
    broadcaster.tick()
    for ws in sockets:
        assert (await _packet(ws)).status["pose"][0] == 0.3
    await asyncio.sleep(0.6)  # one token back at 2/s
    late = await client.ws_connect("/ws")
    assert (await _packet(late)).kind == KIND_FULL
    network = (await (await client.get("/api/status")).json())["network"]
    assert network["connections_refused"] == 2
    for ws in [*sockets, late]:
        await ws.close()
    assert_no_exception_logged(server_log)


# -- a client that never reads --------------------------------------------------------------------------


async def test_a_raw_client_that_never_reads_loses_deltas_gets_full_maps_and_costs_bounded_memory(
    aiohttp_client, state, server_log, fake_grid, mirror
) -> None:
    rng = np.random.default_rng(11)
    grid = fake_grid(rows=300, cols=300)
    state.map = grid
    app = _app(state, send_queue_packets=4, heartbeat_s=30.0)

    @web.middleware
    async def small_send_buffer(request: web.Request, handler: Any) -> web.StreamResponse:
        # the kernel's send buffer is the first stage (up to net.ipv4.tcp_wmem's max, 4 MiB here): shrink
        # it for this one connection so the test reaches the web layer's own bound in a few packets
        if request.headers.get("X-Test-Slow"):
            request.transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 8192)
        return await handler(request)

    app.middlewares.append(small_send_buffer)
    broadcaster = app[BROADCASTER_KEY]
    client = await aiohttp_client(app)
    sleeper = await RawWebSocket.connect(client.server.host, client.server.port, rcvbuf=4096,
                                         headers="X-Test-Slow: 1\r\n")
    await _until(lambda: len(broadcaster.viewers) == 1)
    (stuck,) = broadcaster.viewers
    # stuck.ws is the server's side; its transport's write buffer is what the kernel could not take
    transport = stuck.ws._req.transport  # type: ignore[union-attr]
    try:
        fast = await client.ws_connect("/ws", max_msg_size=0)
        page = mirror()
        built = []
        buffered = []
        for _ in range(60):
            flip = rng.random(grid.cells.shape) < 0.1  # big deltas: tens of KB each
            grid.cells[flip] = rng.choice(np.array([-1, 0, 100], np.int8), int(flip.sum()))
            broadcaster.tick()
            built.append(broadcaster.bytes_built)
            while True:
                p = await _packet(fast)
                page.apply(RawFull.encode(p))
                if p.seq == broadcaster.seq:
                    break
            assert stuck.queued <= 4  # the queue bound, whatever the client does
            buffered.append(transport.get_write_buffer_size())
        assert page.matches(grid) and page.gaps == 0
        assert stuck.dropped > 0 and stuck.sent_packets < 60
        assert decode_packet(stuck.pending()[0]).kind == KIND_FULL  # what it will get when it reads again
        full_bytes = len(broadcaster.full_packet())
        # aiohttp's writer checks for back-pressure every writer_limit (64 KiB) of output and then waits while
        # the transport is over its high-water mark (64 KiB): two limits and a frame, never more
        assert max(buffered) <= 2 * 64 * 1024 + full_bytes, (max(buffered), full_bytes)
        print(f"\nnever-reading client: {built[-1] / 1e6:.1f} MB built for everyone, it was sent "
              f"{stuck.sent_bytes / 1e3:.0f} kB, {stuck.dropped} items dropped, queue <= 4, "
              f"server write buffer max {max(buffered) / 1024:.0f} KiB")
    finally:
        sleeper.close()
    await _until(lambda: len(broadcaster.viewers) == 1)
    await fast.close()
    assert_no_exception_logged(server_log)


class RawFull:
    """Re-encode a decoded packet for the mirror (which takes bytes)."""

    @staticmethod
    def encode(packet: Any) -> bytes:
        from mazebot.web.protocol import encode_packet

        return encode_packet(packet)


async def test_a_client_that_never_answers_pings_is_closed_by_the_heartbeat(aiohttp_client, state,
                                                                           server_log) -> None:
    app = _app(state, heartbeat_s=0.6)
    broadcaster = app[BROADCASTER_KEY]
    client = await aiohttp_client(app)
    sleeper = await RawWebSocket.connect(client.server.host, client.server.port)
    try:
        await _until(lambda: len(broadcaster.viewers) == 1)
        await _until(lambda: not broadcaster.viewers, timeout_s=20)
    finally:
        sleeper.close()
    assert_no_exception_logged(server_log)


# -- static files -------------------------------------------------------------------------------------------


TRAVERSALS = [
    "/static/../mazebot/config.py",
    "/static/../../etc/passwd",
    "/static/%2e%2e/mazebot/config.py",
    "/static/%2e%2e%2fmazebot%2fconfig.py",
    "/static/..%2f..%2fetc%2fpasswd",
    "/static/%2E%2E/%2E%2E/etc/passwd",
    "/static/vendor/../../pyproject.toml",
    "/static/vendor/%2e%2e/%2e%2e/pyproject.toml",
    "/static//etc/passwd",
    "/static/%2fetc%2fpasswd",
    "/static/..\\mazebot\\config.py",
    "/static/%5c..%5c..%5cpyproject.toml",
    "/static/%252e%252e/pyproject.toml",
    "/static/outside-link/pyproject.toml",
    "/static/outside-file",
    "/../pyproject.toml",
    "//etc/passwd",
]


@pytest.mark.parametrize("path", TRAVERSALS)
async def test_static_files_refuse_path_traversal(aiohttp_client, state, tmp_path: Path, path: str) -> None:
    static = tmp_path / "static"
    (static / "vendor").mkdir(parents=True)
    (static / "index.html").write_text("<html>page</html>")
    (static / "outside-link").symlink_to(ROOT)  # symlinks out of the folder are not followed
    (static / "outside-file").symlink_to(ROOT / "pyproject.toml")
    client = await aiohttp_client(create_app(state, static_dir=static))
    raw = await RawWebSocket.connect(client.server.host, client.server.port, handshake=False)
    try:  # a raw request: aiohttp's client would normalise the path before sending it
        status, reply = await raw.http(f"GET {path} HTTP/1.1\r\nHost: robot\r\nConnection: close\r\n\r\n".encode())
    finally:
        raw.close()
    assert status in (400, 403, 404), (path, status)
    for secret in (b"[project]", b"root:", b"class WebConfig"):
        assert secret not in reply, path


# -- tokens ------------------------------------------------------------------------------------------------


async def test_every_control_path_compares_tokens_with_hmac_compare_digest(aiohttp_client, state,
                                                                           monkeypatch) -> None:
    calls: list[tuple[bytes, bytes]] = []
    real = auth.hmac.compare_digest

    def spy(a: bytes, b: bytes) -> bool:
        calls.append((a, b))
        return real(a, b)

    monkeypatch.setattr(auth.hmac, "compare_digest", spy)
    client = await aiohttp_client(_app(state, view_open=False))
    expected = []
    for path, headers in [("/api/start", {"X-Mazebot-Token": "111111"}),
                          ("/api/stop", {"Authorization": f"Bearer {TOKEN}"})]:
        await client.post(path, headers=headers)
        expected.append(headers.get("X-Mazebot-Token", TOKEN))
    await client.get("/api/status", headers={"X-Mazebot-Token": TOKEN})
    expected.append(TOKEN)
    await client.get("/map.png?token=222222")
    expected.append("222222")
    ws = await client.ws_connect(f"/ws?token={TOKEN}")
    expected.append(TOKEN)
    for token in ("333333", TOKEN):
        await ws.send_json({"type": "stop", "token": token})
        await _text(ws, "reply")
        expected.append(token)
    await ws.close()
    assert calls == [(TOKEN.encode(), t.encode()) for t in expected]


async def test_wrong_pins_back_off_per_address_over_http_and_websocket(aiohttp_client, state) -> None:
    client = await aiohttp_client(_app(state))
    ws = await client.ws_connect("/ws")
    for i in range(4):
        resp = await client.post("/api/start", headers={"X-Mazebot-Token": f"00000{i}"})
        assert resp.status == 403
    await ws.send_json({"type": "start", "token": "999999"})  # the fifth, over the other path
    assert (await _text(ws, "reply"))["status"] == 403
    resp = await client.post("/api/start", headers={"X-Mazebot-Token": TOKEN})  # right, but too soon
    assert resp.status == 429 and resp.headers["Retry-After"] == "1"
    assert (await resp.json())["error"] == "too many wrong PINs from this address; try again in 1 s"
    await ws.send_json({"type": "stop", "token": TOKEN})
    reply = await _text(ws, "reply")
    assert (reply["ok"], reply["status"]) == (False, 429) and "try again in" in reply["message"]
    assert state.commands.empty()
    status = await (await client.get("/api/status")).json()
    assert status["network"]["pin_lockouts"] == 1 and status["network"]["locked_out_now"] == 1
    await ws.close()
