"""Starts the web application inside the daemon's event loop."""

from __future__ import annotations

import logging
import socket
from typing import Any

from aiohttp import web

from mazebot.config import Config
from mazebot.errors import ConfigError, HardwareUnavailable
from mazebot.state import SharedState
from mazebot.web.app import WebSettings, create_app
from mazebot.web.auth import load_or_create_token, resolve_state_dir

log = logging.getLogger(__name__)


def control_token(config: Config) -> str:
    """The configured token, or the one kept in the state dir (generated and logged once)."""
    state_dir = resolve_state_dir(config.daemon.state_dir)
    try:
        token, created = load_or_create_token(config.web.control_token, state_dir)
    except OSError as exc:
        raise ConfigError(
            f"cannot keep the control token in {state_dir} ({exc.strerror or exc}); "
            "set [daemon] state_dir to a writable folder or [web] control_token"
        ) from None
    if created:
        # shown once on the console; ``secret`` keeps it out of recordings (record_task.LogTap)
        log.warning("control PIN for start/stop: %s (generated once, kept in %s)", token, state_dir / "control_token",
                    extra={"secret": True})
    return token


async def start_web_server(state: SharedState, config: Config, hardware: Any = None) -> web.AppRunner:
    """Serve the page on ``[web] host:port``; the caller owns ``runner.cleanup()``."""
    settings = WebSettings.from_config(config.web, control_token(config))
    app = create_app(state, settings=settings)
    runner = web.AppRunner(app, handle_signals=False, access_log=None, shutdown_timeout=2.0)
    await runner.setup()
    site = web.TCPSite(runner, config.web.host, config.web.port)
    try:
        await site.start()
    except socket.gaierror as exc:  # not an address, nor a name this machine can resolve
        await runner.cleanup()
        raise ConfigError(
            f"web.host: {config.web.host!r} is not an address of this machine ({exc.strerror or exc}); "
            "use an interface's address, 127.0.0.1 (this machine only) or 0.0.0.0 (every interface)"
        ) from None
    except OSError as exc:
        await runner.cleanup()
        raise HardwareUnavailable(
            f"web server cannot listen on {config.web.host}:{config.web.port} "
            f"({exc.strerror or exc}); choose another [web] port or stop the other program"
        ) from None
    return runner
