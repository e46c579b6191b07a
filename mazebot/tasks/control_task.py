"""The motor control loop: the only writer of motor commands.

It runs at a fixed period (20 Hz by default) and applies the planner's latest
command only while the robot is RUNNING and the command is fresh; in every other
case it commands zero, so a stalled planner, a stop press or a fault stops the wheels
within one period, independently of the motor driver's own time-to-live.
"""

from __future__ import annotations

from mazebot.clock import Clock
from mazebot.state import RunState, SharedState

#: A planner command older than this many control periods is stale.
STALE_PERIODS = 3


async def run(motors, state: SharedState, clock: Clock, period_s: float) -> None:
    next_tick_s = clock.now_s()
    while True:
        now_s = clock.now_s()
        state.control_lateness_ms.append(max(0.0, (now_s - next_tick_s) * 1000.0))
        command = state.throttle_command
        fresh = command is not None and now_s - command[2] <= STALE_PERIODS * period_s
        if state.run_state is RunState.RUNNING and fresh:
            motors.set(command[0], command[1])
        else:
            motors.stop()
        next_tick_s += period_s
        if next_tick_s < now_s:  # we fell behind (a stalled loop): do not try to catch up
            next_tick_s = now_s + period_s
        await clock.sleep(next_tick_s - clock.now_s())
