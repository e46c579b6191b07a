"""The same exploration on a fast and on a slow computer ends the same way.

A slower computer (a Raspberry Pi core is 3-5x slower than this machine) is emulated
deterministically on the virtual clock (:class:`mazebot.sim.virtual_time.SlowCpu`): every
callback of the daemon's tasks costs virtual time while the simulated world waits for
nothing, and the loop stalls for 0.1-0.25 s every few seconds (a garbage-collector pause,
a throttled cgroup period). The robot then sees its revolutions late and in bursts, its
map grows in fewer, later steps and its ticks come late, but it still drives the same
maze: whatever the robot decides must depend on what it saw and did, not on how much
wall time passed while the loop could not run. Outcome compared: done, coverage, no
collision, no fault.
"""

from __future__ import annotations

import pytest

from mazebot.bench.runner import RunSpec, run_one
from mazebot.config import Config
from mazebot.sim.virtual_time import PI_CLASS_CPU as SLOW

pytestmark = pytest.mark.slow  # whole simulated runs on a slowed CPU


def _outcome(metrics: dict) -> dict:
    return {
        "done": metrics["done"],
        "covered": metrics["coverage"] is not None and metrics["coverage"] >= 0.99,
        "collisions": metrics["collisions"],
        "fault": metrics["fault"],
    }


def test_a_slow_cpu_with_loop_stalls_explores_the_maze_as_a_fast_one_does() -> None:
    spec = RunSpec(None, (6, 6), 1, "explore", max_sim_s=400.0)
    fast, _ = run_one(Config(), spec)
    slow, record = run_one(Config(), RunSpec(None, (6, 6), 1, "explore", max_sim_s=400.0, slow=SLOW))
    expected = {"done": True, "covered": True, "collisions": 0, "fault": None}
    assert _outcome(fast) == expected, fast
    assert _outcome(slow) == expected, (slow, record.state.planner_events if record.state else None)
