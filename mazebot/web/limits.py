"""How much a single websocket client may send: a token bucket per connection.

A phone sends a handful of messages a minute (start, stop, an occasional resync), so a
client sending more than ``rate_per_s`` for longer than ``burst`` messages is broken or
hostile. Its excess messages are dropped unread; it is told once, and closed with 1008
(policy violation) if it keeps on for another ``burst`` messages.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass
class TokenBucket:
    """``burst`` tokens, refilled at ``rate_per_s``; each message takes one.

    Example::

        bucket = TokenBucket(rate_per_s=20, burst=40)
        bucket.take()      # True while tokens last
    """

    rate_per_s: float
    burst: float
    now_s: Callable[[], float] = time.monotonic
    tokens: float = field(init=False)
    _last_s: float = field(init=False)

    def __post_init__(self) -> None:
        if self.rate_per_s <= 0 or self.burst < 1:
            raise ValueError(f"a token bucket needs rate_per_s > 0 and burst >= 1, got {self.rate_per_s}, {self.burst}")
        self.tokens = float(self.burst)
        self._last_s = self.now_s()

    def _refill(self) -> None:
        now = self.now_s()
        self.tokens = min(float(self.burst), self.tokens + (now - self._last_s) * self.rate_per_s)
        self._last_s = now

    def take(self) -> bool:
        """Whether one more message fits now (and count it if so)."""
        self._refill()
        if self.tokens >= 1.0:
            self.tokens -= 1.0
            return True
        return False

    @property
    def full(self) -> bool:
        self._refill()
        return self.tokens >= self.burst


class MessageLimiter:
    """One client's verdict on each message it sends: ``"ok"``, ``"warn"`` (first excess:
    tell it), ``"drop"`` (excess, already told) or ``"close"`` (kept on for another burst)."""

    def __init__(self, rate_per_s: float, burst: int, now_s: Callable[[], float] = time.monotonic) -> None:
        self.bucket = TokenBucket(rate_per_s, burst, now_s)
        self.burst = burst
        self.excess = 0  # messages dropped since the client was last calm (bucket full)

    def verdict(self) -> str:
        if self.excess and self.bucket.full:
            self.excess = 0  # it calmed down: forgive
        if self.bucket.take():
            return "ok"
        self.excess += 1
        if self.excess == 1:
            return "warn"
        return "close" if self.excess > self.burst else "drop"


class ConnectionLimiter:
    """New websocket connections per client address: a token bucket for each.

    A page opens one socket and reconnects at most every second or so; a client opening
    dozens a second (or reconnecting as soon as it is closed for flooding) costs the
    server a handshake, a hello and a full map each time, on the loop the control task
    shares. Its excess connections are refused before the upgrade (HTTP 429). At most
    ``max_clients`` addresses are remembered; the ones whose bucket is full again go first.

    Example::

        limiter = ConnectionLimiter(rate_per_s=5, burst=20)
        limiter.allow("10.0.0.7")   # True while that address has tokens left
    """

    def __init__(self, rate_per_s: float, burst: int, max_clients: int = 4096,
                 now_s: Callable[[], float] = time.monotonic) -> None:
        self.rate_per_s = rate_per_s
        self.burst = burst
        self.max_clients = max_clients
        self.refused = 0
        self._now_s = now_s
        self._buckets: dict[str, TokenBucket] = {}

    def allow(self, key: str) -> bool:
        bucket = self._buckets.get(key)
        if bucket is None:
            if len(self._buckets) >= self.max_clients:
                self._forget()
            bucket = self._buckets[key] = TokenBucket(self.rate_per_s, self.burst, self._now_s)
        if bucket.take():
            return True
        self.refused += 1
        return False

    def _forget(self) -> None:
        for key in [k for k, b in self._buckets.items() if b.full]:
            del self._buckets[key]
        while len(self._buckets) >= self.max_clients:
            del self._buckets[next(iter(self._buckets))]
