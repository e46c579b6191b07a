"""Who may do what on the page: the PIN, the origin check, and the commands a replay refuses.

Shared by every route that moves the robot or shows it (start/stop in :mod:`mazebot.web.app`,
jogging in :mod:`mazebot.web.setup`, calibration in :mod:`mazebot.web.calibration`), so each
command is guarded the same way: the origin first, then a replay's refusal, then the PIN.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from aiohttp import web

from mazebot.state import SharedState
from mazebot.web.auth import ControlAuth, origin_allowed

log = logging.getLogger("mazebot.web.app")

TOKEN_HEADER = "X-Mazebot-Token"


@dataclass(frozen=True)
class WebSettings:
    """What the web layer needs from ``[web]``, as plain values (see :class:`mazebot.config.WebConfig`).

    ``broadcast_hz = 0`` starts no broadcast task (tests call ``Broadcaster.tick()``).
    """

    control_token: str
    broadcast_hz: float = 5.0
    resync_every: int = 50
    view_open: bool = True
    allowed_origins: tuple[str, ...] = ()
    send_queue_packets: int = 8
    max_message_bytes: int = 4096
    heartbeat_s: float = 10.0
    trail_points: int = 1000
    message_rate_per_s: float = 20.0
    message_burst: int = 40
    connect_rate_per_s: float = 5.0
    connect_burst: int = 20

    @classmethod
    def from_config(cls, web_config: Any, control_token: str) -> WebSettings:
        return cls(
            control_token=control_token,
            broadcast_hz=web_config.broadcast_hz,
            resync_every=web_config.resync_every,
            view_open=web_config.view_open,
            allowed_origins=tuple(web_config.allowed_origins),
            send_queue_packets=web_config.send_queue_packets,
            max_message_bytes=web_config.max_message_bytes,
            heartbeat_s=web_config.heartbeat_s,
            trail_points=web_config.trail_points,
            message_rate_per_s=web_config.message_rate_per_s,
            message_burst=web_config.message_burst,
            connect_rate_per_s=web_config.connect_rate_per_s,
            connect_burst=web_config.connect_burst,
        )


STATE_KEY = web.AppKey("state", SharedState)
SETTINGS_KEY = web.AppKey("settings", WebSettings)
AUTH_KEY = web.AppKey("auth", ControlAuth)
#: A replay (``mazebot replay --serve``): what to tell clients about it; absent for a robot.
REPLAY_KEY = web.AppKey[Callable[[], dict[str, Any]]]("replay")
#: The answer to start/stop during a replay: 409 Conflict (there is no robot behind the page).
REPLAY_COMMAND_STATUS = 409


def presented_token(request: web.Request) -> str | None:
    token = request.headers.get(TOKEN_HEADER)
    if token is None:
        auth = request.headers.get("Authorization", "")
        if auth.lower().startswith("bearer "):
            token = auth[7:].strip()
    if token is None:
        token = request.query.get("token")
    return token


AUTH_MESSAGES = {
    401: "a PIN is needed: send it in the X-Mazebot-Token header",
    403: "wrong PIN",
    429: "too many wrong PINs from this address; try again in {retry_s} s",
}


def auth_message(status: int, retry_after_s: float = 0.0) -> str:
    return AUTH_MESSAGES[status].format(retry_s=math.ceil(retry_after_s))


def auth_error(request: web.Request, status: int) -> web.Response:
    headers = None
    retry_s = 0.0
    if status == 401:
        headers = {"WWW-Authenticate": 'Bearer realm="mazebot"'}
    elif status == 429:
        retry_s = request.app[AUTH_KEY].retry_after_s(request.remote or "?")
        headers = {"Retry-After": str(math.ceil(retry_s))}
    return web.json_response({"error": auth_message(status, retry_s)}, status=status, headers=headers)


def check_origin(request: web.Request) -> None:
    settings = request.app[SETTINGS_KEY]
    if not origin_allowed(request.headers.get("Origin"), request.host, settings.allowed_origins):
        raise web.HTTPForbidden(
            text=f"origin {request.headers.get('Origin')!r} may not use this robot; add it to [web] allowed_origins"
        )


def check_view(request: web.Request) -> web.Response | None:
    """None if the request may watch; else the error response."""
    if request.app[SETTINGS_KEY].view_open:
        return None
    status = request.app[AUTH_KEY].check(presented_token(request), request.remote or "?")
    return None if status == 200 else auth_error(request, status)


def replay_refusal(app: web.Application, command: str) -> str | None:
    """Why ``command`` cannot be done when the page shows a replay; None for a robot."""
    replay = app.get(REPLAY_KEY)
    if replay is None:
        return None
    return f"this page shows a replay of {replay()['file']}: there is no robot to {command}"


def authorize_command(request: web.Request, command: str) -> web.Response | None:
    """None when ``command`` (start, stop, jog, calibrate…) may be done; else the refusal to send.

    Raises ``HTTPForbidden`` for a foreign origin (:func:`check_origin`).
    """
    check_origin(request)
    if (refusal := replay_refusal(request.app, command)) is not None:
        return web.json_response({"error": refusal}, status=REPLAY_COMMAND_STATUS)
    status = request.app[AUTH_KEY].check(presented_token(request), request.remote or "?")
    if status != 200:
        log.warning("refused %s from %s (%d)", command, request.remote, status)
        return auth_error(request, status)
    return None
