"""The aiohttp application: routes in one place, built by a factory that never runs it.

Routes::

    GET  /                 the page (static/index.html)
    GET  /static/...       its assets (app.js, style.css, vendor/d3.min.js)
    GET  /ws               the live websocket (docs/protocol.md)
    GET  /api/status       run state, pose, coverage, elapsed time, faults, versions (JSON)
    POST /api/start        start exploring   (token: X-Mazebot-Token or Authorization: Bearer)
    POST /api/stop         stop the robot    (token as above)
    GET  /map.png          the map as an image (``?download``: saved as mazebot-map-DATE-TIME.png)
    GET  /map.pgm          the map for ROS map_server, with
    GET  /map.yaml         its YAML
    GET  /map.zip          both of one snapshot, for download (mazebot-map-DATE-TIME.pgm + .yaml)
    GET  /api/setup, POST /api/jog, GET /api/doctor   the setup view (mazebot.web.setup)
    GET, POST /api/calibration[/stop|/write]           calibration from the setup view (mazebot.web.calibration)
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.resources
import logging
import math
import platform
import secrets
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import aiohttp
import numpy as np
from aiohttp import WSCloseCode, WSMsgType, web
from aiohttp.typedefs import Handler

from mazebot import __version__
from mazebot.clock import RealClock
from mazebot.errors import MazebotError
from mazebot.state import SharedState
from mazebot.web import map_images
from mazebot.web.access import (
    AUTH_KEY,
    REPLAY_COMMAND_STATUS,
    REPLAY_KEY,
    SETTINGS_KEY,
    STATE_KEY,
    WebSettings,
    auth_message,
    authorize_command,
    check_origin,
    check_view,
    replay_refusal,
)
from mazebot.web.auth import ControlAuth, client_key
from mazebot.web.broadcaster import Broadcaster, Viewer
from mazebot.web.limits import ConnectionLimiter, MessageLimiter
from mazebot.web.protocol import PROTOCOL_VERSION, ProtocolError, parse_client_message, server_message

log = logging.getLogger(__name__)

#: Close codes of the websocket beyond the standard ones: 4000 + the HTTP status.
CLOSE_UNAUTHORIZED = 4401
#: How long a close waits for the client's close frame (RFC 6455 §7.1.1), reading what it sends meanwhile.
CLOSE_HANDSHAKE_S = 2.0
#: How long the close frame to a flooder may take to go out before the connection is cut anyway.
FLOODER_CLOSE_FRAME_S = 1.0
CLOSE_FORBIDDEN = 4403


STATIC_DIR_KEY = web.AppKey("static_dir", Path)
BROADCASTER_KEY = web.AppKey("broadcaster", Broadcaster)
CONNECTIONS_KEY = web.AppKey("connections", ConnectionLimiter)


@dataclass
class NetworkStats:
    """What the network did wrong, for ``/api/status`` (counts since start, and the last one in words)."""

    bad_messages: int = 0  # malformed JSON, unknown type, binary frames: answered with an error
    flood_warnings: int = 0  # clients told they send too fast
    flood_closes: int = 0  # ... and closed (1008) because they kept on
    broken_frames: int = 0  # oversized or invalid websocket frames: answered, closed (1009/1002/1007)
    last_problem: str | None = None

    def note(self, counter: str, sentence: str) -> None:
        setattr(self, counter, getattr(self, counter) + 1)
        self.last_problem = sentence


STATS_KEY = web.AppKey("network_stats", NetworkStats)


def find_static_dir() -> Path:
    """The page and its assets: the package data ``mazebot.static``, however mazebot is installed.

    In the repository the folder is the top-level ``static/``; ``pyproject.toml`` maps it to
    the package ``mazebot.static`` (``package-dir``), so a wheel installs it as
    ``mazebot/static/`` next to the code (venv, ``pip install --user``, system pip) and an
    editable install finds it in the checkout. ``importlib.resources`` finds it in both
    (https://docs.python.org/3/library/importlib.resources.html). aiohttp serves files from
    a real directory, which a wheel installed on disk always gives.
    """
    folder = importlib.resources.files("mazebot.static")
    if not isinstance(folder, Path) or not (folder / "index.html").is_file():
        raise MazebotError(f"the phone page is missing from the installed package ({folder}); reinstall mazebot")
    return folder


DEFAULT_STATIC_DIR = find_static_dir()


def status_json(
    state: SharedState, viewers: int | None = None, network: dict[str, Any] | None = None
) -> dict[str, Any]:
    """The run state as ``/api/status`` shows it; ``network``: what clients did wrong (web layer)."""
    fault = state.active_fault
    now_s = RealClock().now_s()  # the daemon's clock: the loop's time
    elapsed = state.elapsed_s(now_s)
    elapsed_s = None if elapsed is None else round(elapsed, 1)
    grid = state.map
    return {
        "state": state.run_state.value,
        "pose": {
            "x_m": round(state.pose.x_m, 4),
            "y_m": round(state.pose.y_m, 4),
            "theta_rad": round(state.pose.theta_rad, 4),
        },
        "coverage": None if state.coverage is None else round(float(state.coverage), 4),
        "distance_m": None if (d := state.run_distance_m()) is None else round(d, 3),
        "elapsed_s": elapsed_s,
        "planner": state.planner_status,
        "safety_stop": state.safety_stop or None,
        "safety_stops": state.safety_stops,
        "fault": None if fault is None else {"source": fault.source, "message": fault.message},
        "faults": [{"source": f.source, "message": f.message} for f in state.faults[-10:]],
        # recent faults and notices, newest last, with their age: what happened while nobody looked
        "events": [
            {"source": e.source, "message": e.message, "age_s": round(now_s - e.time_s, 1)} for e in state.events
        ],
        "sensors": vars(state.sensors),
        # CPU time per part of the daemon since it started (mazebot.cpu_budget)
        "cpu": state.cpu.table(state.cpu.age_s(now_s)),
        "record": vars(state.record),
        "map": None if grid is None else {
            "rows": grid.shape[0], "cols": grid.shape[1], "resolution_m": grid.resolution_m,
            "origin_m": list(grid.origin_m), "generation": grid.generation,
        },
        "viewers": viewers,
        "network": network,
        "version": __version__,
        "versions": {
            "mazebot": __version__,
            "protocol": PROTOCOL_VERSION,
            "python": platform.python_version(),
            "aiohttp": aiohttp.__version__,
            "numpy": np.__version__,
        },
    }


#: Why aiohttp closes a socket on a bad frame, in words for the client.
_FRAME_CLOSE_REASONS: dict[int, str] = {
    WSCloseCode.MESSAGE_TOO_BIG: "message larger than {limit} bytes",
    WSCloseCode.PROTOCOL_ERROR: "broken websocket frame",
    WSCloseCode.INVALID_TEXT: "text frame is not valid UTF-8",
}


class GuardedWebSocket(web.WebSocketResponse):
    """A websocket that tells its client, in words, why a broken frame closes it.

    aiohttp refuses a frame over ``max_msg_size`` (1009) or one that breaks RFC 6455 (1002,
    1007 bad UTF-8) by closing the socket itself, with no reason. Here the client first
    gets a one-line ``error`` message, and the close frame carries the same words.
    """

    def __init__(self, *, stats: NetworkStats, max_message_bytes: int, **kwargs: Any) -> None:
        super().__init__(max_msg_size=max_message_bytes, **kwargs)
        self.stats = stats
        self.max_message_bytes = max_message_bytes
        self.remote = "?"

    async def close(self, *, code: int = WSCloseCode.OK, message: bytes = b"", drain: bool = True) -> bool:
        reason = _FRAME_CLOSE_REASONS.get(int(code))
        if reason is not None and not message and not self.closed:
            text = reason.format(limit=self.max_message_bytes)
            self.stats.note("broken_frames", f"{self.remote}: {text}; closed ({int(code)})")
            with contextlib.suppress(Exception):  # the socket may be gone already: the close says it anyway
                await asyncio.wait_for(self.send_str(server_message("error", status=int(code), message=text)), 1.0)
            message = text.encode()[:120]  # a close reason fits in 123 bytes
        return await super().close(code=code, message=message, drain=drain)


# -- handlers -----------------------------------------------------------------------------


async def get_index(request: web.Request) -> web.FileResponse:
    return web.FileResponse(request.app[STATIC_DIR_KEY] / "index.html", headers={"Cache-Control": "no-cache"})


async def get_status(request: web.Request) -> web.Response:
    if (denied := check_view(request)) is not None:
        return denied
    viewers = len(request.app[BROADCASTER_KEY].viewers)
    body = status_json(request.app[STATE_KEY], viewers, _network_json(request.app))
    if (replay := request.app.get(REPLAY_KEY)) is not None:
        body["replay"] = replay()
    return web.json_response(body)


def _network_json(app: web.Application) -> dict[str, Any]:
    auth = app[AUTH_KEY]
    return {**vars(app[STATS_KEY]), "pin_lockouts": auth.lockouts, "locked_out_now": auth.locked_out,
            "connections_refused": app[CONNECTIONS_KEY].refused}


def _queue_command(state: SharedState, command: str) -> bool:
    try:
        state.commands.put_nowait(command)
    except asyncio.QueueFull:  # the command task is behind; say so instead of waiting
        return False
    return True


async def post_command(request: web.Request) -> web.Response:
    """``POST /api/start`` and ``/api/stop``: the command queued for the daemon, once the PIN allows it."""
    command = request.match_info["command"]
    if (refused := authorize_command(request, command)) is not None:
        return refused
    if not _queue_command(request.app[STATE_KEY], command):
        return web.json_response({"error": "too many commands queued; try again"}, status=503)
    return web.json_response({"accepted": command})


#: kind: (content type, download name (None: the snapshot's stem + suffix), encoder of a snapshot).
#: /map.pgm and /map.yaml keep the names the YAML's ``image: map.pgm`` refers to.
_MAP_FILES: dict[str, tuple[str, str | None, Callable[[map_images.MapSnapshot], bytes]]] = {
    "png": ("image/png", None, lambda snap: map_images.encode_map_png(snap.three_state)),
    "pgm": ("image/x-portable-graymap", "map.pgm", lambda snap: map_images.encode_pgm(snap.three_state)),
    "yaml": ("text/yaml", "map.yaml", lambda snap: map_images.encode_yaml(snap.resolution_m, snap.origin_m)),
    "zip": ("application/zip", None, map_images.encode_ros_zip),
}


async def get_map(request: web.Request) -> web.Response:
    """``/map.png``, ``.pgm``, ``.yaml``, ``.zip``: one map file of one snapshot; ``?download`` (and
    always the zip) asks the browser to save it."""
    kind = request.match_info["kind"]
    if (denied := check_view(request)) is not None:
        return denied
    grid = request.app[STATE_KEY].map
    if grid is None:
        return web.json_response({"error": "no map yet: start the robot (SLAM builds the map)"}, status=404)
    snap = map_images.take_snapshot(grid)  # read on the loop (one writer); encode off it
    content_type, name, encode = _MAP_FILES[kind]
    filename = name or f"{snap.stem}.{kind}"
    disposition = "attachment" if kind == "zip" or "download" in request.query else "inline"
    headers = {"Cache-Control": "no-store", "Content-Disposition": f'{disposition}; filename="{filename}"'}
    body = await asyncio.get_running_loop().run_in_executor(None, encode, snap)
    return web.Response(body=body, content_type=content_type, headers=headers)


async def get_ws(request: web.Request) -> web.WebSocketResponse:
    """The live websocket: packets out, start/stop/resync in (docs/protocol.md)."""
    check_origin(request)
    app = request.app
    settings = app[SETTINGS_KEY]
    remote = request.remote or "?"
    if not app[CONNECTIONS_KEY].allow(client_key(remote)):  # refused before any work: no hello, no map
        retry_s = math.ceil(1.0 / settings.connect_rate_per_s)
        raise web.HTTPTooManyRequests(
            text=f"too many connections from {remote}: at most {settings.connect_rate_per_s:g} a second "
            f"(bursts of {settings.connect_burst}); try again in {retry_s} s",
            headers={"Retry-After": str(retry_s)},
        )
    ws = GuardedWebSocket(
        stats=app[STATS_KEY],
        max_message_bytes=settings.max_message_bytes,
        heartbeat=settings.heartbeat_s,
        compress=False,  # packets are deflated already
        writer_limit=64 * 1024,  # a slow viewer's writer waits early, so its own queue fills, not memory
        timeout=CLOSE_HANDSHAKE_S,
    )
    await ws.prepare(request)
    ws.remote = remote
    if not settings.view_open:
        status = app[AUTH_KEY].check(request.query.get("token"), remote)
        if status != 200:
            text = auth_message(status, app[AUTH_KEY].retry_after_s(remote))
            await ws.send_str(server_message("error", status=status, message=text))
            await ws.close(code=4000 + status, message=text.encode())
            return ws
    broadcaster = app[BROADCASTER_KEY]
    viewer = broadcaster.add(ws, remote)
    writer = asyncio.create_task(viewer.pump(), name=f"ws-writer {remote}")
    log.debug("viewer %s connected (%d watching)", remote, len(broadcaster.viewers))
    limiter = MessageLimiter(settings.message_rate_per_s, settings.message_burst)
    stats = app[STATS_KEY]
    try:
        async for msg in ws:
            if msg.type not in (WSMsgType.TEXT, WSMsgType.BINARY):
                continue
            verdict = limiter.verdict()
            if verdict == "warn":
                text = (f"too many messages: at most {settings.message_rate_per_s:g} a second "
                        f"(bursts of {settings.message_burst}); slow down or be disconnected")
                stats.note("flood_warnings", f"{remote} sent messages too fast and was told to slow down")
                broadcaster.reply(viewer, server_message("error", status=429, message=text))
            elif verdict == "close":
                stats.note("flood_closes", f"{remote} kept sending too fast and was disconnected (1008)")
                log.warning("viewer %s kept sending too fast: closed (1008)", remote)
                viewer.drop_packets()
                await viewer.drained(1.0)  # the warning goes out before the close
                reason = f"too many messages (over {settings.message_rate_per_s:g}/s)".encode()
                await _hang_up(request, ws, WSCloseCode.POLICY_VIOLATION, reason)
                break
            if verdict != "ok":
                # read no further for a token's time: aiohttp stops reading the socket once its
                # queue is full, so TCP holds the flooder back instead of our loop parsing its frames
                await asyncio.sleep(1.0 / settings.message_rate_per_s)
                continue
            if msg.type == WSMsgType.TEXT:
                _on_client_text(app, viewer, msg.data)
            else:
                stats.note("bad_messages", f"{remote} sent a binary frame")
                broadcaster.reply(viewer, server_message(
                    "error", status=400, message="binary frames are not part of the protocol; send JSON text"))
    finally:
        broadcaster.remove(viewer)
        writer.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await writer
        if not ws.closed:  # the client vanished: closing cancels aiohttp's heartbeat, which holds the socket
            with contextlib.suppress(Exception):
                await asyncio.wait_for(ws.close(code=WSCloseCode.GOING_AWAY), 1.0)
        log.debug("viewer %s left (%d dropped packets)", remote, viewer.dropped)
    return ws


async def _hang_up(request: web.Request, ws: web.WebSocketResponse, code: int, reason: bytes) -> None:
    """Send the close frame and cut the TCP connection at once, reading nothing more from it.

    For a flooder. A close handshake (``ws.close``) reads, and parses, everything the client
    sends until its own close frame: a flooder sends as fast as TCP takes it, so even 0.1 s of
    that handshake kept the loop parsing for 0.1 s (control ticks ~80 ms late at p99 under the
    abuse set on a quiet machine). RFC 6455 §7.1.1 lets the server close the connection first.
    """
    with contextlib.suppress(Exception):  # the socket may be gone already
        await asyncio.wait_for(ws.send_frame(code.to_bytes(2, "big") + reason, WSMsgType.CLOSE),
                               FLOODER_CLOSE_FRAME_S)
    if request.transport is not None:
        request.transport.close()  # stops reading now; what is queued to send is still flushed


def _on_client_text(app: web.Application, viewer: Viewer, text: str) -> None:
    broadcaster = app[BROADCASTER_KEY]
    try:
        msg = parse_client_message(text)
    except ProtocolError as exc:
        app[STATS_KEY].note("bad_messages", f"{viewer.remote} sent a bad message: {exc}")
        broadcaster.reply(viewer, server_message("error", status=400, message=str(exc)))
        return
    if msg.type == "resync":
        broadcaster.resync(viewer)
        return
    if (refusal := replay_refusal(app, msg.type)) is not None:
        broadcaster.reply(viewer, server_message("reply", command=msg.type, ok=False,
                                                 status=REPLAY_COMMAND_STATUS, message=refusal))
        return
    status = app[AUTH_KEY].check(msg.token, viewer.remote)
    if status != 200:
        log.warning("refused %s from %s over the websocket (%d)", msg.type, viewer.remote, status)
        text = auth_message(status, app[AUTH_KEY].retry_after_s(viewer.remote))
        broadcaster.reply(viewer, server_message("reply", command=msg.type, ok=False, status=status, message=text))
        return
    if not _queue_command(app[STATE_KEY], msg.type):
        broadcaster.reply(viewer, server_message("reply", command=msg.type, ok=False, status=503,
                                                 message="too many commands queued; try again"))
        return
    broadcaster.reply(viewer, server_message("reply", command=msg.type, ok=True, status=200, message="accepted"))


# -- lifecycle ----------------------------------------------------------------------------


async def _broadcast_ctx(app: web.Application) -> AsyncIterator[None]:
    """The broadcaster's task lives exactly as long as the application."""
    settings = app[SETTINGS_KEY]
    task = None
    if settings.broadcast_hz > 0:
        task = asyncio.create_task(app[BROADCASTER_KEY].run(), name="web-broadcast")
    yield
    if task is not None:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task


@web.middleware
async def compress_assets(request: web.Request, handler: Handler) -> web.StreamResponse:
    """Page, script and style go compressed (D3 shrinks from 280 KB to 92 KB on the phone's Wi-Fi)."""
    response = await handler(request)
    if isinstance(response, web.FileResponse) and request.path.endswith((".js", ".css", ".html", "/")):
        response.enable_compression()
    return response


async def _close_websockets(app: web.Application) -> None:
    await app[BROADCASTER_KEY].close_all(WSCloseCode.GOING_AWAY, "server shutting down")


def create_app(
    state: SharedState,
    static_dir: Path = DEFAULT_STATIC_DIR,
    settings: WebSettings | None = None,
    replay: Callable[[], dict[str, Any]] | None = None,
    state_dir: Path | None = None,
    calibration: Any = None,
) -> web.Application:
    """Build the web application for one daemon's shared state.

    Without ``settings`` control needs a random token nobody knows (control is locked).
    ``replay`` marks the state as a recording played back (``mazebot replay --serve``): it
    returns what clients are told (``replay`` in ``hello`` and ``/api/status``), and start
    and stop are refused with 409. ``calibration`` (a
    :class:`mazebot.calibration.on_daemon.PageCalibration`) lets the setup view calibrate the
    daemon's devices; without it the calibration routes answer that there is none.
    """
    settings = settings if settings is not None else WebSettings(control_token=secrets.token_hex(16))
    app = web.Application(client_max_size=64 * 1024, middlewares=[compress_assets])
    app[STATE_KEY] = state
    app[STATIC_DIR_KEY] = static_dir
    app[SETTINGS_KEY] = settings
    app[AUTH_KEY] = ControlAuth(settings.control_token)
    app[STATS_KEY] = NetworkStats()
    app[CONNECTIONS_KEY] = ConnectionLimiter(settings.connect_rate_per_s, settings.connect_burst)
    app[BROADCASTER_KEY] = Broadcaster(
        state,
        rate_hz=settings.broadcast_hz or 5.0,
        resync_every=settings.resync_every,
        queue_packets=settings.send_queue_packets,
        heartbeat_s=settings.heartbeat_s,
        trail_points=settings.trail_points,
    )
    if replay is not None:
        app[REPLAY_KEY] = replay
        app[BROADCASTER_KEY].hello_fields = lambda: {"replay": replay()}
    app.router.add_get("/", get_index)
    app.router.add_get("/ws", get_ws)
    app.router.add_get("/api/status", get_status)
    app.router.add_post("/api/{command:start|stop}", post_command)
    app.router.add_get("/map.{kind:" + "|".join(_MAP_FILES) + "}", get_map)
    from mazebot.web import setup  # the setup view: raw scan, wheels, jog, doctor, calibration

    setup.add_routes(app, state_dir, calibration)
    app.router.add_static("/static/", static_dir, follow_symlinks=False)
    app.cleanup_ctx.append(_broadcast_ctx)
    app.on_shutdown.append(_close_websockets)

    return app
