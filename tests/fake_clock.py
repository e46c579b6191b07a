"""A clock the test moves by hand: ``t`` is now, ``sleep`` advances it at once (no waiting)."""

from __future__ import annotations


class FakeClock:
    def __init__(self, now_s: float = 0.0) -> None:
        self.t = now_s

    def now_s(self) -> float:
        return self.t

    async def sleep(self, duration_s: float) -> None:
        self.t += duration_s
