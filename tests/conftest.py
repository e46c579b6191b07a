"""What every test must leave as it found it: the test process's scheduling.

The control process asks for ``SCHED_FIFO`` (``mazebot.tasks.priority``). A test that runs
its entry point in the test process itself would make the whole test session real-time,
and everything started afterwards inherits the policy: a headless Chromium started as
``SCHED_FIFO`` on this 2-core machine once spun both cores in the kernel while reaping a
child, starving every other process. So each test's scheduling policy and nice value are
checked after it, restored, and a change is an error of that test.
"""

from __future__ import annotations

import contextlib
import os
from collections.abc import Iterator

import pytest


def _scheduling() -> tuple[int, int]:
    return os.sched_getscheduler(0), os.getpriority(os.PRIO_PROCESS, 0)


@pytest.fixture(autouse=True)
def _scheduling_left_as_found() -> Iterator[None]:
    before = _scheduling()
    yield
    after = _scheduling()
    if after == before:
        return
    os.sched_setscheduler(0, before[0], os.sched_param(0))
    with contextlib.suppress(PermissionError):  # a lower nice than before needs privilege; the policy is the danger
        os.setpriority(os.PRIO_PROCESS, 0, before[1])
    pytest.fail(f"the test changed the test process's scheduling (policy, nice) from {before} to {after}; "
                "give it a config with [daemon] control_rt_priority = 0 and control_nice = 0")
