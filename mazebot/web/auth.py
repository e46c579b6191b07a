"""Who may start and stop the robot, and from which pages.

Control (start/stop) needs a PIN/token: the configured one, or one generated on first
start and kept in the state directory (``control_token``, mode 0600). Tokens are compared
in constant time (``hmac.compare_digest``), and a client that keeps guessing is locked
out for a while. Browsers must come from the page's own origin (or a configured one).
"""

from __future__ import annotations

import hmac
import os
import secrets
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

TOKEN_FILE = "control_token"
#: Generated PINs have this many digits: typed on a phone, guarded by the lockout below.
PIN_DIGITS = 6


def resolve_state_dir(configured: str, env: Mapping[str, str] = os.environ) -> Path:
    """The ``[daemon] state_dir``, else systemd's ``$STATE_DIRECTORY``, else ``$XDG_STATE_HOME/mazebot``
    (``~/.local/state/mazebot``)."""
    if configured:
        return Path(configured).expanduser()
    if env.get("STATE_DIRECTORY"):
        return Path(env["STATE_DIRECTORY"].split(":")[0])
    base = env.get("XDG_STATE_HOME") or str(Path.home() / ".local" / "state")
    return Path(base) / "mazebot"


def load_or_create_token(configured: str, state_dir: Path) -> tuple[str, bool]:
    """The control token and whether it was just generated.

    A configured token wins. Otherwise the one stored in ``state_dir/control_token`` is
    used, or a new random PIN is written there (owner-only) on first start.
    """
    if configured:
        return configured, False
    path = state_dir / TOKEN_FILE
    try:
        stored = path.read_text(encoding="utf-8").strip()
    except FileNotFoundError:
        stored = ""
    except OSError as exc:
        raise OSError(f"cannot read the control token {path} ({exc.strerror or exc}); "
                      "fix its permissions or set [web] control_token") from None
    if stored:
        return stored, False
    token = f"{secrets.randbelow(10**PIN_DIGITS):0{PIN_DIGITS}d}"
    state_dir.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "w", encoding="utf-8") as f:
        f.write(token + "\n")
    return token, True


def token_matches(expected: str, presented: str | None) -> bool:
    """Constant-time comparison; no token presented never matches."""
    if presented is None:
        return False
    return hmac.compare_digest(expected.encode(), presented.encode())


@dataclass
class ControlAuth:
    """Checks control tokens and locks out a client after repeated wrong ones.

    ``check`` answers an HTTP status: 200 ok, 401 no token, 403 wrong token, 429 locked out
    (``max_failures`` wrong tokens within ``window_s`` lock that client out for ``lockout_s``).

    Example::

        auth = ControlAuth("123456")
        auth.check("123456", "10.0.0.7")   # 200
        auth.check(None, "10.0.0.7")       # 401
    """

    token: str
    max_failures: int = 5
    window_s: float = 60.0
    lockout_s: float = 60.0
    now_s: Callable[[], float] = time.monotonic
    _failures: dict[str, list[float]] = field(default_factory=dict)
    _locked_until: dict[str, float] = field(default_factory=dict)

    def check(self, presented: str | None, client: str) -> int:
        now = self.now_s()
        if self._locked_until.get(client, 0.0) > now:
            return 429
        if presented is None or presented == "":
            return 401
        if token_matches(self.token, presented):
            self._failures.pop(client, None)
            return 200
        recent = [t for t in self._failures.get(client, []) if now - t < self.window_s]
        recent.append(now)
        self._failures[client] = recent
        if len(recent) >= self.max_failures:
            self._locked_until[client] = now + self.lockout_s
            del self._failures[client]
        if len(self._failures) > 1000:  # bounded memory whatever the clients do
            self._failures.clear()
        return 403


def origin_allowed(origin: str | None, host: str | None, allowed: Iterable[str]) -> bool:
    """Whether a request's ``Origin`` may use the websocket and the control API.

    No ``Origin`` (curl, scripts: not a browser page, so no cross-site risk) is allowed;
    a browser's must be the page's own (same host:port as the ``Host`` header) or one of
    ``allowed`` (full origins like ``http://robot.local:8080``; ``*`` allows any).
    """
    if origin is None:
        return True
    allowed = list(allowed)
    if "*" in allowed or origin in allowed:
        return True
    if origin == "null" or host is None:
        return False
    parts = urlsplit(origin)
    if parts.scheme not in ("http", "https") or not parts.netloc:
        return False
    default_port = 443 if parts.scheme == "https" else 80
    return _host_port(parts.netloc, default_port) == _host_port(host, default_port)


def _host_port(netloc: str, default_port: int) -> tuple[str, int]:
    parts = urlsplit("//" + netloc)
    try:
        port = parts.port or default_port
    except ValueError:
        port = -1
    return (parts.hostname or "").lower(), port
