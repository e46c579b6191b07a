"""The planner loop: one :class:`~mazebot.planner.pilot.Pilot` tick per planner period.

The tick reads the map and pose SLAM published and writes the goal, the path and the
body-velocity command; the wheels are the control task's. A tick costs a few
milliseconds (graph update, route search, DWA); it runs on the event loop so it sees a
consistent map (its inputs are taken at the start of each half) and never races the
writers, in two halves (goal, then motion) with the loop free in between, the motion half
itself in stages (the DWA's clearance queries, :meth:`Pilot.drive_steps`), so a control
tick never waits for a whole planner tick.
"""

from __future__ import annotations

import asyncio

from mazebot.clock import Clock
from mazebot.cpu_budget import RecentValues
from mazebot.planner.pilot import Pilot
from mazebot.state import SharedState
from mazebot.steps import run_steps_async


async def run(state: SharedState, clock: Clock, pilot: Pilot, tick_ms: RecentValues | None = None) -> None:
    """Tick the pilot at its rate; ``tick_ms`` (if given) collects each tick's CPU time in ms."""
    period_s = pilot.params.period_s
    next_tick_s = clock.now_s()
    while True:
        cpu_s = [0.0]  # each half in stages (map and graph, goal; DWA blocks), the loop free in between
        if await run_steps_async(pilot.plan_steps(state, clock.now_s()), cpu_s):
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
