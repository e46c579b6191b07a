"""Starts the web application inside the daemon's event loop."""

from __future__ import annotations

from typing import Any

from aiohttp import web

from mazebot.config import Config
from mazebot.errors import HardwareUnavailable
from mazebot.state import SharedState
from mazebot.web.app import create_app


async def start_web_server(state: SharedState, config: Config, hardware: Any) -> web.AppRunner:
    """Serve the page on ``[web] host:port``; the caller owns ``runner.cleanup()``."""
    app = create_app(state)
    runner = web.AppRunner(app, handle_signals=False, access_log=None)
    await runner.setup()
    site = web.TCPSite(runner, config.web.host, config.web.port)
    try:
        await site.start()
    except OSError as exc:
        await runner.cleanup()
        raise HardwareUnavailable(
            f"web server cannot listen on {config.web.host}:{config.web.port} "
            f"({exc.strerror or exc}); choose another [web] port or stop the other program"
        ) from None
    return runner
