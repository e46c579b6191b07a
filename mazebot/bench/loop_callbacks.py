"""Names for the event loop's callbacks, for the benchmarks that count or time them.

``bench/sim_speed.py --wakeups`` counts the loop's passes by callback and
``bench/loop_stalls.py`` times them; both need to say which task or function a
``asyncio.Handle`` runs.
"""

from __future__ import annotations

import asyncio


def callback_name(handle: asyncio.Handle) -> str:
    """``task <coroutine> (<file>)`` for a task's step, else the callback's qualified name."""
    callback = handle._callback  # type: ignore[attr-defined]
    owner = getattr(callback, "__self__", None)
    if isinstance(owner, asyncio.Task):
        coro = owner.get_coro()
        code = getattr(coro, "cr_code", None)
        where = code.co_filename.rsplit("/", 1)[-1] if code is not None else "?"
        return f"task {getattr(coro, '__qualname__', '?')} ({where})"
    return getattr(callback, "__qualname__", type(callback).__name__)
