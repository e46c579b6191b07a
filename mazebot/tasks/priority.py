"""Scheduling precedence for the motor control process, where the system permits it.

Why: under a CPU quota (or on a Pi 4 core kept busy by SLAM and the planner) a control
tick that falls due while the daemon's group is throttled waits for the next period, and
then for the busy main process's threads that the fair scheduler also wakes. A task under
``SCHED_FIFO`` runs the moment it wakes, ahead of every fair-scheduled task, and is not
subject to CFS bandwidth control (Linux kernel documentation,
``Documentation/scheduler/sched-rt-group.rst`` and ``sched-bwc.rst``); a real-time task
is instead bounded by the real-time runtime of its group (``cpu.rt_runtime_us``) or the
system-wide ``sched_rt_runtime_us`` (95 % by default), so a runaway loop cannot take the
whole CPU. The control loop sleeps 49 of every 50 ms, which is the kind of task a
real-time priority is meant for.

Order of attempts: ``SCHED_FIFO`` at the configured priority (needs ``CAP_SYS_NICE``, or a
``RLIMIT_RTPRIO`` at least that high: systemd's ``LimitRTPRIO=``, and not
``RestrictRealtime=yes``; with real-time group scheduling, a group that has real-time
runtime), then a lower nice value (``RLIMIT_NICE``: systemd's ``LimitNICE=``), then
nothing: the loop runs as before, and the caller says what it got.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

#: No real-time priority asked for.
RT_OFF = 0


def raise_priority(
    rt_priority: int,
    nice: int,
    set_scheduler: Callable[[int, int, Any], None] | None = None,
    set_nice: Callable[[int, int, int], None] | None = None,
) -> str:
    """Give the calling process ``SCHED_FIFO`` at ``rt_priority``, else ``nice``, else nothing; says which.

    ``rt_priority`` 0 skips the real-time attempt, ``nice`` 0 the nice one. Refusals
    (``PermissionError``, or ``OSError`` such as ``EINVAL`` on a kernel without the
    policy) are expected on an unprivileged system and are not errors: the result is a
    short phrase for the log, e.g. ``"SCHED_FIFO 10"``, ``"nice -10"`` or
    ``"the fair scheduler at nice 0 (SCHED_FIFO refused: ...)"``. The setters are
    parameters so tests can refuse them.
    """
    sched = set_scheduler if set_scheduler is not None else _sched_setscheduler
    renice = set_nice if set_nice is not None else os.setpriority
    why: list[str] = []
    if rt_priority > RT_OFF:
        try:
            sched(0, os.SCHED_FIFO, os.sched_param(rt_priority))
            return f"SCHED_FIFO {rt_priority}"
        except (OSError, AttributeError) as exc:
            why.append(f"SCHED_FIFO refused: {_reason(exc)}")
    if nice != 0:
        try:
            renice(os.PRIO_PROCESS, 0, nice)
            return f"nice {nice}" + (f" ({'; '.join(why)})" if why else "")
        except OSError as exc:
            why.append(f"nice {nice} refused: {_reason(exc)}")
    return "the fair scheduler at nice 0" + (f" ({'; '.join(why)})" if why else "")


def _sched_setscheduler(pid: int, policy: int, param: Any) -> None:
    os.sched_setscheduler(pid, policy, param)


def _reason(exc: BaseException) -> str:
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return type(exc).__name__
