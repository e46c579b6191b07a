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
