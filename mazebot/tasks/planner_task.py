"""The planner loop: one :class:`~mazebot.planner.pilot.Pilot` tick per planner period.

The tick reads the map and pose SLAM published and writes the goal, the path and the
body-velocity command; the wheels are the control task's. A tick costs a few
milliseconds (graph update, route search, DWA); it runs on the event loop so it sees a
consistent map (its inputs are taken at the start of each half) and never races the
writers, in two halves (goal, then motion) with the loop free in between, the motion half
itself in stages (the DWA's clearance queries, :meth:`Pilot.drive_steps`), so a control
tick never waits for a whole planner tick.

The goal half is in stages too (the maze graph, then the goal; a frontier search over
the whole grid in several). When it takes longer than a planner period of wall time (a
16x16 maze on a Pi 4's share of a core: a frontier goal is ~25 ms of CPU here, more than
100 ms of wall time under the quota, behind SLAM's stages), a motion half runs between
two of its stages (:meth:`Pilot.motion_due`, :meth:`Pilot.interim_drive_steps`): the DWA
on the latest pose and scan along the path being followed, so the control loop gets a
fresh command within a period and a control period instead of stopping the wheels for a
stale one. Both halves are this task's: one writer of the goal, the path and the command.
"""

from __future__ import annotations

import asyncio

from mazebot.clock import Clock
from mazebot.cpu_budget import RecentValues
from mazebot.planner.pilot import Pilot
from mazebot.state import SharedState
from mazebot.steps import run_steps_async, timed_stages


async def run(state: SharedState, clock: Clock, pilot: Pilot, tick_ms: RecentValues | None = None) -> None:
    """Tick the pilot at its rate; ``tick_ms`` (if given) collects each tick's CPU time in ms."""
    period_s = pilot.params.period_s
    next_tick_s = clock.now_s()
    while True:
        cpu_s = [0.0]  # each half in stages (map and graph, goal; DWA blocks), the loop free in between
        if await _goal_half(state, clock, pilot, cpu_s):
            await asyncio.sleep(0)  # let a due control tick run between the two halves
            await run_steps_async(pilot.drive_steps(state, clock.now_s()), cpu_s)
        spent_s = cpu_s[0]
        state.cpu.part("planner tick").add(spent_s)
        if tick_ms is not None:
            tick_ms.append(spent_s * 1000.0)
        next_tick_s += period_s
        now_s = clock.now_s()
        if next_tick_s < now_s:  # fell behind: do not try to catch up
            next_tick_s = now_s + period_s
        await clock.sleep(next_tick_s - now_s)


async def _goal_half(state: SharedState, clock: Clock, pilot: Pilot, cpu_s: list[float]) -> bool:
    """:meth:`Pilot.plan_steps` with the loop free between its stages, and a motion half
    between two of them whenever the last command is overdue (:meth:`Pilot.motion_due`)."""
    stages = timed_stages(pilot.plan_steps(state, clock.now_s()), cpu_s)
    try:
        while True:
            try:
                next(stages)
            except StopIteration as stop:
                return bool(stop.value)
            await asyncio.sleep(0)
            if pilot.motion_due(clock.now_s()):
                await run_steps_async(pilot.interim_drive_steps(state, clock.now_s()), cpu_s)
    finally:
        stages.close()
