"""Starts the web application inside the daemon's event loop."""

from __future__ import annotations

import asyncio
import errno
import logging
import socket
import time
from pathlib import Path
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


async def start_web_server(
    state: SharedState, config: Config, hardware: Any = None, config_path: Path | None = None
) -> web.AppRunner:
    """Serve the page on ``[web] host:port``; the caller owns ``runner.cleanup()``.

    With ``hardware`` (the daemon's devices) the setup view can calibrate them; a confirmed
    calibration replaces ``config_path`` (the file the daemon was started with).
    """
    settings = WebSettings.from_config(config.web, control_token(config))
    state_dir = resolve_state_dir(config.daemon.state_dir)
    calibration = None
    if hardware is not None:
        from mazebot.calibration.on_daemon import PageCalibration

        calibration = PageCalibration(state, config, config_path, sim=getattr(hardware, "sim", None) is not None,
                                      report_dir=state_dir)
    app = create_app(state, settings=settings, state_dir=state_dir, calibration=calibration)
    runner = web.AppRunner(app, handle_signals=False, access_log=None, shutdown_timeout=2.0)
    await runner.setup()
    site = web.TCPSite(runner, config.web.host, config.web.port)
    try:
        await _wait_for_address(config.web.host, config.web.bind_wait_s)
        await site.start()
    except socket.gaierror as exc:  # not an address, nor a name this machine can resolve
        await runner.cleanup()
        raise ConfigError(
            f"web.host: {config.web.host!r} is not an address of this machine ({exc.strerror or exc}); "
            "use an interface's address, 127.0.0.1 (this machine only) or 0.0.0.0 (every interface)"
        ) from None
    except OSError as exc:
        await runner.cleanup()
        if exc.errno == errno.EADDRNOTAVAIL:
            raise HardwareUnavailable(
                f"web server cannot listen on {config.web.host}:{config.web.port}: no interface of this machine "
                f"has that address (waited {config.web.bind_wait_s:.0f} s, [web] bind_wait_s); check the network "
                "or use 0.0.0.0 (every interface)"
            ) from None
        raise HardwareUnavailable(
            f"web server cannot listen on {config.web.host}:{config.web.port} "
            f"({exc.strerror or exc}); choose another [web] port or stop the other program"
        ) from None
    return runner


BIND_RETRY_S = 0.5


def _address_is_up(host: str) -> bool:
    """Whether an interface has ``host``'s address: a bind to it on a free port succeeds.

    Binding port 0 asks only about the address, so a port taken by another program shows up
    later, in the real bind, with its own message. A name that does not resolve raises
    ``socket.gaierror`` here, as it would there.
    """
    for family, kind, proto, _name, address in socket.getaddrinfo(host or None, 0, type=socket.SOCK_STREAM,
                                                                   flags=socket.AI_PASSIVE):
        with socket.socket(family, kind, proto) as probe:
            try:
                probe.bind((*address[:1], 0, *address[2:]))
            except OSError as exc:
                if exc.errno == errno.EADDRNOTAVAIL:
                    return False
                raise
    return True


async def _wait_for_address(host: str, wait_s: float) -> None:
    """Wait up to ``wait_s`` for ``host``'s address to exist on this machine.

    A robot set to serve on its Wi-Fi address starts at boot, often before the network has
    given it that address: the bind fails with EADDRNOTAVAIL for a few seconds. Exiting then
    (69) would leave the robot without its page, since systemd does not restart on 69.
    After ``wait_s`` the real bind is tried anyway and fails with its own error.
    """
    deadline_s = time.monotonic() + wait_s
    loop = asyncio.get_running_loop()
    if await loop.run_in_executor(None, _address_is_up, host):  # a name's lookup may take a while
        return
    log.warning("web.host %s is not an address of this machine yet; waiting up to %.0f s "
                "for the network to bring it up ([web] bind_wait_s)", host, wait_s)
    while time.monotonic() < deadline_s:
        await asyncio.sleep(BIND_RETRY_S)
        if await loop.run_in_executor(None, _address_is_up, host):
            log.info("web.host %s is up: serving", host)
            return
