"""Applies the user's start/stop commands (from the web page) to the run state."""

from __future__ import annotations

import logging

from mazebot.clock import Clock
from mazebot.state import RunState, SharedState

log = logging.getLogger(__name__)


def apply_command(command: str, state: SharedState, motors, clock: Clock) -> str:
    """Apply one command; return a short human answer. Stop always wins and always stops.

    Start from ``idle`` or ``done`` begins a new exploration (``run_number`` grows, the
    planner forgets its goals); start from ``stopped`` resumes the one under way (the
    planner puts it back to ``returning`` if that is where it was). Start in ``fault``
    clears latched faults and refuses while any other is active.
    """
    if command == "stop":
        motors.stop()
        state.motion_command = None
        if state.interrupted is not None:  # stopped during a fault: once it clears, stay stopped
            state.interrupted = RunState.STOPPED
        if state.run_state.moving or state.run_state in (RunState.IDLE, RunState.DONE):
            state.run_state = RunState.STOPPED
        return "stopped"
    if command == "start":
        if state.run_state is RunState.FAULT:
            # latched faults (seen only while driving) get another chance; the rest must clear first
            state.clear_faults(latched_only=True)
        if state.run_state is RunState.FAULT:
            fault = state.active_fault
            return f"cannot start: {fault.message if fault else 'a fault is active'}"
        if state.run_state.moving:
            return str(state.run_state)
        if state.run_state in (RunState.IDLE, RunState.DONE) or state.started_at_s is None:
            state.run_number += 1
            state.begin_run(clock.now_s())
        state.run_state = RunState.EXPLORING
        return str(state.run_state)
    return f"unknown command {command!r}; expected start or stop"


async def run(state: SharedState, motors, clock: Clock) -> None:
    while True:
        command = await state.commands.get()
        answer = apply_command(command, state, motors, clock)
        log.info("command %s: %s", command, answer)
