"""The names the loop benchmarks give the event loop's callbacks."""

from __future__ import annotations

import asyncio

from mazebot.bench.loop_callbacks import callback_name


async def _sleeper() -> None:
    await asyncio.sleep(0)


def test_a_task_step_is_named_by_its_coroutine_and_file_a_plain_callback_by_its_name() -> None:
    loop = asyncio.new_event_loop()
    try:
        task = loop.create_task(_sleeper())
        handles = list(loop._ready)  # the task's first step, scheduled by create_task
        assert [callback_name(h) for h in handles] == ["task _sleeper (test_loop_callbacks.py)"]
        plain = loop.call_soon(print)
        assert callback_name(plain) == "print"
        loop.run_until_complete(task)
    finally:
        loop.close()
