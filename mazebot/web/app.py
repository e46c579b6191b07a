"""The aiohttp application: routes in one place, built by a factory that never runs it."""

from __future__ import annotations

import sys
import time
from pathlib import Path
from typing import Any

from aiohttp import web

from mazebot import __version__
from mazebot.state import SharedState

STATE_KEY = web.AppKey("state", SharedState)
STATIC_DIR_KEY = web.AppKey("static_dir", Path)



def find_static_dir() -> Path:
    """The page and its assets: the repository's ``static/`` folder in a checkout, or the
    copy ``pip install`` puts under ``<prefix>/share/mazebot/static``."""
    checkout = Path(__file__).resolve().parents[2] / "static"
    if (checkout / "index.html").is_file():
        return checkout
    return Path(sys.prefix) / "share" / "mazebot" / "static"


DEFAULT_STATIC_DIR = find_static_dir()


def status_json(state: SharedState) -> dict[str, Any]:
    """The run state as the page and ``/api/status`` show it."""
    fault = state.active_fault
    elapsed_s = None
    if state.started_at_s is not None:
        elapsed_s = round(time.monotonic() - state.started_at_s, 1)
    return {
        "state": state.run_state.value,
        "pose": {
            "x_m": round(state.pose.x_m, 4),
            "y_m": round(state.pose.y_m, 4),
            "theta_rad": round(state.pose.theta_rad, 4),
        },
        "elapsed_s": elapsed_s,
        "fault": None if fault is None else {"source": fault.source, "message": fault.message},
        "faults": [{"source": f.source, "message": f.message} for f in state.faults[-10:]],
        "sensors": vars(state.sensors),
        "version": __version__,
    }


async def get_status(request: web.Request) -> web.Response:
    return web.json_response(status_json(request.app[STATE_KEY]))


async def _post_command(request: web.Request, command: str) -> web.Response:
    state = request.app[STATE_KEY]
    try:
        state.commands.put_nowait(command)
    except Exception:  # asyncio.QueueFull: the command task is behind; say so
        return web.json_response({"error": "too many commands queued; try again"}, status=503)
    return web.json_response({"accepted": command})


async def post_start(request: web.Request) -> web.Response:
    return await _post_command(request, "start")


async def post_stop(request: web.Request) -> web.Response:
    return await _post_command(request, "stop")


async def get_index(request: web.Request) -> web.FileResponse:
    return web.FileResponse(request.app[STATIC_DIR_KEY] / "index.html")


def create_app(state: SharedState, static_dir: Path = DEFAULT_STATIC_DIR) -> web.Application:
    """Build the web application for one daemon's shared state."""
    app = web.Application(client_max_size=64 * 1024)
    app[STATE_KEY] = state
    app[STATIC_DIR_KEY] = static_dir
    app.router.add_get("/", get_index)
    app.router.add_get("/api/status", get_status)
    app.router.add_post("/api/start", post_start)
    app.router.add_post("/api/stop", post_stop)
    app.router.add_static("/static/", static_dir, follow_symlinks=False)
    return app
