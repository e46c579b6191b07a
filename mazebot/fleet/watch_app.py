"""``mazebot watch``'s web page: every robot of the fleet, each on the phone page of its own.

Routes::

    GET  /                        the robots found, with links (plain HTML, refreshes itself)
    GET  /api/robots              the same as JSON
    GET  /robot/<name>/           the phone page (static/index.html), fed from Zenoh
    GET  /robot/<name>/ws         the page's websocket (docs/protocol.md): the robot's own packets
    GET  /robot/<name>/api/status what the watcher knows of the robot (JSON)
    POST /robot/<name>/api/start  start/stop, forwarded over Zenoh with the PIN the page sends;
    POST /robot/<name>/api/stop   the robot checks it (and backs off wrong ones) as its own page does
    GET  /static/...              the page's assets

The page finds its websocket and API next to itself (``static/app.js``: relative to the
page's folder), so the same page serves a robot and a robot seen through the watcher.
"""

from __future__ import annotations

import asyncio
import contextlib
import html
from collections.abc import AsyncIterator
from pathlib import Path

from aiohttp import WSMsgType, web

from mazebot.fleet.watcher import Fleet, RobotMirror
from mazebot.web.access import TOKEN_HEADER
from mazebot.web.app import DEFAULT_STATIC_DIR
from mazebot.web.auth import origin_allowed
from mazebot.web.broadcaster import Viewer
from mazebot.web.limits import MessageLimiter
from mazebot.web.protocol import ProtocolError, parse_client_message, server_message

FLEET_KEY = web.AppKey("fleet", Fleet)
#: Heartbeats to the browsers, seconds (the page reconnects after ~2.5 silent heartbeats).
HEARTBEAT_S = 10.0
QUEUE_PACKETS = 8
MAX_MESSAGE_BYTES = 4096


def _robot(request: web.Request) -> RobotMirror:
    robot = request.app[FLEET_KEY].robots.get(request.match_info["name"])
    if robot is None:
        raise web.HTTPNotFound(text=f"no robot {request.match_info['name']!r} found on the Zenoh network (yet)")
    return robot


def _check_origin(request: web.Request) -> None:
    if not origin_allowed(request.headers.get("Origin"), request.host, ()):
        raise web.HTTPForbidden(text=f"origin {request.headers.get('Origin')!r} may not use this watcher")


async def get_list(request: web.Request) -> web.Response:
    rows = []
    for robot in sorted(request.app[FLEET_KEY].robots.values(), key=lambda r: r.name):
        s = robot.summary()
        name = html.escape(robot.name)
        coverage = "" if s["coverage"] is None else f"{100 * s['coverage']:.0f} %"
        rows.append(f'<tr><td><a href="/robot/{name}/">{name}</a></td><td>{html.escape(str(s["state"]))}</td>'
                    f'<td>{coverage}</td><td>{"here" if robot.alive else "gone"}</td></tr>')
    body = ("<!doctype html><meta charset=utf-8><meta name=viewport content='width=device-width'>"
            "<meta http-equiv=refresh content=2><title>mazebot fleet</title>"
            "<h1>mazebot fleet</h1><table><tr><th>robot<th>state<th>coverage<th>on the network</tr>"
            + "".join(rows) + "</table>" + ("" if rows else "<p>No robot found yet.</p>"))
    return web.Response(text=body, content_type="text/html")


async def get_robots(request: web.Request) -> web.Response:
    return web.json_response([r.summary() for r in request.app[FLEET_KEY].robots.values()])


async def get_page(request: web.Request) -> web.FileResponse:
    _robot(request)
    return web.FileResponse(DEFAULT_STATIC_DIR / "index.html", headers={"Cache-Control": "no-cache"})


async def get_status(request: web.Request) -> web.Response:
    robot = _robot(request)
    return web.json_response({**robot.summary(), "status": robot.status, "pose_message": robot.pose})


async def post_command(request: web.Request) -> web.Response:
    """``POST /robot/NAME/api/start`` and ``/stop``: forwarded to the robot with the PIN given."""
    command = request.match_info["command"]
    _check_origin(request)
    robot = _robot(request)
    token = request.headers.get(TOKEN_HEADER)
    reply = await request.app[FLEET_KEY].control(robot.name, command, token)
    if reply.get("ok"):
        return web.json_response({"accepted": command})
    return web.json_response({"error": reply.get("message")}, status=int(reply.get("status", 502)))


async def get_ws(request: web.Request) -> web.WebSocketResponse:
    _check_origin(request)
    robot = _robot(request)
    fleet = request.app[FLEET_KEY]
    ws = web.WebSocketResponse(max_msg_size=MAX_MESSAGE_BYTES, heartbeat=HEARTBEAT_S, compress=False)
    await ws.prepare(request)
    remote = request.remote or "?"
    viewer = Viewer(ws, remote, QUEUE_PACKETS)
    viewer.offer(robot.hello(), robot.full_packet)
    if not robot.waiting_full:
        viewer.offer(robot.full_packet(), robot.full_packet)
    robot.viewers.add(viewer)
    writer = asyncio.create_task(viewer.pump(), name=f"watch-writer {remote}")
    limiter = MessageLimiter(20.0, 40)
    try:
        async for msg in ws:
            if msg.type != WSMsgType.TEXT:
                continue
            if limiter.verdict() != "ok":
                continue
            try:
                parsed = parse_client_message(msg.data)
            except ProtocolError as exc:
                viewer.offer(server_message("error", status=400, message=str(exc)), robot.full_packet)
                continue
            if parsed.type == "resync":
                if not robot.waiting_full:
                    viewer.offer(robot.full_packet(), robot.full_packet)
                continue
            reply = await fleet.control(robot.name, parsed.type, parsed.token)
            viewer.offer(server_message("reply", **{k: v for k, v in reply.items() if k != "type"}), robot.full_packet)
    finally:
        robot.viewers.discard(viewer)
        writer.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await writer
    return ws


async def _heartbeats(app: web.Application) -> AsyncIterator[None]:
    async def beat() -> None:
        while True:
            await asyncio.sleep(HEARTBEAT_S)
            for robot in app[FLEET_KEY].robots.values():
                text = server_message("heartbeat", seq=robot.seq)
                for viewer in robot.viewers:
                    viewer.offer(text, robot.full_packet)

    task = asyncio.create_task(beat(), name="watch-heartbeats")
    yield
    task.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await task


async def _close_viewers(app: web.Application) -> None:
    for robot in app[FLEET_KEY].robots.values():
        for viewer in list(robot.viewers):
            with contextlib.suppress(Exception):
                await asyncio.wait_for(viewer.ws.close(message=b"watcher shutting down"), 1.0)


def create_watch_app(fleet: Fleet, static_dir: Path = DEFAULT_STATIC_DIR) -> web.Application:
    """The watcher's application for ``fleet`` (already started); never runs it."""
    app = web.Application(client_max_size=64 * 1024)
    app[FLEET_KEY] = fleet
    app.router.add_get("/", get_list)
    app.router.add_get("/api/robots", get_robots)
    app.router.add_get("/robot/{name}/", get_page)
    app.router.add_get("/robot/{name}/ws", get_ws)
    app.router.add_get("/robot/{name}/api/status", get_status)
    app.router.add_post("/robot/{name}/api/{command:start|stop}", post_command)
    app.router.add_static("/static/", static_dir, follow_symlinks=False)
    app.cleanup_ctx.append(_heartbeats)
    app.on_shutdown.append(_close_viewers)
    return app


def robot_url(base: str, name: str) -> str:
    return f"{base.rstrip('/')}/robot/{name}/"

