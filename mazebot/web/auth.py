"""Who may start and stop the robot, and from which pages.

Control (start/stop) needs a PIN/token: the configured one, or one generated on first
start and kept in the state directory (``control_token``, mode 0600). Tokens are compared
in constant time (``hmac.compare_digest``), and an address that keeps guessing is backed
off exponentially (see :class:`ControlAuth`). Browsers must come from the page's own origin
(or a configured one).
"""

from __future__ import annotations

import hmac
import ipaddress
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


def client_key(remote: str) -> str:
    """The address wrong PINs are counted against: IPv4 as is, IPv6 by its /64.

    One IPv6 host usually owns a whole /64 (SLAAC privacy addresses, RFC 8981), so
    counting single addresses would hand an attacker a fresh budget per address.
    """
    try:
        ip = ipaddress.ip_address(remote.split("%")[0])
    except ValueError:
        return remote
    if isinstance(ip, ipaddress.IPv6Address):
        if ip.ipv4_mapped is not None:
            return str(ip.ipv4_mapped)
        return str(ipaddress.IPv6Network((ip, 64), strict=False))
    return str(ip)


@dataclass
class _Strikes:
    failures: int = 0  # consecutive wrong PINs
    last_s: float = 0.0  # when the last one came
    locked_until_s: float = 0.0


@dataclass
class ControlAuth:
    """Checks control tokens and backs off a client address that keeps guessing.

    ``check`` answers an HTTP status: 200 ok, 401 no token, 403 wrong token, 429 locked out.
    The first ``free_failures - 1`` wrong PINs in a row cost nothing (typos); the next one
    locks the address out for ``first_delay_s``, and every further one doubles the lockout
    up to ``max_delay_s``. While locked out every token is refused unseen, right or wrong,
    so a guess made then teaches nothing. A right PIN clears the count; an address quiet for
    ``forget_s`` is forgotten. With the defaults (5, 1 s, 60 s) a 6-digit PIN costs an
    address one guess a minute once warmed up: ~1 year to try half of 10**6.

    At most ``max_clients`` addresses are remembered (bounded memory); the quiet ones go
    first, then the oldest.

    Example::

        auth = ControlAuth("123456")
        auth.check("123456", "10.0.0.7")   # 200
        auth.check(None, "10.0.0.7")       # 401
    """

    token: str
    free_failures: int = 5
    first_delay_s: float = 1.0
    max_delay_s: float = 60.0
    forget_s: float = 3600.0
    max_clients: int = 4096
    now_s: Callable[[], float] = time.monotonic
    lockouts: int = 0  # how many times an address was locked out (shown in /api/status)
    _clients: dict[str, _Strikes] = field(default_factory=dict)

    def check(self, presented: str | None, client: str) -> int:
        now = self.now_s()
        key = client_key(client)
        strikes = self._clients.get(key)
        if strikes is not None and strikes.locked_until_s > now:
            return 429
        if presented is None or presented == "":
            return 401
        if token_matches(self.token, presented):
            self._clients.pop(key, None)
            return 200
        if strikes is None or now - strikes.last_s > self.forget_s:
            strikes = _Strikes()
        self._clients.pop(key, None)  # re-insert: the dict stays ordered by last failure
        self._clients[key] = strikes
        strikes.failures += 1
        strikes.last_s = now
        if strikes.failures >= self.free_failures:
            doublings = min(strikes.failures - self.free_failures, 30)
            strikes.locked_until_s = now + min(self.max_delay_s, self.first_delay_s * 2.0**doublings)
            self.lockouts += 1
        self._bound(now)
        return 403

    def retry_after_s(self, client: str) -> float:
        """Seconds until ``client`` may try again (0 when it is not locked out)."""
        strikes = self._clients.get(client_key(client))
        return 0.0 if strikes is None else max(0.0, strikes.locked_until_s - self.now_s())

    @property
    def locked_out(self) -> int:
        """Addresses locked out right now."""
        now = self.now_s()
        return sum(1 for s in self._clients.values() if s.locked_until_s > now)

    def _bound(self, now: float) -> None:
        if len(self._clients) <= self.max_clients:
            return
        for key in [k for k, s in self._clients.items() if now - s.last_s > self.forget_s and s.locked_until_s <= now]:
            del self._clients[key]
        while len(self._clients) > self.max_clients:
            del self._clients[next(iter(self._clients))]


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
