"""The control process's scheduling precedence: asked for, and a refusal falls back without failing."""

from __future__ import annotations

import os
from typing import Any

from mazebot.tasks.priority import raise_priority


class Recorder:
    def __init__(self, refuse: bool) -> None:
        self.refuse = refuse
        self.calls: list[tuple[Any, ...]] = []

    def __call__(self, *args: Any) -> None:
        self.calls.append(args)
        if self.refuse:
            raise PermissionError(1, "Operation not permitted")


def test_sched_fifo_is_asked_for_first_and_nice_is_then_left_alone() -> None:
    sched, nice = Recorder(refuse=False), Recorder(refuse=False)
    assert raise_priority(10, -10, sched, nice) == "SCHED_FIFO 10"
    (pid, policy, param), = sched.calls
    assert (pid, policy, param.sched_priority) == (0, os.SCHED_FIFO, 10)
    assert nice.calls == []


def test_a_refused_sched_fifo_falls_back_to_a_lower_nice_value() -> None:
    sched, nice = Recorder(refuse=True), Recorder(refuse=False)
    got = raise_priority(10, -10, sched, nice)
    assert got.startswith("nice -10") and "SCHED_FIFO refused: Operation not permitted" in got
    assert nice.calls == [(os.PRIO_PROCESS, 0, -10)]


def test_when_everything_is_refused_the_loop_stays_on_the_fair_scheduler_and_says_why() -> None:
    got = raise_priority(10, -10, Recorder(refuse=True), Recorder(refuse=True))
    assert got.startswith("the fair scheduler at nice 0")
    assert "SCHED_FIFO refused" in got and "nice -10 refused" in got


def test_zero_asks_for_nothing() -> None:
    sched, nice = Recorder(refuse=False), Recorder(refuse=False)
    assert raise_priority(0, 0, sched, nice) == "the fair scheduler at nice 0"
    assert sched.calls == [] and nice.calls == []
